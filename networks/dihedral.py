"""The 8 symmetries of the square image plane, for images and camera-space normal maps (numpy and torch).

Normals are in camera coordinates (x right = columns, y up = -rows, z toward the camera). With an orthographic
camera, mirroring or rotating the image by 90° is the image of the mirrored / rotated scene (lights included), so
these transforms make exact new training samples and exact test-time-augmentation views.
"""
from __future__ import annotations

import numpy as np

#: (transpose, flip_columns, flip_rows), applied in that order. The first k are the ``views=k`` of
#: test-time augmentation: 1 = identity, 2 = + left-right mirror, 4 = + up-down mirrors, 8 = + transposes.
DIHEDRAL = (
    (False, False, False), (False, True, False), (False, False, True), (False, True, True),
    (True, False, False), (True, True, False), (True, False, True), (True, True, True),
)


def _apply(a: np.ndarray, op: str, normal: bool) -> np.ndarray:
    """One involutive step on an (H, W[, C]) map: ``transpose`` maps normal (x, y) to (-y, -x), ``flip_c`` (mirror
    the columns) negates x, ``flip_r`` (mirror the rows) negates y."""
    if op == "transpose":
        a = a.swapaxes(0, 1)
        return a[..., [1, 0, 2]] * np.array([-1.0, -1.0, 1.0], a.dtype) if normal else a
    a = np.array(a[:, ::-1] if op == "flip_c" else a[::-1])
    if normal:
        a[..., 0 if op == "flip_c" else 1] *= -1
    return a


def _ops(t: tuple[bool, bool, bool]) -> list[str]:
    return [op for op, on in zip(("transpose", "flip_c", "flip_r"), t) if on]


def transform_map(a: np.ndarray, t: tuple[bool, bool, bool], normal: bool = False) -> np.ndarray:
    """Apply ``t`` to an (H, W[, C]) map; ``normal=True`` also turns the vectors of an (H, W, 3) normal map."""
    for op in _ops(t):
        a = _apply(a, op, normal)
    return np.array(a, copy=True, order="C")


def untransform_map(a: np.ndarray, t: tuple[bool, bool, bool], normal: bool = False) -> np.ndarray:
    """Inverse of :func:`transform_map`: each step is its own inverse, undone in reverse order."""
    for op in reversed(_ops(t)):
        a = _apply(a, op, normal)
    return np.array(a, copy=True, order="C")


def transform_images(x, t: tuple[bool, bool, bool]):
    """Apply ``t`` to the last two (row, column) axes of a torch tensor, e.g. images (N, 3, H, W)."""
    transpose, flip_c, flip_r = t
    if transpose:
        x = x.transpose(-1, -2)
    if flip_c:
        x = x.flip(-1)
    if flip_r:
        x = x.flip(-2)
    return x.contiguous()

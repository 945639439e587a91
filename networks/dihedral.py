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


def transform_map(a: np.ndarray, t: tuple[bool, bool, bool], normal: bool = False) -> np.ndarray:
    """Apply ``t`` to an (H, W[, C]) map; ``normal=True`` also turns the vectors of an (H, W, 3) normal map:
    transposing maps (x, y) to (-y, -x), mirroring the columns negates x, mirroring the rows negates y."""
    transpose, flip_c, flip_r = t
    a = np.array(a, copy=True)
    if transpose:
        a = a.swapaxes(0, 1)
        if normal:
            a = a[..., [1, 0, 2]] * np.array([-1.0, -1.0, 1.0], a.dtype)
    if flip_c:
        a = a[:, ::-1]
        if normal:
            a[..., 0] *= -1
    if flip_r:
        a = a[::-1]
        if normal:
            a[..., 1] *= -1
    return np.ascontiguousarray(a)


def untransform_map(a: np.ndarray, t: tuple[bool, bool, bool], normal: bool = False) -> np.ndarray:
    """Inverse of :func:`transform_map` (the steps undone in reverse order)."""
    transpose, flip_c, flip_r = t
    a = np.array(a, copy=True)
    if flip_r:
        a = a[::-1]
        if normal:
            a[..., 1] *= -1
    if flip_c:
        a = a[:, ::-1]
        if normal:
            a[..., 0] *= -1
    if transpose:
        a = a.swapaxes(0, 1)
        if normal:
            a = a[..., [1, 0, 2]] * np.array([-1.0, -1.0, 1.0], a.dtype)
    return np.ascontiguousarray(a)


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

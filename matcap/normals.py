"""Normal-map conventions: the tangent frame of a flat sample, OpenGL / DirectX encodings (part of
:mod:`matcap.formats`, which re-exports everything here; a module of its own only to keep each under 800 lines).

Camera space is x right, y up, z toward the camera. An exported flat sample's UVs are the image axes (U right,
V up), so with the ``"camera"`` frame (T = +x, B = +y, N = +z) the OpenGL tangent-space normal equals the camera
normal; ``"fit"`` takes the mean normal over the mask as N. OpenGL (+Y, green up) and DirectX (-Y) maps store
(n + 1) / 2, green flipped for DirectX.
"""
from __future__ import annotations

import numpy as np

FOLD_Z = 1e-3
NORMAL_CONVENTIONS = ("gl", "dx")


def unit_normals(n: np.ndarray) -> np.ndarray:
    """``n`` (..., 3) scaled to unit length, float32; vectors shorter than 1e-6 become (0, 0, 1), facing the
    camera."""
    n = np.asarray(n, np.float32)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    flat = np.zeros_like(n)
    flat[..., 2] = 1.0
    return np.where(norm > 1e-6, n / np.maximum(norm, 1e-6), flat).astype(np.float32)


def tangent_frame(normal: np.ndarray, mask: np.ndarray, frame: str = "camera") -> np.ndarray:
    """3×3 matrix whose rows are T, B, N of the flat sample in camera space.

    ``"camera"``: the identity (UV = image axes, U right, V up, N toward the camera). ``"fit"``: N = the mean normal
    over ``mask`` (a sample photographed slightly obliquely), T = image x projected onto the sample plane,
    B = N × T (identity when the mean normal is unusable)."""
    if frame == "camera":
        return np.eye(3)
    if frame != "fit":
        raise ValueError(f"unknown tangent frame {frame!r}; choose 'camera' or 'fit'")
    n0 = np.asarray(normal, np.float64)[np.asarray(mask, bool)].sum(axis=0)
    if not np.isfinite(n0).all() or np.linalg.norm(n0) < 1e-9 or n0[2] <= 0:
        return np.eye(3)
    n0 /= np.linalg.norm(n0)
    t = np.array([1.0, 0.0, 0.0]) - n0[0] * n0
    t /= np.linalg.norm(t)
    return np.stack([t, np.cross(n0, t), n0])


def camera_to_tangent(normal: np.ndarray, mask: np.ndarray, frame: str | np.ndarray = "camera") -> np.ndarray:
    """Camera-space normals (H, W, 3) -> OpenGL tangent-space unit normals of the flat sample (z >= 1e-3: normals
    facing away from the camera are folded to the horizon). Off-mask and zero normals become (0, 0, 1)."""
    mask = np.asarray(mask, bool)
    m = tangent_frame(normal, mask, frame) if isinstance(frame, str) else np.asarray(frame, np.float64)
    n = np.nan_to_num(np.asarray(normal, np.float64)) @ m.T
    length = np.linalg.norm(n, axis=2)
    bad = ~mask | (length < 1e-6)
    n = n / np.maximum(length, 1e-6)[..., None]
    n[..., 2] = np.maximum(n[..., 2], FOLD_Z)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    n[bad] = (0.0, 0.0, 1.0)
    return n.astype(np.float32)


def tangent_to_camera(tangent: np.ndarray, mask: np.ndarray, frame: np.ndarray | None = None) -> np.ndarray:
    """Inverse of :func:`camera_to_tangent` (up to folding): unit camera-space normals, 0 off-mask."""
    m = np.eye(3) if frame is None else np.asarray(frame, np.float64)
    n = np.asarray(tangent, np.float64) @ m
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-8)
    return np.where(np.asarray(mask, bool)[..., None], n, 0.0).astype(np.float32)


def _check_convention(convention: str) -> None:
    if convention not in NORMAL_CONVENTIONS:
        raise ValueError(f"normal convention must be 'gl' or 'dx', got {convention!r}")


def encode_normal(normal: np.ndarray, convention: str = "gl", mask: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (H, W, 3) -> (n + 1) / 2 in [0, 1].

    ``"gl"`` keeps +Y up (OpenGL tangent space; camera-space normals use the same encoding); ``"dx"`` flips green
    (G = 1 - G). With ``mask`` (H, W) bool, off-mask pixels are 0 (black), as in a result's ``normal.png``."""
    _check_convention(convention)
    enc = (np.asarray(normal, np.float32) + 1.0) * 0.5
    if convention == "dx":
        enc[..., 1] = 1.0 - enc[..., 1]
    if mask is not None:
        enc = np.where(np.asarray(mask, bool)[..., None], enc, 0.0)
    return enc.astype(np.float32)


def decode_normal(encoded: np.ndarray, convention: str = "gl", mask: np.ndarray | None = None) -> np.ndarray:
    """Inverse of :func:`encode_normal`: unit vectors (renormalised); 0 off ``mask`` when given."""
    _check_convention(convention)
    n = np.asarray(encoded, np.float64) * 2.0 - 1.0
    if convention == "dx":
        n[..., 1] = -n[..., 1]
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)
    if mask is not None:
        n = np.where(np.asarray(mask, bool)[..., None], n, 0.0)
    return n.astype(np.float32)

"""Angular-error metrics for normal maps, and the error-map colouring.

The angular error at a pixel is ``degrees(arccos(clip(dot(n_pred, n_gt), -1, 1)))`` after both vectors are
normalised (computed as ``atan2(|a x b|, a . b)``, which is accurate for small angles too). Only pixels inside
the mask count. A predicted vector of (near) zero length inside the mask -- a method that gave up on a pixel --
is scored as 90 degrees. Ground-truth pixels of zero length are left out of the mask.
"""
from __future__ import annotations

import numpy as np

THRESHOLDS_DEG = (10.0, 20.0, 30.0)


def angular_error_map(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(H, W) angular error in degrees (float64); NaN outside ``mask`` and where ``gt`` is zero."""
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise ValueError(f"normal maps must both be (..., 3) of one shape, got {pred.shape} and {gt.shape}")
    valid = np.linalg.norm(gt, axis=-1) > 1e-8
    if mask is not None:
        valid &= np.asarray(mask, dtype=bool)
    pn = np.linalg.norm(pred, axis=-1)
    cross = np.linalg.norm(np.cross(pred, gt), axis=-1)
    dot = np.sum(pred * gt, axis=-1)
    err = np.degrees(np.arctan2(cross, dot))
    err = np.where(pn > 1e-8, err, 90.0)
    return np.where(valid, err, np.nan)


def summarize_errors(err: np.ndarray) -> dict[str, float]:
    """Statistics of the finite entries of an error map: mean, median, share under 10/20/30 degrees (0..1)."""
    e = np.asarray(err, dtype=np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        raise ValueError("no valid pixels to evaluate")
    out = {"mae": float(e.mean()), "median": float(np.median(e)), "pixels": int(e.size)}
    for t in THRESHOLDS_DEG:
        out[f"under{int(t)}"] = float(np.mean(e < t))
    return out


def normal_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Mean angular error (``mae``), ``median``, ``under10``/``under20``/``under30`` (fractions) and ``pixels``."""
    return summarize_errors(angular_error_map(pred, gt, mask))


# Colour map for error maps: 0 deg dark blue -> blue -> cyan -> green -> yellow -> red -> dark red at 90 deg.
_ANCHORS = np.array([
    [0.00, 0.00, 0.00, 0.50],
    [0.12, 0.00, 0.20, 1.00],
    [0.30, 0.00, 0.85, 1.00],
    [0.45, 0.20, 1.00, 0.40],
    [0.62, 1.00, 1.00, 0.00],
    [0.80, 1.00, 0.30, 0.00],
    [1.00, 0.55, 0.00, 0.00],
])


def colorize_error(err: np.ndarray, max_deg: float = 90.0, background: float = 0.0) -> np.ndarray:
    """(H, W) degrees -> (H, W, 3) RGB in [0, 1]; 0..``max_deg`` mapped blue->red, NaN -> ``background``."""
    err = np.asarray(err, dtype=np.float64)
    t = np.clip(np.nan_to_num(err, nan=0.0) / max_deg, 0.0, 1.0)
    rgb = np.stack([np.interp(t, _ANCHORS[:, 0], _ANCHORS[:, c]) for c in (1, 2, 3)], axis=-1)
    rgb[~np.isfinite(err)] = background
    return rgb.astype(np.float32)


def colorbar(height: int, width: int = 12, max_deg: float = 90.0) -> np.ndarray:
    """(height, width, 3) vertical colour bar, ``max_deg`` at the top, 0 at the bottom."""
    col = np.linspace(max_deg, 0.0, max(height, 2))[:, None]
    return colorize_error(np.repeat(col, width, axis=1), max_deg)


def analytic_sphere(mask: np.ndarray, rim: float = 0.98) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth for a photographed sphere from its silhouette (orthographic view).

    mask: (H, W) bool, the sphere's disc. Returns normals (H, W, 3) in camera space (x right, y up, z toward the
    camera; row 0 at the top), ``((x - cx) / r, -(y - cy) / r, sqrt(1 - ...))`` with the disc's centre and radius
    taken from the mask's bounding box, and the (H, W) bool pixels to score: inside the disc, where
    ``nx^2 + ny^2 < rim`` (at the rim one pixel spans many degrees).
    """
    mask = np.asarray(mask, bool)
    if mask.ndim != 2 or not mask.any():
        raise ValueError(f"analytic_sphere needs a non-empty (H, W) mask, got shape {mask.shape}")
    ys, xs = np.nonzero(mask)
    cx, cy = (xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2
    radius = ((xs.max() - xs.min()) + (ys.max() - ys.min())) / 4 + 0.5
    yy, xx = np.mgrid[0:mask.shape[0], 0:mask.shape[1]]
    nx, ny = (xx - cx) / radius, -(yy - cy) / radius
    normal = np.stack([nx, ny, np.sqrt(np.clip(1 - nx ** 2 - ny ** 2, 0, 1))], -1).astype(np.float32)
    return normal, mask & (nx ** 2 + ny ** 2 < rim)


def high_pass(normal: np.ndarray, mask: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """The fine detail of a normal map: (H, W, 3) ``normal`` minus its Gaussian blur of ``sigma`` px taken over
    ``mask`` (H, W) alone (the background is not blended in at the edges)."""
    from scipy import ndimage

    m = np.asarray(mask, bool)
    n = np.asarray(normal, np.float64)
    if n.shape[:2] != m.shape or n.shape[-1] != 3:
        raise ValueError(f"normal {n.shape} and mask {m.shape} do not match (want (H, W, 3) and (H, W))")
    w = ndimage.gaussian_filter(m.astype(np.float64), sigma)[..., None]
    blur = np.stack([ndimage.gaussian_filter(np.where(m, n[..., i], 0.0), sigma) for i in range(3)], -1)
    return n - blur / np.maximum(w, 1e-9)


def detail_scores(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, sigma: float = 1.5,
                  erode: int = 6) -> dict[str, float]:
    """How much of ``gt``'s fine detail (:func:`high_pass`) ``pred`` carries, on ``mask`` eroded by ``erode`` px:
    ``error`` the mean length of the difference of the two high-pass vectors, ``truth_size`` the mean length of
    the truth's (what ``error`` is when the detail is missing), ``correlation`` of their x, y components,
    ``amplitude`` the least-squares gain from the truth's x, y to the prediction's (1: full strength)."""
    from scipy import ndimage

    inner = ndimage.binary_erosion(np.asarray(mask, bool), iterations=erode)
    if inner.sum() < 16:
        raise ValueError(f"the mask eroded by {erode} px leaves {int(inner.sum())} pixels: too small to score")
    hp, ht = high_pass(pred, mask, sigma)[inner], high_pass(gt, mask, sigma)[inner]
    return {"error": float(np.linalg.norm(hp - ht, axis=-1).mean()),
            "truth_size": float(np.linalg.norm(ht, axis=-1).mean()),
            "correlation": float(np.corrcoef(hp[:, :2].ravel(), ht[:, :2].ravel())[0, 1]),
            "amplitude": float((hp[:, :2] * ht[:, :2]).sum() / max((ht[:, :2] ** 2).sum(), 1e-12))}


def fine_energy_share(normal: np.ndarray, mask: np.ndarray, max_period: float, sigma: float = 1.5) -> float:
    """Share of a normal map's fine detail (:func:`high_pass`, x and y) whose spatial period along x or y is at
    most ``max_period`` px, over the largest square centred on the mask's centroid that lies inside it (a power
    spectrum needs a rectangle). The networks' interleaved 128 px tiles leave a grid of period side / 128 px (2 px
    at 256^2, 4 px at 512^2): where it dominates, this share is far above the truth's."""
    m = np.asarray(mask, bool)
    ys, xs = np.nonzero(m)
    if len(ys) == 0:
        raise ValueError("the mask is empty")
    cy, cx = int(round(ys.mean())), int(round(xs.mean()))
    half = 0  # an even side, so that a period of 2 px falls on a frequency bin
    while (cy - half - 1 >= 0 and cx - half - 1 >= 0 and cy + half + 1 <= m.shape[0] and cx + half + 1 <= m.shape[1]
           and m[cy - half - 1:cy + half + 1, cx - half - 1:cx + half + 1].all()):
        half += 1
    if 2 * half < 8:
        raise ValueError(f"the mask holds no square of 8 px around its centre ({2 * half} px)")
    sl = (slice(cy - half, cy + half), slice(cx - half, cx + half))
    hp = high_pass(normal, m, sigma)[sl][..., :2]
    power = (np.abs(np.fft.fft2(hp, axes=(0, 1))) ** 2).sum(-1)
    fy = np.abs(np.fft.fftfreq(power.shape[0]))[:, None]
    fx = np.abs(np.fft.fftfreq(power.shape[1]))[None, :]
    band = (fx >= 1.0 / max_period) | (fy >= 1.0 / max_period)
    return float(power[band].sum() / max(power.sum(), 1e-30))

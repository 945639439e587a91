"""Classical calibrated photometric stereo: least-squares Lambertian (Woodham 1980) and a robust variant.

Model: a pixel's value under light k is ``I_k = e_k * rho * max(0, n . l_k)`` with ``l_k`` the unit direction to
the light and ``e_k`` its RGB intensity. The images are divided by ``e_k`` per channel and averaged over RGB into
one grey observation per light; for K >= 3 lights the scaled normal ``g = rho n`` is the least-squares solution
of ``L g = I`` (``L`` is K x 3), the normal is ``g / |g|`` and ``rho`` per channel is refitted afterwards.

* :func:`least_squares_ps` -- every observation counts (one pseudo-inverse shared by all pixels). Attached and
  cast shadows (``I = 0`` where ``n . l < 0``) and specular highlights break the linear model and bias it.
* :func:`robust_least_squares_ps` -- per pixel, the observations are ranked and the darkest
  ``floor(dark_frac * K)`` (shadows) and the brightest ``floor(bright_frac * K)`` (highlights) are discarded
  before the least-squares fit (defaults :data:`DEFAULT_DARK_FRAC` = 0.3 and :data:`DEFAULT_BRIGHT_FRAC` = 0.1:
  with 12 lights, 3 darkest and 1 brightest dropped, 8 kept; with 96 lights 28 and 9 dropped). The drops shrink
  (highlights first) so that at least 3 observations remain. Solved as a batch of per-pixel 3x3 normal
  equations; pixels whose kept lights are degenerate fall back to the plain fit.

Both return unit normals in the frame of the light directions (our camera frame when the lights come from
:mod:`matcap.evaluation.datasets`), zeros outside the mask and where a pixel is black under every light.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_DARK_FRAC = 0.3
DEFAULT_BRIGHT_FRAC = 0.1


@dataclass
class PSResult:
    """normal: (H, W, 3) float32 unit normals (0 off-mask); albedo: (H, W, 3) float32 (0 off-mask)."""

    normal: np.ndarray
    albedo: np.ndarray


def _prepare(images, light_dirs, mask, light_intensities):
    imgs = [np.asarray(im, dtype=np.float32) for im in images]
    k = len(imgs)
    if k < 3:
        raise ValueError(f"least-squares photometric stereo needs at least 3 images, got {k}")
    h, w = imgs[0].shape[:2]
    mask = np.ones((h, w), bool) if mask is None else np.asarray(mask, dtype=bool)
    L = np.asarray(light_dirs, dtype=np.float64).reshape(-1, 3)
    if len(L) != k:
        raise ValueError(f"{len(L)} light directions for {k} images")
    L = L / np.linalg.norm(L, axis=1, keepdims=True)
    E = np.ones((k, 3)) if light_intensities is None else np.asarray(light_intensities, np.float64).reshape(-1, 3)
    if len(E) != k:
        raise ValueError(f"{len(E)} light intensities for {k} images")
    if (E <= 0).any():
        raise ValueError("light intensities must be positive")
    # (K, P, 3) observations inside the mask, divided by the light colour
    obs_rgb = np.stack([im[mask] for im in imgs]).astype(np.float64) / E[:, None, :]
    return obs_rgb, obs_rgb.mean(axis=2), L, mask


def _finish(g: np.ndarray, obs_rgb: np.ndarray, L: np.ndarray, weight: np.ndarray | None, mask) -> PSResult:
    length = np.linalg.norm(g, axis=1, keepdims=True)
    n = np.where(length > 1e-12, g / np.maximum(length, 1e-300), 0.0)  # (P, 3)
    shading = np.maximum(L @ n.T, 0.0)  # (K, P)
    if weight is not None:
        shading = shading * weight
    denom = np.sum(shading**2, axis=0)  # (P,)
    rho = np.einsum("kp,kpc->pc", shading, obs_rgb) / np.maximum(denom, 1e-12)[:, None]
    h, w = mask.shape
    normal = np.zeros((h, w, 3), np.float32)
    albedo = np.zeros((h, w, 3), np.float32)
    normal[mask] = n
    albedo[mask] = np.where(denom[:, None] > 1e-12, rho, 0.0)
    return PSResult(normal, albedo)


def least_squares_ps(images, light_dirs, mask=None, light_intensities=None) -> PSResult:
    """Woodham's least-squares Lambertian photometric stereo over all given images.

    images: K (H, W, 3) linear arrays; light_dirs: (K, 3) toward the lights; mask: (H, W) bool or None;
    light_intensities: (K, 3) RGB or None (ones).
    """
    obs_rgb, obs, L, mask = _prepare(images, light_dirs, mask, light_intensities)
    g = (np.linalg.pinv(L) @ obs).T  # (P, 3)
    return _finish(g, obs_rgb, L, None, mask)


def robust_keep_weights(obs: np.ndarray, dark_frac: float, bright_frac: float) -> np.ndarray:
    """(K, P) 0/1 weights: per column, 0 for the darkest ``dark_frac`` and brightest ``bright_frac`` shares."""
    if not (0.0 <= dark_frac < 1.0 and 0.0 <= bright_frac < 1.0):
        raise ValueError("dark_frac and bright_frac must lie in [0, 1)")
    k = obs.shape[0]
    n_dark = int(np.floor(dark_frac * k + 1e-9))
    n_bright = int(np.floor(bright_frac * k + 1e-9))
    while k - n_dark - n_bright < 3 and n_bright > 0:
        n_bright -= 1
    while k - n_dark - n_bright < 3 and n_dark > 0:
        n_dark -= 1
    rank = np.empty_like(obs, dtype=np.int64)
    order = np.argsort(obs, axis=0, kind="stable")
    np.put_along_axis(rank, order, np.arange(k)[:, None].repeat(obs.shape[1], axis=1), axis=0)
    return ((rank >= n_dark) & (rank < k - n_bright)).astype(np.float64)


def robust_least_squares_ps(images, light_dirs, mask=None, light_intensities=None,
                            dark_frac: float = DEFAULT_DARK_FRAC,
                            bright_frac: float = DEFAULT_BRIGHT_FRAC) -> PSResult:
    """Least squares after discarding, per pixel, the darkest and brightest observations (see module doc)."""
    obs_rgb, obs, L, mask = _prepare(images, light_dirs, mask, light_intensities)
    wgt = robust_keep_weights(obs, dark_frac, bright_frac)  # (K, P)
    outer = (L[:, :, None] * L[:, None, :]).reshape(len(L), 9)  # (K, 9)
    A = (wgt.T @ outer).reshape(-1, 3, 3)  # (P, 3, 3)
    b = (wgt * obs).T @ L  # (P, 3)
    # well-conditioned pixels: batched solve; the rest: the plain fit
    eig_min = np.linalg.eigvalsh(A)[:, 0]
    ok = eig_min > 1e-6 * np.maximum(np.trace(A, axis1=1, axis2=2), 1e-12)
    g = (np.linalg.pinv(L) @ obs).T
    if ok.any():
        g[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    wgt[:, ~ok] = 1.0
    return _finish(g, obs_rgb, L, wgt, mask)

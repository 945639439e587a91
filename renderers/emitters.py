"""Mitsuba emitter dicts for :mod:`scenes.lights` (pure functions; Mitsuba imported lazily).

World space = our camera space (x right, y up, z toward the camera).
"""
from __future__ import annotations

import warnings

import numpy as np

from scenes.lights import DirectionalLight, EnvironmentLight, Light, PointLight


# A map's negative texels are clamped silently while their (absolute) radiance is below this fraction of the map's
# positive radiance: lossy EXR compression (DWAB) leaves a few small negatives in many maps, and clamping those
# changes no render visibly. Above it, or for NaN / Inf texels, the user hears about it once per map.
NEGATIVE_ENERGY_WARN = 1e-3
_warned: set[str] = set()


def sanitize_envmap(pixels: np.ndarray, name: str = "environment map") -> np.ndarray:
    """(H, W, 3) float32 equirectangular radiance with negative and non-finite texels set to 0.

    Warns once per map ``name`` per process, and only when it matters: a non-finite texel, or negative texels
    holding more than :data:`NEGATIVE_ENERGY_WARN` of the map's positive radiance."""
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"{name}: expected (H, W, 3) pixels, got {arr.shape}")
    finite = np.isfinite(arr)
    bad = ~finite | (arr < 0)
    if bad.any():
        clean = np.where(bad, 0.0, arr).astype(np.float32)
        negative = float(-arr[finite & (arr < 0)].sum(dtype=np.float64))
        positive = float(clean.sum(dtype=np.float64))
        share = negative / positive if positive > 0 else float("inf")
        if (not finite.all() or share > NEGATIVE_ENERGY_WARN) and name not in _warned:
            _warned.add(name)
            warnings.warn(f"{name}: {int(bad.any(axis=2).sum())} texel(s) negative or non-finite "
                          f"(negative radiance {100 * share:.2g}% of the map's), clamped to 0", stacklevel=2)
        arr = clean
    return np.ascontiguousarray(arr)


def emitter_dict(light: Light, envmap_pixels: np.ndarray | None = None) -> dict:
    """The Mitsuba dict for one light. ``envmap_pixels`` (H, W, 3) is required for an EnvironmentLight."""
    import mitsuba as mi

    if isinstance(light, DirectionalLight):
        d = np.asarray(light.direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        # Mitsuba's `directional` takes the direction the light travels: from the light toward the scene.
        return {
            "type": "directional",
            "direction": [float(-d[0]), float(-d[1]), float(-d[2])],
            "irradiance": {"type": "rgb", "value": [float(v) for v in light.irradiance]},
        }
    if isinstance(light, PointLight):
        return {
            "type": "point",
            "position": [float(v) for v in light.position],
            "intensity": {"type": "rgb", "value": [float(v) for v in light.intensity]},
        }
    if isinstance(light, EnvironmentLight):
        if envmap_pixels is None:
            raise ValueError("an EnvironmentLight needs its pixels")
        pixels = sanitize_envmap(envmap_pixels, light.source or "environment map")
        return {
            "type": "envmap",
            "bitmap": mi.Bitmap(pixels, pixel_format=mi.Bitmap.PixelFormat.RGB),
            "scale": float(light.scale),
            "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], float(light.rotation_deg)),
        }
    raise TypeError(f"not a light: {light!r}")

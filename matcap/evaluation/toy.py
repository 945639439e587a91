"""Analytic test objects: Lambertian sphere and plane under known distant lights, written in the DiLiGenT layout.

Used by the tests and handy for checking an installation (``matcap eval`` on a folder written by
:func:`write_diligent_object` must give the least-squares baseline well under a degree).
Camera convention: x right, y up, z toward the camera; row 0 is the top of the image.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from matcap import imageio


def sphere_normals(size: int, radius_frac: float = 0.45, max_angle_deg: float = 90.0) -> tuple[np.ndarray, np.ndarray]:
    """(normal (H, W, 3), mask) of a sphere seen orthographically; pixels whose normal is more than
    ``max_angle_deg`` from the viewer are left out of the mask."""
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    x = (xx - c) / (radius_frac * size)
    y = -(yy - c) / (radius_frac * size)  # y up
    r2 = x**2 + y**2
    inside = r2 < 1.0
    z = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    n = np.stack([x, y, z], axis=-1)
    mask = inside & (z > np.cos(np.radians(max_angle_deg)) + 1e-9)
    return np.where(mask[:, :, None], n, 0.0).astype(np.float32), mask


def plane_normals(size: int, normal=(0.3, -0.2, 0.9), margin: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A tilted plane filling the image except a ``margin``-pixel border."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    mask = np.zeros((size, size), bool)
    mask[margin:size - margin, margin:size - margin] = True
    return np.where(mask[:, :, None], n, 0.0).astype(np.float32), mask


def cone_lights(count: int, max_angle_deg: float, seed: int = 0) -> np.ndarray:
    """``count`` unit directions spread over a cone of half-angle ``max_angle_deg`` around +z (deterministic)."""
    rng = np.random.default_rng(seed)
    golden = np.pi * (3.0 - np.sqrt(5.0))
    i = np.arange(count) + 0.5
    cos_t = 1.0 - (1.0 - np.cos(np.radians(max_angle_deg))) * i / count
    phi = golden * i + rng.uniform(0, 2 * np.pi)
    sin_t = np.sqrt(1.0 - cos_t**2)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)


def render_lambertian(normal, mask, lights, intensities=None, albedo=(0.8, 0.6, 0.4),
                      specular: float = 0.0, shininess: float = 200.0) -> list[np.ndarray]:
    """Linear images ``e_k * albedo * max(0, n . l_k)`` (+ an optional Blinn-Phong highlight), 0 off-mask."""
    lights = np.asarray(lights, np.float64)
    e = np.ones((len(lights), 3)) if intensities is None else np.asarray(intensities, np.float64)
    a = np.asarray(albedo, np.float64)
    n = np.asarray(normal, np.float64)
    out = []
    for l, ek in zip(lights, e, strict=True):
        shade = np.maximum(n @ l, 0.0)
        img = shade[:, :, None] * a[None, None, :]
        if specular:
            h = l + np.array([0.0, 0.0, 1.0])
            h /= np.linalg.norm(h)
            img = img + (specular * np.maximum(n @ h, 0.0) ** shininess * (shade > 0))[:, :, None]
        img = img * ek[None, None, :]
        out.append(np.where(mask[:, :, None], img, 0.0).astype(np.float32))
    return out


def write_diligent_object(folder: str | os.PathLike, images, mask, normal, lights, intensities=None,
                          normal_format: str = "mat") -> Path:
    """Write an object folder in the DiLiGenT layout: 16-bit PNG images (values must lie in [0, 1]),
    ``filenames.txt``, ``light_directions.txt``, ``light_intensities.txt``, ``mask.png`` and the ground truth as
    ``Normal_gt.mat`` (``normal_format="mat"``), ``normal.txt`` ("txt") or 16-bit ``Normal_gt.png`` ("png")."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{i + 1:03d}.png" for i in range(len(images))]
    for name, img in zip(names, images, strict=True):
        imageio.write_png(folder / name, img, bits=16)
    imageio.write_text_atomic(folder / "filenames.txt", "\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", np.asarray(lights, np.float64), fmt="%.8f")
    e = np.ones((len(images), 3)) if intensities is None else np.asarray(intensities, np.float64)
    np.savetxt(folder / "light_intensities.txt", e, fmt="%.8f")
    imageio.write_png(folder / "mask.png", mask.astype(np.float32), bits=8)
    if normal_format == "mat":
        import scipy.io

        scipy.io.savemat(str(folder / "Normal_gt.mat"), {"Normal_gt": np.asarray(normal, np.float64)})
    elif normal_format == "txt":
        np.savetxt(folder / "normal.txt", np.asarray(normal, np.float64).reshape(-1, 3), fmt="%.8f")
    elif normal_format == "png":
        imageio.write_png(folder / "Normal_gt.png", np.where(mask[:, :, None], (normal + 1) / 2, 0), bits=16)
    else:
        raise ValueError(f"normal_format must be mat, txt or png, got {normal_format!r}")
    return folder

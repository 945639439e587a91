"""A known capture for the refinement's tests and benchmarks: a glossy sphere rendered by our own Mitsuba
relighting path (``renderers.relight.render``) under known lights, and "network-like" perturbed start maps.

Only :func:`render_capture` uses Mitsuba (through ``renderers``); the rest is numpy.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from matcap.evaluation.toy import cone_lights, sphere_normals
from scenes.materialmaps import MaterialMaps


def _on_mask(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``a`` ((H, W) or (H, W, C)) as float32, zero off ``mask``."""
    a = np.asarray(a)
    return np.where(mask if a.ndim == 2 else mask[..., None], a, 0).astype(np.float32)


def sphere_maps(size: int = 64) -> MaterialMaps:
    """A sphere with a bumpy band (so the normals are not all analytic), two materials side by side: left half
    glossy dielectric (roughness 0.3), right half rough (0.7); base colour varies smoothly; metallic 0."""
    normal, mask = sphere_normals(size, radius_frac=0.46, max_angle_deg=80.0)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    bump = 0.15 * np.sin(2 * np.pi * 3 * xx) * np.exp(-((yy - 0.5) / 0.15) ** 2)
    n = normal.copy()
    n[..., 0] += bump
    n /= np.linalg.norm(n, axis=-1, keepdims=True).clip(1e-6)
    n[~mask] = 0
    base = np.stack([0.55 + 0.3 * xx, 0.45 + 0.2 * yy, 0.35 + 0.1 * (1 - xx)], -1).astype(np.float32)
    rough = np.where(xx < 0.5, 0.3, 0.7).astype(np.float32)
    metal = np.zeros((size, size), np.float32)
    return MaterialMaps(normal=n.astype(np.float32), mask=mask, base_color=_on_mask(base, mask),
                        roughness=_on_mask(rough, mask), metallic=_on_mask(metal, mask))


def textured_dome(size: int, detail: MaterialMaps, strength: float = 2.0, roughness: float = 0.4) -> MaterialMaps:
    """A sphere seen up to its occluding contour, carrying the tangent-space detail and the base colour of a
    texture set ``detail`` (e.g. a CC0 wood set through :func:`matcap.formats.load_maps`, at least ``size``
    pixels square): its normal map's x, y scaled by ``strength``, constant ``roughness``, metallic 0."""
    normal, mask, d = _dome(size, detail)
    t = np.asarray(d.normal[:size, :size], np.float32).copy()
    t[..., :2] *= strength
    t /= np.linalg.norm(t, axis=-1, keepdims=True).clip(1e-6)
    tangent = np.float32([1, 0, 0]) - (normal @ np.float32([1, 0, 0]))[..., None] * normal
    tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True).clip(1e-6)
    bitangent = np.cross(normal, tangent)
    n = t[..., :1] * tangent + t[..., 1:2] * bitangent + t[..., 2:3] * normal
    n /= np.linalg.norm(n, axis=-1, keepdims=True).clip(1e-6)
    return _dome_maps(n, mask, d, roughness)


def _dome(size: int, detail: MaterialMaps):
    """(sphere normals, mask, ``detail`` with defaults) of the domes: a sphere up to its occluding contour."""
    if min(detail.shape) < size:
        raise ValueError(f"the texture set is {detail.shape}, smaller than the dome's {size} px")
    normal, mask = sphere_normals(size, radius_frac=0.47, max_angle_deg=89.0)
    return normal, mask, detail.with_defaults()


def _dome_maps(normal: np.ndarray, mask: np.ndarray, d: MaterialMaps, roughness: float) -> MaterialMaps:
    """A dome's maps: ``normal`` and the base colour of ``d`` on ``mask``, constant ``roughness``, metallic 0."""
    h, w = mask.shape
    return MaterialMaps(normal=_on_mask(normal, mask), mask=mask, base_color=_on_mask(d.base_color[:h, :w], mask),
                        roughness=_on_mask(np.full((h, w), roughness), mask), metallic=_on_mask(np.zeros((h, w)), mask))


def height_from_normals(normal: np.ndarray) -> np.ndarray:
    """(H, W) height (pixel units, mean 0) whose gradient best fits a normal map's in least squares
    (Frankot & Chellappa 1988: the projection onto integrable fields, periodic boundary): a baked normal map made a
    surface that can exist. normal: (H, W, 3), x right, y up, z toward the viewer."""
    n = np.asarray(normal, np.float64)
    nz = np.clip(n[..., 2], 0.05, None)
    dz_dcol, dz_drow = -n[..., 0] / nz, n[..., 1] / nz  # y up: rows run down
    h, w = dz_dcol.shape
    wc = 2.0 * np.pi * np.fft.fftfreq(w)[None, :]
    wr = 2.0 * np.pi * np.fft.fftfreq(h)[:, None]
    # the spectral derivative of a central difference, so that np.gradient of the height gives back the slopes
    dc, dr = 1j * np.sin(wc), 1j * np.sin(wr)
    den = np.abs(dc) ** 2 + np.abs(dr) ** 2
    den[0, 0] = 1.0
    z = (np.conj(dc) * np.fft.fft2(dz_dcol) + np.conj(dr) * np.fft.fft2(dz_drow)) / den
    z[0, 0] = 0.0
    return np.real(np.fft.ifft2(z))


def relief_dome(size: int, detail: MaterialMaps, strength: float = 1.0, roughness: float = 0.4) -> MaterialMaps:
    """A sphere seen up to its occluding contour whose surface carries the relief of a texture set's normal map
    (:func:`height_from_normals`, times ``strength``) and its base colour: unlike :func:`textured_dome`, one
    height field (every photo of a real object is of one), so integrability holds. Constant ``roughness``,
    metallic 0; mask and outline as :func:`textured_dome`."""
    _, mask, d = _dome(size, detail)
    relief = strength * height_from_normals(d.normal[:size, :size])
    c, r = (size - 1) / 2.0, 0.47 * size
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = xx - c, -(yy - c)
    z0 = np.sqrt(np.clip(r * r - x * x - y * y, 1e-6, None))
    dh_drow, dh_dcol = np.gradient(relief)
    gx, gy = -x / z0 + dh_dcol, -y / z0 - dh_drow  # dz/dx, dz/dy (y up) of sphere + relief
    n = np.stack([-gx, -gy, np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return _dome_maps(n, mask, d, roughness)


def known_lights(count: int = 12, seed: int = 3, max_angle_deg: float = 55.0, kind: str = "directional",
                 distance: float = 3.0):
    """``count`` DirectionalLights (or PointLights at ``distance``) in a cone around the view, RGB-tinted."""
    from scenes.lights import DirectionalLight, PointLight

    dirs = cone_lights(count, max_angle_deg, seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for d in dirs:
        tint = rng.uniform(0.8, 1.2, 3) * 2.5
        if kind == "point":
            out.append(PointLight(position=tuple(float(v) for v in d * distance),
                                  intensity=tuple(float(v) for v in tint * distance ** 2)))
        else:
            out.append(DirectionalLight(direction=tuple(float(v) for v in d), irradiance=tuple(float(v) for v in tint)))
    return out


def highlighted(normal: np.ndarray, lights, within_deg: float = 6.0) -> np.ndarray:
    """(N,) bool: the normals ``normal`` (N, 3) within ``within_deg`` of some light's half vector (seen along +z),
    where a highlight shows the roughness; ``lights``: objects with a ``direction``."""
    seen = np.zeros(len(normal), bool)
    for light in lights:
        h = np.asarray(light.direction, np.float64) + (0.0, 0.0, 1.0)
        seen |= normal @ (h / np.linalg.norm(h)) > np.cos(np.radians(within_deg))
    return seen


def render_capture(maps: MaterialMaps, lights, ambient: float = 0.05, spp: int = 32, seed: int = 0):
    """K (H, W, 3) float32 linear photos of ``maps``: each light plus a uniform environment of radiance ``ambient``.
    Rendered on one thread, so that the same call gives the same photos bit for bit however busy the machine."""
    from renderers.relight import render
    from renderers.variant import one_thread
    from scenes.lights import EnvironmentLight

    env = {"uniform": np.full((16, 32, 3), ambient, np.float32)}
    # render the whole frame with the normals continued past the mask (the renderer's bilinear texture lookup
    # would otherwise blend rim pixels with the flat background), then black out the background
    full = extend_maps(maps)
    photos = []
    with one_thread():
        for i, light in enumerate(lights):
            extra = [EnvironmentLight(source="uniform")] if ambient > 0 else []
            img = render(full, [light] + extra, env if extra else None, spp=spp, seed=seed + i)
            photos.append(np.where(maps.mask[..., None], img, 0.0).astype(np.float32))
    return photos


def extend_maps(maps: MaterialMaps) -> MaterialMaps:
    """``maps`` with every map continued past the mask by the nearest masked pixel and an all-true mask."""
    from scipy import ndimage

    idx = ndimage.distance_transform_edt(~maps.mask, return_distances=False, return_indices=True)
    near = lambda a: None if a is None else a[idx[0], idx[1]]  # noqa: E731
    return MaterialMaps(normal=near(maps.normal), mask=np.ones_like(maps.mask), base_color=near(maps.base_color),
                        roughness=near(maps.roughness), metallic=near(maps.metallic))


def perturb(maps: MaterialMaps, seed: int = 0, normal_deg: float = 8.0, rough_shift: float = 0.2,
            base_gain: float = 0.8) -> MaterialMaps:
    """Network-like start maps: normals tilted by a smooth field plus per-pixel noise (about ``normal_deg``),
    roughness shifted toward 0.5 by ``rough_shift``, base colour scaled by ``base_gain``; metallic 0.1."""
    rng = np.random.default_rng(seed)
    h, w = maps.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) / max(h, w)
    t = np.radians(normal_deg)
    field = np.stack([np.sin(2 * np.pi * yy + 1.0), np.cos(2 * np.pi * xx), np.zeros_like(xx)], -1) * 0.7 * t
    field += rng.normal(0, 0.5 * t, (h, w, 3)) * np.float32([1, 1, 0])
    n = maps.normal + field
    n /= np.linalg.norm(n, axis=-1, keepdims=True).clip(1e-6)
    n[..., 2] = np.maximum(n[..., 2], 0.05)
    n /= np.linalg.norm(n, axis=-1, keepdims=True).clip(1e-6)
    m = maps.mask
    n[~m] = 0
    r = np.where(m, maps.roughness + rough_shift * np.sign(0.5 - maps.roughness), 0)
    return MaterialMaps(normal=n.astype(np.float32), mask=m,
                        base_color=(maps.base_color * base_gain).astype(np.float32),
                        roughness=r.astype(np.float32), metallic=np.where(m, 0.1, 0).astype(np.float32))


def ball_lights(count: int = 16, seed: int = 0, max_polar_deg: float = 45.0, min_polar_deg: float = 8.0,
                unequal: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(directions (K, 3) unit, toward the lamps; RGB irradiances (K, 3)): polar angles spread between
    ``min_polar_deg`` and ``max_polar_deg`` from the view axis, azimuths on a golden-angle spiral; each lamp's power
    drawn in [1 - unequal, 1 + unequal] and its colour tinted by up to 5 % per channel."""
    rng = np.random.default_rng(seed)
    i = np.arange(count) + 0.5
    lo, hi = np.cos(np.radians(min_polar_deg)), np.cos(np.radians(max_polar_deg))
    cos_t = lo + (hi - lo) * i / count
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i * count / 2 + rng.uniform(0, 2 * np.pi)
    sin_t = np.sqrt(1.0 - cos_t ** 2)
    dirs = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], 1)
    dirs = dirs[rng.permutation(count)]
    power = rng.uniform(1.0 - unequal, 1.0 + unequal, (count, 1))
    tint = rng.uniform(0.95, 1.05, (count, 3))
    return dirs, power * tint


def matte_ball(folder: Path, side: int = 192, seed: int = 0, count: int = 16, unequal: float = 0.3,
                ambient: float = 0.02, full_well: float = 20000.0, read_noise: float = 4.0,
                max_polar_deg: float = 45.0, albedo_variation: float = 0.1, brdf: str = "lambert",
                roughness: float = 0.8) -> dict:
    """Write the matte ball's photos (16-bit linear PNG), ``mask.png`` and ``lights.txt`` (the true directions, one
    row per photo) to ``folder``. Noise: Poisson photon noise for a full well of ``full_well`` electrons at the
    PNG's white, plus Gaussian read noise of ``read_noise`` electrons. ``brdf`` "lambert" (a matte ball), or
    "principled": the fit's own model (:func:`matcap.refine.model.shade_directional`, ``roughness``, metallic 0,
    specular 0.5), so that the model can explain the photos exactly. Returns {directions, irradiance, mask}."""
    from matcap import imageio

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1000 + seed)
    c = (side - 1) / 2.0
    yy, xx = np.mgrid[0:side, 0:side].astype(np.float64)
    x, y = (xx - c) / (0.42 * side), -(yy - c) / (0.42 * side)
    inside = x ** 2 + y ** 2 < 1.0
    n = np.stack([x, y, np.sqrt(np.clip(1 - x ** 2 - y ** 2, 0, 1))], -1)
    base = np.array([0.62, 0.55, 0.47])
    vary = 1.0 + albedo_variation * np.sin(2.1 * x + 0.7) * np.cos(1.7 * y - 0.4)  # smooth, low contrast
    albedo = base[None, None] * vary[..., None]
    dirs, irr = ball_lights(count, seed, max_polar_deg, unequal=unequal)
    sky = ambient * (1.0 + n[..., 2:3]) / 2.0  # a weak fixed light from the camera's side
    if brdf == "lambert":
        shading = np.clip(np.einsum("hwc,kc->khw", n, dirs), 0, None)[..., None] * irr[:, None, None, :]
        img = albedo[None] * (shading + sky[None])
    else:
        import torch

        from matcap.refine.model import shade_directional

        t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
        flat = n.reshape(-1, 3).copy()
        flat[:, 2] = np.maximum(flat[:, 2], 1e-3)
        flat /= np.linalg.norm(flat, axis=1, keepdims=True)
        pix = len(flat)
        with torch.no_grad():
            direct = shade_directional(t(flat), t(albedo.reshape(-1, 3)), t(np.full(pix, roughness)),
                                       t(np.zeros(pix)), t(dirs), t(irr), torch.zeros(1, 9, 3)).numpy()
        img = direct.reshape((count,) + n.shape) * np.pi + (albedo * sky)[None]
    img = np.where(inside[None, ..., None], img, 0.0)
    img *= 0.85 / np.percentile(img[:, inside].max(axis=(1, 2)), 99)  # the brightest photo near 0.85 of white
    e = rng.poisson(np.clip(img, 0, None) * full_well).astype(np.float64)
    e += rng.normal(0.0, read_noise, e.shape) + 0.0
    photos = np.clip(e / full_well, 0.0, 1.0)
    for k in range(count):
        imageio.write_png(folder / f"{k + 1:03d}.png", photos[k], bits=16)
    imageio.write_png(folder / "mask.png", inside.astype(np.float32), bits=8)
    np.savetxt(folder / "lights.txt", dirs, fmt="%.6f")
    return {"directions": dirs, "irradiance": irr, "mask": inside}

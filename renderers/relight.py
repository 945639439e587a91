"""Relight SVBRDF maps with Mitsuba 3's Principled BSDF (pure scene builder + render call).

The surface is the flat plane of :mod:`renderers.plane` (framed exactly like the input photos) carrying a
``principled`` BSDF: base colour (linear, passed raw: ``MaterialMaps`` already holds linear values), roughness and
metallic (raw), wrapped in ``normalmap`` with the camera-space normals encoded as (n + 1) / 2 (raw). On that plane,
camera space equals OpenGL-convention tangent space. Height maps are not used for displacement (flat plane).

Masked-out pixels: the plane is rendered with neutral values there (normal +z, defaults from
``MaterialMaps.with_defaults``) and :func:`render` multiplies the result by the mask's pixel coverage, so the
background is black (and transparent in PNGs written by :mod:`matcap.relight`).

Integrator: ``direct`` with multiple importance sampling. A plane cannot see itself, so one-bounce direct
lighting is the exact answer (same as ``path``), at a lower cost. Environment texels that can only light the
back of the plane are zeroed before rendering (:func:`cull_back_hemisphere`; exact for the plane), which cuts
the noise about 4x for typical maps whose light is mostly behind the object.
"""
from __future__ import annotations

import numpy as np

from renderers.emitters import emitter_dict, sanitize_envmap
from renderers.plane import ortho_sensor, plane_shape, plane_to_uv
from scenes.lights import EnvironmentLight, Light, envmap_directions
from scenes.materialmaps import MaterialMaps

DEFAULT_SPP = 16  # 1024x1024 under an env map in ~3 s on 2 cores; see docs/relight.md for the noise
DEFAULT_SPECULAR = 0.5  # Principled "specular" 0.5 = F0 of 4 % (IOR 1.5), the glTF / Disney default


def _bitmap(arr: np.ndarray):
    import mitsuba as mi

    arr = np.ascontiguousarray(np.asarray(arr, dtype=np.float32))
    return mi.Bitmap(arr)


TEXTURE_FILTERS = ("bilinear", "nearest")


def _texture(arr: np.ndarray, to_uv, texture_filter: str = "bilinear") -> dict:
    """A raw (no sRGB decoding) bitmap texture (bilinear or nearest texel), clamped at the borders."""
    return {
        "type": "bitmap",
        "bitmap": _bitmap(arr),
        "raw": True,
        "filter_type": texture_filter,
        "wrap_mode": "clamp",
        "to_uv": to_uv,
    }


def prepare_maps(maps: MaterialMaps) -> MaterialMaps:
    """Maps ready for rendering: missing BRDF maps filled, values clipped, masked-out normals set to +z."""
    m = maps.with_defaults()
    normal = np.array(m.normal, dtype=np.float32)
    norm = np.linalg.norm(normal, axis=2, keepdims=True)
    bad = (~m.mask) | (norm[..., 0] < 1e-6) | ~np.isfinite(norm[..., 0])
    normal = np.where(norm > 1e-6, normal / np.maximum(norm, 1e-6), 0.0)
    normal[bad] = (0.0, 0.0, 1.0)
    normal[..., 2] = np.maximum(normal[..., 2], 0.0)  # never face away from the camera
    normal /= np.linalg.norm(normal, axis=2, keepdims=True).clip(1e-6)
    return MaterialMaps(
        normal=normal,
        mask=m.mask,
        base_color=np.clip(np.nan_to_num(m.base_color), 0.0, 1.0),
        roughness=np.clip(np.nan_to_num(m.roughness, nan=0.5), 0.0, 1.0),
        metallic=np.clip(np.nan_to_num(m.metallic), 0.0, 1.0),
        height=m.height,
        meta=m.meta,
    )


def surface_bsdf(maps: MaterialMaps, specular: float = DEFAULT_SPECULAR, texture_filter: str = "bilinear") -> dict:
    """``normalmap(principled(base_color, roughness, metallic))`` for maps prepared by :func:`prepare_maps`.

    ``texture_filter``: "bilinear" (smooth at any output size) or "nearest" (one texel per pixel at the maps' own
    size: exactly the per-pixel model of the photo fit, :mod:`matcap.refine.model`, whose normals may change a lot
    from one pixel to the next; between two such normals the bilinear blend shows highlights that neither has)."""
    if texture_filter not in TEXTURE_FILTERS:
        raise ValueError(f"texture_filter must be one of {TEXTURE_FILTERS}, got {texture_filter!r}")
    to_uv = plane_to_uv()
    tex = lambda arr: _texture(arr, to_uv, texture_filter)  # noqa: E731
    principled = {
        "type": "principled",
        "base_color": tex(maps.base_color),
        "roughness": tex(maps.roughness[..., None]),
        "metallic": tex(maps.metallic[..., None]),
        "specular": float(specular),
    }
    return {
        "type": "normalmap",
        "normalmap": tex((maps.normal + 1.0) * 0.5),
        "bsdf": principled,
        # no shadow-terminator darkening: a normal map here stands for a surface that really turns that way (an
        # object's or a swatch's), which the photos show without it
        "use_shadowing_function": False,
    }


def _size(maps: MaterialMaps, size) -> tuple[int, int]:
    h, w = maps.shape
    if size is None:
        return int(w), int(h)
    width, height = (int(size[0]), int(size[1]))
    if width < 1 or height < 1:
        raise ValueError(f"size must be positive, got {width}x{height}")
    return width, height


def build_scene(
    maps: MaterialMaps,
    lights: list[Light],
    envmaps: dict[str, np.ndarray] | None,
    spp: int = DEFAULT_SPP,
    size: tuple[int, int] | None = None,
    *,
    seed: int = 0,
    specular: float = DEFAULT_SPECULAR,
    cull_back: bool = True,
    texture_filter: str = "bilinear",
) -> dict:
    """The Mitsuba scene dict that shows ``maps`` on the framing plane under ``lights``.

    ``envmaps`` maps an :class:`EnvironmentLight`'s ``source`` to its (H, W, 3) linear equirectangular pixels.
    ``size`` is the film's (width, height); default: the maps' size; ``texture_filter``: :func:`surface_bsdf`'s.
    Pure apart from building ``mi.Bitmap``s (call ``renderers.variant.choose_variant()`` first).
    """
    if not lights:
        raise ValueError("relighting needs at least one light")
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    width, height = _size(maps, size)
    h, w = maps.shape
    if abs(width / height - w / h) > 0.02 * (w / h):
        raise ValueError(f"size {width}x{height} does not keep the maps' aspect ratio ({w}x{h})")
    prepared = prepare_maps(maps)
    scene: dict = {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 1},
        "sensor": ortho_sensor(width, height, spp, seed=seed),
        "surface": plane_shape(w, h, surface_bsdf(prepared, specular, texture_filter)),
    }
    for i, light in enumerate(lights):
        pixels = None
        if isinstance(light, EnvironmentLight):
            if not envmaps or light.source not in envmaps:
                raise ValueError(f"no pixels for environment map {light.source!r}")
            pixels = envmaps[light.source]
            if cull_back:
                pixels = cull_back_hemisphere(sanitize_envmap(pixels, light.source or "environment map"),
                                              light.rotation_deg)
        scene[f"light_{i}"] = emitter_dict(light, pixels)
    return scene


def mask_coverage(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width) float32 fraction of each output pixel covered by ``mask`` (area resampling)."""
    m = np.asarray(mask, dtype=np.float32)
    if m.shape == (height, width):
        return m
    import cv2

    return np.clip(cv2.resize(m, (width, height), interpolation=cv2.INTER_AREA), 0.0, 1.0)


def render(
    maps: MaterialMaps,
    lights: list[Light],
    envmaps: dict[str, np.ndarray] | None = None,
    spp: int = DEFAULT_SPP,
    size: tuple[int, int] | None = None,
    seed: int = 0,
    *,
    specular: float = DEFAULT_SPECULAR,
    texture_filter: str = "bilinear",
) -> np.ndarray:
    """Render ``maps`` under ``lights``: (H, W, 3) linear float32 radiance, black where ``maps.mask`` is False
    (``texture_filter``: :func:`surface_bsdf`'s)."""
    import mitsuba as mi

    from renderers.variant import choose_variant, render_array

    choose_variant()
    scene_dict = build_scene(maps, lights, envmaps, spp, size, seed=seed, specular=specular,
                             texture_filter=texture_filter)
    scene = mi.load_dict(scene_dict)
    img = render_array(scene, spp=spp, seed=seed)[..., :3]
    height, width = img.shape[:2]
    img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
    img *= mask_coverage(maps.mask, width, height)[..., None]
    return np.ascontiguousarray(img, dtype=np.float32)


def cull_back_hemisphere(pixels: np.ndarray, rotation_deg: float = 0.0) -> np.ndarray:
    """Zero the texels that can only light the back of the plane (world z < 0), with a 2-texel margin.

    Exact for the flat plane (Mitsuba's ``normalmap`` only lets light through that is in front of both the
    geometric and the shading frame), and it stops importance sampling from wasting samples on the half of
    the sphere the surface cannot see.
    """
    h, w = pixels.shape[:2]
    d = envmap_directions(h, w, rotation_deg)
    margin = np.sin(2.0 * np.pi / h)  # two texels (pi / H rad each) past the horizon: bilinear support
    keep = d[..., 2] > -margin
    return np.where(keep[..., None], pixels, 0.0).astype(np.float32)

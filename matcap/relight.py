"""Relight SVBRDF maps (a capture result, a texture set from disk, or a ``MaterialMaps``) with Mitsuba 3.

    from matcap import relight
    images = relight("result/", env="studio.exr", rotate=90, exposure=-1, out="result/")

Each environment map gives one render (point / directional lights are added to every render; with no
environment map, the lights alone give one render). With ``out`` set, each render is written as
``relight_<name>.exr`` (linear radiance, black background) and ``relight_<name>.png`` (tone mapped, see
:func:`tonemap`; alpha = mask coverage, so the background is transparent).

Tone mapping (PNG only, the EXR stays linear): the ACES filmic curve fit of Narkowicz (2015),
``f(x) = x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)`` applied per channel to the linear radiance, clipped to
[0, 1], then sRGB-encoded. ``tonemap="clip"`` gives plain clip + sRGB instead.
"""
from __future__ import annotations

import os
import sys
import types
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from matcap import formats
from matcap.errors import MatcapError
from scenes.materialmaps import MaterialMaps

ENV_SUFFIXES = (".exr", ".hdr")
DEFAULT_ENVMAP = "studio_small_03.exr"
TONEMAPS = ("aces", "clip")


def default_envmap_path() -> Path:
    """The bundled CC0 environment map (Poly Haven "studio_small_03", 512x256, see matcap/data/envmaps)."""
    return Path(__file__).resolve().parent / "data" / "envmaps" / DEFAULT_ENVMAP


# --------------------------------------------------------------------------------------------- inputs
#: Any map source (result, export, texture set, .glb, synthetic scene): the one loader of matcap.formats.
load_maps = formats.load_maps
downsample_maps = formats.downsample_maps


def maps_from_texture_set(folder: str | os.PathLike, max_side: int | None = None, *,
                          max_size: int | None = None) -> MaterialMaps:
    """A foreign PBR texture set folder (:func:`matcap.formats.read_texture_set`: Substance / Poly Haven /
    ambientCG / plain ``basecolor`` ``normal_gl`` ``arm`` names), area-downsampled so that the longer side is at
    most ``max_side`` (``max_size`` is its former name)."""
    return formats.load_maps(formats.read_texture_set(folder), max_side=max_side or max_size)


def check_spp(spp: int) -> int:
    """``spp`` if it is a usable samples-per-pixel count (1..65536), else a one-line error."""
    if spp < 1 or spp > 65536:
        raise MatcapError(f"--spp must be between 1 and 65536, got {spp}")
    return spp


def load_envmap(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 linear equirectangular radiance from an ``.exr`` or Radiance ``.hdr`` file."""
    from matcap.imageio import check_finite, read_image

    path = Path(path)
    if path.suffix.lower() not in ENV_SUFFIXES:
        raise MatcapError(f"{path}: environment maps must be .exr or .hdr")
    if not path.is_file():
        raise MatcapError(f"{path}: no such file")
    pixels = read_image(path).pixels.astype(np.float32)
    check_finite(pixels, str(path))  # a map with NaN / Inf texels is broken; negative ones are clamped when rendering
    h, w = pixels.shape[:2]
    if abs(w / h - 2.0) > 0.1:
        raise MatcapError(f"{path}: {w}x{h} is not an equirectangular (2:1) map")
    return pixels


def env_paths(envs) -> list[Path]:
    """Expand ``envs`` (a file, a folder of .exr/.hdr, or a list of them) to sorted files; None -> default."""
    if envs is None:
        return [default_envmap_path()]
    items = [envs] if isinstance(envs, (str, os.PathLike)) else list(envs)
    out: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.suffix.lower() in ENV_SUFFIXES and q.is_file())
            if not found:
                raise MatcapError(f"{p}: no .exr or .hdr environment maps in this folder")
            out.extend(found)
        else:
            if not p.is_file():
                raise MatcapError(f"{p}: no such environment map")
            out.append(p)
    return out


def parse_vec3(value, what: str = "vector") -> tuple[float, float, float]:
    """``"X,Y,Z"`` or a 3-sequence -> 3 floats (one-line error otherwise)."""
    if isinstance(value, str):
        parts = [p for p in re.split(r"[,\s]+", value.strip()) if p]
    else:
        parts = list(value)
    try:
        vec = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        raise MatcapError(f"{what} must be three numbers X,Y,Z, got {value!r}") from None
    if len(vec) != 3 or not all(np.isfinite(vec)):
        raise MatcapError(f"{what} must be three finite numbers X,Y,Z, got {value!r}")
    return vec  # type: ignore[return-value]


def parse_rgb(value, what: str) -> tuple[float, float, float]:
    """A scalar or an RGB triple (``"W"`` or ``"R,G,B"``) -> 3 non-negative floats."""
    if isinstance(value, (int, float)):
        vec = (float(value),) * 3
    elif isinstance(value, str) and "," not in value:
        try:
            vec = (float(value),) * 3
        except ValueError:
            raise MatcapError(f"{what} must be a number or R,G,B, got {value!r}") from None
    else:
        vec = parse_vec3(value, what)
    if not all(np.isfinite(vec)) or min(vec) < 0:
        raise MatcapError(f"{what} must be finite and >= 0, got {value!r}")
    return vec


def parse_size(value) -> tuple[int, int] | None:
    """``"WxH"``, ``"N"`` (square) or a pair -> (width, height)."""
    if value is None:
        return None
    if isinstance(value, str):
        parts = value.lower().replace("*", "x").split("x")
    elif isinstance(value, int):
        parts = [value, value]
    else:
        parts = list(value)
    try:
        nums = [int(p) for p in parts]
    except (TypeError, ValueError):
        raise MatcapError(f"size must be WxH, got {value!r}") from None
    if len(nums) == 1:
        nums = nums * 2
    if len(nums) != 2 or min(nums) < 1 or max(nums) > 16384:
        raise MatcapError(f"size must be WxH with 1..16384 pixels per side, got {value!r}")
    return nums[0], nums[1]


# Renders larger than this are refused before Mitsuba allocates their film (a typo such as --size 100000 would
# otherwise end in an out-of-memory kill): 8192 x 8192, the largest texture size engines commonly use.
MAX_RENDER_PIXELS = 8192 * 8192


def fit_size(maps: MaterialMaps, size) -> tuple[int, int]:
    """The render size: ``size`` (W, H), or a single number = the longer side (aspect kept); None: maps' size.
    At most :data:`MAX_RENDER_PIXELS`."""
    h, w = maps.shape
    if size is None:
        width, height = w, h
    elif isinstance(size, int) or (isinstance(size, str) and size.strip().isdigit()):
        side = int(size)
        if side < 1:
            raise MatcapError(f"size must be positive, got {size!r}")
        s = side / max(h, w)
        width, height = max(1, round(w * s)), max(1, round(h * s))
    else:
        width, height = parse_size(size)
        if abs(width / height - w / h) > 0.02 * (w / h):
            raise MatcapError(f"size {width}x{height} does not keep the maps' aspect ratio {w}x{h}")
    if width * height > MAX_RENDER_PIXELS:
        raise MatcapError(f"a {width}x{height} render is {width * height / 1e6:.0f} megapixels; the most is "
                          f"{MAX_RENDER_PIXELS / 1e6:.0f} (8192x8192): pass a smaller --size")
    return width, height


# -------------------------------------------------------------------------------------------- outputs


def tonemap(linear: np.ndarray, mode: str = "aces") -> np.ndarray:
    """Linear radiance -> display sRGB in [0, 1] (see the module docstring)."""
    from matcap.imageio import linear_to_srgb

    x = np.clip(np.nan_to_num(np.asarray(linear, np.float32)), 0.0, None)
    if mode == "aces":
        x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
    elif mode != "clip":
        raise MatcapError(f"tone mapping must be one of {', '.join(TONEMAPS)}, got {mode!r}")
    return linear_to_srgb(np.clip(x, 0.0, 1.0))


def write_render(stem: str | os.PathLike, linear: np.ndarray, coverage: np.ndarray | None = None,
                 tonemap_mode: str = "aces") -> tuple[Path, Path]:
    """Write ``<stem>.exr`` (linear RGB) and ``<stem>.png`` (8-bit sRGB tone mapped; RGBA if ``coverage``)."""
    display = tonemap(linear, tonemap_mode)
    if coverage is not None and float(coverage.min()) < 1.0:
        # un-premultiply so the transparent edge keeps its colour
        display = tonemap(linear / np.maximum(coverage[..., None], 1e-3), tonemap_mode)
    return formats.write_render(stem, linear, display, coverage)


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "render"


def _num(v: float) -> str:
    return f"{v:g}".replace("-", "m")


# -------------------------------------------------------------------------------------------- relight


def build_lights(
    env_files: Sequence[Path] | None,
    *,
    rotate: float = 0.0,
    exposure: float = 0.0,
    point=None,
    intensity=None,
    directional=None,
    irradiance=None,
) -> list[tuple[str, list, dict[str, np.ndarray]]]:
    """The renders to make: ``[(name, lights, envmap pixels)]`` (one per environment map, or one for the
    point / directional lights alone)."""
    from scenes.lights import DirectionalLight, EnvironmentLight, PointLight

    if not np.isfinite(rotate) or not np.isfinite(exposure):
        raise MatcapError("rotate and exposure must be finite numbers")
    gain = float(2.0 ** exposure)
    extra: list = []
    tag = []
    if point is not None:
        pos = parse_vec3(point, "point light position")
        if pos[2] <= 0:
            raise MatcapError(f"point light {point!r} must be in front of the surface (Z > 0)")
        dist2 = float(np.dot(pos, pos))
        # default: irradiance pi at the centre when the light faces it (white Lambertian -> radiance 1)
        inten = parse_rgb(intensity, "intensity") if intensity is not None else (np.pi * dist2,) * 3
        extra.append(PointLight(position=pos, intensity=tuple(gain * v for v in inten)))
        tag.append("point_" + "_".join(_num(v) for v in pos))
    elif intensity is not None:
        raise MatcapError("intensity needs a point light (point=X,Y,Z / --point)")
    if directional is not None:
        d = parse_vec3(directional, "directional light direction")
        if np.linalg.norm(d) == 0:
            raise MatcapError("directional light direction must not be zero")
        irr = parse_rgb(irradiance, "irradiance") if irradiance is not None else (np.pi,) * 3
        extra.append(DirectionalLight(direction=d, irradiance=tuple(gain * v for v in irr)))
        tag.append("directional_" + "_".join(_num(v) for v in d))
    elif irradiance is not None:
        raise MatcapError("irradiance needs a directional light (directional=X,Y,Z / --directional)")
    jobs = []
    for path in env_files or []:
        pixels = load_envmap(path)
        light = EnvironmentLight(source=str(path), rotation_deg=float(rotate), scale=gain)
        jobs.append((_safe_name(Path(path).stem), [light, *extra], {str(path): pixels}))
    if not jobs:
        if not extra:
            raise MatcapError("nothing lights the scene: give an environment map, a point or a directional light")
        jobs.append((_safe_name("_".join(tag)), extra, {}))
    return jobs


def file_lights(lights_path, image: int | None, source=None, *, exposure: float = 0.0
                ) -> list[tuple[str, list, dict[str, np.ndarray]]]:
    """The render of input ``image`` under its light estimated by the fit: ``[("input_<k>", lights, envmaps)]``.

    ``lights_path``: a lights.json (default: ``source``/lights.json when ``source`` is a result folder). The
    entry's directional / point light is used as it is and its SH ambient becomes an environment map
    (:func:`matcap.refine.lightfile.entry_to_lights`); ``exposure`` scales them all by 2**EV.
    """
    from matcap.refine.lightfile import entry_for_image, entry_to_lights, read_lights
    from scenes.lights import DirectionalLight, EnvironmentLight, PointLight

    if image is None:
        raise MatcapError("--lights needs --image K: the input image to re-render under its estimated light")
    if isinstance(image, bool) or not isinstance(image, (int, np.integer)):
        raise MatcapError(f"--image must be an image index (0, 1, ...), got {image!r}")
    if lights_path is None:
        if not isinstance(source, (str, os.PathLike)) or not Path(source).is_dir():
            raise MatcapError("--image needs --lights FILE (a lights.json written by the fit)")
        lights_path = Path(source) / "lights.json"
        if not lights_path.is_file():
            raise MatcapError(f"{lights_path}: no such file (pass --lights FILE, or run the fit first)")
    if not np.isfinite(exposure):
        raise MatcapError("exposure must be a finite number")
    gain = float(2.0 ** exposure)
    entry = entry_for_image(read_lights(lights_path), int(image), str(lights_path))
    lights, envmaps = entry_to_lights(entry)
    scaled: list = []
    for light in lights:
        if isinstance(light, DirectionalLight):
            scaled.append(DirectionalLight(light.direction, tuple(gain * v for v in light.irradiance)))
        elif isinstance(light, PointLight):
            scaled.append(PointLight(light.position, tuple(gain * v for v in light.intensity)))
        else:
            scaled.append(EnvironmentLight(source=light.source, rotation_deg=light.rotation_deg, scale=gain))
    return [(f"input_{int(image)}", scaled, envmaps)]


@dataclass
class RelightPlan:
    """Checked relight settings with the environment maps already read (:func:`plan`); :func:`render_plan` renders
    them for any maps. ``jobs``: ``[(name, lights, envmap pixels)]``, one render each."""

    jobs: list
    spp: int
    size: object = None
    seed: int = 0
    tonemap_mode: str = "aces"
    per_pixel: bool = False  # at the maps' own size, one texel per pixel (the photo fit's model: --lights/--image)

    @property
    def names(self) -> list[str]:
        return [name for name, _, _ in self.jobs]


def plan(
    *,
    env=None,
    rotate: float = 0.0,
    exposure: float = 0.0,
    point=None,
    intensity=None,
    directional=None,
    irradiance=None,
    spp: int | None = None,
    size=None,
    seed: int = 0,
    tonemap_mode: str = "aces",
    lights=None,
    image: int | None = None,
    source=None,
) -> RelightPlan:
    """Check relight settings and read the environment maps once (arguments as :func:`relight`), before any
    expensive work: bad input fails here with a one-line error. ``lights`` / ``image``: the lights.json entry of
    one input photo instead of env / point / directional lights (:func:`file_lights`; ``source``: the result
    folder whose lights.json is the default)."""
    from renderers.relight import DEFAULT_SPP

    spp = check_spp(DEFAULT_SPP if spp is None else int(spp))
    if tonemap_mode not in TONEMAPS:
        raise MatcapError(f"tone mapping must be one of {', '.join(TONEMAPS)}, got {tonemap_mode!r}")
    if size is not None and not (isinstance(size, int) or (isinstance(size, str) and size.strip().isdigit())):
        parse_size(size)
    if lights is not None or image is not None:
        given = [name for name, v in (("env", env), ("point", point), ("directional", directional),
                                      ("intensity", intensity), ("irradiance", irradiance)) if v is not None]
        if rotate:
            given.append("rotate")
        if given:
            raise MatcapError(f"--lights/--image re-render an input under its estimated light; they do not combine "
                              f"with --{', --'.join(given)}")
        jobs = file_lights(lights, image, source, exposure=exposure)
    else:
        if env is None and point is None and directional is None:
            files = env_paths(None)
        else:
            files = env_paths(env) if env is not None else []
        jobs = build_lights(files, rotate=rotate, exposure=exposure, point=point, intensity=intensity,
                            directional=directional, irradiance=irradiance)
    names = [name for name, _, _ in jobs]
    if len(set(names)) != len(names):
        raise MatcapError("two environment maps have the same name; rename one")
    return RelightPlan(jobs, spp, size, seed, tonemap_mode, per_pixel=lights is not None or image is not None)


def _targets(out: Path, names: Sequence[str], overwrite: bool) -> list[Path]:
    if out.exists() and not out.is_dir():
        raise MatcapError(f"{out} exists and is not a folder")
    targets = []
    for name in names:
        stem = out / f"relight_{name}"
        for suffix in (".exr", ".png"):
            if stem.with_name(stem.name + suffix).exists() and not overwrite:
                raise MatcapError(f"{stem}{suffix} already exists; pass --overwrite to replace it")
        targets.append(stem)
    return targets


def render_plan(maps: MaterialMaps, how: RelightPlan, *, out=None, overwrite: bool = False,
                progress: bool = False) -> list[np.ndarray]:
    """Render ``maps`` for each job of ``how``; with ``out``, write ``relight_<name>.exr/.png`` there (refused
    before the first render when one exists, unless ``overwrite``). Returns (H, W, 3) linear float32 images."""
    from renderers.relight import mask_coverage, render

    width, height = fit_size(maps, how.size)
    # re-rendering an input: at the maps' own size each pixel shows its texel, as the photo fit modelled it
    texels = "nearest" if how.per_pixel and (height, width) == tuple(maps.shape) else "bilinear"
    targets = _targets(Path(out), how.names, overwrite) if out is not None else []
    images = []
    iterator = how.jobs
    if progress and len(how.jobs) > 1:
        from networks.progress import progress as progress_bar

        iterator = progress_bar(how.jobs, desc="relight", unit="render")
    for i, (name, lights, pixels) in enumerate(iterator):
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            img = render(maps, lights, pixels, spp=how.spp, size=(width, height), seed=how.seed,
                         texture_filter=texels)
        images.append(img)
        if out is not None:
            write_render(targets[i], img, mask_coverage(maps.mask, width, height), how.tonemap_mode)
    return images


def relight(
    maps_or_result_dir,
    *,
    env=None,
    rotate: float = 0.0,
    exposure: float = 0.0,
    point=None,
    intensity=None,
    directional=None,
    irradiance=None,
    spp: int | None = None,
    size=None,
    out=None,
    overwrite: bool = False,
    seed: int = 0,
    tonemap_mode: str = "aces",
    progress: bool = False,
    lights=None,
    image: int | None = None,
) -> list[np.ndarray]:
    """Render the maps under new light; returns one (H, W, 3) linear float32 image per render.

    maps_or_result_dir: ``MaterialMaps`` or any map source :func:`matcap.formats.load_maps` reads (a capture
    result, an export, a texture set, a ``.glb``).
    env: an .exr/.hdr path, a folder of them, or a list; None = the bundled studio map unless only a point or
    directional light is given. rotate: degrees about +y (up); exposure: EV, scales every light by 2**EV.
    point: ``(X, Y, Z)`` or ``"X,Y,Z"`` in camera space (the surface spans x in [-1, 1]); intensity: W/sr, scalar
    or RGB (default pi * |P|^2: irradiance pi at the centre). directional: direction toward the light;
    irradiance (default pi). spp: samples per pixel (default ``renderers.relight.DEFAULT_SPP``). size: ``"WxH"``,
    (W, H) or the longer side. out: folder for ``relight_<name>.exr/.png`` (refuses to overwrite unless
    ``overwrite``). lights / image: re-render input ``image`` (index k) under its light from a lights.json
    (default: the result folder's) as ``relight_input_<k>``, instead of env / point / directional lights
    (see :func:`file_lights`).
    """
    maps = load_maps(maps_or_result_dir)
    how = plan(env=env, rotate=rotate, exposure=exposure, point=point, intensity=intensity,
               directional=directional, irradiance=irradiance, spp=spp, size=size, seed=seed,
               tonemap_mode=tonemap_mode, lights=lights, image=image, source=maps_or_result_dir)
    return render_plan(maps, how, out=out, overwrite=overwrite, progress=progress)


# ``from matcap import relight`` gives this module (Python binds the submodule); make it callable so that
# ``relight(...)`` works while ``matcap.relight.maps_from_texture_set`` etc. stay reachable.
class _CallableModule(types.ModuleType):
    def __call__(self, *args, **kwargs):
        return relight(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule

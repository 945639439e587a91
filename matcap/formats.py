"""Every map file matcap writes or reads, in one table, and one loader for every kind of map source.

:data:`LAYOUTS` lists per layout (``result``: a capture result folder; ``scene``: a synthetic scene, whose
``basecolor.png`` is linear; ``export``: a ``matcap export`` texture set; ``glb``: the textures inside ``NAME.glb``;
``gallery``: display copies) each file with what its channels hold, its bit depth, its colour space and its normal
convention. Every writer (:func:`write_result_maps`, :func:`write_scene_maps`, :func:`write_file`,
:func:`write_render`, :func:`write_json`, :func:`write_visual`; ``matcap.export``, ``matcap.gallery``) and every
reader (:func:`load_maps`: result, scene, export, foreign texture set by :data:`FOREIGN_NAMES`, ``.glb``) goes
through it; ``docs/formats.md`` is the user's copy.

The normal conventions (:mod:`matcap.normals`, re-exported here: ``tangent_frame``, ``camera_to_tangent``,
``encode_normal`` / ``decode_normal`` with ``"gl"`` / ``"dx"``) belong to this module too; results, export and
relight take them from here.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from matcap import imageio
from matcap.errors import MatcapError
from matcap.normals import (  # noqa: F401  (part of this module's API)
    FOLD_Z,
    NORMAL_CONVENTIONS,
    camera_to_tangent,
    decode_normal,
    encode_normal,
    tangent_frame,
    tangent_to_camera,
    unit_normals,
)
from scenes.atomic import write_json_atomic
from scenes.materialmaps import MaterialMaps

# ------------------------------------------------------------------------------------------------ the table
@dataclass(frozen=True)
class MapFile:
    """One file of a layout.

    file: name; ``{name}`` = export name, ``{render}`` = render name, ``{index}`` = photo number.
    channels: what each stored channel holds: ``base_color.r|g|b``, ``normal.x|y|z``, ``roughness``, ``smoothness``
        (1 - roughness), ``metallic``, ``occlusion``, ``height``, ``mask``, ``0``, ``1``, ``image.*`` / ``radiance.*``
        (linear), ``display.*`` (display-encoded: renders, visualisations), ``coverage``; () if not an image.
    bits: 8 / 16 (PNG), 32 (float32 EXR), 0 (not an image: JSON, glb, PLY, npz).
    colour: ``"sRGB"``: base colour channels are sRGB-encoded on disk (decoded once when read); ``"linear"``.
    normal: ``"camera"`` (camera space, 0 off-mask), ``"gl"`` / ``"dx"`` (tangent space, +Y / -Y); integer files
        store (n + 1) / 2, float files the vectors.
    """

    key: str
    file: str
    channels: tuple[str, ...] = ()
    bits: int = 0
    colour: str = ""
    normal: str = ""
    description: str = ""

    def path(self, folder: str | os.PathLike, **names: Any) -> Path:
        return Path(folder) / self.file.format(**names)

    @property
    def is_image(self) -> bool:
        return self.bits > 0


RGB_BASE = ("base_color.r", "base_color.g", "base_color.b")
XYZ = ("normal.x", "normal.y", "normal.z")
DISPLAY = ("display.r", "display.g", "display.b")


def _table(*files: MapFile) -> dict[str, MapFile]:
    return {f.key: f for f in files}


REFINE_FILES = (
    MapFile("lights", "lights.json", description="refinement: the fitted lights (JSON, write_json)"),
    MapFile("fit", "fit.json", description="refinement: fit settings and losses (JSON, write_json)"),
    MapFile("residual", "residual.png", DISPLAY, 8, "sRGB",
            description="refinement: per-pixel residual, 0 .. vmax blue -> red, background black (write_visual)"),
    MapFile("light_variation", "light_variation.png", DISPLAY, 8, "sRGB",
            description="refinement: how much the light varies per pixel, 0 .. vmax blue -> red (write_visual)"),
)
RENDER_FILES = (
    MapFile("render_exr", "relight_{render}.exr", ("radiance.r", "radiance.g", "radiance.b"), 32, "linear",
            description="relit render, linear radiance, black background"),
    MapFile("render_png", "relight_{render}.png", DISPLAY + ("coverage",), 8, "sRGB",
            description="relit render tone mapped to display sRGB; alpha = mask coverage (RGB where fully covered)"),
)

LAYOUTS: dict[str, dict[str, MapFile]] = {
    "result": _table(
        MapFile("normal_exr", "normal.exr", XYZ, 32, "linear", "camera",
                "camera-space unit normals (x right, y up, z toward the camera), 0 off-mask"),
        MapFile("normal", "normal.png", XYZ, 16, "linear", "camera", "(n + 1) / 2 of the same normals; 0 off-mask"),
        MapFile("mask", "mask.png", ("mask",), 8, "linear", description="255 = surface"),
        MapFile("basecolor", "basecolor.png", RGB_BASE, 16, "sRGB", description="base colour (BRDF model only)"),
        MapFile("roughness", "roughness.png", ("roughness",), 16, "linear", description="perceptual roughness"),
        MapFile("metallic", "metallic.png", ("metallic",), 16, "linear", description="metalness"),
        MapFile("height", "height.exr", ("height",), 32, "linear",
                description="height along +z in pixel units (only when the maps carry one)"),
        MapFile("capture", "capture.json", description="inputs used, colour handling, model, settings, timings"),
        *REFINE_FILES,
        *RENDER_FILES,
        MapFile("preview", "preview_3x3.png", DISPLAY, 8, "sRGB",
                description="matcap tile: the tiled maps repeated 3 x 3, rendered under the bundled studio map, "
                            "tone mapped (a picture for people, not data)"),
    ),
    "scene": _table(
        MapFile("image", "{index:03d}.png", ("image.r", "image.g", "image.b"), 16, "linear",
                description="rendered photo k, linear, exposed and clipped"),
        MapFile("mask", "mask.png", ("mask",), 8, "linear", description="255 = object"),
        MapFile("normal_exr", "normal.exr", XYZ, 32, "linear", "camera", "ground-truth camera-space normals"),
        MapFile("basecolor", "basecolor.png", RGB_BASE, 16, "linear",
                description="ground-truth base colour, LINEAR (unlike a result's sRGB basecolor.png)"),
        MapFile("roughness", "roughness.png", ("roughness",), 16, "linear", description="ground-truth roughness"),
        MapFile("metallic", "metallic.png", ("metallic",), 16, "linear", description="ground-truth metalness"),
        MapFile("spec", "spec.json", description="the scene specification (+ ground_truth_stats)"),
        MapFile("lights", "lights.json", description="basis lights, per-image weights and exposure"),
        MapFile("data", "data.npz", description="training arrays (float16 basis renders and ground truth)"),
    ),
    "export": _table(
        MapFile("basecolor", "{name}_basecolor.png", RGB_BASE, 8, "sRGB",
                description="base colour (albedo), sRGB-encoded"),
        MapFile("normal", "{name}_normal.png", XYZ, 16, "linear", "gl",
                "tangent-space normal, OpenGL (+Y up), (n + 1) / 2"),
        MapFile("normal_dx", "{name}_normal_dx.png", XYZ, 16, "linear", "dx",
                "tangent-space normal, DirectX (-Y, G = 1 - G of the OpenGL map)"),
        MapFile("roughness", "{name}_roughness.png", ("roughness",), 16, "linear",
                description="perceptual roughness (glTF / Principled)"),
        MapFile("metallic", "{name}_metallic.png", ("metallic",), 16, "linear", description="metalness"),
        MapFile("orm", "{name}_orm.png", ("occlusion", "roughness", "metallic"), 16, "linear",
                description="R ambient occlusion (from the height map; 1 with occlusion off), G roughness, "
                            "B metallic (glTF metallicRoughness / Unreal ORM)"),
        MapFile("mask", "{name}_mask.png", ("mask",), 8, "linear",
                description="255 where the captured surface is valid, 0 elsewhere"),
        MapFile("occlusion", "{name}_occlusion.png", ("occlusion",), 16, "linear",
                description="ambient occlusion baked from the height map (1 = open sky); also in ORM R / mask "
                            "map G"),
        MapFile("maskmap", "{name}_maskmap.png", ("metallic", "occlusion", "1", "smoothness"), 16, "linear",
                description="Unity HDRP mask map: R metallic, G occlusion, B detail mask (1), A smoothness = "
                            "1 - roughness"),
        MapFile("height", "{name}_height.exr", ("height",), 32, "linear",
                description="height along +N in pixel units (1 = one pixel width), zero mean over the mask, "
                            "0 off-mask"),
        MapFile("mesh", "{name}_mesh.ply",
                description="binary PLY, one vertex per masked pixel, x right / y up / z height, pixel units, "
                            "sRGB vertex colours"),
        MapFile("glb", "{name}.glb",
                description="glTF 2.0 quad (width 1, height H/W, facing +Z, +Y up) with a metallic-roughness "
                            "material; 8-bit textures inside"),
        MapFile("json", "{name}.json", description="describes the set: files, conventions, tangent frame, model"),
    ),
    "glb": _table(
        MapFile("baseColorTexture", "{name}.glb", RGB_BASE + ("mask",), 8, "sRGB",
                description="base colour, alpha = mask (alphaMode MASK) when part of the image is off-mask"),
        MapFile("metallicRoughnessTexture", "{name}.glb", ("occlusion", "roughness", "metallic"), 8, "linear",
                description="G roughness, B metallic (R occlusion, as ORM)"),
        MapFile("normalTexture", "{name}.glb", XYZ, 8, "linear", "gl", "OpenGL tangent space"),
        MapFile("occlusionTexture", "{name}.glb", ("occlusion", "occlusion", "occlusion"), 8, "linear",
                description="ambient occlusion (R)"),
    ),
    "gallery": _table(
        MapFile("normal", "maps/normal.png", XYZ, 8, "linear", "camera", "display copy: (n + 1) / 2, black off-mask"),
        MapFile("basecolor", "maps/basecolor.png", RGB_BASE, 8, "sRGB", description="display copy, black off-mask"),
        MapFile("roughness", "maps/roughness.png", ("roughness",), 8, "linear", description="display copy"),
        MapFile("metallic", "maps/metallic.png", ("metallic",), 8, "linear", description="display copy"),
    ),
}

#: Foreign texture sets: a file whose name (lower case, split at ``_ - . space`` and camelCase, resolution tokens
#: like ``2k`` / ``4096`` and format tokens like ``png`` dropped) ends with one of these token sequences holds that
#: map; the longest match wins. Substance (``Mat_BaseColor``, ``Mat_Normal_OpenGL``, ``Mat_Normal_DirectX``,
#: ``Mat_OcclusionRoughnessMetallic``), Poly Haven (``brick_diff_2k``, ``brick_nor_gl_2k``, ``brick_arm_2k``,
#: ``brick_rough_2k``), ambientCG (``Bricks_1K_Color``, ``_NormalGL``, ``_NormalDX``, ``_Metalness``) and our
#: export without its ``NAME.json`` (``NAME_basecolor``, ``NAME_normal``, ``NAME_orm``, ``NAME_mask``) all load.
FOREIGN_NAMES: dict[str, tuple[tuple[str, ...], ...]] = {
    "base_color": (("basecolor",), ("base", "color"), ("base", "colour"), ("albedo",), ("diffuse",), ("diff",),
                   ("color",), ("colour",), ("col",)),
    "normal_gl": (("normal", "gl"), ("normalgl",), ("nor", "gl"), ("normal", "opengl"), ("nrm", "gl"),
                  ("normal",), ("nor",), ("nrm",), ("norm",)),
    "normal_dx": (("normal", "dx"), ("normaldx",), ("nor", "dx"), ("normal", "directx"), ("nrm", "dx")),
    "arm": (("arm",), ("orm",), ("occlusion", "roughness", "metallic"), ("occlusionroughnessmetallic",)),
    "roughness": (("roughness",), ("rough",), ("rgh",)),
    "metallic": (("metallic",), ("metalness",), ("metal",), ("mtl",)),
    "mask": (("mask",), ("opacity",)),
}
#: How each foreign map is stored (any bit depth is accepted when reading; 16-bit and float base colour: see
#: :func:`read_planes`).
FOREIGN_FILES: dict[str, MapFile] = {
    "base_color": MapFile("base_color", "", RGB_BASE, 8, "sRGB"),
    "normal_gl": MapFile("normal_gl", "", XYZ, 8, "linear", "gl"),
    "normal_dx": MapFile("normal_dx", "", XYZ, 8, "linear", "dx"),
    "arm": MapFile("arm", "", ("occlusion", "roughness", "metallic"), 8, "linear"),
    "roughness": MapFile("roughness", "", ("roughness",), 8, "linear"),
    "metallic": MapFile("metallic", "", ("metallic",), 8, "linear"),
    "mask": MapFile("mask", "", ("mask",), 8, "linear"),
}
_IGNORED_TOKENS = re.compile(r"^(\d+k|\d+|png|jpe?g|tiff?|exr|hdr|webp)$")


# ------------------------------------------------------------------------------------------------ encoding
def sources(maps: MaterialMaps, *, frame: np.ndarray | None = None, defaults: dict[str, Any] | None = None,
            masked: bool = False) -> dict[str, np.ndarray]:
    """The channel sources of :class:`MapFile` for ``maps``: linear planes (H, W) plus ``"normal"`` (H, W, 3)
    camera space and, with ``frame`` (3×3 rows T, B, N), ``"tangent"`` (H, W, 3) OpenGL tangent space.

    defaults: ``{"base_color": (r, g, b), "roughness": v, "metallic": v}`` fills missing BRDF maps (otherwise
    their channels are absent); masked: BRDF planes are 0 off-mask (display copies)."""
    h, w = maps.shape
    full = maps.with_defaults(defaults["base_color"], defaults["roughness"], defaults["metallic"]) if defaults \
        else maps
    mask = maps.mask
    src: dict[str, np.ndarray] = {
        "normal": np.where(mask[:, :, None], maps.normal, 0.0).astype(np.float32),
        "mask": mask.astype(np.float32),
        "occlusion": np.ones((h, w), np.float32),
        "0": np.zeros((h, w), np.float32),
        "1": np.ones((h, w), np.float32),
    }
    if frame is not None:
        src["tangent"] = camera_to_tangent(maps.normal, mask, frame)

    def clean(x: np.ndarray, nan: float = 0.0) -> np.ndarray:
        x = np.clip(np.nan_to_num(np.asarray(x, np.float32), nan=nan), 0.0, 1.0)
        return np.where(mask[..., None] if x.ndim == 3 else mask, x, 0.0).astype(np.float32) if masked else x

    if full.base_color is not None:
        base = clean(full.base_color)
        for i, c in enumerate("rgb"):
            src[f"base_color.{c}"] = base[..., i]
    if full.roughness is not None:
        src["roughness"] = clean(full.roughness, nan=0.5)
        src["smoothness"] = 1.0 - src["roughness"]
    if full.metallic is not None:
        src["metallic"] = clean(full.metallic)
    if maps.height is not None:
        src["height"] = np.asarray(maps.height, np.float32)
    return src


def pixels(spec: MapFile, src: dict[str, np.ndarray]) -> np.ndarray:
    """The array a writer stores for ``spec`` from :func:`sources`: (H, W) or (H, W, C), encoded ([0, 1] for PNG:
    normals (n + 1) / 2 in the file's convention, base colour sRGB-encoded in ``"sRGB"`` files)."""
    if spec.normal:
        if spec.normal == "camera":
            n = src["normal"]
            return n if spec.bits == 32 else encode_normal(n, "gl", mask=src["mask"] > 0.5)
        n = src["tangent"]
        return n if spec.bits == 32 else encode_normal(n, spec.normal)
    planes = [src[c] for c in spec.channels]
    if spec.colour == "sRGB" and spec.bits != 32:
        colour_idx = [i for i, c in enumerate(spec.channels) if c.startswith("base_color.")]
        if colour_idx:
            enc = imageio.linear_to_srgb(np.stack([planes[i] for i in colour_idx], axis=-1))
            for j, i in enumerate(colour_idx):
                planes[i] = enc[..., j]
    return planes[0] if len(planes) == 1 else np.stack(planes, axis=2)


def write_file(folder: str | os.PathLike, spec: MapFile, src: dict[str, np.ndarray], **names: Any) -> Path:
    """Write one image file of the table (atomically) from :func:`sources`. Returns its path."""
    path = spec.path(folder, **names)
    arr = pixels(spec, src)
    if spec.bits == 32:
        imageio.write_exr(path, arr)
    elif spec.bits in (8, 16):
        imageio.write_png(path, arr, bits=spec.bits)
    else:
        raise ValueError(f"{spec.file} is not an image file")
    return path


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write a JSON file of the table (``capture.json``, ``lights.json``, ``fit.json`` ...) atomically (numpy values
    and paths are converted). Returns the path."""
    write_json_atomic(path, obj)
    return Path(path)


def write_visual(folder: str | os.PathLike, key: str, values: np.ndarray, *, vmax: float,
                 layout: str = "result") -> Path:
    """Write a visualisation file of the table (``residual.png``, ``light_variation.png``): (H, W) values, 0 ..
    ``vmax`` mapped blue -> red (the error-map colours of ``matcap eval``), NaN = background (black), 8-bit RGB.
    A picture for people, not data. Returns the path."""
    from matcap.evaluation.metrics import colorize_error

    spec = LAYOUTS[layout][key]
    v = np.asarray(values, np.float64)
    if v.ndim != 2:
        raise ValueError(f"{spec.file}: expected (H, W) values, got {v.shape}")
    if not vmax > 0:
        raise ValueError(f"{spec.file}: vmax must be positive, got {vmax}")
    rgb = colorize_error(v, max_deg=vmax, background=0.0)
    return write_file(folder, spec, {c: rgb[..., i] for i, c in enumerate(DISPLAY)})


def write_result_maps(maps: MaterialMaps, folder: str | os.PathLike) -> list[str]:
    """Write the map files of a result folder (``normal.exr``, ``normal.png``, ``mask.png`` and the BRDF / height
    maps the maps carry) into ``folder`` (which must exist). Returns the names written."""
    src = sources(maps)
    names = []
    for spec in files_of("result", ("normal_exr", "normal", "mask", "basecolor", "roughness", "metallic", "height")):
        if spec.normal or all(c in src for c in spec.channels):
            names.append(write_file(folder, spec, src).name)
    return names


def write_scene_maps(folder: str | os.PathLike, *, normal: np.ndarray, mask: np.ndarray, base_color: np.ndarray,
                     roughness: np.ndarray, metallic: np.ndarray) -> None:
    """Write the ground-truth map files of a synthetic scene (values as given: normal (H, W, 3) camera space,
    mask (H, W) bool, base_color (H, W, 3) linear, roughness / metallic (H, W))."""
    src = {"normal": np.asarray(normal, np.float32), "mask": np.asarray(mask, np.float32),
           "roughness": np.asarray(roughness, np.float32), "metallic": np.asarray(metallic, np.float32)}
    for i, c in enumerate("rgb"):
        src[f"base_color.{c}"] = np.asarray(base_color, np.float32)[..., i]
    for key in ("mask", "normal_exr", "basecolor", "roughness", "metallic"):
        write_file(folder, LAYOUTS["scene"][key], src)


def write_scene_image(folder: str | os.PathLike, index: int, image: np.ndarray) -> Path:
    """Write photo ``index`` of a synthetic scene: (H, W, 3) linear in [0, 1], 16-bit."""
    image = np.asarray(image, np.float32)
    return write_file(folder, LAYOUTS["scene"]["image"], {f"image.{c}": image[..., i] for i, c in enumerate("rgb")},
                      index=index)


def write_render(stem: str | os.PathLike, linear: np.ndarray, display: np.ndarray,
                 coverage: np.ndarray | None = None) -> tuple[Path, Path]:
    """Write ``<stem>.exr`` (linear radiance (H, W, 3)) and ``<stem>.png`` (``display`` (H, W, 3) display-encoded
    in [0, 1], 8-bit; RGBA with ``coverage`` (H, W) as alpha when part of the image is uncovered)."""
    stem = Path(stem)
    exr_spec, png_spec = RENDER_FILES
    exr, png = stem.with_name(stem.name + ".exr"), stem.with_name(stem.name + ".png")
    src = {f"radiance.{c}": linear[..., i] for i, c in enumerate("rgb")}
    src.update({f"display.{c}": display[..., i] for i, c in enumerate("rgb")})
    imageio.write_exr(exr, pixels(exr_spec, src))
    channels = png_spec.channels
    if coverage is not None and float(coverage.min()) < 1.0:
        src["coverage"] = coverage.astype(np.float32)
    else:
        channels = channels[:3]
    imageio.write_png(png, pixels(replace(png_spec, channels=channels), src), bits=png_spec.bits)
    return exr, png


# ------------------------------------------------------------------------------------------------ decoding
def _float_image(arr, path: str = "") -> np.ndarray:
    """Integer images divided by 255 / 65535 (to [0, 1]); float images as they are (NaN / Inf refused)."""
    arr = np.asarray(arr)
    if arr.dtype.kind in "ui":
        return arr.astype(np.float32) / float(np.iinfo(arr.dtype).max)
    imageio.check_finite(arr, path)
    return arr.astype(np.float32)


def read_planes(path: str | os.PathLike, spec: MapFile) -> dict[str, np.ndarray]:
    """Read one image file of the table back into linear channels (the inverse of :func:`pixels`).

    Any stored bit depth is accepted (8 / 16-bit integers are divided by their top value). Base colour in an
    ``"sRGB"`` file is decoded once when stored as integers (a float file is taken as linear). Normal files give
    ``"normal"`` (camera) or ``"tangent"`` (OpenGL tangent space) as (H, W, 3) unit vectors (float files: the
    vectors as stored). A single-channel spec reads the green channel (grey files repeat it; a roughness map
    packed as G of an RGB file still reads right)."""
    stored = imageio.read_image(path)
    x, integer = _float_image(stored.pixels, stored.path), stored.kind != "float"
    if spec.normal:
        if not integer and spec.normal == "camera":
            return {"normal": x}
        n = decode_normal(x, "dx" if spec.normal == "dx" else "gl") if integer else x
        return {"normal" if spec.normal == "camera" else "tangent": n}
    if len(spec.channels) == 1:
        return {spec.channels[0]: np.ascontiguousarray(x[..., 1])}
    out = {c: np.ascontiguousarray(x[..., i]) for i, c in enumerate(spec.channels[:3])}
    if spec.colour == "sRGB" and integer:
        idx = [c for c in out if c.startswith("base_color.")]
        if idx:
            dec = imageio.srgb_to_linear(np.stack([out[c] for c in idx], axis=-1))
            out.update({c: dec[..., j] for j, c in enumerate(idx)})
    return out


def _base(ch: dict[str, np.ndarray]) -> np.ndarray | None:
    if not all(c in ch for c in RGB_BASE):
        return None
    return np.stack([ch[c] for c in RGB_BASE], axis=-1).astype(np.float32)


def _read_json_object(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise MatcapError(f"{path}: not valid JSON ({exc})") from None
    except OSError as exc:
        raise MatcapError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not isinstance(data, dict):
        raise MatcapError(f"{path}: expected a JSON object, got a {type(data).__name__}")
    return data


def _camera_maps(folder: Path, layout: str, meta_file: str) -> MaterialMaps:
    """A result or synthetic-scene folder (camera-space normals; mask.png > 0 is the surface)."""
    table = LAYOUTS[layout]
    ch: dict[str, np.ndarray] = {}
    for key in ("mask", "basecolor", "roughness", "metallic", "height"):
        spec = table.get(key)
        if spec is not None and spec.path(folder).is_file():
            ch.update(read_planes(spec.path(folder), spec))
    exr, png = table["normal_exr"].path(folder), folder / "normal.png"
    if exr.is_file():  # normal.exr wins over its PNG copy
        normal = read_planes(exr, table["normal_exr"])["normal"]
    elif "normal" in table and png.is_file():
        normal = read_planes(png, table["normal"])["normal"]
    else:
        raise MatcapError(f"{folder}: no normal.exr or normal.png (not a matcap result folder?)")
    if normal.ndim != 3 or normal.shape[2] != 3:
        raise MatcapError(f"{folder}: normal map has shape {normal.shape}, expected (H, W, 3)")
    if "mask" in ch:
        mask = ch.pop("mask") > 0
    elif exr.is_file():
        mask = np.linalg.norm(normal, axis=2) > 0.5
    else:  # the PNG is black (0) off-mask
        mask = imageio.read_image(png).pixels.max(axis=2) > 0
    if mask.shape != normal.shape[:2]:
        raise MatcapError(f"{folder}: mask.png is {mask.shape[::-1]} but normals are {normal.shape[1::-1]} (W, H)")
    if not exr.is_file():
        normal = np.where(mask[..., None], normal, 0.0).astype(np.float32)
    if not mask.any():
        raise MatcapError(f"{folder}: the mask is empty (no surface pixel to use)")
    meta = _read_json_object(folder / meta_file) if (folder / meta_file).is_file() else {}
    if layout == "scene":
        meta = {"source": str(folder), "kind": "synthetic scene", "spec": meta}
    try:
        return MaterialMaps(normal=normal, mask=mask, base_color=_base(ch), roughness=ch.get("roughness"),
                            metallic=ch.get("metallic"), height=ch.get("height"), meta=meta)
    except ValueError as exc:
        raise MatcapError(f"{folder}: {exc}") from None


def read_result(folder: str | os.PathLike) -> MaterialMaps:
    """A capture result folder (see the ``result`` layout) as linear :class:`MaterialMaps`. A synthetic scene
    folder is read as one (:func:`read_scene`: its base colour is linear, not sRGB)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MatcapError(f"{folder}: not a result folder")
    if is_scene(folder):
        return read_scene(folder)
    return _camera_maps(folder, "result", "capture.json")


def read_scene(folder: str | os.PathLike) -> MaterialMaps:
    """The ground-truth maps of a synthetic scene folder (its ``basecolor.png`` is linear: read as stored)."""
    return _camera_maps(Path(folder), "scene", "spec.json")


def is_scene(folder: Path) -> bool:
    """A synthetic scene folder: ``spec.json``, ``normal.exr``, ``mask.png`` and photo ``000.png``."""
    return all((folder / n).is_file() for n in ("spec.json", "normal.exr", "mask.png", "000.png"))


def is_result(folder: Path) -> bool:
    """A capture result folder: ``normal.exr``, or ``normal.png`` with ``mask.png`` or ``capture.json`` (a lone
    ``normal.png`` beside ``basecolor.png`` is a plain texture set's OpenGL map)."""
    if is_scene(folder):
        return False
    if (folder / "normal.exr").is_file():
        return True
    return (folder / "normal.png").is_file() and ((folder / "mask.png").is_file()
                                                  or (folder / "capture.json").is_file())


def read_export(json_path: str | os.PathLike) -> MaterialMaps:
    """An exported texture set (``NAME.json`` and the files it lists) as linear :class:`MaterialMaps`: normals from
    the OpenGL map (else the DirectX one) through the tangent frame recorded in the JSON."""
    json_path = Path(json_path)
    info = _read_json_object(json_path)
    if "matcap_export" not in info or not isinstance(info.get("files"), dict):
        raise MatcapError(f"{json_path}: not a matcap export description (no matcap_export / files)")
    folder, files = json_path.parent, info["files"]
    table = LAYOUTS["export"]
    ch: dict[str, np.ndarray] = {}
    for key in ("mask", "basecolor", "roughness", "metallic", "normal_dx", "normal", "height"):
        if key not in files:
            continue
        path = folder / str(files[key]["file"])
        if not path.is_file():
            raise MatcapError(f"{path}: listed in {json_path.name} but missing")
        ch.update(read_planes(path, table[key]))
    if "tangent" not in ch:
        raise MatcapError(f"{json_path}: the set has no normal map")
    if "mask" not in ch:
        raise MatcapError(f"{json_path}: the set has no mask map")
    mask = ch["mask"] >= 0.5
    try:
        frame = np.asarray(info["conventions"]["tangent_frame"]["rows_T_B_N_in_camera_space"], np.float64)
    except (KeyError, TypeError):
        frame = np.eye(3)
    if frame.shape != (3, 3) or not np.isfinite(frame).all():
        raise MatcapError(f"{json_path}: tangent frame must be 3x3 numbers")
    normal = tangent_to_camera(ch["tangent"], mask, frame)
    height = ch.get("height")
    if height is not None:
        imageio.check_finite(height, str(folder / files["height"]["file"]))
    try:
        return MaterialMaps(normal=normal, mask=mask, base_color=_base(ch), roughness=ch.get("roughness"),
                            metallic=ch.get("metallic"), height=height,
                            meta={"source": str(json_path), "kind": "export", "export": info})
    except ValueError as exc:
        raise MatcapError(f"{json_path}: {exc}") from None


def _tokens(stem: str) -> list[str]:
    stem = re.sub(r"([a-z])([A-Z])", r"\1_\2", stem)  # camelCase -> camel_Case
    parts = [t for t in re.split(r"[_\-. ]+", stem.lower()) if t]
    return [t for t in parts if not _IGNORED_TOKENS.match(t)]


def foreign_role(name: str) -> tuple[str, str] | None:
    """(map role, set prefix) of a texture file name by :data:`FOREIGN_NAMES`, or None."""
    stem = Path(name).stem
    tokens = _tokens(stem)
    # also the un-split lower-case words (NormalGL -> normalgl, BaseColor -> basecolor)
    joined = [t for t in re.split(r"[_\-. ]+", stem.lower()) if t and not _IGNORED_TOKENS.match(t)]
    best = None
    for words in (joined, tokens):
        for role, patterns in FOREIGN_NAMES.items():
            for pat in patterns:
                if len(words) >= len(pat) and tuple(words[len(words) - len(pat):]) == pat:
                    if best is None or len(pat) > best[0]:
                        best = (len(pat), role, "_".join(words[: len(words) - len(pat)]))
    return None if best is None else (best[1], best[2])


def texture_set_files(folder: Path) -> dict[str, Path]:
    """{role: file} of the foreign texture set in ``folder`` (one file per role; an error when two files claim the
    same role, e.g. two sets in one folder)."""
    found: dict[str, list[Path]] = {}
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.name.startswith(".") or p.suffix.lower() not in imageio.IMAGE_SUFFIXES:
            continue
        hit = foreign_role(p.name)
        if hit is not None:
            found.setdefault(hit[0], []).append(p)
    for role, paths in found.items():
        if len(paths) > 1:
            names = ", ".join(p.name for p in paths[:3])
            raise MatcapError(f"{folder}: {len(paths)} files hold the {role.replace('_', ' ')} map ({names}); "
                              "keep one texture set per folder")
    return {role: paths[0] for role, paths in found.items()}


def _resize(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    return cv2.resize(np.ascontiguousarray(arr), size, interpolation=cv2.INTER_AREA)


def read_texture_set(folder: str | os.PathLike) -> MaterialMaps:
    """A foreign texture set (names: :data:`FOREIGN_NAMES`) as linear :class:`MaterialMaps`.

    Base colour sRGB (8- and 16-bit integer files decoded, float files taken as linear); ``arm`` / ``orm`` packed
    R occlusion, G roughness, B metallic; separate roughness / metallic override the packed ones; normals OpenGL
    (``normal``, ``normal_gl``; ``normal_dx`` has green flipped, used only without an OpenGL map), tangent space =
    camera space of the flat sample. Maps of another size are resized (area) to the base colour's size (else the
    normal map's). The mask is the ``mask`` / ``opacity`` file (>= 0.5), else the whole image. Missing maps stay
    None (defaults at render time)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MatcapError(f"{folder}: not a folder")
    files = texture_set_files(folder)
    if "base_color" not in files and "normal_gl" not in files and "normal_dx" not in files:
        raise MatcapError(f"{folder}: no base colour or normal texture (not a texture set: see docs/formats.md for "
                          "the names that load)")
    if "normal_gl" in files:
        files.pop("normal_dx", None)
    ch: dict[str, np.ndarray] = {}
    for role in ("base_color", "normal_gl", "normal_dx", "arm", "roughness", "metallic", "mask"):
        if role in files:
            planes = read_planes(files[role], FOREIGN_FILES[role])
            if role == "arm":
                planes.pop("occlusion", None)
            ch.update(planes)
    first = ch.get("base_color.r", ch.get("tangent"))
    h, w = first.shape[:2]
    for k, v in ch.items():
        if v.shape[:2] != (h, w):
            ch[k] = _resize(v, (w, h))
    mask = ch["mask"] >= 0.5 if "mask" in ch else np.ones((h, w), bool)
    if not mask.any():
        raise MatcapError(f"{files['mask']}: the mask is empty (no surface pixel to use)")
    if "tangent" in ch:
        normal = tangent_to_camera(ch["tangent"], mask)
    else:
        normal = np.where(mask[..., None], np.float32([0, 0, 1]), 0.0).astype(np.float32)
    return MaterialMaps(
        normal=normal, mask=mask, base_color=_base(ch), roughness=ch.get("roughness"), metallic=ch.get("metallic"),
        meta={"source": str(folder), "kind": "texture set", "files": {k: v.name for k, v in files.items()},
              "normal_convention": "OpenGL tangent = camera space"},
    )


def read_glb(path: str | os.PathLike) -> MaterialMaps:
    """The material of a textured quad ``.glb`` (as :mod:`matcap.export` writes) as linear :class:`MaterialMaps`.

    Base colour sRGB-decoded (times baseColorFactor); roughness / metallic = the metallicRoughness texture's
    G / B times the factors; the mask from the base colour alpha (all valid without one); normals decoded as OpenGL
    tangent space = camera space of the flat sample. Texture rows follow the quad's UVs (image top = V 1)."""
    import trimesh

    try:
        loaded = trimesh.load(str(path), force="scene")
    except Exception as exc:  # trimesh raises many kinds for broken files
        raise MatcapError(f"{path}: cannot read glb ({exc})") from None
    geoms = list(loaded.geometry.values())
    if len(geoms) != 1 or not hasattr(geoms[0].visual, "material"):
        raise MatcapError(f"{path}: expected one textured quad, found {len(geoms)} geometries")
    quad = geoms[0]
    mat = quad.visual.material
    if getattr(mat, "normalTexture", None) is None:
        raise MatcapError(f"{path}: material has no normal texture")
    # which image row is the top of the quad? (our quads: the +y vertices have v = 1 in trimesh's v-up UVs)
    top = quad.vertices[:, 1] >= quad.vertices[:, 1].max() - 1e-9
    flip_rows = float(np.mean(quad.visual.uv[top, 1])) < 0.5

    def image(img) -> np.ndarray:
        arr = _float_image(img)
        return arr[::-1] if flip_rows else arr

    table = LAYOUTS["glb"]
    nimg = image(mat.normalTexture.convert("RGB"))
    h, w = nimg.shape[:2]

    def factor(value, default: float) -> float:
        return default if value is None else float(value)

    if mat.baseColorTexture is not None:
        rgba = image(mat.baseColorTexture.convert("RGBA"))
        if table["baseColorTexture"].colour == "sRGB":
            base = imageio.srgb_to_linear(rgba[..., :3])
        else:
            base = rgba[..., :3]
        mask = rgba[..., 3] >= 0.5
    else:
        base, mask = None, np.ones((h, w), bool)
    bcf = getattr(mat, "baseColorFactor", None)
    if bcf is not None:
        f = np.asarray(bcf, np.float32)
        f = f / 255.0 if np.asarray(bcf).dtype == np.uint8 else f
        if base is None:
            base = np.broadcast_to(f[:3], (h, w, 3)).copy()
        else:
            base = base * f[:3]
    rf, mf = factor(mat.roughnessFactor, 1.0), factor(mat.metallicFactor, 1.0)
    if mat.metallicRoughnessTexture is not None:
        mr = image(mat.metallicRoughnessTexture.convert("RGB"))
        rough, metal = mr[..., 1] * rf, mr[..., 2] * mf
    else:
        rough, metal = np.full((h, w), rf, np.float32), np.full((h, w), mf, np.float32)
    normal = tangent_to_camera(decode_normal(nimg, table["normalTexture"].normal), mask)
    return MaterialMaps(normal=normal, mask=mask, base_color=base, roughness=rough, metallic=metal,
                        meta={"source": str(path), "kind": "glb"})


def _export_descriptions(folder: Path) -> list[Path]:
    out = []
    for p in sorted(folder.glob("*.json")):
        if p.name.startswith(".") or p.stat().st_size > 10_000_000:
            continue
        try:
            data = json.loads(p.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(data, dict) and "matcap_export" in data:
            out.append(p)
    return out


KINDS = ("result", "scene", "export", "texture set", "glb")


def identify(source: str | os.PathLike) -> tuple[str, Path]:
    """(kind, path) of a map source: one of :data:`KINDS` (a folder, an export's ``NAME.json`` or a ``.glb``)."""
    path = Path(source)
    if path.is_file():
        if path.suffix.lower() == ".glb":
            return "glb", path
        if path.suffix.lower() == ".json":
            return "export", path
        raise MatcapError(f"{path}: not a map folder, an export's NAME.json or a .glb")
    if not path.is_dir():
        raise MatcapError(f"{path}: no such folder (expected a capture result, a texture set, an export or a .glb)")
    if is_scene(path):
        return "scene", path
    if is_result(path):
        return "result", path
    described = _export_descriptions(path)
    if len(described) > 1:
        names = ", ".join(p.name for p in described[:3])
        raise MatcapError(f"{path}: holds {len(described)} exported texture sets ({names}); pass one NAME.json")
    if described:
        return "export", described[0]
    if texture_set_files(path):
        return "texture set", path
    glbs = [p for p in path.glob("*.glb") if not p.name.startswith(".")]
    if len(glbs) == 1:
        return "glb", glbs[0]
    raise MatcapError(f"{path}: no basecolor.* or normal_gl.* texture, normal.exr or .glb (not a capture result "
                      "or texture set; docs/formats.md lists the names that load)")


def default_name(source: str | os.PathLike) -> str:
    """The name a map source gives its export: ``NAME`` of an export's ``NAME.json`` / a ``NAME.glb``, else the
    folder's name."""
    try:
        kind, path = identify(source)
    except MatcapError:
        return Path(source).resolve().name
    return path.stem if kind in ("export", "glb") else path.resolve().name


READERS = {"result": read_result, "scene": read_scene, "export": read_export, "texture set": read_texture_set,
           "glb": read_glb}


def load_maps(source: MaterialMaps | str | os.PathLike, max_side: int | None = None) -> MaterialMaps:
    """Linear :class:`MaterialMaps` from any map source: ``MaterialMaps`` (returned as is), a capture result
    folder, a synthetic scene folder, an export (its folder or ``NAME.json``), a foreign texture set folder or a
    ``.glb``. Every file is decoded once, by the table. ``max_side`` area-downsamples so that the longer side is
    at most that many pixels."""
    if isinstance(source, MaterialMaps):
        maps = source
    else:
        kind, path = identify(source)
        maps = READERS[kind](path)
    if max_side and max(maps.shape) > max_side:
        maps = downsample_maps(maps, max_side)
    return maps


def downsample_maps(maps: MaterialMaps, max_side: int) -> MaterialMaps:
    """Area-downsample every map so the longer side is at most ``max_side`` (normals renormalised, heights scaled
    to the new pixel size)."""
    h, w = maps.shape
    if max(h, w) <= max_side:
        return maps
    s = max_side / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    mask = _resize(maps.mask.astype(np.float32), size) > 0.5
    n = _resize(maps.normal, size)
    n = n / np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-6)
    n[~mask] = 0.0

    def r(x):
        return None if x is None else _resize(x, size)

    return MaterialMaps(normal=n, mask=mask, base_color=r(maps.base_color), roughness=r(maps.roughness),
                        metallic=r(maps.metallic), height=None if maps.height is None else r(maps.height) * s,
                        meta=dict(maps.meta))


def files_of(layout: str, keys: Iterable[str] | None = None) -> list[MapFile]:
    """The table rows of ``layout`` (all, or those of ``keys`` in that order)."""
    table = LAYOUTS[layout]
    return list(table.values()) if keys is None else [table[k] for k in keys]

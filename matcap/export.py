"""Engine-ready SVBRDF texture sets: loose PNG/EXR maps, packed maps per engine preset, a glTF 2.0 ``.glb`` quad.

Every file, channel layout, encoding and convention is listed in ONE table in ``docs/export.md``; this module is
the only place where export encodings are decided. Summary:

* Tangent space. Capture normals are camera-space (x right, y up, z toward the camera). The exported material is a
  flat sample whose UVs are the image axes (U right, V up, image row 0 = V 1), so with tangent T = +U = +x,
  bitangent B = +V = +y and N = +z the tangent-space normal equals the camera-space normal (``frame="camera"``,
  default). ``frame="fit"`` instead treats the mean normal over the mask as the sample's N (a sample photographed
  slightly obliquely): T = image x projected onto the sample plane, B = N × T, and normals are expressed in
  (T, B, N). Normals facing away from the camera (z < 0) are folded to the horizon (z = 1e-3); off-mask normals
  are flat (0, 0, 1).
* OpenGL (+Y, green = up) is the default; DirectX (-Y) is the same map with G = 1 - G.
* Colour: base colour is sRGB-encoded; everything else is linear ("Non-Color").
* Presets are data (:data:`PRESETS`): which packed textures to add, the default normal convention and how each
  engine input is wired. One code path writes any preset.

Missing BRDF maps (normal-only results): single maps that do not exist are not written; packed maps that need
them are written if at least one of their BRDF sources exists, with missing channels filled with the
``MaterialMaps.with_defaults`` constants (base colour 0.8, roughness 0.5, metallic 0, occlusion 1). ``NAME.json``
lists ``missing`` maps and ``filled`` channels. The glb uses glTF factors for maps that do not exist.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from matcap import imageio
from matcap.errors import MatcapError
from scenes.materialmaps import MaterialMaps

FORMAT_VERSION = 1
DEFAULTS = {"base_color": (0.8, 0.8, 0.8), "roughness": 0.5, "metallic": 0.0, "occlusion": 1.0}
FOLD_Z = 1e-3


# ------------------------------------------------------------------------------------------------ presets as data
@dataclass(frozen=True)
class Texture:
    """One PNG: ``channels`` names the source of each channel (1, 3 or 4 channels).

    Sources: ``base_color.r|g|b`` (sRGB-encoded), ``normal_gl.x|y|z`` / ``normal_dx.x|y|z`` ((n + 1) / 2),
    ``roughness``, ``smoothness`` (1 - roughness), ``metallic``, ``occlusion`` (baked from the height map, or 1),
    ``mask``, ``0``, ``1``.
    """

    key: str  # file name is NAME_<key>.png
    channels: tuple[str, ...]
    bits: int
    colorspace: str  # "sRGB" or "linear"
    description: str


@dataclass(frozen=True)
class Preset:
    name: str
    normal: str  # default normal convention, "gl" or "dx"
    extra: tuple[Texture, ...] = ()
    # engine input -> (texture key, channel(s) used, engine import setting)
    slots: dict[str, tuple[str, str, str]] = field(default_factory=dict)
    notes: str = ""


RGB_BASE = ("base_color.r", "base_color.g", "base_color.b")
TEXTURES: dict[str, Texture] = {
    t.key: t
    for t in (
        Texture("basecolor", RGB_BASE, 8, "sRGB", "base colour (albedo), sRGB-encoded"),
        Texture("normal", ("normal_gl.x", "normal_gl.y", "normal_gl.z"), 16, "linear",
                "tangent-space normal, OpenGL (+Y up), (n + 1) / 2"),
        Texture("normal_dx", ("normal_dx.x", "normal_dx.y", "normal_dx.z"), 16, "linear",
                "tangent-space normal, DirectX (-Y, G = 1 - G of the OpenGL map)"),
        Texture("roughness", ("roughness",), 16, "linear", "perceptual roughness (glTF / Principled)"),
        Texture("metallic", ("metallic",), 16, "linear", "metalness"),
        Texture("orm", ("occlusion", "roughness", "metallic"), 16, "linear",
                "R ambient occlusion (from the height map; 1 with occlusion off), G roughness, B metallic "
                "(glTF metallicRoughness / Unreal ORM)"),
        Texture("mask", ("mask",), 8, "linear", "255 where the captured surface is valid, 0 elsewhere"),
        Texture("occlusion", ("occlusion",), 16, "linear",
                "ambient occlusion baked from the height map (1 = open sky); also in ORM R / mask map G"),
    )
}
UNITY_MASKMAP = Texture("maskmap", ("metallic", "occlusion", "1", "smoothness"), 16, "linear",
                        "Unity HDRP mask map: R metallic, G occlusion, B detail mask (1), A smoothness = 1 - roughness")

PRESETS: dict[str, Preset] = {
    p.name: p
    for p in (
        Preset("gltf", "gl", (), {
            "baseColorTexture": ("basecolor", "RGB", "sRGB"),
            "metallicRoughnessTexture": ("orm", "G roughness, B metallic", "linear"),
            "normalTexture": ("normal", "RGB", "linear, OpenGL"),
        }, "glTF 2.0 metallic-roughness; three.js / Babylon / model-viewer load NAME.glb directly."),
        Preset("unreal", "dx", (), {
            "Base Color": ("basecolor", "RGB", "sRGB on"),
            "Normal": ("normal_dx", "RGB", "Compression Settings: Normalmap (sRGB off)"),
            "Ambient Occlusion / Roughness / Metallic": ("orm", "R / G / B", "Compression Settings: Masks (sRGB off)"),
        }, "Unreal Engine: DirectX normal map and the packed ORM texture."),
        Preset("unity-hdrp", "gl", (UNITY_MASKMAP,), {
            "Base Map": ("basecolor", "RGB", "sRGB (Color Texture) on"),
            "Mask Map": ("maskmap", "R metallic, G occlusion, B detail mask, A smoothness", "sRGB (Color Texture) off"),
            "Normal Map": ("normal", "RGB", "Texture Type: Normal map"),
        }, "Unity HDRP Lit: OpenGL normal map; smoothness = 1 - roughness in the mask map's alpha."),
        Preset("blender", "gl", (), {
            "Base Color": ("basecolor", "RGB", "Color Space: sRGB"),
            "Roughness": ("roughness", "grey", "Color Space: Non-Color"),
            "Metallic": ("metallic", "grey", "Color Space: Non-Color"),
            "Normal (Normal Map node, Tangent Space)": ("normal", "RGB", "Color Space: Non-Color"),
            "Displacement (Height)": ("height", "float EXR, pixel units", "Color Space: Non-Color"),
        }, "Blender Principled BSDF: OpenGL normal map; all maps but base colour Non-Color."),
    )
}
NORMAL_CONVENTIONS = ("gl", "dx")


# ------------------------------------------------------------------------------------------------ tangent space
def tangent_frame(normal: np.ndarray, mask: np.ndarray, frame: str = "camera") -> np.ndarray:
    """3×3 matrix whose rows are T, B, N of the flat sample in camera space (see module doc)."""
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
    """Camera-space normals (H, W, 3) -> OpenGL tangent-space unit normals of the flat sample (z >= 1e-3).

    Off-mask and zero normals become (0, 0, 1).
    """
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


def encode_normal(tangent: np.ndarray, convention: str = "gl") -> np.ndarray:
    """Unit tangent-space normals -> (n + 1) / 2 in [0, 1]; ``"dx"`` flips green (G = 1 - G)."""
    enc = (np.asarray(tangent, np.float32) + 1.0) * 0.5
    if convention == "dx":
        enc[..., 1] = 1.0 - enc[..., 1]
    elif convention != "gl":
        raise ValueError(f"normal convention must be 'gl' or 'dx', got {convention!r}")
    return enc


def decode_normal(encoded: np.ndarray, convention: str = "gl") -> np.ndarray:
    """Inverse of :func:`encode_normal`, renormalised."""
    n = np.asarray(encoded, np.float64) * 2.0 - 1.0
    if convention == "dx":
        n[..., 1] = -n[..., 1]
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)
    return n.astype(np.float32)


# ------------------------------------------------------------------------------------------------ sources
def _sources(maps: MaterialMaps, frame: np.ndarray) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per-channel sources in [0, 1] (already encoded), and the BRDF maps that are missing."""
    h, w = maps.shape
    full = maps.with_defaults(DEFAULTS["base_color"], DEFAULTS["roughness"], DEFAULTS["metallic"])
    tangent = camera_to_tangent(maps.normal, maps.mask, frame)
    gl, dx = encode_normal(tangent, "gl"), encode_normal(tangent, "dx")
    base = imageio.linear_to_srgb(np.clip(np.nan_to_num(full.base_color), 0.0, 1.0))
    rough = np.clip(np.nan_to_num(full.roughness, nan=DEFAULTS["roughness"]), 0.0, 1.0)
    src = {
        "roughness": rough,
        "smoothness": 1.0 - rough,
        "metallic": np.clip(np.nan_to_num(full.metallic), 0.0, 1.0),
        "occlusion": np.full((h, w), DEFAULTS["occlusion"], np.float32),
        "mask": maps.mask.astype(np.float32),
        "0": np.zeros((h, w), np.float32),
        "1": np.ones((h, w), np.float32),
    }
    for i, c in enumerate("rgb"):
        src[f"base_color.{c}"] = base[..., i]
    for i, c in enumerate("xyz"):
        src[f"normal_gl.{c}"] = gl[..., i]
        src[f"normal_dx.{c}"] = dx[..., i]
    missing = [k for k in ("base_color", "roughness", "metallic") if getattr(maps, k) is None]
    return src, missing


def _brdf_source(channel: str) -> str | None:
    base = channel.split(".")[0]
    if base in ("base_color", "roughness", "metallic"):
        return base
    if base == "smoothness":
        return "roughness"
    return None


def _stack(src: dict[str, np.ndarray], tex: Texture) -> np.ndarray:
    planes = [src[c] for c in tex.channels]
    return planes[0] if len(planes) == 1 else np.stack(planes, axis=2)


# ------------------------------------------------------------------------------------------------ provenance
def _find_keys(obj: Any, pattern: str, path: str = "") -> list[tuple[str, Any]]:
    found = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            here = f"{path}.{k}" if path else str(k)
            if re.search(pattern, str(k), re.I) and isinstance(v, (str, int, float)):
                found.append((here, v))
            found.extend(_find_keys(v, pattern, here))
    return found


def provenance(meta: dict[str, Any]) -> dict[str, Any]:
    """Model name(s) and licence(s) recorded in a result's ``capture.json`` (``"unknown"`` when not recorded)."""
    models: dict[str, Any] = {}
    recorded = meta.get("models") if isinstance(meta.get("models"), dict) else {}
    for target, info in recorded.items():
        if not isinstance(info, dict):
            continue
        card = info.get("card") if isinstance(info.get("card"), dict) else {}
        name = info.get("name") or card.get("name") or info.get("weights") or card.get("preset") or "unknown"
        licences = [v for _, v in _find_keys(info, r"licen[cs]e")]
        models[target] = {"model": str(name), "licence": str(licences[0]) if licences else "unknown"}
    if not models:
        names = [v for k, v in _find_keys(meta, r"^(model|model_name|weights)$")]
        licences = [v for _, v in _find_keys(meta, r"licen[cs]e")]
        models["all"] = {"model": str(names[0]) if names else "unknown",
                         "licence": str(licences[0]) if licences else "unknown"}
    return models


# ------------------------------------------------------------------------------------------------ export
def _safe_name(name: str) -> str:
    clean = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._")
    if not clean:
        raise MatcapError(f"export name {name!r} has no usable characters (letters, digits, . _ -)")
    return clean


def _load(maps: MaterialMaps | str | os.PathLike) -> tuple[MaterialMaps, str | None]:
    if isinstance(maps, MaterialMaps):
        return maps, None
    folder = Path(maps)
    if not folder.is_dir():
        raise MatcapError(f"{folder}: not a result folder")
    from matcap.results import read_result

    return read_result(folder), folder.resolve().name


def check_preset(preset: str) -> str:
    """``preset`` if it names an export preset, else a one-line error listing them."""
    if preset not in PRESETS:
        raise MatcapError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    return preset


def export(
    maps: MaterialMaps | str | os.PathLike,
    out: str | os.PathLike,
    *,
    name: str | None = None,
    preset: str = "gltf",
    normal: str | None = None,
    height: bool = True,
    mesh: bool = False,
    overwrite: bool = False,
    glb: bool = True,
    height_method: str = "frankot-chellappa",
    frame: str = "camera",
    occlusion: bool = True,
    ao_radius: float | None = None,
) -> dict[str, str]:
    """Write the texture set of ``maps`` (a MaterialMaps or a result folder) into ``out``.

    name: file prefix (default: the result folder's name, else ``"material"``). preset: one of :data:`PRESETS`.
    normal: ``"gl"`` / ``"dx"``; ``None`` = the preset's convention. ``NAME_normal.png`` is always OpenGL;
    ``"dx"`` adds ``NAME_normal_dx.png``. height: write ``NAME_height.exr`` (the maps' height, else integrated
    from the normals with ``height_method``). mesh: also ``NAME_mesh.ply``. occlusion: bake ambient occlusion from
    the height map (:func:`matcap.height.ambient_occlusion`, horizon radius ``ao_radius`` pixels, default 2% of the
    larger image side, at least 4) into the occlusion channels (ORM R, Unity mask map G, glTF occlusionTexture);
    off: occlusion 1. Refuses to replace existing files
    unless ``overwrite``. Returns {file key: path written}.
    """
    from matcap.height import METHODS, ambient_occlusion, height_mesh, integrate_normals

    spec = PRESETS[check_preset(preset)]
    normal = spec.normal if normal is None else normal
    if normal not in NORMAL_CONVENTIONS:
        raise MatcapError(f"unknown normal convention {normal!r}; choose gl or dx")
    if height_method not in METHODS:
        raise MatcapError(f"unknown height method {height_method!r}; choose one of {', '.join(METHODS)}")
    if mesh and not height:
        raise MatcapError("a mesh needs the height map; do not combine mesh with height=False")
    maps, folder_name = _load(maps)
    name = _safe_name(name or folder_name or "material")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise MatcapError(f"{out} exists and is not a folder")
    if not np.isfinite(maps.normal).all():
        raise MatcapError("normal map holds NaN or Inf values")
    if not maps.mask.any():
        raise MatcapError("the mask is empty: nothing to export")

    if ao_radius is not None and not ao_radius >= 1:
        raise MatcapError(f"the occlusion radius must be at least 1 pixel, got {ao_radius}")
    m = tangent_frame(maps.normal, maps.mask, frame)
    src, missing = _sources(maps, m)
    hmap = how = None
    if height or occlusion:
        if maps.height is not None:
            hmap, how = np.where(maps.mask, np.nan_to_num(maps.height), 0.0).astype(np.float32), "given with the maps"
        else:
            # integrate the tangent-space normals: heights along the sample's N (= camera z for frame "camera")
            tangent = camera_to_tangent(maps.normal, maps.mask, m)
            hmap, how = integrate_normals(tangent, maps.mask, height_method), f"integrated ({height_method})"
    occlusion_info: dict[str, Any] = {"method": "none (1 everywhere)"}
    if occlusion:
        h, w = maps.shape
        radius = float(ao_radius) if ao_radius is not None else max(4.0, 0.02 * max(h, w))
        directions = 16
        src["occlusion"] = ambient_occlusion(hmap, maps.mask, radius=radius, directions=directions)
        occlusion_info = {"method": "horizon-based ambient occlusion of the height map", "radius_px": radius,
                          "directions": directions, "mean": float(src["occlusion"][maps.mask].mean())}
    textures = [TEXTURES[k] for k in ("basecolor", "normal", "roughness", "metallic", "orm", "mask")]
    if occlusion:
        textures.insert(5, TEXTURES["occlusion"])
    if normal == "dx":
        textures.insert(2, TEXTURES["normal_dx"])
    textures += list(spec.extra)
    written_tex, filled = [], {}
    for tex in textures:
        needs = {s for s in (_brdf_source(c) for c in tex.channels) if s}
        if needs and needs <= set(missing):
            continue  # every BRDF source of this texture is missing: do not write a made-up map
        for s in sorted(needs & set(missing)):
            filled.setdefault(tex.key, []).append(f"{s} = {DEFAULTS[s]}")
        written_tex.append(tex)

    paths = {t.key: out / f"{name}_{t.key}.png" for t in written_tex}
    if height:
        paths["height"] = out / f"{name}_height.exr"
    if mesh:
        paths["mesh"] = out / f"{name}_mesh.ply"
    if glb:
        paths["glb"] = out / f"{name}.glb"
    paths["json"] = out / f"{name}.json"
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise MatcapError(f"{existing[0]} already exists ({len(existing)} file(s) of this export); "
                          "pass --overwrite to replace them")
    out.mkdir(parents=True, exist_ok=True)

    files: dict[str, dict[str, Any]] = {}
    for tex in written_tex:
        imageio.write_png(paths[tex.key], _stack(src, tex), bits=tex.bits)
        files[tex.key] = {
            "file": paths[tex.key].name, "channels": list(tex.channels), "bits": tex.bits,
            "colorspace": tex.colorspace, "description": tex.description,
        }
    height_info = None
    if height:
        imageio.write_exr(paths["height"], hmap)
        height_info = {"method": how, "range": [float(hmap[maps.mask].min()), float(hmap[maps.mask].max())]}
        files["height"] = {
            "file": paths["height"].name, "channels": ["Y"], "bits": 32, "colorspace": "linear",
            "description": f"height along +N in pixel units (1 = one pixel width), zero mean over the mask, "
                          f"0 off-mask; {how}",
        }
        if mesh:
            surface = height_mesh(hmap, maps.mask, maps.base_color)
            with imageio.atomic_path(paths["mesh"]) as tmp:
                surface.export(tmp, file_type="ply")
            files["mesh"] = {"file": paths["mesh"].name, "description":
                             "binary PLY, one vertex per masked pixel, x right / y up / z height, pixel units, "
                             "sRGB vertex colours"}
    if glb:
        imageio.write_bytes_atomic(paths["glb"], build_glb(maps, src, missing, name, occlusion))
        files["glb"] = {"file": paths["glb"].name, "description":
                        "glTF 2.0 quad (width 1, height H/W, facing +Z, +Y up) with a metallic-roughness "
                        "material; 8-bit textures inside"}

    h, w = maps.shape
    info = {
        "matcap_export": FORMAT_VERSION,
        "name": name,
        "resolution": {"width": w, "height": h},
        "preset": {"name": spec.name, "notes": spec.notes,
                   "slots": {k: {"file": f"{name}_{v[0]}.png" if v[0] != "height" else f"{name}_height.exr",
                                 "channels": v[1], "setting": v[2]} for k, v in spec.slots.items()}},
        "normal_convention": {"gl": "OpenGL (+Y, green up)", "dx": "DirectX (-Y, green down)"}[normal],
        "conventions": {
            "tangent_space": "flat sample, UV = image axes: U right, V up (image row 0 = V 1); T = +U, B = +V, N out "
                             "of the surface; NAME_normal.png is OpenGL (+Y), NAME_normal_dx.png has G = 1 - G",
            "tangent_frame": {"kind": frame, "rows_T_B_N_in_camera_space": np.round(m, 8).tolist()},
            "normal_encoding": "(n + 1) / 2 per channel; off-mask texels are flat (0.5, 0.5, 1)",
            "colour": "basecolor sRGB-encoded (IEC 61966-2-1); all other maps linear (Non-Color)",
            "height_units": "pixels along +N",
        },
        "files": files,
        "missing": missing,
        "filled": filled,
        "defaults": {k: list(v) if isinstance(v, tuple) else v for k, v in DEFAULTS.items()},
        "height": height_info,
        "occlusion": occlusion_info,
        "model": provenance(maps.meta),
        "constant_maps": dict(maps.meta.get("constant_maps") or {}),  # maps set by hand (--constant)
    }
    imageio.write_text_atomic(paths["json"], json.dumps(info, indent=2) + "\n")
    return {k: str(p) for k, p in paths.items()}


# ------------------------------------------------------------------------------------------------ glb
def _pil(x: np.ndarray):
    from PIL import Image

    return Image.fromarray(imageio.quantize(x, 8))


def build_glb(maps: MaterialMaps, src: dict[str, np.ndarray], missing: list[str], name: str,
              occlusion: bool = False) -> bytes:
    """The glb bytes: one quad, UV = image axes (V up), glTF metallic-roughness material with 8-bit textures
    (``occlusion``: plus ``src["occlusion"]`` as the occlusionTexture)."""
    import trimesh
    from trimesh.visual.material import PBRMaterial

    h, w = maps.shape
    hx, hy = 0.5, 0.5 * h / w
    vertices = np.array([[-hx, hy, 0], [hx, hy, 0], [-hx, -hy, 0], [hx, -hy, 0]], np.float64)  # TL TR BL BR
    uv = np.array([[0, 1], [1, 1], [0, 0], [1, 0]], np.float64)  # trimesh UVs: v up (glTF flips on export)
    faces = np.array([[0, 2, 3], [0, 3, 1]])
    kwargs: dict[str, Any] = {"name": name, "doubleSided": False}
    cut = not maps.mask.all()
    if "base_color" not in missing or cut:
        rgb = [src[c] for c in RGB_BASE]
        kwargs["baseColorTexture"] = _pil(np.stack(rgb + ([src["mask"]] if cut else []), axis=2))
        if cut:
            kwargs["alphaMode"] = "MASK"
            kwargs["alphaCutoff"] = 0.5
    else:
        kwargs["baseColorFactor"] = [*DEFAULTS["base_color"], 1.0]
    if not {"roughness", "metallic"} <= set(missing):
        kwargs["metallicRoughnessTexture"] = _pil(np.stack([src["occlusion"], src["roughness"], src["metallic"]], 2))
        kwargs["roughnessFactor"], kwargs["metallicFactor"] = 1.0, 1.0
    else:
        kwargs["roughnessFactor"], kwargs["metallicFactor"] = float(DEFAULTS["roughness"]), float(DEFAULTS["metallic"])
    kwargs["normalTexture"] = _pil(np.stack([src[f"normal_gl.{c}"] for c in "xyz"], axis=2))
    if occlusion:
        kwargs["occlusionTexture"] = _pil(np.repeat(src["occlusion"][..., None], 3, axis=2))
    material = PBRMaterial(**kwargs)
    quad = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_normals=np.tile([0.0, 0.0, 1.0], (4, 1)),
                           visual=trimesh.visual.TextureVisuals(uv=uv, material=material), process=False)
    scene = trimesh.Scene()
    scene.add_geometry(quad, geom_name=name, node_name=name)
    return _add_tangents(scene.export(file_type="glb", include_normals=True), (1.0, 0.0, 0.0, 1.0))


def _add_tangents(glb: bytes, tangent: tuple[float, float, float, float]) -> bytes:
    """Give every primitive an explicit TANGENT attribute (trimesh cannot write one: it prefixes custom
    attributes with "_"). T = +x, w = +1 makes the bitangent cross(N, T) * w = +y = image up, so the OpenGL normal
    texture means the same in every engine instead of depending on runtime-generated (MikkTSpace) tangents."""
    import struct

    magic, version, _ = struct.unpack_from("<4sII", glb, 0)
    if magic != b"glTF" or version != 2:
        raise ValueError("not a glTF 2.0 binary")
    json_len, json_type = struct.unpack_from("<I4s", glb, 12)
    tree = json.loads(glb[20:20 + json_len])
    rest = glb[20 + json_len:]
    if rest:
        bin_len, bin_type = struct.unpack_from("<I4s", rest, 0)
        binary = bytearray(rest[8:8 + bin_len])
    else:
        binary = bytearray()
    for mesh in tree.get("meshes", []):
        for prim in mesh["primitives"]:
            count = tree["accessors"][prim["attributes"]["POSITION"]]["count"]
            offset = len(binary)
            binary += np.tile(np.asarray(tangent, "<f4"), (count, 1)).tobytes()
            tree.setdefault("bufferViews", []).append(
                {"buffer": 0, "byteOffset": offset, "byteLength": 16 * count, "target": 34962})
            tree["accessors"].append({"bufferView": len(tree["bufferViews"]) - 1, "componentType": 5126,
                                      "count": count, "type": "VEC4"})
            prim["attributes"]["TANGENT"] = len(tree["accessors"]) - 1
            # vertex / index buffer view targets (validator hints; lets loaders upload them directly)
            for acc, target in [(a, 34962) for a in prim["attributes"].values()] + [(prim.get("indices"), 34963)]:
                view = tree["accessors"][acc].get("bufferView") if acc is not None else None
                if view is not None:
                    tree["bufferViews"][view].setdefault("target", target)
    binary += b"\0" * (-len(binary) % 4)
    tree["buffers"][0]["byteLength"] = len(binary)
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(text), b"JSON") + text
            + struct.pack("<I4s", len(binary), b"BIN\0") + bytes(binary))


def _float_image(img) -> np.ndarray:
    arr = np.asarray(img)
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    if arr.dtype == np.uint16:
        return arr.astype(np.float32) / 65535.0
    return arr.astype(np.float32)


def maps_from_glb(path: str | os.PathLike) -> MaterialMaps:
    """Read the material of a glb written by :func:`export` back into linear :class:`MaterialMaps`.

    Base colour is sRGB-decoded; roughness / metallic come from the metallicRoughness texture's G / B times the
    factors; the mask from the base colour alpha (all valid without one); normals are decoded as OpenGL tangent
    space = camera space of the flat sample. Texture rows follow the quad's UVs (image top = V 1).
    """
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
    if mat.normalTexture is None:
        raise MatcapError(f"{path}: material has no normal texture")
    # which image row is the top of the quad? (our quads: the +y vertices have v = 1 in trimesh's v-up UVs)
    top = quad.vertices[:, 1] >= quad.vertices[:, 1].max() - 1e-9
    flip_rows = float(np.mean(quad.visual.uv[top, 1])) < 0.5

    def image(img) -> np.ndarray:
        arr = _float_image(img)
        return arr[::-1] if flip_rows else arr

    nimg = image(mat.normalTexture.convert("RGB"))
    h, w = nimg.shape[:2]

    def factor(value, default: float) -> float:
        return default if value is None else float(value)

    if mat.baseColorTexture is not None:
        rgba = image(mat.baseColorTexture.convert("RGBA"))
        base = imageio.srgb_to_linear(rgba[..., :3])
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
    normal = tangent_to_camera(decode_normal(nimg, "gl"), mask)
    return MaterialMaps(normal=normal, mask=mask, base_color=base, roughness=rough, metallic=metal,
                        meta={"source": str(path)})


# ------------------------------------------------------------------------------------------------ read back
def read_texture_set(json_path: str | os.PathLike) -> MaterialMaps:
    """Read an exported loose texture set (``NAME.json`` and its PNG/EXR files) back into linear MaterialMaps."""
    json_path = Path(json_path)
    try:
        info = json.loads(json_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise MatcapError(f"{json_path}: cannot read export description ({exc})") from None
    folder, files = json_path.parent, info["files"]

    def stored(key: str) -> np.ndarray | None:
        if key not in files:
            return None
        return _float_image(imageio.read_image(folder / files[key]["file"]).pixels)

    mask = stored("mask")[..., 0] >= 0.5
    frame = np.asarray(info["conventions"]["tangent_frame"]["rows_T_B_N_in_camera_space"], np.float64)
    normal = tangent_to_camera(decode_normal(stored("normal"), "gl"), mask, frame)
    base = stored("basecolor")
    rough, metal = stored("roughness"), stored("metallic")
    height = imageio.read_exr(folder / files["height"]["file"]) if "height" in files else None
    return MaterialMaps(
        normal=normal, mask=mask,
        base_color=None if base is None else imageio.srgb_to_linear(base),
        roughness=None if rough is None else rough[..., 0],
        metallic=None if metal is None else metal[..., 0],
        height=height, meta={"export": info},
    )

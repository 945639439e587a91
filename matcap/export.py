"""Engine-ready SVBRDF texture sets: loose PNG/EXR maps, packed maps per engine preset, a glTF 2.0 ``.glb`` quad.

Every file, channel layout, encoding and convention is a row of the ``export`` layout of :mod:`matcap.formats` (the
one table of map file formats; users' copies: ``docs/export.md``, ``docs/formats.md``). Summary:

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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from matcap import formats, imageio
from matcap.errors import MatcapError
from scenes.atomic import atomic_files, recover_files
from matcap.normals import NORMAL_CONVENTIONS, camera_to_tangent, tangent_frame
from scenes.materialmaps import MaterialMaps

FORMAT_VERSION = 1
DEFAULTS = {"base_color": (0.8, 0.8, 0.8), "roughness": 0.5, "metallic": 0.0, "occlusion": 1.0}
#: The files of a texture set (``NAME_<key>.png`` ...): channels, bits, colour space, normal convention.
TEXTURES = formats.LAYOUTS["export"]


# ------------------------------------------------------------------------------------------------ presets as data
@dataclass(frozen=True)
class Preset:
    name: str
    normal: str  # default normal convention, "gl" or "dx"
    extra: tuple[formats.MapFile, ...] = ()  # files of TEXTURES added to the common set
    # engine input -> (texture key, channel(s) used, engine import setting)
    slots: dict[str, tuple[str, str, str]] = field(default_factory=dict)
    notes: str = ""


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
        Preset("unity-hdrp", "gl", (TEXTURES["maskmap"],), {
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


# ------------------------------------------------------------------------------------------------ sources
def _sources(maps: MaterialMaps, frame: np.ndarray) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per-channel sources of the table (missing BRDF maps filled with :data:`DEFAULTS`), and the BRDF maps that
    are missing."""
    src = formats.sources(maps, frame=frame, defaults=DEFAULTS)
    missing = [k for k in ("base_color", "roughness", "metallic") if getattr(maps, k) is None]
    return src, missing


def _brdf_source(channel: str) -> str | None:
    base = channel.split(".")[0]
    if base in ("base_color", "roughness", "metallic"):
        return base
    if base == "smoothness":
        return "roughness"
    return None


def _channel_names(tex: formats.MapFile) -> list[str]:
    """The channel list written into NAME.json (normal maps name their convention: normal_gl.x ...)."""
    if tex.normal:
        return [f"normal_{tex.normal}.{c}" for c in "xyz"]
    return list(tex.channels)


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
    """Model name(s) and licence(s) recorded in a result's ``capture.json`` (``"unknown"`` when not recorded), as
    ``{target: {"model": name, "license": text}}`` (cards spell the key ``license``; an old ``licence`` is read
    too)."""
    models: dict[str, Any] = {}
    recorded = meta.get("models") if isinstance(meta.get("models"), dict) else {}
    for target, info in recorded.items():
        if not isinstance(info, dict):
            continue
        card = info.get("card") if isinstance(info.get("card"), dict) else {}
        name = info.get("name") or card.get("name") or info.get("weights") or card.get("preset") or "unknown"
        licences = [v for _, v in _find_keys(info, r"licen[cs]e")]
        models[target] = {"model": str(name), "license": str(licences[0]) if licences else "unknown"}
    if not models:
        names = [v for k, v in _find_keys(meta, r"^(model|model_name|weights)$")]
        licences = [v for _, v in _find_keys(meta, r"licen[cs]e")]
        models["all"] = {"model": str(names[0]) if names else "unknown",
                         "license": str(licences[0]) if licences else "unknown"}
    return models


# ------------------------------------------------------------------------------------------------ export
def _safe_name(name: str) -> str:
    clean = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._")
    if not clean:
        raise MatcapError(f"export name {name!r} has no usable characters (letters, digits, . _ -)")
    return clean


def _load(maps: MaterialMaps | str | os.PathLike) -> tuple[MaterialMaps, str | None]:
    """The maps, and the default export name (:func:`matcap.formats.default_name`)."""
    if isinstance(maps, MaterialMaps):
        return maps, None
    return formats.load_maps(maps), formats.default_name(maps)


def check_preset(preset: str) -> str:
    """``preset`` if it names an export preset, else a one-line error listing them."""
    if preset not in PRESETS:
        raise MatcapError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    return preset


def check_options(
    out: str | os.PathLike,
    *,
    name: str | None = None,
    preset: str = "gltf",
    normal: str | None = None,
    height: bool = True,
    mesh: bool = False,
    height_method: str = "frankot-chellappa",
    frame: str = "camera",
    ao_radius: float | None = None,
    overwrite: bool = False,
    glb: bool = True,
    occlusion: bool = True,
    tileable: bool = False,
    tile_size: int | None = None,
) -> None:
    """One-line errors for bad :func:`export` settings (everything that does not need the maps), so that a caller
    can check them before expensive work (``matcap capture --export``). Takes :func:`export`'s keywords."""
    from matcap.height import METHODS

    check_preset(preset)
    if normal is not None and normal not in NORMAL_CONVENTIONS:
        raise MatcapError(f"unknown normal convention {normal!r}; choose gl or dx")
    if height_method not in METHODS:
        raise MatcapError(f"unknown height method {height_method!r}; choose one of {', '.join(METHODS)}")
    if mesh and not height:
        raise MatcapError("a mesh needs the height map; do not combine mesh with height=False")
    if frame not in ("camera", "fit"):
        raise MatcapError(f"unknown tangent frame {frame!r}; choose 'camera' or 'fit'")
    if name is not None:
        _safe_name(name)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise MatcapError(f"{out} exists and is not a folder")
    if ao_radius is not None and not ao_radius >= 1:
        raise MatcapError(f"the occlusion radius must be at least 1 pixel, got {ao_radius}")
    if tile_size is not None:
        if not tileable:
            raise MatcapError("a tile size needs the tileable export (--tileable)")
        from matcap.tile import check_size

        check_size(tile_size, what="--tile-size")


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
    tileable: bool = False,
    tile_size: int | None = None,
) -> dict[str, str]:
    """Write the texture set of ``maps`` (a MaterialMaps or any map source :func:`matcap.formats.load_maps`
    reads: a result folder, an earlier export, a texture set, a ``.glb``) into ``out``.

    name: file prefix (default: the result folder's name, else ``"material"``). preset: one of :data:`PRESETS`.
    normal: ``"gl"`` / ``"dx"``; ``None`` = the preset's convention. ``NAME_normal.png`` is always OpenGL;
    ``"dx"`` adds ``NAME_normal_dx.png``. height: write ``NAME_height.exr`` (the maps' height, else integrated
    from the normals with ``height_method``). mesh: also ``NAME_mesh.ply``. occlusion: bake ambient occlusion from
    the height map (:func:`matcap.height.ambient_occlusion`, horizon radius ``ao_radius`` pixels, default 2% of the
    larger image side, at least 4) into the occlusion channels (ORM R, Unity mask map G, glTF occlusionTexture);
    off: occlusion 1. tileable: export the seamless set of :mod:`matcap.tile` (maps that are not tiled yet are
    tiled first, ``tile_size`` pixels or the size it chooses): the height map and the occlusion wrap around the
    borders and the glb is a 3 x 3 repeat of the tile (UVs 0 .. 3, REPEAT samplers). Refuses to replace existing
    files unless ``overwrite``. Returns {file key: path written}.
    """
    from matcap.height import ambient_occlusion, height_mesh, integrate_normals

    check_options(out, name=name, preset=preset, normal=normal, height=height, mesh=mesh, height_method=height_method,
                  frame=frame, ao_radius=ao_radius, tileable=tileable, tile_size=tile_size)
    spec = PRESETS[preset]
    normal = spec.normal if normal is None else normal
    maps, folder_name = _load(maps)
    tiling = None
    if tileable:
        from matcap.tile import is_tiled, tile_maps

        if frame != "camera":
            raise MatcapError("a tileable export keeps the camera tangent frame (the tile is a flat swatch); "
                              "drop --fit-frame")
        height_method = "periodic"
        if is_tiled(maps) and (tile_size is None or tile_size == maps.shape[0]):
            tiling = {**maps.meta["tiling"], "done": "before the export (the input was tiled)"}
        else:
            maps, tiling = tile_maps(maps, tile_size, what="--tile-size")
            tiling = {**tiling, "done": "by the export"}
    name = _safe_name(name or folder_name or "material")
    out = Path(out)
    if not np.isfinite(maps.normal).all():
        raise MatcapError("normal map holds NaN or Inf values")
    if not maps.mask.any():
        raise MatcapError("the mask is empty: nothing to export")

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
        src["occlusion"] = ambient_occlusion(hmap, maps.mask, radius=radius, directions=directions,
                                             wrap=tileable)
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

    paths = {t.key: t.path(out, name=name) for t in written_tex}
    for key, wanted in (("height", height), ("mesh", mesh), ("glb", glb), ("json", True)):
        if wanted:
            paths[key] = TEXTURES[key].path(out, name=name)
    recover_files(out, name)  # a staging folder of a killed run: finished if complete, else removed
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise MatcapError(f"{existing[0]} already exists ({len(existing)} file(s) of this export); "
                          "pass --overwrite to replace them")
    # every file is written into a hidden staging folder inside `out` and moved into place when the set is
    # complete: a run killed part-way leaves no partial texture set (and the next run tidies its staging folder)
    with atomic_files(out, tag=name, last=paths["json"].name) as stage:
        files: dict[str, dict[str, Any]] = {}
        for tex in written_tex:
            formats.write_file(stage, tex, src, name=name)
            files[tex.key] = {
                "file": paths[tex.key].name, "channels": _channel_names(tex), "bits": tex.bits,
                "colorspace": tex.colour, "description": tex.description,
            }
        height_info = None
        if height:
            src["height"] = hmap
            formats.write_file(stage, TEXTURES["height"], src, name=name)
            height_info = {"method": how, "range": [float(hmap[maps.mask].min()), float(hmap[maps.mask].max())]}
            files["height"] = {
                "file": paths["height"].name, "channels": ["Y"], "bits": 32, "colorspace": "linear",
                "description": f"{TEXTURES['height'].description}; {how}",
            }
            if mesh:
                surface = height_mesh(hmap, maps.mask, maps.base_color)
                with imageio.atomic_path(stage / paths["mesh"].name) as tmp:
                    surface.export(tmp, file_type="ply")
                files["mesh"] = {"file": paths["mesh"].name, "description": TEXTURES["mesh"].description}
        if glb:
            imageio.write_bytes_atomic(stage / paths["glb"].name,
                                       build_glb(maps, src, missing, name, occlusion, repeats=3 if tileable else 1))
            files["glb"] = {"file": paths["glb"].name, "description": TEXTURES["glb"].description}

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
                "tangent_space": "flat sample, UV = image axes: U right, V up (image row 0 = V 1); T = +U, B = +V, "
                                 "N out of the surface; NAME_normal.png is OpenGL (+Y), NAME_normal_dx.png has "
                                 "G = 1 - G",
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
        if tiling is not None:
            info["tiling"] = {k: v for k, v in tiling.items() if k != "preview"}
            info["conventions"]["tiling"] = ("every map tiles (repeat the textures; the glb shows 3 x 3 repeats "
                                             "with REPEAT samplers)")
        formats.write_json(stage / paths["json"].name, info)
    return {k: str(p) for k, p in paths.items()}


# ------------------------------------------------------------------------------------------------ glb
def _pil(x: np.ndarray):
    from PIL import Image

    return Image.fromarray(imageio.quantize(x, 8))


def build_glb(maps: MaterialMaps, src: dict[str, np.ndarray], missing: list[str], name: str,
              occlusion: bool = False, repeats: int = 1) -> bytes:
    """The glb bytes: one quad, UV = image axes (V up), glTF metallic-roughness material with 8-bit textures
    (``occlusion``: plus ``src["occlusion"]`` as the occlusionTexture). ``repeats`` > 1: the quad is that many
    tiles wide and high, its UVs run 0 .. repeats and every texture's sampler wraps with REPEAT (a tileable set)."""
    import trimesh
    from trimesh.visual.material import PBRMaterial

    h, w = maps.shape
    hx, hy = 0.5 * repeats, 0.5 * repeats * h / w
    vertices = np.array([[-hx, hy, 0], [hx, hy, 0], [-hx, -hy, 0], [hx, -hy, 0]], np.float64)  # TL TR BL BR
    # trimesh UVs: v up (glTF stores 1 - v): 0 .. repeats in the file, image top = glTF V 0 as for one tile
    uv = np.array([[0, 1], [1, 1], [0, 0], [1, 0]], np.float64)
    uv[:, 0] *= repeats
    uv[:, 1] = 1.0 - repeats * (1.0 - uv[:, 1])
    faces = np.array([[0, 2, 3], [0, 3, 1]])
    kwargs: dict[str, Any] = {"name": name, "doubleSided": False}
    table = formats.LAYOUTS["glb"]
    cut = not maps.mask.all()
    if "base_color" not in missing or cut:
        spec = table["baseColorTexture"]
        if not cut:
            spec = replace(spec, channels=spec.channels[:3])
        kwargs["baseColorTexture"] = _pil(formats.pixels(spec, src))
        if cut:
            kwargs["alphaMode"] = "MASK"
            kwargs["alphaCutoff"] = 0.5
    else:
        kwargs["baseColorFactor"] = [*DEFAULTS["base_color"], 1.0]
    if not {"roughness", "metallic"} <= set(missing):
        kwargs["metallicRoughnessTexture"] = _pil(formats.pixels(table["metallicRoughnessTexture"], src))
        kwargs["roughnessFactor"], kwargs["metallicFactor"] = 1.0, 1.0
    else:
        kwargs["roughnessFactor"], kwargs["metallicFactor"] = float(DEFAULTS["roughness"]), float(DEFAULTS["metallic"])
    kwargs["normalTexture"] = _pil(formats.pixels(table["normalTexture"], src))
    if occlusion:
        kwargs["occlusionTexture"] = _pil(formats.pixels(table["occlusionTexture"], src))
    material = PBRMaterial(**kwargs)
    quad = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_normals=np.tile([0.0, 0.0, 1.0], (4, 1)),
                           visual=trimesh.visual.TextureVisuals(uv=uv, material=material), process=False)
    scene = trimesh.Scene()
    scene.add_geometry(quad, geom_name=name, node_name=name)
    glb = _add_tangents(scene.export(file_type="glb", include_normals=True), (1.0, 0.0, 0.0, 1.0))
    return _repeat_samplers(glb) if repeats > 1 else glb


GL_REPEAT, GL_LINEAR, GL_LINEAR_MIPMAP_LINEAR = 10497, 9729, 9987


def _glb_split(glb: bytes) -> tuple[dict, bytearray]:
    import struct

    magic, version, _ = struct.unpack_from("<4sII", glb, 0)
    if magic != b"glTF" or version != 2:
        raise ValueError("not a glTF 2.0 binary")
    json_len = struct.unpack_from("<I", glb, 12)[0]
    tree = json.loads(glb[20:20 + json_len])
    rest = glb[20 + json_len:]
    binary = bytearray(rest[8:8 + struct.unpack_from("<I", rest, 0)[0]]) if rest else bytearray()
    return tree, binary


def _glb_join(tree: dict, binary: bytearray) -> bytes:
    import struct

    binary = binary + b"\0" * (-len(binary) % 4)
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(text), b"JSON") + text
            + struct.pack("<I4s", len(binary), b"BIN\0") + bytes(binary))


def _repeat_samplers(glb: bytes) -> bytes:
    """Give every texture one explicit sampler: wrapS = wrapT = REPEAT, linear / trilinear filtering."""
    tree, binary = _glb_split(glb)
    tree["samplers"] = [{"magFilter": GL_LINEAR, "minFilter": GL_LINEAR_MIPMAP_LINEAR,
                         "wrapS": GL_REPEAT, "wrapT": GL_REPEAT}]
    for tex in tree.get("textures", []):
        tex["sampler"] = 0
    return _glb_join(tree, binary)


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


# ------------------------------------------------------------------------------------------------ read back
#: Reading an export back is :func:`matcap.formats.load_maps` (any map source); these are its two readers.
maps_from_glb = formats.read_glb
read_texture_set = formats.read_export

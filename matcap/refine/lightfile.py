"""``lights.json``: the per-photo lights estimated by the fit (read, write, validate, convert for relighting).

Schema (version 1; camera space: x right, y up, z toward the camera, as normal.exr; orthographic view along -z)::

    {"version": 1, "frame": "...", "colour": "...",
     "intensity_units": "relative",           # or "photos": intensity and sh in the decoded photos' units
     "images": [{"index": 0, "file": "001.png", "kind": "directional",
                 "direction": [x, y, z],      # unit vector from the surface toward the light
                 "intensity": [r, g, b],      # irradiance on a surface facing the light
                 "sh": [[r, g, b]] * 9},      # order-2 real SH of the incident radiance (ambient)
                {"index": 1, "kind": "point",
                 "position": [x, y, z],       # world units of renderers.plane's framing plane (z = 0 plane)
                 "intensity": [r, g, b],      # radiant intensity, inverse-square falloff
                 "sh": [...]}]}

SH basis order Y00, Y1-1, Y10, Y11, Y2-2, Y2-1, Y20, Y21, Y22 with Ramamoorthi & Hanrahan (2001) constants.
Unknown keys are ignored; missing, non-finite or wrong-length required values are refused with one-line
:class:`MatcapError` messages.

For relighting (``matcap relight R --lights R/lights.json --image k``), :func:`entry_to_lights` turns one entry
into ``scenes.lights`` objects: the directional / point light as it is, plus the SH ambient as an
equirectangular :class:`EnvironmentLight` whose texels hold the SH radiance in their directions (Mitsuba's
``envmap`` convention, as ``scenes.lights.envmap_directions``), negative radiance clamped to 0.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from matcap.errors import MatcapError
from scenes.lights import DirectionalLight, EnvironmentLight, Light, PointLight, envmap_directions

VERSION = 1
FRAME = "camera: x right, y up, z toward the camera (as normal.exr); orthographic view along -z"
COLOUR = "linear RGB in the units of the decoded photos"
KINDS = ("directional", "point")
#: What the intensities are (``intensity_units``): "relative" (their ratios only; the photos' exposure sets their
#: power) or "photos" (in the decoded photos' linear units, power included). A document without the key: relative.
INTENSITY_UNITS = ("relative", "photos")
SH_COUNT = 9
#: Real SH constants (R&H 2001), basis order Y00, Y1-1, Y10, Y11, Y2-2, Y2-1, Y20, Y21, Y22.
SH_C0, SH_C1, SH_C2, SH_C3, SH_C4 = 0.282095, 0.488603, 1.092548, 0.315392, 0.546274
#: Clamped-cosine convolution per band: irradiance E(n) = sum_j A_j L_j Y_j(n).
SH_A = np.array([math.pi] + [2.0 * math.pi / 3.0] * 3 + [math.pi / 4.0] * 5)
ENV_SIZE = (128, 64)  # (width, height) of the SH environment map: plenty for an order-2 (smooth) radiance


# ------------------------------------------------------------------------------------------- SH helpers


def sh_basis(dirs: np.ndarray) -> np.ndarray:
    """(..., 3) unit vectors -> (..., 9) real SH basis values."""
    d = np.asarray(dirs, dtype=np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([np.full_like(x, SH_C0), SH_C1 * y, SH_C1 * z, SH_C1 * x, SH_C2 * x * y, SH_C2 * y * z,
                     SH_C3 * (3.0 * z * z - 1.0), SH_C2 * x * z, SH_C4 * (x * x - y * y)], axis=-1)


def sh_radiance(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Radiance (..., 3) in directions ``dirs`` (..., 3) of the SH coefficients ``sh`` (9, 3) (not clamped)."""
    return sh_basis(dirs) @ np.asarray(sh, dtype=np.float64)


def sh_irradiance(sh: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance (..., 3) on surfaces with ``normals`` (..., 3) under the SH radiance ``sh`` (9, 3) (R&H 2001;
    exact for a radiance that is itself order-2 SH, integrated over the normal's whole hemisphere)."""
    return sh_basis(normals) @ (SH_A[:, None] * np.asarray(sh, dtype=np.float64))


def sh_to_envmap(sh: np.ndarray, height: int = ENV_SIZE[1], width: int = ENV_SIZE[0]) -> np.ndarray:
    """(H, W, 3) float32 equirectangular radiance of the SH ``sh`` (9, 3), negative radiance clamped to 0."""
    return np.clip(sh_radiance(sh, envmap_directions(height, width)), 0.0, None).astype(np.float32)


def project_sh(pixels: np.ndarray, rotation_deg: float = 0.0) -> np.ndarray:
    """Order-2 SH coefficients (9, 3) of an equirectangular radiance map (H, W, 3) (texel solid-angle
    quadrature, Mitsuba's ``envmap`` convention)."""
    arr = np.asarray(pixels, dtype=np.float64)
    h, w = arr.shape[:2]
    theta = np.pi * (np.arange(h) + 0.5) / h
    d_omega = (2.0 * np.pi / w) * (np.pi / h) * np.sin(theta)  # per texel row
    basis = sh_basis(envmap_directions(h, w, rotation_deg))  # (H, W, 9)
    return np.einsum("hwj,hwc,h->jc", basis, arr, d_omega)


# ------------------------------------------------------------------------------------------- validation


def _vector(value: Any, length: int, where: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != length:
        raise MatcapError(f"{where}: expected a list of {length} numbers, got {json.dumps(value)[:60]}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise MatcapError(f"{where}: expected {length} finite numbers, got {json.dumps(value)[:60]}")
        out.append(float(v))
    return out


def validate_entry(entry: Any, where: str) -> dict:
    """One ``images`` entry checked and normalised (floats, unit direction); unknown keys kept as they are."""
    if not isinstance(entry, dict):
        raise MatcapError(f"{where}: expected an object")
    out = dict(entry)
    index = entry.get("index")
    if isinstance(index, bool) or not isinstance(index, int) or index < 0:
        raise MatcapError(f"{where}: 'index' must be a non-negative integer, got {json.dumps(index)}")
    where = f"{where} (index {index})"
    kind = entry.get("kind")
    if kind not in KINDS:
        raise MatcapError(f"{where}: 'kind' must be one of {', '.join(KINDS)}, got {json.dumps(kind)}")
    if "file" in entry and not isinstance(entry["file"], str):
        raise MatcapError(f"{where}: 'file' must be a string")
    for key in ("intensity", "sh") + (("direction",) if kind == "directional" else ("position",)):
        if key not in entry:
            raise MatcapError(f"{where}: missing '{key}'")
    out["intensity"] = _vector(entry["intensity"], 3, f"{where} intensity")
    if min(out["intensity"]) < 0:
        raise MatcapError(f"{where}: 'intensity' must not be negative, got {out['intensity']}")
    sh = entry["sh"]
    if not isinstance(sh, (list, tuple)) or len(sh) != SH_COUNT:
        raise MatcapError(f"{where}: 'sh' must be {SH_COUNT} rows of [r, g, b]")
    out["sh"] = [_vector(row, 3, f"{where} sh[{j}]") for j, row in enumerate(sh)]
    if kind == "directional":
        d = np.array(_vector(entry["direction"], 3, f"{where} direction"))
        norm = float(np.linalg.norm(d))
        if norm < 1e-6:
            raise MatcapError(f"{where}: 'direction' must not be the zero vector")
        out["direction"] = [float(v) for v in d / norm]
    else:
        out["position"] = _vector(entry["position"], 3, f"{where} position")
        if out["position"][2] <= 0:
            raise MatcapError(f"{where}: 'position' must be in front of the plane (z > 0), got {out['position']}")
    return out


def validate_lights(doc: Any, source: str = "lights.json") -> dict:
    """A lights.json document checked and normalised; one-line :class:`MatcapError` for anything wrong."""
    if not isinstance(doc, dict):
        raise MatcapError(f"{source}: expected a JSON object with 'version' and 'images'")
    version = doc.get("version")
    if version != VERSION:
        raise MatcapError(f"{source}: unsupported version {json.dumps(version)} (this matcap reads version {VERSION})")
    images = doc.get("images")
    if not isinstance(images, list) or not images:
        raise MatcapError(f"{source}: 'images' must be a non-empty list")
    entries = [validate_entry(e, f"{source}: images[{i}]") for i, e in enumerate(images)]
    seen: set[int] = set()
    for e in entries:
        if e["index"] in seen:
            raise MatcapError(f"{source}: index {e['index']} appears more than once")
        seen.add(e["index"])
    units = doc.get("intensity_units", "relative")
    if units not in INTENSITY_UNITS:
        raise MatcapError(f"{source}: 'intensity_units' must be one of {', '.join(INTENSITY_UNITS)}, got "
                          f"{json.dumps(units)}")
    out = dict(doc)
    out["images"] = entries
    return out


def read_lights(path: str | os.PathLike) -> dict:
    """Read and validate a lights.json file."""
    path = Path(path)
    if not path.is_file():
        raise MatcapError(f"{path}: no such file")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise MatcapError(f"{path}: cannot read it ({exc.__class__.__name__})") from None
    try:
        doc = json.loads(text, parse_constant=lambda c: float("nan"))
    except json.JSONDecodeError as exc:
        raise MatcapError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    return validate_lights(doc, str(path))


def lights_document(images: list[dict], **extra: Any) -> dict:
    """A validated version-1 document for ``images`` entries (each with index, kind, ...; extra keys kept)."""
    doc = {"version": VERSION, "frame": FRAME, "colour": COLOUR, **extra, "images": list(images)}
    return validate_lights(doc, "lights")


def write_lights(path: str | os.PathLike, images: list[dict], **extra: Any) -> dict:
    """Validate and write lights.json atomically (``scenes.atomic.write_json_atomic``); returns the document."""
    from scenes.atomic import write_json_atomic

    doc = lights_document(images, **extra)  # every number checked finite
    write_json_atomic(path, doc, indent=1)
    return doc


# ------------------------------------------------------------------------------------------- conversion


def entry_for_image(doc: dict, index: int, source: str = "lights.json") -> dict:
    """The entry of input image ``index`` (one-line error naming the available indices)."""
    for e in doc["images"]:
        if e["index"] == index:
            return e
    have = sorted(e["index"] for e in doc["images"])
    span = f"{have[0]}..{have[-1]}" if have == list(range(have[0], have[-1] + 1)) else ", ".join(map(str, have))
    raise MatcapError(f"{source}: no light for image {index} (it has images {span})")


def entry_to_lights(entry: dict, env_size: tuple[int, int] = ENV_SIZE) -> tuple[list[Light], dict[str, np.ndarray]]:
    """``scenes.lights`` objects for one validated entry, and the environment pixels they need.

    Returns ``(lights, envmaps)``: the directional / point light, plus (unless its SH is all zero) an
    :class:`EnvironmentLight` named ``"sh:<index>"`` whose (H, W, 3) pixels are in ``envmaps``.
    """
    if entry["kind"] == "directional":
        lights: list[Light] = [DirectionalLight(tuple(entry["direction"]), tuple(entry["intensity"]))]
    else:
        lights = [PointLight(tuple(entry["position"]), tuple(entry["intensity"]))]
    envmaps: dict[str, np.ndarray] = {}
    sh = np.asarray(entry["sh"], dtype=np.float64)
    if np.any(sh != 0):
        source = f"sh:{entry['index']}"
        envmaps[source] = sh_to_envmap(sh, height=env_size[1], width=env_size[0])
        lights.append(EnvironmentLight(source=source))
    return lights, envmaps

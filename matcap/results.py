"""A capture result folder: the files `matcap capture` writes and `relight` / `export` / `gallery` read.

| file            | content                                                                          |
|-----------------|----------------------------------------------------------------------------------|
| `normal.exr`    | float32 (H, W, 3) camera space: x right, y up, z toward the camera; 0 off-mask   |
| `normal.png`    | 16-bit RGB, (n + 1) / 2 of the same normals; black (0) off-mask                  |
| `mask.png`      | 8-bit grey, 255 = surface                                                        |
| `basecolor.png` | 16-bit RGB, sRGB-encoded base color (BRDF model only)                            |
| `roughness.png` | 16-bit grey, linear (BRDF model only)                                            |
| `metallic.png`  | 16-bit grey, linear (BRDF model only)                                            |
| `capture.json`  | inputs used, colour handling, model, settings, timings                           |

A folder is written into a hidden temporary sibling and renamed into place when complete, so an interrupted run
never leaves a half-written result and never destroys the previous one.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from matcap import imageio
from matcap.errors import MatcapError
from scenes.materialmaps import MaterialMaps

RESULT_FILES = ("normal.exr", "normal.png", "mask.png", "basecolor.png", "roughness.png", "metallic.png", "capture.json")


def check_output_dir(path: str | os.PathLike, overwrite: bool) -> Path:
    """Refuse (one-line error) an existing non-empty folder unless ``overwrite``; refuse a file in its place."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise MatcapError(f"{path} exists and is not a folder")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise MatcapError(f"{path} already holds files; pass --overwrite to replace them")
    # the folder is built next to `path` and renamed into place: its parent (or the nearest existing ancestor,
    # which the parents are created in) must be writable; fail now, not after the work
    parent = path.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if parent.exists() and not (parent.is_dir() and os.access(parent, os.W_OK | os.X_OK)):
        raise MatcapError(f"{path}: cannot write in {parent} (read-only or no permission)")
    return path


def check_not_replacing_inputs(out: str | os.PathLike, *inputs) -> None:
    """Refuse an output folder that is, or contains, one of ``inputs`` (paths or None): :func:`output_dir` replaces
    the whole folder, so with ``--overwrite`` it would delete the photos or maps the command reads."""
    out_r = Path(out).resolve()
    for item in inputs:
        if item is None or not isinstance(item, (str, os.PathLike)):
            continue
        src = Path(item).resolve()
        if src == out_r or out_r in src.parents:
            raise MatcapError(f"--out {out} would replace the input {item}; choose another output folder")


@contextlib.contextmanager
def output_dir(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary folder; on success it atomically replaces ``path``.

    The previous content of ``path`` (allowed only with ``overwrite``) is kept until the new folder is complete.
    """
    path = check_output_dir(path, overwrite).absolute()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        yield tmp
        old = None
        if path.exists():
            old = path.parent / f".{path.name}.old-{os.getpid()}"
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def encode_normal(normal: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals -> (n + 1) / 2 in [0, 1], 0 outside ``mask``."""
    return np.where(mask[:, :, None], (normal + 1.0) * 0.5, 0.0).astype(np.float32)


def decode_normal(encoded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_normal`, renormalised to unit length; 0 outside ``mask``."""
    n = encoded.astype(np.float32) * 2.0 - 1.0
    length = np.linalg.norm(n, axis=2, keepdims=True)
    n = n / np.maximum(length, 1e-8)
    return np.where(mask[:, :, None], n, 0.0).astype(np.float32)


def write_maps(maps: MaterialMaps, folder: str | os.PathLike) -> list[str]:
    """Write the map files of a result folder into ``folder`` (which must exist). Returns the names written."""
    folder = Path(folder)
    names = ["normal.exr", "normal.png", "mask.png"]
    normal = np.where(maps.mask[:, :, None], maps.normal, 0.0).astype(np.float32)
    imageio.write_exr(folder / "normal.exr", normal)
    imageio.write_png(folder / "normal.png", encode_normal(normal, maps.mask), bits=16)
    imageio.write_png(folder / "mask.png", maps.mask.astype(np.float32), bits=8)
    if maps.base_color is not None:
        imageio.write_png(folder / "basecolor.png", imageio.linear_to_srgb(maps.base_color), bits=16)
        names.append("basecolor.png")
    for name in ("roughness", "metallic"):
        value = getattr(maps, name)
        if value is not None:
            imageio.write_png(folder / f"{name}.png", value, bits=16)
            names.append(f"{name}.png")
    if maps.height is not None:
        imageio.write_exr(folder / "height.exr", maps.height)
        names.append("height.exr")
    return names


def write_result(
    maps: MaterialMaps,
    out_dir: str | os.PathLike,
    overwrite: bool = False,
    extra_json: dict[str, Any] | None = None,
    extra_files: Callable[[Path], list[str]] | None = None,
) -> Path:
    """Write a complete result folder atomically (see module docstring). Returns its path.

    ``extra_files(tmp_folder) -> names`` writes more files into the folder before it is renamed into place."""
    with output_dir(out_dir, overwrite) as tmp:
        files = write_maps(maps, tmp)
        if extra_files is not None:
            files += extra_files(tmp)
        info = dict(maps.meta)
        info.update(extra_json or {})
        info["files"] = files + ["capture.json"]
        imageio.write_text_atomic(tmp / "capture.json", json.dumps(info, indent=2, default=_json_default) + "\n")
    return Path(out_dir)


def _json_default(obj):
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def read_result(folder: str | os.PathLike) -> MaterialMaps:
    """Read a result folder written by :func:`write_result` back into :class:`MaterialMaps` (linear values)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MatcapError(f"{folder}: not a result folder")
    if not (folder / "normal.exr").exists() and not (folder / "normal.png").exists():
        raise MatcapError(f"{folder}: no normal.exr or normal.png (not a matcap result folder?)")
    if (folder / "mask.png").exists():
        mask = imageio.read_image(folder / "mask.png").pixels[:, :, 0] > 0
    else:
        mask = None
    if (folder / "normal.exr").exists():
        normal = imageio.read_exr(folder / "normal.exr")
        imageio.check_finite(normal, str(folder / "normal.exr"))
        if mask is None:
            mask = np.linalg.norm(normal, axis=2) > 0.5
    else:
        stored = imageio.read_image(folder / "normal.png").pixels
        top = 65535.0 if stored.dtype == np.uint16 else 255.0
        if mask is None:
            mask = stored.max(axis=2) > 0
        normal = decode_normal(stored / top, mask)
    if normal.ndim != 3 or normal.shape[2] != 3:
        raise MatcapError(f"{folder}: normal map has shape {normal.shape}, expected (H, W, 3)")
    if mask.shape != normal.shape[:2]:
        raise MatcapError(f"{folder}: mask.png is {mask.shape[::-1]} but normals are {normal.shape[1::-1]} (W, H)")
    if not mask.any():
        raise MatcapError(f"{folder}: the mask is empty (no surface pixel to use)")

    def grey(name: str) -> np.ndarray | None:
        p = folder / name
        if not p.exists():
            return None
        stored = imageio.read_image(p)
        arr, _ = imageio.to_linear_float(stored, decode_srgb_8bit=False)
        return arr[:, :, 0]

    base_color = None
    if (folder / "basecolor.png").exists():
        stored = imageio.read_image(folder / "basecolor.png").pixels
        top = 65535.0 if stored.dtype == np.uint16 else 255.0
        base_color = imageio.srgb_to_linear(stored.astype(np.float32) / top)
    height = imageio.read_exr(folder / "height.exr") if (folder / "height.exr").exists() else None
    if height is not None:
        imageio.check_finite(height, str(folder / "height.exr"))
    meta: dict[str, Any] = {}
    if (folder / "capture.json").exists():
        try:
            meta = json.loads((folder / "capture.json").read_text())
        except json.JSONDecodeError as exc:
            raise MatcapError(f"{folder / 'capture.json'}: not valid JSON ({exc})") from None
        if not isinstance(meta, dict):
            raise MatcapError(f"{folder / 'capture.json'}: expected a JSON object, got a {type(meta).__name__}")
    try:
        return MaterialMaps(
            normal=normal, mask=mask, base_color=base_color, roughness=grey("roughness.png"),
            metallic=grey("metallic.png"), height=height, meta=meta,
        )
    except ValueError as exc:
        raise MatcapError(f"{folder}: {exc}") from None

"""A capture result folder: the files `matcap capture` writes and `relight` / `export` / `gallery` read.

Which files a result holds, and how each is encoded, is the ``result`` layout of :mod:`matcap.formats` (the one
table of map file formats; ``docs/formats.md``): ``normal.exr``, ``normal.png``, ``mask.png``, ``basecolor.png``
(16-bit sRGB), ``roughness.png`` / ``metallic.png`` (16-bit linear), ``capture.json``.

A folder is written into a hidden temporary sibling and renamed into place when complete
(:func:`scenes.atomic.atomic_dir`), so an interrupted run never leaves a half-written result and never destroys
the previous one.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any, Callable, Iterator

from matcap import formats
from matcap.errors import MatcapError
from scenes.atomic import atomic_dir
from scenes.materialmaps import MaterialMaps


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
    path = check_output_dir(path, overwrite)
    with atomic_dir(path) as tmp:
        yield tmp


def write_result(
    maps: MaterialMaps,
    out_dir: str | os.PathLike,
    overwrite: bool = False,
    extra_json: dict[str, Any] | None = None,
    extra_files: Callable[[Path], list[str]] | None = None,
) -> Path:
    """Write a complete result folder atomically (see module docstring). Returns its path.

    ``extra_files(tmp_folder) -> names`` writes more files into the folder before it is renamed into place (the
    refinement outputs: rows of the ``result`` layout, written with ``formats.write_json`` /
    ``formats.write_visual``)."""
    with output_dir(out_dir, overwrite) as tmp:
        files = formats.write_result_maps(maps, tmp)
        if extra_files is not None:
            files += extra_files(tmp)
        info = dict(maps.meta)
        info.update(extra_json or {})
        info["files"] = files + ["capture.json"]
        formats.write_json(tmp / "capture.json", info)
    return Path(out_dir)


def read_result(folder: str | os.PathLike) -> MaterialMaps:
    """Read a result folder written by :func:`write_result` back into :class:`MaterialMaps` (linear values)."""
    return formats.read_result(folder)

"""Lights you know: read a rig's light file and match its rows to the photos of a capture.

Formats (:func:`read_light_file` tells them apart by name and content):

- our ``lights.json`` (a calibration's, from ``matcap calibrate``, or a previous capture's): entries matched to
  the photos by their ``file`` names, else by order;
- an RTI ``.lp`` file: a count line, then ``filename x y z`` per photo, matched by file name (or stem);
- a plain text table, one row per photo: ``x y z`` optionally followed by ``r g b`` relative intensities, with
  an optional first line holding only the count (the UW ``lights.txt``). Its rows follow a ``names.txt`` /
  ``filenames.txt`` beside the file (the UW and DiLiGenT conventions) when there is one, else the photos' natural
  file-name order (2 before 10);
- the two-file convention ``light_directions.txt`` + ``light_intensities.txt``: the second is picked up beside
  the first.

Directions point from the surface toward the light in the camera frame of ``normal.exr``: x right, y up, z toward
the camera. They are normalised on reading. Intensities are relative (one overall scale is fitted) unless a
``lights.json`` says ``"intensity_units": "photos"``: then they, and its ambient, are in the decoded photos' linear
units and the fit holds their power as given. Where a file gives no intensities, the fit finds one per photo. Every
problem (a count or file-name mismatch, a zero or non-finite row, a light behind the object's plane) is one
:class:`MatcapError` line naming the file and the row.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from matcap.errors import MatcapError

#: Where the lights of a capture came from, strongest first (``capture.json`` / ``lights.json`` ``source``).
SOURCES = ("file", "ball", "estimated")
NAME_LISTS = ("names.txt", "filenames.txt")


@dataclass
class KnownLights:
    """One light per photo, in the order of the photos they were matched to.

    directions: (K, 3) unit vectors toward the light, camera frame (x right, y up, z toward the camera);
    intensities: (K, 3) relative linear RGB, or None (fitted per photo);
    positions: (K, 3) point-light positions in the framing plane's units (``docs/lights.md``) where the file
        held point lights (a previous capture's near lamps), else None; ``directions`` are then toward the
        object's centre;
    source: "file", "ball" or "estimated" (a flat sample's lamps, found from their falloff); path: the file read
        ("" where none was); matched: how rows met photos ("name", "order", "names.txt");
    ambient: (K, 9, 3) the SH ambient radiance each photo was taken under, in the intensities' units (a
        ``lights.json``'s ``sh``), where the file gives intensities; else None;
    intensity_units: "relative" (only the intensities' ratios are known) or "photos" (they are in the decoded
        photos' linear units: the fit holds their power; :data:`matcap.refine.lightfile.INTENSITY_UNITS`).
    """

    directions: np.ndarray
    intensities: np.ndarray | None
    source: str
    path: str
    matched: str
    positions: np.ndarray | None = None
    ambient: np.ndarray | None = None
    intensity_units: str = "relative"

    def __len__(self) -> int:
        return len(self.directions)

    def subset(self, index: Sequence[int]) -> "KnownLights":
        """The lights of the photos ``index`` (e.g. the ``--max-images`` pick)."""
        idx = np.asarray(index, int)
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        return KnownLights(self.directions[idx], pick(self.intensities), self.source, self.path, self.matched,
                           pick(self.positions), pick(self.ambient), self.intensity_units)

    def record(self) -> dict:
        """capture.json / fit.json summary."""
        return {"source": self.source, "file": self.path or None, "matched_by": self.matched,
                "intensities": "given" if self.intensities is not None else "fitted",
                **({"intensity_units": self.intensity_units} if self.intensities is not None else {}),
                "ambient": "given" if self.ambient is not None else ("none" if self.intensities is not None
                                                                    else "fitted"),
                "kind": "point" if self.positions is not None else "directional"}


def natural_key(name: str):
    """Sort key putting ``img2`` before ``img10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


# ----------------------------------------------------------------------------------------------- parsing


@dataclass
class _Rows:
    """Rows of a light file before matching: directions (R, 3) raw, intensities (R, 3) or None, names (R) or
    None, positions (R, 3) or None, line numbers (R) for messages, ambient (R, 9, 3) or None, what the
    intensities are ("relative" or "photos")."""

    directions: np.ndarray
    intensities: np.ndarray | None
    names: list[str] | None
    positions: np.ndarray | None
    lines: list[int]
    ambient: np.ndarray | None = None
    intensity_units: str = "relative"


def _numbers(path: Path, lineno: int, fields: list[str]) -> list[float]:
    try:
        vals = [float(v) for v in fields]
    except ValueError:
        raise MatcapError(f"{path.name} line {lineno}: expected numbers, got {' '.join(fields)!r}") from None
    return vals


def _text_lines(path: Path) -> list[tuple[int, list[str]]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise MatcapError(f"cannot read light file {path}: {e}") from None
    out = []
    for i, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if line:
            out.append((i, line.replace(",", " ").split()))
    return out


def _count_line(path: Path, lines: list[tuple[int, list[str]]]) -> list[tuple[int, list[str]]]:
    """Drop a first line holding only the row count (checked against the rows that follow)."""
    if lines and len(lines[0][1]) == 1:
        lineno, (word,) = lines[0]
        try:
            count = int(word)
        except ValueError:
            raise MatcapError(f"{path.name} line {lineno}: expected the number of lights, got {word!r}") from None
        if count != len(lines) - 1:
            raise MatcapError(f"{path.name} line {lineno}: says {count} lights but {len(lines) - 1} rows follow")
        return lines[1:]
    return lines


def _read_table(path: Path) -> _Rows:
    lines = _count_line(path, _text_lines(path))
    if not lines:
        raise MatcapError(f"{path.name}: no light rows")
    dirs, ints, nums = [], [], []
    for lineno, fields in lines:
        if len(fields) not in (3, 6):
            raise MatcapError(f"{path.name} line {lineno}: expected 'x y z' or 'x y z r g b', got "
                              f"{len(fields)} values")
        v = _numbers(path, lineno, fields)
        dirs.append(v[:3])
        ints.append(v[3:] if len(v) == 6 else None)
        nums.append(lineno)
    given = [i is not None for i in ints]
    if any(given) and not all(given):
        lineno = nums[given.index(False)]
        raise MatcapError(f"{path.name} line {lineno}: some rows give intensities and this one does not")
    intens = np.array(ints, np.float64) if all(given) else None
    if intens is None and path.name == "light_directions.txt" and (path.parent / "light_intensities.txt").is_file():
        ipath = path.parent / "light_intensities.txt"
        ilines = _count_line(ipath, _text_lines(ipath))
        if len(ilines) != len(lines):
            raise MatcapError(f"{ipath.name}: {len(ilines)} rows but {path.name} has {len(lines)}")
        rows = []
        for lineno, fields in ilines:
            if len(fields) not in (1, 3):
                raise MatcapError(f"{ipath.name} line {lineno}: expected 'r g b' (or one value), got "
                                  f"{len(fields)} values")
            v = _numbers(ipath, lineno, fields)
            rows.append(v * 3 if len(v) == 1 else v)
        intens = np.array(rows, np.float64)
        _check_intensities(ipath, intens, [n for n, _ in ilines])
    return _Rows(np.array(dirs, np.float64), intens, None, None, nums)


def _read_lp(path: Path) -> _Rows:
    lines = _text_lines(path)
    if not lines:
        raise MatcapError(f"{path.name}: empty light file")
    body = lines[1:] if len(lines[0][1]) == 1 else lines
    if len(lines[0][1]) == 1:
        _count_line(path, lines)
    names, dirs, nums = [], [], []
    for lineno, fields in body:
        if len(fields) != 4:
            raise MatcapError(f"{path.name} line {lineno}: expected 'filename x y z', got {len(fields)} fields")
        names.append(os.path.basename(fields[0].replace("\\", "/")))
        dirs.append(_numbers(path, lineno, fields[1:]))
        nums.append(lineno)
    return _Rows(np.array(dirs, np.float64), None, names, None, nums)


def _read_json(path: Path) -> tuple[_Rows, str]:
    from matcap.refine.lightfile import read_lights

    doc = read_lights(path)
    images = doc["images"]
    names = [e.get("file") for e in images]
    dirs, pos, ints = [], [], []
    for e in images:
        if e["kind"] == "point":
            p = np.asarray(e["position"], np.float64)
            pos.append(p)
            dirs.append(p)  # refined toward the object's centre by the fit; here only checked to face it
        else:
            pos.append(None)
            dirs.append(np.asarray(e["direction"], np.float64))
        ints.append(e.get("intensity"))
    has_pos = [p is not None for p in pos]
    if any(has_pos) and not all(has_pos):  # mixed: point lights keep their positions, distant ones are far away
        pos = [p if p is not None else np.asarray(d) / max(np.linalg.norm(d), 1e-12) * 1e6 for p, d in zip(pos, dirs)]
    positions = np.array(pos, np.float64) if any(has_pos) else None
    intens = None if any(i is None for i in ints) else np.array(ints, np.float64)
    if intens is not None and doc.get("intensity_known") is False:  # a calibration that could not tell them
        intens = None
    # the ambient is taken only beside given intensities: in their units, it is known only relative to them
    sh = [e.get("sh") for e in images]
    ambient = None if intens is None or any(a is None for a in sh) else np.array(sh, np.float64)
    source = "ball" if doc.get("source") == "ball" else "file"
    return _Rows(np.array(dirs, np.float64), intens,
                 names if all(isinstance(n, str) for n in names) else None, positions,
                 [e.get("index", i) for i, e in enumerate(images)], ambient,
                 doc.get("intensity_units", "relative")), source


def _check_intensities(path: Path, intens: np.ndarray, lines: list[int]) -> None:
    for i, row in enumerate(intens):
        if not np.isfinite(row).all() or (row < 0).any() or not (row > 0).any():
            raise MatcapError(f"{path.name} line {lines[i]}: intensity {row.tolist()} must be finite, not "
                              f"negative and not all zero")


def _check_rows(path: Path, rows: _Rows, what: str) -> np.ndarray:
    """Unit directions (R, 3); one line for a zero, non-finite or behind-the-plane row."""
    out = np.zeros_like(rows.directions)
    for i, d in enumerate(rows.directions):
        where = f"{path.name} {what} {rows.lines[i]}"
        if not np.isfinite(d).all():
            raise MatcapError(f"{where}: light {d.tolist()} is not finite")
        size = float(np.linalg.norm(d))
        if size < 1e-9:
            raise MatcapError(f"{where}: light direction is zero")
        if d[2] <= 0.0:
            raise MatcapError(f"{where}: light {d.tolist()} is behind the object's plane (z must be > 0: z points "
                              f"toward the camera)")
        out[i] = d / size
    if rows.intensities is not None:
        _check_intensities(path, rows.intensities, rows.lines)
    return out


# ----------------------------------------------------------------------------------------------- matching


def _match_names(path: Path, names: list[str], photos: list[str]) -> np.ndarray | None:
    """Row index per photo by file name, then by stem; None where the names do not cover the photos."""
    base = [os.path.basename(p) for p in photos]
    for key in (lambda s: s, lambda s: os.path.splitext(s)[0]):
        table: dict[str, int] = {}
        for i, n in enumerate(names):
            table.setdefault(key(n).lower(), i)
        idx = [table.get(key(b).lower()) for b in base]
        if all(i is not None for i in idx):
            return np.array(idx, int)
    return None


def _name_list(path: Path) -> tuple[Path, list[str]] | None:
    for name in NAME_LISTS:
        p = path.parent / name
        if p.is_file():
            try:
                names = [ln.strip() for ln in p.read_text(encoding="utf-8-sig").splitlines() if ln.strip()]
            except (OSError, UnicodeDecodeError) as e:
                raise MatcapError(f"cannot read {p}: {e}") from None
            return p, [os.path.basename(n.replace("\\", "/")) for n in names]
    return None


def read_light_file(path: str | os.PathLike, photos: Sequence[str], source: str | None = None) -> KnownLights:
    """The lights of ``photos`` (file names of the capture's photos, in the capture's order) from a light file.

    Returns :class:`KnownLights` with one row per photo. Rows meet photos by name where the file names them (an
    ``.lp`` file, a ``lights.json`` with ``file`` entries, a table with a ``names.txt`` / ``filenames.txt``
    beside it); by order otherwise (the photos sorted naturally, 2 before 10), which needs as many rows as photos.
    A ``lights.json`` whose names are another capture's (a calibration shot, ``chrome.3.png`` for ``owl.3.png``)
    is matched by order too.
    """
    p = Path(path)
    if not p.is_file():
        raise MatcapError(f"light file {p} does not exist")
    photos = list(photos)
    suffix = p.suffix.lower()
    what = "line"
    if suffix == ".json":
        rows, found_source = _read_json(p)  # lightfile.read_lights words every problem in one line
        what = "entry"
    elif suffix == ".lp":
        rows, found_source = _read_lp(p), "file"
    else:
        rows, found_source = _read_table(p), "file"
    directions = _check_rows(p, rows, what)
    positions = rows.positions
    if positions is not None:  # point lights: must be in front of the plane (z > 0), direction toward them
        directions = positions / np.maximum(np.linalg.norm(positions, axis=1, keepdims=True), 1e-12)
    names, matched = rows.names, "name"
    if names is None and suffix not in (".json", ".lp"):
        listed = _name_list(p)
        if listed is not None:
            lst, names = listed
            if len(names) != len(rows.directions):
                raise MatcapError(f"{lst.name} lists {len(names)} photos but {p.name} has {len(rows.directions)} "
                                  f"lights")
            matched = lst.name
    idx = None
    if names is not None:
        idx = _match_names(p, names, photos)
        if idx is None and suffix != ".json":
            missing = [os.path.basename(f) for f in photos
                       if os.path.basename(f).lower() not in {n.lower() for n in names}
                       and os.path.splitext(os.path.basename(f))[0].lower()
                       not in {os.path.splitext(n)[0].lower() for n in names}]
            raise MatcapError(f"{p.name} names no light for photo {missing[0]}"
                              + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")
                              + (f"; its rows follow {matched}" if matched != "name" else ""))
    if idx is None:
        if len(rows.directions) != len(photos):
            raise MatcapError(f"{p.name} has {len(rows.directions)} lights but the capture has {len(photos)} "
                              f"photos")
        order = sorted(range(len(photos)), key=lambda i: natural_key(os.path.basename(photos[i])))
        idx = np.empty(len(photos), int)
        idx[np.array(order)] = np.arange(len(photos))  # the n-th photo in natural order takes row n
        matched = "order"
    pick = lambda a: None if a is None else np.asarray(a, np.float64)[idx]  # noqa: E731
    return KnownLights(directions[idx], pick(rows.intensities), source or found_source, str(p), matched,
                       pick(positions), pick(rows.ambient), rows.intensity_units)

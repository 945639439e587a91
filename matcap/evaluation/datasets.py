"""Photometric-stereo evaluation data -> :class:`PSObject`, all in one camera convention.

**Camera convention (everything this module returns):** x right, y up, z toward the camera (viewer); image row 0
is the top of the image. Normals are unit vectors, zeros outside the mask. Light directions point from the surface
toward the light.

Three layouts are recognised (:func:`discover` decides from the files present):

``diligent``  -- DiLiGenT (Shi et al., CVPR 2016) and anything written in its layout, one folder per object::

        001.png ... 096.png      16-bit RGB, linear (kept 16-bit: read with OpenCV, divided by 65535)
        filenames.txt            image file names, one a line, in light order (else the NNN.png files sorted)
        light_directions.txt     one row "x y z" per image
        light_intensities.txt    one row "r g b" per image (optional; 1 1 1 if missing)
        mask.png                 object mask (non-zero = object)
        Normal_gt.mat            variable ``Normal_gt``, (H, W, 3) float    } ground truth, first found wins;
        normal.txt               H*W rows "x y z"                          } all optional
        Normal_gt.png            (n + 1) / 2 encoded, 8- or 16-bit         }

    DiLiGenT's camera frame is x right, y up, z pointing out of the image toward the viewer, for the normals and
    for the light directions alike (the convention of its readme and of the loaders that evaluate on it:
    CNN-PS, PS-FCN, SDPS-Net read ``Normal_gt.mat`` and ``light_directions.txt`` without any axis flip). That is
    our convention, so the conversion :data:`DILIGENT_TO_CAMERA` is the identity; it is applied anyway (to
    normals and lights) so the place to change it is obvious. ``normal.txt`` rows are matched to pixels in
    row-major order unless column-major (MATLAB) order fits the mask better. Known-bad images are dropped by
    default (:data:`KNOWN_BAD_IMAGES`: the first 20 images of ``bearPNG``, as in the published evaluations).

``uw``  -- the UW CSE455 photometric-stereo captures (``shared/data/captures/uw_*``)::

        <obj>.0.png ... <obj>.11.png   8-bit RGB
        <obj>.mask.png                 soft-edged mask: pixels >= 128 count as object
        lights.txt                     first line the count, then one "x y z" row per image, already in our
                                       convention (x right, y up, z toward the camera; checked on uw_chrome)
        names.txt                      image file names in light order (optional)

    No ground truth. The 8-bit values are taken as **linear** (value / 255) for the classical baselines: the
    course data were made for Lambertian photometric stereo with linear images and decoding sRGB makes the
    least-squares fit worse. Networks are given the sRGB-decoded images (``PSObject.srgb_8bit`` is True), as
    ``matcap capture`` would do with 8-bit photos, unless ``matcap eval --linear`` (the same values as the
    baselines; closer to least squares for the bundled model: docs/eval.md).

``synthetic``  -- our rendered split: ``DATA/manifest.json`` and ``DATA/scene_XXXXXX/`` with ``000.png`` ...
    (linear 16-bit RGB), ``mask.png`` (0/255), ``normal.exr`` (float32, our convention, zeros outside the mask),
    ``spec.json`` (``"lighting_group"``: ``"directional"`` / ``"environment"`` / ``"both"``; optional ``"split"``)
    and ``lights.json`` (basis lights + per-image weights and exposure). Lights count as calibrated only when every
    image is lit by exactly one directional basis light (then its direction, and irradiance x weight x exposure
    as intensity, are used); otherwise ``light_dirs`` is None and the least-squares baselines report "n/a".
    ``manifest.json`` names the split the folder holds and the scenes' lighting groups.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from matcap import formats, imageio
from matcap.errors import MatcapError

#: DiLiGenT camera frame -> ours (x right, y up, z toward the viewer). Identity: the frames agree.
DILIGENT_TO_CAMERA = np.eye(3, dtype=np.float64)

#: Images excluded from DiLiGenT objects by default: object name -> number of leading images to drop.
KNOWN_BAD_IMAGES = {"bearPNG": 20}

#: Mask threshold for soft-edged 8-bit masks (UW): a pixel is object when its value is >= this.
UW_MASK_THRESHOLD = 128


@dataclass
class PSObject:
    """One photometric-stereo object, in our camera convention.

    images: list of N (H, W, 3) float32 arrays, linear radiometry as the dataset defines it (the classical
        baselines use them as they are; light intensities are *not* divided out here).
    mask: (H, W) bool.
    normal_gt: (H, W, 3) float32 unit normals, zeros outside the mask, or None (no ground truth).
    light_dirs: (N, 3) float64 unit vectors toward the lights, or None (uncalibrated).
    light_intensities: (N, 3) float64 RGB light intensities, or None (means all ones when ``light_dirs`` is set).
    group: label the results are grouped by (synthetic: the lighting group; otherwise the dataset kind).
    srgb_8bit: True when ``images`` are 8-bit values taken as linear although the files are sRGB-ish photos;
        :meth:`network_images` then sRGB-decodes them for the learned methods.
    """

    name: str
    images: list[np.ndarray]
    mask: np.ndarray
    normal_gt: np.ndarray | None = None
    light_dirs: np.ndarray | None = None
    light_intensities: np.ndarray | None = None
    group: str = ""
    kind: str = ""
    source: str = ""
    bit_depth: str = ""
    srgb_8bit: bool = False
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.images:
            raise MatcapError(f"{self.source or self.name}: no images")
        try:
            h, w = imageio.check_same_size([(f"image {i}", im.shape[:2]) for i, im in enumerate(self.images)])
        except MatcapError as exc:
            raise MatcapError(f"{self.source or self.name}: {exc}") from None
        for i, im in enumerate(self.images):
            if im.shape != (h, w, 3):
                raise MatcapError(f"{self.source or self.name}: image {i} has shape {im.shape}, expected {(h, w, 3)}")
        self.mask = np.asarray(self.mask, dtype=bool)
        if self.mask.shape != (h, w):
            raise MatcapError(f"{self.source or self.name}: mask is {self.mask.shape}, images are {(h, w)}")
        if not self.mask.any():
            raise MatcapError(f"{self.source or self.name}: mask is empty")
        if self.normal_gt is not None and self.normal_gt.shape != (h, w, 3):
            raise MatcapError(f"{self.source or self.name}: normals are {self.normal_gt.shape}, images {(h, w)}")
        n = len(self.images)
        if self.light_dirs is not None:
            self.light_dirs = np.asarray(self.light_dirs, dtype=np.float64).reshape(-1, 3)
            if len(self.light_dirs) != n:
                raise MatcapError(f"{self.source or self.name}: {len(self.light_dirs)} light directions "
                                  f"for {n} images")
            norms = np.linalg.norm(self.light_dirs, axis=1, keepdims=True)
            if (norms < 1e-9).any():
                raise MatcapError(f"{self.source or self.name}: a light direction is zero")
            self.light_dirs = self.light_dirs / norms
            if self.light_intensities is None:
                self.light_intensities = np.ones((n, 3))
            self.light_intensities = np.asarray(self.light_intensities, dtype=np.float64).reshape(-1, 3)
            if len(self.light_intensities) != n:
                raise MatcapError(f"{self.source or self.name}: {len(self.light_intensities)} light "
                                  f"intensities for {n} images")

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape

    @property
    def calibrated(self) -> bool:
        return self.light_dirs is not None

    def network_images(self, indices: list[int] | np.ndarray | None = None,
                       decode_srgb: bool = True) -> list[np.ndarray]:
        """Linear float32 images for a learned method (sRGB-decoded when ``srgb_8bit`` and ``decode_srgb``; with
        ``decode_srgb=False`` the 8-bit values are taken as linear, as `matcap capture --linear` does)."""
        idx = range(len(self.images)) if indices is None else indices
        if self.srgb_8bit and decode_srgb:
            return [imageio.srgb_to_linear(self.images[i]) for i in idx]
        return [self.images[i] for i in idx]


@dataclass
class ObjectSource:
    """A discovered object, loaded on demand (evaluation holds one object in memory at a time)."""

    name: str
    kind: str
    path: Path
    group: str
    loader: Callable[[], PSObject]

    def load(self) -> PSObject:
        return self.loader()


# ----------------------------------------------------------------------------------------------- helpers


def _read_lines(path: Path) -> list[str]:
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]


def _read_matrix(path: Path, cols: int = 3, skip_count_line: bool = False) -> np.ndarray:
    try:
        rows = _read_lines(path)
        if skip_count_line and rows and len(rows[0].split()) == 1:
            count = int(float(rows[0]))
            rows = rows[1:]
            if count != len(rows):
                raise MatcapError(f"{path}: first line says {count} rows, found {len(rows)}")
        arr = np.array([[float(v) for v in re.split(r"[,\s]+", r)] for r in rows], dtype=np.float64)
    except (ValueError, IndexError):
        raise MatcapError(f"{path}: not a table of numbers") from None
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise MatcapError(f"{path}: expected {cols} numbers per row, got shape {arr.shape}")
    return arr


def _read_mask(path: Path, threshold: int = 1) -> np.ndarray:
    """Read a mask image: a pixel is object when any channel is >= ``threshold`` (8-bit scale)."""
    px = imageio.read_image(path).pixels
    if px.dtype == np.uint16:
        px = px // 257
    elif px.dtype.kind == "f":
        px = np.clip(px, 0, 1) * 255.0
    return (px.max(axis=2) >= threshold)


def _read_linear(path: Path) -> tuple[np.ndarray, str]:
    stored = imageio.read_image(path)
    arr, _ = imageio.to_linear_float(stored, decode_srgb_8bit=False)
    return arr, stored.kind


def _unit_normals(n: np.ndarray, mask: np.ndarray) -> np.ndarray:
    n = np.asarray(n, dtype=np.float64)
    length = np.linalg.norm(n, axis=2, keepdims=True)
    out = np.where(length > 1e-8, n / np.maximum(length, 1e-12), 0.0)
    return np.where(mask[:, :, None], out, 0.0).astype(np.float32)


def _kinds(kinds: set[str]) -> str:
    return "/".join(sorted(kinds)) if kinds else "?"


# ----------------------------------------------------------------------------------------------- DiLiGenT


def is_diligent_object(folder: Path) -> bool:
    return (folder / "light_directions.txt").is_file() and (folder / "mask.png").is_file()


def _diligent_image_names(folder: Path) -> list[str]:
    if (folder / "filenames.txt").is_file():
        return _read_lines(folder / "filenames.txt")
    names = sorted(p.name for p in folder.iterdir() if re.fullmatch(r"\d+\.png", p.name, flags=re.I))
    if not names:
        raise MatcapError(f"{folder}: no filenames.txt and no NNN.png images")
    return names


def _normal_txt(path: Path, mask: np.ndarray) -> np.ndarray:
    h, w = mask.shape
    try:
        flat = np.loadtxt(path, dtype=np.float64)
    except ValueError:
        raise MatcapError(f"{path}: not a table of numbers") from None
    if flat.shape != (h * w, 3):
        raise MatcapError(f"{path}: expected {h * w} rows of 3 numbers, got {flat.shape}")
    row_major = flat.reshape(h, w, 3)
    col_major = flat.reshape(w, h, 3).transpose(1, 0, 2)
    fit = [np.mean((np.linalg.norm(c, axis=2) > 1e-6) == mask) for c in (row_major, col_major)]
    return row_major if fit[0] >= fit[1] else col_major


def load_diligent_object(folder: str | os.PathLike, group: str = "diligent",
                         exclude_known_bad: bool = True) -> PSObject:
    """Load one object folder in the DiLiGenT layout (see the module docstring for files and conventions)."""
    folder = Path(folder)
    names = _diligent_image_names(folder)
    dirs = _read_matrix(folder / "light_directions.txt") @ DILIGENT_TO_CAMERA.T
    ints_path = folder / "light_intensities.txt"
    ints = _read_matrix(ints_path) if ints_path.is_file() else np.ones((len(names), 3))
    if not (len(names) == len(dirs) == len(ints)):
        raise MatcapError(f"{folder}: {len(names)} images, {len(dirs)} light directions, {len(ints)} intensities")
    keep = list(range(len(names)))
    notes = []
    drop = KNOWN_BAD_IMAGES.get(folder.name, 0) if exclude_known_bad else 0
    if drop:
        keep = keep[drop:]
        notes.append(f"first {drop} images excluded (known bad)")
    images, kinds = [], set()
    for i in keep:
        arr, kind = _read_linear(folder / names[i])
        images.append(arr)
        kinds.add(kind)
    mask = _read_mask(folder / "mask.png")
    normal = None
    if (folder / "Normal_gt.mat").is_file():
        import scipy.io

        try:
            mat = scipy.io.loadmat(str(folder / "Normal_gt.mat"))
        except Exception as exc:  # scipy raises several types for broken files
            raise MatcapError(f"{folder / 'Normal_gt.mat'}: cannot read ({exc})") from None
        if "Normal_gt" not in mat:
            raise MatcapError(f"{folder / 'Normal_gt.mat'}: no variable 'Normal_gt'")
        normal = np.asarray(mat["Normal_gt"], dtype=np.float64)
    elif (folder / "normal.txt").is_file():
        normal = _normal_txt(folder / "normal.txt", mask)
    elif (folder / "Normal_gt.png").is_file():
        stored = imageio.read_image(folder / "Normal_gt.png")
        enc, _ = imageio.to_linear_float(stored, decode_srgb_8bit=False)
        normal = formats.decode_normal(enc, "gl")  # (n + 1) / 2, +Y up: our camera convention
    if normal is not None:
        if normal.shape != mask.shape + (3,):
            raise MatcapError(f"{folder}: ground-truth normals are {normal.shape}, mask is {mask.shape}")
        normal = _unit_normals(normal @ DILIGENT_TO_CAMERA.T, mask)
    return PSObject(name=folder.name, images=images, mask=mask, normal_gt=normal, light_dirs=dirs[keep],
                    light_intensities=ints[keep], group=group, kind="diligent", source=str(folder),
                    bit_depth=_kinds(kinds), srgb_8bit=False, notes=notes)


# ----------------------------------------------------------------------------------------------- UW captures


def _uw_prefix(folder: Path) -> str | None:
    masks = sorted(folder.glob("*.mask.png"))
    if len(masks) == 1 and (folder / "lights.txt").is_file():
        return masks[0].name[: -len(".mask.png")]
    return None


def is_uw_object(folder: Path) -> bool:
    return _uw_prefix(folder) is not None


def load_uw_object(folder: str | os.PathLike, group: str = "uw") -> PSObject:
    """Load one UW-layout capture (``<obj>.N.png``, ``<obj>.mask.png``, ``lights.txt``); see module docstring."""
    folder = Path(folder)
    prefix = _uw_prefix(folder)
    if prefix is None:
        raise MatcapError(f"{folder}: not a UW capture (needs one <obj>.mask.png and lights.txt)")
    dirs = _read_matrix(folder / "lights.txt", skip_count_line=True)
    if (folder / "names.txt").is_file():
        names = _read_lines(folder / "names.txt")
    else:
        pat = re.compile(rf"{re.escape(prefix)}\.(\d+)\.png")
        found = [(int(m.group(1)), p.name) for p in folder.iterdir() if (m := pat.fullmatch(p.name))]
        names = [n for _, n in sorted(found)]
    if len(names) != len(dirs):
        raise MatcapError(f"{folder}: {len(names)} images but {len(dirs)} lights in lights.txt")
    images, kinds = [], set()
    for n in names:
        arr, kind = _read_linear(folder / n)
        images.append(arr)
        kinds.add(kind)
    mask = _read_mask(folder / f"{prefix}.mask.png", UW_MASK_THRESHOLD)
    name = folder.name
    return PSObject(name=name, images=images, mask=mask, normal_gt=None, light_dirs=dirs,
                    light_intensities=np.ones_like(dirs), group=group, kind="uw", source=str(folder),
                    bit_depth=_kinds(kinds), srgb_8bit=kinds == {"8bit"},
                    notes=["8-bit values taken as linear for the baselines"] if "8bit" in kinds else [])


# ----------------------------------------------------------------------------------------------- synthetic split


def is_synthetic_scene(folder: Path) -> bool:
    return (folder / "normal.exr").is_file() and (folder / "mask.png").is_file() and (folder / "000.png").is_file()


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise MatcapError(f"{path}: invalid JSON ({exc.msg} at line {exc.lineno})") from None


def _single_directional(entry: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """(direction, irradiance) if ``entry`` describes exactly one directional light, else None."""
    if isinstance(entry, dict) and "lights" in entry:
        entry = entry["lights"]
    if isinstance(entry, list):
        if len(entry) != 1:
            return None
        entry = entry[0]
    if not isinstance(entry, dict) or entry.get("kind", entry.get("type")) != "directional":
        return None
    if "direction" not in entry:
        return None
    direction = np.asarray(entry["direction"], dtype=np.float64).reshape(3)
    irr = np.asarray(entry.get("irradiance", (1.0, 1.0, 1.0)), dtype=np.float64).reshape(-1)
    irr = np.repeat(irr, 3) if irr.size == 1 else irr[:3]
    return direction, irr


def synthetic_lights(data: Any, n_images: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Calibrated (directions, intensities) from a scene's ``lights.json``, or None if any image is not lit by
    exactly one directional light.

    The generator's format (``matcap synth``): ``{"basis": [light dicts], "images": [{"weights": [one per basis
    light], "exposure": e}, ...]}``; an image is directional when exactly one weight is non-zero and that basis
    light is ``"directional"``; its intensity is ``weight * exposure * irradiance``. Also accepted: a list (or
    ``{"images"|"per_image"|"lights": [...]}``) with one light dict (or one-element list) per image.
    """
    if isinstance(data, dict) and isinstance(data.get("basis"), list) and isinstance(data.get("images"), list):
        basis, per_image = data["basis"], data["images"]
        if len(per_image) != n_images:
            return None
        dirs, ints = [], []
        for entry in per_image:
            w = np.asarray(entry.get("weights", []) if isinstance(entry, dict) else [], dtype=np.float64)
            on = np.flatnonzero(w > 0)
            if len(w) != len(basis) or len(on) != 1:
                return None
            one = _single_directional(basis[on[0]])
            if one is None:
                return None
            scale = w[on[0]] * float(entry.get("exposure", 1.0))
            dirs.append(one[0])
            ints.append(one[1] * scale)
        return np.stack(dirs), np.stack(ints)
    per_image = data
    if isinstance(data, dict):
        for key in ("images", "per_image", "lights"):
            if isinstance(data.get(key), list):
                per_image = data[key]
                break
    if not isinstance(per_image, list) or len(per_image) != n_images:
        return None
    found = [_single_directional(e) for e in per_image]
    if any(f is None for f in found):
        return None
    return np.stack([f[0] for f in found]), np.stack([f[1] for f in found])


def load_synthetic_scene(folder: str | os.PathLike, group: str | None = None) -> PSObject:
    """Load one scene of our synthetic split (see the module docstring)."""
    folder = Path(folder)
    names = sorted(p.name for p in folder.iterdir() if re.fullmatch(r"\d{3,}\.png", p.name))
    images, kinds = [], set()
    for n in names:
        arr, kind = _read_linear(folder / n)
        images.append(arr)
        kinds.add(kind)
    mask = _read_mask(folder / "mask.png")
    path = formats.LAYOUTS["scene"]["normal_exr"].path(folder)  # float32 camera-space normals, as stored
    normal = imageio.read_exr(path)
    if normal.ndim != 3:
        raise MatcapError(f"{path}: expected RGB normals")
    imageio.check_finite(normal, str(path))
    normal = _unit_normals(normal, mask)
    spec = _read_json(folder / "spec.json") if (folder / "spec.json").is_file() else {}
    if group is None:
        group = str((spec.get("lighting_group") if isinstance(spec, dict) else None) or "unknown")
    dirs = ints = None
    if (folder / "lights.json").is_file():
        lights = synthetic_lights(_read_json(folder / "lights.json"), len(images))
        if lights is not None:
            dirs, ints = lights
    return PSObject(name=folder.name, images=images, mask=mask, normal_gt=normal, light_dirs=dirs,
                    light_intensities=ints, group=group, kind="synthetic", source=str(folder),
                    bit_depth=_kinds(kinds), srgb_8bit=False)


def _manifest_scenes(root: Path, split: str | None) -> list[tuple[str, str | None]] | None:
    """(folder name, group or None) from ``manifest.json`` if it lists scenes, else None.

    The generator writes ``{"split": "test", "scenes": ["scene_000000", ...], "lighting_groups": {name: group}}``
    (one split per folder); lists of ``{"dir"|"name"|..., "split", "lighting_group"}`` dicts are accepted too.
    """
    path = root / "manifest.json"
    if not path.is_file():
        return None
    data = _read_json(path)
    entries = None
    groups: dict[str, Any] = {}
    if isinstance(data, dict):
        if split and isinstance(data.get("split"), str) and data["split"] != split:
            raise MatcapError(f"{path}: this folder holds the {data['split']!r} split, not {split!r} "
                              f"(pass --split {data['split']} to evaluate it)")
        if isinstance(data.get("lighting_groups"), dict):
            groups = data["lighting_groups"]
        for key in ("scenes", "items", "entries"):
            if isinstance(data.get(key), list):
                entries = data[key]
                break
    elif isinstance(data, list):
        entries = data
    if entries is None:
        return None
    out = []
    for e in entries:
        if isinstance(e, str):
            name, group, esplit = e, None, None
        elif isinstance(e, dict):
            name = next((str(e[k]) for k in ("dir", "path", "folder", "name", "id") if k in e), None)
            group, esplit = e.get("lighting_group"), e.get("split")
            if name is None:
                continue
        else:
            continue
        if split and esplit is not None and esplit != split:
            continue
        if not (root / name).is_dir() and (root / Path(name).name).is_dir():
            name = Path(name).name
        group = group if group is not None else groups.get(name)
        out.append((name, str(group) if group is not None else None))
    return out


# ----------------------------------------------------------------------------------------------- discovery


def _source_for(folder: Path, synthetic_group: str | None = None) -> ObjectSource | None:
    if is_diligent_object(folder):
        return ObjectSource(folder.name, "diligent", folder, "diligent", lambda: load_diligent_object(folder))
    if is_uw_object(folder):
        return ObjectSource(folder.name, "uw", folder, "uw", lambda: load_uw_object(folder))
    if is_synthetic_scene(folder):
        group = synthetic_group
        if group is None and (folder / "spec.json").is_file():
            spec = _read_json(folder / "spec.json")
            group = spec.get("lighting_group") if isinstance(spec, dict) else None
        group = str(group) if group is not None else "unknown"
        return ObjectSource(folder.name, "synthetic", folder, group,
                            lambda: load_synthetic_scene(folder, group))
    return None


def discover(path: str | os.PathLike, split: str | None = "test") -> tuple[list[ObjectSource], list[str]]:
    """Find the objects under ``path``: an object folder itself, or a folder of object folders.

    For the synthetic split, ``manifest.json`` (if it lists scenes) decides which scenes belong to ``split``;
    otherwise every ``scene_*`` folder whose ``spec.json`` has no other ``"split"`` is taken. Returns the sources
    (sorted by name) and notes about sub-folders that were skipped.
    """
    root = Path(path)
    if not root.is_dir():
        raise MatcapError(f"{root}: no such folder")
    own = _source_for(root)
    if own is not None:
        return [own], []
    notes: list[str] = []
    sources: list[ObjectSource] = []
    listed = _manifest_scenes(root, split)
    if listed is not None:
        for name, group in listed:
            folder = root / name
            src = _source_for(folder, group) if folder.is_dir() else None
            if src is None:
                notes.append(f"{name}: listed in manifest.json but not a readable scene folder")
            else:
                sources.append(src)
        return sorted(sources, key=lambda s: s.name), notes
    for folder in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        src = _source_for(folder)
        if src is None:
            notes.append(f"{folder.name}: not a recognised object folder (skipped)")
            continue
        if src.kind == "synthetic" and split and (folder / "spec.json").is_file():
            spec = _read_json(folder / "spec.json")
            if isinstance(spec, dict) and spec.get("split", split) != split:
                continue
        sources.append(src)
    if not sources:
        raise MatcapError(f"{root}: no DiLiGenT-layout, UW or synthetic-split objects found")
    return sources, notes

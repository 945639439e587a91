"""Reading a capture folder: its photos decoded to linear light (shrunk by ``--max-side`` as they are read, picked
by ``--max-images``), its mask and its light file; the memory check that refuses a capture too large for the machine
before anything is decoded; and the shrinking and upscaling of images and maps.
"""
from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from matcap import imageio
from matcap.errors import MatcapError
from matcap.lightfiles import natural_key

#: Files in a capture folder that are not photos: masks and ground-truth maps.
_SKIP = re.compile(
    r"^(mask|.*\.mask|normal|normal_gt|basecolor|base_color|albedo|roughness|metallic|height|relight)([._-].*)?$",
    re.IGNORECASE,
)
_MASK = re.compile(r"^(mask|.*\.mask)$", re.IGNORECASE)


@dataclass
class Capture:
    """A folder of photos, decoded to linear light.

    images: list of (H, W, 3) float32 linear RGB; mask: (H, W) bool or None.
    """

    images: list[np.ndarray]
    files: list[str]
    mask: np.ndarray | None = None
    mask_file: str | None = None
    colour: str = "linear"
    skipped: list[str] = field(default_factory=list)
    lamp_off_file: str | None = None  # the lamp-off photo subtracted from every photo (absolute path), or None
    photo_size_wh: tuple[int, int] | None = None  # (W, H) of the photos as stored (before --max-side)
    picked: list[int] = field(default_factory=list)  # indices of ``files`` among the folder's photos (--max-images)


def read_mask(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W) bool mask from an image file (> 0 in any channel is foreground, > 0.5 for float files)."""
    stored = imageio.read_image(path)
    px = stored.pixels
    mask = px.max(axis=2) > (0.5 if px.dtype.kind == "f" else 0)
    if shape is not None and mask.shape != tuple(shape):
        raise MatcapError(
            f"{path}: mask is {mask.shape[1]}x{mask.shape[0]} but the images are {shape[1]}x{shape[0]} (W x H)"
        )
    return mask


# Peak memory of a capture, per pixel of one photo at working size (the largest measured: the fit at full size, 16
# photos of 4,000 x 3,000, about 93 B/px over the base; docs/ci.md, "Huge inputs"): the decoded photos, the fit's
# copies of them and its re-render. A capture whose estimate exceeds MEMORY_FRACTION of the available memory is
# refused up front (the rest is the margin for what else the machine does meanwhile).
BYTES_PER_IMAGE_PIXEL = 95
FIXED_BYTES = 1.5e9  # Python, torch, two small networks
MEMORY_FRACTION = 0.9


def available_memory() -> int:
    """Bytes this process may use: ``MATCAP_MEMORY_GB`` if set, else MemAvailable from /proc/meminfo, else the
    physical memory (sysconf)."""
    forced = os.environ.get("MATCAP_MEMORY_GB")
    if forced:
        try:
            return int(float(forced) * 1e9)
        except ValueError:
            raise MatcapError(f"MATCAP_MEMORY_GB must be a number of gigabytes, got {forced!r}") from None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 1 << 62  # unknown: no limit


def memory_needed(n_images: int, size_hw: tuple[int, int], photo_hw: tuple[int, int] | None = None) -> int:
    """Estimated peak bytes of capturing ``n_images`` photos at working size ``size_hw`` (after --max-side), when
    each photo is decoded at ``photo_hw`` first (one at a time)."""
    h, w = size_hw
    ph, pw = photo_hw or size_hw
    decode = ph * pw * 3 * (4 + 2) if (ph, pw) != (h, w) else 0  # one photo in float32 + as stored
    return int(FIXED_BYTES + n_images * h * w * BYTES_PER_IMAGE_PIXEL + decode)


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f}" if n < 1e10 else f"{n / 1e9:.0f}"


def check_memory(n_images: int, size_hw: tuple[int, int], photo_hw: tuple[int, int] | None = None,
                 total_images: int | None = None) -> None:
    """Refuse (one-line :class:`MatcapError`) a capture that would not fit in memory, naming the options that
    make it fit: ``--max-side`` (photos shrunk as they are read) and ``--max-images``."""
    need, have = memory_needed(n_images, size_hw, photo_hw), available_memory()
    if need <= MEMORY_FRACTION * have:
        return
    h, w = size_hw
    ph, pw = photo_hw or size_hw
    budget = MEMORY_FRACTION * have - FIXED_BYTES - ph * pw * 3 * (4 + 2)  # minus decoding one photo at full size
    per_image = max(budget, 0) / max(n_images, 1) / BYTES_PER_IMAGE_PIXEL  # pixels per image that would fit
    side = int(max(w, h) * min(1.0, (per_image / (h * w)) ** 0.5)) // 64 * 64
    fits_k = int(max(budget, 0) // (h * w * BYTES_PER_IMAGE_PIXEL))
    hints = []
    if side >= 64:
        hints.append(f"--max-side {side}")
    if fits_k >= 2:
        hints.append(f"--max-images {min(fits_k, 16)}")
    hint = " or ".join(hints) if hints else "--max-side 1024 --max-images 16"
    raise MatcapError(
        f"{total_images or n_images} photos of {pw}x{ph} would need about {_gb(need)} GB of memory, more than "
        f"the {_gb(MEMORY_FRACTION * have)} GB that can be spared here; use {hint}"
    )


def _fit_side(size_hw: tuple[int, int], max_side: int | None) -> tuple[int, int]:
    """(H, W) shrunk so that the longer side is at most ``max_side`` (as :func:`downscale_arrays` does)."""
    h, w = size_hw
    if max_side is None or max(h, w) <= max_side:
        return h, w
    s = max_side / max(h, w)
    return max(1, round(h * s)), max(1, round(w * s))


def shrink_image(image: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """``image`` (H, W) or (H, W, C) area-averaged to ``size_wh`` (W, H)."""
    import cv2

    return cv2.resize(image, size_wh, interpolation=cv2.INTER_AREA)


def pick_images(n: int, max_images: int | None, seed: int) -> np.ndarray:
    """Indices of the photos a capture uses: all, or ``max_images`` of them drawn with ``seed`` (sorted)."""
    if max_images is None or max_images >= n:
        return np.arange(n)
    if max_images < 2:
        raise MatcapError(f"--max-images must be at least 2, got {max_images}")
    return np.sort(np.random.default_rng(seed).choice(n, size=max_images, replace=False))


def _scan(folder: Path) -> tuple[list[Path], list[str], Path | None]:
    """(photos in natural file-name order, names skipped, the mask file or None) of a capture folder."""
    photos, skipped, found_mask = [], [], None
    for p in sorted(folder.iterdir(), key=lambda p: natural_key(p.name)):
        if not p.is_file() or p.suffix.lower() not in imageio.IMAGE_SUFFIXES or p.name.startswith("."):
            continue
        stem = p.name[: -len(p.suffix)]
        if _SKIP.match(stem):
            if _MASK.match(stem) and found_mask is None:
                found_mask = p
            else:
                skipped.append(p.name)
            continue
        photos.append(p)
    return photos, skipped, found_mask


def photo_names(folder: str | os.PathLike) -> list[str]:
    """File names of a capture folder's photos in the order :func:`load_capture` reads them (natural order; masks
    and other non-photos left out)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MatcapError(f"{folder}: not a folder of images")
    return [p.name for p in _scan(folder)[0]]


def read_lights_for(path: str | os.PathLike, folder: str | os.PathLike, picked: Sequence[int] | None = None):
    """:class:`matcap.lightfiles.KnownLights` of the photos of ``folder`` from the light file ``path`` (rows met
    with all of the folder's photos, then the ``picked`` ones kept, in their order)."""
    from matcap.lightfiles import read_light_file

    known = read_light_file(path, photo_names(folder))
    return known if picked is None else known.subset(picked)


def load_capture(folder: str | os.PathLike, mask: str | os.PathLike | None = None, linear: bool = False,
                 max_side: int | None = None, max_images: int | None = None, seed: int = 0,
                 contrast: float = 1.0, lamp_off: str | os.PathLike | None = None) -> Capture:
    """Read the photos of ``folder``; ``mask.*`` / ``*.mask.*`` is the mask unless ``mask`` names one.

    8-bit images are decoded from sRGB unless ``linear``, after undoing a camera tone curve of ``contrast`` > 1
    (:func:`matcap.imageio.tone_curve`); 16-bit and float images are taken as linear.
    ``max_side``: each photo is shrunk as soon as it is read (area average in linear light) so that its longer
    side is at most that; ``max_images``: only that many photos, drawn with ``seed`` (:func:`pick_images`), are
    read. Sizes come from the files' headers first, so mixed sizes and a capture too large for the memory
    (:func:`check_memory`) are refused before anything is decoded.
    ``lamp_off``: a photo taken with the lamp off (the room's own light), outside ``folder``: decoded as the photos
    are and subtracted from each of them (:func:`subtract_lamp_off`).
    Raises :class:`MatcapError` for no/one image, mixed sizes, unreadable files, NaN/Inf, a mask of another size.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise MatcapError(f"{folder}: not a folder of images")
    if max_side is not None:
        check_max_side(max_side)
    contrast = imageio.check_contrast(contrast)
    photos, skipped, found_mask = _scan(folder)
    if not photos:
        raise MatcapError(f"{folder}: no images found (PNG, JPEG, TIFF, EXR or HDR)")
    if len(photos) < 2:
        raise MatcapError(f"{folder}: only one image ({photos[0].name}); photometric stereo needs at least 2 lights")
    headers = [(p.name, imageio.image_size(p)) for p in photos]
    if all(hw is not None for _, hw in headers):  # every header read: check sizes and memory before decoding
        photo_hw = imageio.check_same_size(headers)
        picked = pick_images(len(photos), max_images, seed)
        work_hw = _fit_side(photo_hw, max_side)
        check_memory(len(picked), work_hw, photo_hw, total_images=len(photos))
    else:
        picked = pick_images(len(photos), max_images, seed)
    photos = [photos[i] for i in picked]
    images, kinds, sizes = [], set(), []
    for p in photos:
        stored = imageio.read_image(p)
        sizes.append((p.name, stored.pixels.shape[:2]))
        arr, how = imageio.to_linear_float(stored, decode_srgb_8bit=not linear, contrast=contrast)
        kinds.add(f"{stored.kind}:{how}")
        del stored
        work_hw = _fit_side(arr.shape[:2], max_side)
        if work_hw != arr.shape[:2]:
            arr = shrink_image(arr, (work_hw[1], work_hw[0]))
        images.append(arr)
    size = imageio.check_same_size(sizes)
    if lamp_off is not None:
        off = Path(lamp_off)
        if off.resolve().parent == folder.resolve():
            raise MatcapError(f"{off}: the lamp-off photo is in the photos' folder, where it would be read as a photo; "
                              f"move it out")
        stored = imageio.read_image(off)
        if stored.pixels.shape[:2] != size:
            raise MatcapError(f"{off}: the lamp-off photo is {stored.pixels.shape[1]}x{stored.pixels.shape[0]}, the "
                              f"photos {size[1]}x{size[0]}")
        dark, _ = imageio.to_linear_float(stored, decode_srgb_8bit=not linear, contrast=contrast)
        if dark.shape[:2] != images[0].shape[:2]:
            dark = shrink_image(dark, (images[0].shape[1], images[0].shape[0]))
        images = [subtract_lamp_off(im, dark) for im in images]
    mask_path = Path(mask) if mask is not None else found_mask
    mask_arr = read_mask(mask_path, size) if mask_path is not None else None
    if mask_arr is not None and max_side is not None and images[0].shape[:2] != size:
        mask_arr = shrink_image(mask_arr.astype(np.float32), images[0].shape[1::-1]) > 0.5
        if not mask_arr.any():
            raise MatcapError(f"the mask vanishes at --max-side {max_side}; use a larger value")
    if mask_arr is not None and not mask_arr.any():
        raise MatcapError(f"{mask_path}: the mask is empty")
    words = {
        "8bit:srgb-decoded": "8-bit sRGB decoded to linear",
        f"8bit:srgb-decoded, tone curve {contrast:.2f} undone": f"8-bit sRGB decoded to linear after undoing a tone "
                                                                 f"curve of contrast {contrast:.2f}",
        "8bit:linear": "8-bit taken as linear",
        "16bit:linear": "16-bit taken as linear",
        "float:linear": "float taken as linear",
    }
    colour = ", ".join(sorted(words[k] for k in kinds))
    return Capture(images, [p.name for p in photos], mask_arr, str(mask_path) if mask_path else None, colour, skipped,
                   None if lamp_off is None else str(Path(lamp_off).resolve()), photo_size_wh=(size[1], size[0]),
                   picked=[int(i) for i in picked])


def subtract_lamp_off(photo: np.ndarray, lamp_off: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32: ``photo`` minus ``lamp_off`` (both (H, W, 3) linear), clipped at 0: the lamp's light alone.
    An observation that clips in ``photo`` (per channel, at 0.999 of its maximum) stays at the result's maximum, so
    that the fit still finds it clipped (:func:`matcap.refine.photos.clipping_level`)."""
    from matcap.refine.photos import clipping_level

    photo = np.asarray(photo, np.float32)
    out = np.maximum(photo - np.asarray(lamp_off, np.float32), 0.0)
    clipped = photo >= clipping_level(photo, np.ones(photo.shape[:2], bool))
    return np.where(clipped, out.reshape(-1, 3).max(axis=0), out).astype(np.float32)


def check_max_side(max_side: int) -> None:
    if max_side < 16:
        raise MatcapError(f"--max-side must be at least 16, got {max_side}")


def downscale_arrays(images: list[np.ndarray], mask: np.ndarray | None, max_side: int):
    """``(images, mask)`` shrunk so that the longer side is at most ``max_side`` pixels, keeping the aspect ratio:
    images (H, W, 3) area-averaged in linear light, mask (H, W) bool by area coverage > 0.5. Unchanged (the same
    objects) when they already fit."""
    check_max_side(max_side)
    h, w = images[0].shape[:2]
    if max(h, w) <= max_side:
        return images, mask
    import cv2

    s = max_side / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))  # cv2: (width, height)
    small = [cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in images]
    if mask is not None:
        mask = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5
        if not mask.any():
            raise MatcapError(f"the mask vanishes at --max-side {max_side}; use a larger value")
    return small, mask


def upscale_normals(normal: np.ndarray, size_hw: tuple[int, int], mask: np.ndarray | None = None) -> np.ndarray:
    """(h, w, 3) unit normals (zero outside their mask) to (H, W, 3): bilinear, renormalised; pixels with no normal
    nearby face the camera; zero outside ``mask`` (H, W) when given."""
    import cv2

    h, w = size_hw
    if normal.shape[:2] == (h, w):
        up = normal.astype(np.float32)
    else:
        up = cv2.resize(normal.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    norm = np.linalg.norm(up, axis=-1, keepdims=True)
    out = np.where(norm > 1e-6, up / np.maximum(norm, 1e-6), np.float32([0, 0, 1])).astype(np.float32)
    if mask is not None:
        out[~mask.astype(bool)] = 0
    return out


def downscale(cap: Capture, max_side: int) -> Capture:
    """``cap`` with images (area-averaged in linear light) and mask shrunk so that the longer side is at most
    ``max_side`` pixels, keeping the aspect ratio; unchanged when it already fits."""
    images, mask = downscale_arrays(cap.images, cap.mask, max_side)
    if images is cap.images:
        return cap
    return dataclasses.replace(cap, images=images, mask=mask)

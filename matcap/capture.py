"""From a folder of photos (one camera, several unknown lights) to SVBRDF maps.

Pipeline: read the folder (:func:`load_capture`) -> choose up to K images -> crop to the mask's box, pad (never
squash) to a square, resize to the network's native side (or pad to a multiple of it and use the scalable
polyphase mode for larger inputs) -> normalise -> SDM-UniPS normal network (+ BRDF network when available) ->
undo the geometry -> :class:`MaterialMaps`.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from matcap import imageio
from matcap.errors import MatcapError
from matcap.lightfiles import natural_key
from scenes.materialmaps import MaterialMaps, check_constant

if TYPE_CHECKING:
    from matcap.refine.flat import FlatLights

#: Files in a capture folder that are not photos: masks and ground-truth maps.
_SKIP = re.compile(
    r"^(mask|.*\.mask|normal|normal_gt|basecolor|base_color|albedo|roughness|metallic|height|relight)([._-].*)?$",
    re.IGNORECASE,
)
_MASK = re.compile(r"^(mask|.*\.mask)$", re.IGNORECASE)

#: Whether `matcap capture` refines the maps when neither --refine nor --no-refine is given (docs/refine.md).
REFINE_BY_DEFAULT = True

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "networks" / "weights"
DEFAULT_WEIGHTS = {"normal": WEIGHTS_DIR / "normal_small.safetensors", "brdf": WEIGHTS_DIR / "brdf_small.safetensors"}


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


def _shrink(image: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
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
                 contrast: float = 1.0) -> Capture:
    """Read the photos of ``folder``; ``mask.*`` / ``*.mask.*`` is the mask unless ``mask`` names one.

    8-bit images are decoded from sRGB unless ``linear``, after undoing a camera tone curve of ``contrast`` > 1
    (:func:`matcap.imageio.tone_curve`); 16-bit and float images are taken as linear.
    ``max_side``: each photo is shrunk as soon as it is read (area average in linear light) so that its longer
    side is at most that; ``max_images``: only that many photos, drawn with ``seed`` (:func:`pick_images`), are
    read. Sizes come from the files' headers first, so mixed sizes and a capture too large for the memory
    (:func:`check_memory`) are refused before anything is decoded.
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
            arr = _shrink(arr, (work_hw[1], work_hw[0]))
        images.append(arr)
    size = imageio.check_same_size(sizes)
    mask_path = Path(mask) if mask is not None else found_mask
    mask_arr = read_mask(mask_path, size) if mask_path is not None else None
    if mask_arr is not None and max_side is not None and images[0].shape[:2] != size:
        mask_arr = _shrink(mask_arr.astype(np.float32), images[0].shape[1::-1]) > 0.5
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
                   photo_size_wh=(size[1], size[0]), picked=[int(i) for i in picked])


# ------------------------------------------------------------------------------------------- models


@dataclass
class LoadedModel:
    model: Any
    config: Any
    card: dict
    path: str


def resolve_weights(weights: Sequence[str | os.PathLike] | None) -> list[Path]:
    """Weight files named by ``--weights`` (files or folders; ours or published), or the installed defaults."""
    if not weights:
        found = [p for p in DEFAULT_WEIGHTS.values() if p.exists()]
        if not DEFAULT_WEIGHTS["normal"].exists():
            raise MatcapError(
                "no trained default model is installed; train one (`matcap train --target normal ...`) or import the "
                "published SDM-UniPS checkpoints (`matcap weights import nml.pytmodel brdf.pytmodel --out DIR`) "
                "and pass --weights DIR"
            )
        return found
    files: list[Path] = []
    for w in weights:
        p = Path(w)
        if p.is_dir():
            inside = sorted(q for q in p.iterdir() if q.suffix in (".safetensors", ".pytmodel"))
            if not inside:
                raise MatcapError(f"{p}: no .safetensors or .pytmodel files in this folder")
            files.extend(inside)
        elif p.is_file():
            files.append(p)
        else:
            raise MatcapError(f"{p}: no such weights file or folder")
    return files


def load_networks(weights: Sequence[str | os.PathLike] | None, device: str = "cpu") -> dict[str, "LoadedModel"]:
    """{"normal": LoadedModel, "brdf": LoadedModel (if given)} from ``--weights`` or the installed defaults."""
    out: dict[str, LoadedModel] = {}
    for f in resolve_weights(weights):
        loaded = load_network(f, device)
        target = loaded.config.target
        if target in out:
            raise MatcapError(f"two {target} models given: {out[target].path} and {f}")
        out[target] = loaded
    if "normal" not in out:
        raise MatcapError("--weights holds no normal model (a BRDF model alone cannot give normals)")
    return {k: out[k] for k in sorted(out, key=lambda t: t != "normal")}


def load_network(path: Path, device: str = "cpu") -> LoadedModel:
    """Load our safetensors weights or a published ``.pytmodel`` (never unpickled: ``weights_only=True``)."""

    from networks.checkpoint import import_published, load_model
    from networks.model import SDMUniPS

    if path.suffix == ".pytmodel":
        config, state = import_published(path)
        model = SDMUniPS(config)
        model.load_state_dict(state, strict=True)
        model = model.to(device)
        card = {"name": path.name, "source": "published SDM-UniPS checkpoint",
                "license": "MIT with a non-commercial clause (Ikehata); not redistributable"}
    else:
        model, config, card = load_model(path, device=device)
    model.eval()
    return LoadedModel(model, config, card or {}, str(path))


# ------------------------------------------------------------------------------------------- geometry


@dataclass
class _Frame:
    """How the original image maps into the square network input."""

    box: tuple[int, int, int, int]  # y0, y1, x0, x1 of the crop in the original image
    pad: tuple[int, int]  # (top, left) padding inside the square of side `side`
    side: int  # square side before resizing
    size: int  # network input side
    scale: float  # size / side (1 when padded instead of resized)


def _plan(shape: tuple[int, int], mask: np.ndarray | None, native: int, margin: int = 8) -> _Frame:
    h, w = shape
    if mask is not None:
        ys, xs = np.nonzero(mask)
        y0, y1 = max(int(ys.min()) - margin, 0), min(int(ys.max()) + 1 + margin, h)
        x0, x1 = max(int(xs.min()) - margin, 0), min(int(xs.max()) + 1 + margin, w)
    else:
        y0, y1, x0, x1 = 0, h, 0, w
    side = max(y1 - y0, x1 - x0)
    pad = ((side - (y1 - y0)) // 2, (side - (x1 - x0)) // 2)
    if side <= native:
        size, scale = native, native / side
    else:  # larger than native: pad to a multiple of native and run the scalable (polyphase) mode
        size = int(np.ceil(side / native)) * native
        pad = (pad[0] + (size - side) // 2, pad[1] + (size - side) // 2)
        side, scale = size, 1.0
    return _Frame((y0, y1, x0, x1), pad, side, size, scale)


def _to_square(arr: np.ndarray, fr: _Frame, interp: str) -> np.ndarray:
    import cv2

    y0, y1, x0, x1 = fr.box
    crop = arr[y0:y1, x0:x1]
    out = np.zeros((fr.side, fr.side) + arr.shape[2:], dtype=arr.dtype)
    out[fr.pad[0] : fr.pad[0] + crop.shape[0], fr.pad[1] : fr.pad[1] + crop.shape[1]] = crop
    if fr.size != fr.side:
        flag = cv2.INTER_CUBIC if interp == "cubic" else cv2.INTER_NEAREST
        out = cv2.resize(out, (fr.size, fr.size), interpolation=flag)
    return out


def _from_square(arr: np.ndarray, fr: _Frame, shape: tuple[int, int]) -> np.ndarray:
    import cv2

    if fr.size != fr.side:
        arr = cv2.resize(arr, (fr.side, fr.side), interpolation=cv2.INTER_CUBIC)
    y0, y1, x0, x1 = fr.box
    crop = arr[fr.pad[0] : fr.pad[0] + (y1 - y0), fr.pad[1] : fr.pad[1] + (x1 - x0)]
    out = np.zeros(tuple(shape) + arr.shape[2:], dtype=np.float32)
    out[y0:y1, x0:x1] = crop
    return out


def _native_side(config) -> int:
    """Side of the network input at inference: the training resolution recorded by `matcap train`, else the
    published 512 (= 2 x canonical)."""
    return int(config.extra.get("native_resolution", 2 * config.canonical_resolution))


# ------------------------------------------------------------------------------------------- estimate


def estimate(
    images: Sequence[np.ndarray],
    mask: np.ndarray | None = None,
    *,
    weights: Sequence[str | os.PathLike] | None = None,
    max_images: int | None = None,
    seed: int = 0,
    device: str = "cpu",
    pixel_samples: int | None = None,
    bf16: bool = False,
    views: int = 1,
    progress: bool | Callable[[str, int, int], None] = False,
    models: dict[str, LoadedModel] | None = None,
) -> MaterialMaps:
    """Recover SVBRDF maps from photos of one scene under different lights.

    images: sequence of (H, W, 3) float32 linear RGB (at least 2); mask: (H, W) bool or None (whole image).
    ``views`` (1, 2, 4 or 8) averages the networks' predictions over that many mirrored / transposed copies of the
    input (test-time augmentation, ``networks.inference.predict_views``; costs ``views`` times the time).
    Returns :class:`MaterialMaps` at (H, W); BRDF maps only when a BRDF model is available. ``meta`` records the
    model, settings and timings.
    """
    import torch

    from networks.inference import bf16_is_native, predict, predict_scalable, predict_views
    from networks.preprocess import normalize_images

    if len(images) < 2:
        raise MatcapError(f"photometric stereo needs at least 2 images, got {len(images)}")
    shape = images[0].shape[:2]
    for i, im in enumerate(images):
        if im.ndim != 3 or im.shape[2] != 3 or im.shape[:2] != shape:
            raise MatcapError(f"image {i} has shape {im.shape}, expected {shape + (3,)}")
    if mask is not None and mask.shape != shape:
        raise MatcapError(f"mask has shape {mask.shape}, expected {shape}")
    if bf16 and not bf16_is_native(device):
        import sys

        print(f"warning: --bf16: this CPU has no bfloat16 instructions ({torch.backends.cpu.get_cpu_capability()}), "
              "so bf16 is emulated and several times slower than the default float32: drop --bf16",
              file=sys.stderr)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if models is None:
        models = load_networks(weights, device)
    timings["load_s"] = time.perf_counter() - t0

    order = np.arange(len(images))
    if max_images is not None and max_images < len(images):
        if max_images < 2:
            raise MatcapError(f"--max-images must be at least 2, got {max_images}")
        order = np.sort(np.random.default_rng(seed).choice(len(images), size=max_images, replace=False))
    full_mask = mask if mask is not None else np.ones(shape, dtype=bool)

    results: dict[str, np.ndarray] = {}
    settings: dict[str, Any] = {}
    for target, loaded in models.items():
        t1 = time.perf_counter()
        native = _native_side(loaded.config)
        fr = _plan(shape, mask, native)
        stack = np.stack([_to_square(images[i], fr, "cubic") for i in order])  # (N, S, S, 3)
        msq = _to_square(full_mask.astype(np.uint8), fr, "nearest") > 0
        x = torch.from_numpy(np.clip(stack, 0, None)).permute(0, 3, 1, 2).float().to(device)
        m = torch.from_numpy(msq).to(device)
        x = normalize_images(x, m.float().unsqueeze(0))
        cb = None
        if progress:
            cb = _progress_callback(target, progress)
        kwargs = dict(
            pixel_samples=pixel_samples, seed=seed, progress=cb,
            autocast_dtype=torch.bfloat16 if bf16 else None,
        )
        if fr.size > native:
            run = functools.partial(predict_scalable, loaded.model, decoder_resolution=native)
        else:
            run = functools.partial(predict, loaded.model)
        with torch.inference_mode():
            out = predict_views(run, x, m, views=views, **kwargs)
        if target == "normal":
            n = _from_square(out["normal"], fr, shape)
            length = np.linalg.norm(n, axis=2, keepdims=True)
            valid = full_mask & (length[:, :, 0] > 0.5)
            results["normal"] = np.where(valid[:, :, None], n / np.maximum(length, 1e-8), 0.0).astype(np.float32)
            results["mask"] = valid
        else:
            for key in ("base_color", "roughness", "metallic"):
                results[key] = np.clip(_from_square(out[key], fr, shape), 0.0, 1.0)
        timings[f"{target}_s"] = time.perf_counter() - t1
        settings[target] = {"input_side": fr.size, "scalable": fr.size > native, "native_side": native,
                            "crop_box_yyxx": list(fr.box), "weights": loaded.path, "card": loaded.card}
    timings["total_s"] = time.perf_counter() - t0
    mask_out = results["mask"]
    for key in ("base_color", "roughness", "metallic"):
        if key in results:
            v = results[key]
            results[key] = np.where(mask_out[..., None] if v.ndim == 3 else mask_out, v, 0.0).astype(np.float32)
    meta = {
        "images_used": [int(i) for i in order],
        "seed": seed, "device": device, "bf16": bf16, "views": views, "pixel_samples": pixel_samples,
        "models": settings, "timings": timings,
    }
    return MaterialMaps(
        normal=results["normal"], mask=mask_out, base_color=results.get("base_color"),
        roughness=results.get("roughness"), metallic=results.get("metallic"), meta=meta,
    )


#: A flat sample's photos longer than this (pixels, the longer side) meet the networks as a copy of this size,
#: whose maps are upsampled as the start of the fit at the photos' full size (which makes the detail).
FLAT_NETWORK_SIDE = 1024


def network_maps(images: Sequence[np.ndarray], mask: np.ndarray | None, flat: bool | None, refine: bool,
                 **estimate_kwargs) -> MaterialMaps:
    """The networks' maps (:func:`estimate`) of ``images`` (K, (H, W, 3) linear RGB), at (H, W).

    For a flat sample with the fit to follow (``refine``; ``flat`` True, or None and
    :func:`matcap.refine.flat.check_flat` finds the copy's normals flat), photos longer than
    :data:`FLAT_NETWORK_SIDE` are seen by the networks as a copy of that size, and the maps upsampled (normals
    renormalised): their detail is the fit's to find, and the networks' time grows with the pixel count.
    ``meta["network_size_wh"]`` records the size they saw.
    """
    h, w = images[0].shape[:2]
    if refine and flat is not False and max(h, w) > FLAT_NETWORK_SIDE:
        small_images, small_mask = downscale_arrays(list(images), mask, FLAT_NETWORK_SIDE)
        small = estimate(small_images, small_mask, **estimate_kwargs)
        if flat or flat_choice(None, small)[0]:
            return _upsampled(small, (h, w), mask)
    maps = estimate(images, mask, **estimate_kwargs)  # an object: the networks see every pixel
    maps.meta["network_size_wh"] = [w, h]
    return maps


def _upsampled(small: MaterialMaps, size_hw: tuple[int, int], mask: np.ndarray | None) -> MaterialMaps:
    """``small``'s maps at (H, W) = ``size_hw``: normals by :func:`upscale_normals`, the others bilinear; the
    mask is the small one's (nearest) within ``mask`` (H, W) where given."""
    import cv2

    h, w = size_hw
    sh, sw = small.shape
    valid = cv2.resize(small.mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    full = valid if mask is None else valid & mask

    def up(a: np.ndarray | None) -> np.ndarray | None:
        if a is None:
            return None
        out = np.clip(cv2.resize(a, (w, h), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
        return out * (full[..., None] if out.ndim == 3 else full)

    return MaterialMaps(normal=upscale_normals(small.normal, (h, w), full), mask=full,
                        base_color=up(small.base_color), roughness=up(small.roughness), metallic=up(small.metallic),
                        meta={**small.meta, "network_size_wh": [sw, sh]})


def _progress_callback(target: str, progress):
    if callable(progress):
        return lambda done, total: progress(target, done, total)
    from networks.progress import progress as progress_bar

    bar = progress_bar(total=None, desc=f"{target} network", unit="px", leave=False)

    def cb(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
        bar.n = done
        bar.refresh()
        if done >= total:
            bar.close()

    return cb


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


def _relight_requests(relight) -> list[dict[str, Any]]:
    """``relight`` of :func:`capture` as a list of keyword dicts for :func:`matcap.relight.plan`."""
    if relight is None:
        return []
    if isinstance(relight, (str, os.PathLike, dict)):
        relight = [relight]
    out = []
    for item in relight:
        if isinstance(item, dict):
            out.append(dict(item))
        elif isinstance(item, (str, os.PathLike)):
            out.append({"env": item})
        else:
            raise MatcapError(f"relight entries must be an environment map path or a dict of relight settings, "
                              f"got {type(item).__name__}")
    return out


def _export_request(export, out: Path, overwrite: bool) -> dict[str, Any] | None:
    """``export`` of :func:`capture` as keyword arguments of :func:`matcap.export.export` (``out`` included)."""
    if export is None:
        return None
    request = {"out": export} if isinstance(export, (str, os.PathLike)) else dict(export)
    if "out" not in request:
        raise MatcapError("export settings need an output folder: export={'out': DIR, ...}")
    request.setdefault("name", Path(out).name)
    request.setdefault("overwrite", overwrite)
    return request


def capture(
    folder: str | os.PathLike,
    out: str | os.PathLike,
    *,
    mask: str | os.PathLike | None = None,
    linear: bool | None = False,
    contrast: float = 1.0,
    overwrite: bool = False,
    constants: dict[str, float] | None = None,
    max_side: int | None = None,
    relight=None,
    export=None,
    refine: bool = False,
    refine_settings=None,
    lights: str | os.PathLike | None = None,
    ball: str | os.PathLike | None = None,
    flat: bool | None = None,
    on_fit=None,
    **estimate_kwargs,
) -> tuple[MaterialMaps, Path]:
    """Read ``folder``, estimate the maps and write a result folder (see :mod:`matcap.results`); then, optionally,
    relight and export them: the whole chain of ``matcap capture``.

    ``constants`` (e.g. ``{"metallic": 0.0}``) replaces estimated roughness / metallic maps by constants on the mask
    (recorded in ``capture.json`` as ``constant_maps``). ``max_side`` shrinks the photos first so that their
    longer side is at most that many pixels (a quick pass over large photos; maps come out at that size).
    ``linear=None`` with ``refine``: 8-bit photos are decoded as the fit decides (:func:`decide_colour`; recorded
    in capture.json ``colour_decision``); ``contrast`` > 1: sRGB after undoing a camera tone curve of that
    contrast (:func:`matcap.imageio.tone_curve`; not with ``linear=True``; nothing is decided then).
    ``refine`` fits lights and maps to the photos after the networks (:mod:`matcap.refine`; ``refine_settings``
    a :class:`matcap.refine.RefineSettings`) and adds lights.json, fit.json, residual.png, light_variation.png;
    ``lights``: a light file (:mod:`matcap.lightfiles`) whose lights the fit holds instead of estimating them;
    ``ball``: "auto" or a mask file of a mirror ball inside the photos: the lights come from its highlights
    (:mod:`matcap.calibrate`), the ball is kept out of the object's mask and ``calibration.png`` is written.
    ``flat``: the photos show a flat sample facing the camera (True), not (False), or decide from the networks'
    normals (None: :func:`matcap.refine.flat.check_flat`); a flat sample's lamps, unless given, are found from
    their falloff over the plane (recorded in capture.json as ``flat``).
    ``on_fit(result, settings)``: called once the fit is done (:func:`refine_maps`).
    ``relight``: an environment map path, or a dict of :func:`matcap.relight.relight` settings (``env``,
    ``point``, ``spp``, ``size`` ...), or a list of them; each renders ``relight_<name>.exr/.png`` into the result
    folder. ``export``: a folder, or a dict of :func:`matcap.export.export` settings with ``out`` (``preset``,
    ``normal`` ...; ``name`` defaults to the result folder's name, ``overwrite`` to this call's). Every setting
    (env maps read once, spp, preset, output folders) is checked before the networks run.
    Returns the maps and the result folder.
    """
    from matcap import relight as relighting
    from matcap.export import check_options
    from matcap.export import export as export_maps
    from matcap.results import check_not_replacing_inputs, check_output_dir, write_result

    constants = {name: check_constant(name, value) for name, value in (constants or {}).items()}
    contrast = imageio.check_contrast(contrast)
    linear_given = linear is not None or contrast != 1.0  # --linear / --srgb / --tone-curve said it
    if contrast != 1.0:  # a tone curve given: sRGB photos, nothing left to decide
        if linear:
            raise MatcapError("--tone-curve undoes a camera's curve over sRGB; it contradicts --linear")
        linear = False
    if max_side is not None:
        check_max_side(max_side)  # fail before the expensive part
    max_images = estimate_kwargs.pop("max_images", None)
    seed = estimate_kwargs.get("seed", 0)
    known = None
    if lights is not None or ball is not None:
        if not refine:
            raise MatcapError(f"{'a light file' if lights is not None else 'a mirror ball'} gives the fit its lights; "
                              f"it has no use without the fit")
        if lights is not None and ball is not None:
            raise MatcapError("a light file and a mirror ball both give the lights; choose one")
    if flat and not refine:
        raise MatcapError("a flat sample's lamps are found by the fit of the photos; without the fit there is nothing "
                          "to take as flat")
    picked = pick_images(len(photo_names(folder)), max_images, seed)  # as load_capture picks them
    if flat and lights is None and ball is None and len(picked) < 3:
        raise MatcapError(f"a flat sample's lamps are found from at least 3 photos, got {len(picked)}")
    if lights is not None:
        known = read_lights_for(lights, folder, picked)
    check_output_dir(out, overwrite)  # fail before the expensive part
    check_not_replacing_inputs(out, folder, mask)  # --overwrite replaces the out folder: never the photos in it
    plans = [relighting.plan(**request) for request in _relight_requests(relight)]
    names = [name for p in plans for name in p.names]
    if len(set(names)) != len(names):
        raise MatcapError("two relight renders have the same name; rename an environment map")
    export_request = _export_request(export, Path(out), overwrite)
    if export_request is not None:
        check_options(**export_request)
    # --max-side and --max-images act while reading: photos are shrunk one by one and unused ones never decoded
    calibration = ball_region = None
    if ball is not None:
        known, calibration, ball_region = ball_lights(folder, ball, linear, contrast, max_side, max_images, seed)
    colour_decision, cap, maps, lamps = None, None, None, None
    if refine and linear is None:  # neither --linear nor --srgb: let the fit decide for 8-bit photos
        t0 = time.perf_counter()
        linear, colour_decision, cap, maps, lamps = decide_colour(folder, mask, max_side, refine_settings,
                                                                  dict(estimate_kwargs, max_images=max_images),
                                                                  known, exclude=ball_region, flat=flat)
        if colour_decision is not None:
            colour_decision["seconds"] = round(time.perf_counter() - t0, 3)
    linear = bool(linear)  # None without the fit: sRGB, the default
    if cap is None:
        cap = without_region(load_capture(folder, mask=mask, linear=linear, max_side=max_side,
                                           max_images=max_images, seed=seed, contrast=contrast), ball_region)
    original_wh = list(cap.photo_size_wh)
    if flat:
        from matcap.refine.flat import check_plane_mask

        check_plane_mask(cap.mask if cap.mask is not None else np.ones(cap.images[0].shape[:2], bool))
    if maps is None:
        maps = network_maps(cap.images, cap.mask, flat, refine, **estimate_kwargs)
    else:  # the decision's sRGB prediction: the same call, made once
        maps = dataclasses.replace(maps, meta=dict(maps.meta))
    flat_record = None
    if refine:
        flat, flat_record = flat_choice(flat, maps)
    maps = maps.with_constants(constants)
    if colour_decision is not None:  # its quick fits ran before the networks' timed call
        maps.meta["timings"] = dict(maps.meta.get("timings", {}), colour_decision_s=colour_decision["seconds"])
    used = [cap.files[i] for i in maps.meta["images_used"]]
    refine_writer = None
    if refine:
        used_lights = None if known is None else known.subset(maps.meta["images_used"])
        found = None if lamps is None or not flat else lamps.of(maps.meta["images_used"], maps.mask)
        maps, refine_writer = refine_maps(maps, [cap.images[i] for i in maps.meta["images_used"]], used,
                                          cap.colour, refine_settings, constants,
                                          progress=bool(estimate_kwargs.get("progress")), seed=seed,
                                          device=estimate_kwargs.get("device", "cpu"), lights=used_lights,
                                          flat=flat, found_lamps=found, on_fit=on_fit)
    maps.meta["images_used"] = [cap.picked[i] for i in maps.meta["images_used"]]  # indices among all the photos
    maps.meta.update(
        {
            "tool": "matcap capture",
            "input_folder": str(Path(folder).resolve()),
            "inputs": used,
            "mask_file": cap.mask_file,
            "skipped_files": cap.skipped,
            "colour_handling": cap.colour,
            "decoding": decoding_record(cap, linear, "fit" if colour_decision else "flag" if linear_given else
                                        "default", contrast),
            **({"tone_curve_contrast": contrast} if contrast != 1.0 and "8-bit" in cap.colour else {}),
            **({"colour_decision": colour_decision} if colour_decision else {}),
            "image_size_wh": [cap.images[0].shape[1], cap.images[0].shape[0]],
            "photo_size_wh": original_wh,  # image_size_wh differs from it after --max-side
            **({"ball": calibration.document_fields()["ball"]} if calibration is not None else {}),
            **({"flat": flat_record} if flat_record is not None else {}),
        }
    )

    def finish(folder: Path) -> list[str]:
        """Runs before the result folder is swapped into place: the refinement's files and the renders are part
        of the atomic result, and the export is done (itself atomically) before the result appears, so a run
        killed at any point leaves either nothing or everything."""
        written = list(refine_writer(folder)) if refine_writer is not None else []
        if calibration is not None:
            from matcap.calibrate import DIAGNOSTIC, diagnostic_image

            imageio.write_png(folder / DIAGNOSTIC, diagnostic_image(calibration, cap.images), bits=8)
            written.append(DIAGNOSTIC)
        for p in plans:
            relighting.render_plan(maps, p, out=folder, overwrite=True)
        if export_request is not None:
            export_maps(maps, **export_request)
        return written + [f"relight_{name}{suffix}" for p in plans for name in p.names for suffix in (".exr", ".png")]

    write_result(maps, out, overwrite=overwrite, extra_files=finish)
    return maps, Path(out)


#: A capture is taken as a flat sample without being told only where it has at least this many photos.
FLAT_MIN_PHOTOS = 4


def flat_choice(flat: bool | None, maps: MaterialMaps) -> tuple[bool, dict[str, Any]]:
    """(whether the fit takes the capture as a flat sample, capture.json ``flat``): ``flat`` as given (True / False:
    the user said it), or, for None, :func:`matcap.refine.flat.check_flat` on the networks' normals (and at least
    ``FLAT_MIN_PHOTOS`` photos)."""
    from matcap.refine.flat import check_flat

    found = check_flat(maps.normal, maps.mask)
    detected = found.flat and len(maps.meta.get("images_used", ())) >= FLAT_MIN_PHOTOS
    record = {"flat": bool(detected if flat is None else flat), "chosen_by": "detection" if flat is None else "flag",
              "coverage": found.coverage, "tilt_mean_deg": found.tilt_mean_deg, "tilt_p90_deg": found.tilt_p90_deg}
    if flat is None:
        record["why"] = found.describe()
    return record["flat"], record


def without_region(cap: Capture, region: np.ndarray | None) -> Capture:
    """``cap`` with the pixels ``region`` (H, W) bool kept out of its mask (a mirror ball in the frame)."""
    if region is None:
        return cap
    if region.shape != cap.images[0].shape[:2]:
        raise MatcapError(f"the ball's region is {region.shape[1]}x{region.shape[0]} but the photos are "
                          f"{cap.images[0].shape[1]}x{cap.images[0].shape[0]}")
    base = cap.mask if cap.mask is not None else np.ones(region.shape, bool)
    mask = base & ~region
    if not mask.any():
        raise MatcapError("the mask holds nothing but the mirror ball")
    return dataclasses.replace(cap, mask=mask)


def ball_lights(folder, ball: str | os.PathLike, linear: bool | None, contrast: float, max_side: int | None,
                max_images: int | None, seed: int):
    """(KnownLights of the photos read, :class:`matcap.calibrate.Calibration`, the ball's region (H, W) bool) from
    a mirror ball inside the capture's own photos (``ball``: "auto", or a mask file of the ball). The highlights
    are found on the photos as decoded (8-bit as linear unless --srgb: the decoding moves no highlight); the
    relative intensities are kept only where the photos are linear."""
    from matcap.calibrate import calibrate, read_ball_mask
    from matcap.lightfiles import KnownLights

    cap = load_capture(folder, linear=linear is not False, max_side=max_side, max_images=max_images, seed=seed,
                       contrast=contrast)
    ball_mask = None
    if str(ball) != "auto":
        full = cap.photo_size_wh[::-1]
        ball_mask = read_ball_mask(ball, full)
        if tuple(full) != cap.images[0].shape[:2]:
            ball_mask = _shrink(ball_mask.astype(np.float32), cap.images[0].shape[1::-1]) > 0.5
    cal = calibrate(cap.images, ball_mask=ball_mask, names=cap.files)
    linear_photos = "8-bit sRGB" not in cap.colour
    known = KnownLights(cal.directions, cal.intensities if linear_photos else None, "ball",
                        f"mirror ball in {Path(folder).name}", "order")
    return known, cal, cal.ball_mask()


def decoding_record(cap: Capture, linear: bool | None, chosen_by: str, contrast: float = 1.0) -> dict[str, Any]:
    """capture.json ``decoding``: how the photos became linear light, as fields. ``8bit``: "linear" or "srgb"
    (None when no photo is 8-bit); ``tone_curve_contrast``: the camera curve undone (1: none); ``chosen_by``:
    "flag" (--linear / --srgb / --tone-curve), "fit" (the colour decision) or "default" (sRGB)."""
    eight = "8-bit" in cap.colour
    return {"8bit": ("linear" if linear else "srgb") if eight else None,
            "tone_curve_contrast": contrast if eight else 1.0, "chosen_by": chosen_by if eight else "flag"}


@dataclass(frozen=True)
class FoundLamps:
    """A flat sample's lamps found from its photos: ``result``, what :func:`matcap.refine.flat.flat_lights`
    returned (:class:`matcap.refine.flat.FlatLights`) for the photos ``images`` (indices among those read) over
    ``mask`` ((H, W) bool)."""

    result: FlatLights
    images: tuple[int, ...]
    mask: np.ndarray

    def of(self, images: Sequence[int], mask: np.ndarray) -> FlatLights | None:
        """``result`` where it was found from the photos ``images`` over ``mask``, else None."""
        return self.result if tuple(images) == self.images and np.array_equal(mask, self.mask) else None


def decide_colour(folder, mask, max_side, settings, estimate_kwargs, known=None, pixels: int = 6000,
                  exclude: np.ndarray | None = None, flat: bool | None = None):
    """(linear?, record, capture, maps, lamps) for 8-bit photos given neither --linear nor --srgb: run the networks
    on the sRGB-decoded photos, fit both decodings (a quick fit on ``pixels`` random object pixels) and keep the one
    whose re-render is closer to the photos *as stored* (RMS in 8-bit units / 255). ``capture`` is the photos read
    the chosen way; ``maps`` the networks' maps when they were made from those photos (sRGB chosen), else None, so
    the caller reads and predicts nothing twice. 16-bit and float photos: (False, None, capture, None, None).
    ``known``: the :class:`matcap.lightfiles.KnownLights` of the photos read, held by both quick fits; ``exclude``:
    (H, W) pixels kept out of the mask (a mirror ball); ``flat``: as :func:`capture` (a flat sample's lamps are
    found from each decoding's photos over the whole sample, then held by its quick fit). ``lamps``: the chosen
    decoding's :class:`FoundLamps` where they were found, else None, so that the fit need not find them again."""
    from matcap.refine import RefineSettings, refine
    from networks.progress import progress as progress_bar

    shown = estimate_kwargs.get("progress") is True
    kwargs = dict(estimate_kwargs)  # the networks' stages show their own progress, as in any capture
    max_images = kwargs.pop("max_images", None)
    caps = {lin: without_region(load_capture(folder, mask=mask, linear=lin, max_side=max_side, max_images=max_images,
                                             seed=kwargs.get("seed", 0)), exclude) for lin in (False, True)}
    if "8-bit" not in caps[False].colour:
        return False, None, caps[False], None, None
    maps = network_maps(caps[False].images, caps[False].mask, flat, True, **kwargs)
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(maps.mask)
    pick = rng.choice(len(ys), size=min(len(ys), pixels), replace=False)
    sub = np.zeros_like(maps.mask)
    sub[ys[pick], xs[pick]] = True
    maps_sub = dataclasses.replace(maps, mask=sub)
    base = settings if settings is not None else RefineSettings()
    quick = base.replace({"lights.iters": min(base.lights.iters, 200), "pixels.coarse_iters": 0,
                          "pixels.fine_iters": min(base.pixels.fine_iters, 10)})
    rmse, found = {}, {}
    flat, _ = flat_choice(flat, maps)
    bar = progress_bar(total=len(caps), desc="colour decision", unit="decoding", enabled=shown)
    for lin, cap in caps.items():
        images = [cap.images[i] for i in maps.meta["images_used"]]
        held = None if known is None else known.subset(maps.meta["images_used"])
        if held is None and flat:
            from matcap.refine.flat import flat_lights

            lamps_bar = progress_bar(total=3, desc=f"flat lamps ({'linear' if lin else 'sRGB'})", unit="step",
                                     enabled=shown)
            found[lin] = FoundLamps(flat_lights(images, maps.mask, on_stage=lambda: lamps_bar.update(1)),
                                    tuple(maps.meta["images_used"]), maps.mask)
            lamps_bar.close()
            held = found[lin].result.lights
        res = refine(images, maps_sub, quick, lights=held)
        pred = np.clip(res.prediction[:, sub], 0.0, 1.0)
        photo = np.stack([im[sub] for im in images])
        if not lin:
            pred, photo = imageio.linear_to_srgb(pred), imageio.linear_to_srgb(np.clip(photo, 0.0, 1.0))
        rmse[lin] = float(np.sqrt(((pred - photo) ** 2).mean()))
        bar.update(1)
    bar.close()
    linear = rmse[True] < rmse[False]
    record = {"chosen": "linear" if linear else "srgb", "rms_8bit_linear": round(rmse[True], 5),
              "rms_8bit_srgb": round(rmse[False], 5),
              "how": "quick refinement of both decodings on a pixel subsample; RMS of the re-render against the "
                     "stored 8-bit values / 255"}
    return linear, record, caps[linear], None if linear else maps, found.get(linear)


def refine_maps(maps: MaterialMaps, images: list[np.ndarray], files: list[str], colour: str, settings=None,
                constants: dict[str, float] | None = None, *, progress: bool = False, seed: int = 0,
                device: str = "cpu", lights=None, flat: bool = False, found_lamps: FlatLights | None = None,
                on_fit=None):
    """Run :func:`matcap.refine.refine` on ``maps`` (the networks' output) and the photos they came from.

    Returns ``(refined maps, writer)``: ``writer(folder)`` writes lights.json / fit.json / residual.png /
    light_variation.png and returns their names. The network maps stay recorded only in capture.json's summary
    (``refine.normal_change_deg_mean``); the ``constants`` maps stay constant.
    ``lights``: :class:`matcap.lightfiles.KnownLights` of ``images`` (held by the fit), or None (estimated).
    ``on_fit(result, settings)``: called with the :class:`matcap.refine.RefineResult` (its warning, the reasons in
    its report, the candidate light models judged) and the settings it ran with, as soon as the fit is done.
    ``flat``, ``found_lamps``: a flat sample (:func:`matcap.refine.refine`'s).
    """
    from matcap.refine import RefineSettings, refine
    from matcap.refine.outputs import write_refine_outputs

    s = settings if settings is not None else RefineSettings(seed=seed, device=device)
    held: dict[str, float | int] = {f"priors.{'metal' if k == 'metallic' else 'rough'}": 1e4
                                     for k in (constants or {})}
    if "roughness" in (constants or {}):
        held["roughness.choose"] = False  # no roughness to choose (the metallic vote stays)
    if "metallic" in (constants or {}):
        held["roughness.metallic_hold"] = 0.0  # no metallic to vote on
    if held:  # constant maps stay where the caller put them
        s = s.replace(held)
    result = refine(images, maps, s, progress=progress, lights=lights, flat=flat, found_lamps=found_lamps)
    if on_fit is not None:
        on_fit(result, s)
    lin = result.report.get("linear") or {}
    refined = result.maps.with_constants(constants or {})
    refined.meta = dict(maps.meta)
    r = result.report
    refined.meta["refine"] = {
        # the fit's record of the lights it held (known, from a ball, or a flat sample's found lamps): what the
        # file gave and what the fit did with it (its ambient given, fitted or none)
        "lights": r.get("lights", {"source": "estimated"}),
        "psnr_db_mean": r["psnr_db_mean"], "normal_change_deg_mean": r["normal_change_deg_mean"],
        "light_model": (r["lights"]["kind"] if "lights" in r else
                        "point" if lin.get("check") == "near lamps" else s.model.light),  # what was fitted
        "seconds": r["timings"]["total_s"],
        "weak_light_variation_fraction": r["light_variation"]["weak_fraction"],
        "kept_network_maps": r["kept_network_maps"],
        **({"flat_lamps": r["flat"]["lamps"]} if "flat" in r and "lamps" in r["flat"] else {}),
        "files": ["lights.json", "fit.json", "residual.png", "light_variation.png"],
    }
    refined.meta["timings"] = dict(maps.meta.get("timings", {}), refine_s=r["timings"]["total_s"])

    def writer(folder):
        return write_refine_outputs(folder, result, files, colour,
                                    source=lights.source if lights is not None else "estimated")

    return refined, writer


def parse_constants(items: list[str] | None) -> dict[str, float]:
    """``["metallic=0", "roughness=0.4"]`` -> ``{"metallic": 0.0, "roughness": 0.4}`` (``--constant``)."""
    out: dict[str, float] = {}
    for item in items or []:
        name, _, text = item.partition("=")
        try:
            out[name.strip()] = check_constant(name.strip(), float(text))
        except ValueError:
            raise MatcapError(f"--constant {item!r}: expected roughness=V or metallic=V with V in [0, 1]") from None
    return out

"""The networks' stage of a capture: the SDM-UniPS networks (normal, + BRDF when available) loaded from their
weights and run on the photos.

:func:`estimate`: choose up to K images -> crop to the mask's box, pad (never squash) to a square, resize to the
network's native side (or pad to a multiple of it and use the scalable polyphase mode for larger inputs) ->
normalise -> the networks -> undo the geometry -> :class:`MaterialMaps`. :func:`network_maps` is the capture's call
(a large flat sample's networks see a smaller copy). torch loads only when a network is loaded or run.
"""
from __future__ import annotations

import functools
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from matcap.errors import MatcapError
from matcap.photos import downscale_arrays, upscale_normals
from scenes.materialmaps import MaterialMaps

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "networks" / "weights"
DEFAULT_WEIGHTS = {"normal": WEIGHTS_DIR / "normal_small.safetensors", "brdf": WEIGHTS_DIR / "brdf_small.safetensors"}


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
    from matcap.refine.flat import flat_choice  # the capture's rule for taking photos as a flat sample

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
    """``small``'s maps at (H, W) = ``size_hw``: normals by :func:`~matcap.photos.upscale_normals`, the others
    bilinear; the mask is the small one's (nearest) within ``mask`` (H, W) where given."""
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

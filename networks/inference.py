"""Whole-object inference: every mask pixel predicted in sample sets, plus the published "scalable" mode."""
from __future__ import annotations

import contextlib
from typing import Callable

import numpy as np
import torch

from networks.dihedral import DIHEDRAL, transform_images, untransform_map
from networks.model import SDMUniPS

Progress = Callable[[int, int], None]


def check_device(name: str) -> torch.device:
    """``torch.device(name)``, or a one-line ``ValueError`` for a name torch rejects or CUDA it does not have."""
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"--device {name!r}: not a torch device (e.g. cpu, cuda, cuda:1)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available in this torch build")
    return device


def bf16_is_native(device: str | torch.device = "cpu") -> bool:
    """Whether bfloat16 matrix products run in hardware on ``device``: always assumed on GPUs; on a CPU only with
    AVX512-BF16 or AMX (oneDNN's own check). Without it bf16 is emulated and much slower than float32 (measured on
    an AVX2-only EPYC: the ``small`` network at 512², K=16 took 317 s in bf16 against 58 s in fp32)."""
    if torch.device(device).type != "cpu":
        return True
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # an older / different torch build: say native, as before
        return True


def _check(model: SDMUniPS, images: torch.Tensor, mask: torch.Tensor, multiple: int) -> None:
    if not isinstance(images, torch.Tensor) or images.dim() != 4 or images.shape[1] != 3:
        shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ValueError(f"images must be a tensor of shape (N, 3, S, S), got {shape}")
    n, _, h, w = images.shape
    if h != w or h == 0 or h % multiple:
        raise ValueError(f"images must be square with a side that is a multiple of {multiple}, got {tuple(images.shape)}")
    if not isinstance(mask, torch.Tensor) or tuple(mask.shape) != (h, w):
        shape = tuple(mask.shape) if isinstance(mask, (torch.Tensor, np.ndarray)) else type(mask).__name__
        raise ValueError(f"mask must be a tensor of shape ({h}, {w}) to match images, got {shape}")
    if not images.is_floating_point():
        raise ValueError(f"images must be floating point, got {images.dtype}")


def split_sample_sets(count: int, m: int) -> list[int]:
    """Sizes of the sample sets for ``count`` pixels and set size ``m``: one set when count <= m, else
    ``count // m + 1`` near-equal sets (the first ``count % k`` one larger, like ``numpy.array_split``)."""
    if count <= m:
        return [count] if count else []
    k = count // m + 1
    base, extra = divmod(count, k)
    return [base + 1] * extra + [base] * (k - extra)


def _empty_maps(model: SDMUniPS, s: int) -> dict[str, np.ndarray]:
    out = {"normal": np.zeros((s, s, 3), np.float32)}
    if model.config.target == "brdf":
        out["base_color"] = np.zeros((s, s, 3), np.float32)
        out["roughness"] = np.zeros((s, s), np.float32)
        out["metallic"] = np.zeros((s, s), np.float32)
    return out


@contextlib.contextmanager
def _eval_mode(model: torch.nn.Module):
    was = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was)


def _autocast(device: torch.device, dtype: torch.dtype | None):
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def predict(model: SDMUniPS, images: torch.Tensor, mask: torch.Tensor, *, pixel_samples: int | None = None,
            seed: int = 0, progress: Progress | None = None, autocast_dtype: torch.dtype | None = None,
            _done_offset: int = 0, _total: int | None = None) -> dict[str, np.ndarray]:
    """Predict the maps of ONE object at its own resolution (decoder resolution = S).

    images: (N, 3, S, S) float (linear, already normalised, S a multiple of the canonical resolution), on the device
    to run on; mask: (S, S) bool (or 0/1). Mask pixels are shuffled with a ``torch.Generator`` seeded with ``seed``
    and split into sample sets of at most ``pixel_samples`` (default: ``model.config.pixel_samples``) pixels
    (:func:`split_sample_sets`); each set is one attention set in the regressor. ``progress(done, total)`` is
    called after each set with pixel counts. Returns float32 numpy maps: ``normal (S, S, 3)`` (unit inside the mask,
    zero outside) and for a BRDF network ``base_color (S, S, 3)``, ``roughness (S, S)``, ``metallic (S, S)``
    (zero outside the mask).
    """
    _check(model, images, mask, model.config.canonical_resolution)
    m = int(pixel_samples or model.config.pixel_samples)
    if m < 1:
        raise ValueError(f"pixel_samples must be >= 1, got {m}")
    n, _, s, _ = images.shape
    device = images.device
    mask_b = mask.to(device=device).bool()
    out = _empty_maps(model, s)
    ids = torch.nonzero(mask_b.reshape(-1), as_tuple=False).squeeze(1)
    total = _total if _total is not None else int(ids.numel())
    if ids.numel() == 0:
        return out
    g = torch.Generator(device="cpu").manual_seed(int(seed))
    ids = ids[torch.randperm(ids.numel(), generator=g).to(device)]
    sizes = split_sample_sets(int(ids.numel()), m)
    flat = {k: np.zeros((s * s, v.shape[2] if v.ndim == 3 else 1), np.float32) for k, v in out.items()}
    x = images[None]
    mk = mask_b[None, None].to(images.dtype)
    with _eval_mode(model), torch.inference_mode(), _autocast(device, autocast_dtype):
        feats = model.encode(x, mk)
        start = 0
        for size in sizes:
            sel = ids[start:start + size]
            res = model.decode(x, mk, feats, sel[None])
            sel_np = sel.cpu().numpy()
            for k in flat:
                flat[k][sel_np] = res[k][0].float().cpu().numpy()
            start += size
            if progress is not None:
                progress(_done_offset + start, total)
    for k, v in flat.items():
        out[k] = v.reshape(out[k].shape)
    return out


def predict_scalable(model: SDMUniPS, images: torch.Tensor, mask: torch.Tensor, *, decoder_resolution: int = 512,
                     pixel_samples: int | None = None, seed: int = 0, progress: Progress | None = None,
                     autocast_dtype: torch.dtype | None = None) -> dict[str, np.ndarray]:
    """The published "scalable" mode for images larger than the decoder size.

    images: (N, 3, S, S) with S a multiple of ``decoder_resolution`` (itself a multiple of the canonical
    resolution); mask: (S, S). The input is split into s^2 polyphase sub-images ``x[a::s, b::s]`` (s = S /
    decoder_resolution), each predicted independently with :func:`predict` (same ``seed``), and the results are
    interleaved back. Memory is that of one decoder_resolution-sized prediction. Returns maps at S x S as in
    :func:`predict`.
    """
    g = model.config.canonical_resolution
    if decoder_resolution < g or decoder_resolution % g:
        raise ValueError(f"decoder_resolution must be a positive multiple of {g}, got {decoder_resolution}")
    _check(model, images, mask, decoder_resolution)
    s_full = images.shape[-1]
    s = s_full // decoder_resolution
    if s == 1:
        return predict(model, images, mask, pixel_samples=pixel_samples, seed=seed, progress=progress,
                       autocast_dtype=autocast_dtype)
    mask_b = mask.bool()
    total = int(mask_b.sum())
    out = _empty_maps(model, s_full)
    done = 0
    for a in range(s):
        for b in range(s):
            sub_mask = mask_b[a::s, b::s]
            count = int(sub_mask.sum())
            if count == 0:
                continue
            res = predict(model, images[:, :, a::s, b::s].contiguous(), sub_mask.contiguous(),
                          pixel_samples=pixel_samples, seed=seed, progress=progress, autocast_dtype=autocast_dtype,
                          _done_offset=done, _total=total)
            done += count
            for k, v in res.items():
                out[k][a::s, b::s] = v
    return out


# ------------------------------------------------------------------------------------ test-time augmentation
# DIHEDRAL, transform_images and untransform_map live in networks/dihedral.py (training shares them).


def predict_views(predict_fn: Callable[..., dict[str, np.ndarray]], images: torch.Tensor, mask: torch.Tensor,
                  views: int = 1, **kwargs) -> dict[str, np.ndarray]:
    """Test-time augmentation: run ``predict_fn`` (:func:`predict` or :func:`predict_scalable`) on ``views``
    mirrored / transposed copies of the input (:data:`DIHEDRAL`) and average the results in the original frame.

    images: (N, 3, S, S); mask: (S, S). Normals are summed and re-normalised; BRDF maps are averaged. ``views=1``
    is exactly ``predict_fn(images, mask, **kwargs)``. Cost: ``views`` times one prediction. A ``progress``
    callback in ``kwargs`` sees the pixel counts of all views one after another.
    """
    if views not in (1, 2, 4, 8):
        raise ValueError(f"views must be 1, 2, 4 or 8, got {views}")
    if views == 1:
        return predict_fn(images, mask, **kwargs)
    progress = kwargs.pop("progress", None)
    total = int(mask.bool().sum()) * views
    acc: dict[str, np.ndarray] | None = None
    for i, t in enumerate(DIHEDRAL[:views]):
        cb = None
        if progress is not None:
            cb = (lambda done, _tot, _off=i * total // views: progress(_off + done, total))
        res = predict_fn(transform_images(images, t), transform_images(mask, t), progress=cb, **kwargs)
        res = {k: untransform_map(v, t, normal=(k == "normal")) for k, v in res.items()}
        if acc is None:
            acc = res
        else:
            for k in acc:
                acc[k] = acc[k] + res[k]
    assert acc is not None
    n = acc["normal"]
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    acc["normal"] = np.where(length > 1e-6, n / np.maximum(length, 1e-12), 0.0).astype(np.float32)
    for k in acc:
        if k != "normal":
            acc[k] = (acc[k] / views).astype(np.float32)
    return acc

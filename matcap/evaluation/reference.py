"""Check our SDM-UniPS implementation against a reference run (``matcap reference-check CASE.npz``).

The case (``CASE.npz`` + ``CASE.json`` with the same stem) holds images, mask and the outputs of the published
network loaded with the SPEC's deterministic weights (salt in the JSON). We build the same weights for our
``paper`` networks (normal and brdf), run them with the case's settings and compare.

Preprocessing: the reference outputs were produced from the images exactly as stored (``uint16 / 1024``) with the
mask, *without* the test-time per-image normalisation (max over mask pixels of the per-pixel RGB mean). Measured on
case_a: raw input gives a 0.002 deg mean normal difference, the normalised input 1.7 deg - so the case is a network
check, not an end-to-end pipeline check.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

NORMAL_MEAN_DEG = 0.01
NORMAL_MAX_DEG = 0.1
BRDF_REL = 1e-3


@dataclass(frozen=True)
class CheckResult:
    normal_mean_deg: float
    normal_max_deg: float
    brdf_max_rel: float

    @property
    def ok(self) -> bool:
        return (self.normal_mean_deg <= NORMAL_MEAN_DEG and self.normal_max_deg <= NORMAL_MAX_DEG
                and self.brdf_max_rel <= BRDF_REL)

    def line(self) -> str:
        return (f"normal_mean_deg={self.normal_mean_deg:.5f} normal_max_deg={self.normal_max_deg:.5f} "
                f"brdf_max_rel={self.brdf_max_rel:.2e}")


def load_case(path: str | Path):
    """(arrays, settings) of a reference case; ValueError / FileNotFoundError (one line) for a bad one."""
    import numpy as np

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such case file: {path}")
    meta_path = path.with_suffix(".json")
    if not meta_path.is_file():
        raise FileNotFoundError(f"missing {meta_path.name} next to {path.name}")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{meta_path} is not valid JSON: {exc}") from None
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError/OSError/BadZipFile/AttributeError (a .npy)
        raise ValueError(f"{path}: not a readable .npz case file ({type(exc).__name__})") from None
    need = {"images", "mask", "normal"}
    if not need <= set(data):
        raise ValueError(f"{path} lacks arrays {sorted(need - set(data))}")
    if not isinstance(meta, dict):
        raise ValueError(f"{meta_path}: expected a JSON object, got a {type(meta).__name__}")
    for key in ("salt", "canonical_resolution", "decoder_resolution", "pixel_samples"):
        if key not in meta:
            raise ValueError(f"{meta_path} lacks '{key}'")
    for key in ("canonical_resolution", "decoder_resolution", "pixel_samples"):
        try:
            ok = int(meta[key]) >= 1
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{meta_path}: '{key}' must be a positive whole number, got {meta[key]!r}")
    images = data["images"]
    if images.ndim != 4 or images.shape[-1] != 3 or images.shape[1] != images.shape[2]:
        raise ValueError(f"case images must have shape (N, S, S, 3), got {images.shape}")
    return data, meta


def compare(ours: dict, ref: dict, mask) -> tuple[float, float, float]:
    """(normal mean deg, normal max deg over mask pixels, worst BRDF |diff| / max|ref| over the BRDF maps)."""
    import numpy as np

    n = ours["normal"][mask].astype(np.float64)
    r = ref["normal"][mask].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    r /= np.maximum(np.linalg.norm(r, axis=-1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip((n * r).sum(-1), -1.0, 1.0)))
    rel = 0.0
    for key in ("base_color", "roughness", "metallic"):
        if key not in ref:
            continue
        a = np.asarray(ours[key], np.float64)
        b = np.asarray(ref[key], np.float64)
        scale = max(float(np.abs(b).max()), 1e-12)
        rel = max(rel, float(np.abs(a - b).max()) / scale)
    return float(ang.mean()), float(ang.max()), rel


def check_case(path: str | Path, device: str = "cpu", threads: int = 0) -> CheckResult:
    """Run our paper-size networks with the case's deterministic weights and compare with its stored outputs."""
    import numpy as np
    import torch

    from networks.checkpoint import reference_weights
    from networks.config import get_config
    from networks.inference import check_device, predict
    from networks.model import build_model

    if threads < 0:
        raise ValueError(f"--threads must be 0 (torch's choice) or more, got {threads}")
    check_device(device)
    if threads:
        torch.set_num_threads(threads)
    path = Path(path)
    data, meta = load_case(path)
    manifest_path = path.parent / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else None

    dev = torch.device(device)
    images = torch.from_numpy(data["images"].astype(np.float32) / 1024.0).permute(0, 3, 1, 2).contiguous()
    mask_np = data["mask"] > 0
    side = images.shape[-1]
    dres = int(meta["decoder_resolution"])
    if side != dres:
        raise ValueError(f"case images are {side}x{side} but decoder_resolution is {dres}; unsupported case")
    images = images.to(dev)
    mask = torch.from_numpy(mask_np).to(dev)

    outputs: dict = {}
    targets = ["normal"] + (["brdf"] if "base_color" in data else [])
    for target in targets:
        cfg = get_config("paper", target)
        cfg.canonical_resolution = int(meta["canonical_resolution"])
        cfg.pixel_samples = int(meta["pixel_samples"])
        cfg.validate()
        weights = reference_weights(cfg, str(meta["salt"]), manifest[target] if manifest else None)
        model = build_model(cfg, weights).to(dev).eval()
        res = predict(model, images, mask, pixel_samples=cfg.pixel_samples, seed=0)
        if target == "normal":
            outputs["normal"] = res["normal"]
        else:
            outputs.update({k: res[k] for k in ("base_color", "roughness", "metallic")})
        del model
    return CheckResult(*compare(outputs, data, mask_np))

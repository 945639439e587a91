"""fp32 equality of the fast inference path with the implementation it replaced.

Two kinds of checks, no timings:
- ``tests/data/speed_reference.npz``: outputs of :func:`networks.inference.predict` written by the code of commit
  f87ac8c (before any speed work) for three fixed cases (deterministic weights, salt "speed"; a shaded sphere,
  seed 5, several sample sets). Today's code must give the same maps: normals within 0.01 deg mean / 0.1 deg max,
  BRDF maps within 1e-3 of their largest value (the SPEC's tolerances for the published reference).
- the same functions with :func:`networks.model.reference_ops` (the straightforward forms: explicit attention,
  per-image K/V in the PMA, convolution smoothing, NCHW UPerNet) against the fast forms on random inputs.
Regenerate the stored file (only if the network itself changes): ``python tests/test_networks_speed_equality.py``.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from networks.checkpoint import reference_weights  # noqa: E402
from networks.config import SDMUniPSConfig, get_config  # noqa: E402
from networks.inference import predict  # noqa: E402
from networks.model import PMA, build_model, gaussian_smooth, reference_ops  # noqa: E402

STORED = REPO / "tests" / "data" / "speed_reference.npz"

# name: (preset, target, side, K, sphere radius / side, pixel_samples); seed 5 for the pixel order
CASES = {
    "small_normal": ("small", "normal", 512, 4, 0.09, 2000),
    "small_brdf": ("small", "brdf", 256, 3, 0.15, 5000),
    "paper_normal": ("paper", "normal", 512, 3, 0.06, 1000),
}


def make_object(side: int, k: int, radius: float, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A sphere (radius ``radius * side``) with a diffuse + specular lobe under K random lights and random
    per-image colours: images (K, 3, S, S) float32 normalised to a max mean of 1, mask (S, S) bool."""
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    x = (xx + 0.5 - side / 2) / (radius * side)
    y = -(yy + 0.5 - side / 2) / (radius * side)
    mask = x * x + y * y < 1.0
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))
    normal = np.stack([x, y, z], -1) * mask[..., None]
    light = rng.normal(size=(k, 3))
    light[:, 2] = np.abs(light[:, 2]) + 0.5
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    albedo = rng.uniform(0.3, 0.9, size=(k, 3))
    shade = np.clip(np.einsum("hwc,kc->khw", normal, light), 0.0, None)
    images = (shade[:, None] * albedo[:, :, None, None] + 0.5 * shade[:, None] ** 20) * mask
    images /= images.reshape(k, 3, -1).mean(1).max() + 1e-6
    return images.astype(np.float32), mask


def run_case(name: str) -> dict[str, np.ndarray]:
    """predict() for one case; returns each map at the mask pixels (row-major order)."""
    preset, target, side, k, radius, m = CASES[name]
    cfg = get_config(preset, target)
    model = build_model(cfg, reference_weights(cfg, "speed")).eval()
    images, mask = make_object(side, k, radius)
    res = predict(model, torch.from_numpy(images), torch.from_numpy(mask), pixel_samples=m, seed=5)
    return {key: v[mask].astype(np.float32) for key, v in res.items()}


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors (..., 3), accurate near 0 (atan2 of |a x b| and a.b, in float64)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def _compare(ours: dict, ref: dict) -> None:
    ang = angle_deg(ours["normal"], ref["normal"])
    assert ang.mean() < 0.01 and ang.max() < 0.1, (ang.mean(), ang.max())
    for key in ours:
        if key != "normal":
            scale = max(float(np.abs(ref[key]).max()), 1e-6)
            assert np.abs(ours[key] - ref[key]).max() <= 1e-3 * scale, key


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n.startswith("paper") else n
                                  for n in CASES])
def test_predict_matches_outputs_stored_before_the_speed_work(name):
    stored = np.load(STORED)
    ref = {key.split("/", 1)[1]: stored[key] for key in stored.files if key.startswith(name + "/")}
    ours = run_case(name)
    assert set(ours) == set(ref)
    _compare(ours, ref)
    # the comparison can fail: a normal map rotated by 0.2 deg is refused
    c, s = np.cos(np.radians(0.2)), np.sin(np.radians(0.2))
    rotated = ref["normal"] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32).T
    with pytest.raises(AssertionError):
        _compare(dict(ours, normal=rotated), ref)


@pytest.mark.parametrize("target,side", [("normal", 64), ("brdf", 128)])
def test_fast_forward_equals_reference_ops(target, side):
    """encode + decode (several sample sets of a tiny network, random weights) with and without reference_ops."""
    cfg = get_config("tiny", target)
    model = build_model(cfg, reference_weights(cfg, "eq")).eval()
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 3, 3, side, side, generator=g)
    mask = (torch.rand(1, 1, side, side, generator=g) > 0.3).float()
    idx = torch.randperm(side * side, generator=g)[:600][None]
    with torch.inference_mode():
        fa = model.encode(x, mask)
        fast = model.decode(x, mask, fa, idx)
        with reference_ops():
            fb = model.encode(x, mask)
            ref = model.decode(x, mask, fb, idx)
    assert torch.allclose(fa, fb, atol=1e-5, rtol=1e-4)
    _compare({k: v[0].numpy() for k, v in fast.items()}, {k: v[0].numpy() for k, v in ref.items()})
    assert np.abs(fast["normal"].numpy() - ref["normal"].numpy()).max() < 1e-4


def test_pma_pooling_equals_attention_of_the_seed():
    torch.manual_seed(0)
    pma = PMA(32, 8, 48, scale=0.2, dropout=0.1).double().eval()
    x = torch.randn(50, 7, 32, dtype=torch.float64)
    with torch.no_grad():
        with reference_ops():
            ref = pma(x)
        ours = pma(x)
    assert ours.shape == ref.shape == (50, 1, 32)
    assert torch.allclose(ours, ref, atol=1e-12)


@pytest.mark.parametrize("channels_last", [False, True])
def test_gaussian_smoothing_band_matrices_equal_convolution(channels_last):
    x = torch.rand(2, 5, 24, 24, dtype=torch.float64)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    with reference_ops():
        ref = gaussian_smooth(x, 21, 1.0)
    ours = gaussian_smooth(x, 21, 1.0)
    assert torch.allclose(ours, ref, atol=1e-12)
    assert ours.is_contiguous(memory_format=torch.channels_last) == channels_last or not channels_last


if __name__ == "__main__":
    torch.set_num_threads(2)
    out = {}
    with reference_ops():
        for case in CASES:
            for key, value in run_case(case).items():
                out[f"{case}/{key}"] = value
    np.savez_compressed(STORED, **out)
    print(f"wrote {STORED}")


def test_bf16_fp32_stages_by_preset():
    """paper keeps glc_upsample, the PMA and the regressor in fp32 under bf16, the other presets the PMA and the
    regressor; a config can name its own; unknown names are refused."""
    assert get_config("paper").resolved_bf16_fp32_stages() == ("glc_upsample", "glc_aggregation.pma", "regressor")
    assert get_config("small").resolved_bf16_fp32_stages() == ("glc_aggregation.pma", "regressor")
    assert get_config("tiny").resolved_bf16_fp32_stages() == ("glc_aggregation.pma", "regressor")
    own = dataclasses.replace(get_config("small"), bf16_fp32_stages=["glc_upsample"])
    assert own.resolved_bf16_fp32_stages() == ("glc_upsample",)
    assert SDMUniPSConfig.from_json(own.to_json()) == own
    assert build_model(dataclasses.replace(get_config("tiny"), bf16_fp32_stages=())).fp32_under_autocast == ()
    with pytest.raises(ValueError, match="bf16_fp32_stages"):
        dataclasses.replace(get_config("tiny"), bf16_fp32_stages=("heads",))
    model = build_model(get_config("tiny"), reference_weights(get_config("tiny"), "eq")).eval()
    seen = {}
    model.regressor.comm.register_forward_hook(lambda mod, inp, out: seen.__setitem__("out", out.dtype))
    model.glc_upsample.register_forward_hook(lambda mod, inp, out: seen.__setitem__("up", out.dtype))
    with torch.autocast("cpu", dtype=torch.bfloat16), torch.inference_mode():
        out = model(torch.rand(1, 2, 3, 64, 64), torch.ones(1, 1, 64, 64), torch.arange(100)[None])
    assert seen == {"out": torch.float32, "up": torch.bfloat16}
    assert out["normal"].dtype == torch.float32


def test_bf16_inference_keeps_the_listed_decoder_stages_in_fp32():
    """Under bf16 autocast at inference the listed stages (here glc_upsample and the PMA pooling,
    model.fp32_under_autocast) return float32; the other stages run in bf16; training keeps autocast everywhere."""
    cfg = dataclasses.replace(get_config("tiny", "normal"), bf16_fp32_stages=("glc_upsample", "glc_aggregation.pma"))
    model = build_model(cfg, reference_weights(cfg, "eq"))
    assert model.fp32_under_autocast == ("glc_upsample", "glc_aggregation.pma")
    seen = {}
    for name, mod in (("glc_upsample", model.glc_upsample), ("aggregation SABs", model.glc_aggregation.aggregation.enc),
                      ("pma", model.glc_aggregation.aggregation.dec[0]), ("regressor", model.regressor.comm)):
        mod.register_forward_hook(lambda mod, inp, out, name=name: seen.__setitem__(name, (inp[0].dtype, out.dtype)))
    x = torch.rand(1, 2, 3, 64, 64)
    mask = torch.ones(1, 1, 64, 64)
    idx = torch.arange(100)[None]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        with torch.inference_mode():
            model.eval()(x, mask, idx)
        assert seen["glc_upsample"] == (torch.float32, torch.float32)
        assert seen["regressor"][1] == torch.bfloat16  # not listed here: runs in bf16
        assert seen["pma"] == (torch.bfloat16, torch.float32)
        assert seen["aggregation SABs"][1] == torch.bfloat16
        model.train()(x, mask, idx)
        assert seen["glc_upsample"][1] == torch.bfloat16

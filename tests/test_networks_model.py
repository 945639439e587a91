"""SDM-UniPS model: published shapes, tiny forward passes, input checks."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from networks.config import SDMUniPSConfig, get_config
from networks.model import SDMUniPS, gaussian_kernel_1d, gaussian_smooth

torch.set_num_threads(1)
SHARED = Path(__file__).resolve().parents[1].parent / "shared"
MANIFEST = SHARED / "reference" / "sdm_unips" / "manifest.json"


def _tiny(target="normal", seed=0):
    torch.manual_seed(seed)
    return SDMUniPS(get_config("tiny", target)).eval()


def _inputs(b=2, n=3, side=64, seed=1):
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(b, n, 3, side, side, generator=g)
    mask = (torch.rand(b, 1, side, side, generator=g) > 0.3).float()
    idx = torch.randint(0, side * side, (b, 50), generator=g)
    return images, mask, idx


@pytest.mark.parametrize("target", ["normal", "brdf"])
def test_paper_state_dict_matches_manifest(target):
    if not MANIFEST.is_file():
        pytest.skip(f"reference manifest not found at {MANIFEST}")
    manifest = json.loads(MANIFEST.read_text())[target]
    with torch.device("meta"):
        model = SDMUniPS(get_config("paper", target))
    ours = [[k, list(v.shape)] for k, v in model.state_dict().items()]
    assert ours == manifest  # same keys, shapes and order
    assert len(ours) == {"normal": 373, "brdf": 385}[target]
    if target == "normal":
        assert sum(v.numel() for v in model.state_dict().values()) == 62_753_711


@pytest.mark.parametrize("target", ["normal", "brdf"])
def test_tiny_forward_shapes_and_unit_normals(target):
    model = _tiny(target)
    images, mask, idx = _inputs()
    with torch.no_grad():
        out = model(images, mask, idx)
    expected = {"normal": 3} if target == "normal" else {"normal": 3, "base_color": 3, "roughness": 1, "metallic": 1}
    assert {k: tuple(v.shape) for k, v in out.items()} == {k: (2, 50, c) for k, c in expected.items()}
    assert torch.allclose(out["normal"].norm(dim=-1), torch.ones(2, 50), atol=1e-5)
    for k in expected:
        assert out[k].dtype == torch.float32 and torch.isfinite(out[k]).all()
        if k != "normal":
            assert (out[k] >= 0).all()  # ReLU on the BRDF heads


def test_unclamped_brdf_outputs_are_the_heads_before_their_relu():
    model = _tiny("brdf", seed=4)
    images, mask, idx = _inputs()
    with torch.no_grad():
        clamped = model(images, mask, idx)
        raw = model(images, mask, idx, clamp=False)
    for key in ("base_color", "roughness", "metallic"):
        assert torch.equal(torch.relu(raw[key]), clamped[key])
    assert torch.equal(raw["normal"], clamped["normal"])
    # a random tiny net puts some outputs below zero: there the loss on raw outputs still has a gradient
    assert any(bool((raw[k] < 0).any()) for k in ("base_color", "roughness", "metallic"))


def test_encode_shape_and_decode_consistency():
    model = _tiny()
    images, mask, idx = _inputs(side=64)
    with torch.no_grad():
        feats = model.encode(images, mask)
        assert tuple(feats.shape) == (2, 3, 16, 16, 16)  # (B, N, C, H/4, W/4)
        a = model.decode(images, mask, feats, idx)["normal"]
        b = model(images, mask, idx)["normal"]
    assert torch.equal(a, b)


def test_determinism_and_dropout_only_in_training():
    images, mask, idx = _inputs()
    m1, m2 = _tiny(seed=5), _tiny(seed=5)
    with torch.no_grad():
        a = m1(images, mask, idx)["normal"]
        b = m2(images, mask, idx)["normal"]
        c = m1(images, mask, idx)["normal"]
    assert torch.equal(a, b) and torch.equal(a, c)
    m1.train()
    torch.manual_seed(0)
    with torch.no_grad():
        d = m1(images, mask, idx)["normal"]
    assert not torch.allclose(a, d)  # dropout active in train mode


def test_pixel_set_is_one_attention_set():
    """Every pixel of a row attends to the others: changing one pixel's inputs moves the others' outputs."""
    model = _tiny()
    images, mask, idx = _inputs(b=1)
    with torch.no_grad():
        a = model(images, mask, idx)["normal"]
        b = model(images, mask, torch.cat([idx[:, :49], (idx[:, 49:] + 7) % 4096], dim=1))["normal"]
    assert not torch.allclose(a[0, :49], b[0, :49])


def test_backward_and_autocast():
    model = _tiny("brdf")
    model.train()
    images, mask, idx = _inputs()
    out = model(images, mask, idx)
    loss = sum(v.mean() for v in out.values())
    loss.backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    model.eval()
    with torch.no_grad():
        ref = model(images, mask, idx)["normal"]
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = model(images, mask, idx)["normal"]
    assert low.dtype == torch.float32
    cos = (ref * low).sum(-1).clamp(-1, 1)
    assert torch.rad2deg(torch.acos(cos)).mean() < 5.0


@pytest.mark.parametrize(
    "images_shape, mask_shape, match",
    [
        ((2, 3, 64, 64), (2, 1, 64, 64), r"\(2, 3, 64, 64\)"),  # missing N axis
        ((2, 3, 3, 64, 48), (2, 1, 64, 48), r"\(2, 3, 3, 64, 48\)"),  # not square
        ((2, 3, 3, 40, 40), (2, 1, 40, 40), r"\(2, 3, 3, 40, 40\)"),  # not a multiple of G=32
        ((2, 3, 3, 64, 64), (2, 64, 64), r"\(2, 64, 64\)"),  # mask without channel axis
    ],
)
def test_bad_shapes_raise_value_error_naming_the_shape(images_shape, mask_shape, match):
    model = _tiny()
    with pytest.raises(ValueError, match=match):
        model(torch.rand(images_shape), torch.ones(mask_shape), torch.zeros(2, 5, dtype=torch.long))


def test_bad_pixel_index():
    model = _tiny()
    images, mask, _ = _inputs()
    with pytest.raises(ValueError, match=r"\(2, 5, 1\)"):
        model(images, mask, torch.zeros(2, 5, 1, dtype=torch.long))
    with pytest.raises(ValueError, match="4096"):
        model(images, mask, torch.full((2, 5), 4096))


def test_gaussian_smoothing_matches_2d_kernel():
    x = torch.rand(2, 3, 20, 20, dtype=torch.float64)
    k1 = gaussian_kernel_1d(21, 1.0)
    k2 = torch.outer(k1, k1)
    ref = torch.nn.functional.conv2d(x.reshape(6, 1, 20, 20), k2.view(1, 1, 21, 21), padding=10).reshape(2, 3, 20, 20)
    assert torch.allclose(gaussian_smooth(x, 21, 1.0), ref, atol=1e-12)
    assert abs(k2.sum().item() - 1.0) < 1e-12
    assert SDMUniPS(get_config("tiny")).smoothing_kernel_size(64) == 21  # 10 * (64 // 32) + 1


def test_config_round_trip_and_presets():
    for name in ("paper", "small", "tiny"):
        for target in ("normal", "brdf"):
            cfg = get_config(name, target)
            assert SDMUniPSConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ValueError, match="unknown preset"):
        get_config("huge")
    with pytest.raises(ValueError, match="target"):
        get_config("paper", "albedo")
    with pytest.raises(ValueError, match="unknown SDMUniPSConfig fields"):
        SDMUniPSConfig.from_dict({"nope": 1})
    small = sum(p.numel() for p in SDMUniPS(get_config("small")).parameters())
    assert small < 62_753_711 / 5


@pytest.mark.parametrize("lk", [3, 16, 65, 200])
def test_attention_short_and_long_paths_match_fused_kernel(lk):
    """The explicit short-sequence attention and the fused kernel agree (values and gradients)."""
    from networks.model import SHORT_SEQUENCE, attention

    g = torch.Generator().manual_seed(lk)
    q, k, v = (torch.randn(5, 4, 7 if i == 0 else lk, 12, generator=g, dtype=torch.float64, requires_grad=True)
               for i in range(3))
    ours = attention(q, k, v, 0.3)
    ref = torch.nn.functional.scaled_dot_product_attention(q, k, v, scale=0.3)
    assert (lk <= SHORT_SEQUENCE) == (lk < 65)
    assert torch.allclose(ours, ref, atol=1e-12)
    g1 = torch.autograd.grad(ours.square().sum(), (q, k, v))
    g2 = torch.autograd.grad(ref.square().sum(), (q, k, v))
    for a, b in zip(g1, g2):
        assert torch.allclose(a, b, atol=1e-10)

"""Whole-object inference (sample sets, scalable mode) and the reference check on case_a."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from networks.config import get_config
from networks.inference import predict, predict_scalable, split_sample_sets
from networks.model import SDMUniPS

torch.set_num_threads(1)
SHARED = Path(__file__).resolve().parents[1].parent / "shared"
CASE_A = SHARED / "reference" / "sdm_unips" / "case_a.npz"


def _model(target="normal"):
    torch.manual_seed(0)
    return SDMUniPS(get_config("tiny", target)).eval()


def _object(side=64, n=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(n, 3, side, side, generator=g)
    yy, xx = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    mask = ((yy - side / 2) ** 2 + (xx - side / 2) ** 2) < (0.4 * side) ** 2
    return images, mask


def test_split_sample_sets():
    assert split_sample_sets(6357, 10000) == [6357]
    assert split_sample_sets(10000, 10000) == [10000]
    assert split_sample_sets(20000, 10000) == [6667, 6667, 6666]  # 20000 // 10000 + 1 = 3 sets
    assert split_sample_sets(10001, 10000) == [5001, 5000]
    assert split_sample_sets(0, 5) == []


@pytest.mark.parametrize("target", ["normal", "brdf"])
def test_predict_shapes_mask_and_progress(target):
    model = _model(target)
    images, mask = _object()
    calls = []
    out = predict(model, images, mask, pixel_samples=500, progress=lambda d, t: calls.append((d, t)))
    count = int(mask.sum())
    assert len(calls) == len(split_sample_sets(count, 500)) and calls[-1] == (count, count)
    shapes = {"normal": (64, 64, 3), "base_color": (64, 64, 3), "roughness": (64, 64), "metallic": (64, 64)}
    assert {k: v.shape for k, v in out.items()} == {k: shapes[k] for k in out}
    assert set(out) == ({"normal"} if target == "normal" else set(shapes))
    m = mask.numpy()
    assert all(v.dtype == np.float32 for v in out.values())
    assert np.allclose(np.linalg.norm(out["normal"][m], axis=-1), 1.0, atol=1e-5)
    for v in out.values():
        assert not v[~m].any()


def test_predict_seed_and_single_set_matches_decode():
    model = _model()
    images, mask = _object()
    a = predict(model, images, mask, pixel_samples=300, seed=1)
    b = predict(model, images, mask, pixel_samples=300, seed=1)
    c = predict(model, images, mask, pixel_samples=300, seed=2)
    assert np.array_equal(a["normal"], b["normal"]) and not np.array_equal(a["normal"], c["normal"])
    # one set (m >= mask pixels): the result does not depend on the order -> seeds agree; equals decode()
    d = predict(model, images, mask, pixel_samples=10000, seed=1)
    e = predict(model, images, mask, pixel_samples=10000, seed=7)
    assert np.allclose(d["normal"], e["normal"], atol=1e-5)
    idx = torch.nonzero(mask.reshape(-1)).squeeze(1)[None]
    with torch.no_grad():
        ref = model(images[None], mask[None, None].float(), idx)["normal"][0].numpy()
    assert np.allclose(d["normal"].reshape(-1, 3)[idx[0].numpy()], ref, atol=1e-5)


def test_predict_rejects_bad_shapes():
    model = _model()
    images, mask = _object()
    with pytest.raises(ValueError, match=r"\(1, 3, 3, 64, 64\)"):
        predict(model, images[None], mask)
    with pytest.raises(ValueError, match=r"\(32, 32\)"):
        predict(model, images, mask[:32, :32])
    with pytest.raises(ValueError, match=r"\(3, 3, 48, 48\)"):
        predict(model, images[:, :, :48, :48], mask[:48, :48])


def test_predict_scalable():
    model = _model("brdf")
    images, mask = _object(side=128)
    out = predict_scalable(model, images, mask, decoder_resolution=64, pixel_samples=400)
    m = mask.numpy()
    assert out["normal"].shape == (128, 128, 3) and out["roughness"].shape == (128, 128)
    assert np.allclose(np.linalg.norm(out["normal"][m], axis=-1), 1.0, atol=1e-5)
    for v in out.values():
        assert not v[~m].any()
    # each polyphase sub-image is an independent prediction
    sub = predict(model, images[:, :, 1::2, 0::2].contiguous(), mask[1::2, 0::2].contiguous(), pixel_samples=400)
    assert np.array_equal(out["normal"][1::2, 0::2], sub["normal"])
    with pytest.raises(ValueError, match="multiple of 64"):
        predict_scalable(model, images[:, :, :96, :96], mask[:96, :96], decoder_resolution=64)


@pytest.mark.slow
def test_reference_check_case_a(capsys):
    if not CASE_A.is_file():
        pytest.skip(f"reference case not found at {CASE_A}")
    from matcap.cli import main

    torch.set_num_threads(2)
    try:
        code = main(["reference-check", str(CASE_A)])
    finally:
        torch.set_num_threads(1)
    line = capsys.readouterr().out.strip()
    assert line.startswith("normal_mean_deg=") and "brdf_max_rel=" in line
    values = dict(kv.split("=") for kv in line.split())
    assert float(values["normal_mean_deg"]) <= 0.01
    assert float(values["normal_max_deg"]) <= 0.1
    assert float(values["brdf_max_rel"]) <= 1e-3
    assert code == 0

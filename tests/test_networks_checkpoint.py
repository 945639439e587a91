"""Weights: our safetensors format, published-checkpoint import, deterministic reference weights."""
from __future__ import annotations

import math
import pickle
import zlib

import pytest
import torch

from networks.checkpoint import (
    convert_published_state_dict,
    import_published,
    load_model,
    read_metadata,
    reference_weights,
    save_weights,
)
from networks.config import get_config
from networks.model import SDMUniPS

torch.set_num_threads(1)


def _inputs():
    g = torch.Generator().manual_seed(3)
    images = torch.rand(1, 2, 3, 32, 32, generator=g)
    mask = torch.ones(1, 1, 32, 32)
    idx = torch.randint(0, 1024, (1, 40), generator=g)
    return images, mask, idx


def _fake_published(target="normal"):
    """A published-style state dict of paper shapes; stride-0 tensors keep the file tiny."""
    with torch.device("meta"):
        model = SDMUniPS(get_config("paper", target))
    return {f"module.{k}": torch.full((1,), 0.5).expand(v.shape) for k, v in model.state_dict().items()}


@pytest.mark.parametrize("target", ["normal", "brdf"])
def test_round_trip(tmp_path, target):
    torch.manual_seed(0)
    cfg = get_config("tiny", target)
    model = SDMUniPS(cfg).eval()
    path = save_weights(tmp_path / "w.safetensors", model, cfg, card={"name": "t", "licence": "MIT"})
    loaded, cfg2, card = load_model(path)
    assert cfg2 == cfg and card == {"name": "t", "licence": "MIT"}
    assert not loaded.training
    images, mask, idx = _inputs()
    with torch.no_grad():
        a, b = model(images, mask, idx), loaded(images, mask, idx)
    # The weights come back bit for bit; the outputs agree to rounding (oneDNN may pick other kernels for tensors
    # loaded at another memory alignment, so exact output equality is not guaranteed).
    ours, theirs = model.state_dict(), loaded.state_dict()
    assert ours.keys() == theirs.keys()
    for k in ours:
        assert torch.equal(ours[k], theirs[k]), k
    assert a.keys() == b.keys()
    for k in a:
        assert (a[k] - b[k]).abs().max().item() < 1e-5, k
    assert read_metadata(path)[0] == cfg


def test_load_refuses_foreign_files(tmp_path):
    from safetensors.torch import save_file

    p = tmp_path / "plain.safetensors"
    save_file({"x": torch.zeros(2)}, str(p))
    with pytest.raises(ValueError, match="metadata"):
        load_model(p)
    q = tmp_path / "junk.safetensors"
    q.write_bytes(b"not a safetensors file at all")
    with pytest.raises(ValueError, match="not a safetensors file"):
        load_model(q)


def test_import_published_fake_file(tmp_path):
    p = tmp_path / "nml.pytmodel"
    torch.save(_fake_published("normal"), p)
    cfg, state = import_published(p)
    assert cfg.target == "normal" and cfg.preset == "paper"
    assert len(state) == 373 and not any(k.startswith("module.") for k in state)
    assert state["regressor.prediction_normal.regression.2.bias"].tolist() == [0.5, 0.5, 0.5]


def test_convert_detects_brdf_and_is_strict():
    sd = _fake_published("brdf")
    out = convert_published_state_dict(sd)
    assert len(out) == 385 and "regressor.prediction_metal.regression.2.bias" in out
    bad = dict(sd)
    bad["module.extra.weight"] = torch.zeros(1)
    with pytest.raises(ValueError, match="unexpected"):
        convert_published_state_dict(bad)
    no_prefix = {k[len("module."):]: v for k, v in sd.items()}
    with pytest.raises(ValueError, match="prefix"):
        convert_published_state_dict(no_prefix)
    wrong_shape = dict(sd)
    wrong_shape["module.regressor.prediction_base.regression.2.bias"] = torch.zeros(4)
    with pytest.raises(ValueError, match=r"\(4,\)"):
        convert_published_state_dict(wrong_shape)


class _Payload:
    def __reduce__(self):  # would run code under plain unpickling
        return (print, ("unpickled!",))


def test_import_refuses_wrong_and_pickled_files(tmp_path):
    wrong = tmp_path / "wrong.pytmodel"
    torch.save({"module.conv.weight": torch.zeros(3, 3)}, wrong)
    with pytest.raises(ValueError, match="does not match"):
        import_published(wrong)
    evil = tmp_path / "evil.pytmodel"
    torch.save({"module.x": _Payload()}, evil, pickle_module=pickle)
    with pytest.raises(ValueError, match="weights-only") as info:
        import_published(evil)
    assert "\n" not in str(info.value)
    garbage = tmp_path / "garbage.pytmodel"
    garbage.write_bytes(b"\x00garbage")
    with pytest.raises(ValueError):
        import_published(garbage)


def test_weights_cli_import(tmp_path, capsys):
    from matcap.cli import main

    src = tmp_path / "nml.pytmodel"
    torch.save(_fake_published("normal"), src)
    out = tmp_path / "out"
    assert main(["weights", "import", str(src), "--out", str(out)]) == 0
    cfg, card = read_metadata(out / "normal.safetensors")
    assert cfg.target == "normal" and "non-commercial" in card["license"]
    assert main(["weights", "import", str(src), "--out", str(out)]) == 2  # refuses to overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(["weights", "import", str(src), "--out", str(out), "--overwrite"]) == 0


def test_reference_weights_rule():
    cfg = get_config("tiny")
    w = reference_weights(cfg, "salt")
    with torch.device("meta"):
        keys = list(SDMUniPS(cfg).state_dict())
    assert list(w) == keys and all(v.dtype == torch.float32 for v in w.values())

    def draw(key, shape):
        g = torch.Generator().manual_seed(zlib.crc32(f"salt:{key}".encode()))
        return torch.randn(shape, generator=g, dtype=torch.float64)

    k1 = "regressor.comm.enc.0.mab.ln0.weight"
    assert torch.equal(w[k1], (0.1 * draw(k1, w[k1].shape) + 1.0).float())
    k2 = "regressor.comm.enc.0.mab.ln0.bias"
    assert torch.equal(w[k2], (0.1 * draw(k2, w[k2].shape)).float())
    k3 = "image_encoder.backbone.backbone.0.downsample_layers.0.0.weight"
    shape = w[k3].shape
    assert torch.equal(w[k3], (draw(k3, shape) / math.sqrt(math.prod(shape[1:]))).float())
    assert torch.equal(reference_weights(cfg, "salt")[k3], w[k3])
    with pytest.raises(AssertionError):
        reference_weights(cfg, "salt", manifest=[["x", [1]]])

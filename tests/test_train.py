"""Training: loss decreases, resume equals uninterrupted, DDP ranks agree, validation numbers, data sampling."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from networks.data import SampleSpec, SceneCache, draw_batch, list_scenes
from networks.trainconfig import TrainConfig


def _tc(data: Path, out: Path, **kw) -> TrainConfig:
    sample = SampleSpec(resolution=64, min_images=3, max_images=4, pixel_samples=128)
    base = dict(data=str(data), target="normal", preset="tiny", out=str(out), steps=6, batch=2, lr=2e-3,
                warmup_steps=2, log_every=1, checkpoint_every_s=1e9, val_every_s=1e9, sample=sample)
    base.update(kw)
    return TrainConfig(**base)


def _state(path: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    return load_file(str(path))


def test_draw_batch_is_a_pure_function_of_the_step(tiny_dataset):
    cache = SceneCache(list_scenes(tiny_dataset))
    spec = SampleSpec(resolution=32, pixel_samples=64)
    a = draw_batch(cache, spec, 2, seed=3, step=5)
    b = draw_batch(cache, spec, 2, seed=3, step=5)
    c = draw_batch(cache, spec, 2, seed=3, step=6)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert a["images"].shape[0] == 2 and a["images"].shape[2:] == (3, 32, 32)
    assert 3 <= a["images"].shape[1] <= 6
    assert not np.array_equal(a["pixel_index"], c["pixel_index"])
    # every sampled pixel lies in the loss mask and its normal is unit length
    flat = a["loss_mask"].reshape(2, -1)
    assert all(flat[i, a["pixel_index"][i]].all() for i in range(2))
    n = a["normal"].reshape(2, -1, 3)[0, a["pixel_index"][0]]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-3)


def test_micro_batches_are_drawn_apart_from_the_plain_batch(tiny_dataset):
    cache = SceneCache(list_scenes(tiny_dataset))
    spec = SampleSpec(resolution=32, pixel_samples=64)
    plain = draw_batch(cache, spec, 2, seed=3, step=5)
    zero = draw_batch(cache, spec, 2, seed=3, step=5, micro=0)
    one = draw_batch(cache, spec, 2, seed=3, step=5, micro=1)
    assert all(np.array_equal(plain[k], zero[k]) for k in plain)  # micro-batch 0 is the batch without accumulation
    assert not np.array_equal(plain["pixel_index"], one["pixel_index"])
    again = draw_batch(cache, spec, 2, seed=3, step=5, micro=1)
    assert all(np.array_equal(one[k], again[k]) for k in one)


def test_accumulated_micro_batches_step_like_one_big_batch(tiny_dataset, tmp_path, monkeypatch):
    """Two micro-batches of one sample each, gradients averaged, give the weights of one batch of both samples."""
    import networks.train as train_mod

    spec = SampleSpec(resolution=64, min_images=3, max_images=3, pixel_samples=128)
    pool = draw_batch(SceneCache(list_scenes(tiny_dataset)), spec, 2, seed=0, step=0)

    def fixed(cache, sample, batch, seed, step, rank=0, micro=0):
        return {k: v[micro * batch:(micro + 1) * batch].copy() for k, v in pool.items()}

    monkeypatch.setattr(train_mod, "draw_batch", fixed)
    common = dict(steps=3, dropout=0.0, sample=spec, threads=1)
    train_mod.train(_tc(tiny_dataset, tmp_path / "big", batch=2, **common), progress=False)
    train_mod.train(_tc(tiny_dataset, tmp_path / "micro", batch=1, accumulate=2, **common), progress=False)
    train_mod.train(_tc(tiny_dataset, tmp_path / "half", batch=1, **common), progress=False)
    big, micro, half = (_state(tmp_path / name / "last.safetensors") for name in ("big", "micro", "half"))
    worst = max(float((big[k] - micro[k]).abs().max()) for k in big)
    assert worst < 1e-5, worst
    # one sample alone moves the weights elsewhere (the comparison above can fail)
    assert max(float((big[k] - half[k]).abs().max()) for k in big) > 1e-3


def test_resume_equals_uninterrupted_with_accumulation(tiny_dataset, tmp_path):
    from networks.train import train

    train(_tc(tiny_dataset, tmp_path / "straight", steps=4, batch=1, accumulate=2), progress=False)
    train(_tc(tiny_dataset, tmp_path / "split", steps=2, batch=1, accumulate=2), progress=False)
    train(_tc(tiny_dataset, tmp_path / "split", steps=4, batch=1, accumulate=2), resume=True, progress=False)
    a, b = _state(tmp_path / "straight" / "last.safetensors"), _state(tmp_path / "split" / "last.safetensors")
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_accumulate_below_one_is_a_clear_error(tiny_dataset, tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "matcap", "train", "--data", str(tiny_dataset), "--preset", "tiny",
         "--out", str(tmp_path / "none"), "--accumulate", "0", "--steps", "1", "--quiet"],
        capture_output=True, text=True,
    )
    assert r.returncode == 2
    assert "--accumulate must be at least 1" in r.stderr and "Traceback" not in r.stderr


def test_dihedral_augmentation_is_an_exact_symmetry_of_the_plain_sample(tiny_dataset):
    from networks.data import draw_sample, load_scene
    from networks.dihedral import DIHEDRAL, transform_map

    scene = load_scene(list_scenes(tiny_dataset)[0])
    used = set()
    for seed in range(12):
        plain = draw_sample(scene, SampleSpec(resolution=32, pixel_samples=64, dihedral=False),
                            np.random.default_rng(seed))
        aug = draw_sample(scene, SampleSpec(resolution=32, pixel_samples=64), np.random.default_rng(seed))
        matches = []
        for t in DIHEDRAL:
            same = all(np.array_equal(transform_map(plain[k], t, normal=(k == "normal")), aug[k])
                       for k in ("normal", "loss_mask", "base_color", "roughness", "input_mask"))
            images = transform_map(plain["images"].transpose(2, 3, 0, 1), t).transpose(2, 3, 0, 1)
            if same and np.array_equal(images, aug["images"]):
                matches.append(t)
        assert matches, seed  # the augmented sample is the plain one under some symmetry
        used.add(matches[0])
        flat = aug["loss_mask"].ravel()
        assert flat[aug["pixel_index"]].all()
    assert len(used) >= 4  # and the symmetry is drawn at random


def test_loss_decreases(tiny_dataset, tmp_path):
    import json

    from networks.train import train

    train(_tc(tiny_dataset, tmp_path, steps=40, lr=3e-3), progress=False)
    losses = [json.loads(line)["loss"] for line in (tmp_path / "log.jsonl").read_text().splitlines()
              if json.loads(line)["event"] == "train"]
    assert len(losses) == 40
    assert np.mean(losses[-10:]) < 0.8 * np.mean(losses[:10]), (np.mean(losses[:10]), np.mean(losses[-10:]))


def test_resume_equals_uninterrupted(tiny_dataset, tmp_path):
    from networks.train import train

    train(_tc(tiny_dataset, tmp_path / "straight", steps=6), progress=False)
    train(_tc(tiny_dataset, tmp_path / "split", steps=3), progress=False)
    train(_tc(tiny_dataset, tmp_path / "split", steps=6), resume=True, progress=False)
    a, b = _state(tmp_path / "straight" / "last.safetensors"), _state(tmp_path / "split" / "last.safetensors")
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_sigterm_saves_a_checkpoint_that_resumes_exactly(tiny_dataset, tmp_path):
    import json
    import signal
    import time

    from networks.train import train

    out = tmp_path / "stopped"
    args = [sys.executable, "-m", "networks.train", "--data", str(tiny_dataset), "--preset", "tiny", "--out", str(out),
            "--steps", "100000", "--batch", "2", "--resolution", "64", "--pixel-samples", "128", "--min-images", "3",
            "--max-images", "4", "--lr", "2e-3", "--warmup-steps", "2", "--log-every", "1", "--threads", "1",
            "--quiet"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, OMP_NUM_THREADS="1"))
    log = out / "log.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and not (log.exists() and log.read_text().count("\n") >= 2):
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert "continue with --resume" in err and "Traceback" not in err
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert records[-1]["event"] == "stopped"
    stopped = records[-1]["step"]
    ckpt = torch.load(out / "checkpoint.pt", weights_only=True)
    assert ckpt["step"] == stopped
    # resuming from the signal's checkpoint lands on the same weights as an uninterrupted run
    sample = SampleSpec(resolution=64, min_images=3, max_images=4, pixel_samples=128)
    common = dict(steps=stopped + 2, threads=1, sample=sample)
    train(_tc(tiny_dataset, out, **common), resume=True, progress=False)
    train(_tc(tiny_dataset, tmp_path / "straight", **common), progress=False)
    a, b = _state(tmp_path / "straight" / "last.safetensors"), _state(out / "last.safetensors")
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_worker_processes_draw_the_same_batches(tiny_dataset, tmp_path):
    from networks.train import train

    train(_tc(tiny_dataset, tmp_path / "inline", steps=3), progress=False)
    train(_tc(tiny_dataset, tmp_path / "workers", steps=3, workers=2), progress=False)
    a, b = _state(tmp_path / "inline" / "last.safetensors"), _state(tmp_path / "workers" / "last.safetensors")
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_validation_reports_error_per_lighting_group(tiny_dataset, tiny_val_dataset, tmp_path):
    from networks.train import train

    result = train(_tc(tiny_dataset, tmp_path, steps=2, val_data=str(tiny_val_dataset)), progress=False)
    val = result["validation"]
    assert set(val) >= {"mae", "mae_directional", "mae_environment"}
    assert 0.0 < val["mae"] < 180.0
    assert (tmp_path / "best.safetensors").exists()


def test_resume_without_checkpoint_is_a_clear_error(tiny_dataset, tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "matcap", "train", "--data", str(tiny_dataset), "--preset", "tiny",
         "--out", str(tmp_path / "none"), "--resume", "--steps", "1", "--quiet"],
        capture_output=True, text=True,
    )
    assert r.returncode == 2
    assert "checkpoint.pt does not exist" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
@pytest.mark.parametrize("accumulate", [1, 2])
def test_ddp_two_processes_hold_identical_weights(tiny_dataset, tmp_path, accumulate):
    """With accumulation the gradients are averaged across processes on the last micro-batch only (no_sync)."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", f"--master_port={29533 + accumulate}",
           "-m", "networks.train", "--data", str(tiny_dataset), "--preset", "tiny", "--out", str(tmp_path),
           "--steps", "3", "--batch", "1", "--accumulate", str(accumulate), "--resolution", "64",
           "--pixel-samples", "64", "--max-images", "4", "--threads", "1", "--save-all-ranks", "--quiet"]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    a, b = _state(tmp_path / "final_rank0.safetensors"), _state(tmp_path / "final_rank1.safetensors")
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    # and training moved them away from the initial weights
    from networks.config import get_config
    from networks.model import SDMUniPS

    torch.manual_seed(0)
    fresh = SDMUniPS(get_config("tiny", "normal")).state_dict()
    assert any(not torch.equal(fresh[k], a[k]) for k in a)


def test_brdf_validation_reports_rmse_and_constant_baseline(tiny_dataset, tiny_val_dataset, tmp_path):
    from networks.train import train

    result = train(_tc(tiny_dataset, tmp_path, steps=2, target="brdf", val_data=str(tiny_val_dataset)), progress=False)
    val = result["validation"]
    for key in ("base_color", "roughness", "metallic"):
        assert val[f"rmse_{key}"] >= 0 and val[f"rmse_const_{key}"] >= 0
    # the numpy scenes have roughness 1 and metallic 0 everywhere: the constant baseline is exact there
    assert val["rmse_const_roughness"] < 1e-3 and val["rmse_const_metallic"] < 1e-3
    assert val["rmse_const_base_color"] > 0.01
    # one free scale per scene can only help (scale 1 is among the candidates)
    assert 0 <= val["rmse_base_color_exposure_aligned"] <= val["rmse_base_color"] + 1e-9
    assert val["rmse_const_base_color_exposure_aligned"] > 0
    # the stand-alone scorer gives the same numbers from the saved weights, plus the gain over the constant
    from networks.validate import main as validate_main

    out = tmp_path / "score.json"
    assert validate_main([str(tmp_path / "last.safetensors"), str(tiny_val_dataset), "--json", str(out)]) == 0
    import json

    scored = json.loads(out.read_text())
    assert scored["target"] == "brdf" and scored["scenes"] == len(list_scenes(tiny_val_dataset))
    assert abs(scored["rmse_base_color"] - val["rmse_base_color"]) < 1e-6
    assert scored["gain_base_color"] == pytest.approx(1 - val["rmse_base_color"] / val["rmse_const_base_color"])
    assert validate_main([str(tmp_path / "missing.safetensors"), str(tiny_val_dataset)]) == 2
    # test-time views: a different prediction (mirrored copies averaged), scored the same way
    assert validate_main([str(tmp_path / "last.safetensors"), str(tiny_val_dataset), "--views", "2", "--json",
                          str(out)]) == 0
    two = json.loads(out.read_text())
    assert two["views"] == 2 and scored["views"] == 1
    assert 0 <= two["rmse_base_color"] < 1 and two["rmse_base_color"] != scored["rmse_base_color"]


def test_brdf_loss_weights_scale_each_map_term():
    from networks.train import compute_loss

    g = torch.Generator().manual_seed(0)
    b, h, m = 2, 8, 10
    batch = {"pixel_index": torch.randint(0, h * h, (b, m), generator=g),
             "normal": torch.nn.functional.normalize(torch.randn(b, h, h, 3, generator=g), dim=-1),
             "base_color": torch.rand(b, h, h, 3, generator=g), "roughness": torch.rand(b, h, h, generator=g),
             "metallic": torch.rand(b, h, h, generator=g)}
    pred = {"normal": torch.nn.functional.normalize(torch.randn(b, m, 3, generator=g), dim=-1),
            "base_color": torch.rand(b, m, 3, generator=g), "roughness": torch.randn(b, m, 1, generator=g),
            "metallic": torch.randn(b, m, 1, generator=g)}
    plain, terms = compute_loss(pred, batch, "brdf")
    weighted, same_terms = compute_loss(pred, batch, "brdf", (0.5, 2.0, 3.0))
    assert terms == same_terms  # the logged terms stay unweighted
    assert float(plain) == pytest.approx(terms["base_color"] + terms["roughness"] + terms["metallic"], rel=1e-6)
    assert float(weighted) == pytest.approx(0.5 * terms["base_color"] + 2 * terms["roughness"] + 3 * terms["metallic"],
                                            rel=1e-6)


@pytest.mark.parametrize("text", ["1,2", "1,x,2", "1,-1,2"])
def test_bad_brdf_weights_are_a_one_line_usage_error(text, capsys):
    from networks.train import main

    with pytest.raises(SystemExit) as exc:
        main(["--data", "nowhere", "--brdf-weights", text])
    assert exc.value.code == 2
    assert "expected three non-negative numbers" in capsys.readouterr().err


def test_brdf_training_with_weights_and_loss_before_relu_runs_and_resumes(tiny_dataset, tmp_path):
    from networks.train import train

    kw = dict(target="brdf", brdf_weights=(1.0, 2.0, 2.0), brdf_loss_before_relu=True)
    full = train(_tc(tiny_dataset, tmp_path / "full", steps=4, **kw), progress=False)
    train(_tc(tiny_dataset, tmp_path / "part", steps=2, **kw), progress=False)
    train(_tc(tiny_dataset, tmp_path / "part", steps=4, **kw), resume=True, progress=False)
    a, b = _state(tmp_path / "full" / "last.safetensors"), _state(tmp_path / "part" / "last.safetensors")
    assert full["step"] == 4 and all(torch.equal(a[k], b[k]) for k in a)


def test_exposure_aligned_base_color_factors_out_one_scale_per_scene():
    from networks.train import exposure_aligned_sse

    rng = np.random.default_rng(3)
    truth = rng.uniform(0.0, 1.0, (50, 3))
    # a prediction off by an exposure only scores zero; the constant side is the spread around the scene mean
    sse, const = exposure_aligned_sse(0.37 * truth, truth)
    assert sse < 1e-20
    np.testing.assert_allclose(const, ((truth - truth.mean()) ** 2).sum(), rtol=1e-12)
    # any other prediction: the least-squares scale beats (or ties) every other scale
    pred = truth + rng.normal(0, 0.1, truth.shape)
    sse, _ = exposure_aligned_sse(pred, truth)
    for s in (0.5, 0.9, 1.0, 1.1, 2.0):
        assert sse <= ((s * pred - truth) ** 2).sum() + 1e-12
    with pytest.raises(ValueError, match=r"\(50, 3\)"):
        exposure_aligned_sse(pred[:, :2], truth)


def test_init_weights_bring_their_canonical_resolution_and_dropout(tiny_dataset, tiny_val_dataset, tmp_path):
    """Starting from weights trained at another canonical resolution / dropout keeps theirs unless overridden."""
    import dataclasses

    from networks.checkpoint import load_model, save_weights
    from networks.config import get_config
    from networks.model import SDMUniPS
    from networks.train import train

    cfg = dataclasses.replace(get_config("tiny", "normal"), canonical_resolution=64, dropout=0.0)
    save_weights(tmp_path / "init.safetensors", SDMUniPS(cfg), cfg, {"name": "init"})
    train(_tc(tiny_dataset, tmp_path / "a", steps=1), init=str(tmp_path / "init.safetensors"), progress=False)
    _, got, _ = load_model(tmp_path / "a" / "last.safetensors")
    assert (got.canonical_resolution, got.dropout) == (64, 0.0)
    train(_tc(tiny_dataset, tmp_path / "b", steps=1, canonical_resolution=32), init=str(tmp_path / "init.safetensors"),
          progress=False)
    assert load_model(tmp_path / "b" / "last.safetensors")[1].canonical_resolution == 32
    # validation images (64x64) that the model cannot predict at canonical resolution 128: refused before any step
    with pytest.raises(ValueError, match="validation images are 64x64 but the model's canonical resolution is 128"):
        train(_tc(tiny_dataset, tmp_path / "c", canonical_resolution=128, val_data=str(tiny_val_dataset)),
              progress=False)
    assert not (tmp_path / "c" / "checkpoint.pt").exists()


def test_every_setting_has_a_flag_whose_help_is_its_docstring():
    import argparse
    import dataclasses

    from networks.trainconfig import add_arguments, config_from_args, field_docs

    p = argparse.ArgumentParser()
    add_arguments(p)
    actions = {a.dest: a for a in p._actions}
    settings = [f.name for f in dataclasses.fields(TrainConfig) if f.name != "sample"]
    settings += [f.name for f in dataclasses.fields(SampleSpec)]
    docs = {**field_docs(TrainConfig), **field_docs(SampleSpec)}
    assert set(docs) == set(settings) | {"sample"}  # every field is documented
    for name in settings:
        if name == "save_all_ranks":
            continue
        words = " ".join(docs[name].split()[:4])
        assert words in actions[name].help, (name, actions[name].help)
    assert "(default: 0.05)" in actions["weight_decay"].help
    # the defaults of the flags are the dataclass defaults
    assert config_from_args(p.parse_args(["--data", "D"])) == TrainConfig(data="D")

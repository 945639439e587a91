"""The data-v2 pool and GPU recipes (docs/recipes/make_pool.py, docs/recipes/gpu_v2.sh), run on this CPU with
tiny settings: the pool resumes without re-rendering, and a dry run of the GPU recipe unpacks packs, trains both
runs 3 steps from the bundled weights, resumes them in a second call and exports fp16 safetensors."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba")
REPO = Path(__file__).resolve().parents[1]


def _pool(out: Path, *extra: str) -> str:
    cmd = [sys.executable, str(REPO / "docs/recipes/make_pool.py"), "--out", str(out), "--scenes", "3", "--block", "2",
           "--resolution", "128", "--spp", "1", "--val", "2", *extra]  # training needs 128-multiples
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(cmd, capture_output=True, text=True, env=env, check=True, cwd=REPO).stdout


@pytest.fixture(scope="module")
def pool(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pool") / "p"
    _pool(out)
    return out


@pytest.mark.slow  # renders 5 tiny scenes in two processes (about a minute on 2 cores)
def test_pool_blocks_and_resume(pool):
    packs = sorted(p.name for p in (pool / "packs").glob("*.npz"))
    assert packs == ["train_0000.npz", "train_0001.npz", "val.npz"]
    assert not (pool / "render").exists() or not any((pool / "render").iterdir())  # renders deleted once packed
    blocks = [json.loads(line) for line in (pool / "blocks.jsonl").read_text().splitlines()]
    assert sorted(b["scenes"] for b in blocks) == [1, 2, 2]
    before = {p: p.stat().st_mtime_ns for p in (pool / "packs").glob("*.npz")}
    text = _pool(pool)  # everything done: nothing is rendered again
    assert "3 of 3 packs already done; 0 to render" in text
    assert before == {p: p.stat().st_mtime_ns for p in (pool / "packs").glob("*.npz")}
    with np.load(pool / "packs" / "train_0001.npz") as z:
        assert z.files == ["train_0001_scene_000000"]  # block 1 holds the 3rd scene, drawn with seed 1001
    with pytest.raises(subprocess.CalledProcessError):
        _pool(pool, "--seed", "5")  # other settings into the same pool are refused


@pytest.mark.slow  # two calls, each training both runs 3 CPU steps of the small preset at 128^2 (minutes)
def test_gpu_recipe_dry_run(pool, tmp_path):
    weights = REPO / "networks" / "weights"
    if not (weights / "normal_small.safetensors").exists():
        pytest.skip("bundled weights not in the working tree")
    env = {**os.environ, "PYTHONPATH": str(REPO), "DRY_RUN": "1", "OUT": str(tmp_path / "out"),
           "DATA_DIR": str(tmp_path / "d"), "RUNS_DIR": str(tmp_path / "runs"), "PYTHON": sys.executable,
           "POLL_S": "1"}
    (tmp_path / "runs").mkdir()
    packs = pool / "packs"
    first = subprocess.run(["bash", "docs/recipes/gpu_v2.sh", "1", "600", str(packs / "val.npz"),
                            str(packs / "train_0000.npz")], capture_output=True, text=True, env=env, cwd=REPO,
                           timeout=600)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    assert "training scenes: 2, validation scenes: 2" in first.stdout
    second = subprocess.run(["bash", "docs/recipes/gpu_v2.sh", "2", "600", str(packs / "train_0001.npz")],
                            capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert second.returncode == 0, second.stdout[-2000:]
    assert "training scenes: 3, validation scenes: 2" in second.stdout
    from safetensors import safe_open

    for r in ("n", "b"):
        log = (tmp_path / "runs" / f"run_{r}" / "train.log").read_text()
        assert "event=val" in log
        for w in ("best", "last"):
            with safe_open(str(tmp_path / "out" / f"{r}_{w}.safetensors"), "pt") as f:
                assert f.metadata() and all(str(f.get_tensor(k).dtype) in ("torch.float16", "torch.int64", "torch.bool")
                                            for k in list(f.keys())[:5])
    runs_out = (tmp_path / "runs" / "run_b.out").read_text()
    assert "Traceback" not in runs_out
    cfg = json.loads((tmp_path / "runs" / "run_b" / "log.jsonl").read_text().splitlines()[0]).get("train_config", {})
    if cfg:  # the BRDF run trains with the weighted loss
        assert cfg.get("brdf_loss_before_relu") is True

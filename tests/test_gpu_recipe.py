"""The self-contained GPU recipe (docs/recipes/gpu_train.py) run on this CPU at tiny sizes: three calls, the second on
the same machine (the runs resume from their checkpoints, the renderers continue the same seed), the third on a
fresh machine that has only what the second call returned (the runs continue from the returned float16 weights, the
renderers draw a new seed, the validation set is rendered again and comes out the same)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba")
REPO = Path(__file__).resolve().parents[1]


def _call(n: int, seconds: float, work: Path, out: Path, carry: Path) -> str:
    cmd = [sys.executable, str(REPO / "docs/recipes/gpu_train.py"), "--call", str(n), "--seconds", str(seconds),
           "--dry-run", "--work", str(work), "--out", str(out), "--carry", str(carry), "--init-normal", "none",
           "--init-brdf", "none"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO, timeout=400)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r.stdout


def _records(log: Path) -> list[dict]:
    return [json.loads(line) for line in log.read_text().splitlines()]


def _card(path: Path) -> dict:
    from networks.checkpoint import read_metadata

    return read_metadata(path)[1]


@pytest.mark.slow  # three calls of 15-30 s, each starting Mitsuba and two trainers (about 1.5 min on 2 cores)
def test_dry_run_of_three_calls_with_a_machine_return(tmp_path):
    from safetensors import safe_open

    carry, w1, w2 = tmp_path / "carry", tmp_path / "machine1", tmp_path / "machine2"
    # call 1: a fresh machine
    text = _call(1, 30, w1, tmp_path / "out1", carry)
    assert "variant probe scalar_rgb: ok" in text and "validation set: 1 scenes" in text
    assert "run n: started from random weights" in text
    out1 = sorted(p.name for p in (tmp_path / "out1").iterdir())
    assert {"n_last.safetensors", "b_last.safetensors", "logs.tar.gz"} <= set(out1)
    for r in ("n", "b"):
        with safe_open(str(tmp_path / "out1" / f"{r}_last.safetensors"), "pt") as f:
            assert all(str(f.get_tensor(k).dtype) == "torch.float16" for k in list(f.keys())[:5])
    steps1 = _card(tmp_path / "out1" / "n_last.safetensors")["steps"]
    assert steps1 >= 1
    state1 = json.loads((w1 / "state.json").read_text())
    assert state1["train_seed"] == 2001 and state1["variant"] == "scalar_rgb"
    names1 = (w1 / "run_n" / "scenes.txt").read_text().split()
    scenes1 = len(list((w1 / "train").glob("scene_*/data.npz")))

    # call 2: the same machine (kept warm): checkpoints resume, the renderers go on with the same seed
    text = _call(2, 15, w1, tmp_path / "out2", carry)
    assert "run n: started --resume" in text and "--resume-from" not in text
    assert json.loads((w1 / "state.json").read_text())["train_seed"] == 2001
    assert len(list((w1 / "train").glob("scene_*/data.npz"))) > scenes1
    names2 = (w1 / "run_n" / "scenes.txt").read_text().split()
    assert names2[:len(names1)] == names1  # the run's scene order only grows at the end
    recs = _records(w1 / "run_n" / "log.jsonl")
    train_steps = [r["step"] for r in recs if r["event"] == "train"]
    assert train_steps == list(range(1, len(train_steps) + 1))  # resumed exactly after its checkpoint, no gap
    steps2 = _card(tmp_path / "out2" / "n_last.safetensors")["steps"]
    assert steps2 > steps1

    # the machine is returned: call 3 has only the carried weights of call 2
    (carry / "resume").mkdir(parents=True)
    for r in ("n", "b"):
        shutil.copy(tmp_path / "out2" / f"{r}_last.safetensors", carry / "resume")
    text = _call(3, 20, w2, tmp_path / "out3", carry)
    assert "run n: started --resume-from" in text and "run b: started --resume-from" in text
    assert json.loads((w2 / "state.json").read_text())["train_seed"] == 2003  # scenes no earlier machine drew
    for r in ("n", "b"):
        first = next(x for x in _records(w2 / f"run_{r}" / "log.jsonl") if x["event"] == "train")
        assert first["step"] == _card(tmp_path / "out2" / f"{r}_last.safetensors")["steps"] + 1
    assert _card(tmp_path / "out3" / "n_last.safetensors")["steps"] > steps2
    # the validation set is the same scenes on every machine (seeded)
    with np.load(w1 / "val" / "scene_000000" / "data.npz") as a, np.load(w2 / "val" / "scene_000000" / "data.npz") as b:
        assert np.array_equal(a["normal"], b["normal"]) and np.array_equal(a["mask"], b["mask"])
        assert np.allclose(a["images"].astype(np.float32), b["images"].astype(np.float32), atol=1e-3)
    # validation curves over the three calls, and what comes back holds the logs
    vals = [x for w in (w1, w2) for x in _records(w / "run_n" / "log.jsonl") if x["event"] == "val"]
    assert vals and all(np.isfinite(v["mae"]) for v in vals)
    with tarfile.open(tmp_path / "out3" / "logs.tar.gz") as tar:
        names = tar.getnames()
    assert {"run_n/log.jsonl", "run_b/train.log", "render.jsonl", "call_3.log", "state.json"} <= set(names)
    for w in (w1, w2):
        for r in ("n", "b"):
            assert "Traceback" not in (w / f"run_{r}.out").read_text()

"""Training on a folder that is still being rendered (networks.data.GrowingScenes, --rescan-every-s) and continuing a
run from its weights alone (--resume-from): what the GPU recipe (docs/recipes/gpu_train.py) relies on."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from networks.data import GrowingScenes, SampleSpec, SceneCache, draw_batch, read_scene_index
from networks.trainconfig import TrainConfig

SPEC = SampleSpec(resolution=64, min_images=3, max_images=4, pixel_samples=128)


def _copy(src: Path, dst: Path, names: list[str]) -> None:
    dst.mkdir(exist_ok=True)
    for n in names:
        shutil.copytree(src / n, dst / n)


def _tc(data: Path, out: Path, **kw) -> TrainConfig:
    base = dict(data=str(data), target="normal", preset="tiny", out=str(out), steps=6, batch=2, lr=2e-3,
                warmup_steps=2, log_every=1, checkpoint_every_s=1e9, val_every_s=1e9, sample=SPEC, threads=1)
    base.update(kw)
    return TrainConfig(**base)


def test_growing_scenes_only_append_and_resume_keeps_the_order(tiny_dataset, tmp_path):
    names = sorted(p.name for p in tiny_dataset.iterdir() if (p / "data.npz").exists())
    data = tmp_path / "data"
    _copy(tiny_dataset, data, names[2:4])
    g = GrowingScenes(data, tmp_path / "run" / "scenes.txt")
    assert [p.name for p in g.scenes] == names[2:4] and g.refresh() == 0
    _copy(tiny_dataset, data, [names[0], names[5]])  # one sorts before the scenes already listed
    assert g.refresh() == 2
    order = names[2:4] + [names[0], names[5]]
    assert [p.name for p in g.scenes] == order
    assert (tmp_path / "run" / "scenes.txt").read_text().split() == order
    assert [p.name for p in read_scene_index(g.index, data, 3)] == order[:3]
    # a resumed run on the same folder keeps the order; more scenes join at the end
    _copy(tiny_dataset, data, [names[1]])
    again = GrowingScenes(data, g.index, resume=True)
    assert [p.name for p in again.scenes] == order + [names[1]]
    # a scene gone (another machine's folder): the folder is listed afresh
    shutil.rmtree(data / names[0])
    fresh = GrowingScenes(data, g.index, resume=True)
    assert len(fresh) == 4 and names[0] not in g.index.read_text().split()
    with pytest.raises(ValueError, match="fewer than"):
        read_scene_index(g.index, data, 9)


def test_a_scene_still_being_written_is_not_listed(tiny_dataset, tmp_path):
    """A generator writes each scene into a hidden folder and renames it when done; a trainer looking in between
    must not take the hidden folder for a scene (it is gone a moment later)."""
    from networks.data import list_scenes

    names = sorted(p.name for p in tiny_dataset.iterdir() if (p / "data.npz").exists())
    data = tmp_path / "data"
    _copy(tiny_dataset, data, names[:2])
    shutil.copytree(tiny_dataset / names[2], data / f".tmp-{names[2]}-12345")
    assert [p.name for p in list_scenes(data)] == names[:2]
    g = GrowingScenes(data, tmp_path / "run" / "scenes.txt")
    assert g.refresh() == 0 and [p.name for p in g.scenes] == names[:2]
    (data / f".tmp-{names[2]}-12345").rename(data / names[2])
    assert g.refresh() == 1 and g.scenes[-1].name == names[2]


def test_a_batch_draws_only_from_the_first_n_scenes(tiny_dataset):
    from networks.data import list_scenes

    cache = SceneCache(list_scenes(tiny_dataset))
    a = draw_batch(cache, SPEC, 2, seed=0, step=5, n_scenes=2)
    b = draw_batch(SceneCache(cache.scenes[:2]), SPEC, 2, seed=0, step=5)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    with pytest.raises(ValueError):
        draw_batch(cache, SPEC, 2, seed=0, step=5, n_scenes=7)


def test_worker_processes_follow_a_growing_folder(tiny_dataset, tmp_path):
    """The batches the workers draw after the folder grew are those drawn here from the first n scenes."""
    import networks.train as T

    names = sorted(p.name for p in tiny_dataset.iterdir() if (p / "data.npz").exists())
    data = tmp_path / "data"
    _copy(tiny_dataset, data, names[:2])
    g = GrowingScenes(data, tmp_path / "scenes.txt")
    tc = _tc(data, tmp_path, steps=6, workers=1, rescan_every_s=1e-9)
    growth = []
    batches = T._batches(SceneCache(g.scenes), g, tc, 0, 0, on_growth=lambda s, n: growth.append((s, n)))
    got = [next(batches)]
    _copy(tiny_dataset, data, names[2:])  # 4 more scenes appear while the run goes on
    got += list(batches)
    assert growth and growth[0][1] == 6
    first_grown = growth[0][0]
    assert 0 < first_grown <= 3  # the steps asked for ahead of the growth keep the old count
    full = SceneCache(read_scene_index(g.index, data))
    for step, (micro,) in got:
        n = 2 if step < first_grown else 6
        expect = draw_batch(full, tc.sample, tc.batch, tc.seed, step, 0, 0, n_scenes=n)
        for k in expect:
            assert np.array_equal(micro[k], expect[k]), (step, k)


def test_resume_from_weights_continues_the_step_the_best_score_and_warms_up_again(tiny_dataset, tiny_val_dataset,
                                                                                 tmp_path):
    from safetensors.torch import load_file, save_file
    from safetensors import safe_open

    from networks.train import lr_factor, train

    first = train(_tc(tiny_dataset, tmp_path / "a", steps=4, val_data=str(tiny_val_dataset), val_scenes=1),
                  progress=False)
    src = tmp_path / "a" / "last.safetensors"
    with safe_open(str(src), "pt") as f:
        meta = f.metadata()
    half = tmp_path / "n_last.safetensors"  # what a call returns: float16
    save_file({k: v.half() for k, v in load_file(str(src)).items()}, str(half), metadata=meta)
    tc = _tc(tiny_dataset, tmp_path / "b", steps=8, warmup_steps=3, val_data=str(tiny_val_dataset), val_scenes=1)
    train(tc, resume_from=str(half), progress=False)
    recs = [json.loads(line) for line in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert recs[0] == {"event": "data", "step": 4, "scenes": 6}
    steps = [r for r in recs if r["event"] == "train"]
    assert [r["step"] for r in steps] == [5, 6, 7, 8]
    # warm-up again from step 4: the learning rate after steps 4, 5, 6 is 2/3, 3/3, 3/3 of the schedule's
    assert [r["lr"] for r in steps[:3]] == pytest.approx([tc.lr * lr_factor(s, tc) * min(1, (s - 4 + 1) / 3)
                                                          for s in (5, 6, 7)])
    assert steps[0]["lr"] == pytest.approx(tc.lr * 2 / 3 * tc.decay_factor ** (5 // tc.decay_every))
    from networks.checkpoint import read_metadata

    card = read_metadata(tmp_path / "b" / "last.safetensors")[1]
    assert card["steps"] == 8 and card["rewarm_from"] == 4
    assert card["best"] <= first["best"] and math.isfinite(card["best"])
    assert torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)["rewarm_from"] == 4
    with pytest.raises(ValueError, match="exclude"):
        train(tc, resume=True, resume_from=str(half), progress=False)

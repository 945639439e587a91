"""Training of the SDM-UniPS networks on `matcap synth` data, single process or data-parallel.

    python -m networks.train --data DATA/ --target normal --preset small --out runs/NAME [--resume] [--steps N]
    torchrun --nproc_per_node=2 -m networks.train ...        # the same, DDP (gloo on CPU, nccl on GPU)

Defaults follow the paper's recipe (AdamW, lr 1e-4, weight decay 0.05, linear warm-up, step decay x0.8; MSE on unit
normals inside the mask; BRDF: MSE on base color, roughness, metallic); every field is overridable.

Resumable bit-for-bit: the data of step s and the dropout noise of step s are pure functions of (seed, s, rank),
and the checkpoint holds model, optimiser and schedule state at a step boundary.
Files in ``--out``: ``checkpoint.pt`` (tensors and numbers only, loaded with ``weights_only=True``),
``best.safetensors`` (best validation so far, with config and card), ``last.safetensors``, ``log.jsonl``
(one JSON record per log/validation event) and ``train.log``.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from networks.config import SDMUniPSConfig, get_config
from networks.data import GrowingScenes, SceneCache, draw_batch, list_scenes, load_scene, read_scene_index
from networks.inference import check_device
from networks.preprocess import normalize_images
from networks.trainconfig import TrainConfig, add_arguments, check_config, config_from_args
from scenes.atomic import atomic_path

# ------------------------------------------------------------------------------------------ helpers


def lr_factor(step: int, tc: TrainConfig, rewarm_from: int | None = None) -> float:
    """Warm-up then step decay: the multiplier of ``lr`` at ``step``. A run continued from weights alone
    (``--resume-from``, a fresh optimiser) warms up again over ``warmup_steps`` from step ``rewarm_from``."""
    warm = min(1.0, (step + 1) / max(tc.warmup_steps, 1))
    if rewarm_from is not None:
        warm = min(warm, max(step - rewarm_from + 1, 0) / max(tc.warmup_steps, 1))
    return warm * tc.decay_factor ** (step // max(tc.decay_every, 1))


def gather_pixels(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """x: (B, H, W, C) or (B, H, W); index: (B, m) flat -> (B, m, C)."""
    b = x.shape[0]
    flat = x.reshape(b, -1, x.shape[-1] if x.dim() == 4 else 1)
    return torch.gather(flat, 1, index.unsqueeze(-1).expand(-1, -1, flat.shape[-1]))


BRDF_KEYS = ("base_color", "roughness", "metallic")


def compute_loss(pred: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], target: str,
                 brdf_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)):
    """MSE on unit normals (and BRDF maps) at the sampled pixels, which all lie inside the loss mask. The BRDF
    loss is ``sum(w_k * MSE_k)`` over base color, roughness, metallic with ``brdf_weights``; the returned terms
    are the unweighted MSEs."""
    idx = batch["pixel_index"]
    terms = {"normal": F.mse_loss(pred["normal"].float(), gather_pixels(batch["normal"], idx))}
    if target == "brdf":
        for key in BRDF_KEYS:
            terms[key] = F.mse_loss(pred[key].float(), gather_pixels(batch[key], idx))
        total = sum(w * terms[key] for w, key in zip(brdf_weights, BRDF_KEYS))
    else:
        total = terms["normal"]
    return total, {k: float(v.detach()) for k, v in terms.items()}


def to_torch(batch: dict[str, np.ndarray], device) -> dict[str, torch.Tensor]:
    out = {k: torch.from_numpy(v).to(device) for k, v in batch.items()}
    out["input_mask"] = out["input_mask"].unsqueeze(1)  # (B, 1, R, R)
    out["images"] = normalize_images(out["images"], out["input_mask"])
    return out


def exposure_aligned_sse(pred: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Squared errors of one scene's base color once its unknown exposure is factored out.

    pred, truth: (P, 3) linear base color of the scene's valid pixels. Returns (SSE of ``s * pred`` with the
    least-squares scale ``s``, SSE of the best constant grey for this scene, i.e. the truth's mean): each side
    gets exactly one free parameter per scene.
    """
    pred, truth = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    if pred.shape != truth.shape:
        raise ValueError(f"pred {pred.shape} and truth {truth.shape} differ")
    scale = float((pred * truth).sum() / max(float((pred * pred).sum()), 1e-12))
    return float(((scale * pred - truth) ** 2).sum()), float(((truth - truth.mean()) ** 2).sum())


@torch.no_grad()
def validate(model, scenes: list[Path], target: str, device, max_scenes: int, seed: int = 0,
             pixel_samples: int | None = None, views: int = 1) -> dict:
    """Mean angular error (degrees) per lighting group, and BRDF RMSEs (pooled over pixels, with the RMSE of the
    best constant prediction beside them), on the first ``max_scenes`` scenes. Base color is also scored
    exposure-aligned (``rmse_base_color_exposure_aligned``): the network sees images normalised per image, so the
    absolute albedo scale of a scene is not observable; there the prediction and the per-scene constant each get
    their best single scale per scene.

    Each scene is predicted with its 10 stored images and its ground-truth mask, every pixel, in sample sets of
    ``pixel_samples`` pixels (default: the model's), averaged over ``views`` mirrored / transposed copies of the
    input as `matcap capture --views` does (1 = none).
    """
    from functools import partial

    from networks.inference import predict, predict_views

    was_training = model.training
    model.eval()
    groups: dict[str, list[float]] = {}
    keys = ("base_color", "roughness", "metallic")
    sse = dict.fromkeys(keys, 0.0)  # pooled over every valid pixel (and channel) of every scene
    s1, s2, count = dict.fromkeys(keys, 0.0), dict.fromkeys(keys, 0.0), dict.fromkeys(keys, 0)
    sse_aligned = [0.0, 0.0]  # base color: prediction and per-scene constant, each with its best scene scale
    for path in scenes[:max_scenes]:
        scene = load_scene(path)
        try:
            group = json.loads((path / "spec.json").read_text()).get("lighting_group") or "all"
        except (OSError, json.JSONDecodeError):
            group = "all"
        mask = scene["mask"].astype(bool)
        gt = scene["normal"].astype(np.float32)
        valid = mask & (np.linalg.norm(gt, axis=2) > 0.5)
        images = torch.from_numpy(scene["images"].astype(np.float32)).permute(0, 3, 1, 2).to(device)
        m = torch.from_numpy(mask).to(device)
        images = normalize_images(images, m.float().unsqueeze(0))
        out = predict_views(partial(predict, model), images, m, views=views, seed=seed, pixel_samples=pixel_samples)
        n = out["normal"][valid]
        g = gt[valid] / np.linalg.norm(gt[valid], axis=1, keepdims=True)
        err = np.degrees(np.arccos(np.clip((n * g).sum(1) / np.maximum(np.linalg.norm(n, axis=1), 1e-8), -1, 1)))
        groups.setdefault(group, []).append(float(err.mean()))
        if target == "brdf":
            for key in keys:
                truth = scene[key].astype(np.float64)[valid]
                sse[key] += float(((out[key][valid] - truth) ** 2).sum())
                s1[key] += float(truth.sum())
                s2[key] += float((truth**2).sum())
                count[key] += truth.size
            # exposure-aligned base color: with the light intensity unknown, albedo is only defined up to one
            # scale per scene; give the prediction and the constant baseline one free scale each
            for i, value in enumerate(exposure_aligned_sse(out["base_color"][valid], scene["base_color"][valid])):
                sse_aligned[i] += value
    if was_training:
        model.train()
    result = {f"mae_{g}": float(np.mean(v)) for g, v in sorted(groups.items())}
    result["mae"] = float(np.mean([e for v in groups.values() for e in v])) if groups else float("nan")
    if target == "brdf":
        for key in keys:
            n = max(count[key], 1)
            result[f"rmse_{key}"] = math.sqrt(sse[key] / n)
            # the best constant prediction (the mean) has an RMSE equal to the standard deviation of the truth
            result[f"rmse_const_{key}"] = math.sqrt(max(s2[key] / n - (s1[key] / n) ** 2, 0.0))
        result["rmse_mean"] = float(np.mean([result[f"rmse_{k}"] for k in keys]))
        n = max(count["base_color"], 1)
        result["rmse_base_color_exposure_aligned"] = math.sqrt(sse_aligned[0] / n)
        result["rmse_const_base_color_exposure_aligned"] = math.sqrt(sse_aligned[1] / n)
    return result


def _save_atomic(obj, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _plain(obj):
    """Checkpoint-safe copy of a config dict (only containers, strings and numbers)."""
    return json.loads(json.dumps(obj))


# ------------------------------------------------------------------------------------------ train


_worker_cache: SceneCache | None = None
_worker_index: tuple[Path, Path] | None = None  # (scene index file, data folder) of a growing dataset


def _worker_init(scenes: list[Path], index: Path | None = None, root: Path | None = None) -> None:
    global _worker_cache, _worker_index
    import cv2

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the main process handles Ctrl-C and stops the pool
    cv2.setNumThreads(1)
    _worker_cache = SceneCache(list(scenes))
    _worker_index = None if index is None else (Path(index), Path(root))


def _step_batches(cache: SceneCache, sample, batch: int, accumulate: int, seed: int, rank: int,
                  step: int, n_scenes: int | None = None) -> list[dict[str, np.ndarray]]:
    """The ``accumulate`` micro-batches of one optimiser step, drawn from the first ``n_scenes`` scenes."""
    grow = {} if n_scenes is None else {"n_scenes": n_scenes}  # None: every scene of the cache
    return [draw_batch(cache, sample, batch, seed, step, rank, micro, **grow) for micro in range(accumulate)]


def _worker_batch(sample, batch: int, accumulate: int, seed: int, rank: int, step: int,
                  n_scenes: int | None = None) -> list[dict[str, np.ndarray]]:
    assert _worker_cache is not None
    if n_scenes is not None and n_scenes > len(_worker_cache.scenes):
        # the dataset grew: the main process wrote the new scene order to the index before asking for this step
        assert _worker_index is not None
        paths = read_scene_index(_worker_index[0], _worker_index[1], n_scenes)
        if paths is None:
            raise RuntimeError(f"a scene named in {_worker_index[0]} has disappeared")
        _worker_cache.scenes = paths  # the first scenes are the same ones: cached entries stay valid
    return _step_batches(_worker_cache, sample, batch, accumulate, seed, rank, step, n_scenes)


def _batches(cache: SceneCache, scenes: GrowingScenes, tc: TrainConfig, start: int, rank: int, on_growth=None):
    """Yield ``(step, micro-batches)`` for steps ``start .. tc.steps - 1`` in order: drawn here, or by ``tc.workers``
    spawned processes at most ``2 * workers`` steps ahead (the same batches: each is a pure function of its step and
    of the number of scenes it draws from). With ``tc.rescan_every_s`` the data folder is re-listed that often and
    the steps asked for after it draw from the grown set; ``on_growth(step, count)`` is told of each growth."""
    last_scan = time.perf_counter()

    def count(step: int) -> int | None:
        nonlocal last_scan
        if tc.rescan_every_s <= 0:
            return None  # a fixed folder: every scene
        if time.perf_counter() - last_scan >= tc.rescan_every_s:
            last_scan = time.perf_counter()
            if scenes.refresh() and on_growth is not None:
                on_growth(step, len(scenes))
        return len(scenes)

    if tc.workers <= 0:
        for step in range(start, tc.steps):
            yield step, _step_batches(cache, tc.sample, tc.batch, tc.accumulate, tc.seed, rank, step, count(step))
        return
    import collections
    import functools
    import multiprocessing

    work = functools.partial(_worker_batch, tc.sample, tc.batch, tc.accumulate, tc.seed, rank)
    init = (list(scenes.scenes), scenes.index, scenes.root)
    with multiprocessing.get_context("spawn").Pool(tc.workers, _worker_init, init) as pool:
        pending: collections.deque = collections.deque()  # (step, async result), oldest first
        upcoming = iter(range(start, tc.steps))
        for step in upcoming:
            pending.append((step, pool.apply_async(work, (step, count(step)))))
            if len(pending) >= 2 * tc.workers:
                break
        while pending:
            step, result = pending.popleft()
            nxt = next(upcoming, None)
            if nxt is not None:
                pending.append((nxt, pool.apply_async(work, (nxt, count(nxt)))))
            yield step, result.get()


@contextlib.contextmanager
def _stop_requests(enabled: bool):
    """While active, SIGINT / SIGTERM only set ``flag["stop"]``: the loop then finishes its step, writes the
    checkpoint and returns, so Ctrl-C or ``kill`` loses nothing and ``--resume`` continues exactly there. Off for
    data-parallel runs (ranks could see the signal at different steps) and outside the main thread."""
    flag = {"stop": False}
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, _frame):
        flag["stop"] = True

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield flag
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


#: Files of a run folder that a fresh run would replace.
RUN_FILES = ("checkpoint.pt", "best.safetensors", "last.safetensors")


def check_run_folder(out: Path, resume: bool, overwrite: bool) -> None:
    """A fresh run never replaces an earlier one's checkpoint or weights unless asked to."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a folder")
    held = [name for name in RUN_FILES if (out / name).exists()]
    if held and not resume and not overwrite:
        raise ValueError(f"--out {out} holds an earlier run ({', '.join(held)}); pass --resume to continue it, "
                         "--overwrite to start over, or choose another folder")


def train(tc: TrainConfig, resume: bool = False, init: str | None = None, progress: bool = True,
          overwrite: bool = False, resume_from: str | None = None) -> dict:
    """Run (or continue) training. Returns the final record (step, best, last validation; ``"stopped": True``
    when SIGINT / SIGTERM ended it early, after saving the checkpoint). A fresh run (not ``resume``) refuses an
    ``out`` folder that holds an earlier run unless ``overwrite``.

    ``resume_from``: continue a run from weights it wrote (``last.safetensors``, float16 copies too) when its
    checkpoint is gone, e.g. on a fresh machine: the step, the best validation score and the wall time come from
    the file's card; the optimiser starts afresh and the learning rate warms up again over ``warmup_steps``. Not
    bit-for-bit (that needs ``resume`` and ``checkpoint.pt``)."""
    from networks.checkpoint import load_model, read_metadata, save_weights
    from networks.model import SDMUniPS

    check_config(tc)
    check_run_folder(Path(tc.out), resume, overwrite)
    check_device(tc.device)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    ddp = world > 1
    device = torch.device(tc.device)
    if ddp:
        import torch.distributed as dist

        backend = "nccl" if device.type == "cuda" else "gloo"
        if device.type == "cuda":
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(device)
        dist.init_process_group(backend=backend)
    if tc.threads:
        torch.set_num_threads(tc.threads)
    out = Path(tc.out)
    if resume and resume_from:
        raise ValueError("--resume and --resume-from exclude each other")
    if init and resume_from:
        raise ValueError("--init and --resume-from exclude each other")
    list_scenes(tc.data)  # fails here on a folder without scenes
    val_scenes = list_scenes(tc.val_data) if tc.val_data else []
    out.mkdir(parents=True, exist_ok=True)  # after the data checks: a bad --data leaves no empty run folder
    scenes = GrowingScenes(tc.data, out / ("scenes.txt" if rank == 0 else f"scenes.rank{rank}.txt"), resume=resume)
    cache = SceneCache(scenes.scenes)  # the same list: it grows with the folder (tc.rescan_every_s)

    torch.manual_seed(tc.seed)
    config = get_config(tc.preset, tc.target)
    from_card: dict = {}
    if resume_from:
        init = resume_from
        from_card = read_metadata(resume_from)[1]
        if "steps" not in from_card:
            raise ValueError(f"--resume-from {resume_from}: its card has no step count (not written by a training run)")
    src, init_config = (load_model(init, device="cpu")[:2]) if init else (None, None)
    overrides = {"pixel_samples": tc.sample.pixel_samples}  # inference uses the sample-set size it was trained with
    # canonical resolution and dropout: the command line's, else those of the weights we start from, else the preset's
    if tc.canonical_resolution:
        overrides["canonical_resolution"] = tc.canonical_resolution
    elif init_config is not None:
        overrides["canonical_resolution"] = init_config.canonical_resolution
    if tc.dropout >= 0:
        overrides["dropout"] = tc.dropout
    elif init_config is not None:
        overrides["dropout"] = init_config.dropout
    config = dataclasses.replace(config, **overrides)
    config.extra["native_resolution"] = tc.sample.resolution
    if val_scenes:  # fail now, not at the first validation an hour in
        side = load_scene(val_scenes[0])["mask"].shape
        if side[0] != side[1] or side[0] % config.canonical_resolution:
            raise ValueError(f"validation images are {side[1]}x{side[0]} but the model's canonical resolution is "
                             f"{config.canonical_resolution}: they must be square with a side that is a multiple "
                             f"of it (--canonical-resolution)")
    model = SDMUniPS(config).to(device)
    if src is not None:
        missing = model.load_state_dict(src.state_dict(), strict=False)
        if rank == 0:
            print(f"initialised from {init} (missing: {len(missing.missing_keys)} keys)", file=sys.stderr)
    rewarm = {"from": None}  # the step a --resume-from run warms up again from (kept in the checkpoint)
    opt = torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, tc, rewarm["from"]))
    start, best, wall_before = 0, float("inf"), 0.0
    ckpt_path = out / "checkpoint.pt"
    if resume_from:
        start = int(from_card["steps"])
        best = float(from_card.get("best", float("inf")))
        wall_before = float(from_card.get("wall_time_s", 0.0))
        rewarm["from"] = start
        sched.last_epoch = start
        for group in opt.param_groups:
            group["lr"] = tc.lr * lr_factor(start, tc, start)
        if rank == 0:
            print(f"continuing from {resume_from} at step {start} (fresh optimiser, warm-up again)", file=sys.stderr)
    if resume:
        if not ckpt_path.exists():
            raise ValueError(f"--resume: {ckpt_path} does not exist")
        ckpt = torch.load(ckpt_path, map_location=device, weights_only=True)
        if "model_config" in ckpt:  # the run's own network shape, even if the preset changed since
            config = SDMUniPSConfig.from_dict(ckpt["model_config"])
            model = SDMUniPS(config).to(device)
            opt = torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
            sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, tc, rewarm["from"]))
        rewarm["from"] = ckpt.get("rewarm_from")
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        sched.load_state_dict(ckpt["scheduler"])
        # a resumed run may change --lr (e.g. to anneal): the schedule then follows the new peak learning rate
        sched.base_lrs = [tc.lr for _ in sched.base_lrs]
        for group in opt.param_groups:
            group["initial_lr"] = tc.lr
            group["lr"] = tc.lr * lr_factor(sched.last_epoch, tc, rewarm["from"])
        start, best, wall_before = int(ckpt["step"]), float(ckpt["best"]), float(ckpt["wall_s"])
    net = model
    if ddp:
        from torch.nn.parallel import DistributedDataParallel

        net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)

    log = open(out / "log.jsonl", "a") if rank == 0 else None
    text_log = open(out / "train.log", "a") if rank == 0 else None

    def record(rec: dict) -> None:
        if log is not None:
            log.write(json.dumps(rec) + "\n")
            log.flush()
            text_log.write(" ".join(f"{k}={v:.5g}" if isinstance(v, float) else f"{k}={v}" for k, v in rec.items()) + "\n")
            text_log.flush()

    def card(step: int, wall: float, val: dict | None) -> dict:
        return {
            "preset": tc.preset, "target": tc.target, "steps": step, "wall_time_s": round(wall, 1),
            "data": str(tc.data), "train_scenes": len(scenes), "val_data": str(tc.val_data),
            "validation": val or {}, "train_config": _plain(dataclasses.asdict(tc)), "world_size": world,
            "best": best if math.isfinite(best) else None, "rewarm_from": rewarm["from"],
        }

    def save_checkpoint(step: int, wall: float) -> None:
        _save_atomic(
            {"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
             "step": step, "best": best, "wall_s": wall, "train_config": _plain(dataclasses.asdict(tc)),
             "model_config": _plain(config.to_dict()), "rewarm_from": rewarm["from"]},
            ckpt_path,
        )

    bar = None
    if progress and rank == 0:
        from networks.progress import progress as progress_bar

        bar = progress_bar(total=tc.steps, initial=start, desc=f"train {tc.target}/{tc.preset}", unit="step")
    t_start = time.perf_counter()
    last_ckpt = last_val = t_start
    autocast = torch.autocast(device.type, dtype=torch.bfloat16) if tc.bf16 else None
    net.train()
    last_val_result: dict | None = None
    running = []
    step = start
    stopped = False
    def grown(first_step: int, count: int) -> None:
        record({"event": "data", "step": first_step, "scenes": count})

    if rank == 0 and (resume_from or tc.rescan_every_s > 0):
        record({"event": "data", "step": start, "scenes": len(scenes)})
    batches = _batches(cache, scenes, tc, start, rank, on_growth=grown if rank == 0 else None)
    clamp = not tc.brdf_loss_before_relu
    with _stop_requests(enabled=not ddp) as stop:
        for step, micro_batches in batches:
            torch.manual_seed(tc.seed * 1_000_003 + step * 7919 + rank)  # dropout noise of this step
            opt.zero_grad(set_to_none=True)
            loss_sum, terms = 0.0, {}
            for micro, drawn in enumerate(micro_batches):
                last_micro = micro == len(micro_batches) - 1
                # DDP averages gradients across processes once per step, on the last micro-batch's backward
                sync = net.no_sync() if ddp and not last_micro else contextlib.nullcontext()
                with sync:
                    batch = to_torch(drawn, device)
                    with autocast if autocast is not None else contextlib.nullcontext():
                        pred = net(batch["images"], batch["input_mask"], batch["pixel_index"], clamp=clamp)
                    loss, micro_terms = compute_loss(pred, batch, tc.target, tc.brdf_weights)
                    (loss / len(micro_batches)).backward()
                loss_sum += float(loss.detach())
                for key, value in micro_terms.items():
                    terms[key] = terms.get(key, 0.0) + value / len(micro_batches)
            if tc.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
            opt.step()
            sched.step()
            running.append(loss_sum / len(micro_batches))
            now = time.perf_counter()
            wall = wall_before + now - t_start
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{running[-1]:.4f}")
            if rank == 0 and ((step + 1) % tc.log_every == 0 or step + 1 == tc.steps):
                record({"event": "train", "step": step + 1, "loss": float(np.mean(running)), **terms,
                        "lr": sched.get_last_lr()[0], "wall_s": round(wall, 1)})
                running = []
            done = step + 1 == tc.steps
            stopped = stop["stop"] and not done
            if rank == 0 and val_scenes and (done or now - last_val >= tc.val_every_s):
                last_val_result = validate(model, val_scenes, tc.target, device, tc.val_scenes, tc.seed)
                record({"event": "val", "step": step + 1, "wall_s": round(wall, 1), **last_val_result})
                score = last_val_result["rmse_mean"] if tc.target == "brdf" else last_val_result["mae"]
                if score < best:
                    best = score
                    save_weights(out / "best.safetensors", model, config, card(step + 1, wall, last_val_result))
                last_val = time.perf_counter()
            if rank == 0 and (done or stopped or now - last_ckpt >= tc.checkpoint_every_s):
                save_checkpoint(step + 1, wall)
                save_weights(out / "last.safetensors", model, config, card(step + 1, wall, last_val_result))
                last_ckpt = time.perf_counter()
            if stopped:
                record({"event": "stopped", "step": step + 1, "wall_s": round(wall, 1)})
                break
    batches.close()  # stops the worker processes, if any
    if bar is not None:
        bar.close()
    final = {"step": step + 1 if stopped else tc.steps, "best": best, "validation": last_val_result}
    if stopped:
        final["stopped"] = True
    if ddp:
        import torch.distributed as dist

        dist.barrier()
    if tc.save_all_ranks:
        save_weights(out / f"final_rank{rank}.safetensors", model, config, card(step + 1, 0.0, None))
    if ddp:
        import torch.distributed as dist

        dist.destroy_process_group()
    if log is not None:
        log.close()
        text_log.close()
    return final


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m networks.train", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.add_argument("--resume-from", metavar="WEIGHTS", help="continue a run from weights it wrote (last.safetensors, "
                   "fp16 copies too) when its checkpoint.pt is gone: step, best score and wall time from their card, "
                   "a fresh optimiser warmed up again over --warmup-steps (not bit-for-bit)")
    args = p.parse_args(argv)
    try:
        result = train(config_from_args(args), resume=args.resume, init=args.init, progress=not args.quiet,
                       overwrite=args.overwrite, resume_from=args.resume_from)
    except ValueError as exc:
        print(f"networks.train: error: {exc}", file=sys.stderr)
        return 2
    if int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps(result))
    if result.get("stopped"):
        print(f"networks.train: stopped at step {result['step']} (checkpoint saved); continue with --resume",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())

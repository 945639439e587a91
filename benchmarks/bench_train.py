"""Benchmark one training step (forward, backward, AdamW) of the `small` network on the CPU.

The settings are those of the shipped model's runs: canonical resolution 128, no dropout, B = 2 samples of K
images at 128^2, 768 supervised pixels each, bfloat16 autocast. Inputs are random (the step cost does not depend
on the pixel values), so no dataset is needed. Prints a table: threads, K, mean and best step time over the timed
steps (after warm-up).

Usage:
  python benchmarks/bench_train.py                      # threads 1 and 2, K = 4
  python benchmarks/bench_train.py --threads 2 --k 3,5 --steps 10 [--fp32]
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import time


def step_times(threads: int, k: int, steps: int, warmup: int, bf16: bool) -> list[float]:
    import torch
    import torch.nn.functional as F

    from networks.config import get_config
    from networks.model import SDMUniPS

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    cfg = dataclasses.replace(get_config("small", "normal"), canonical_resolution=128, dropout=0.0,
                              pixel_samples=768)
    model = SDMUniPS(cfg).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, weight_decay=0.05)
    g = torch.Generator().manual_seed(1)
    images = torch.rand(2, k, 3, 128, 128, generator=g)
    mask = torch.ones(2, 1, 128, 128)
    index = torch.randint(0, 128 * 128, (2, 768), generator=g)
    target = F.normalize(torch.randn(2, 768, 3, generator=g), dim=-1)
    times = []
    for i in range(warmup + steps):
        t0 = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            pred = model(images, mask, index)
        loss = F.mse_loss(pred["normal"].float(), target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        if i >= warmup:
            times.append(time.perf_counter() - t0)
    return times


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", default="1,2", help="comma-separated torch thread counts (default 1,2)")
    ap.add_argument("--k", default="4", help="comma-separated images per sample (default 4)")
    ap.add_argument("--steps", type=int, default=8, help="timed steps per row (default 8)")
    ap.add_argument("--warmup", type=int, default=2, help="untimed steps first (default 2)")
    ap.add_argument("--fp32", action="store_true", help="no bfloat16 autocast")
    args = ap.parse_args(argv)
    print("| threads | K | precision | mean step (s) | best step (s) |")
    print("|---:|---:|---|---:|---:|")
    for threads in (int(t) for t in args.threads.split(",")):
        for k in (int(v) for v in args.k.split(",")):
            t = step_times(threads, k, args.steps, args.warmup, not args.fp32)
            print(f"| {threads} | {k} | {'fp32' if args.fp32 else 'bf16'} | {statistics.mean(t):.3f} | {min(t):.3f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark SDM-UniPS inference on the CPU: wall time and peak RSS per configuration.

Rows (each runs in its own subprocess so that peak RSS is per row):
  paper 512^2 K=16 (fp32, bf16), small 512^2 K=16 (fp32, bf16), paper 2048^2 K=16 scalable (fp32, bf16).
bf16 rows run under ``torch.autocast("cpu", dtype=torch.bfloat16)`` and report the mean / max angular difference of
their normals to the fp32 row of the same configuration (when that row ran first in the same invocation).

Input: a Lambertian sphere (disc mask of radius 0.45 S, ~64% of the pixels) under K random directional lights;
weights: the SPEC's deterministic reference weights (salt "bench"), so timings are those of real-sized tensors.

Usage:
  python benchmarks/bench_networks.py --quick          # small 512 K=16 fp32, paper 512 K=4 fp32
  python benchmarks/bench_networks.py                  # every row (long: about an hour on 2 cores)
  python benchmarks/bench_networks.py --rows paper-512-k16-fp32,paper-512-k16-bf16
  python benchmarks/bench_networks.py --flops          # analytic FLOP count (meta tensors), paper vs small
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

ROWS = {
    # name: (preset, side, K, mode, dtype)
    "paper-512-k16-fp32": ("paper", 512, 16, "direct", "fp32"),
    "paper-512-k16-bf16": ("paper", 512, 16, "direct", "bf16"),
    "small-512-k16-fp32": ("small", 512, 16, "direct", "fp32"),
    "small-512-k16-bf16": ("small", 512, 16, "direct", "bf16"),
    "paper-2048-k16-scalable-fp32": ("paper", 2048, 16, "scalable", "fp32"),
    "paper-2048-k16-scalable-bf16": ("paper", 2048, 16, "scalable", "bf16"),
    "paper-512-k4-fp32": ("paper", 512, 4, "direct", "fp32"),
}
QUICK = ["small-512-k16-fp32", "paper-512-k4-fp32"]
FULL = [r for r in ROWS if r != "paper-512-k4-fp32"]


def make_object(side: int, k: int, seed: int = 0):
    """Lambertian sphere, K random lights from the upper hemisphere: images (K, 3, S, S) float32, mask (S, S)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    x = (xx + 0.5 - side / 2) / (0.45 * side)
    y = -(yy + 0.5 - side / 2) / (0.45 * side)
    mask = x * x + y * y < 1.0
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))
    normal = np.stack([x, y, z], -1) * mask[..., None]
    light = rng.normal(size=(k, 3))
    light[:, 2] = np.abs(light[:, 2]) + 0.5
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    albedo = np.array([0.8, 0.6, 0.4])
    shade = np.clip(np.einsum("hwc,kc->khw", normal, light), 0.0, None)
    images = shade[:, None] * albedo[None, :, None, None] * mask
    images /= images.reshape(k, 3, -1).mean(1).max() + 1e-6
    return images.astype(np.float32), mask


def run_row(name: str, threads: int, out_npz: str | None) -> dict:
    """Run one row in this process; returns the result record."""
    import resource

    import numpy as np
    import torch

    from networks.checkpoint import reference_weights
    from networks.config import get_config
    from networks.inference import predict, predict_scalable
    from networks.model import build_model

    torch.set_num_threads(threads)
    preset, side, k, mode, dtype = ROWS[name]
    cfg = get_config(preset, "normal")
    model = build_model(cfg, reference_weights(cfg, "bench")).eval()
    images, mask = make_object(side, k)
    images_t, mask_t = torch.from_numpy(images), torch.from_numpy(mask)
    autocast = torch.bfloat16 if dtype == "bf16" else None
    t0 = time.perf_counter()
    if mode == "scalable":
        out = predict_scalable(model, images_t, mask_t, decoder_resolution=512, autocast_dtype=autocast)
    else:
        out = predict(model, images_t, mask_t, autocast_dtype=autocast)
    wall = time.perf_counter() - t0
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if out_npz:
        np.savez(out_npz, normal=out["normal"], mask=mask)
    return {"row": name, "wall_s": wall, "peak_rss_mb": rss_mb, "pixels": int(mask.sum()), "threads": threads}


def normal_diff_deg(a_npz: str, b_npz: str) -> tuple[float, float]:
    import numpy as np

    a, b = np.load(a_npz), np.load(b_npz)
    m = a["mask"]
    cos = np.clip((a["normal"][m].astype(np.float64) * b["normal"][m]).sum(-1), -1, 1)
    ang = np.degrees(np.arccos(cos))
    return float(ang.mean()), float(ang.max())


def flops_table() -> None:
    """FLOPs of one 512^2, K=16 object (all pixels, sample sets of 10,000), counted on meta tensors."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from networks.config import get_config
    from networks.model import SDMUniPS

    def count(fn):
        with FlopCounterMode(display=False) as fc:
            fn()
        return fc.get_total_flops() / 1e12

    rows = {}
    for preset in ("paper", "small"):
        cfg = get_config(preset)
        side, k, m = 512, 16, 10000
        with torch.device("meta"):
            net = SDMUniPS(cfg).eval()
            x, mk = torch.empty(1, k, 3, side, side), torch.empty(1, 1, side, side)
            feats = net.encode(x, mk)
            enc = count(lambda: net.encode(x, mk))
            dec = count(lambda: net.decode(x, mk, feats, torch.zeros(1, m, dtype=torch.long)))
            reg = count(lambda: net.regressor(torch.empty(1, m, cfg.glc_aggregation_dim)))
        sets = side * side / m
        rows[preset] = {"encoder": enc, "per-pixel decoder": (dec - reg) * sets, "regressor": reg * sets,
                        "total": enc + dec * sets}
    print(f"{'TFLOP (512^2, K=16, all pixels)':34s} {'paper':>8s} {'small':>8s} {'ratio':>6s}")
    for part in rows["paper"]:
        p, s = rows["paper"][part], rows["small"][part]
        print(f"{part:34s} {p:8.2f} {s:8.2f} {p / s:6.1f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="only " + ", ".join(QUICK))
    ap.add_argument("--rows", help="comma-separated row names: " + ", ".join(ROWS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--flops", action="store_true", help="print the FLOP table and exit")
    ap.add_argument("--json", help="also write the results as JSON here")
    ap.add_argument("--_child", help=argparse.SUPPRESS)
    ap.add_argument("--_out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args._child:
        print(json.dumps(run_row(args._child, args.threads, args._out)))
        return 0
    if args.flops:
        flops_table()
        return 0
    rows = QUICK if args.quick else (args.rows.split(",") if args.rows else FULL)
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        ap.error(f"unknown rows {unknown}; choose from {list(ROWS)}")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        print(f"{'row':32s} {'pixels':>8s} {'wall s':>8s} {'peak RSS MB':>12s} {'bf16-fp32 normal deg (mean/max)':>32s}",
              flush=True)
        for row in rows:
            out = os.path.join(tmp, f"{row}.npz")
            env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
            proc = subprocess.run([sys.executable, __file__, "--_child", row, "--_out", out, "--threads",
                                   str(args.threads)], capture_output=True, text=True, env=env)
            if proc.returncode != 0:
                print(f"{row:32s} FAILED: {proc.stderr.strip().splitlines()[-1:]}", flush=True)
                continue
            rec = json.loads(proc.stdout.strip().splitlines()[-1])
            diff = ""
            if row.endswith("bf16"):
                ref = os.path.join(tmp, row[: -len("bf16")] + "fp32.npz")
                if os.path.exists(ref):
                    mean, mx = normal_diff_deg(ref, out)
                    rec["bf16_normal_mean_deg"], rec["bf16_normal_max_deg"] = mean, mx
                    diff = f"{mean:.3f} / {mx:.3f}"
                else:
                    diff = "(no fp32 row)"
            results.append(rec)
            print(f"{row:32s} {rec['pixels']:8d} {rec['wall_s']:8.1f} {rec['peak_rss_mb']:12.0f} {diff:>32s}",
                  flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

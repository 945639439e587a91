"""Throughput of `matcap synth` (train split): scenes/hour at a given resolution and spp.

    python benchmarks/bench_synth.py [--scenes 8] [--resolution 256] [--spp 16] [--assets ../shared/data]

Reports wall-clock scenes/hour and a CPU-time estimate (process CPU seconds / available cores), which is the
figure to trust when other jobs share the machine. The first scene (kernel compilation, asset loading) is
timed separately. Nothing is kept: the dataset goes to a temporary folder.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--assets", default=None)
    ap.add_argument("--seed", type=int, default=123)
    args = ap.parse_args()

    from matcap.synth import run_synth

    cores = len(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "d"
        w0, _c0 = time.perf_counter(), time.process_time()
        run_synth(out, 1, args.resolution, args.seed, assets=args.assets, spp=args.spp, progress=False)
        w1, c1 = time.perf_counter(), time.process_time()
        stats = run_synth(out, 1 + args.scenes, args.resolution, args.seed, assets=args.assets, spp=args.spp,
                          progress=False)
        w2, c2 = time.perf_counter(), time.process_time()
        size = sum(f.stat().st_size for f in out.glob("scene_*/*")) / (1 + args.scenes)
    n = args.scenes
    wall, cpu = (w2 - w1) / n, (c2 - c1) / n
    load = os.getloadavg()[0]
    result = {
        "resolution": args.resolution, "spp": args.spp, "scenes": n, "assets": bool(args.assets),
        "first_scene_s": round(w1 - w0, 2), "wall_s_per_scene": round(wall, 2), "cpu_s_per_scene": round(cpu, 2),
        "scenes_per_hour_wall": round(3600 / wall), f"scenes_per_hour_cpu_estimate_{cores}_cores": round(3600 / (cpu / cores)),
        "redrawn": stats["redrawn"], "mb_per_scene": round(size / 1e6, 2), "load_average_1min": round(load, 1),
        "cores": cores,
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

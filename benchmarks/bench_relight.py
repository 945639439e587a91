"""Relighting speed and noise: one 1024x1024 frame under an environment map at the default sample count.

    python benchmarks/bench_relight.py [--spp 16 32] [--texture-set DIR] [--env FILE] [--repeat 2]

Time: wall seconds of `renderers.relight.render` (scene build + render + mask), after one warm-up render
(kernel compilation is cached in ~/.drjit). Noise: per-pixel error against a 512-spp reference, measured at
256x256 (the per-pixel noise depends on the sample count, not the resolution), as relative RMSE of the linear
radiance and as RMS error in 8-bit levels of the tone-mapped PNG.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_TEX = REPO.parent / "shared" / "data" / "textures" / "painted_wooden_cabinet"


def main() -> None:
    from matcap.relight import default_envmap_path, load_envmap, load_maps, tonemap
    from renderers.relight import DEFAULT_SPP, render
    from scenes.lights import EnvironmentLight

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, nargs="+", default=[DEFAULT_SPP, 2 * DEFAULT_SPP])
    ap.add_argument("--texture-set", default=str(DEFAULT_TEX))
    ap.add_argument("--env", default=str(default_envmap_path()))
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--ref-spp", type=int, default=512)
    args = ap.parse_args()

    maps = load_maps(args.texture_set)
    env = {"env": load_envmap(args.env)}
    lights = [EnvironmentLight("env")]
    render(maps, lights, env, spp=1, size=(64, 64))  # warm-up: variant probe, kernel compilation
    ref = render(maps, lights, env, spp=args.ref_spp, size=(256, 256), seed=1234)
    print(f"maps {maps.shape[1]}x{maps.shape[0]} from {args.texture_set}; env {args.env}; "
          f"cpu count {os.cpu_count()}, load average {os.getloadavg()[0]:.2f}")
    print("| spp | seconds per 1024² frame (best of %d) | rel. RMSE (linear) | RMS error (8-bit PNG levels) |" % args.repeat)
    print("|---|---|---|---|")
    for spp in args.spp:
        times = []
        for r in range(args.repeat):
            t = time.perf_counter()
            render(maps, lights, env, spp=spp, size=(args.size, args.size), seed=r)
            times.append(time.perf_counter() - t)
        img = render(maps, lights, env, spp=spp, size=(256, 256), seed=7)
        rel = float(np.sqrt(np.mean((img - ref) ** 2)) / ref.mean())
        levels = float(np.sqrt(np.mean((tonemap(img) - tonemap(ref)) ** 2)) * 255)
        print(f"| {spp} | {min(times):.2f} | {rel:.3f} | {levels:.2f} |")


if __name__ == "__main__":
    main()

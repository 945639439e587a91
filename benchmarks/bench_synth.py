"""Throughput of `matcap synth` (train split): scenes/hour at a given resolution and spp.

    python benchmarks/bench_synth.py [--scenes 8] [--resolution 256] [--spp 16] [--assets ../shared/data]
    python benchmarks/bench_synth.py --basis-ab 6 --resolution 128 --assets ../shared/data

Reports wall-clock scenes/hour and a CPU-time estimate (process CPU seconds / available cores), which is the
figure to trust when other jobs share the machine. The first scene (kernel compilation, asset loading) is
timed separately. Nothing is kept: the dataset goes to a temporary folder.

``--compare N`` renders and writes N train-split scenes both ways, interleaved scene by scene so that a shared
machine's load hits both alike: fresh Mitsuba scenes per scene and per kind of light (``persistent=False``)
against one set of persistent Mitsuba scenes whose buffers are overwritten (what `matcap synth` does). It prints
CPU and wall seconds per scene and their ratio, and checks that both ways give the same images.

``--basis-ab N`` times only the basis renders of N train-split scenes, three rounds each way: one loaded Mitsuba
scene per kind of light whose emitter is updated between lights (what `matcap synth` does) against a freshly
loaded scene per light (``reuse=False``).
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


def basis_ab(scenes: int, resolution: int, spp: int, assets: str | None, seed: int) -> None:
    from matcap.synth import AssetCache, catalog_from_dir
    from renderers.synth import DELTA_SPP_FACTOR, SceneRenderer
    from scenes.lights import EnvironmentLight
    from scenes.synth_build import build_render_objects
    from scenes.synth_spec import generate_scene

    catalog, cache = catalog_from_dir(assets), AssetCache(assets)
    prepared = []
    for k in range(scenes):
        spec = generate_scene(seed, "train", k, resolution, catalog, 0)
        meshes, sets, envs = cache.for_spec(spec)
        prepared.append((build_render_objects(spec, meshes, sets), spec.lights(), envs))
    delta_spp = max(1, round(spp * DELTA_SPP_FACTOR))

    def run(reuse: bool) -> float:
        t0 = time.perf_counter()
        for objects, lights, envs in prepared:
            r = SceneRenderer(objects, resolution, spp, seed)
            for light in lights:
                r.render([light], envs, spp=None if isinstance(light, EnvironmentLight) else delta_spp, reuse=reuse)
        return time.perf_counter() - t0

    run(True), run(False)  # warm-up: kernel compilation, asset loading
    rows = [(run(True), run(False)) for _ in range(3)]
    print(f"| basis renders of {scenes} scenes at {resolution}², {spp} spp | reused scene | fresh scene per light |")
    print("|---|---:|---:|")
    for k, (a, b) in enumerate(rows):
        print(f"| round {k + 1} | {a:.2f} s | {b:.2f} s |")
    a, b = (sum(x) / len(rows) for x in zip(*rows))
    print(f"| mean | {a:.2f} s | {b:.2f} s ({1 - a / b:.0%} saved) |")


def compare(scenes: int, resolution: int, spp: int, assets: str | None, seed: int, data_version: int = 1) -> None:
    import numpy as np

    from matcap.synth import AssetCache, catalog_from_dir, render_spec, write_scene
    from scenes.synth_spec import generate_scene

    catalog = catalog_from_dir(assets)
    caches = {False: AssetCache(assets), True: AssetCache(assets)}
    times = {False: [], True: []}
    worst = 0.0
    kwargs = {} if data_version == 1 else {"data_version": data_version}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(scenes + 1):  # scene 0 warms up both ways (kernel compilation, asset loading)
            spec = generate_scene(seed, "train", k, resolution, catalog, 0, **kwargs)
            results = {}
            for persistent in ((False, True) if k % 2 else (True, False)):
                w0, c0 = time.perf_counter(), time.process_time()
                results[persistent] = render_spec(spec, caches[persistent], spp, persistent=persistent)
                write_scene(results[persistent], Path(tmp) / f"{k}_{persistent}")
                if k:
                    times[persistent].append((time.process_time() - c0, time.perf_counter() - w0))
            a, b = results[True].render.basis, results[False].render.basis
            worst = max(worst, float(np.abs(a - b).max()))
    cores = len(os.sched_getaffinity(0))
    print(f"| {scenes} train scenes at {resolution}², {spp} spp, 10 images + ground truth, written | CPU s/scene | "
          f"wall s/scene | scenes/h ({cores} cores, from CPU time) |")
    print("|---|---:|---:|---:|")
    rows = {}
    for persistent, label in ((False, "fresh Mitsuba scenes (before)"), (True, "persistent scenes (now)")):
        cpu = sum(t[0] for t in times[persistent]) / scenes
        wall = sum(t[1] for t in times[persistent]) / scenes
        rows[persistent] = (cpu, wall)
        print(f"| {label} | {cpu:.2f} | {wall:.2f} | {3600 / (cpu / cores):.0f} |")
    print(f"| ratio before / now | {rows[False][0] / rows[True][0]:.2f}x | {rows[False][1] / rows[True][1]:.2f}x | |")
    print(f"largest basis-render difference between the two ways: {worst:.2e}; load average {os.getloadavg()[0]:.1f}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--assets", default=None)
    ap.add_argument("--seed", type=int, default=123)
    ap.add_argument("--basis-ab", type=int, metavar="N", help="time basis renders only: reused vs fresh scenes")
    ap.add_argument("--compare", type=int, metavar="N", help="whole scenes: fresh vs persistent Mitsuba scenes")
    ap.add_argument("--data-version", type=int, default=1, help="scene generator version for --compare")
    args = ap.parse_args()
    if args.compare:
        compare(args.compare, args.resolution, args.spp, args.assets, args.seed, args.data_version)
        return
    if args.basis_ab:
        basis_ab(args.basis_ab, args.resolution, args.spp, args.assets, args.seed)
        return

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

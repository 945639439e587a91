"""A large flat sample end to end: time and peak memory of `matcap capture --flat` on full-size photos (a table).

    python benchmarks/flat_large.py                          # 4000 x 3000, 16 photos, near lamps, wood_table_worn
    python benchmarks/flat_large.py --width 2000 --height 1500 --set curtain --work W   # W keeps the photos

A CC0 texture set of ``shared/data/textures`` (:func:`flat_check.load_sample` at 2048 px, then stretched to
``--width`` x ``--height``) is photographed under the near lamps of :mod:`flat_check` (1-3 sample widths away,
16-bit linear PNGs). The photos are rendered with the fit's own Principled model
(:func:`matcap.refine.model.shade_fast`; a Mitsuba render of 12 MP x 16 would take longer than the capture), so
the scores say little about accuracy (``flat_check.py`` measures that); the point is the time and memory. Then
``matcap capture photos --flat --linear --quiet`` runs in a subprocess with ``--threads`` CPU threads; the table
gives its wall seconds, the stage timings it recorded, the peak resident memory of the process, and the normal /
base colour scores of the result against the truth.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import flat_check as fc  # noqa: E402


def render(maps, lights, rows_per_chunk: int = 256) -> list[np.ndarray]:
    """(H, W, 3) linear photos of ``maps`` on the framing plane under each point light of ``lights``, with
    :func:`matcap.refine.model.shade_fast` (no ambient), row band by row band."""
    import torch

    from matcap.refine.model import LightParams, plane_positions, shade_fast

    h, w = maps.shape
    out = []
    for light in lights:
        pos = torch.tensor([light.position], dtype=torch.float32)
        lp = LightParams("point", pos, torch.log(torch.tensor([light.intensity], dtype=torch.float32)),
                         torch.zeros(1, 9, 3))
        img = np.zeros((h, w, 3), np.float32)
        for r0 in range(0, h, rows_per_chunk):
            r1 = min(h, r0 + rows_per_chunk)
            rr, cc = np.mgrid[r0:r1, 0:w]
            rr, cc = rr.ravel(), cc.ravel()
            with torch.no_grad():
                wo, irr = lp.incident(plane_positions(torch.from_numpy(rr), torch.from_numpy(cc), h, w))
                t = lambda a: torch.from_numpy(np.ascontiguousarray(a[rr, cc]))  # noqa: E731
                px = shade_fast(t(maps.normal), t(maps.base_color), t(maps.roughness), t(maps.metallic), wo, irr,
                                lp.sh)
            img[r0:r1] = np.clip(px[0].numpy(), 0.0, 1.0).reshape(r1 - r0, w, 3)
        out.append(img)
    return out


def stretched_sample(set_name: str, width: int, height: int):
    """The texture set as a ``width`` x ``height`` flat sample (MaterialMaps): read at 2048 px, resized."""
    import cv2

    from scenes.materialmaps import MaterialMaps

    maps, _ = fc.load_sample(fc.TEXTURES / set_name, 2048)
    size = (width, height)
    n = cv2.resize(maps.normal, size, interpolation=cv2.INTER_LINEAR)
    n /= np.linalg.norm(n, axis=2, keepdims=True).clip(1e-6)
    lin = lambda a: np.clip(cv2.resize(a, size, interpolation=cv2.INTER_LINEAR), 0.0, 1.0)  # noqa: E731
    return MaterialMaps(normal=n, mask=np.ones((height, width), bool), base_color=lin(maps.base_color),
                        roughness=lin(maps.roughness), metallic=lin(maps.metallic))


def error_blocks(normal: np.ndarray, truth: np.ndarray, blocks: int = 4) -> tuple[float, float]:
    """(median angular error, worst mean over a ``blocks`` x ``blocks`` grid of the image) in degrees: a failure
    confined to one part of the swatch shows in the second, the overall level in the first."""
    from matcap.evaluation.metrics import angular_error_map

    err = angular_error_map(normal, truth)
    h, w = err.shape[0] // blocks * blocks, err.shape[1] // blocks * blocks
    grid = err[:h, :w].reshape(blocks, h // blocks, blocks, w // blocks).mean(axis=(1, 3))
    return float(np.median(err)), float(grid.max())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--set", default="wood_table_worn", help="texture set (default wood_table_worn)")
    p.add_argument("--width", type=int, default=4000)
    p.add_argument("--height", type=int, default=3000)
    p.add_argument("--photos", type=int, default=16)
    p.add_argument("--threads", type=int, default=2, help="CPU threads of the capture (default 2)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--work", help="folder for the photos and the result (default: a new one under /tmp); photos "
                                  "already there are reused")
    args = p.parse_args(argv)
    work = Path(args.work) if args.work else Path(f"/tmp/flat_large_{args.width}x{args.height}")
    sample = work / "sample"
    if not (sample / "sample.json").is_file():
        t0 = time.perf_counter()
        truth_maps = stretched_sample(args.set, args.width, args.height)
        lights = fc.make_lights("near", args.photos, args.seed)
        photos = render(truth_maps, lights)
        fc.write_sample(sample, truth_maps, lights, photos,
                        {"set": args.set, "size_wh": [args.width, args.height], "photos": args.photos,
                         "render": "matcap.refine.model.shade_fast", "render_s": time.perf_counter() - t0})
        del photos
    out = work / "result"
    env = dict(fc._env(), OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads))
    cmd = [sys.executable, "-m", "matcap", "capture", str(sample / "photos"), "--flat", "--linear", "--quiet",
           "--overwrite", "--out", str(out)]
    t0 = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=fc.REPO)
    wall = time.perf_counter() - t0
    peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024 ** 2  # KiB -> GiB
    if run.returncode != 0:
        print(run.stderr.strip().splitlines()[-1] if run.stderr.strip() else f"exit {run.returncode}")
        return 1
    from matcap.results import read_result

    doc = json.loads((out / "capture.json").read_text())
    timings = doc.get("timings", {})
    fit_timings = json.loads((out / "fit.json").read_text())["timings"]
    result, truth = read_result(out), fc.read_truth(sample)
    scores = fc.score(result, truth, rough_constant=False)
    median, worst = error_blocks(result.normal, truth["normal"])
    print(f"`matcap capture --flat` of a {args.width} x {args.height} swatch ({args.set}), {args.photos} photos, "
          f"{args.threads} threads\n")
    print("| wall (s) | networks (s) | fit (s) | fit stages (s) | peak memory (GiB) | networks saw | normal (deg) | "
          "median / worst sixteenth (deg) | base colour % below const. |")
    print("|---|---|---|---|---|---|---|---|---|")
    stages = ", ".join(f"{k[:-2]} {v:.0f}" for k, v in fit_timings.items() if k != "total_s")
    saw = "x".join(str(v) for v in doc.get("network_size_wh", []))
    nets = sum(v for k, v in timings.items() if k in ("normal_s", "brdf_s"))
    print(f"| {wall:.0f} | {nets:.0f} | {fit_timings['total_s']:.0f} | {stages} | "
          f"{peak_gb:.1f} | {saw} | {scores['normal_deg']:.2f} | {median:.2f} / {worst:.2f} | "
          f"{scores.get('base_below_pct', float('nan')):.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

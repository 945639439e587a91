"""The bundled normal model on a sphere with analytic ground truth: the ToyPS sphere (SDPS-Net renders, 50 images).

    python benchmarks/sphere_check.py [--capture ../shared/data/captures/toyps_sphere] [--views 1,4]

The truth comes from the silhouette (``matcap.evaluation.metrics.analytic_sphere``). Rows: every normal facing the
camera; the bundled model with the 8-bit images sRGB-decoded (the default for photos) and taken as linear
(`matcap capture --linear`; the ToyPS images are linear renders); with test-time views. Prints a Markdown table:
mean / median angular error in degrees over the disc (rim left out) and the seconds per run.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    from matcap.estimate import estimate, load_networks
    from matcap.evaluation.metrics import analytic_sphere, angular_error_map
    from matcap.photos import load_capture

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    repo = Path(__file__).resolve().parents[1]
    ap.add_argument("--capture", default=str(repo.parent / "shared" / "data" / "captures" / "toyps_sphere"))
    ap.add_argument("--views", default="1,4", help="test-time views for the linear rows (default 1,4)")
    args = ap.parse_args(argv)
    models = load_networks([repo / "networks" / "weights" / "normal_small.safetensors"])
    print(f"`{args.capture}`: bundled normal_small vs the analytic sphere; degrees over the disc without its rim")
    print("| prediction | mean | median | s |")
    print("|---|---:|---:|---:|")
    rows = [("flat (every normal faces the camera)", None, 1), ("sRGB-decoded input (the default)", False, 1)]
    rows += [(f"linear input (`--linear`){f', --views {v}' if v > 1 else ''}", True, v)
             for v in (int(x) for x in args.views.split(","))]
    captures = {linear: load_capture(args.capture, linear=linear) for linear in (False, True)}  # read once each
    truth, scored = analytic_sphere(captures[False].mask)
    for label, linear, views in rows:
        cap = captures[bool(linear)]
        t0 = time.perf_counter()
        if linear is None:
            normal = np.zeros(truth.shape, np.float32)
            normal[..., 2] = 1
        else:
            normal = estimate(cap.images, cap.mask, models=models, seed=0, views=views).normal
        err = angular_error_map(normal, truth, scored)[scored]
        print(f"| {label} | {err.mean():.2f} | {np.median(err):.2f} | {time.perf_counter() - t0:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

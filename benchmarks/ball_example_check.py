"""The bundled known-lights example (`examples/ball`: Spot and a chrome ball, 16 lights) captured three ways, its
object normals against the rendered truth (`normal_gt.exr`).

    python benchmarks/ball_example_check.py [--example examples/ball] [--set KEY=VALUE ...]

Rows: the capture (`matcap.capture.capture`, as `matcap capture` runs it) with the lights unknown (estimated), with
`--ball auto` (calibrated from the ball in the photos) and with `--lights lights.json` (the true lights); ``--set``
changes a fit setting (`RefineSettings.replace`, e.g. ``loss.shadow=0``). Columns: mean, median and 90th percentile
of the angle to the true normal over the object's mask, the mean over its interior (the mask eroded by 2 px: the
outline's pixels mix object and backdrop, which one normal per pixel cannot describe), the re-render PSNR, and the
time.
"""
from __future__ import annotations

import argparse
import ast
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main(argv: list[str] | None = None) -> int:
    from scipy import ndimage

    from matcap.capture import capture
    from matcap.evaluation.metrics import angular_error_map
    from matcap.imageio import read_exr
    from matcap.refine import RefineSettings

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--example", default=str(REPO / "examples" / "ball"))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a fit setting")
    args = ap.parse_args(argv)
    settings = RefineSettings(seed=0).replace({k: ast.literal_eval(v) for k, v in
                                               (item.split("=", 1) for item in args.set)})
    example = Path(args.example)
    truth = read_exr(example / "normal_gt.exr")[..., :3]
    mask = np.linalg.norm(truth, axis=-1) > 0.5
    inner = ndimage.binary_erosion(mask, iterations=2)
    ways = [("lights estimated", {}), ("`--ball auto`", {"ball": "auto"}),
            ("`--lights lights.json` (true)", {"lights": example / "lights.json"})]
    print(f"`{example}`: object normals vs `normal_gt.exr` (degrees; {int(mask.sum())} object pixels, "
          f"{int(inner.sum())} inside){' with ' + ', '.join(args.set) if args.set else ''}")
    print("| lights | mean | median | p90 | interior mean | re-render PSNR dB | s |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, more) in enumerate(ways):
            out = Path(tmp) / f"r{i}"
            t = time.perf_counter()
            capture(example, out, linear=None, refine=True, refine_settings=settings, **more)
            seconds = time.perf_counter() - t
            err = angular_error_map(read_exr(out / "normal.exr")[..., :3], truth, mask)
            psnr = json.loads((out / "fit.json").read_text())["psnr_db_mean"]
            print(f"| {label} | {err[mask].mean():.2f} | {np.median(err[mask]):.2f} | "
                  f"{np.percentile(err[mask], 90):.2f} | {err[inner].mean():.2f} | {psnr:.1f} | {seconds:.1f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

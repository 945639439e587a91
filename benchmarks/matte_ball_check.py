"""The estimated-lights fit on a rendered matte ball: is it ever worse than the networks?

    python benchmarks/matte_ball_check.py [--side 192] [--seeds 0,1,2] [--threads 1] [--set KEY=VALUE ...]
    python benchmarks/matte_ball_check.py --unequal 0          # lamps of equal power
    python benchmarks/matte_ball_check.py --brdf principled    # rendered with the fit's own model (a control)

A Lambertian sphere (:func:`matcap.refine.synthetic.matte_ball`: a DiLiGenT-ball-like capture, 16 distant lamps
within 45 degrees of the view axis, lamps of unequal power (``--unequal``), a slightly varying grey-brown albedo, a
weak sky-like ambient, photon and read noise, 16-bit linear PNGs, attached shadows, no cast shadows) is written to
a capture folder and run through the bundled networks (``matcap.capture.estimate``, the "before") and :func:`matcap.refine.refine` (the "after"). Prints a
Markdown table: mean normal error against the analytic sphere (``analytic_sphere`` of the mask), light-direction
error against the true lamps (median / max degrees), re-render PSNR, the check.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from matcap.refine.synthetic import matte_ball  # noqa: E402
from refine_check import _angle, _mean_err  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
from refine_check import _settings as refine_settings  # noqa: E402


def _settings(items):
    """RefineSettings(seed=0) with ``--set KEY=VALUE`` overrides, as refine_check.py reads them."""
    return refine_settings(argparse.Namespace(set=items))


def run_ball(folder: Path, models, settings, true_dirs=None, cache: Path | None = None) -> dict:
    """Networks then the fit on the capture in ``folder``: {network, fit, light_median, light_max, psnr, report}."""
    from matcap.capture import estimate, load_capture
    from matcap.evaluation.metrics import analytic_sphere
    from matcap.refine import refine
    from scenes.materialmaps import MaterialMaps

    cap = load_capture(folder, linear=True)
    if cache is not None and cache.exists():
        z = np.load(cache)
        maps = MaterialMaps(**{k: z[k] for k in ("normal", "mask", "base_color", "roughness", "metallic")},
                            meta={"images_used": list(range(len(cap.images)))})
    else:
        maps = estimate(cap.images, cap.mask, models=models, seed=0)
        if cache is not None:
            np.savez(cache, normal=maps.normal, mask=maps.mask, base_color=maps.base_color,
                     roughness=maps.roughness, metallic=maps.metallic)
    truth, scored = analytic_sphere(cap.mask)
    scored = scored & maps.mask
    res = refine(cap.images, maps, settings)
    out = {"network": _mean_err(maps.normal, truth, scored), "fit": _mean_err(res.maps.normal, truth, scored),
           "psnr": res.report["psnr_db_mean"], "report": res.report, "maps": maps, "images": cap.images}
    if true_dirs is not None:
        d = [_angle(e["direction"] if "direction" in e else e["position"], t) for e, t in zip(res.lights, true_dirs)]
        out["light_median"], out["light_max"] = float(np.median(d)), float(np.max(d))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--side", type=int, default=192)
    ap.add_argument("--seeds", default="0,1,2", help="one ball per seed (lamps, albedo, noise)")
    ap.add_argument("--unequal", type=float, default=0.3, help="lamp power in [1 - u, 1 + u] (default 0.3)")
    ap.add_argument("--ambient", type=float, default=0.02)
    ap.add_argument("--max-polar", type=float, default=45.0, help="lamps within this many degrees of the view")
    ap.add_argument("--brdf", choices=("lambert", "principled"), default="lambert",
                    help="lambert (default), or the fit's own Principled model at --roughness")
    ap.add_argument("--roughness", type=float, default=0.8)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--set", action="append", help="RefineSettings group.field=value (repeatable)")
    ap.add_argument("--keep", default=None, help="write the captures (and cached network maps) under this folder")
    args = ap.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    from matcap.capture import load_networks

    models = load_networks(None)
    settings = _settings(args.set)
    print(f"matte ball {args.side}^2, 16 lamps within {args.max_polar:g} deg, power +-{args.unequal:g}, ambient "
          f"{args.ambient:g}, 16-bit with photon + read noise; normals vs the analytic sphere (mean deg), lights vs "
          f"the true lamps (median / max deg)")
    print("| seed | network | fit | lights median | lights max | PSNR dB | check |")
    print("|---|---:|---:|---:|---:|---:|---|")
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="matte_ball_"))
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        folder = root / (f"ball_{args.side}_s{seed}_u{args.unequal:g}_a{args.ambient:g}_p{args.max_polar:g}"
                         + (f"_principled{args.roughness:g}" if args.brdf == "principled" else ""))
        truth = matte_ball(folder, args.side, seed, unequal=args.unequal, ambient=args.ambient,
                           max_polar_deg=args.max_polar, brdf=args.brdf, roughness=args.roughness)
        cache = folder.parent / f"{folder.name}.maps.npz" if args.keep else None
        t0 = time.perf_counter()
        r = run_ball(folder, models, settings, truth["directions"], cache)
        lin = r["report"].get("linear") or {}
        check = "kept: " + str(lin.get("reason")) if r["report"]["kept_network_maps"] else "fitted"
        rows.append((r["network"], r["fit"], r["light_median"], r["light_max"], r["psnr"]))
        print(f"| {seed} | {r['network']:.2f} | {r['fit']:.2f} | {r['light_median']:.2f} | {r['light_max']:.2f} | "
              f"{r['psnr']:.2f} | {check} ({time.perf_counter() - t0:.0f} s) |", flush=True)
    a = np.array(rows).mean(0)
    print(f"| **mean** | {a[0]:.2f} | {a[1]:.2f} | {a[2]:.2f} | {a[3]:.2f} | {a[4]:.2f} | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The estimated-lights fit on a rendered matte ball: is it ever worse than the networks?

    python benchmarks/matte_ball_check.py [--side 192] [--seeds 0,1,2] [--threads 1] [--set KEY=VALUE ...]
    python benchmarks/matte_ball_check.py --unequal 0          # lamps of equal power
    python benchmarks/matte_ball_check.py --brdf principled    # rendered with the fit's own model (a control)
    python benchmarks/matte_ball_check.py --capture ../shared/data/captures/uw_gray --max-side 160   # a real ball
    python benchmarks/matte_ball_check.py --capture ../shared/data/captures/uw_gray --lights rig.json  # its rig's

A Lambertian sphere (:func:`matcap.refine.synthetic.matte_ball`: a DiLiGenT-ball-like capture, 16 distant lamps
within 45 degrees of the view axis, lamps of unequal power (``--unequal``), a slightly varying grey-brown albedo, a
weak sky-like ambient, photon and read noise, 16-bit linear PNGs, attached shadows, no cast shadows) is written to
a capture folder and run through the bundled networks (``matcap.estimate.estimate``, the "before") and
:func:`matcap.refine.refine` (the "after"). Prints a Markdown table: mean normal error against the analytic sphere
(``analytic_sphere`` of the mask), light-direction error against the true lamps (median / max degrees), re-render
PSNR, the check, and the fit given the true lamps (``lights.txt``: the known-lights fit).

``--capture FOLDER`` (repeatable) runs photographed balls instead: a folder of photos whose mask is the ball's
disc, with a ``lights.txt`` (the UW gray ball: 12 photos, 8-bit read as linear), shrunk to ``--max-side``;
``--lights FILE`` gives the known-lights fit that file instead (a calibration's ``rig.json``: ``matcap calibrate
../shared/data/captures/uw_chrome --out rig.json``); the light columns still compare with ``lights.txt``.
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


def run_ball(folder: Path, models, settings, true_dirs=None, cache: Path | None = None,
             max_side: int | None = None, lights_file: Path | None = None) -> dict:
    """Networks then the fit on the capture in ``folder`` (photos shrunk to ``max_side``), lights estimated and,
    where ``folder`` has a ``lights.txt``, given (``lights_file`` where given, else that ``lights.txt``):
    {network, fit, fit_known, light_median, light_max, psnr, report}."""
    from matcap.estimate import estimate
    from matcap.evaluation.metrics import analytic_sphere
    from matcap.photos import load_capture
    from matcap.refine import refine
    from scenes.materialmaps import MaterialMaps

    from matcap.lightfiles import read_light_file

    cap = load_capture(folder, linear=True, max_side=max_side)
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
    fit_known = known = None
    if (folder / "lights.txt").is_file():
        known = read_light_file(folder / "lights.txt", [Path(f).name for f in cap.files])
        given = known if lights_file is None else read_light_file(lights_file, [Path(f).name for f in cap.files])
        fit_known = _mean_err(refine(cap.images, maps, settings, lights=given).maps.normal, truth, scored)
    out = {"network": _mean_err(maps.normal, truth, scored), "fit": _mean_err(res.maps.normal, truth, scored),
           "fit_known": fit_known,
           "psnr": res.report["psnr_db_mean"], "report": res.report, "maps": maps, "images": cap.images}
    if true_dirs is None and known is not None:  # a photographed ball: its lights.txt
        true_dirs = known.directions
    if true_dirs is not None:
        d = [_angle(e["direction"] if "direction" in e else e["position"], t) for e, t in zip(res.lights, true_dirs)]
        out["light_median"], out["light_max"] = float(np.median(d)), float(np.max(d))
    return out


def _balls(args, root: Path):
    """(name, folder, true light directions (K, 3) or None (those of its lights.txt), max_side) of every ball to
    run: the rendered seeds, written under ``root``, or the ``--capture`` folders with their ``lights.txt``."""
    if args.capture:
        for c in args.capture:  # the true lamps are the lights.txt that run_ball reads
            yield Path(c).name, Path(c), None, args.max_side
        return
    for seed in (int(s) for s in args.seeds.split(",")):
        folder = root / (f"ball_{args.side}_s{seed}_u{args.unequal:g}_a{args.ambient:g}_p{args.max_polar:g}"
                         + (f"_principled{args.roughness:g}" if args.brdf == "principled" else ""))
        truth = matte_ball(folder, args.side, seed, unequal=args.unequal, ambient=args.ambient,
                           max_polar_deg=args.max_polar, brdf=args.brdf, roughness=args.roughness)
        yield f"seed {seed}", folder, truth["directions"], None


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
    ap.add_argument("--capture", action="append", help="a photographed ball's folder instead (repeatable)")
    ap.add_argument("--max-side", type=int, default=160, help="--capture: photos shrunk to this side")
    ap.add_argument("--lights", type=Path, default=None,
                    help="--capture: the light file of the known-lights fit (default: each folder's lights.txt)")
    args = ap.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    from matcap.estimate import load_networks

    models = load_networks(None)
    settings = _settings(args.set)
    if args.capture:
        print(f"photographed balls (8-bit read as linear, --max-side {args.max_side}); normals vs the analytic sphere "
              f"of the mask (mean deg), lights vs lights.txt (median / max deg)")
    else:
        print(f"matte ball {args.side}^2, 16 lamps within {args.max_polar:g} deg, power +-{args.unequal:g}, ambient "
              f"{args.ambient:g}, 16-bit with photon + read noise; normals vs the analytic sphere (mean deg), lights "
              f"vs the true lamps (median / max deg)")
    print("| ball | network | fit | fit, lights given | lights median | lights max | PSNR dB | check |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="matte_ball_"))
    rows = []
    for name, folder, dirs, max_side in _balls(args, root):
        cache = folder.parent / f"{folder.name}.maps.npz" if args.keep else None
        t0 = time.perf_counter()
        r = run_ball(folder, models, settings, dirs, cache, max_side, args.lights)
        lin = r["report"].get("linear") or {}
        check = "kept: " + str(lin.get("reason")) if r["report"]["kept_network_maps"] else "fitted"
        rows.append((r["network"], r["fit"], r["fit_known"], r["light_median"], r["light_max"], r["psnr"]))
        print(f"| {name} | {r['network']:.2f} | {r['fit']:.2f} | {r['fit_known']:.2f} | {r['light_median']:.2f} | "
              f"{r['light_max']:.2f} | {r['psnr']:.2f} | {check} ({time.perf_counter() - t0:.0f} s) |", flush=True)
    a = np.array(rows).mean(0)
    print(f"| **mean** | {a[0]:.2f} | {a[1]:.2f} | {a[2]:.2f} | {a[3]:.2f} | {a[4]:.2f} | {a[5]:.2f} | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

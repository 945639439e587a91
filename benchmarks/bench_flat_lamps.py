"""How long finding a flat sample's lamps takes (matcap.refine.flat.plane_lamps), old code against new (Markdown).

    python benchmarks/bench_flat_lamps.py                        # three swatches, near lamps, 128 px, 16 photos
    python benchmarks/bench_flat_lamps.py --old main --sets sofa_03,bell_pepper --repeats 2

The swatches are rendered as ``benchmarks/flat_check.py`` renders them (its ``near`` condition: point lamps 1-3
sample widths away). ``--old REV``: ``matcap/refine/flat.py`` of that git revision, imported beside this one (the rest
of matcap is this checkout's), timed alternately with this one on the same photos. One torch thread. Columns: wall
seconds of ``plane_lamps``, the median and largest lamp position error (in lamp distances from the sample's centre),
the median and largest angle between the found and true directions from the centre, whether the falloff placed the
lamps, and which step placed them (``plane``: the plane under the Principled BSDF; ``free normals``: near-light
photometric stereo).
"""
from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _old_module(rev: str):
    """``matcap/refine/flat.py`` of git revision ``rev`` as a module of its own."""
    text = subprocess.run(["git", "show", f"{rev}:matcap/refine/flat.py"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout
    path = Path(tempfile.mkdtemp(prefix="flat_old-")) / "flat_old.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("flat_old", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["flat_old"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def main(argv=None) -> int:
    import torch

    import flat_check as fc
    from matcap.refine import flat as new

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="sofa_03,bell_pepper,painted_wooden_stool", help="texture sets, comma-separated, or 'all'")
    ap.add_argument("--size", type=int, default=128, help="swatch side in pixels (default 128)")
    ap.add_argument("--old", default=None, help="git revision to compare with")
    ap.add_argument("--repeats", type=int, default=1, help="timings per code and swatch (default 1)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    codes = [("this", new)] + ([(args.old, _old_module(args.old))] if args.old else [])
    print("| swatch | code | seconds | position error median / max | angle median / max (deg) | lamps placed "
          "| placed by |")
    print("|---|---|---:|---|---|---|---|")
    for name in fc.texture_sets() if args.sets == "all" else args.sets.split(","):
        maps, _ = fc.load_sample(fc.TEXTURES / name, args.size)
        lights = fc.make_lights("near", 16, 0)  # as flat_check.py draws them
        photos = fc.render_photos(maps, lights)
        truth = np.array([light.position for light in lights], float)
        mask = np.ones(photos[0].shape[:2], bool)
        for _ in range(args.repeats):
            for label, module in codes:
                t0 = time.perf_counter()
                lamps = module.plane_lamps(photos, mask)
                secs = time.perf_counter() - t0
                err = np.linalg.norm(lamps.positions - truth, axis=1) / np.linalg.norm(truth - lamps.centre, axis=1)
                toward = (truth - lamps.centre) / np.linalg.norm(truth - lamps.centre, axis=1, keepdims=True)
                ang = np.degrees(np.arccos(np.clip((lamps.directions * toward).sum(1), -1.0, 1.0)))
                by = ("plane" if getattr(lamps, "plane_placed", False) else "free normals") if lamps.near else "-"
                print(f"| {name} | {label} | {secs:.1f} | {np.median(err):.3f} / {err.max():.3f} | "
                      f"{np.median(ang):.1f} / {ang.max():.1f} | {lamps.near} | {by} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

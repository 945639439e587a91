"""Why a flat sample under distant lights of unknown direction keeps the plane's normals. Prints a table.

    python benchmarks/flat_twin.py                      # all 11 CC0 texture sets, 64 px, 4 distant lights
    python benchmarks/flat_twin.py --sets sofa_03 --size 128 --photos 16

Each texture set is rendered as :mod:`flat_check` renders it under distant lights (its "far" condition), and so is
its **twin**: the same swatch with its relief turned inside out (the normal map's x and y negated: every bump a
dent) under the same lights turned half a circle about the camera axis (their x and y negated). An isotropic BSDF
seen by an orthographic camera depends only on the angles between the normal, the light and the view, and this
turn keeps every one of them, so the two sets of photos are the same (the table's PSNR between them, against a
second render of the swatch itself with another sampling seed). Any method that is given only the photos then
returns one normal map for both swatches; a map whose tilts are ``c`` times the true ones is off by about
``|1 - c|`` times the tilt on the swatch and ``|1 + c|`` times on its twin, so over the pair none is closer than
the plane (``c`` = 0), whose error the table gives beside the true map's on the twin (about twice the plane's).
Lights that are given (a file, a mirror ball) or near enough for their falloff to show tell the two apart.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import flat_check  # noqa: E402


def twin(maps, lights):
    """The swatch's twin: ``maps`` with the normal map's x and y negated, ``lights`` turned half a circle."""
    from scenes.lights import DirectionalLight

    turned = [DirectionalLight((-light.direction[0], -light.direction[1], light.direction[2]), light.irradiance)
              for light in lights]
    return dataclasses.replace(maps, normal=maps.normal * np.array([-1.0, -1.0, 1.0], np.float32)), turned


def psnr(a: list, b: list) -> float:
    """PSNR (dB, peak 1) between two lists of photos."""
    mse = np.mean([np.mean((np.asarray(x, np.float64) - np.asarray(y, np.float64)) ** 2) for x, y in zip(a, b)])
    return float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))


def main(argv=None) -> int:
    sets = flat_check.texture_sets()
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sets", default=",".join(sets), help="comma-separated texture sets (default: all)")
    p.add_argument("--size", type=int, default=64, help="sample side in pixels (default 64)")
    p.add_argument("--photos", type=int, default=4, help="distant lights (default 4)")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    args = p.parse_args(argv)
    chosen = [s for s in args.sets.split(",") if s]
    unknown = sorted(set(chosen) - set(sets))
    if unknown:
        p.error(f"unknown texture sets: {', '.join(unknown)} (known: {', '.join(sets)})")
    print("| set | photos vs twin's (dB) | vs another seed (dB) | plane's normals (deg) | "
          "true normals on the twin (deg) |")
    print("|---|---:|---:|---:|---:|")
    for name in chosen:
        maps, _ = flat_check.load_sample(flat_check.TEXTURES / name, args.size)
        lights = flat_check.make_lights("far", args.photos, 0, args.size)
        photos = flat_check.render_photos(maps, lights, spp=args.spp, seed=1)
        twin_maps, twin_lights = twin(maps, lights)
        twins = flat_check.render_photos(twin_maps, twin_lights, spp=args.spp, seed=1)
        reseeded = flat_check.render_photos(maps, lights, spp=args.spp, seed=2)
        print(f"| {name} | {psnr(photos, twins):.1f} | {psnr(photos, reseeded):.1f} | "
              f"{flat_check.flat_baseline({'normal': maps.normal})['normal_deg']:.2f} | "
              f"{flat_check.mean_angular_error(maps.normal, twin_maps.normal):.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

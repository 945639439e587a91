"""Make ``examples/ball``: a glossy object (Spot the cow, CC0) with a chrome ball beside it, 16 photos under known
distant lights, rendered with Mitsuba 3 (``renderers.ballscene.example_scene``), so that a capture can take its
lights from the ball (``matcap calibrate``) and be compared with the unknown-light path.

Writes into ``--out`` (default ``examples/ball``): ``photo_01.png`` ... ``photo_16.png`` (16-bit PNG, linear,
the render times ``--exposure``; the ball's highlights clip, as in a camera), ``mask.png`` (the object only, 8-bit),
``lights.json`` (the true lights: directions, irradiance times the exposure, the uniform ambient as SH, in photo
order, with file names),
``normal_gt.exr`` (the object's camera-space normals, half float; zeros elsewhere) and ``mask_ball.png`` (the
ball's disc, for ``matcap calibrate --ball-mask``). Same seed, same files (the renders are deterministic).

    PYTHONPATH=. python examples/make_ball_example.py [--mesh ../shared/data/meshes/spot.ply] [--size 256]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DEFAULT_MESH = REPO.parent / "shared" / "data" / "meshes" / "spot.ply"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(REPO / "examples" / "ball"))
    ap.add_argument("--mesh", default=str(DEFAULT_MESH), help="Spot (Keenan Crane, CC0) as PLY or OBJ")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exposure", type=float, default=1.0, help="scale of the linear render before 16-bit")
    args = ap.parse_args(argv)

    import trimesh

    from matcap.imageio import write_exr, write_png
    from matcap.refine.lightfile import SH_C0, write_lights
    from renderers.ballscene import example_scene, render

    mesh = trimesh.load(args.mesh, force="mesh", process=False)
    scene = example_scene((np.asarray(mesh.vertices), np.asarray(mesh.faces)), count=16, seed=args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    r = render(scene, size=args.size, spp=args.spp, seed=args.seed)
    names = []
    for k, img in enumerate(r.images):
        name = f"photo_{k + 1:02d}.png"
        write_png(out / name, np.clip(img * args.exposure, 0, 1), bits=16)
        names.append(name)
    write_png(out / "mask.png", r.object_mask.astype(np.float32), bits=8)
    write_png(out / "mask_ball.png", r.ball_mask.astype(np.float32), bits=8)
    write_exr(out / "normal_gt.exr", r.normal, half=True)
    cx, cy, rad = r.circle
    # the scene's uniform ambient radiance as order-2 SH (only the constant term: radiance = c0 * Y00)
    sh = [[scene.ambient / SH_C0 * args.exposure] * 3] + [[0.0, 0.0, 0.0]] * 8
    entries = [{"index": k, "file": names[k], "kind": "directional", "direction": [float(v) for v in r.directions[k]],
                "intensity": [float(v) * args.exposure for v in r.irradiance[k]], "sh": sh}
               for k in range(len(names))]
    write_lights(out / "lights.json", entries, source="rendered (true lights)", camera="orthographic",
                 ball={"circle_px": [cx, cy, rad], "image_size_wh": [args.size, args.size]},
                 made_by=f"examples/make_ball_example.py --size {args.size} --spp {args.spp} --seed {args.seed} "
                         f"--exposure {args.exposure}")
    clipped = [int((np.clip(img * args.exposure, 0, 1).max(axis=2) >= 1).sum()) for img in r.images]
    print(f"wrote {len(names)} photos ({args.size}x{args.size}) to {out}/; object {int(r.object_mask.sum())} px, "
          f"ball r = {rad:.1f} px, clipped px per photo {min(clipped)}-{max(clipped)}; "
          f"object p99 {float(np.percentile(r.images[:, r.object_mask] * args.exposure, 99)):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

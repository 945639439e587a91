"""`matcap synth`: render synthetic photometric-stereo scenes with ground truth (see docs/synth.md)."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "synth", help="generate synthetic training / test scenes with Mitsuba 3",
        description="Render PS-Mix-style synthetic scenes (10 images + basis renders + ground truth per scene). "
                    "Sharded and resumable: finished scenes are never rendered twice.",
    )
    p.add_argument("--out", required=True, help="dataset folder (created; re-run to resume)")
    p.add_argument("--scenes", type=int, required=True, help="number of scenes in the whole dataset")
    p.add_argument("--resolution", type=int, default=256, help="image size in pixels (square, default 256)")
    p.add_argument("--seed", type=int, default=0, help="global seed (default 0)")
    p.add_argument("--shard", default=None, help="i/n: render scenes with index %% n == i (default 0/1)")
    p.add_argument("--assets", default=None,
                   help="assets folder laid out like shared/data (meshes/, envmaps/, textures/); "
                        "default: procedural shapes, textures and skies only")
    p.add_argument("--split", choices=["train", "test"], default="train",
                   help="train, or the fixed test split (held-out assets, PS-Wild-Test lighting groups)")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel per basis render (default 16)")
    p.add_argument("--data-version", type=int, choices=[1, 2], default=1,
                   help="scene generator: 1 (default; the scenes a seed always gave) or 2 (spot / area / near "
                        "lights, a strong fixed light with a weak moving one, normal maps, displacement, up to 6 "
                        "objects and occluders, per-image light vectors; see docs/synth.md)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--no-progress", dest="quiet", action="store_true", help=argparse.SUPPRESS)  # the old name
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from matcap.synth import run_synth

    stats = run_synth(args.out, args.scenes, resolution=args.resolution, seed=args.seed, shard=args.shard,
                      assets=args.assets, split=args.split, spp=args.spp, progress=not args.quiet,
                      data_version=args.data_version)
    print(f"synth: {stats['rendered']} rendered, {stats['skipped']} already done, {stats['failed']} failed "
          f"({stats['redrawn']} re-drawn, see failures.log) in {stats['seconds']:.1f} s -> {args.out}")
    return 1 if stats["failed"] else 0

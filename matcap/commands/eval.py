"""`matcap eval DATASET_DIR`: normal-estimation benchmark (DiLiGenT layout, UW captures, our synthetic split)."""
from __future__ import annotations

import argparse
import shlex

METHOD_NAMES = ("least-squares", "least-squares-robust", "sdm-unips", "flat")  # keep in step with runner.METHODS


def _whole_number(minimum: int):
    """argparse type: an int of at least ``minimum``, with a one-line message otherwise."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {v}")
        return v

    return parse


_positive, _non_negative = _whole_number(1), _whole_number(0)


def register(sub) -> None:
    p = sub.add_parser(
        "eval",
        help="benchmark normal estimation: mean angular error per object and lighting group, with baselines",
        description="Evaluate a normal-estimation method on DiLiGenT-layout objects, UW-style captures or our "
                    "synthetic test split: mean/median angular error, share under 10/20/30 degrees, seconds "
                    "per object, as a Markdown table (stdout) and optional JSON; see docs/eval.md.",
    )
    p.add_argument("dataset", help="an object folder, or a folder of object folders / synthetic scenes")
    p.add_argument("--method", default="least-squares", choices=METHOD_NAMES,
                   help="method to evaluate (default least-squares)")
    p.add_argument("--reference", choices=METHOD_NAMES,
                   help="score against this method on all images instead of ground-truth normals "
                        "(for data without ground truth, e.g. --reference least-squares)")
    p.add_argument("--objects", help="comma-separated object names to evaluate (default: all)")
    p.add_argument("--max-images", type=_positive, metavar="K",
                   help="K images drawn at random per trial (default: all images, one trial)")
    p.add_argument("--trials", type=_positive, default=10, help="trials for --max-images (default 10)")
    p.add_argument("--seed", type=_non_negative, default=0, help="base seed of the image subsets (default 0)")
    p.add_argument("--split", default="test", help="synthetic split to evaluate (default test)")
    p.add_argument("--weights", action="append", metavar="FILE_OR_DIR",
                   help="network weights for sdm-unips (repeatable; default: the bundled model)")
    p.add_argument("--device", default="cpu", help="torch device for sdm-unips (default cpu)")
    p.add_argument("--views", type=int, choices=(1, 2, 4, 8), default=1,
                   help="sdm-unips: test-time augmentation views, as in `matcap capture --views` (default 1)")
    p.add_argument("--max-side", type=_positive, metavar="PX",
                   help="sdm-unips: shrink the images so that their longer side is at most PX, as `matcap capture "
                        "--max-side` does, and scale the normals back to full size for scoring")
    p.add_argument("--linear", action="store_true",
                   help="sdm-unips: give the network 8-bit images as stored (linear), as `matcap capture --linear` "
                        "does, instead of sRGB-decoded like photos (the UW captures are linear data)")
    p.add_argument("--refine", action="store_true",
                   help="with --method sdm-unips: follow the network by the photo-consistent fit of lights and maps "
                        "(matcap.refine); on captures with calibrated lights also report the angles between the "
                        "estimated and the calibrated light directions")
    p.add_argument("--out", metavar="DIR",
                   help="write results.md, results.json and error_maps/<object>.png (0-90 deg) here (a new or "
                        "empty folder unless --overwrite)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an --out folder that already holds files, or existing --json / --markdown files")
    p.add_argument("--json", metavar="FILE", help="also write the JSON report to FILE (atomically)")
    p.add_argument("--markdown", metavar="FILE", help="also write the Markdown table to FILE (atomically)")
    p.add_argument("--quiet", action="store_true", help="no per-object progress lines on stderr")
    p.set_defaults(func=run)


def command_line(args) -> str:
    """A canonical `matcap eval ...` line reproducing ``args`` (written into the tables)."""
    parts = ["matcap", "eval", args.dataset, "--method", args.method]
    if getattr(args, "refine", False):
        parts += ["--refine"]
    if args.reference:
        parts += ["--reference", args.reference]
    if args.objects:
        parts += ["--objects", args.objects]
    if args.max_images:
        parts += ["--max-images", str(args.max_images), "--trials", str(args.trials), "--seed", str(args.seed)]
    if args.split != "test":
        parts += ["--split", args.split]
    for w in args.weights or []:
        parts += ["--weights", w]
    if args.views != 1:
        parts += ["--views", str(args.views)]
    if args.max_side is not None:
        parts += ["--max-side", str(args.max_side)]
    if args.linear:
        parts += ["--linear"]
    return " ".join(shlex.quote(p) for p in parts)


def run(args) -> int:
    from matcap.errors import MatcapError
    from matcap.evaluation import runner

    objects = [o.strip() for o in args.objects.split(",") if o.strip()] if args.objects else None
    if args.objects is not None and not objects:
        raise MatcapError("--objects is empty")
    if "sdm-unips" in (args.method, args.reference):
        from networks.inference import check_device

        check_device(args.device)
    _, md = runner.evaluate_to_files(
        args.dataset, args.method, args.reference, out=args.out, json_path=args.json, markdown_path=args.markdown,
        overwrite=args.overwrite, objects=objects, max_images=args.max_images, trials=args.trials, seed=args.seed,
        weights=args.weights, device=args.device, views=args.views, max_side=args.max_side, linear=args.linear,
        split=args.split, command=command_line(args), log=None if args.quiet else runner.stderr_log,
        refine=args.refine,
    )
    print(md, end="")
    return 0

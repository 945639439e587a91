"""`matcap reference-check CASE.npz`: check our SDM-UniPS networks against a reference run
(:mod:`matcap.evaluation.reference`)."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "reference-check",
        help="check our SDM-UniPS networks against a reference run (deterministic weights)",
        description="Run our paper-size normal and BRDF networks with the SPEC's deterministic weights on a "
                    "reference case and compare with the stored outputs. Prints one line; exit 0 = match.",
    )
    p.add_argument("case", help="CASE.npz (CASE.json with the same stem next to it)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's choice)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from matcap.evaluation.reference import check_case

    result = check_case(args.case, device=args.device, threads=args.threads)
    print(result.line())
    return 0 if result.ok else 1

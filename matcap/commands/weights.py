"""`matcap weights import nml.pytmodel brdf.pytmodel --out DIR`: convert the published SDM-UniPS checkpoints
(:func:`matcap.models.import_published`).

The published files (hosted by the authors, MIT licence with a non-commercial clause, never redistributed by us)
are read with ``torch.load(weights_only=True)`` and written as our safetensors files ``DIR/normal.safetensors`` /
``DIR/brdf.safetensors`` (which one is detected from the keys), with the config and a model card (source, sha256,
licence) in the metadata.
"""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "weights",
        help="manage network weights (import the published SDM-UniPS checkpoints)",
        description="Manage network weights.",
    )
    sub = p.add_subparsers(dest="weights_command", metavar="ACTION")
    imp = sub.add_parser(
        "import",
        help="convert published nml.pytmodel / brdf.pytmodel files to matcap safetensors files",
        description="Convert the published SDM-UniPS checkpoints (normal/nml.pytmodel, brdf/brdf.pytmodel; "
                    "MIT licence with a non-commercial clause) into DIR/normal.safetensors and "
                    "DIR/brdf.safetensors. Files are read with weights_only=True (no arbitrary code).",
    )
    imp.add_argument("files", nargs="+", help="published .pytmodel files (normal and/or brdf)")
    imp.add_argument("--out", required=True, help="output folder")
    imp.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if getattr(args, "weights_command", None) != "import":
        raise ValueError("choose an action: matcap weights import FILE... --out DIR")
    from matcap.models import import_published

    for item in import_published(args.files, args.out, overwrite=args.overwrite):
        print(f"{item['source']} -> {item['dest']} ({item['target']}, {item['parameters']:,} parameters)")
    return 0

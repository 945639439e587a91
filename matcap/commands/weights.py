"""`matcap weights import nml.pytmodel brdf.pytmodel --out DIR`: convert the published SDM-UniPS checkpoints.

The published files (hosted by the authors, MIT licence with a non-commercial clause, never redistributed by us)
are read with ``torch.load(weights_only=True)`` and written as our safetensors files ``DIR/normal.safetensors`` /
``DIR/brdf.safetensors`` (which one is detected from the keys), with the config and a model card (source, sha256,
licence) in the metadata.
"""
from __future__ import annotations

import argparse
import hashlib
from pathlib import Path


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


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def run(args: argparse.Namespace) -> int:
    if getattr(args, "weights_command", None) != "import":
        raise ValueError("choose an action: matcap weights import FILE... --out DIR")
    from matcap.errors import MatcapError
    from networks.checkpoint import PUBLISHED_LICENSE, import_published, save_weights
    from networks.model import build_model

    out_dir = Path(args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise MatcapError(f"--out {out_dir} exists and is not a folder")
    converted = {}
    for name in args.files:
        path = Path(name)
        config, state = import_published(path)
        target = config.target
        if target in converted:
            raise MatcapError(f"two {target} checkpoints given ({converted[target][0]} and {path})")
        dest = out_dir / f"{target}.safetensors"
        if dest.exists() and not args.overwrite:
            raise MatcapError(f"{dest} exists; pass --overwrite to replace it")
        converted[target] = (path, config, state, dest)
    for target, (path, config, state, dest) in converted.items():
        model = build_model(config, state)
        card = {
            "name": f"sdm-unips-{target}-published",
            "architecture": "SDM-UniPS (Ikehata, CVPR 2023)",
            "preset": "paper",
            "target": target,
            "source_file": path.name,
            "source_sha256": _sha256(path),
            "license": PUBLISHED_LICENSE,
            "commercial_use": False,
            "redistribute": False,
        }
        save_weights(dest, model, config, card)
        print(f"{path} -> {dest} ({target}, {sum(v.numel() for v in state.values()):,} parameters)")
    return 0

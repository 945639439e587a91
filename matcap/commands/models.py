"""`matcap models`: list installed models and their cards; `matcap models install`: ship trained weights."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("models", help="list installed models (or install trained weights)")
    p.add_argument("action", nargs="?", choices=("list", "install"), default="list")
    p.add_argument("weights", nargs="?", help="install: a trained run's .safetensors (e.g. runs/x/best.safetensors)")
    p.add_argument("--name", help="install: model name, e.g. normal_small (the default normal model)")
    p.add_argument("--fp32", action="store_true", help="install: keep float32 (default: store float16)")
    p.add_argument("--notes", help="install: Markdown file appended to the model card")
    p.add_argument("--pixel-samples", type=int, default=None,
                   help="install: default inference sample-set size (default: the training run's)")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--json", action="store_true", help="list: print JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    import json
    from pathlib import Path

    from matcap.errors import MatcapError
    from matcap.models import WEIGHTS_DIR, install, installed_models

    if args.action == "install":
        if not args.weights or not args.name:
            raise MatcapError("usage: matcap models install WEIGHTS --name NAME")
        notes = Path(args.notes).read_text() if args.notes else ""
        dst = install(args.weights, args.name, fp16=not args.fp32, overwrite=args.overwrite, notes=notes,
                      pixel_samples=args.pixel_samples)
        print(f"installed {dst} (+ {dst.with_suffix('.md').name})")
        return 0
    models = installed_models()
    if args.json:
        print(json.dumps(models, indent=2))
        return 0
    if not models:
        print(f"no models installed in {WEIGHTS_DIR}")
        return 0
    for m in models:
        if "error" in m:
            print(f"{m['name']}: unreadable ({m['error']})")
            continue
        val = m["card"].get("validation") or {}
        vals = ", ".join(f"{k} {v:.2f}" for k, v in sorted(val.items()))
        print(f"{m['name']}: {m['target']} network, preset {m['preset']}, {m['size_mb']} MB, "
              f"{m['card'].get('steps', '?')} steps; validation: {vals or 'none'}")
        if m["card_file"]:
            print(f"    card: {m['card_file']}")
    return 0

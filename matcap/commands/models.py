"""`matcap models`: list installed models and their cards; `matcap models install`: ship trained weights."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "models", help="list installed models (or install trained weights)",
        description="List the installed models (networks/weights/) with their validation scores and which ones "
                    "`matcap capture` uses by default, or install trained weights as a model with a card: "
                    "`matcap models install runs/NAME/best.safetensors --name normal_small`.",
    )
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
    from matcap.estimate import DEFAULT_WEIGHTS
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
        default = " (default)" if m["name"] == DEFAULT_WEIGHTS.get(m["target"], Path()).stem else ""
        print(f"{m['name']}{default}: {m['target']} network, preset {m['preset']}, {m['size_mb']} MB, "
              f"{m['card'].get('steps', '?')} steps; validation: "
              f"{validation_summary(m['target'], m['card'].get('validation') or {})}")
        if m["card_file"]:
            print(f"    card: {m['card_file']}")
    if not any(m.get("name") == DEFAULT_WEIGHTS["normal"].stem for m in models):
        print("no default normal model (normal_small): `matcap capture` needs --weights")
    return 0


def validation_summary(target: str, val: dict) -> str:
    """The validation figures that mean something for a model's ``target``: mean angular error per lighting group
    for a normal network; RMSE of each BRDF map beside the best constant's for a BRDF network (its normal head is
    not trained, so its normal error is left out)."""
    if target == "brdf":
        maps = [k for k in ("base_color", "roughness", "metallic") if f"rmse_{k}" in val]
        if not maps:
            return "none"
        own = " / ".join(f"{val[f'rmse_{k}']:.3f}" for k in maps)
        const = " / ".join(f"{val[f'rmse_const_{k}']:.3f}" for k in maps if f"rmse_const_{k}" in val)
        text = f"RMSE {' / '.join(k.replace('_', ' ') for k in maps)} {own}"
        return text + (f" (best constant: {const})" if const else "")
    if "mae" not in val:
        return "none"
    groups = ", ".join(f"{k[4:]} {v:.2f}°" for k, v in sorted(val.items()) if k.startswith("mae_"))
    return f"mean angular error {val['mae']:.2f}°" + (f" ({groups})" if groups else "")

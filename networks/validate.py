"""Score trained weights on a synthetic split, exactly as training validation does.

    python -m networks.validate WEIGHTS.safetensors DATA_TEST [--scenes N] [--pixel-samples P] [--views V]
        [--json FILE]

Prints one JSON object: mean angular error (degrees) per lighting group and over all scenes, and for a BRDF network
the RMSE of base color, roughness and metallic next to the RMSE of the best constant prediction
(``rmse_const_*``, the standard deviation of the truth) and the relative improvement over it (``gain_*``; the
bundled BRDF model's training goal is >= 0.30 for each map). Base color is also scored exposure-aligned (one free
scale per scene for the prediction and for a per-scene constant), since per-image normalisation hides the absolute
albedo scale.
Every scene is predicted with its stored images and ground-truth mask.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from scenes.atomic import write_text_atomic


def score(weights: str | Path, data: str | Path, scenes: int | None = None, device: str = "cpu",
          pixel_samples: int | None = None, views: int = 1) -> dict:
    """Validation numbers of ``weights`` on the first ``scenes`` scenes of ``data`` (all when None), predicted in
    sample sets of ``pixel_samples`` pixels (default: the model's), averaged over ``views`` test-time views."""
    import torch

    from networks.checkpoint import load_model
    from networks.data import list_scenes
    from networks.train import validate

    model, config, _ = load_model(weights, device=device)
    found = list_scenes(data)
    count = len(found) if scenes is None else min(scenes, len(found))
    result = validate(model, found, config.target, torch.device(device), count,  # validate() runs without grad
                      pixel_samples=pixel_samples, views=views)
    result = {"weights": str(weights), "target": config.target, "scenes": count, "views": views,
              "pixel_samples": pixel_samples or config.pixel_samples, **result}
    if config.target == "brdf":
        for key in ("base_color", "roughness", "metallic", "base_color_exposure_aligned"):
            const = result[f"rmse_const_{key}"]
            result[f"gain_{key}"] = 1.0 - result[f"rmse_{key}"] / const if const > 0 else float("nan")
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m networks.validate", description=__doc__.split("\n\n")[0])
    p.add_argument("weights", help="our .safetensors weights (normal or BRDF network)")
    p.add_argument("data", help="a `matcap synth` dataset folder (the test split)")
    p.add_argument("--scenes", type=int, help="use the first N scenes (default: all)")
    p.add_argument("--pixel-samples", type=int, help="pixels per sample set (default: the model's)")
    p.add_argument("--views", type=int, choices=(1, 2, 4, 8), default=1,
                   help="test-time augmentation views, as in `matcap capture --views` (default 1)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--json", metavar="FILE", help="also write the result to FILE")
    args = p.parse_args(argv)
    try:
        result = score(args.weights, args.data, args.scenes, args.device, args.pixel_samples, args.views)
    except (ValueError, OSError) as exc:
        print(f"networks.validate: error: {exc}", file=sys.stderr)
        return 2
    text = json.dumps(result, indent=1)
    if args.json:  # atomically: a reader never sees half a file
        write_text_atomic(args.json, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

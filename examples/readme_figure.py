"""A one-row figure of a capture: four of the input photos, the recovered normal map, the base color, roughness
and metallic maps (when the capture has them) and a relit render.

    matcap capture examples/bunny --linear --out bunny-maps
    matcap relight bunny-maps                             # the render under the default studio map
    python examples/readme_figure.py                      # reads bunny-maps/, writes ./bunny_capture.png

It never replaces an existing file unless told to; the README's figure was made with
``python examples/readme_figure.py bunny-maps docs/images/bunny_capture.png --overwrite``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from matcap import imageio
from matcap.photos import load_capture
from matcap.results import read_result


def main(result: str, out: str) -> None:
    maps = read_result(result)
    cap = load_capture(maps.meta["input_folder"], linear="--linear" in maps.meta.get("colour_handling", ""))
    picks = np.linspace(0, len(cap.images) - 1, 4).round().astype(int)
    tiles = [imageio.linear_to_srgb(np.clip(cap.images[i] / max(np.percentile(cap.images[i], 99.5), 1e-6), 0, 1))
             for i in picks]  # each photo scaled so its 99.5th percentile is white
    if tiles[0].shape[:2] != maps.shape:  # a capture made with --max-side: photos at the maps' size
        import cv2

        tiles = [cv2.resize(t.astype(np.float32), maps.shape[::-1], interpolation=cv2.INTER_AREA) for t in tiles]
    tiles.append(np.where(maps.mask[..., None], (maps.normal + 1) / 2, 0.0))
    if maps.base_color is not None:
        tiles.append(np.where(maps.mask[..., None], imageio.linear_to_srgb(np.clip(maps.base_color, 0, 1)), 0.0))
    for scalar in (maps.roughness, maps.metallic):
        if scalar is not None:
            tiles.append(np.repeat(np.where(maps.mask, scalar, 0.0)[..., None], 3, axis=2))
    relit = sorted(Path(result).glob("relight_*.png"))
    if relit:
        rgba = imageio.read_image(relit[0]).pixels.astype(np.float32) / 255.0
        tiles.append(rgba[..., :3])
    gap = np.ones((tiles[0].shape[0], 4, 3), np.float32)
    row = np.concatenate([t for tile in tiles for t in (tile, gap)][:-1], axis=1)
    imageio.write_png(out, row, bits=8)
    print(f"wrote {out}")


def cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Make a one-row figure of a capture result folder.")
    p.add_argument("result", nargs="?", default="bunny-maps", help="capture result folder (default: bunny-maps)")
    p.add_argument("out", nargs="?", default="bunny_capture.png", help="PNG to write (default: ./bunny_capture.png)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    args = p.parse_args(argv)
    if Path(args.out).exists() and not args.overwrite:
        print(f"readme_figure.py: error: {args.out} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    if not Path(args.result).is_dir():
        print(f"readme_figure.py: error: no result folder {args.result}; make it with `matcap capture examples/bunny "
              f"--linear --out {args.result} --relight matcap/data/envmaps/studio_small_03.exr`", file=sys.stderr)
        return 2
    main(args.result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(cli())

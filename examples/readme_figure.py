"""Make docs/images/bunny_capture.png: four of the input photos, the recovered normal map, the base color,
roughness and metallic maps (when the capture has them) and a relit render.

    matcap capture examples/bunny --linear --out bunny-maps --relight matcap/data/envmaps/studio_small_03.exr
    python examples/readme_figure.py bunny-maps docs/images/bunny_capture.png
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from matcap import imageio
from matcap.capture import load_capture
from matcap.results import read_result


def main(result: str, out: str) -> None:
    maps = read_result(result)
    cap = load_capture(maps.meta["input_folder"], linear="--linear" in maps.meta.get("colour_handling", ""))
    picks = np.linspace(0, len(cap.images) - 1, 4).round().astype(int)
    tiles = [imageio.linear_to_srgb(np.clip(cap.images[i] / max(np.percentile(cap.images[i], 99.5), 1e-6), 0, 1))
             for i in picks]  # each photo scaled so its 99.5th percentile is white
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


if __name__ == "__main__":
    main(*sys.argv[1:3])

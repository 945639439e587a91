"""Seams before and after `matcap tile`, for every map of the CC0 texture sets (and any capture result).

    python benchmarks/tile_check.py                         # the 11 sets in ../shared/data/textures
    python benchmarks/tile_check.py --also RESULT_DIR ...   # plus capture results (or any map source)

For each source the tile is made as `matcap tile` makes it (default size), and each map is measured twice:

* before: the square the tile is cut from, as it is (P x P, its height integrated as `matcap export` does);
* after: the tile.

`ratio` is :func:`matcap.tile.seam_energy`: the gradient energy across the tile borders (the map wrapped by half
its size) over the energy of the 4 lines of neighbour pairs on each side of them (goal: within 10 %, i.e. at most
1.10, where a seam gives many times 1). One line of a natural texture varies by itself (wood grain, the islands of a
UV atlas), so the table also gives `rank`: the share of the tile's own lines (every row / column position, the same
measure) whose ratio is below the border's: a seam ranks at 100 %, an ordinary line anywhere. `cut` is
:func:`matcap.tile.cut_energy`: the same measure across the cut inside the tile. Constant maps (a set without a
normal or metallic map gets flat normals / metallic 0) are left out.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from matcap import formats  # noqa: E402
from matcap.height import integrate_normals  # noqa: E402
from matcap.tile import SEAM_BAND, seam_energy, tile_maps  # noqa: E402

TEXTURES = ROOT.parent / "shared" / "data" / "textures"
MAPS = ("normal", "base_color", "roughness", "metallic", "height")


def line_ratios(x: np.ndarray, band: int = SEAM_BAND) -> np.ndarray:
    """seam_energy's ratio with the border put at every position t (the pair of column t, t+1 and of row t, t+1
    on the torus): (P,) values; the tile's own border is t = P - 1."""
    a = np.asarray(x, np.float64)
    a = a[..., None] if a.ndim == 2 else a
    lx = np.sum((np.roll(a, -1, axis=1) - a) ** 2, axis=2).mean(axis=0)  # per column pair
    ly = np.sum((np.roll(a, -1, axis=0) - a) ** 2, axis=2).mean(axis=1)  # per row pair
    line = lx + ly
    near = np.mean([np.roll(line, k) for k in range(-band, band + 1) if k], axis=0)
    return line / np.maximum(near, 1e-30)


def _spread(x: np.ndarray) -> float:
    """The largest per-channel range of a map (0: constant)."""
    x = np.asarray(x, np.float64)
    return float(np.ptp(x.reshape(x.shape[0] * x.shape[1], -1), axis=0).max())


def before_square(maps, info) -> dict[str, np.ndarray]:
    """The P x P square the tile is cut from (its first P rows / columns, resampled as the tile was), untiled."""
    from matcap.tile import _resize

    crop, p = info["crop"], info["size"]
    r, c, n, k = crop["row"], crop["col"], crop["side"], crop["resampled_to"]
    out = {}
    for name in MAPS[:4]:
        v = getattr(maps, name)
        if v is not None:
            out[name] = _resize(np.asarray(v, np.float32)[r:r + n, c:c + n], k)[:p, :p]
    n_sq = out["normal"] / np.maximum(np.linalg.norm(out["normal"], axis=2, keepdims=True), 1e-6)
    out["height"] = integrate_normals(n_sq, None, "frankot-chellappa")
    return out


def check(source: str | Path, label: str) -> list[tuple]:
    maps = formats.load_maps(source)
    t0 = time.perf_counter()
    tiled, info = tile_maps(maps)
    seconds = time.perf_counter() - t0
    before = before_square(maps, info)
    rows = []
    for name in MAPS:
        after_map = getattr(tiled, name)
        if after_map is None or name not in before:
            continue
        if _spread(after_map) < 1e-5 and _spread(before[name]) < 1e-5:
            continue  # a constant map (a set without it: flat normals, metallic 0) has no seam to measure
        b = seam_energy(before[name])["ratio"]
        a = seam_energy(after_map)["ratio"]
        lines = line_ratios(after_map)
        rank = float(np.mean(lines[:-1] < lines[-1]))
        rows.append((label, info["size"], name, b, a, rank, info["cut_energy"][name]["ratio"], seconds))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--textures", default=str(TEXTURES), help="folder of texture-set folders")
    ap.add_argument("--also", nargs="*", default=[], help="more map sources (capture results, exports)")
    args = ap.parse_args(argv)
    sources = [(p, p.name) for p in sorted(Path(args.textures).iterdir()) if p.is_dir()]
    sources += [(Path(p), Path(p).name) for p in args.also]
    if not sources:
        print(f"no texture sets in {args.textures}", file=sys.stderr)
        return 2
    print(f"| source | P | map | before | after | rank | cut | tile s |")
    print("|---|---|---|---|---|---|---|---|")
    all_rows = []
    for path, label in sources:
        try:
            rows = check(path, label)
        except Exception as exc:  # one broken set must not hide the others
            print(f"| {label} | - | - | error: {exc} | | | | |")
            continue
        for i, (lab, p, name, b, a, rank, cut, sec) in enumerate(rows):
            print(f"| {lab if i == 0 else ''} | {p if i == 0 else ''} | {name} | {b:.2f} | {a:.2f} | {rank:.0%} | "
                  f"{cut:.2f} | {f'{sec:.1f}' if i == 0 else ''} |")
        all_rows += rows
    if all_rows:
        before = np.array([r[3] for r in all_rows])
        after = np.array([r[4] for r in all_rows])
        cut = np.array([r[6] for r in all_rows])
        rank = np.array([r[5] for r in all_rows])
        print(f"\n{len(all_rows)} maps: before median {np.median(before):.2f} (max {before.max():.2f}); after median "
              f"{np.median(after):.2f} (max {after.max():.2f}), {np.mean(after <= 1.10):.0%} at most 1.10; rank "
              f"median {np.median(rank):.0%}; cut median {np.median(cut):.2f} (max {cut.max():.2f}), "
              f"{np.mean(cut <= 1.10):.0%} at most 1.10")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Tileable texture sets: every map of a result made seamless together, with a periodic height map.

    from matcap.tile import tile
    tile("result/", "tiled/", size=512)          # a result folder readable by matcap.results.read_result

Steps (:func:`tile_maps` does 1-5 on :class:`MaterialMaps`, :func:`tile` adds the files):

1. **Square.** The largest axis-aligned square inside the mask (exact: a binary search on the side with an
   integral image; among the squares of that side, the one nearest the mask's centre). The tile side ``P`` is the
   given ``size`` (a power of two, at most the square's side), for which the whole square is resampled (Lanczos)
   to ``P + K`` (``K`` = :func:`overlap`, the material the cut may use); else the largest power of two that fits
   with its overlap at the maps' own resolution (at most :data:`DEFAULT_MAX_SIZE`), cropped from the square with
   the border on an ordinary line (:func:`border_offsets`).
2. **One cut for all maps.** The ``K`` columns beyond the tile continue its last column; placed over its first
   ``K`` columns they make it wrap. The boundary between them and the tile's own columns is the minimum-error
   vertical path (dynamic programming, 8-connected, as in image quilting) through the joint error of *all* maps
   (normal, base colour, roughness, metallic, each divided by its variance so that each map counts the same). Then
   the same across rows on the result, with a horizontal path that closes around the tile (its two ends meet, so
   the output stays periodic in x). Every output texel is thus one texel of the source, moved by one of four
   shifts (0 or P per axis): the same for every map.
3. **Gradient-domain blend.** A hard cut still shows a small jump where the two sides differ. Each map is rebuilt
   from its gradients (the source's gradient inside each region; across the cut the mean of the two sources'
   gradients) by a Poisson solve on the torus (FFT), keeping its mean: no jump at the cut, no ghosting (nothing is
   cross-faded), and the output is exactly periodic. Normals are renormalised afterwards and turned so that their
   mean is +z (:func:`level`); colours, roughness and metallic clipped to [0, 1].
4. **Height.** Integrated from the tiled normals by the periodic Fourier solve
   (:func:`matcap.height.frankot_chellappa` with ``periodic=True``), so the height tiles too.
5. **Check.** :func:`seam_energy`: per map, the gradient energy across the tile borders (the tile wrapped by half
   its size) against the interior's; recorded in ``capture.json`` with the cut's.

Limits (measured in docs/export.md, "Tileable texture sets"): the output is a re-arrangement of the square, so a
sample with a gradient of light or colour across it (vignetting, an uneven lamp) keeps it as a smooth
low-frequency change; strongly structured patterns (bricks, planks) may show a cut through a feature where no path
of low error exists.
"""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from matcap.errors import MatcapError
from matcap.normals import unit_normals
from scenes.materialmaps import MaterialMaps

MIN_SIZE = 16
MAX_SIZE = 8192
DEFAULT_MAX_SIZE = 4096
PREVIEW_TILE = 256  # each of the 3 x 3 copies in preview_3x3.png is at most this many pixels wide
PREVIEW_SPP = 16
SEAM_BAND = 4  # lines on each side of a border (or cut) that seam_energy / cut_energy compare it with
MAP_NAMES = ("normal", "base_color", "roughness", "metallic", "height")


# ------------------------------------------------------------------------------------------------ checks
def is_power_of_two(n: int) -> bool:
    return n >= 1 and (n & (n - 1)) == 0


def check_size(size, square: int | None = None, what: str = "--size") -> int | None:
    """``size`` as an int if it is a power of two in [MIN_SIZE, MAX_SIZE] (and at most ``square``), else a
    one-line error naming the option ``what``; None stays None."""
    if size is None:
        return None
    try:
        value = int(size)
    except (TypeError, ValueError):
        raise MatcapError(f"{what} must be a power of two such as 512 or 1024, got {size!r}") from None
    if isinstance(size, float) and size != value:
        raise MatcapError(f"{what} must be a power of two such as 512 or 1024, got {size!r}")
    if not is_power_of_two(value) or not MIN_SIZE <= value <= MAX_SIZE:
        raise MatcapError(f"{what} must be a power of two from {MIN_SIZE} to {MAX_SIZE}, got {size!r}")
    if square is not None and value > square:
        raise MatcapError(f"{what} {value} is larger than the largest square of surface in the maps ({square} x "
                          f"{square} pixels); the tiler does not upsample: choose {largest_power_of_two(square)} "
                          "or less")
    return value


def default_size(square: int) -> int:
    """The tile side chosen for a square of surface ``square`` pixels wide: the largest power of two that fits
    with its overlap at the maps' own resolution (nothing resampled), at most DEFAULT_MAX_SIZE; if none fits,
    the largest power of two within the square (then resampled)."""
    p = largest_power_of_two(min(square, DEFAULT_MAX_SIZE))
    while p > MIN_SIZE and p + overlap(p) > square:
        p //= 2
    return p if p + overlap(p) <= square else largest_power_of_two(min(square, DEFAULT_MAX_SIZE))


def largest_power_of_two(n: int) -> int:
    return 1 << (int(n).bit_length() - 1) if n >= 1 else 0


# ------------------------------------------------------------------------------------------------ step 1: square
def largest_square(mask: np.ndarray) -> tuple[int, int, int]:
    """(row, col, side) of the largest axis-aligned square of True pixels in ``mask`` (side 0 if none). Among the
    squares of that side, the one whose centre is nearest the mask's centroid."""
    m = np.asarray(mask, bool)
    h, w = m.shape
    if not m.any():
        return 0, 0, 0
    integral = np.zeros((h + 1, w + 1), np.int64)
    integral[1:, 1:] = np.cumsum(np.cumsum(m, axis=0, dtype=np.int64), axis=1)

    def full(k: int) -> np.ndarray:  # (h-k+1, w-k+1) bool: the k x k window at (r, c) is all True
        s = integral[k:, k:] - integral[:-k, k:] - integral[k:, :-k] + integral[:-k, :-k]
        return s == k * k

    lo, hi = 1, min(h, w)  # full(lo) has a hit (the mask is not empty)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if full(mid).any():
            lo = mid
        else:
            hi = mid - 1
    rows, cols = np.nonzero(full(lo))
    rr, cc = np.nonzero(m)
    cy, cx = rr.mean(), cc.mean()
    best = int(np.argmin((rows + (lo - 1) / 2 - cy) ** 2 + (cols + (lo - 1) / 2 - cx) ** 2))
    return int(rows[best]), int(cols[best]), int(lo)


def _resize(arr: np.ndarray, side: int) -> np.ndarray:
    """A square (n, n[, C]) array resampled to (side, side[, C]) with a Lanczos filter widened when shrinking
    (PIL), so that every output line is filtered alike (an area filter at a non-integer ratio blurs some lines
    more than others, which shows as stripes of gradient energy)."""
    from PIL import Image

    arr = np.asarray(arr, np.float32)
    if arr.shape[0] == side:
        return np.ascontiguousarray(arr)
    planes = arr[..., None] if arr.ndim == 2 else arr
    out = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(planes[..., i]), mode="F")
                               .resize((side, side), Image.LANCZOS)) for i in range(planes.shape[2])], axis=2)
    return out[..., 0] if arr.ndim == 2 else out


def _stack(maps: MaterialMaps) -> tuple[np.ndarray, dict[str, slice]]:
    """The maps as one (H, W, C) float32 array and each map's channel slice (normal, base_color, roughness,
    metallic: those present)."""
    planes, groups, k = [], {}, 0
    for name in MAP_NAMES[:4]:
        value = getattr(maps, name)
        if value is None:
            continue
        value = np.asarray(value, np.float32)
        value = value[..., None] if value.ndim == 2 else value
        planes.append(value)
        groups[name] = slice(k, k + value.shape[2])
        k += value.shape[2]
    return np.concatenate(planes, axis=2), groups


def border_offsets(square: MaterialMaps, n: int, p: int, band: int = 4, tolerance: float = 0.08
                   ) -> tuple[tuple[int, int], dict[str, Any]]:
    """Where to take the n x n crop inside ``square`` (side > n): (row, col) offsets, and why.

    The tile's border joins source columns (and rows) ``offset + P - 1`` and ``offset + P``: a real pair of
    neighbours, so no seam, but it should also be an *ordinary* pair, not one of the lines where the source files
    carry more gradient energy than their neighbours (the 8 x 8 block edges of a JPEG, an atlas island's edge).
    Per axis, the offset nearest the centre whose border line's gradient energy is, in every map, within
    ``tolerance`` (in log) of the mean of the ``band`` lines on each side; failing that, the offset whose worst map
    is the most ordinary."""
    side = square.shape[0]
    planes = [np.asarray(v, np.float32) for v in map_planes(square).values()]
    planes = [v[..., None] if v.ndim == 2 else v for v in planes]
    cand = np.arange(side - n + 1)
    line = cand + p - 1  # the source pair (line, line + 1) becomes the border
    centre = np.abs(cand - (side - n) / 2)

    def choose(axis: int, other: int) -> tuple[int, float]:
        """The offset along ``axis`` with the crop at ``other`` on the other axis."""
        badness = np.zeros(len(cand))
        for v in planes:
            v = v[other:other + n] if axis == 1 else v[:, other:other + n]
            energy = (np.diff(v, axis=axis) ** 2).sum(axis=2).mean(axis=1 - axis, dtype=np.float64)
            if not energy.any():
                continue
            near = np.stack([energy[np.clip(line + j, 0, side - 2)] for j in range(-band, band + 1) if j]).mean(0)
            bad = np.abs(np.log(np.maximum(energy[line], 1e-30) / np.maximum(near, 1e-30)))
            badness = np.maximum(badness, bad)
        ok = badness <= tolerance
        best = int(cand[ok][np.argmin(centre[ok])]) if ok.any() else int(cand[np.argmin(badness)])
        return best, float(badness[best])

    mid = (side - n) // 2
    col, _ = choose(1, mid)  # columns with the rows centred, then rows with those columns, then columns again
    row, row_bad = choose(0, col)
    col, col_bad = choose(1, row)
    offsets = [row, col]
    why = {"row": {"offset": row, "worst_map_border_line_log_ratio": round(row_bad, 4)},
           "col": {"offset": col, "worst_map_border_line_log_ratio": round(col_bad, 4)}}
    return (offsets[0], offsets[1]), {"rule": "the border on an ordinary line of the source, nearest the centre",
                                      **why}


# ------------------------------------------------------------------------------------------------ step 2: the cut
def joint_error(a: np.ndarray, b: np.ndarray, groups: dict[str, slice], scale: dict[str, float]) -> np.ndarray:
    """(H, W) error between two stacks: per map the mean squared channel difference over the map's variance,
    summed over maps (each map counts the same, whatever its units)."""
    err = np.zeros(a.shape[:2])
    for name, sl in groups.items():
        err += np.mean((a[..., sl] - b[..., sl]) ** 2, axis=2) / scale[name]
    return err


def min_vertical_path(cost: np.ndarray) -> np.ndarray:
    """Columns (one per row) of the 8-connected top-to-bottom path of least total ``cost`` (H, B)."""
    h, b = cost.shape
    acc = cost[0].copy()
    step = np.zeros((h, b), np.int8)
    big = np.inf
    for r in range(1, h):
        left = np.concatenate([[big], acc[:-1]])
        right = np.concatenate([acc[1:], [big]])
        choice = np.stack([left, acc, right])
        k = np.argmin(choice, axis=0)
        step[r] = k - 1
        acc = cost[r] + choice[k, np.arange(b)]
    path = np.zeros(h, np.int64)
    path[-1] = int(np.argmin(acc))
    for r in range(h - 1, 0, -1):
        path[r - 1] = path[r] + step[r, path[r]]
    return path


def min_closed_path(cost: np.ndarray, starts: int = 64) -> np.ndarray:
    """Like :func:`min_vertical_path` on ``cost`` (H, B), but the path closes: its last column is within one of
    its first (rows wrap around, so the path is a closed loop on the torus). Up to ``starts`` first columns are
    tried (evenly spaced), all at once."""
    h, b = cost.shape
    cand = np.unique(np.linspace(0, b - 1, min(starts, b)).round().astype(np.int64))
    big = np.inf
    acc = np.full((len(cand), b), big)
    acc[np.arange(len(cand)), cand] = cost[0, cand]
    for r in range(1, h):
        left = np.concatenate([np.full((len(cand), 1), big), acc[:, :-1]], axis=1)
        right = np.concatenate([acc[:, 1:], np.full((len(cand), 1), big)], axis=1)
        acc = cost[r][None, :] + np.minimum(np.minimum(left, acc), right)
    cols = np.arange(b)
    closing = np.abs(cols[None, :] - cand[:, None]) <= 1
    total = np.where(closing, acc, big).min(axis=1)
    start = int(cand[int(np.argmin(total))])
    # the best start again, with the path kept: only columns next to the start are allowed at the end
    fixed = np.full_like(cost, big)
    fixed[1:] = cost[1:]
    fixed[0, start] = cost[0, start]
    end_ok = np.abs(cols - start) <= 1
    fixed[-1] = np.where(end_ok, cost[-1], big)
    return min_vertical_path(fixed)


def overlap(p: int) -> int:
    """Texels of extra material beyond the tile on each axis that the cut may use: P / 8, at least 8."""
    return max(8, p // 8)


def cut_shifts(stack: np.ndarray, p: int, groups: dict[str, slice], scale: dict[str, float]
               ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """The source coordinates (rows, cols), each (P, P), of the seamless P x P arrangement of ``stack``
    (P + K, P + K, C), K = :func:`overlap` (module doc, step 2), and the cut's description."""
    k = stack.shape[0] - p
    m = max(1, k // 8)  # the cut keeps this far from the ends of the overlap
    rr, cc = np.mgrid[0:p + k, 0:p]
    # x: the columns beyond the tile, P .. P+K, continue column P-1; placed at columns 0 .. K they make the tile
    # wrap. Left of a min-error path through the overlap they are used, right of it the tile's own columns.
    ex = joint_error(stack[:, :k], stack[:, p:p + k], groups, scale)  # (P+K, K)
    vpath = min_vertical_path(ex[:, m:k - m]) + m
    sx = np.where(cc < vpath[:, None], p, 0)
    xs = stack[rr, cc + sx]  # (P+K, P): seamless in x
    # y: the same with rows, on the x-seamless result; the path closes around the columns (x stays periodic)
    ey = joint_error(xs[:k], xs[p:p + k], groups, scale)  # (K, P)
    hpath = min_closed_path(ey[m:k - m].T) + m
    r2, c2 = np.mgrid[0:p, 0:p]
    src_r = r2 + np.where(r2 < hpath[None, :], p, 0)
    src_c = c2 + sx[src_r, c2]
    info = {"overlap": int(k), "search_band": [int(m), int(k - m - 1)],
            "vertical_path_cols": [int(vpath.min()), int(vpath.max())],
            "horizontal_path_rows": [int(hpath.min()), int(hpath.max())],
            "mean_error_on_cut": float(0.5 * (ex[np.arange(p + k), vpath].mean() + ey[hpath, np.arange(p)].mean())),
            "mean_error_in_overlap": float(0.5 * (ex.mean() + ey.mean()))}
    return src_r, src_c, info


# ------------------------------------------------------------------------------------------------ step 3: blend
def _torus_poisson(gx: np.ndarray, gy: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """u (P, P, C) on the torus whose forward differences u[:, c+1] - u[:, c] and u[r+1] - u[r] best fit
    (least squares) ``gx`` / ``gy`` (P, P, C), with mean ``mean`` (C,)."""
    from scipy import fft

    p, q = gx.shape[:2]
    dx = (np.exp(2j * np.pi * fft.fftfreq(q)) - 1.0)[None, :, None]
    dy = (np.exp(2j * np.pi * fft.fftfreq(p)) - 1.0)[:, None, None]
    denom = np.abs(dx) ** 2 + np.abs(dy) ** 2
    denom[0, 0] = 1.0
    spec = (np.conj(dx) * fft.fft2(gx, axes=(0, 1), workers=-1)
            + np.conj(dy) * fft.fft2(gy, axes=(0, 1), workers=-1)) / denom
    spec[0, 0] = 0.0
    return np.real(fft.ifft2(spec, axes=(0, 1), workers=-1)) + np.asarray(mean)[None, None, :]


def blend(stack: np.ndarray, src_r: np.ndarray, src_c: np.ndarray) -> np.ndarray:
    """The arrangement ``stack[src_r, src_c]`` (P, P, C) rebuilt from its gradients on the torus (module doc,
    step 3): each forward difference is the source's own where both texels come from the same shift, else the mean
    of the two sources' (both are real differences of the source: the cut keeps off the source's edges). One
    channel at a time (memory)."""
    right_r, right_c = np.roll(src_r, -1, axis=1), np.roll(src_c, -1, axis=1) - 1
    down_r, down_c = np.roll(src_r, -1, axis=0) - 1, np.roll(src_c, -1, axis=0)
    out = np.empty(src_r.shape + (stack.shape[2],), np.float32)
    for ch in range(stack.shape[2]):
        a = stack[..., ch].astype(np.float64)
        gxa = np.zeros_like(a)
        gya = np.zeros_like(a)
        gxa[:, :-1] = np.diff(a, axis=1)
        gya[:-1] = np.diff(a, axis=0)
        gx = 0.5 * (gxa[src_r, src_c] + gxa[right_r, right_c])
        gy = 0.5 * (gya[src_r, src_c] + gya[down_r, down_c])
        del gxa, gya
        out[..., ch] = _torus_poisson(gx[..., None], gy[..., None], [a[src_r, src_c].mean()])[..., 0]
    return out


# ------------------------------------------------------------------------------------------------ step 5: check
def _pair_energy(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared jumps (summed over channels) between each texel and its right / lower neighbour on the torus."""
    dx = np.sum((np.roll(a, -1, axis=1) - a) ** 2, axis=2)
    dy = np.sum((np.roll(a, -1, axis=0) - a) ** 2, axis=2)
    return dx, dy


def _ratio(border: float, interior: float) -> float:
    if interior > 0:
        return border / interior
    return 1.0 if border == 0 else float("inf")


def seam_energy(x: np.ndarray, band: int = SEAM_BAND) -> dict[str, float]:
    """Gradient energy across the tile borders against the interior's beside them, for one map (H, W) or (H, W, C).

    The map is wrapped by half its size, so its borders meet in the middle; ``border`` is the mean squared jump
    (summed over channels) across those two lines, ``interior`` the mean over the ``band`` lines of neighbour
    pairs on each side of each border (the same rows and columns, so that the content's own variation from one
    part of the texture to another cancels), ``ratio`` = border / interior: about 1 (0.85 .. 1.2 for one line of
    a natural texture) where the borders look like any other line, far above 1 at a seam."""
    a = np.asarray(x, np.float64)
    a = a[..., None] if a.ndim == 2 else a
    h, w = a.shape[:2]
    dx, dy = _pair_energy(np.roll(a, (h // 2, w // 2), axis=(0, 1)))
    bx, by = w // 2 - 1, h // 2 - 1  # the pairs that were the borders
    near_x = [bx + k for k in range(-band, band + 1) if k]
    near_y = [by + k for k in range(-band, band + 1) if k]
    border = float(np.concatenate([dx[:, bx], dy[by, :]]).mean())
    interior = float(np.concatenate([dx[:, near_x].ravel(), dy[near_y, :].ravel()]).mean())
    return {"border": border, "interior": interior, "ratio": _ratio(border, interior)}


def cut_energy(x: np.ndarray, shift_id: np.ndarray, band: int = SEAM_BAND) -> dict[str, float]:
    """The same measure for the cut inside the tile: the mean squared jump across the texel pairs whose two texels
    come from different shifts (``shift_id`` (P, P) ints), against the pairs 1 .. ``band`` texels beside them
    along the same rows / columns that do not cross the cut."""
    a = np.asarray(x, np.float64)
    a = a[..., None] if a.ndim == 2 else a
    dx, dy = _pair_energy(a)
    cx = shift_id != np.roll(shift_id, -1, axis=1)
    cy = shift_id != np.roll(shift_id, -1, axis=0)
    if not cx.any() and not cy.any():
        return {"border": 0.0, "interior": 0.0, "ratio": 1.0}
    nx, ny = np.zeros_like(cx), np.zeros_like(cy)
    for k in range(1, band + 1):
        for sgn in (-1, 1):
            nx |= np.roll(cx, sgn * k, axis=1)
            ny |= np.roll(cy, sgn * k, axis=0)
    nx &= ~cx
    ny &= ~cy
    border = float(np.concatenate([dx[cx], dy[cy]]).mean())
    interior = float(np.concatenate([dx[nx], dy[ny]]).mean())
    return {"border": border, "interior": interior, "ratio": _ratio(border, interior)}


def map_planes(maps: MaterialMaps) -> dict[str, np.ndarray]:
    """The maps :func:`seam_energy` is reported for (those present)."""
    return {name: getattr(maps, name) for name in MAP_NAMES if getattr(maps, name) is not None}


def seam_report(maps: MaterialMaps) -> dict[str, dict[str, float]]:
    """:func:`seam_energy` of each map."""
    return {name: seam_energy(v) for name, v in map_planes(maps).items()}


# ------------------------------------------------------------------------------------------------ tile_maps
def tile_maps(maps: MaterialMaps, size: int | None = None, *, what: str = "--size"
              ) -> tuple[MaterialMaps, dict[str, Any]]:
    """The seamless square power-of-two version of ``maps`` (module doc) and a description of what was done
    (crop, size, cut, seam energies) for ``capture.json``. The result's mask is all True; its height is the
    periodic integral of its normals."""
    from matcap.height import integrate_normals

    if not np.isfinite(maps.normal).all():
        raise MatcapError("the normal map holds NaN or Inf values")
    row, col, side = largest_square(maps.mask)
    if side < MIN_SIZE:
        raise MatcapError(f"the mask covers no square of at least {MIN_SIZE} x {MIN_SIZE} pixels (largest: "
                          f"{side} x {side}); tiling needs a square patch of the surface")
    p = check_size(size, side, what) or default_size(side)
    k = overlap(p)
    # no size given: the tile and its overlap at the maps' own resolution (a crop of the square, when it holds
    # them); a size given: the whole square resampled to that size (plus the overlap)
    n = side if size is not None else min(side, p + k)
    placed: dict[str, Any] = {"rule": "the whole square" + (", resampled" if side != p + k else "")}
    if side > n:
        square_maps = MaterialMaps(
            normal=maps.normal[row:row + side, col:col + side], mask=np.ones((side, side), bool),
            **{name: None if getattr(maps, name) is None else getattr(maps, name)[row:row + side, col:col + side]
               for name in ("base_color", "roughness", "metallic")})
        (dr, dc), placed = border_offsets(square_maps, n, p)
        row, col = row + dr, col + dc
    crop = (slice(row, row + n), slice(col, col + n))

    def square(x):
        return None if x is None else _resize(np.nan_to_num(np.asarray(x, np.float32)[crop]), p + k)

    sq = MaterialMaps(normal=square(maps.normal), mask=np.ones((p + k, p + k), bool),
                      base_color=square(maps.base_color),
                      roughness=square(maps.roughness), metallic=square(maps.metallic), meta=dict(maps.meta))
    sq.normal = unit_normals(sq.normal)
    stack, groups = _stack(sq)
    scale = {name: max(float(np.mean(np.var(stack[..., sl], axis=(0, 1)))), 1e-6) for name, sl in groups.items()}
    src_r, src_c, cut = cut_shifts(stack, p, groups, scale)
    out = blend(stack, src_r, src_c)
    values: dict[str, np.ndarray] = {}
    for name, sl in groups.items():
        v = out[..., sl]
        values[name] = unit_normals(v) if name == "normal" else np.clip(v if v.shape[2] > 1 else v[..., 0], 0.0, 1.0)
    normal, tilt = level(values.pop("normal"))
    height = integrate_normals(normal, None, "periodic")
    tiled = MaterialMaps(normal=normal, mask=np.ones((p, p), bool), height=height, meta=dict(maps.meta), **values)
    shifts = np.stack([src_r - np.arange(p)[:, None], src_c - np.arange(p)[None, :]], axis=-1)
    region = np.unique(shifts.reshape(-1, 2), axis=0, return_counts=True)
    shift_id = shifts[..., 0] * p + shifts[..., 1]
    info = {
        "method": "square crop with an overlap of P/8, one min-error cut shared by all maps (dynamic programming "
                  "on the joint error), Poisson blend on the torus, height by periodic Fourier integration",
        "source_size": {"width": int(maps.shape[1]), "height": int(maps.shape[0])},
        "crop": {"row": row, "col": col, "side": n, "largest_square": side, "resampled_to": p + k,
                 "scale": (p + k) / n, "placement": placed},
        "size": p,
        "maps": list(groups) + ["height"],
        "cut": {**cut, "texels_per_shift": {f"{int(s[0])},{int(s[1])}": int(c) for s, c in zip(*region)}},
        "height": "periodic Fourier integration of the tiled normals (pixel units, zero mean)",
        "mean_tilt_removed_deg": round(tilt, 4),
        "seam_energy": {name: {k: round(v, 8) for k, v in e.items()} for name, e in seam_report(tiled).items()},
        "cut_energy": {name: {k: round(v, 8) for k, v in cut_energy(x, shift_id).items()}
                       for name, x in map_planes(tiled).items()},
    }
    tiled.meta = {**{k: v for k, v in maps.meta.items() if k != "tiling"}, "tiling": info}
    return tiled, info


def level(normal: np.ndarray) -> tuple[np.ndarray, float]:
    """The normals turned so that their mean is +z (a periodic height has no mean slope: without this a tilted
    sample's normals and its tiled height would disagree by the tilt everywhere), and the tilt removed in degrees.
    The turn is ``matcap export --fit-frame``'s tangent frame (N = the mean normal, T = image x projected onto the
    plane)."""
    from matcap.formats import camera_to_tangent, tangent_frame

    mask = np.ones(normal.shape[:2], bool)
    frame = tangent_frame(normal, mask, "fit")
    tilt = float(np.degrees(np.arccos(np.clip(frame[2, 2], -1.0, 1.0))))  # rows T, B, N in camera space
    return camera_to_tangent(normal, mask, frame), tilt


def is_tiled(maps: MaterialMaps) -> bool:
    """Maps already made seamless by :func:`tile_maps` (their ``meta`` records the tiling and they are square)."""
    h, w = maps.shape
    return isinstance(maps.meta.get("tiling"), dict) and h == w and bool(maps.mask.all())


# ------------------------------------------------------------------------------------------------ preview
def preview(maps: MaterialMaps, *, repeats: int = 3, tile_px: int = PREVIEW_TILE, spp: int = PREVIEW_SPP,
            seed: int = 0) -> np.ndarray:
    """(N, N, 3) display-sRGB render of ``maps`` repeated ``repeats`` x ``repeats`` under the bundled studio
    environment map (N = repeats x min(tile_px, side)), tone mapped as ``matcap relight`` does."""
    from matcap.relight import build_lights, default_envmap_path, tonemap
    from renderers.relight import render

    p = maps.shape[0]
    t = min(tile_px, p)
    small = MaterialMaps(
        normal=unit_normals(_resize(maps.normal, t)), mask=np.ones((t, t), bool),
        base_color=None if maps.base_color is None else _resize(maps.base_color, t),
        roughness=None if maps.roughness is None else _resize(maps.roughness, t),
        metallic=None if maps.metallic is None else _resize(maps.metallic, t))

    def rep(x):
        return None if x is None else np.tile(x, (repeats, repeats) + (1,) * (x.ndim - 2))

    grid = MaterialMaps(normal=rep(small.normal), mask=rep(small.mask), base_color=rep(small.base_color),
                        roughness=rep(small.roughness), metallic=rep(small.metallic))
    (_, lights, envmaps), = build_lights([default_envmap_path()])
    n = repeats * t
    return tonemap(render(grid, lights, envmaps, spp=spp, size=(n, n), seed=seed))


# ------------------------------------------------------------------------------------------------ tile (files)
def tile(source: MaterialMaps | str | os.PathLike, out: str | os.PathLike, *, size: int | None = None,
         overwrite: bool = False, preview_image: bool = True, spp: int = PREVIEW_SPP,
         progress: bool = False) -> dict[str, Any]:
    """Tile ``source`` (any map source :func:`matcap.formats.load_maps` reads) into the result folder ``out``:
    the maps (with ``height.exr``), ``preview_3x3.png`` (unless ``preview_image`` is off) and ``capture.json``
    with a ``tiling`` entry. Written atomically; refuses an existing non-empty ``out`` unless ``overwrite``.
    ``progress``: one line (or bar) per stage on stderr. Returns the tiling description."""
    from networks.progress import progress as progress_bar
    from matcap import formats
    from matcap.relight import check_spp
    from matcap.results import check_not_replacing_inputs, check_output_dir, write_result

    check_size(size)
    check_spp(spp)
    if not isinstance(source, MaterialMaps) and not Path(source).exists():
        raise MatcapError(f"{source}: no such result folder")
    check_output_dir(out, overwrite)
    check_not_replacing_inputs(out, source if not isinstance(source, MaterialMaps) else None)
    maps = formats.load_maps(source)
    bar = progress_bar(total=3 if preview_image else 2, desc="tile", unit="stage", enabled=progress)
    tiled, info = tile_maps(maps, size)
    bar.update(1)
    if not isinstance(source, MaterialMaps):
        info["source"] = str(source)
    spec = formats.LAYOUTS["result"]["preview"]
    picture = None
    if preview_image:
        picture = preview(tiled, spp=spp)
        info["preview"] = {"file": spec.file, "repeats": 3, "size": int(picture.shape[0]), "spp": spp,
                           "envmap": "studio_small_03.exr (bundled)", "tonemap": "aces"}
        bar.update(1)

    def extra(folder: Path) -> list[str]:
        if picture is None:
            return []
        formats.write_file(folder, spec, {c: picture[..., i] for i, c in enumerate(formats.DISPLAY)})
        return [spec.file]

    write_result(replace(tiled, meta={**tiled.meta, "tiling": info}), out, overwrite=overwrite, extra_files=extra)
    bar.update(1)
    bar.close()
    return info

"""Light directions (and relative intensities) from a mirror ball photographed under each light.

Model
-----
Camera frame as ``normal.exr``: x right, y up, z toward the camera. Pixel coordinates ``(x, y)`` = (column, row)
of a pixel's centre, row 0 at the top, so a pixel's "up" offset is ``-(row - cy)``.

* **Orthographic camera** (default): every pixel looks along ``v = (0, 0, 1)`` (toward the camera). A pixel at
  ``(x, y)`` inside the ball's circle ``(cx, cy, r)`` sees the ball's normal
  ``n = ((x - cx) / r, -(y - cy) / r, sqrt(1 - nx^2 - ny^2))`` and the direction that the ball reflects into the
  camera, ``d = 2 (n . v) n - v``. Each pixel of the ball then covers the same solid angle of reflected directions,
  ``4 / r^2`` sr.
* **Perspective camera** (``focal_px`` given): a pinhole at the origin with the principal point at the image centre
  ``((W - 1) / 2, (H - 1) / 2)`` and focal length ``focal_px`` in pixels. The ball (radius 1) is placed by the
  cone of rays tangent to it: the rays through its outline's points (found at sub-pixel, or the mask's outline)
  all make the same angle with the ray to its centre, so a robust fit of that small circle on the sphere of
  directions gives the centre's direction and the angular radius (exact for the slightly elliptical image of an
  off-axis sphere). Each pixel's ray is intersected with the ball and ``v`` is that pixel's direction back to
  the camera.

A photo's light direction is the mean of the reflected directions ``d`` over its highlight, each pixel weighted
by its brightness above the local background, normalised. The highlight is the connected blob around the
brightest pixel of the ball (above half of the peak over the ball's median) grown by its tails (4 % of the
radius, at least 2 px); the background is the median of a ring around it. Weighting pixel-averaged values
keeps the centre of a highlight smaller than a pixel, and a clipped highlight gives the centre of its blob. A
photo whose ball holds no highlight (peak not 3x the ball's 90th percentile) or a highlight clipped into a large
blob (over 20 deg across in reflected directions) is refused with one line naming the photo.

Relative intensities: a mirror ball reflects a distant light's whole irradiance (times the ball's reflectance)
into its highlight, so the highlight's energy above the ball's background, summed over its pixels, is
proportional to the light's irradiance (summed over the blob grown by 15 % of the radius, above the median of a
ring around that). That holds only while the highlight is not clipped: when any photo's
highlight reaches the photo's clipping level, intensities are left unknown (``None``; the fit estimates them).
Known intensities are scaled to a mean of 1 over all photos and channels (relative, colour kept).

The ball is found automatically: a circle whose outline stays put in every photo (circle candidates by a Hough
transform of the log of the photos' mean), each refined to sub-pixel by a robust fit of the strongest radial edge
along 180 rays, and scored by its edge support and by how sharp a highlight every photo shows inside it. Where
that fails, ``ball_mask`` (an (H, W) bool image of the ball's disc) gives the circle instead.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from matcap.errors import MatcapError

#: Part of the circle's radius searched for highlights (the very rim only reflects what is behind the ball).
RIM = 0.985
#: A highlight's peak must exceed the ball's 90th percentile by this factor (else: "no highlight").
MIN_PEAK_RATIO = 3.0
#: A clipped highlight whose equivalent radius, in reflected directions, exceeds this is refused (degrees).
MAX_CLIPPED_DEG = 20.0
#: Pixels within this fraction of a photo's maximum count as clipped (when several share that maximum).
CLIP_TOLERANCE = 1e-3
#: Pixels of margin around the ball's disc in :meth:`Calibration.ball_mask`, as a fraction of the radius.
MASK_MARGIN = 0.06
#: Rays along which the ball's outline is located.
RAYS = 180
#: Circles are searched on copies of the photos shrunk to this longer side (then refined at full size).
WORK_SIDE = 1024
#: The diagnostic picture written beside the light file.
DIAGNOSTIC = "calibration.png"


@dataclass
class Calibration:
    """The result of :func:`calibrate`.

    directions: (K, 3) unit vectors toward each photo's light, camera frame (x right, y up, z toward the camera).
    intensities: (K, 3) relative linear RGB irradiance (mean 1), or None when unknown (a clipped highlight).
    circle: (cx, cy, r) of the ball in pixels (column, row of pixel centres; radius).
    highlights: (K, 2) sub-pixel (x, y) = (column, row) of each photo's highlight centre.
    names: K photo names (file names where known).
    quality: per photo a dict: ``peak`` (linear), ``blob_px``, ``clipped_px``, ``spread_deg`` (weighted RMS angle
        of the highlight's reflected directions about the result), ``note`` (empty or a warning).
    size: (H, W) of the photos.
    camera: ``"orthographic"`` or ``"perspective f=<focal_px> px, principal point at the image centre"``.
    circle_source: ``"auto"`` (found in the photos) or ``"mask"`` (from ``ball_mask``).
    notes: remarks about the whole calibration (e.g. why intensities are unknown).
    cone: perspective camera only: (unit ray to the ball's centre (3,), the ball's angular radius in radians).
    """

    directions: np.ndarray
    intensities: np.ndarray | None
    circle: tuple[float, float, float]
    highlights: np.ndarray
    names: list[str]
    quality: list[dict]
    size: tuple[int, int]
    camera: str = "orthographic"
    focal_px: float | None = None
    circle_source: str = "auto"
    notes: list[str] = field(default_factory=list)
    cone: tuple[np.ndarray, float] | None = None

    def ball_mask(self, margin: float = MASK_MARGIN) -> np.ndarray:
        """(H, W) bool: the ball's disc grown by ``margin`` x radius (at least 2 pixels), to keep the ball out of
        an object's mask."""
        h, w = self.size
        cx, cy, r = self.circle
        yy, xx = np.mgrid[0:h, 0:w]
        grow = max(margin * r, 2.0)
        return (xx - cx) ** 2 + (yy - cy) ** 2 <= (r + grow) ** 2

    def entries(self) -> list[dict]:
        """``lights.json`` image entries (``matcap.refine.lightfile`` schema): directional lights, intensity
        [1, 1, 1] where unknown, zero SH, each with its photo's ``file`` name and highlight position."""
        out = []
        for k, name in enumerate(self.names):
            inten = [1.0, 1.0, 1.0] if self.intensities is None else [float(v) for v in self.intensities[k]]
            q = self.quality[k]
            out.append({
                "index": k, "file": name, "kind": "directional",
                "direction": [float(v) for v in self.directions[k]],
                "intensity": inten,
                "sh": [[0.0, 0.0, 0.0]] * 9,
                "highlight_px": [round(float(v), 3) for v in self.highlights[k]],
                "spread_deg": round(float(q["spread_deg"]), 3),
                **({"note": q["note"]} if q.get("note") else {}),
            })
        return out

    def document_fields(self) -> dict:
        """Top-level fields added to ``lights.json``: where the lights came from and the camera model."""
        cx, cy, r = self.circle
        return {
            "source": "ball",
            "camera": self.camera,
            "intensity_known": self.intensities is not None,
            "intensity_units": "relative",  # a ball's highlights give the lamps' ratios, not their power
            "ball": {"circle_px": [round(cx, 3), round(cy, 3), round(r, 3)], "found": self.circle_source,
                     "image_size_wh": [int(self.size[1]), int(self.size[0])],
                     **({} if self.cone is None else {
                         "centre_ray": [round(float(v), 6) for v in self.cone[0]],
                         "angular_radius_deg": round(math.degrees(self.cone[1]), 4)})},
            **({"notes": list(self.notes)} if self.notes else {}),
        }


# ------------------------------------------------------------------------------------------- helpers


def _luminance(img: np.ndarray) -> np.ndarray:
    """(H, W) float32 mean of RGB."""
    import cv2

    arr = np.ascontiguousarray(img, dtype=np.float32)
    out = cv2.transform(arr, np.full((1, 3), 1.0 / 3.0, dtype=np.float32))  # (H, W) (or (H, W, 1))
    return out.reshape(arr.shape[:2])


def _box(circle, size: tuple[int, int], grow: float = 1.1, pad: int = 4) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the pixels within ``grow`` x the circle's radius (+ ``pad``), clipped to the image."""
    cx, cy, r = circle
    m = grow * r + pad
    h, w = size
    return (max(0, int(math.floor(cy - m))), min(h, int(math.ceil(cy + m)) + 1),
            max(0, int(math.floor(cx - m))), min(w, int(math.ceil(cx + m)) + 1))


def _check_images(images: Sequence[np.ndarray], names: Sequence[str]) -> tuple[int, int]:
    if len(images) < 2:
        raise MatcapError(f"calibration needs at least 2 photos of the ball, got {len(images)}")
    shape = None
    for img, name in zip(images, names):
        arr = np.asarray(img)
        if arr.ndim != 3 or arr.shape[2] != 3:
            raise MatcapError(f"{name}: expected an (H, W, 3) RGB image, got shape {arr.shape}")
        if shape is None:
            shape = arr.shape[:2]
        elif arr.shape[:2] != shape:
            raise MatcapError(f"{name}: {arr.shape[1]}x{arr.shape[0]} but the first photo is {shape[1]}x{shape[0]}")
        if not np.all(np.isfinite(arr)):
            raise MatcapError(f"{name}: holds NaN or infinite values")
    return int(shape[0]), int(shape[1])


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    from scipy.ndimage import map_coordinates

    return map_coordinates(img, [y.ravel(), x.ravel()], order=1, mode="nearest").reshape(x.shape)


def _fit_circle(x: np.ndarray, y: np.ndarray, start: tuple[float, float, float] | None = None):
    """Robust geometric circle fit (soft-L1 loss, 0.7 px scale) of points (x, y); returns (cx, cy, r)."""
    from scipy.optimize import least_squares

    if start is None:  # algebraic (Kasa) fit
        a = np.stack([x, y, np.ones_like(x)], axis=1)
        b = x * x + y * y
        sol, *_ = np.linalg.lstsq(a, b, rcond=None)
        cx, cy = sol[0] / 2, sol[1] / 2
        start = (cx, cy, math.sqrt(max(sol[2] + cx * cx + cy * cy, 1e-6)))

    def resid(p):
        return np.hypot(x - p[0], y - p[1]) - p[2]

    res = least_squares(resid, np.asarray(start, dtype=np.float64), loss="soft_l1", f_scale=0.7)
    return tuple(float(v) for v in res.x)


def _structure_images(lums: Sequence[np.ndarray], log: bool = True,
                      median: bool = True) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Two (H, W) float32 images in which the ball's outline stays put: the log of the photos' mean luminance
    (every edge visible, for finding circles) and the photos' median luminance (linear, without the moving
    highlights and shadows: where a pixel-averaged edge's steepest point is the edge itself, for sub-pixel
    refinement; the log would move it toward the dark side), both lightly smoothed."""
    import cv2

    out_log = out_median = None
    if log:
        mean = np.mean(lums, axis=0, dtype=np.float32)
        positive = mean[mean > 0]
        eps = max(float(np.percentile(positive, 5)) if positive.size else 1e-6, 1e-6)
        out_log = cv2.GaussianBlur(np.log(mean + eps).astype(np.float32), (0, 0), 1.0)
    if median:
        out_median = cv2.GaussianBlur(np.median(lums, axis=0).astype(np.float32), (0, 0), 0.7)
    return out_log, out_median


def _refine_circle(log: np.ndarray, start: tuple[float, float, float], rays: int = RAYS,
                   widths: tuple[str, ...] = ("wide", "mid", "narrow")):
    """Sub-pixel circle from the strongest radial edge of the image ``log`` along ``rays`` rays around ``start``,
    searched within +-25 % of the radius, then +-(8 % + 2 px), then +-3 px (``widths``).

    Returns (cx, cy, r, support, contrast, points): the share of rays whose edge lies within 1 px of the fitted
    circle, the median step across it, and those edge points (N, 2) (x, y)."""
    cx, cy, r = start
    theta = np.linspace(0, 2 * np.pi, rays, endpoint=False)
    cos, sin = np.cos(theta), np.sin(theta)
    support, contrast, points = 0.0, 0.0, np.zeros((0, 2))
    for which in widths:
        half_width = {"wide": 0.25 * r, "mid": 0.08 * r + 2.0, "narrow": 3.0}[which]
        s = np.arange(-half_width, half_width + 1e-9, 0.25)  # radial offsets, px
        rad = r + s[None, :]
        xs = cx + cos[:, None] * rad
        ys = cy + sin[:, None] * rad
        prof = _bilinear(log, xs, ys)  # (rays, S)
        grad = np.gradient(prof, s, axis=1)
        sign = np.sign(np.median(grad[np.arange(rays), np.argmax(np.abs(grad), axis=1)]))
        if sign == 0:
            sign = 1.0
        g = sign * grad
        j = np.argmax(g, axis=1)
        jj = np.clip(j, 1, len(s) - 2)
        g0, g1, g2 = g[np.arange(rays), jj - 1], g[np.arange(rays), jj], g[np.arange(rays), jj + 1]
        den = g0 - 2 * g1 + g2
        off = np.where(np.abs(den) > 1e-12, 0.5 * (g0 - g2) / np.where(den == 0, 1, den), 0.0)
        pos = s[jj] + np.clip(off, -1, 1) * 0.25
        strength = g1
        ok = (strength > 0) & (j > 0) & (j < len(s) - 1)
        if ok.sum() < 12:
            return cx, cy, r, 0.0, 0.0, np.zeros((0, 2))
        ex = cx + cos[ok] * (r + pos[ok])
        ey = cy + sin[ok] * (r + pos[ok])
        cx, cy, r = _fit_circle(ex, ey, (cx, cy, r))
        dist = np.abs(np.hypot(ex - cx, ey - cy) - r)
        inl = dist < 1.0
        if inl.sum() >= 12:  # refit on the inliers only (a stand, the object or a shadow touching the ball)
            cx, cy, r = _fit_circle(ex[inl], ey[inl], (cx, cy, r))
            dist = np.abs(np.hypot(ex - cx, ey - cy) - r)
            inl = dist < 1.0
        support = float(inl.sum()) / rays
        contrast = float(np.median(strength[ok][inl])) if inl.any() else 0.0
        points = np.stack([ex[inl], ey[inl]], axis=1)
    return cx, cy, r, support, contrast, points


def _disc(shape: tuple[int, int], circle, scale: float = 1.0) -> np.ndarray:
    h, w = shape
    cx, cy, r = circle
    yy, xx = np.mgrid[0:h, 0:w]
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= (scale * r) ** 2


def _highlight_sharpness(lums: Sequence[np.ndarray], circle) -> float:
    """Median over photos of log(peak / 90th percentile) inside the circle (a mirror ball: large)."""
    y0, y1, x0, x1 = _box(circle, lums[0].shape)
    disc = _disc((y1 - y0, x1 - x0), (circle[0] - x0, circle[1] - y0, circle[2]), RIM)
    if disc.sum() < 20:
        return 0.0
    vals = []
    for lum in lums:
        v = lum[y0:y1, x0:x1][disc]
        p90 = float(np.percentile(v, 90))
        vals.append(math.log((float(v.max()) + 1e-9) / (p90 + 1e-9)))
    return float(np.median(vals))


def find_ball(images: Sequence[np.ndarray]) -> tuple[tuple[float, float, float], dict]:
    """The mirror ball's circle (cx, cy, r) in pixels found in the photos, and a dict describing the choice.

    Raises :class:`MatcapError` when no circle has a clear outline and a highlight in every photo."""
    import cv2

    size = images[0].shape[:2]
    scale = min(1.0, WORK_SIDE / max(size))
    if scale < 1.0:  # find circles on smaller copies; the chosen one is refined at full size below
        wh = (max(1, round(size[1] * scale)), max(1, round(size[0] * scale)))
        lums = [cv2.resize(_luminance(im), wh, interpolation=cv2.INTER_AREA) for im in images]
    else:
        lums = [_luminance(im) for im in images]
    log, _ = _structure_images(lums, median=False)
    h, w = log.shape
    lo, hi = np.percentile(log, [1, 99.5])
    u8 = (np.clip((log - lo) / max(hi - lo, 1e-6), 0, 1) * 255).astype(np.uint8)
    side = min(h, w)
    min_r, max_r = max(int(0.01 * side), 5), int(0.5 * side)
    found = cv2.HoughCircles(u8, cv2.HOUGH_GRADIENT, dp=1, minDist=max(4, min_r // 2), param1=60, param2=18,
                             minRadius=min_r, maxRadius=max_r)
    cands = [] if found is None else [tuple(float(v) for v in c) for c in found[0][:25]]
    best, best_score, tried = None, 0.0, []
    for c in cands:
        cx, cy, r, support, contrast, _ = _refine_circle(log, c)
        if not (min_r * 0.8 <= r <= max_r * 1.1) or support < 0.4:
            continue
        sharp = _highlight_sharpness(lums, (cx, cy, r))
        score = support * math.log1p(max(sharp, 0.0)) * min(contrast, 1.0) ** 0.25
        tried.append((score, (cx, cy, r), support, sharp))
        if score > best_score:
            best, best_score = (cx, cy, r), score
    if best is None or best_score <= 0:
        raise MatcapError("no mirror ball found in the photos (no steady circular outline with a highlight in "
                          "each photo); give its disc as a mask with --ball-mask")
    tried.sort(key=lambda t: -t[0])
    # back to full-size pixel centres, then the sub-pixel edge on the photos' median around the circle
    best = ((best[0] + 0.5) / scale - 0.5, (best[1] + 0.5) / scale - 0.5, best[2] / scale)
    y0, y1, x0, x1 = _box(best, size, grow=1.3, pad=8)
    crops = [_luminance(im[y0:y1, x0:x1]) for im in images]
    _, median = _structure_images(crops, log=False)
    local = (best[0] - x0, best[1] - y0, best[2])
    cx, cy, r, support, _, points = _refine_circle(median, local, widths=("mid", "narrow"))
    edge = None
    if support >= 0.5 and abs(r - best[2]) < 0.05 * best[2] + 1 + 1 / scale and \
            math.hypot(cx - local[0], cy - local[1]) < 2 + 1 / scale:
        best = (cx + x0, cy + y0, r)
        edge = points + [x0, y0]
    info = {"candidates": len(cands), "support": tried[0][2], "sharpness": tried[0][3], "median_support": support,
            "work_scale": scale, "edge_px": edge}
    return best, info


def circle_from_mask(mask: np.ndarray) -> tuple[float, float, float]:
    """(cx, cy, r) of a ball's disc given as an (H, W) bool mask: a robust circle fit to its outline (the
    outline between inside and outside pixels, at half a pixel)."""
    return _circle_and_outline(mask)[0]


def _circle_and_outline(mask: np.ndarray) -> tuple[tuple[float, float, float], np.ndarray]:
    """:func:`circle_from_mask` and the outline's points (N, 2) (x, y) in pixels (holes filled: only the
    outer outline counts)."""
    from scipy.ndimage import binary_fill_holes

    m = binary_fill_holes(np.asarray(mask, dtype=bool))
    if m.sum() < 20:
        raise MatcapError(f"the ball mask has {int(m.sum())} pixels; it should cover the ball's disc")
    import cv2

    # half-way points between boundary pixels and their outside neighbours
    pts_x, pts_y = [], []
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        shifted = np.zeros_like(m)
        ys = slice(max(dy, 0), m.shape[0] + min(dy, 0))
        xs = slice(max(dx, 0), m.shape[1] + min(dx, 0))
        ys0 = slice(max(-dy, 0), m.shape[0] + min(-dy, 0))
        xs0 = slice(max(-dx, 0), m.shape[1] + min(-dx, 0))
        shifted[ys0, xs0] = m[ys, xs]  # shifted[y, x] = m[y + dy, x + dx]
        edge = m & ~shifted
        yy, xx = np.nonzero(edge)
        pts_x.append(xx + 0.5 * dx)
        pts_y.append(yy + 0.5 * dy)
    x = np.concatenate(pts_x).astype(np.float64)
    y = np.concatenate(pts_y).astype(np.float64)
    inside = (x >= 0) & (y >= 0) & (x <= m.shape[1] - 1) & (y <= m.shape[0] - 1)  # not the image's border
    x, y = x[inside], y[inside]
    n, labels = cv2.connectedComponents(m.astype(np.uint8))
    if n > 2:  # keep the largest piece's outline
        sizes = np.bincount(labels.ravel())[1:]
        keep = labels == (1 + int(np.argmax(sizes)))
        return _circle_and_outline(keep)
    cx, cy, r = _fit_circle(x, y)
    disc = _disc(m.shape, (cx, cy, r))
    iou = float((disc & m).sum()) / max(float((disc | m).sum()), 1.0)
    if iou < 0.9:
        raise MatcapError(f"the ball mask is not a disc (it overlaps the best-fitting circle by {100 * iou:.0f} %)")
    return (cx, cy, r), np.stack([x, y], axis=1)


# ------------------------------------------------------------------------------------------- geometry


def _pixel_rays(x: np.ndarray, y: np.ndarray, size: tuple[int, int], focal_px: float) -> np.ndarray:
    """(N, 3) unit ray directions (from the pinhole into the scene, camera frame) of pixel coordinates (N,)."""
    h, w = size
    px, py = (w - 1) / 2.0, (h - 1) / 2.0
    x = np.asarray(x, dtype=np.float64)
    d = np.stack([(x - px) / focal_px, -(np.asarray(y, dtype=np.float64) - py) / focal_px, -np.ones_like(x)],
                 axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def ball_cone(circle, size: tuple[int, int], focal_px: float, edge_px: np.ndarray | None = None):
    """The perspective ball as the cone of rays tangent to it: (unit ray to its centre (3,), half-angle in
    radians). From ``edge_px`` (N, 2) points of its outline, a robust fit of the small circle that their rays
    trace on the sphere of directions (exact for a sphere's off-axis, elliptical image); else from the circle:
    along the image's radial line through it, the rays to its near and far edges bound the cone."""
    from scipy.optimize import least_squares

    cx, cy, r = circle
    h, w = size
    px, py = (w - 1) / 2.0, (h - 1) / 2.0
    f = float(focal_px)
    rho = math.hypot(cx - px, cy - py)
    a1, a2 = math.atan2(rho - r, f), math.atan2(rho + r, f)
    alpha = 0.5 * (a2 - a1)
    beta = 0.5 * (a1 + a2)  # angle of the ball's centre off the optical axis
    ux, uy = ((cx - px) / rho, (cy - py) / rho) if rho > 1e-9 else (1.0, 0.0)
    t = f * math.tan(beta)
    c = _pixel_rays(np.array([px + ux * t]), np.array([py + uy * t]), size, f)[0]
    if edge_px is None or len(edge_px) < 12:
        return c, alpha
    rays = _pixel_rays(edge_px[:, 0], edge_px[:, 1], size, f)

    def resid(p):
        cc = p[:3] / np.linalg.norm(p[:3])
        return (np.arccos(np.clip(rays @ cc, -1, 1)) - p[3]) * f  # ~ pixels

    res = least_squares(resid, np.concatenate([c, [alpha]]), loss="soft_l1", f_scale=0.7)
    c = res.x[:3] / np.linalg.norm(res.x[:3])
    return c, float(res.x[3])


def _view_and_normal(x: np.ndarray, y: np.ndarray, circle, size: tuple[int, int], focal_px: float | None,
                     cone=None):
    """Per pixel (N,) coordinates: unit view vectors v (toward the camera) and ball normals n, (N, 3) each, and a
    bool (N,) for pixels whose ray meets the ball. ``cone``: the perspective ball (:func:`ball_cone`; default:
    from the circle)."""
    cx, cy, r = circle
    if focal_px is None:
        nx = (x - cx) / r
        ny = -(y - cy) / r
        q = 1.0 - nx * nx - ny * ny
        hit = q >= 0
        n = np.stack([nx, ny, np.sqrt(np.clip(q, 0, None))], axis=1)
        v = np.broadcast_to(np.array([0.0, 0.0, 1.0]), n.shape)
        return v, n, hit
    c, alpha = cone if cone is not None else ball_cone(circle, size, focal_px)
    dist = 1.0 / math.sin(alpha)  # the ball has radius 1
    centre = np.asarray(c) * dist
    d = _pixel_rays(x, y, size, float(focal_px))
    b = d @ centre
    disc = b * b - (dist * dist - 1.0)
    hit = disc >= 0
    t = b - np.sqrt(np.clip(disc, 0, None))
    n = d * t[:, None] - centre[None, :]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return -d, n, hit


def reflect(x: np.ndarray, y: np.ndarray, circle, size: tuple[int, int], focal_px: float | None = None, cone=None):
    """Reflected directions (N, 3) (unit, toward what the ball reflects into each pixel) for pixel coordinates
    ``x``, ``y`` (N,) (column, row), and a bool (N,) for pixels on the ball. ``cone``: see :func:`ball_cone`."""
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    v, n, hit = _view_and_normal(x, y, circle, size, focal_px, cone)
    d = 2.0 * np.sum(n * v, axis=1, keepdims=True) * n - v
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, hit


def direction_to_pixel(direction: np.ndarray, circle, size: tuple[int, int], focal_px: float | None = None,
                       cone=None):
    """(x, y) pixel (column, row) where the ball reflects ``direction`` (3,) into the camera (inverse of
    :func:`reflect`; for the perspective model, found by a few Newton steps)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    cx, cy, r = circle
    n = d + np.array([0.0, 0.0, 1.0])
    n /= max(np.linalg.norm(n), 1e-12)
    x, y = cx + r * n[0], cy - r * n[1]
    if focal_px is None:
        return float(x), float(y)
    for _ in range(20):
        got, _ = reflect(np.array([x, x + 0.01, x]), np.array([y, y, y + 0.01]), circle, size, focal_px, cone)
        jac = np.stack([(got[1] - got[0]) / 0.01, (got[2] - got[0]) / 0.01], axis=1)  # (3, 2)
        step, *_ = np.linalg.lstsq(jac, d - got[0], rcond=None)
        x, y = x + step[0], y + step[1]
        if np.hypot(*step) < 1e-4:
            break
    return float(x), float(y)


# ------------------------------------------------------------------------------------------- highlights


def _clip_level(img: np.ndarray) -> float | None:
    """The photo's clipping level: its maximum channel value where several pixels share it, else None."""
    top = float(img.max())
    if top <= 0:
        return None
    count = int(np.count_nonzero(img >= top * (1 - CLIP_TOLERANCE)))  # channel values: at least 2 pixels' worth
    return top if count >= 6 else None


def _check_clipped(clipped_px: int, r: float, name: str) -> None:
    """Refuse a clipped area whose equivalent radius in reflected directions (each pixel of an orthographic ball
    covers 4 / r^2 sr) exceeds :data:`MAX_CLIPPED_DEG`."""
    radius_deg = math.degrees(2.0 * math.sqrt(clipped_px / math.pi) / r)
    if radius_deg > MAX_CLIPPED_DEG:
        raise MatcapError(f"{name}: the highlight is clipped into a large blob ({clipped_px} px, about "
                          f"{radius_deg:.0f} deg across in reflected directions); take it with less exposure")


def locate_highlight(image: np.ndarray, circle, name: str, focal_px: float | None = None, cone=None) -> dict:
    """The highlight of one photo (H, W, 3) on the ball: its light direction and where it is.

    Returns a dict: ``direction`` (3,), ``pixel`` (x, y), ``energy`` (3,) (sum over the highlight of the RGB
    above the ball's median, in pixel units), ``peak``, ``blob_px``, ``clipped_px``, ``clipped`` (bool),
    ``spread_deg``. Raises :class:`MatcapError` naming ``name`` for no highlight or a large clipped blob."""
    import cv2

    full = np.asarray(image)
    size = full.shape[:2]
    level = _clip_level(full)  # the photo's own clipping level
    y0, y1, x0, x1 = _box(circle, size, grow=1.0)
    img = full[y0:y1, x0:x1].astype(np.float64)  # the ball's box: pixel (x, y) here is (x + x0, y + y0)
    lum = img.mean(axis=2)
    disc = _disc(img.shape[:2], (circle[0] - x0, circle[1] - y0, circle[2]), RIM)
    vals = lum[disc]
    if vals.size < 20:
        raise MatcapError(f"{name}: the ball's circle holds only {vals.size} pixels")
    base = float(np.median(vals))
    p90 = float(np.percentile(vals, 90))
    peak = float(vals.max())
    r = circle[2]
    if level is not None:  # a photo clipped over much of the ball (checked before "no highlight": it looks flat)
        clipped_disc = int(np.count_nonzero(disc & (img.max(axis=2) >= level * (1 - CLIP_TOLERANCE))))
        _check_clipped(clipped_disc, r, name)
    if not (peak > MIN_PEAK_RATIO * max(p90, 1e-12) and peak > base):
        raise MatcapError(f"{name}: no highlight on the ball (brightest {peak:.3g} vs the ball's 90th percentile "
                          f"{p90:.3g}); is the light in this photo visible in the ball?")
    thresh = base + 0.5 * (peak - base)
    above = (lum > thresh) & disc
    n, labels = cv2.connectedComponents(above.astype(np.uint8), connectivity=8)
    sums = np.bincount(labels.ravel(), weights=np.where(above, lum - thresh, 0).ravel(), minlength=n)
    sums[0] = 0
    blob = labels == int(np.argmax(sums))
    # the highlight's energy above the local background, over the blob grown by its tails: the centroid of a
    # pixel-averaged image is the centroid of the light itself, also for a highlight smaller than a pixel
    grow = max(2, int(round(0.04 * r)))
    grown = cv2.dilate(blob.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=grow).astype(bool) & disc
    ring = cv2.dilate(grown.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=2).astype(bool) & disc & ~grown
    bg = np.median(img[ring], axis=0) if ring.sum() >= 8 else np.median(img[disc], axis=0)
    yy, xx = np.nonzero(grown)
    wgt = np.clip(lum[yy, xx] - float(bg.mean()), 0, None)
    dirs, hit = reflect(xx + x0, yy + y0, circle, size, focal_px, cone)
    wgt = np.where(hit, wgt, 0.0)
    if wgt.sum() <= 0:
        raise MatcapError(f"{name}: the highlight lies on the ball's rim; it cannot be located")
    mean = (dirs * wgt[:, None]).sum(axis=0)
    direction = mean / np.linalg.norm(mean)
    cosang = np.clip(dirs @ direction, -1, 1)
    spread = math.degrees(math.sqrt(float((wgt * np.arccos(cosang) ** 2).sum() / wgt.sum())))
    # the energy: over a wider region (a glossy ball's highlight has long tails), above that region's ring
    wide = cv2.dilate(blob.astype(np.uint8), np.ones((3, 3), np.uint8),
                      iterations=max(3, int(round(0.15 * r)))).astype(bool) & disc
    ring = cv2.dilate(wide.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=2).astype(bool) & disc & ~wide
    bg_wide = np.median(img[ring], axis=0) if ring.sum() >= 8 else np.median(img[disc], axis=0)
    energy = (img[wide] - bg_wide).sum(axis=0)
    clipped_px = 0
    if level is not None:
        clipped_px = int(np.count_nonzero(blob & (img.max(axis=2) >= level * (1 - CLIP_TOLERANCE))))
        _check_clipped(clipped_px, r, name)
    px, py = direction_to_pixel(direction, circle, size, focal_px, cone)
    return {"direction": direction, "pixel": (px, py), "energy": energy, "peak": peak, "blob_px": int(blob.sum()),
            "clipped_px": clipped_px, "clipped": clipped_px > 0, "spread_deg": spread}


# ------------------------------------------------------------------------------------------- calibrate


def calibrate(images: Sequence[np.ndarray], ball_mask: np.ndarray | None = None, focal_px: float | None = None,
              names: Sequence[str] | None = None) -> Calibration:
    """Light directions from a mirror ball in K photos (one light each, camera and ball fixed).

    images: K >= 2 arrays (H, W, 3) float32 linear RGB (any scale). ball_mask: (H, W) bool disc of the ball
    (default: found automatically). focal_px: focal length in pixels for a perspective camera (principal point at
    the image centre); default orthographic (see the module docstring for both models). names: K photo names for
    messages and ``lights.json`` (default ``photo 0``, ...).
    Raises :class:`MatcapError` (one line) for fewer than 2 photos, mixed sizes, a wrong mask size, no ball found,
    or a photo without a usable highlight.
    """
    names = list(names) if names is not None else [f"photo {k}" for k in range(len(images))]
    if len(names) != len(images):
        raise ValueError(f"{len(names)} names for {len(images)} images")
    size = _check_images(images, names)
    if focal_px is not None:
        if not (isinstance(focal_px, (int, float)) and math.isfinite(focal_px) and focal_px > 0):
            raise MatcapError(f"the focal length must be a positive number of pixels, got {focal_px!r}")
        camera = f"perspective f={float(focal_px):g} px, principal point at the image centre"
    else:
        camera = "orthographic"
    notes: list[str] = []
    if ball_mask is not None:
        m = np.asarray(ball_mask)
        if m.shape != size:
            raise MatcapError(f"the ball mask is {m.shape[1] if m.ndim > 1 else '?'}x{m.shape[0]} but the photos "
                              f"are {size[1]}x{size[0]} (W x H)")
        circle, edge = _circle_and_outline(m.astype(bool))
        source = "mask"
    else:
        circle, info = find_ball(images)
        edge = info["edge_px"]
        source = "auto"
    cone = ball_cone(circle, size, focal_px, edge) if focal_px is not None else None
    found = [locate_highlight(img, circle, name, focal_px, cone) for img, name in zip(images, names)]
    directions = np.array([f["direction"] for f in found])
    highlights = np.array([f["pixel"] for f in found])
    quality = []
    for f in found:
        note = ""
        if f["clipped"]:
            note = f"clipped ({f['clipped_px']} px)"
        if f["direction"][2] < 0:
            note = (note + "; " if note else "") + "light behind the ball's plane"
        quality.append({"peak": f["peak"], "blob_px": f["blob_px"], "clipped_px": f["clipped_px"],
                        "spread_deg": f["spread_deg"], "note": note})
    clipped = [n for n, f in zip(names, found) if f["clipped"]]
    if clipped:
        intensities = None
        notes.append(f"intensities unknown: {len(clipped)} of {len(names)} highlights are clipped "
                     f"(first: {clipped[0]}); the fit estimates them")
    else:
        energy = np.array([f["energy"] for f in found])
        scale = float(energy.mean())
        if scale > 0 and np.all(energy.sum(axis=1) > 0):
            intensities = energy / scale
        else:
            intensities = None
            notes.append("intensities unknown: a highlight carries no energy above the ball's background")
    return Calibration(directions=directions, intensities=intensities, circle=tuple(float(v) for v in circle),
                       highlights=highlights, names=names, quality=quality, size=size, camera=camera,
                       focal_px=None if focal_px is None else float(focal_px), circle_source=source, notes=notes,
                       cone=None if cone is None else (np.asarray(cone[0], dtype=np.float64), float(cone[1])))


# ------------------------------------------------------------------------------------------- outputs


def diagnostic_image(cal: Calibration, images: Sequence[np.ndarray], max_scale: int = 4) -> np.ndarray:
    """(H', W', 3) float32 display values in [0, 1]: the photos' max (log-scaled grey) with the ball's circle
    (green) and each photo's highlight (red cross, numbered from 0), enlarged up to ``max_scale`` times so that
    the longer side is about 1024 px."""
    import cv2

    h, w = cal.size
    top = np.max([_luminance(im) for im in images], axis=0)
    positive = top[top > 0]
    lo = float(np.percentile(positive, 2)) if positive.size else 1e-6
    hi = float(np.percentile(top, 99.9))
    hi = max(hi, lo * 10, 1e-9)
    grey = np.clip(np.log(np.maximum(top, lo) / lo) / math.log(hi / lo), 0, 1) * 0.8
    scale = int(max(1, min(max_scale, round(1024 / max(h, w)))))
    canvas = np.repeat(cv2.resize(grey.astype(np.float32), (w * scale, h * scale),
                                  interpolation=cv2.INTER_NEAREST)[..., None], 3, axis=2)
    canvas = np.ascontiguousarray((canvas * 255).astype(np.uint8))

    def pt(x, y):  # pixel-centre coordinates -> canvas coordinates (fixed point, 4 fractional bits)
        return int(round(((x + 0.5) * scale - 0.5) * 16)), int(round(((y + 0.5) * scale - 0.5) * 16))

    cx, cy, r = cal.circle
    cv2.circle(canvas, pt(cx, cy), int(round(r * scale * 16)), (0, 255, 0), 1, cv2.LINE_AA, 4)
    arm = max(3, 2 * scale)
    font = max(0.35, 0.12 * scale)
    for k, (x, y) in enumerate(cal.highlights):
        px, py = pt(x, y)
        cv2.line(canvas, (px - arm * 16, py), (px + arm * 16, py), (255, 40, 40), 1, cv2.LINE_AA, 4)
        cv2.line(canvas, (px, py - arm * 16), (px, py + arm * 16), (255, 40, 40), 1, cv2.LINE_AA, 4)
        org = (px // 16 + arm + 1, py // 16 - arm - 1)
        cv2.putText(canvas, str(k), org, cv2.FONT_HERSHEY_SIMPLEX, font, (0, 0, 0), 3, cv2.LINE_AA)  # outline
        cv2.putText(canvas, str(k), org, cv2.FONT_HERSHEY_SIMPLEX, font, (255, 220, 60), 1, cv2.LINE_AA)
    return canvas.astype(np.float32) / 255.0


def write_calibration(cal: Calibration, path: str | os.PathLike, images: Sequence[np.ndarray] | None = None) -> dict:
    """Write ``cal`` as ``lights.json`` at ``path`` (``matcap.refine.lightfile.write_lights``) and, with ``images``,
    the diagnostic picture ``calibration.png`` beside it; the two appear together or not at all
    (``scenes.atomic.atomic_files``). Returns the lights.json document."""
    from matcap.imageio import write_png
    from matcap.refine.lightfile import write_lights
    from scenes.atomic import atomic_files

    path = Path(path)
    with atomic_files(path.parent, tag="calibration", last=path.name) as stage:
        doc = write_lights(stage / path.name, cal.entries(), **cal.document_fields())
        if images is not None:
            write_png(stage / DIAGNOSTIC, diagnostic_image(cal, images), bits=8)
    return doc


def read_ball_mask(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool ball disc from an image file: more than half of full scale in any channel (a soft, anti-aliased
    edge counts at its half-way point). One-line :class:`MatcapError` for a size other than ``shape`` (H, W)."""
    from matcap.imageio import read_image

    px = read_image(path).pixels
    full = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(px.dtype, 1.0)
    mask = px.max(axis=2).astype(np.float64) / full > 0.5
    if mask.shape != tuple(shape):
        raise MatcapError(f"{path}: the ball mask is {mask.shape[1]}x{mask.shape[0]} but the photos are "
                          f"{shape[1]}x{shape[0]} (W x H)")
    if not mask.any():
        raise MatcapError(f"{path}: the ball mask is empty")
    return mask


def calibrate_folder(photos: str | os.PathLike, out: str | os.PathLike, ball_mask: str | os.PathLike | None = None,
                     focal_px: float | None = None, linear: bool = False, overwrite: bool = False) -> Calibration:
    """``matcap calibrate``: read the photos of a folder (:func:`matcap.photos.load_capture`; 8-bit decoded from
    sRGB unless ``linear``; a ``mask.*`` in the folder is not used: it would be the object's), calibrate, and write
    ``out`` (lights.json) and ``calibration.png`` beside it. ``ball_mask``: an image file, > 0 on the ball's disc.
    Refuses (one line) an existing ``out`` or ``calibration.png`` unless ``overwrite``, and an ``out`` inside the
    photos folder (the picture would be read as a photo next time)."""
    from matcap.photos import load_capture

    photos, out = Path(photos), Path(out)
    if out.suffix.lower() != ".json":
        raise MatcapError(f"--out {out}: expected a .json file name (the light file, e.g. rig.json)")
    if out.exists() and out.is_dir():
        raise MatcapError(f"--out {out}: is a folder; give a file name such as {out / 'rig.json'}")
    if photos.is_dir() and out.resolve().parent == photos.resolve():
        raise MatcapError(f"--out {out}: inside the photos folder, where {DIAGNOSTIC} would be taken for a photo; "
                          "write it elsewhere")
    parent = out.absolute().parent
    while not parent.exists() and parent != parent.parent:  # the first folder that exists must take a new one
        parent = parent.parent
    if not (parent.is_dir() and os.access(parent, os.W_OK | os.X_OK)):
        raise MatcapError(f"--out {out}: cannot write in {parent}")
    if not overwrite:
        for p in (out, out.parent / DIAGNOSTIC):
            if p.exists():
                raise MatcapError(f"{p} exists; use --overwrite to replace it")
    cap = load_capture(photos, linear=linear)
    mask = read_ball_mask(ball_mask, cap.images[0].shape[:2]) if ball_mask is not None else None
    cal = calibrate(cap.images, ball_mask=mask, focal_px=focal_px, names=cap.files)
    write_calibration(cal, out, cap.images)
    return cal

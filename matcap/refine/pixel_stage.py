"""The fit's per-pixel stage: with the lights fixed, every pixel's normal, base colour, roughness and metallic.

Each pixel is an independent problem (:func:`_pixel_residuals`): Levenberg-Marquardt on all pixels at once, in
chunks (:func:`_solve_pixels`, :mod:`matcap.refine.solve`), on a half-size copy first whose corrections start the
full-size solve (:func:`_solve_maps`); pixels on the object's outline may mix it with what lies behind
(:func:`_outline`, :class:`_Mixing`); pixels far from their neighbours restart from the neighbours' median
(:func:`_neighbour_restarts`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from matcap.refine.photos import _Problem, _Stopped, _downsample, _free, _loss, _one_thread, _resize, _shade, _workers
from matcap.refine.settings import RefineSettings


def _stage_subsample(torch, obs, mask, weight, sat_level, arrays: dict[str, np.ndarray], full: _Problem, px,
                     s: RefineSettings, rng, shadow: float) -> tuple[_Problem, dict[str, np.ndarray]]:
    """The per-pixel stage's maps (``px`` of the problem ``full``, written over ``arrays``) and a problem of
    ``lights.known_pixels`` pixels of the photos ``obs`` (K, H, W, 3) off the outline of ``mask``, drawn by ``rng``,
    started from and anchored to those maps. Returns (that problem, the maps as (H, W, ...) arrays)."""
    fitted = {k: v.copy() for k, v in arrays.items()}
    with torch.no_grad():
        for key, value in (("normal", px.normal()), ("base", px.base()), ("rough", px.rough()),
                           ("metal", px.metal())):
            fitted[key][full.rows, full.cols] = value.cpu().numpy()
    idx = _known_subsample(mask, s, rng)
    prob = _Problem(torch, obs, mask, fitted, weight, sat_level, torch.device(s.device), idx, fitted["normal"],
                    shadow=shadow)
    return prob, fitted


def _known_subsample(mask: np.ndarray, s: RefineSettings, rng) -> np.ndarray:
    """(S,) sorted indices, among ``mask``'s pixels, of the known lights' light-fit pixels: ``lights.known_pixels``
    drawn by ``rng`` off the outline (whose pixels mix the object with what lies behind it; all pixels where the
    mask is all outline)."""
    inner = np.flatnonzero(~outline_zone(mask, s.pixels.outline)[mask])
    inner = inner if len(inner) else np.arange(int(mask.sum()))
    return np.sort(rng.choice(inner, size=min(len(inner), s.lights.known_pixels), replace=False))


def _stage_sample(n: int, s: RefineSettings, size: int | None = None) -> np.ndarray:
    """(S,) sorted indices of a random sample of ``size`` (default ``roughness.sample``) of ``n`` pixels (all where
    fewer; ``seed``)."""
    size = s.roughness.sample if size is None else size
    return np.sort(np.random.default_rng(s.seed).choice(n, size=min(n, size), replace=False))


def window_median(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, hw: tuple[int, int], size: int = 3,
                  centre: bool = True) -> np.ndarray:
    """(N, C) float32: the channel-wise median of ``values`` (N, C) over each pixel's ``size`` x ``size`` window
    (odd) among the N pixels at ``rows``, ``cols`` (N,) of an ``hw`` frame (``centre`` False: the pixel itself left
    out); an even count takes the mean of the middle two; NaN where a window holds none of them."""
    h, w = hw
    half = size // 2
    values = np.asarray(values, np.float32).reshape(len(rows), -1)
    img = np.full((h + 2 * half, w + 2 * half, values.shape[1]), np.nan, np.float32)
    img[rows + half, cols + half] = values
    out = np.empty_like(values)
    step = max(1, (1 << 22) // (size * size * values.shape[1]))  # pixels per chunk: about 16 MB of windows
    for a in range(0, len(rows), step):
        r, c = rows[a:a + step], cols[a:a + step]
        around = np.sort(np.stack([img[r + dy, c + dx] for dy in range(size) for dx in range(size)
                                   if centre or (dy, dx) != (half, half)]), axis=0)  # NaN (none there) sorts last
        count = np.isfinite(around[:, :, 0]).sum(0)  # (n,) values in the window; the median: the middle one or two
        lo, hi = (np.maximum(count - 1, 0) // 2)[None, :, None], (count // 2)[None, :, None]
        med = 0.5 * (np.take_along_axis(around, lo, 0)[0] + np.take_along_axis(around, hi, 0)[0])
        med[count == 0] = np.nan
        out[a:a + step] = med
    return out


def neighbour_median(normal: np.ndarray, rows: np.ndarray, cols: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """(N, 3) unit: the component-wise median of the normals of each pixel's eight neighbours among the N pixels
    (``normal`` (N, 3) unit at ``rows``, ``cols`` (N,) of an ``hw`` frame), renormalised and kept facing the camera
    (z at least 0.08); NaN where a pixel has no neighbour."""
    med = window_median(normal, rows, cols, hw, 3, centre=False)
    med[:, 2] = np.maximum(med[:, 2], 0.08)
    return med / np.maximum(np.linalg.norm(med, axis=1, keepdims=True), 1e-9)


def _neighbour_restarts(torch, full: _Problem, px, lights, s: RefineSettings, bar, mixing: "_Mixing | None",
                        mask: np.ndarray):
    """Known lights: the per-pixel solve again, from the median normal of the neighbours
    (:func:`neighbour_median`), for the pixels whose normal lies more than ``pixels.restart_deg`` from it (the
    outline's pixels, fitted as mixtures, excepted); each keeps the solution with the lower loss (data and priors,
    :func:`_loss`). A pixel's solve finds the minimum nearest its start, and a lone normal far from its neighbours'
    is often one the photos explain worse than theirs. Returns (:class:`PixelParams`, ``tried`` and ``kept`` pixel
    counts)."""
    from matcap.refine.model import PixelParams

    with torch.no_grad():
        normal = px.normal().cpu().numpy()
    med = neighbour_median(normal, full.rows, full.cols, mask.shape)
    ok = np.isfinite(med).all(axis=1)
    cos = np.clip((np.where(ok[:, None], med, 0.0) * normal).sum(axis=1), -1.0, 1.0)
    tried = ok & (cos < np.cos(np.radians(s.pixels.restart_deg)))
    if mixing is not None:
        tried[mixing.index] = False
    pixels = np.flatnonzero(tried)
    if not len(pixels):
        return px, {"tried": 0, "kept": 0}
    idx = torch.from_numpy(pixels).to(px.grad.device)
    sub = full.part(pixels)
    m = torch.from_numpy(med[pixels].astype(np.float32)).to(px.grad.device)
    start = PixelParams(m[:, :2] / m[:, 2:], px.base_logit[idx], px.rough_logit[idx], px.metal_logit[idx])
    solved = _solve_pixels(torch, sub, start, lights, s, s.loss.cauchy, s.pixels.restart_iters, bar, "restarts")
    with torch.no_grad():
        before = _loss(torch, sub, PixelParams(*[t[idx] for t in px.tensors()]), lights, s, s.loss.cauchy)[0]
        after = _loss(torch, sub, solved, lights, s, s.loss.cauchy)[0]
    kept = after < before
    out = [t.detach().clone() for t in px.tensors()]
    for o, t in zip(out, solved.tensors()):
        o[idx[kept]] = t[kept].detach()
    return PixelParams(*out), {"tried": int(len(pixels)), "kept": int(kept.sum())}


def _solve_maps(torch, obs, mask, arrays, weight, sat_level, start, lights, s: RefineSettings, bar,
                coarse_iters: int, fine_iters: int, shadow: float = 0.0):
    """The per-pixel stage: every pixel's normal, base colour, roughness and metallic under the fixed ``lights``,
    Levenberg-Marquardt on a half-size copy first (skipped at 128 px or less), whose corrections are upsampled as
    the start of the full-size solve.

    obs (K, H, W, 3) photos in fit units; mask (H, W); arrays: the priors ("normal", "base", "rough", "metal");
    weight (H, W) per-pixel data weight; sat_level (K, 3) clipping levels; start (H, W, 3) start normals or None
    (the prior's); shadow: see :class:`_Problem`. The pixels of the mask's outline are fitted as mixtures
    (:func:`_outline`). Returns (the full-size :class:`_Problem`, its :class:`PixelParams`, its outline's
    :class:`_Mixing` or None, iterations done).
    """
    from matcap.refine.model import PixelParams

    device = torch.device(s.device)
    h, w = mask.shape
    c = s.loss.cauchy
    ambient = lights.sh.detach() if shadow > 0 else None  # a cast shadow leaves the ambient's light
    full = _Problem(torch, obs, mask, arrays, weight, sat_level, device, start=start, shadow=shadow,
                    ambient_sh=ambient)
    px_full = PixelParams.from_maps(full.ns, full.b0, full.r0, full.m0)
    iters_done = {"coarse": 0, "fine": 0}
    if coarse_iters > 0 and max(h, w) > 128:
        hw_c = (max(8, h // 2), max(8, w // 2))
        obs_c, mask_c, arr_c = _downsample(obs, mask, arrays if start is None else dict(arrays, start=start), hw_c)
        coarse = _Problem(torch, obs_c, mask_c, arr_c, _resize(weight, hw_c), sat_level, device,
                          start=arr_c.get("start"), shadow=shadow, ambient_sh=ambient)
        px_c0 = PixelParams.from_maps(coarse.ns, coarse.b0, coarse.r0, coarse.m0)
        mix_c = _outline(torch, obs_c, mask_c, coarse, s)
        px_c = _solve_pixels(torch, coarse, px_c0, lights, s, c, coarse_iters, bar, "maps 1/2", mix_c)
        # upsample the corrections (parameter deltas), add them to the full-size start
        delta = np.zeros(hw_c + (7,), np.float32)
        d = torch.cat([(a - b0).reshape(len(coarse), -1) for a, b0 in zip(px_c.tensors(), px_c0.tensors())], 1)
        delta[coarse.rows, coarse.cols] = d.cpu().numpy()
        up = _resize(delta, (h, w), "linear")[full.rows, full.cols]
        up_t = torch.from_numpy(up).to(device)
        px_full = PixelParams(px_full.grad + up_t[:, 0:2], px_full.base_logit + up_t[:, 2:5],
                              px_full.rough_logit + up_t[:, 5], px_full.metal_logit + up_t[:, 6])
        iters_done["coarse"] = coarse_iters
    mixing = _outline(torch, obs, mask, full, s) if coarse_iters > 0 or fine_iters > 0 else None
    if fine_iters > 0:
        px_full = _solve_pixels(torch, full, px_full, lights, s, c, fine_iters, bar, "maps", mixing)
    iters_done["fine"] = fine_iters
    return full, px_full, mixing, iters_done


@dataclass
class _Mixing:
    """The pixels of the mask's outline (:attr:`matcap.refine.settings.PixelStageSettings.outline`), each fitted
    as coverage x the model + (1 - coverage) x what lies behind it: index (M,) int64 into the problem's pixels;
    backdrop (K, M, 3) torch, fit units; cover_logit (M,) torch, their coverage as a logit (updated by the
    solve)."""

    index: np.ndarray
    backdrop: Any
    cover_logit: Any

    def mixer(self, torch, count: int):
        """A function (pred (K, n, 3) of the problem's pixels ``sl``, sl) -> pred with the outline's pixels mixed
        in; ``count``: the problem's pixels. Takes the coverage as it is now (after the solve)."""
        where = np.full(count, -1, np.int64)
        where[self.index] = np.arange(len(self.index))
        cover = torch.sigmoid(self.cover_logit).cpu().numpy()
        backdrop = self.backdrop.cpu().numpy()

        def mix(pred: np.ndarray, sl: slice) -> np.ndarray:
            loc = where[sl]
            sel = np.nonzero(loc >= 0)[0]
            if len(sel) == 0:
                return pred
            a = cover[loc[sel]][None, :, None]
            pred = pred.copy()
            pred[:, sel] = a * pred[:, sel] + (1.0 - a) * backdrop[:, loc[sel]]
            return pred

        return mix


def _outline_record(torch, mixing: "_Mixing | None") -> dict[str, Any]:
    """fit.json ``outline``: how many pixels were fitted as mixtures and their coverage (mean, 10th percentile)."""
    if mixing is None:
        return {"pixels": 0}
    cover = torch.sigmoid(mixing.cover_logit).cpu().numpy()
    return {"pixels": len(cover), "coverage_mean": round(float(cover.mean()), 4),
            "coverage_p10": round(float(np.percentile(cover, 10)), 4)}


def outline_zone(mask: np.ndarray, width: int) -> np.ndarray:
    """(H, W) bool: the pixels of ``mask`` (H, W) within ``width`` pixels (chessboard distance) of a pixel off it,
    where a pixel can mix the object with what lies behind it (the photo's border does not count)."""
    from scipy import ndimage

    mask = np.asarray(mask, bool)
    if width <= 0 or mask.all():
        return np.zeros_like(mask)
    return mask & ndimage.binary_dilation(~mask, np.ones((3, 3), bool), iterations=width)


def _outline(torch, obs, mask, prob: "_Problem", s: RefineSettings) -> "_Mixing | None":
    """The pixels of ``prob`` on the mask's outline and what lies behind each of them (None where there are none).

    obs (K, H, W, 3) photos in fit units; mask (H, W). Outline: the mask's pixels within ``pixels.outline`` pixels
    (chessboard distance) of a pixel off it (the photo's border does not count); behind one: per photo, the mean
    of the off-mask pixels within ``pixels.outline + 1`` pixels of it. Coverage starts at 0.9."""
    from scipy import ndimage

    width = s.pixels.outline
    near = outline_zone(mask, width)
    index = np.nonzero(near[prob.rows, prob.cols])[0]
    if len(index) == 0:
        return None
    rows, cols = prob.rows[index], prob.cols[index]
    size = 2 * width + 3
    pad = size // 2 + 1  # the filters run on the outline's bounding box (and its reach) only
    r0, r1 = max(rows.min() - pad, 0), min(rows.max() + pad + 1, mask.shape[0])
    c0, c1 = max(cols.min() - pad, 0), min(cols.max() + pad + 1, mask.shape[1])
    box_off = (~mask[r0:r1, c0:c1]).astype(np.float32)
    rr, cc = rows - r0, cols - c0
    count = ndimage.uniform_filter(box_off, size, mode="constant")[rr, cc]
    backdrop = np.empty((obs.shape[0], len(index), 3), np.float32)
    for k in range(obs.shape[0]):
        for ch in range(3):
            summed = ndimage.uniform_filter(obs[k, r0:r1, c0:c1, ch] * box_off, size, mode="constant")
            backdrop[k, :, ch] = summed[rr, cc] / np.maximum(count, 1e-6)
    device = prob.obs.device
    return _Mixing(index, torch.from_numpy(backdrop).to(device),
                   torch.full((len(index),), math.log(9.0), dtype=torch.float32, device=device))


def _plane_detail(torch, full: _Problem, px, mask: np.ndarray, share: float):
    """``px`` with the normals' tilts larger than ``share`` of the sample's width taken out: the mean normal around
    each pixel (the unit normals' mask-weighted Gaussian average of sigma ``share`` times the longer side of the
    mask's bounding box; unit vectors, so a few steep outliers move it little) is turned to the camera axis, by
    subtracting its gradient from the pixel's (``n = normalise(gx, gy, 1)``). The average runs on a copy where
    sigma is 8 pixels, then is upsampled."""
    import cv2

    from matcap.refine.model import PixelParams

    h, w = mask.shape
    width = max(np.ptp(full.rows), np.ptp(full.cols)) + 1
    sigma = share * width
    f = min(1.0, 8.0 / max(sigma, 1e-6))
    hw = (max(4, round(h * f)), max(4, round(w * f)))
    m = mask.astype(np.float32)
    normal = np.zeros((h, w, 3), np.float32)
    normal[full.rows, full.cols] = px.normal().detach().cpu().numpy()
    small = [cv2.resize(a, hw[::-1], interpolation=cv2.INTER_AREA) for a in (normal * m[..., None], m)]
    low = [cv2.GaussianBlur(a, (0, 0), sigma * f, borderType=cv2.BORDER_REFLECT) for a in small]
    low = cv2.resize(low[0] / np.maximum(low[1], 1e-6)[..., None], (w, h), interpolation=cv2.INTER_LINEAR)
    low = low[full.rows, full.cols]
    low_grad = low[:, :2] / np.maximum(low[:, 2:3], 0.1)
    grad = px.grad - torch.from_numpy(low_grad).to(px.grad)
    return PixelParams(grad, px.base_logit, px.rough_logit, px.metal_logit)


def _solve_pixels(torch, prob: _Problem, px0, lights, s, c, iters, bar, label, mixing: "_Mixing | None" = None):
    """Every pixel's maps with the lights fixed (independent problems), chunk by chunk: Levenberg-Marquardt
    (:func:`_lm_pixels`) on the loss of :func:`_loss`; the outline's pixels (``mixing``, whose coverage is
    updated in place) as mixtures of the model and what lies behind them, in chunks of their own. The chunks run
    side by side on as many threads as torch was given (:func:`_workers`), each of them with one-thread
    operations, so a chunk's result does not depend on the thread count; progress is reported from the calling
    thread."""
    import queue
    import threading
    from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait

    from matcap.refine.model import PixelParams

    lights = lights.detached()
    out = [t.detach().clone() for t in px0.tensors()]
    n = len(prob)
    step = max(256, s.pixels.lm_observations // prob.obs.shape[0])
    if mixing is None:
        chunks = [(slice(i, min(i + step, n)), None) for i in range(0, n, step)]
    else:
        inner = np.setdiff1d(np.arange(n), mixing.index)
        chunks = [(inner[i:i + step], None) for i in range(0, len(inner), step)]
        chunks += [(mixing.index[i:i + step], slice(i, i + step)) for i in range(0, len(mixing.index), step)]
    bar.add_total(iters * len(chunks))
    losses = queue.SimpleQueue()
    stop = threading.Event()

    def on_step(loss):
        if stop.is_set():
            raise _Stopped
        losses.put(loss)

    def solve(sl, mix_sl):
        part = prob.part(sl)
        tsl = sl if isinstance(sl, slice) else torch.from_numpy(sl).to(prob.obs.device)
        start = [t[tsl] for t in out]
        if mix_sl is not None:
            part.backdrop = mixing.backdrop[:, mix_sl]
            start.append(mixing.cover_logit[mix_sl])
        solved = _lm_pixels(torch, part, start, lights, s, c, iters, on_step)
        for o, t in zip(out, solved):
            o[tsl] = t.detach()
        if mix_sl is not None:
            mixing.cover_logit[mix_sl] = solved[4].detach()

    def report():
        while not losses.empty():
            bar.step(label, losses.get())

    with _one_thread(torch) as threads:
        pool = ThreadPoolExecutor(_workers(threads), initializer=torch.set_num_threads, initargs=(1,))
        try:
            futures = [pool.submit(solve, sl, mix_sl) for sl, mix_sl in chunks]
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=0.05, return_when=FIRST_EXCEPTION)
                report()
                for f in done:
                    f.result()
        except BaseException:
            stop.set()
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    report()
    return PixelParams(*out)


def _lm_pixels(torch, part: _Problem, start, lights, s, c, iters, on_step):
    """:func:`matcap.refine.solve.levenberg_marquardt` on :func:`_loss` of the pixels ``part`` with the lights
    fixed (:func:`_pixel_residuals`). ``start``: the four :class:`PixelParams` tensors, and where the pixels mix
    the object with what lies behind them (``part.backdrop``) their coverage logits; returns them."""
    from matcap.refine.solve import levenberg_marquardt

    theta, residuals, _, system, unpack = _pixel_residuals(torch, part, start, s)
    theta = levenberg_marquardt(lambda t, rows: residuals(t, rows, lights), theta, part.weight / 3.0, c, iters,
                                on_step=on_step, tol=s.pixels.tol,
                                system=lambda t, rows, w, scale: system(t, rows, lights, w, scale))
    return unpack(theta)


def _sum_photos(x):
    """(K, n, 3) -> (n, 3): the photos summed one after another (torch's sum over the first dimension groups its
    terms by the tensor's size, and the fit must not depend on its chunks)."""
    acc = x[0].clone()
    for k in range(1, len(x)):
        acc += x[k]
    return acc


def _pixel_residuals(torch, part: _Problem, start, s):
    """:func:`_loss` of the pixels ``part`` as residuals for Levenberg-Marquardt: the same data term (Cauchy,
    clipped highlights a lower bound only, weighted per pixel and averaged over the colour channels) and the same
    priors. ``start``: the four :class:`PixelParams` tensors, and where the pixels mix the object with what lies
    behind them (``part.backdrop``) their coverage logits. Such a pixel's model is coverage x the Principled model
    + (1 - coverage) x the backdrop, with a prior (``priors.cover``) on 1 - coverage.

    Returns (theta (N, P): the parameters as one array; residuals(theta, rows, lights) -> (robust (n, K * 3),
    entry k * 3 + c photo k's channel c; quadratic); jacobian(theta, rows, lights, state=False) -> those with
    their derivatives by each parameter ((n, K * 3) and (n, Q) each: the light fit's joint solve), and with
    ``state`` a fifth value, the model's pieces {"normal", "base", "metal" (n,), "pred" (K, n, 3), "free" (K, n, 3) 0 / 1,
    "d_level" (n, Q): the priors' derivatives by ``level``}; system(theta, rows, lights, weight (n,), scale) ->
    the Gauss-Newton system of those residuals (``levenberg_marquardt``'s ``system``); unpack(theta) -> the tensors
    of ``start``). ``level`` (a scalar tensor, or None for 0): the log of a factor on the networks' base colour in
    its prior.)"""
    from matcap.refine.model import PixelParams, shade_jacobian

    grad, base_logit, rough_logit, metal_logit = start[:4]
    n = len(part)
    brdf = s.model.fit_brdf  # without it roughness and metallic stay the network's: 5 parameters
    mixed = part.backdrop is not None  # one more: the coverage
    theta = torch.cat([grad, base_logit] + ([rough_logit[:, None], metal_logit[:, None]] if brdf else [])
                      + ([start[4][:, None]] if mixed else []), 1)
    ci = theta.shape[1] - 1  # the coverage's column, where mixed
    roots = [math.sqrt(s.priors.normal), math.sqrt(s.priors.base / 3.0), math.sqrt(s.priors.rough),
             math.sqrt(s.priors.metal), math.sqrt(s.priors.cover)]

    taken = [None, part]  # the rows last taken and their problem: the Jacobian and the trial step share them

    def pixels(t, rows):
        if len(rows) != n and rows is not taken[0]:
            taken[:] = [rows, part.take(rows)]
        sub = part if len(rows) == n else taken[1]
        rl, ml = (t[:, 5], t[:, 6]) if brdf else (rough_logit[rows], metal_logit[rows])
        px = PixelParams(t[:, 0:2], t[:, 2:5], rl, ml)
        return sub, px, px.normal(), px.base(), px.rough() if brdf else sub.r0, px.metal() if brdf else sub.m0

    def prior_base(sub, level):  # the base colour the prior holds: the networks', times exp(level) where given
        return sub.b0 if level is None else sub.b0 * level.exp()

    def priors(sub, nrm, b, r, m, t, level=None):
        b0 = prior_base(sub, level)
        prior = [roots[0] * (nrm - sub.n0), roots[1] * (torch.log(b + 0.02) - torch.log(b0 + 0.02))]
        if brdf:
            prior += [roots[2] * (r - sub.r0)[:, None], roots[3] * (m - sub.m0)[:, None]]
        if mixed:
            prior += [roots[4] * (1.0 - torch.sigmoid(t[:, ci]))[:, None]]
        return torch.cat(prior, 1)

    def mix(t, sub, pred):
        if not mixed:
            return pred
        a = torch.sigmoid(t[:, ci])[None, :, None]
        return a * pred + (1.0 - a) * sub.backdrop

    def residuals(t, rows, lights, level=None):
        sub, _, nrm, b, r, m = pixels(t, rows)
        res = mix(t, sub, _shade(lights, sub.pos, nrm, b, r, m)) - sub.obs
        res = res * _free(sub, res)
        return res.permute(1, 0, 2).reshape(len(t), -1), priors(sub, nrm, b, r, m, t, level)

    def derivatives(t, rows, lights):  # the model and its derivatives, (K, n, 3) each (d_normal: (2, K, n, 3))
        sub, px, nrm, b, r, m = pixels(t, rows)
        # the unit normal's derivatives by its gradient parameters: (e_x - n n_x) / |v|, (e_y - n n_y) / |v|
        size = torch.cat([px.grad, torch.ones_like(px.grad[:, :1])], 1).norm(dim=-1, keepdim=True)
        axes = torch.eye(3, dtype=t.dtype, device=t.device)[:2, None, :]
        tangents = (axes - nrm[None] * nrm.T[:2, :, None]) / size[None]
        wo, irr = lights.incident(sub.pos)
        pred, d_n, d_b, d_r, d_m = shade_jacobian(nrm, b, r, m, wo, irr, lights.sh, tangents)
        d_a = None
        if mixed:  # coverage a: the model's derivatives scale by a; d/d logit(a) = (pred - backdrop) a (1 - a)
            a = torch.sigmoid(t[:, ci])
            d_a = (pred - sub.backdrop) * (a * (1.0 - a))[None, :, None]
            a3 = a[None, :, None]
            pred, d_n, d_b, d_r, d_m = mix(t, sub, pred), d_n * a3[None], d_b * a3, d_r * a3, d_m * a3
        sb = b * (1.0 - b)  # sigmoid's derivative
        d_b = d_b * sb[None]
        if brdf:  # by the logits
            d_r = d_r * (r * (1.0 - r))[None, :, None]
            d_m = d_m * (m * (1.0 - m))[None, :, None]
        res = pred - sub.obs
        # a clipped observation the model exceeds: zero residual, no derivative (a product, not torch.where: the
        # model's values and derivatives are finite, and a product of floats is several times faster)
        free = _free(sub, res).to(t.dtype)
        return sub, nrm, b, r, m, tangents, pred, res, free, d_n, d_b, d_r, d_m, d_a, sb

    def own_priors(t, b, r, m, sb, q_width):
        """The prior residuals that move with one parameter each (all but the normal's three, which move with
        both gradient parameters along the tangents): [(parameter, prior column, derivative (n,))], in the
        parameters' order."""
        own = [(2 + c, 3 + c, roots[1] * sb[:, c] / (b[:, c] + 0.02)) for c in range(3)]
        if brdf:
            own += [(5, 6, roots[2] * r * (1.0 - r)), (6, 7, roots[3] * m * (1.0 - m))]
        if mixed:
            a = torch.sigmoid(t[:, ci])
            own.append((ci, q_width - 1, -roots[4] * a * (1.0 - a)))
        return own

    def prior_jacobian(t, b, r, m, tangents, sb, q_width):  # the priors' derivatives by each parameter, (n, Q)
        count = len(t)
        jq = [torch.cat([roots[0] * tangents[i], t.new_zeros(count, q_width - 3)], 1) for i in range(2)]
        for _, col, d in own_priors(t, b, r, m, sb, q_width):
            jq.append(t.new_zeros(count, q_width))
            jq[-1][:, col] = d
        return jq

    def jacobian(t, rows, lights, state=False, level=None):
        sub, nrm, b, r, m, tangents, pred, res, free, d_n, d_b, d_r, d_m, d_a, sb = derivatives(t, rows, lights)
        count = len(t)
        flat = lambda x: (x * free).permute(1, 0, 2).reshape(count, -1)  # noqa: E731
        robust = flat(res)
        q = priors(sub, nrm, b, r, m, t, level)
        jr = [flat(d_n[0]), flat(d_n[1])] + [flat(d_b * (channel == c).to(t.dtype)) for c in range(3)]
        if brdf:
            jr += [flat(d_r), flat(d_m)]
        if mixed:
            jr.append(flat(d_a))
        jq = prior_jacobian(t, b, r, m, tangents, sb, q.shape[1])
        if state:
            b0 = prior_base(sub, level)
            d_level = t.new_zeros(count, q.shape[1])  # the base prior's derivative by the log of its level
            d_level[:, 3:6] = -roots[1] * b0 / (b0 + 0.02)
            return robust, q, jr, jq, {"normal": nrm, "base": b, "metal": m, "pred": pred, "free": free,
                                       "d_level": d_level}
        return robust, q, jr, jq

    def system(t, rows, lights, weight, scale):
        """The Gauss-Newton system of :func:`jacobian`'s residuals (gradient (n, P), matrix (n, P, P)) with the
        Cauchy loss's IRLS weights, in the model's (K, n, 3) layout: a base colour channel's derivative is zero
        in the other two channels, so its products are taken once for all three, and a clipped observation's
        zero enters through its weight."""
        sub, nrm, b, r, m, tangents, pred, res, free, d_n, d_b, d_r, d_m, d_a, sb = derivatives(t, rows, lights)
        count, p = t.shape
        rf = res * free
        wf = free * (2.0 * weight)[None, :, None] / (scale * scale + rf * rf)  # IRLS weight; 0 where not free
        other = [d_n[0], d_n[1]] + ([d_r, d_m] if brdf else []) + ([d_a] if mixed else [])
        index = [0, 1] + ([5, 6] if brdf else []) + ([ci] if mixed else [])
        total = lambda x: _sum_photos(x).sum(1)  # noqa: E731  (K, n, 3) -> (n,)
        # the priors: prior_jacobian's columns without their zeros
        q = priors(sub, nrm, b, r, m, t)
        grad = t.new_zeros(count, p)
        hess = t.new_zeros(count, p, p)
        r0 = roots[0]
        for i in range(2):
            grad[:, i] = 2.0 * r0 * (q[:, 0:3] * tangents[i]).sum(1)
            for j in range(i, 2):
                hess[:, i, j] = hess[:, j, i] = 2.0 * r0 * r0 * (tangents[i] * tangents[j]).sum(1)
        for i, col, d in own_priors(t, b, r, m, sb, q.shape[1]):
            grad[:, i] = 2.0 * q[:, col] * d
            hess[:, i, i] = 2.0 * d * d
        wr = wf * rf
        grad[:, 2:5] += _sum_photos(wr * d_b)
        wb = wf * d_b
        hess[:, 2:5, 2:5] += torch.diag_embed(_sum_photos(wb * d_b))
        for a_i, (i, col) in enumerate(zip(index, other)):
            grad[:, i] += total(wr * col)
            wc = wf * col
            cross = _sum_photos(wc * d_b)  # (n, 3): with each base colour channel
            hess[:, i, 2:5] += cross
            hess[:, 2:5, i] += cross
            for j, col_j in zip(index[a_i:], other[a_i:]):
                v = total(wc * col_j)
                hess[:, i, j] += v
                if j != i:
                    hess[:, j, i] += v
        return grad, hess

    def unpack(theta):
        out = [theta[:, 0:2], theta[:, 2:5]]
        out += [theta[:, 5], theta[:, 6]] if brdf else [rough_logit, metal_logit]
        out += [theta[:, ci]] if mixed else []
        return [t.contiguous() for t in out]

    channel = torch.arange(3, device=theta.device)
    return theta, residuals, jacobian, system, unpack

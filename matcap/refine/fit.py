"""Photo-consistent refinement: fit per-image lights and per-pixel SVBRDF to the photos of one capture.

Starting from the networks' maps (the *initialisation* and a *prior*), minimise

    sum_p w_p sum_k mean_c rho((I_kc(p) - photo_kc(p)) / c)  +  prior(p)

where ``I`` is :func:`matcap.refine.model.shade` (Principled BSDF * light + order-2 SH ambient), ``rho`` the
Cauchy loss (shadows, interreflections and highlights the model cannot explain are outliers), ``w_p`` the
light-variation weight (:func:`light_variation`), and the prior pulls normals, base colour, roughness and metallic
toward the network's values (this is what stops the drift into the generalized bas-relief family).

The fit's stages (the photos' decoding and the networks run before, in :mod:`matcap.capture`):
  1. photos: :func:`_prepare` (checks, fit units, clipping levels, light variation);
  2. lights, on a downsampled copy of the photos: known (:func:`_refine_known`: a light file or a mirror ball; the
     directions held) or estimated (:func:`_refine_estimated`: the Lambertian factorization of
     :mod:`matcap.refine.linear` and its check, then the candidate light models of :func:`candidate_models` in
     order, judged by one rule, :func:`_judge`); each a joint robust fit of the lights and of the maps of a pixel
     subsample (:func:`_fit_lights`);
  3. per pixel (:func:`_solve_maps`): with the lights fixed every pixel is an independent problem:
     Levenberg-Marquardt on all pixels at once (in chunks; :mod:`matcap.refine.solve`), on a half-size copy first,
     whose corrections are upsampled as the start of the full-size solve;
  4. outputs (:func:`_outputs`): the maps, re-renders, residual, fit.json.
Photos are scaled so that their mean over the mask is 0.5 (the fit's units); lights are reported in photo units.
"""
from __future__ import annotations

import contextlib
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from matcap.errors import MatcapError
from matcap.normals import unit_normals
from matcap.refine.settings import RefineSettings
from scenes.materialmaps import MaterialMaps

if TYPE_CHECKING:
    from matcap.refine.flat import FlatLights

LUMA = (0.2126, 0.7152, 0.0722)


@dataclass
class RefineResult:
    """maps: refined :class:`MaterialMaps`; lights: lights.json ``images`` entries (photo units); report: fit.json;
    residual (H, W) float32 RMS re-render error / the photos' mean (NaN off-mask); variation (H, W) float32
    light variation (NaN off-mask); warning: one line or None; prediction (K, H, W, 3) re-renders in photo units;
    candidates: the estimated lights' candidate light models judged, in order (:class:`Candidate`; empty with
    known lights)."""

    maps: MaterialMaps
    lights: list[dict[str, Any]]
    report: dict[str, Any]
    residual: np.ndarray
    variation: np.ndarray
    warning: str | None = None
    prediction: np.ndarray | None = field(default=None, repr=False)
    candidates: list["Candidate"] = field(default_factory=list, repr=False)


# ----------------------------------------------------------------------------------------------- checks


def check_inputs(images, mask: np.ndarray) -> np.ndarray:
    """(K, H, W, 3) float32 stack of ``images``; one-line MatcapError for <2 images, NaN/Inf, all-dark photos."""
    if len(images) < 2:
        raise MatcapError(f"refinement needs at least 2 photos, got {len(images)}")
    stack = np.stack([np.asarray(im, dtype=np.float32) for im in images])
    if stack.ndim != 4 or stack.shape[3] != 3:
        raise MatcapError(f"expected (H, W, 3) RGB photos, got {stack.shape[1:]}")
    if mask.shape != stack.shape[1:3]:
        raise MatcapError(f"mask is {mask.shape}, photos are {stack.shape[1:3]}")
    bad = ~np.isfinite(stack)
    if bad.any():
        k = int(np.argmax(bad.reshape(len(stack), -1).any(axis=1)))
        raise MatcapError(f"photo {k} holds NaN or Inf values; refinement needs finite pixels")
    if not mask.any():
        raise MatcapError("the mask is empty: nothing to refine")
    means = stack[:, mask].mean(axis=(1, 2))
    if not (means > 1e-6).any():
        raise MatcapError("every photo is black on the object: nothing to fit (check the exposure)")
    return np.clip(stack, 0.0, None)


# ----------------------------------------------------------------------------------------------- diagnostics


def light_variation(stack: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-pixel light variation (H, W): std / mean over the photos of the pixel's luminance (NaN off-mask).

    Near 0 where the lighting barely changes between photos (a weak moving light under a strong fixed one, a
    region outside a spot light): there the photos cannot tell the normal or the BRDF apart.
    """
    lum = np.tensordot(stack, np.float32(LUMA), axes=([3], [0]))  # (K, H, W)
    mean = lum.mean(axis=0)
    std = lum.std(axis=0)
    v = np.where(mean > 1e-6, std / np.maximum(mean, 1e-6), 0.0).astype(np.float32)
    return np.where(mask, v, np.nan).astype(np.float32)


def variation_warning(variation: np.ndarray, mask: np.ndarray, threshold: float) -> tuple[float, str | None]:
    """(fraction of mask pixels below ``threshold``, one-line warning or None when under 5 %)."""
    frac = float((variation[mask] < threshold).mean())
    if frac < 0.05:
        return frac, None
    return frac, (f"light variation: {frac:.0%} of the object's pixels barely change between photos (std/mean "
                  f"< {threshold:g}); their maps are guesses and weigh less in the fit: move the light further "
                  f"off-axis between photos (and dim any fixed light)")


# ----------------------------------------------------------------------------------------------- helpers


def _resize(arr: np.ndarray, hw: tuple[int, int], interp: str = "area") -> np.ndarray:
    import cv2

    flag = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}[interp]
    out = cv2.resize(np.ascontiguousarray(arr, dtype=np.float32), (hw[1], hw[0]), interpolation=flag)
    if arr.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out


def _maps_arrays(maps: MaterialMaps) -> dict[str, np.ndarray]:
    m = maps.with_defaults()
    n = np.asarray(m.normal, np.float32).copy()
    n[~m.mask] = (0.0, 0.0, 1.0)
    return {"normal": unit_normals(n), "base": np.clip(np.nan_to_num(m.base_color), 0, 1).astype(np.float32),
            "rough": np.clip(np.nan_to_num(m.roughness, nan=0.5), 0, 1).astype(np.float32),
            "metal": np.clip(np.nan_to_num(m.metallic), 0, 1).astype(np.float32)}


def _downsample(stack: np.ndarray, mask: np.ndarray, arrays: dict[str, np.ndarray], hw: tuple[int, int]):
    small = np.stack([_resize(im, hw) for im in stack])
    cover = _resize(mask.astype(np.float32), hw)
    m = cover > 0.99
    if m.sum() < 16:
        m = cover > 0.5
    out = {}
    for k, v in arrays.items():
        out[k] = _resize(v, hw)
    for k in ("normal", "start"):
        if k in out:
            out[k] = unit_normals(out[k])
    return small, m, out


@dataclass
class _Photos:
    """The photos ready for the fit (:func:`_prepare`).

    mask (H, W); obs (K, H, W, 3) photos in fit units (their mean over the mask is 0.5); scale: fit units per
    photo unit; sat_level (K, 3) each photo's clipping level per channel in fit units (inf for a black channel);
    arrays: the networks' maps as "normal", "base", "rough", "metal"; variation (H, W) light variation (NaN
    off-mask); weak_fraction and warning: its diagnostic (:func:`variation_warning`); weight (H, W) per-pixel
    data weight (weakly lit pixels weigh less, down to 0.1)."""

    mask: np.ndarray
    obs: np.ndarray
    scale: float
    sat_level: np.ndarray
    arrays: dict[str, np.ndarray]
    variation: np.ndarray
    weak_fraction: float
    warning: str | None
    weight: np.ndarray

    def light_copy(self, side: int):
        """((h, w), (obs, mask, arrays, weight)) of the copy the light fit runs on: longer side at most ``side``
        pixels (these arrays themselves where they are no larger)."""
        h, w = self.mask.shape
        f = min(1.0, side / max(h, w))
        hw = (max(8, round(h * f)), max(8, round(w * f)))
        if hw == (h, w):
            return hw, (self.obs, self.mask, self.arrays, self.weight)
        return hw, (*_downsample(self.obs, self.mask, self.arrays, hw), _resize(self.weight, hw))


def _prepare(images, maps: MaterialMaps, s: RefineSettings) -> _Photos:
    """The first stage of the fit: the photos checked (:func:`check_inputs`, the maps' size), scaled to fit units,
    their clipping levels and light variation measured."""
    mask = np.asarray(maps.mask, bool)
    stack = check_inputs(images, mask)
    if stack.shape[1:3] != maps.shape:
        raise MatcapError(f"photos are {stack.shape[2]}x{stack.shape[1]} but the maps {maps.shape[1]}x{maps.shape[0]}")
    scale = 0.5 / float(stack[:, mask].mean())
    obs = stack * scale
    sat_level = np.array([o[mask].max(axis=0) * 0.999 for o in obs], np.float32)
    sat_level = np.where(sat_level > 0, sat_level, np.inf).astype(np.float32)
    variation = light_variation(stack, mask)
    frac_weak, warning = variation_warning(variation, mask, s.loss.variation_threshold)
    weight = np.clip(np.nan_to_num(variation) / s.loss.variation_threshold, 0.1, 1.0).astype(np.float32)
    return _Photos(mask, obs, scale, sat_level, _maps_arrays(maps), variation, frac_weak, warning, weight)


#: Fit units (the photos' mean over the mask is 0.5): how far below the prediction a cast-shadowed observation is
#: at least.
SHADOW_GAP = 0.05


class _Problem:
    """Observations of N pixels: obs (K, N, 3), weight (N,), positions, priors (torch); shadow: the share of the
    prediction below which an observation counts as cast shadow (0: none; ``loss.shadow``).
    upper (K, N, 3): the residual (prediction - observation) above which an observation adds none: 0 exactly where
    it is clipped (at its photo's ``sat_level``: a lower bound only), the cast-shadow level where ``shadow`` is set
    (an observation below ``shadow`` times the prediction and at least :data:`SHADOW_GAP` below it: an upper bound
    only), else infinite."""

    def __init__(self, torch, stack, mask, arrays, weight, sat_level, device, idx=None, start=None,
                 shadow: float = 0.0):
        rows, cols = np.nonzero(mask)
        if idx is not None:
            rows, cols = rows[idx], cols[idx]
        self.rows, self.cols = rows, cols
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(device)  # noqa: E731
        self.obs = t(stack[:, rows, cols])
        if shadow > 0:  # obs < shadow pred and pred - obs > gap  <=>  pred - obs > max(obs (1 / shadow - 1), gap)
            level = (self.obs * (1.0 / shadow - 1.0)).clamp(min=SHADOW_GAP)
        else:
            level = torch.full_like(self.obs, float("inf"))
        self.upper = torch.where(self.obs >= t(sat_level)[:, None, :], torch.zeros_like(level), level)
        self.weight = t(weight[rows, cols])
        self.n0 = t(arrays["normal"][rows, cols])
        self.b0 = t(arrays["base"][rows, cols])
        self.r0 = t(arrays["rough"][rows, cols])
        self.m0 = t(arrays["metal"][rows, cols])
        self.ns = self.n0 if start is None else t(start[rows, cols])  # start normals (the prior is n0)
        from matcap.refine.model import plane_positions

        h, w = mask.shape
        self.pos = plane_positions(torch.from_numpy(rows), torch.from_numpy(cols), h, w).to(device)
        self.backdrop = None  # (K, N, 3): what lies behind each pixel, where it mixes the object with it

    def __len__(self) -> int:
        return len(self.rows)

    def part(self, sl) -> "_Problem":
        """The pixels ``sl`` (a slice or an index array) of this problem."""
        tsl = sl if isinstance(sl, slice) else __import__("torch").from_numpy(np.asarray(sl)).to(self.obs.device)
        new = self.take(tsl)
        new.rows, new.cols = self.rows[sl], self.cols[sl]
        return new

    def take(self, tsl) -> "_Problem":
        """The torch tensors alone at pixels ``tsl`` (a slice or an index tensor on the device), without the pixel
        coordinates: usable inside ``torch.func`` transforms, where an index cannot become numpy."""
        new = object.__new__(_Problem)
        new.obs, new.upper = self.obs[:, tsl], self.upper[:, tsl]
        for k in ("weight", "n0", "ns", "b0", "r0", "m0", "pos"):
            setattr(new, k, getattr(self, k)[tsl])
        new.backdrop = None if self.backdrop is None else self.backdrop[:, tsl]
        return new


def _loss(torch, prob: _Problem, px, lights, s: RefineSettings, c: float, brdf: bool = True):
    """Per-pixel loss (N,) (data + prior) and the data part alone."""
    n = px.normal()
    b = px.base()
    r = px.rough() if brdf else prob.r0
    m = px.metal() if brdf else prob.m0
    pred = _shade(lights, prob.pos, n, b, r, m)
    res = pred - prob.obs
    res = torch.where(res > prob.upper, torch.zeros_like(res), res)  # clipped: a lower bound; cast shadow: an upper
    rho = torch.log1p((res / c) ** 2)
    data = rho.mean(-1).sum(0) * prob.weight
    prior = s.priors.normal * ((n - prob.n0) ** 2).sum(-1)
    prior = prior + s.priors.base * ((torch.log(b + 0.02) - torch.log(prob.b0 + 0.02)) ** 2).mean(-1)
    if brdf:
        prior = prior + s.priors.rough * (r - prob.r0) ** 2 + s.priors.metal * (m - prob.m0) ** 2
    return data + prior, data


def _shade(lights, pos, n, b, r, m):
    from matcap.refine.model import shade_fast

    wo, irr = lights.incident(pos)
    return shade_fast(n, b, r, m, wo, irr, lights.sh)


def _luminance(obs, rows, cols) -> np.ndarray:
    """(K, P) luminance of the photos ``obs`` (K, H, W, 3) at pixels ``rows``, ``cols``."""
    return np.tensordot(obs[:, rows, cols], np.asarray(LUMA, np.float32), axes=([2], [0]))


def _linear_lights(obs, mask, arrays, s: RefineSettings, rng, lambertian: bool = True):
    """The factorization (:class:`matcap.refine.linear.LinearFit`) of the light-fit copy's photos; its ambiguity
    re-fixed by integrability only where the check can still trust it (kept captures need no lights from it)."""
    from matcap.refine.linear import contour_normals, factorize

    fs = s.factorization
    sel, c_normal = contour_normals(mask, arrays["normal"], gate=fs.contour_gate, nz=fs.contour_nz)
    rows, cols = np.nonzero(mask)
    on_contour = sel[rows, cols]
    inner = np.flatnonzero(~on_contour)
    if len(inner) > s.factorization.pixels:
        inner = np.sort(rng.choice(inner, size=s.factorization.pixels, replace=False))
    idx = np.sort(np.concatenate([inner, np.flatnonzero(on_contour)]))
    r, c = rows[idx], cols[idx]
    lum = _luminance(obs, r, c)
    alb = arrays["base"][r, c] @ np.asarray(LUMA, np.float32)
    fit = factorize(lum, arrays["normal"][r, c], alb, on_contour[idx], c_normal[r, c], s.factorization.contour_weight)
    if _distrust(len(obs), fit, None, s, lambertian) is None:
        fit = _integrable(fit, obs, mask, arrays["normal"], sel, c_normal, fs.contour_weight, fs.equal_lights)
    return fit


def _integrable(fit, obs, mask, network, contour, c_normal, contour_weight, equal_lights):
    """``fit`` with its ambiguity fixed by integrability (:func:`matcap.refine.linear.integrable_ambiguity`) on
    every pixel of the light-fit copy; unchanged where that is ill-posed."""
    import dataclasses

    from matcap.refine.linear import integrable_ambiguity, solve_normals

    rows, cols = np.nonzero(mask)
    lum = _luminance(obs, rows, cols)
    s_lum = fit.directions * fit.irradiance[:, None]
    n, alb, solved = solve_normals(lum, s_lum, network[rows, cols])
    b_img = np.zeros(mask.shape + (3,))
    b_img[rows, cols] = n * alb[:, None]
    ok = np.zeros(mask.shape, bool)
    ok[rows, cols] = solved
    on = contour & mask
    prior = np.where(on[..., None], c_normal, network)
    share = contour_weight * (mask & ~on).sum() / max(int(on.sum()), 1)
    a = integrable_ambiguity(b_img, ok, prior, np.where(on, share, 1.0) * mask, s_lum, equal_lights)
    if a is None or not np.isfinite(a).all() or abs(np.linalg.det(a)) < 1e-12:  # nothing to choose it by
        return fit
    s_new = s_lum @ np.linalg.inv(a)
    b = (fit.normal * fit.albedo[:, None]) @ a.T
    size = np.linalg.norm(b, axis=1)
    irr = np.linalg.norm(s_new, axis=1)
    return dataclasses.replace(fit, directions=s_new / np.maximum(irr, 1e-12)[:, None], irradiance=irr,
                               normal=b / np.maximum(size, 1e-12)[:, None], albedo=size)


def _distrust(k_count: int, linear, solved_fraction: float | None, s: RefineSettings,
              lambertian: bool = True) -> str | None:
    """Why the factorization's lights may not move the maps (one line), or None: the check of docs/refine.md
    (``solved_fraction`` None: the photos' normals are not solved yet, that part of the check waits;
    ``lambertian`` False: the residual / inliers part is left out, for the candidates judged after it)."""
    if k_count < 4:
        return f"{k_count} photos: per-pixel normals need 4 or more"
    if linear.spread < s.checks.spread:
        return (f"the surface is too flat for the photos to tell where the lights were (third singular value "
                f"{linear.spread:.3f} of the first; trusted from {s.checks.spread:g})")
    if lambertian and (linear.residual > s.checks.residual or linear.inliers < s.checks.inliers):
        return (f"distant lights on a diffuse surface do not explain the photos (residual {linear.residual:.0%}, "
                f"inliers {linear.inliers:.0%}; trusted from {s.checks.residual:.0%} / {s.checks.inliers:.0%})")
    if solved_fraction is not None and solved_fraction < s.checks.solved:  # implausible lights: normals face away
        return (f"under the lights found only {solved_fraction:.0%} of the object's pixels get a normal facing the "
                f"camera (trusted from {s.checks.solved:.0%})")
    return None


def _photo_normals(obs, mask, network, s_lum, report=None, positions=None, chunk: int = 1 << 18,
                   max_misfit: float | None = None):
    """Calibrated photometric-stereo normals (H, W, 3) of the photos ``obs`` (K, H, W, 3) under the lights
    ``s_lum`` (K, 3: direction times luminance irradiance at the object's centre): robust Lambertian least squares
    where a pixel is lit in 4 photos or more (and, given ``max_misfit``, where the Lambertian model's RMS misfit
    over the photos that light it is at most that share of its mean brightness), the networks' normals
    ``network`` elsewhere. ``positions`` (K, 3): the lamps' positions on the framing plane's world units (near
    lamps): each pixel then gets its own direction toward each lamp and the irradiance falls off with the squared
    distance. They are both the start and the prior of the per-pixel stage. Returns (normals, report:
    ``solved_fraction``); ``report`` given: reused (a downsampled copy). Pixels are solved ``chunk`` at a time."""
    from matcap.refine.linear import lambertian_shading, solve_normals

    rows, cols = np.nonzero(mask)
    start = network.copy()
    solved_count = 0
    if positions is not None:  # near lamps: every pixel's own light vectors, irradiance referred to the centroid
        import torch

        centre = _centre(torch, mask).double().numpy()
    for a in range(0, len(rows), chunk):
        r, c = rows[a:a + chunk], cols[a:a + chunk]
        lights = s_lum if positions is None else _near_vectors(s_lum, positions, centre, mask.shape, r, c)
        lum = _luminance(obs, r, c)
        n, albedo, solved = solve_normals(lum, lights, network[r, c])
        if max_misfit is not None:
            shade = np.clip(lambertian_shading(lights, n), 0.0, None) * albedo[None]
            lit = shade > 0
            misfit = np.sqrt(((lum - shade) ** 2 * lit).sum(0) / np.maximum(lit.sum(0), 1))
            solved &= misfit <= max_misfit * np.maximum(lum.mean(0), 1e-6)
            n = np.where(solved[:, None], n, network[r, c])
        start[r, c] = n
        solved_count += int(solved.sum())
    if report is None:
        report = {"solved_fraction": round(solved_count / max(len(rows), 1), 4)}
    return start, report


def _near_vectors(s_lum: np.ndarray, positions: np.ndarray, centre: np.ndarray, hw: tuple[int, int], rows,
                  cols) -> np.ndarray:
    """(K, P, 3) per-pixel light vectors of lamps at ``positions`` (K, 3) whose irradiance times direction at
    ``centre`` (3,) is ``s_lum`` (K, 3), at the pixels (rows, cols) of an ``hw`` image (framing plane units)."""
    import torch

    from matcap.refine.model import plane_positions

    pos = plane_positions(torch.from_numpy(np.asarray(rows)), torch.from_numpy(np.asarray(cols)), *hw).double().numpy()
    p = np.asarray(positions, np.float64)
    q = p[:, None, :] - pos[None]
    r2 = (q * q).sum(-1, keepdims=True)
    r2c = ((p - centre) ** 2).sum(-1)[:, None, None]
    return np.linalg.norm(s_lum, axis=1)[:, None, None] * q / np.sqrt(r2) * (r2c / r2)


def _init_lights(torch, prob: _Problem, s: RefineSettings, device, directions=None):
    """Lights per photo: ``directions`` (K, 3) when given (the factorization's), else Lambertian least squares
    from the network normals and base colour (robust: two reweightings); then the RGB irradiance by least
    squares."""
    from matcap.refine.model import LightParams

    luma = torch.tensor(LUMA, device=device)
    n = prob.n0
    alb = (prob.b0 * luma).sum(-1).clamp(min=0.02)
    k_count = prob.obs.shape[0]
    dirs, ints = [], []
    for k in range(k_count):
        if directions is not None:
            d = _above_horizon(torch, torch.as_tensor(directions[k], dtype=torch.float32, device=device))
        else:
            d = _above_horizon(torch, _lambertian_direction(torch, prob.obs[k], n, alb, luma))
        sdiff = (n @ d).clamp(min=0.0) / math.pi
        den = ((prob.b0 * sdiff[:, None]) ** 2).sum(0).clamp(min=1e-8)
        e = (prob.obs[k] * prob.b0 * sdiff[:, None]).sum(0) / den
        dirs.append(d)
        ints.append(e.clamp(min=1e-4))
    vec = torch.stack(dirs)
    log_i = torch.log(torch.stack(ints))
    sh = torch.zeros(1 if s.model.ambient != "per-image" else k_count, 9, 3, device=device)
    return LightParams("directional", vec, log_i, sh)


def _lambertian_direction(torch, obs_k, n, alb, luma):
    """Unit direction of photo k's light by robust Lambertian least squares on normals ``n`` (N, 3) and luminance
    albedo ``alb`` (N,): ``obs_k`` (N, 3); attached shadows and outliers dropped in 3 rounds."""
    device = obs_k.device
    y = (obs_k * luma).sum(-1) / alb * math.pi  # ~ E * max(n . l, 0)
    keep = y > 0.05 * torch.quantile(y, 0.95)
    L = torch.zeros(3, device=device)
    for _ in range(3):
        A, b = n[keep], y[keep]
        if A.shape[0] < 8:
            break
        L = torch.linalg.lstsq(A, b[:, None]).solution[:, 0]
        shading = n @ L
        keep = (shading > 0.05 * shading.max().clamp(min=1e-6)) & (y > 0.02 * torch.quantile(y, 0.95))
        err = (shading - y).abs()
        keep &= err < 3.0 * err[keep].median().clamp(min=1e-6) + 0.05 * y.mean()
    if not torch.isfinite(L).all() or L.norm() < 1e-6:
        L = torch.tensor([0.0, 0.0, 1.0], device=device) * y.mean()
    return L / L.norm()


def _above_horizon(torch, d):
    """A light behind the object cannot light what the camera sees: keep it at the horizon."""
    if d[2] < 0.05:
        d = torch.cat([d[:2], d[2:].clamp(min=0.05)])
        d = d / d.norm()
    return d


def _to_near(torch, lights, centre):
    """Directional -> near lights (:class:`matcap.refine.model.LightParams` "near"): the same directions and
    irradiances at ``centre`` (3,), infinitely far (inverse distance 0) and free to come closer."""
    from matcap.refine.model import LightParams

    k = lights.vec.shape[0]
    return LightParams("near", lights.directions().detach().clone(), lights.log_intensity.detach().clone(),
                       lights.sh.detach().clone(), torch.zeros(k, device=lights.vec.device), centre)


def _centre(torch, mask: np.ndarray):
    """(3,) plane position of the mask's centroid: where near lights' directions and irradiances refer to."""
    from matcap.refine.model import plane_positions

    rows, cols = np.nonzero(mask)
    return plane_positions(torch.from_numpy(rows), torch.from_numpy(cols), *mask.shape).mean(0)


# ----------------------------------------------------------------------------------------------- main


def refine(images, maps: MaterialMaps, settings: RefineSettings | None = None,
           progress: bool | Callable[[str, int, int, float], None] = False, lights=None,
           flat: bool = False, found_lamps: FlatLights | None = None) -> RefineResult:
    """Fit lights and maps to the photos.

    images: K (H, W, 3) float32 linear RGB photos (at the maps' size); maps: the networks' :class:`MaterialMaps`
    (missing BRDF maps start from ``with_defaults``); lights: :class:`matcap.lightfiles.KnownLights` of the photos
    (held: :func:`_refine_known`) or None (estimated: :func:`_refine_estimated`). Deterministic for
    ``settings.seed`` on one device. ``progress``: see :class:`_Bar`.
    ``flat``: the photos show a flat sample facing the camera: without ``lights``, its lamps are found from the
    falloff of their light over the plane (:func:`matcap.refine.flat.flat_lights`) and held like known ones; where
    the falloff does not place them (distant lamps), the networks' maps are kept (the photos of a plane under
    distant lights hold its relief only up to its sign and depth) and the lights fitted to them, but for the
    normals: every one is the camera axis (the plane's own; on rendered flat samples the networks' normals came out
    further from the truth than that, on every one). ``found_lamps``: what :func:`matcap.refine.flat.flat_lights`
    returned for these photos and ``maps.mask``, where the caller found them already (the 8-bit decoding's choice):
    not found again.
    """
    import torch

    s = settings or RefineSettings()
    # The fit repeats bit for bit on a CPU as it is (measured); a GPU's kernels are held to it by torch's
    # deterministic mode, whose switch imports torch's compiler stack (about 1.5 s), so only there.
    on_gpu = torch.device(s.device).type != "cpu"
    if on_gpu:
        was = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
        torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        if lights is None and flat:
            from matcap.refine.flat import flat_lights

            t0 = time.perf_counter()
            if found_lamps is None:
                bar = _Bar(progress, s, total=3)  # the lamps' search: one step per stage of it
                found_lamps = flat_lights(images, maps.mask, on_stage=lambda: bar.step("flat lamps", math.nan))
                bar.close()
            lights, found = found_lamps.lights, found_lamps.record
            lamps_s = time.perf_counter() - t0
            if lights is None:  # distant lamps: the networks' maps are kept (the lights fitted to them), but for
                # their normals, which are the plane's own (the camera axis)
                plane = replace(maps, normal=np.where(maps.mask[..., None], _plane_normals(maps.mask), 0.0))
                result = _refine_estimated(torch, images, plane, s, progress, keep=FLAT_DISTANT)
                result.report["flat"] = found
            else:
                result = _refine_known(torch, images, maps, s, progress, lights, flat=found)
            timings = result.report["timings"]  # the lamps' search is part of the fit's time
            timings["flat_lamps_s"] = round(lamps_s, 3)
            timings["total_s"] = round(timings["total_s"] + lamps_s, 3)
            return result
        if lights is not None:
            return _refine_known(torch, images, maps, s, progress, lights, flat={} if flat else None)
        return _refine_estimated(torch, images, maps, s, progress)
    finally:
        if on_gpu:
            torch.use_deterministic_algorithms(was[0], warn_only=was[1])


def _refine_known(torch, images, maps: MaterialMaps, s: RefineSettings, progress, known,
                  flat: dict | None = None) -> RefineResult:
    """The fit with lights the user knows (:class:`matcap.lightfiles.KnownLights`, one per photo).

    Stages: (1) lights: the given directions (and point-light positions) are held; the per-photo intensities (or,
    where the file gives relative intensities, one overall scale, their colours held) and the low orders of one
    ambient shared by every photo are fitted, first by least squares, then jointly with a subsample's maps under
    the Principled model (:func:`_fit_intensities`). On a flat sample whose given lights come without intensities
    the subsample's mean normal is held to the camera axis (``lights.flat_mean_held``) and the ambient as given; on
    one whose lights come with relative intensities the photos set their overall power, one factor on the
    networks' base colour solved with them (``lights.flat_level_free``; under distant lights the ambient held as
    given). On an object, distant lights whose intensities the file gives are taken as they are, at the
    least-squares scale, with the file's ambient (a ``lights.json``'s ``sh``; else none) at that scale; the start
    normals come from semi-calibrated Lambertian least squares (:func:`known_irradiance`); (2) the per-pixel solve
    (:func:`_solve_maps`) from calibrated photometric-stereo normals, then the roughness stage
    (:func:`_roughness_stage`); (3) outputs. With the lights known there is no
    bas-relief family to choose from, so nothing is gated: the maps are always the fitted ones. ``flat``: what
    :func:`matcap.refine.flat.flat_lights` found (empty where the lights were given), recorded in fit.json as
    ``flat``.
    """
    t_start = time.perf_counter()
    ph = _prepare(images, maps, s)
    mask, obs, scale, sat_level, arrays, weight = ph.mask, ph.obs, ph.scale, ph.sat_level, ph.arrays, ph.weight
    k_count, h, w = obs.shape[:3]
    if len(known) != k_count:
        raise MatcapError(f"{len(known)} known lights for {k_count} photos")
    device = torch.device(s.device)
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    bar = _Bar(progress, s, total=0)
    timings: dict[str, float] = {}

    # ---- 1. lights: intensities and ambient for the given directions
    t0 = time.perf_counter()
    hw_l, (obs_l, mask_l, arr_l, w_l) = ph.light_copy(s.lights.side)
    centre = _centre(torch, mask).numpy().astype(np.float64)
    directions = np.asarray(known.directions, np.float64)
    inv_distance = None
    if known.positions is not None:  # point lights: direction and distance from the object's centre
        rel = np.asarray(known.positions, np.float64) - centre
        dist = np.linalg.norm(rel, axis=1)
        directions, inv_distance = rel / np.maximum(dist, 1e-12)[:, None], 1.0 / np.maximum(dist, 1e-12)
    given = None if known.intensities is None else np.asarray(known.intensities, np.float64)
    if given is not None and inv_distance is not None:  # a point light's radiant intensity -> irradiance at the centre
        given = given * inv_distance[:, None] ** 2
    luma = np.asarray(LUMA, np.float64)
    rows_l, cols_l = np.nonzero(mask_l)
    # a flat sample's photometric normals start from (and, where unsolved, stay at) the plane's own normal: the
    # robust solve weighs each observation by its residual at the start, and a network normal far off on a
    # swatch's corner left it there
    guess = arrays["normal"] if flat is None else _plane_normals(mask)
    guess_l = arr_l["normal"] if flat is None else _plane_normals(mask_l)
    irr = known_irradiance(_luminance(obs_l, rows_l, cols_l), directions, guess_l[rows_l, cols_l],
                           None if given is None else given @ luma)
    s_lum = directions * irr[:, None]
    # a flat sample keeps the misfit Lambertian normals: the networks' are a poorer fallback on a swatch's relief
    misfit = s.priors.lambertian_misfit if flat is None else None
    start, photo_report = _photo_normals(obs, mask, guess, s_lum, positions=known.positions, max_misfit=misfit)
    arrays = dict(arrays, normal=start)
    if hw_l == (h, w):
        arr_l, start_l = arrays, start
    else:
        start_l, _ = _photo_normals(obs_l, mask_l, guess_l, s_lum, photo_report, positions=known.positions,
                                    max_misfit=misfit)
        arr_l = dict(arr_l, normal=start_l)
    idx = _known_subsample(mask_l, s, rng)
    # no cast-shadow rule for a flat sample (a plane facing the camera shades itself only through its small
    # relief) nor for found lamps (their errors would pass for shadow)
    shadow = 0.0 if known.source == "estimated" or flat is not None else s.loss.shadow
    prob = _Problem(torch, obs_l, mask_l, arr_l, w_l, sat_level, device, idx, start_l, shadow=shadow)
    lights = _init_lights(torch, prob, s, device, directions)
    if inv_distance is not None:
        lights = _to_near(torch, lights, torch.as_tensor(centre, dtype=torch.float32, device=device))
        lights.inv_distance = torch.as_tensor(inv_distance, dtype=torch.float32, device=device)
    given_log = None
    # a flat sample's intensities in the photos' units: their power is held (the photos' scale to fit units alone).
    # An object's photos hold light the model does not (interreflections, a room's light on its far side): there
    # the least-squares scale takes its share
    power_held = given is not None and known.intensity_units == "photos" and flat is not None
    if given is not None:  # relative intensities: start from them at the least-squares overall scale
        given_log = torch.as_tensor(np.log(np.maximum(given, 1e-12)), dtype=torch.float32, device=device)
        offset = (torch.tensor(math.log(scale), dtype=torch.float32, device=device) if power_held
                  else (lights.log_intensity - given_log).mean())
        lights.log_intensity = given_log + offset
        if known.ambient is not None and s.model.ambient != "none":  # the file's ambient, at the same scale
            amb = np.asarray(known.ambient, np.float64)
            amb = amb if s.model.ambient == "per-image" else amb.mean(0, keepdims=True)
            lights.sh = torch.as_tensor(amb, dtype=torch.float32, device=device) * offset.exp()
    # a flat sample's given lights without intensities: the sample's mean normal held (found lamps have their wide
    # tilts taken out after the per-pixel solve instead, pixels.found_lamps_detail)
    tilt_held = flat is not None and given is None and known.source != "estimated" and s.lights.flat_mean_held
    # a flat sample whose lights' ratios are known: the photos set their overall power (each photo's own intensity
    # fitted leaves too much freedom for that)
    ratios_on_plane = flat is not None and given is not None and s.lights.flat_level_free
    # nor can a plane's photos tell a constant ambient from each photo's own intensity, or, under distant lights
    # (which light it evenly), from their overall power: there it stays as given
    ambient_free = not (flat is not None and (given is None or inv_distance is None))
    # distant lights whose intensities are given are taken as they are, but for that power on a flat sample; the
    # others are fitted (with their power held, only what else is free: the level, the ambient)
    fitted = ((inv_distance is not None or given is None or ratios_on_plane) and s.lights.known_iters > 0
              and (not power_held or ratios_on_plane or (ambient_free and s.model.ambient != "none")))
    level_free = fitted and ratios_on_plane
    ambient = ("none" if s.model.ambient == "none" else "fitted" if fitted and ambient_free
               else "given" if known.ambient is not None else "none")  # what fit.json says of it
    light_iters, level = 0, 1.0
    if fitted:
        lights, level, light_iters = _fit_intensities(torch, prob, lights, s, bar, relative_to=given_log,
                                                      power_held=power_held, mean_held=tilt_held,
                                                      level_free=level_free, ambient_free=ambient_free)
        if level_free:  # the per-pixel solve's prior: the networks' base colour at the level the photos set
            arrays = dict(arrays, base=np.clip(arrays["base"] * level, 0.0, 1.0).astype(np.float32))
    timings["lights_s"] = time.perf_counter() - t0

    # ---- 2. per pixel (lamps found from the falloff: first rounds of the per-pixel stage on the light-fit copy,
    # each followed by the lamps placed again with its maps and the intensities refitted to them)
    t0 = time.perf_counter()
    found = known.source == "estimated"
    rounds = s.lights.found_lamps_rounds if found and fitted else 0
    rounds_rough_s = 0.0  # the rounds' roughness stages, counted in timings.roughness_s with the full-size one
    moved: list[float] = []  # each round's median angle (degrees, seen from the centre) the lamps moved by
    place_again = s.lights.found_lamps_steps > 0  # found lamps come with positions: "near" lights
    for _ in range(rounds):
        copy, px_l, *_, round_rough_s = _per_pixel_stage(torch, obs_l, mask_l, w_l, sat_level, arr_l, start_l,
                                                         lights, s, bar, shadow, plane=flat is not None,
                                                         lights_found=found)
        rounds_rough_s += round_rough_s
        if place_again:
            px_l = _plane_detail(torch, copy, px_l, mask_l, s.pixels.found_lamps_detail)
            placed = _place_lamps(torch, obs_l, mask_l, w_l, sat_level, arr_l, copy, px_l, lights, s, bar, rng,
                                  shadow)
            moved.append(_median_angle_deg(torch, lights, placed))
            lights = placed
        lights, more, start_l = _refit_intensities(torch, obs_l, mask_l, w_l, sat_level, arr_l, copy, px_l, lights,
                                                   s, bar, rng, shadow, ambient_free)
        light_iters += more
        start = start_l if hw_l == (h, w) else unit_normals(_resize(start_l, (h, w), "linear"))
    full, px_full, mixing, iters_done, restarts, choice, pooled_share, rough_s = _per_pixel_stage(
        torch, obs, mask, weight, sat_level, arrays, start, lights, s, bar, shadow, plane=flat is not None,
        lights_found=found)
    if choice is not None:
        timings["roughness_s"] = rough_s + rounds_rough_s
    detail = s.pixels.found_lamps_detail if found else 0.0
    if detail > 0:
        px_full = _plane_detail(torch, full, px_full, mask, detail)
    timings["maps_s"] = time.perf_counter() - t0
    bar.close()

    # ---- 3. outputs
    t0 = time.perf_counter()
    out = _outputs(torch, full, px_full, lights, s, scale, maps, mixing=mixing)
    timings["outputs_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    report = {
        "lights": {**known.record(), "directions": "held", "ambient": ambient, "mean_normal_held": tilt_held,
                   "base_level": round(level, 4) if level_free else None, "power_held": power_held,
                   "solved_fraction": photo_report["solved_fraction"],
                   **({"found_lamps_moved_deg": moved} if found else {})},
        **({"flat": flat} if flat is not None else {}),
        "psnr_db": [round(p, 3) for p in out.psnr],
        "psnr_db_mean": round(float(np.mean(out.psnr)), 3),
        "residual_mean": round(float(np.nanmean(out.residual)), 5),
        "iterations": {"lights": light_iters, **iters_done, "roughness": s.roughness.iters if choice else 0,
                       "intensity_rounds": rounds},
        "pixels": int(mask.sum()),
        "images": k_count,
        "normal_change_deg_mean": round(out.normal_change_deg, 3),
        "light_variation": {"threshold": s.loss.variation_threshold, "weak_fraction": round(ph.weak_fraction, 4),
                            "warning": ph.warning},
        "photo_scale": scale,
        "linear": None,
        "kept_network_maps": False,
        "ambient_share": round(out.ambient_share, 4),
        "cast_shadow_share": round(out.shadowed_share, 4),
        "outline": _outline_record(torch, mixing),
        "roughness": None if choice is None else {**choice.record(), "pooled_share": round(pooled_share, 4)},
        "restarts": restarts,
        "smooth_tilt_removed_sigma_widths": detail or None,
        "timings": {k: round(v, 3) for k, v in timings.items()},
        "settings": asdict(s),
    }
    return RefineResult(out.maps, lights_to_entries(lights, scale), report, out.residual, ph.variation, ph.warning,
                        out.prediction)


def _per_pixel_stage(torch, obs, mask, weight, sat_level, arrays: dict[str, np.ndarray], start, lights,
                     s: RefineSettings, bar, shadow: float, plane: bool, lights_found: bool):
    """Known lights' per-pixel stage under the fixed ``lights``: the solve (:func:`_solve_maps`: photos ``obs``
    (K, H, W, 3) in fit units, ``mask`` (H, W), ``weight`` (H, W), ``sat_level`` (K, 3), priors ``arrays``, start
    normals ``start`` (H, W, 3) or None), the neighbour restarts, the roughness stage (``plane``, ``lights_found``:
    see :func:`_roughness_stage`) and the pooling. Returns (problem, params, outline mixing, iterations, restarts
    record, roughness choice or None, pooled share, roughness stage seconds)."""
    full, px_full, mixing, iters_done = _solve_maps(torch, obs, mask, arrays, weight, sat_level, start, lights, s,
                                                    bar, s.pixels.coarse_iters, s.pixels.fine_iters, shadow=shadow)
    restarts = None
    if s.pixels.restart_deg > 0 and s.pixels.restart_rounds > 0:
        restarts = {"tried": [], "kept": []}
        for _ in range(s.pixels.restart_rounds):
            px_full, done = _neighbour_restarts(torch, full, px_full, lights, s, bar, mixing, mask)
            restarts["tried"].append(done["tried"])
            restarts["kept"].append(done["kept"])
    choice, pooled_share, rough_s = None, 0.0, 0.0
    if s.roughness.iters > 0 and s.model.fit_brdf:
        t_r = time.perf_counter()
        px_full, choice = _roughness_stage(torch, full, px_full, lights, s, bar, mixing, plane=plane,
                                           lights_found=lights_found)
        px_full, pooled_share = _pool_brdf(torch, full, px_full, lights, mask.shape, s)
        rough_s = time.perf_counter() - t_r
    return full, px_full, mixing, iters_done, restarts, choice, pooled_share, rough_s


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


def _refit_intensities(torch, obs, mask, weight, sat_level, arrays: dict[str, np.ndarray], full: _Problem, px,
                       lights, s: RefineSettings, bar, rng, shadow: float, ambient_free: bool):
    """Each photo's intensity (and the ambient's fitted orders, with ``ambient_free``) fitted again
    (:func:`_fit_intensities`) on ``lights.known_pixels`` pixels of the photos ``obs`` (K, H, W, 3) off the
    outline of ``mask``, their maps started from and anchored to the per-pixel stage's (``px`` of the problem
    ``full``; ``arrays`` off it). Returns (lights, iterations done, (H, W, 3) the stage's normals: the next
    stage's start)."""
    prob, fitted = _stage_subsample(torch, obs, mask, weight, sat_level, arrays, full, px, s, rng, shadow)
    lights, _, done = _fit_intensities(torch, prob, lights, s, bar, ambient_free=ambient_free)
    return lights, done, fitted["normal"]


def _place_lamps(torch, obs, mask, weight, sat_level, arrays: dict[str, np.ndarray], full: _Problem, px, lights,
                 s: RefineSettings, bar, rng, shadow: float):
    """Found lamps (``lights``, "near") placed again: their directions, distances and intensities fitted
    (:func:`_fit_lights`, ``lights.found_lamps_steps`` steps; the ambient held: a plane's photos cannot tell a room's
    light from each photo's intensity) together with the maps of ``lights.known_pixels``
    pixels of the photos ``obs`` (K, H, W, 3) off the outline of ``mask``, started from and anchored to the
    per-pixel stage's maps (``px`` of the problem ``full``, their wide tilts already taken out; ``arrays`` off it),
    the normals' gradient field free but for its smooth part (a polynomial of degree
    ``lights.found_lamps_tilt_degree`` in the plane's position), held at zero. Returns the lamps."""
    prob, _ = _stage_subsample(torch, obs, mask, weight, sat_level, arrays, full, px, s, rng, shadow)
    steps = s.lights.found_lamps_steps
    bar.add_total(steps)
    placed, _ = _fit_lights(torch, prob, lights.detached(), s, bar, "lamps", steps,
                            smooth_tilt_held=s.lights.found_lamps_tilt_degree
                            if s.lights.found_lamps_tilt_degree >= 0 else None, ambient_free=False)
    return placed


def _median_angle_deg(torch, before, after) -> float:
    """Median angle (degrees) between two sets of lights' directions (K, 3), seen from their centre."""
    cos = (before.directions() * after.directions()).sum(-1).clamp(-1.0, 1.0)
    return round(float(torch.rad2deg(torch.arccos(cos)).median()), 3)


def _known_subsample(mask: np.ndarray, s: RefineSettings, rng) -> np.ndarray:
    """(S,) sorted indices, among ``mask``'s pixels, of the known lights' light-fit pixels: ``lights.known_pixels``
    drawn by ``rng`` off the outline (whose pixels mix the object with what lies behind it; all pixels where the
    mask is all outline)."""
    inner = np.flatnonzero(~outline_zone(mask, s.pixels.outline)[mask])
    inner = inner if len(inner) else np.arange(int(mask.sum()))
    return np.sort(rng.choice(inner, size=min(len(inner), s.lights.known_pixels), replace=False))


def _roughness_stage(torch, full: _Problem, px, lights, s: RefineSettings, bar, mixing: "_Mixing | None",
                     plane: bool, lights_found: bool = False):
    """Known lights: pixels' roughness chosen among the values their photos allow (from the fitted normals, base
    colour and metallic; ``plane``: a flat sample's rule, :func:`matcap.refine.roughness.choose_roughness`, its
    undecided pixels at the bottom of their own valley unless ``lights_found`` (lamps found from the photos'
    falloff), else an object's, :func:`_object_choice`) and each material group's metallic, 0 or 1, where the photos
    of a sample of its pixels vote for it (:func:`_metallic_vote`); then the per-pixel solve again for the pixels
    whose roughness the choice moved by more than ``roughness.moved`` (a factor; ``roughness.moved_flat`` on a flat
    sample) or whose metallic lies more than ``roughness.metallic_moved`` from the one held (their group's), from
    the chosen values held by priors of weight ``roughness.hold`` and ``roughness.metallic_hold`` (a group without a
    clear vote holds the networks' metallic, the prior's); a pixel re-solved for its metallic alone keeps its
    normal. The others keep their fit. With ``roughness.choose`` off nothing is chosen: every pixel keeps its
    roughness (held at ``priors.rough``), and only the metallic vote runs.
    Returns (the new :class:`PixelParams`, the :class:`matcap.refine.roughness.RoughnessChoice`)."""
    from matcap.refine.roughness import choose_roughness, decision_rates, held_metallic, held_roughness

    r = s.roughness
    with torch.no_grad():
        normal, base, rough, metal = px.normal(), px.base(), px.rough(), px.metal()
    if not r.choose:
        choice = held_roughness(base.cpu().numpy(), rough.cpu().numpy(), r, s.seed)
    elif plane:
        costs = _grid_costs_parallel(torch, full, normal, base, rough, metal, lights, r)
        few = torch.from_numpy(_stage_sample(len(full), s, r.rate_pixels)).to(normal.device)
        rates = decision_rates(torch, full.pos[few], normal[few], base[few], metal[few], lights, r)
        choice = choose_roughness(costs, base.cpu().numpy(), rough.cpu().numpy(), r, s.seed, rates,
                                  observations=3 * full.obs.shape[0], descend=not lights_found)
    else:
        choice = _object_choice(torch, full, normal, base, rough, metal, lights, s)
    moved = np.abs(np.log(np.maximum(choice.rough, 1e-3)) - np.log(np.maximum(rough.cpu().numpy(), 1e-3))) > np.log(
        r.moved_flat if plane else r.moved)
    held_metal = None
    if r.metallic_hold > 0:
        choice.metallic = _metallic_vote(torch, full, normal, base, rough, metal, choice, lights, s)
        fitted_metal = metal.cpu().numpy()
        held_metal = held_metallic(choice.metallic, choice.groups, full.m0.cpu().numpy())
        metal_only = (np.abs(held_metal - fitted_metal) > r.metallic_moved) & ~moved
        moved |= metal_only
    out = [t.detach().clone() for t in px.tensors()]
    pixels = np.flatnonzero(moved)
    if len(pixels):
        hold = r.hold if r.choose else s.priors.rough  # a held roughness keeps its prior's weight
        _resolve(torch, full, px, out, pixels, choice.rough[pixels], hold, lights, s, bar, mixing,
                 None if held_metal is None else held_metal[pixels], r.metallic_hold)
    if held_metal is not None:  # a pixel re-solved for its metallic alone keeps the normal the per-pixel solve gave
        keep = torch.from_numpy(np.flatnonzero(metal_only)).to(out[0].device)
        out[0][keep] = px.grad[keep]
    from matcap.refine.model import PixelParams

    return PixelParams(*out), choice


def _pool_brdf(torch, full: _Problem, px, lights, hw: tuple[int, int], s: RefineSettings):
    """Known lights, after the roughness stage: each pixel's roughness and metallic become the median of their
    ``roughness.pool`` x ``roughness.pool`` window among the fitted pixels ``full`` (of an ``hw`` frame) where its
    own photos allow those values (their cost, :func:`matcap.refine.roughness.value_scores`, within
    ``roughness.tolerance`` of its cost at its fitted ones): a surface's finish varies far more slowly than one
    pixel's photos pin it down where they show no highlight, and the median keeps the edges between materials.
    Each channel of such a pixel's base colour moves by as much as its closed-form base colour (the one scored, at
    its fitted normal) changes from the fitted roughness and metallic to the pooled ones, so that the maps still
    explain the photos (a shift, not a factor: a glossy pixel's closed-form base colour can be near 0); the normals
    keep their fit.
    Returns (the new :class:`PixelParams`, the share of pixels that took the pooled values)."""
    from matcap.refine.model import PixelParams, _logit
    from matcap.refine.roughness import value_scores

    size = s.roughness.pool
    if size < 2 or len(full) == 0:
        return px, 0.0
    with torch.no_grad():
        normal, base, rough, metal = px.normal(), px.base(), px.rough(), px.metal()
        # the median of the logits: the same values (a median commutes with the sigmoid), none clipped
        fitted = torch.stack([px.rough_logit, px.metal_logit], dim=1).detach().cpu().numpy()
        pooled = torch.from_numpy(window_median(fitted, full.rows, full.cols, hw, size)).to(rough.device)
        r_pool, m_pool = torch.sigmoid(pooled[:, 0]), torch.sigmoid(pooled[:, 1])  # never NaN: a window holds its pixel
        scores = _costs_parallel(  # (2, 4, N): cost and closed-form base colour at the fitted and pooled values
            torch, full, normal, base, rough, metal, lights,
            lambda obs, upper, pos, nrm, sl: value_scores(torch, obs, upper, pos, nrm,
                                                          ((rough[sl], metal[sl]), (r_pool[sl], m_pool[sl])),
                                                          lights, s.roughness.noise))
        take = torch.from_numpy(scores[1, 0] - scores[0, 0] <= s.roughness.tolerance).to(rough.device)
        shift = torch.from_numpy((scores[1, 1:] - scores[0, 1:]).T.copy()).to(base.device)
        new_base = torch.where(take[:, None], base + shift, base).clamp(0.01, 0.99)
    params = PixelParams(px.grad.detach().clone(), torch.where(take[:, None], _logit(new_base), px.base_logit.detach()),
                         torch.where(take, pooled[:, 0], px.rough_logit.detach()),
                         torch.where(take, pooled[:, 1], px.metal_logit.detach()))
    return params, float(take.float().mean())


def _stage_sample(n: int, s: RefineSettings, size: int | None = None) -> np.ndarray:
    """(S,) sorted indices of a random sample of ``size`` (default ``roughness.sample``) of ``n`` pixels (all where
    fewer; ``seed``)."""
    size = s.roughness.sample if size is None else size
    return np.sort(np.random.default_rng(s.seed).choice(n, size=min(n, size), replace=False))


def _metallic_vote(torch, full: _Problem, normal, base, rough, metal, choice, lights,
                   s: RefineSettings) -> np.ndarray:
    """(G,) each material group of ``choice`` (:class:`matcap.refine.roughness.RoughnessChoice`: its ``groups``
    and chosen roughness) gets its metallic (:func:`matcap.refine.roughness.group_metallic`: 0, 1 or NaN) from the
    votes of :func:`_stage_sample`'s pixels of ``full``, at their fitted maps ``normal`` (N, 3), ``base`` (N, 3),
    ``rough`` (N,), ``metal`` (N,) torch."""
    from matcap.refine.roughness import group_metallic, metal_costs

    r = s.roughness
    sample = _stage_sample(len(full), s)
    t_s = torch.from_numpy(sample).to(normal.device)
    held = torch.from_numpy(np.ascontiguousarray(choice.rough[sample], np.float32)).to(normal.device)

    def score(obs, upper, pos, nrm, sl):
        return metal_costs(torch, obs, upper, pos, nrm, held[sl], lights, r.grid, r.noise)

    costs = _costs_parallel(torch, full.part(sample), normal[t_s], base[t_s], rough[t_s], metal[t_s], lights, score)
    return group_metallic(costs, choice.groups[sample], len(choice.targets), metal.cpu().numpy()[sample], r)


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


def _object_choice(torch, full: _Problem, normal, base, rough, metal, lights, s: RefineSettings):
    """An object's roughness choice (:func:`matcap.refine.roughness.object_targets` on a random sample of
    ``roughness.sample`` pixels, then :func:`matcap.refine.roughness.follow_targets` on the pixels farther than
    ``roughness.moved`` from their group's target, the sample's scores reused); the other pixels keep their fitted
    roughness. ``normal`` (N, 3), ``base`` (N, 3), ``rough`` (N,), ``metal`` (N,) torch: the fitted maps of
    ``full``'s pixels.
    Returns a :class:`matcap.refine.roughness.RoughnessChoice` (``decided``: the sample's)."""
    from matcap.refine.roughness import RoughnessChoice, follow_targets, material_groups, object_targets

    r = s.roughness
    base_np, fitted = base.cpu().numpy(), rough.cpu().numpy()
    groups = material_groups(base_np, r.groups, s.seed)
    n_groups = int(groups.max()) + 1 if len(groups) else 0
    sample = _stage_sample(len(full), s)

    def costs(pixels):
        t = torch.from_numpy(pixels).to(normal.device)
        return _grid_costs_parallel(torch, full.part(pixels), normal[t], base[t], rough[t], metal[t], lights, r)

    sample_costs = costs(sample)
    targets, typical, decided = object_targets(sample_costs, groups[sample], n_groups, r)
    own = np.isfinite(targets)
    target = np.where(own, targets, typical)[groups] if n_groups else np.zeros(0)
    has = np.isfinite(target)
    far = has & (np.abs(np.log(np.maximum(fitted, 1e-3)) - np.log(np.where(has, target, 1.0))) > np.log(r.moved))
    chosen = fitted.astype(np.float32).copy()
    pixels = np.flatnonzero(far)
    if len(pixels):  # the sample's pixels among them are scored already
        at = np.full(len(full), -1, np.int64)
        at[sample] = np.arange(len(sample))
        scored = at[pixels] >= 0
        c = np.empty((len(r.grid), len(pixels)), np.float32)
        c[:, scored] = sample_costs[:, at[pixels[scored]]]
        if not scored.all():
            c[:, ~scored] = costs(pixels[~scored])
        chosen[pixels], _ = follow_targets(c, fitted[pixels], target[pixels], own[groups[pixels]], r)
    return RoughnessChoice(chosen, decided, groups, targets, "object", typical=typical)


def _resolve(torch, full: _Problem, px, out: list, pixels: np.ndarray, rough: np.ndarray, weight: float, lights,
             s: RefineSettings, bar, mixing: "_Mixing | None", metal: np.ndarray | None = None,
             metal_weight: float = 0.0) -> None:
    """The per-pixel solve of ``full``'s pixels ``pixels`` (M,) again (``roughness.iters`` iterations), from ``px``
    with their roughness ``rough`` (M,), which is also their prior's, of weight ``weight`` (and, where given, their
    metallic ``metal`` (M,), its prior's weight ``metal_weight``); written into ``out`` (:class:`PixelParams`
    tensors) and, for the outline's pixels among them, ``mixing``'s coverage."""
    import dataclasses

    from matcap.refine.model import PixelParams, _logit

    sub = full.part(pixels)
    sub.r0 = torch.from_numpy(np.ascontiguousarray(rough, np.float32)).to(full.r0.device)
    idx = torch.from_numpy(pixels).to(full.r0.device)
    metal_logit = px.metal_logit[idx]
    priors = dataclasses.replace(s.priors, rough=weight)
    if metal is not None:
        sub.m0 = torch.from_numpy(np.ascontiguousarray(metal, np.float32)).to(full.r0.device)
        metal_logit = _logit(sub.m0.clamp(0.03, 0.97))
        priors = dataclasses.replace(priors, metal=metal_weight)
    start = PixelParams(px.grad[idx], px.base_logit[idx], _logit(sub.r0.clamp(0.03, 0.97)), metal_logit)
    sub_mixing, keep = None, None
    if mixing is not None:  # the outline's pixels among them, indexed within the subset
        where = np.full(len(full), -1, np.int64)
        where[pixels] = np.arange(len(pixels))
        found = np.flatnonzero(where[mixing.index] >= 0)
        if len(found):
            keep = torch.from_numpy(found).to(full.r0.device)
            sub_mixing = _Mixing(where[mixing.index[found]], mixing.backdrop[:, keep], mixing.cover_logit[keep].clone())
    held = dataclasses.replace(s, priors=priors)
    solved = _solve_pixels(torch, sub, start, lights, held, s.loss.cauchy, s.roughness.iters, bar, "roughness",
                           sub_mixing)
    for o, t in zip(out, solved.tensors()):
        o[idx] = t
    if sub_mixing is not None:
        mixing.cover_logit[keep] = sub_mixing.cover_logit


def _grid_costs_parallel(torch, full: _Problem, normal, base, rough, metal, lights, r) -> np.ndarray:
    """:func:`matcap.refine.roughness.grid_costs` of every pixel of ``full`` (its fitted maps ``normal``, ``base``,
    ``rough``, ``metal``), by :func:`_costs_parallel`. Returns (len(r.grid), N)."""
    from matcap.refine.roughness import grid_costs

    if len(full) == 0:
        return np.zeros((len(r.grid), 0), np.float32)
    return _costs_parallel(torch, full, normal, base, rough, metal, lights,
                           lambda obs, upper, pos, nrm, sl: grid_costs(torch, obs, upper, pos, nrm, metal[sl], lights,
                                                                       r.grid, r.noise))


def _costs_parallel(torch, full: _Problem, normal, base, rough, metal, lights, score) -> np.ndarray:
    """``score(obs, upper, pos, normal, sl)`` -> (..., n) of every pixel of ``full`` chunk by chunk (``sl`` the
    chunk's slice of the N pixels), on as many threads as torch was given, each of them with one-thread
    operations (as :func:`_solve_pixels`). The observations the fitted maps ``normal``, ``base``, ``rough``,
    ``metal`` leave in cast shadow have ``upper`` -inf (out at every value scored), clipped ones 0. Returns
    (..., N)."""
    from concurrent.futures import ThreadPoolExecutor

    step = 8192
    parts = [slice(i, min(i + step, len(full))) for i in range(0, len(full), step)]

    def cost(sl):
        obs, upper = full.obs[:, sl], full.upper[:, sl]
        with torch.no_grad():  # cast shadow as the fit left it (upper finite and exceeded)
            res = _shade(lights, full.pos[sl], normal[sl], base[sl], rough[sl], metal[sl]) - obs
        inf = torch.full_like(upper, float("inf"))
        upper = torch.where(upper == 0, upper, torch.where((upper < inf) & (res > upper), -inf, inf))
        return score(obs, upper, full.pos[sl], normal[sl], sl)

    with _one_thread(torch) as threads:
        with ThreadPoolExecutor(_workers(threads), initializer=torch.set_num_threads, initargs=(1,)) as pool:
            out = list(pool.map(cost, parts))
    return np.concatenate(out, axis=-1)


def _plane_normals(mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32: every pixel of ``mask``'s frame facing the camera (+z), a flat sample's own normal."""
    plane = np.zeros(mask.shape + (3,), np.float32)
    plane[..., 2] = 1.0
    return plane


def known_irradiance(luminance: np.ndarray, directions: np.ndarray, normal: np.ndarray,
                     relative: np.ndarray | None = None, rounds: int = 4) -> np.ndarray:
    """Per-photo irradiance (K,) of lights whose directions are known, as the start of the light fit: robust
    Lambertian normals under the lights (:func:`matcap.refine.linear.solve_normals`: shadows and highlights weigh
    little) alternated with each photo's irradiance by least squares over the pixels it lights. From equal lamps,
    this moves little; the joint Principled fit that follows finds each photo's intensity.

    luminance: (K, P) photo luminance; directions: (K, 3) unit; normal: (P, 3) start normals (the networks');
    relative: (K,) given relative irradiances (only their overall scale is found) or None. The overall scale is
    fixed so that the mean irradiance is the photos' mean luminance times pi (the albedo absorbs the rest).
    """
    from matcap.refine.linear import solve_normals

    y = np.asarray(luminance, np.float64)
    d = np.asarray(directions, np.float64)
    level = max(float(y.mean()) * math.pi, 1e-9)
    if relative is not None:
        rel = np.asarray(relative, np.float64)
        return rel * level / max(float(rel.mean()), 1e-12)
    e = np.full(len(d), level)
    for _ in range(rounds):
        n, alb, solved = solve_normals(y, d * e[:, None], normal)
        if solved.sum() < 16:
            break
        shading = np.clip((n[solved] @ d.T), 0.0, None).T * alb[solved][None]  # (K, P) per unit irradiance
        lit = shading > 0.05 * np.maximum(shading.max(axis=1, keepdims=True), 1e-12)
        num = (y[:, solved] * shading * lit).sum(1)
        den = (shading ** 2 * lit).sum(1)
        e = np.clip(np.where(den > 1e-12, num / np.maximum(den, 1e-12), e), 1e-6, None)
        e *= level / e.mean()
    return e


class _Adam:
    """torch's Adam update (:func:`torch.optim.adam.adam`, the function :class:`torch.optim.Adam` steps with, at its
    defaults: betas 0.9 / 0.999, eps 1e-8, no weight decay) over parameter groups ``[(tensors, lr), ...]``, with
    the optimizer's interface (``zero_grad``, ``step``). The optimizer class itself is not used: its first
    construction in a process imports ``torch._dynamo``, about 1.3 s on a 2-core machine, as long as a light fit."""

    def __init__(self, torch, groups):
        self.torch = torch
        self.groups = [(list(tensors), float(lr)) for tensors, lr in groups]
        self.state = {id(t): (torch.zeros_like(t), torch.zeros_like(t), torch.tensor(0.0))
                      for tensors, _ in self.groups for t in tensors}

    def zero_grad(self) -> None:
        for tensors, _ in self.groups:
            for t in tensors:
                t.grad = None

    def step(self) -> None:
        from torch.optim.adam import adam

        with self.torch.no_grad():
            for tensors, lr in self.groups:
                live = [t for t in tensors if t.grad is not None]
                if not live:
                    continue
                m, v, steps = zip(*(self.state[id(t)] for t in live))
                adam(live, [t.grad for t in live], list(m), list(v), [], list(steps), foreach=False,
                     capturable=False, differentiable=False, fused=None, grad_scale=None, found_inf=None,
                     has_complex=False, amsgrad=False, beta1=0.9, beta2=0.999, lr=lr, weight_decay=0.0, eps=1e-8,
                     maximize=False)


def _fit_lights(torch, prob: _Problem, lights, s: RefineSettings, bar, label: str, iters: int,
                maps_free: bool = True, smooth_tilt_held: int | None = None, ambient_free: bool = True):
    """Estimated lights: Adam on the lights, their directions (and a near lamp's distance) included, and, with
    ``maps_free``, on the subsample's maps, anchored by the prior, under the full loss :func:`_loss` of the pixels
    ``prob`` (the caller adds the steps to the progress total); the SH ambient too with ``ambient_free`` (and
    unless ``model.ambient`` is "none"). ``smooth_tilt_held``: a polynomial degree; the part
    of the pixels' normal gradients that such a polynomial in their plane positions explains is taken out at the
    start and after every step (a flat sample has no smooth tilt). Each step's loss and gradient are the sums of
    those of the two halves of the pixels, computed side by side where torch has two threads or more (each on
    one-thread operations), so the result does not depend on the thread count. Returns (lights, a copy without
    gradients; the last step's mean data term)."""
    from concurrent.futures import ThreadPoolExecutor

    from matcap.refine.model import PixelParams

    px = PixelParams.from_maps(prob.ns, prob.b0, prob.r0, prob.m0)
    light_t = ([lights.sh] if s.model.ambient != "none" and ambient_free else []) + [lights.log_intensity, lights.vec]
    light_t += [lights.inv_distance] if lights.kind == "near" else []
    groups = [(light_t, s.lights.lr)]
    if maps_free:
        groups.append((px.tensors(), s.lights.lr_pixel))
    smooth = None
    if smooth_tilt_held is not None and maps_free:  # (N, N) projection onto the polynomial fields of the plane
        x, y = prob.pos[:, 0], prob.pos[:, 1]
        basis = torch.stack([x ** i * y ** j for i in range(smooth_tilt_held + 1)
                             for j in range(smooth_tilt_held + 1 - i)], 1)
        smooth = (basis, torch.linalg.pinv(basis))
        px.grad -= smooth[0] @ (smooth[1] @ px.grad)
    leaves = [t for tensors, _ in groups for t in tensors]
    for t in leaves:
        t.requires_grad_(True)
    opt = _Adam(torch, groups)
    data_mean = float("nan")
    near = lights.kind == "near"
    n = len(prob)
    cut = (n + 1) // 2
    halves = [(sl, prob.part(sl)) for sl in (slice(0, cut), slice(cut, n)) if sl.stop > sl.start]

    def half(sl, part):
        """(loss sum / n, data sum, gradients of the loss by ``leaves``) of the pixels ``sl``."""
        hp = PixelParams(*(t[sl] for t in px.tensors()))
        per, data = _loss(torch, part, hp, lights, s, s.loss.cauchy, s.model.fit_brdf)
        loss = per.sum() / n
        grads = torch.autograd.grad(loss, leaves, allow_unused=True)
        return float(loss.detach()), float(data.detach().sum()), grads

    with _one_thread(torch) as threads:  # a few thousand pixels: too small an operation to share within
        pool = ThreadPoolExecutor(1, initializer=torch.set_num_threads, initargs=(1,)) if _workers(threads) > 1 \
            else None
        try:
            for _ in range(iters):
                later = pool.submit(half, *halves[1]) if pool is not None and len(halves) > 1 else None
                parts = [half(*halves[0])]
                parts += [later.result()] if later is not None else [half(*h) for h in halves[1:]]
                loss = sum(p[0] for p in parts)
                for i, t in enumerate(leaves):
                    gs = [p[2][i] for p in parts if p[2][i] is not None]
                    t.grad = sum(gs[1:], gs[0]) if gs else None
                opt.step()
                if smooth is not None:
                    with torch.no_grad():
                        px.grad -= smooth[0] @ (smooth[1] @ px.grad)
                if near:  # a negative inverse distance, or a direction behind the framing plane, would put the
                    with torch.no_grad():  # lamp where it lights nothing the camera sees
                        lights.inv_distance.clamp_(min=0.0)
                        lights.vec[:, 2].clamp_(min=1e-3)
                data_mean = sum(p[1] for p in parts) / n
                bar.step(label, loss)
        finally:
            if pool is not None:
                pool.shutdown(wait=True)
    for t in lights.tensors():
        t.requires_grad_(False)
    return lights.detached(), data_mean


def _fit_intensities(torch, prob: _Problem, lights, s: RefineSettings, bar, relative_to=None,
                     power_held: bool = False, mean_held: bool = False, level_free: bool = False,
                     ambient_free: bool = True):
    """Lights whose directions (and a near lamp's distance) are known: their log intensities (K, 3) (with
    ``relative_to`` (K, 3) log intensities, only one overall log scale, the colours and ratios held; with
    ``power_held`` as well, none: ``lights``' intensities are kept as they are) and the
    ambient's orders up to ``lights.known_ambient_order`` (with ``ambient_free`` and unless ``model.ambient`` is
    "none"; its higher orders held), fitted with the maps of the pixels ``prob``
    (anchored by the prior) under the loss of :func:`_loss`: Levenberg-Marquardt on the whole
    (:func:`matcap.refine.solve.joint_levenberg_marquardt`; the intensities and the ambient are parameters every
    pixel shares, each pixel's maps its own), ``lights.known_iters`` iterations at most. ``mean_held``: the pixels'
    mean normal gradient is held at 0 (a flat sample's mean normal is the camera axis). ``level_free``: the base
    colour's prior holds its pattern only, one factor on the networks' base colour solved with the rest (the
    photos then set the lights' overall power). Returns (lights, a copy without gradients; that factor (1 where
    not free); iterations done)."""
    from matcap.refine.model import SH_A, PixelParams, sh_basis, sh_irradiance
    from matcap.refine.solve import joint_levenberg_marquardt

    px = PixelParams.from_maps(prob.ns, prob.b0, prob.r0, prob.m0)
    theta, residuals, jacobian, _ = _pixel_residuals(torch, prob, px.tensors(), s)
    k_count = prob.obs.shape[0]
    dev = theta.device
    ambient = ambient_free and s.model.ambient != "none"
    n_sh = lights.sh.shape[0]
    entry = torch.arange(k_count * 3, device=dev)  # a residual entry k * 3 + c: photo k, channel c
    photo, channel = entry // 3, entry % 3
    if relative_to is None:
        start, cols_i = lights.log_intensity.reshape(-1), entry
    elif power_held:
        start, cols_i = lights.log_intensity.new_zeros(0), None
    else:
        start, cols_i = (lights.log_intensity - relative_to).mean().reshape(1), torch.zeros_like(entry)
    n_i = start.shape[0]
    # the ambient's low orders alone move (lights.known_ambient_order): its order 2 would bend to fit what the model
    # misses (a cast shadow, an interreflection) rather than a room's light
    order = s.lights.known_ambient_order
    if order not in (0, 1, 2):
        raise MatcapError(f"fit setting 'lights.known_ambient_order' takes 0, 1 or 2, not {order}")
    terms = (1, 4, 9)[order]
    shared = torch.cat([start, lights.sh[:, :terms].reshape(-1)]) if ambient else start
    if level_free:  # its last entry: the log of the factor on the networks' base colour
        shared = torch.cat([shared, shared.new_zeros(1)])
    n_light = shared.shape[0] - int(level_free)
    col_level = torch.tensor([n_light], device=dev)
    sh_photo = photo if n_sh > 1 else torch.zeros_like(photo)
    cols_sh = [n_i + (sh_photo * terms + j) * 3 + channel for j in range(terms)]

    every = torch.arange(len(prob), device=dev)

    def lights_of(v):
        log_i = (v[:n_i].reshape(k_count, 3) if relative_to is None else lights.log_intensity if power_held
                 else relative_to + v[0])
        sh = torch.cat([v[n_i:n_light].reshape(n_sh, terms, 3), lights.sh[:, terms:]], 1) if ambient else lights.sh
        return replace(lights, log_intensity=log_i, sh=sh)

    def level_of(v):
        return v[n_light] if level_free else None

    def flat(x):
        return x.permute(1, 0, 2).reshape(x.shape[1], -1)

    def jac(t, v):
        hl = lights_of(v)
        robust, q, jr, jq, st = jacobian(t, every, hl, state=True, level=level_of(v))
        albedo = ((1.0 - st["metal"])[:, None] * st["base"] / math.pi)[None]  # (1, N, 3)
        ambient_part = sh_irradiance(st["normal"], hl.sh) * albedo
        # d pred / d log intensity: the direct part
        slots = [] if cols_i is None else [(cols_i, flat((st["pred"] - ambient_part) * st["free"]))]
        if ambient:  # d pred / d sh_j: the albedo times A_j Y_j(n)
            basis = sh_basis(st["normal"])
            slots += [(cols_sh[j], flat(st["free"] * albedo * (SH_A[j] * basis[:, j])[None, :, None]))
                      for j in range(terms)]
        qslots = [(col_level.expand(q.shape[1]), st["d_level"])] if level_free else []
        return robust, q, jr, jq, slots, qslots

    def project(t):
        if not mean_held:
            return t
        return torch.cat([t[:, :2] - t[:, :2].mean(0), t[:, 2:]], 1)

    bar.add_total(s.lights.known_iters)
    with _one_thread(torch):
        _, shared, done = joint_levenberg_marquardt(
            lambda t, v: residuals(t, every, lights_of(v), level_of(v)), jac, theta, shared, prob.weight / 3.0,
            s.loss.cauchy, s.lights.known_iters, project=project, on_step=lambda loss: bar.step("lights", loss))
    bar.add_total(done - s.lights.known_iters)
    level = float(level_of(shared).exp()) if level_free else 1.0
    return lights_of(shared).detached(), level, done


# ----------------------------------------------------------------------------------------------- estimated lights


@dataclass
class Candidate:
    """One candidate light model of the estimated-lights path and what its fit found (:func:`_refine_estimated`).

    model: "distant" (distant lights) or "point" (a lamp per photo whose distance the fit finds), the first
    candidate, under the whole check; "near" (lamps whose distances the fit finds, starting from the networks'
    normals) or "glossy" (distant lamps under the Principled model alone), tried where the first failed only the
    check's residual / inliers part. lights: the fitted :class:`matcap.refine.model.LightParams` (fit units), None
    where the rule refused the candidate before its light fit. solved_fraction: share of the object's pixels that
    get a Lambertian normal facing the camera under the factorization's lights (None: not measured).
    ambient_share: share of the object's irradiance that the fixed ambient gives (near: measured on the light fit's
    pixels after the light fit; glossy: on every pixel after the per-pixel fit; None: not measured).
    distance_radii: median lamp distance in object radii (None: infinitely far, or not near lamps). loss_ratio: the
    near-lamp light fit's data term over that of distant lamps after as many steps (None: not measured).
    reason: why the rule refused the candidate (one line), None where accepted. final: that refusal holds for every
    later candidate (the photos themselves fail the check)."""

    model: str
    lights: Any = None
    solved_fraction: float | None = None
    ambient_share: float | None = None
    distance_radii: float | None = None
    loss_ratio: float | None = None
    reason: str | None = None
    final: bool = False

    def record(self) -> dict[str, Any]:
        """fit.json ``linear`` ``near_fit`` / ``principled_fit`` entry: what a refused later candidate found."""
        if self.lights is None:  # refused by the check before its fit
            return {"solved_fraction": self.solved_fraction}
        if self.model == "near":
            return {"ambient_share": self.ambient_share, "light_distance_radii": self.distance_radii,
                    "loss_ratio": self.loss_ratio, "solved_fraction": self.solved_fraction}
        return {"ambient_share": self.ambient_share, "solved_fraction": self.solved_fraction}


RECORD_KEYS = {"near": "near_fit", "glossy": "principled_fit"}  # fit.json ``linear`` key of a later candidate
CHECK_NAMES = {"near": "near lamps", "glossy": "principled"}  # fit.json ``linear`` ``check``: the one accepted


def candidate_models(s: RefineSettings) -> list[str]:
    """The estimated path's candidate light models, in the order they are tried (:class:`Candidate` ``model``):
    distant lights, then near lamps (``candidates.near``), then glossy distant lamps (``candidates.glossy``); with
    light model "point": point lamps, then near lamps judged on their ambient alone."""
    if s.model.light == "point":
        return ["point", "near"]
    return ["distant"] + (["near"] if s.candidates.near else []) + (["glossy"] if s.candidates.glossy else [])


@dataclass
class _Check:
    """The factorization and its check (:func:`_check`), shared by the candidates judged on the same part of it.

    whole: all of the check (the first candidate) or all but its residual / inliers part (the later ones); idx:
    the light fit's pixel subsample (indices into the light copy's object pixels); linear:
    :class:`matcap.refine.linear.LinearFit` or None (fewer than 4 photos); start (H, W, 3): the photos' calibrated
    normals under its lights, or None where the check failed before they were solved; report: fit.json ``linear``;
    reason: why the check refuses the photos, or None; lambertian_only: only the residual / inliers part failed."""

    whole: bool
    idx: np.ndarray
    linear: Any
    start: np.ndarray | None
    report: dict[str, Any]
    reason: str | None
    lambertian_only: bool

    def s_lum(self) -> np.ndarray:
        """(K, 3) the factorization's lights: direction times luminance irradiance."""
        return self.linear.directions * self.linear.irradiance[:, None]


def _check(ph: _Photos, s: RefineSettings, whole: bool) -> _Check:
    """The light stage's start with estimated lights: the light fit's pixel subsample, the Lambertian factorization
    of the light copy (:func:`_linear_lights`), its check (:func:`_distrust`; ``whole``: with its residual /
    inliers part) and, where its lights pass the check's first parts, the photos' calibrated normals under them."""
    rng = np.random.default_rng(s.seed)
    k_count = ph.obs.shape[0]
    _, (obs_l, mask_l, arr_l, _) = ph.light_copy(s.lights.side)
    n_l = int(mask_l.sum())
    idx = np.sort(rng.choice(n_l, size=min(n_l, s.lights.pixels), replace=False))
    linear = _linear_lights(obs_l, mask_l, arr_l, s, rng, whole) if k_count >= 4 else None
    start, report = None, {}
    if _distrust(k_count, linear, None, s, whole) is None:  # start (and prior) normals from the photos' lights
        start, report = _photo_normals(ph.obs, ph.mask, ph.arrays["normal"],
                                       linear.directions * linear.irradiance[:, None])
    reason = _distrust(k_count, linear, report.get("solved_fraction"), s, whole)
    lambertian_only = reason is not None and whole and _distrust(k_count, linear, None, s, False) is None
    report = {**report, "trusted": reason is None, **({"reason": reason} if reason else {}),
              **({"lambertian_only": True} if lambertian_only else {})}
    if linear is not None:
        report.update(contour_pixels=linear.contour_pixels, residual=round(linear.residual, 4),
                      inliers=round(linear.inliers, 4), spread=round(linear.spread, 5))
    return _Check(whole, idx, linear, start, report, reason, lambertian_only)


@dataclass
class _LightStage:
    """The light stage's result for one candidate (:func:`_light_stage`).

    lights: :class:`matcap.refine.model.LightParams` in fit units; trusted: the maps may move (else the lights were
    fitted to the networks' maps, which are kept); arrays: the per-pixel stage's priors ("normal" the start normals
    where trusted); start (H, W, 3) start normals or None (the priors'); near: lamps whose distances were fitted;
    distance: their median distance in half-widths of the frame (None: infinitely far); found: the near-lamp
    findings for fit.json ``near_lamps`` (ambient_share, light_distance_radii, loss_ratio, solved_fraction) or
    None; iters: light-fit steps run; bar: the candidate's progress; seconds: the stage's time."""

    lights: Any
    trusted: bool
    arrays: dict[str, np.ndarray]
    start: np.ndarray | None
    near: bool
    distance: float | None
    found: dict[str, Any] | None
    iters: int
    bar: Any
    seconds: float


def _light_stage(torch, ph: _Photos, chk: _Check, model: str, s: RefineSettings, progress) -> _LightStage:
    """The lights of candidate ``model`` on the light copy (:func:`_fit_lights`): from the factorization's lights
    where the check ``chk`` passed (the subsample's maps free), else from the networks' maps (kept, fixed). Lamps
    ("point", "near") then come in from infinitely far; for "near" the ambient share, the lamps' distance in object
    radii and, where the rule needs it (:func:`_needs_loss_ratio`), the loss ratio against distant lamps fitted as
    long again are measured."""
    t0 = time.perf_counter()
    device = torch.device(s.device)
    torch.manual_seed(s.seed)
    near, gate = model in ("point", "near"), model == "near"
    bar = _Bar(progress, s, near)
    h, w = ph.mask.shape
    hw_l, (obs_l, mask_l, arr_l, w_l) = ph.light_copy(s.lights.side)
    trusted = chk.reason is None
    arrays, start, start_l = ph.arrays, None, None
    if trusted and model != "near":  # the distant lamps' photo normals carry near lamps' falloff: near lamps start
        start = chk.start  # from the networks' normals (a near-lit dome 1.50 / 1.63 degrees, against 2.29 / 2.41)
        arrays = dict(arrays, normal=start)
        if hw_l == (h, w):
            arr_l, start_l = arrays, start
        else:
            start_l, _ = _photo_normals(obs_l, mask_l, arr_l["normal"], chk.s_lum(), chk.report)
            arr_l = dict(arr_l, normal=start_l)
    prob = _Problem(torch, obs_l, mask_l, arr_l, w_l, ph.sat_level, device, chk.idx, start_l)
    lights = _init_lights(torch, prob, s, device, chk.linear.directions if trusted else None)

    def joint(lights, iters, label):  # kept maps: the lights are fitted to them as they are
        return _fit_lights(torch, prob, lights, s, bar, label, iters, maps_free=trusted)

    iters = s.lights.iters if trusted else s.lights.kept_iters
    compare = gate and s.model.light != "point"  # the loss ratio needs distant lamps fitted as long
    bar.add_total(iters - s.lights.iters + (s.lights.iters if compare else 0))
    lights, _ = joint(lights, iters, "lights")
    found = dist = None
    if near:  # the lamps' distances, from the distant solution
        distant_lights = lights
        lights, near_data = joint(_to_near(torch, lights, _centre(torch, ph.mask).to(device)), s.lights.iters,
                                  "point lights")
        iters += s.lights.iters
        dist = _median_distance(lights)
        if gate:
            with torch.no_grad():
                share = ambient_share(torch, lights, prob.pos, prob.ns)
            found = {"ambient_share": round(share, 4),
                     "light_distance_radii": None if dist is None else round(dist / _object_radius(ph.mask), 2),
                     "loss_ratio": None, "solved_fraction": chk.report.get("solved_fraction")}
            if compare and _needs_loss_ratio(found, s):
                _, distant_data = joint(distant_lights.detached(), s.lights.iters, "distant lights")
                found["loss_ratio"] = round(near_data / max(distant_data, 1e-12), 4)
                iters += s.lights.iters
            elif compare:
                bar.add_total(-s.lights.iters)
    return _LightStage(lights, trusted, arrays, start, near, dist, found, iters, bar, time.perf_counter() - t0)


def _judge(c: Candidate, chk: _Check, earlier: list[Candidate], s: RefineSettings) -> tuple[str | None, bool]:
    """The rule of the estimated-lights path: (why candidate ``c`` may not move the maps, None where it may; whether
    that refusal holds for every later candidate too). A finding not measured yet (None) refuses nothing:
    :func:`_refine_estimated` applies the rule before a candidate's fit, after its light fit and after its per-pixel
    fit, and stops it at the first refusal.

    1. The factorization's check ``chk`` (:func:`_distrust`): the first candidate must pass all of it; the later
       ones, tried only where the first failed on residual / inliers alone, all but that part, and where they fail
       it, every later one does.
    2. Near lamps: :func:`_near_verdict` (their distance, the ambient share, the loss ratio).
    3. Glossy distant lamps: the fixed ambient of their own fit and of the near-lamp fit before them at most
       ``candidates.glossy_ambient`` of the object's irradiance, ``candidates.glossy_ambient_far`` where the
       near-lamp fit left the lamps ``far_distance`` object radii away or more (or infinitely far)."""
    if chk.reason is not None:
        return chk.reason, not chk.lambertian_only
    if c.model == "near" and c.ambient_share is not None:
        return _near_verdict({"light_distance_radii": c.distance_radii, "ambient_share": c.ambient_share,
                              "loss_ratio": c.loss_ratio}, s), False
    if c.model == "glossy":
        cs = s.candidates
        near = next((e for e in earlier if e.model == "near" and e.ambient_share is not None), None)
        far = near is not None and (near.distance_radii is None or near.distance_radii >= cs.far_distance)
        limit = max(cs.glossy_ambient, cs.glossy_ambient_far) if far else cs.glossy_ambient
        if near is not None and near.ambient_share > limit:
            return (f"the near-lamp fit needed a fixed ambient of {near.ambient_share:.0%} of the light (distant "
                    f"lamps tried up to {limit:.0%})"), False
        if c.ambient_share is not None and c.ambient_share > limit:
            return (f"the Principled fit needed a fixed ambient of {c.ambient_share:.0%} of the light (trusted up "
                    f"to {limit:.0%}): not one light per photo"), False
    return None, False


def _near_verdict(found: dict, s: RefineSettings) -> str | None:
    """Why a near-lamp fit's lamps may not move the maps (one line), or None
    (:class:`matcap.refine.settings.CandidateSettings` ``near_*``).
    ``found``: light_distance_radii (None: infinitely far), ambient_share, loss_ratio (None: not measured, with
    light model "point", where only the ambient counts, or where :func:`_needs_loss_ratio` says it cannot
    change the verdict)."""
    radii, share, ratio = found["light_distance_radii"], found["ambient_share"], found["loss_ratio"]
    cs = s.candidates
    point = s.model.light == "point"
    if not point and (radii is None or radii > cs.near_distance):
        return (f"the lamps came out {'infinitely far' if radii is None else f'{radii:.1f} object radii'} away "
                f"(near from {cs.near_distance:g})")
    if share > cs.near_ambient:
        return (f"the near-lamp fit needed a fixed ambient of {share:.0%} of the light (trusted up to "
                f"{cs.near_ambient:.0%}): not one lamp per photo")
    if not point and ratio is not None and ratio > cs.near_loss_ratio and share > cs.near_dark:
        return (f"the lamps' distances explain little (the fit's loss {ratio:.0%} of distant lamps', trusted up to "
                f"{cs.near_loss_ratio:.0%}) under a fixed ambient of {share:.0%} (trusted whatever the loss up to "
                f"{cs.near_dark:.0%})")
    return None


def _needs_loss_ratio(found: dict, s: RefineSettings) -> bool:
    """Whether :func:`_near_verdict` turns on the loss ratio for these findings (it costs ``lights.iters`` more
    joint steps): only for lamps near enough, under an ambient neither too strong nor a dark room's."""
    radii, share, cs = found["light_distance_radii"], found["ambient_share"], s.candidates
    return radii is not None and radii <= cs.near_distance and cs.near_dark < share <= cs.near_ambient


def _object_radius(mask: np.ndarray) -> float:
    """Radius of the disc as large as the mask, in half-widths of the framing plane (:func:`plane_positions`)."""
    return max(math.sqrt(float(np.count_nonzero(mask)) / math.pi) * 2.0 / mask.shape[1], 1e-6)


#: Why a flat sample under distant lamps keeps the networks' maps (fit.json ``linear`` ``reason``).
FLAT_DISTANT = ("a flat sample under distant lamps: its photos hold its relief only up to the relief's sign and "
                "depth (the lamps' falloff over it did not place them), so its normal map is the plane's (the camera "
                "axis)")


def _refine_estimated(torch, images, maps: MaterialMaps, s: RefineSettings, progress,
                      keep: str | None = None) -> RefineResult:
    """The fit with estimated lights. Stages: (1) the photos (:func:`_prepare`); (2) lights: the candidate light
    models of :func:`candidate_models` in order, each fitted (:func:`_check`, :func:`_light_stage`) as far as the
    rule :func:`_judge` lets it; (3) the first accepted candidate's per-pixel solve and (4) outputs
    (:func:`_finish`; a glossy candidate is judged on its ambient share after them). Where none is accepted, the
    networks' maps are kept, the first candidate's lights fitted to them, with every reason once. ``keep``: a
    reason known before any check (:data:`FLAT_DISTANT`): the maps are kept for it, the lights fitted to them.

    The result's ``candidates``: every candidate judged, in order."""
    if s.model.light not in ("directional", "point"):
        raise MatcapError(f"light model must be 'directional' or 'point', got {s.model.light!r}")
    t_start = time.perf_counter()
    ph = _prepare(images, maps, s)
    checks: dict[bool, _Check] = {}
    tried: list[Candidate] = []
    if keep is not None:
        chk = _check(ph, s, True)
        report = {k: v for k, v in chk.report.items() if k != "lambertian_only"}
        chk = replace(chk, reason=keep, report={**report, "trusted": False, "reason": keep}, lambertian_only=False)
        tried.append(Candidate(candidate_models(s)[0], reason=keep, final=True))
        stage = _light_stage(torch, ph, chk, tried[0].model, s, progress)
        return _kept(_finish(torch, ph, maps, chk, stage, s, t_start), tried)
    for model in candidate_models(s):
        whole = not tried
        chk = checks[whole] = checks.get(whole) or _check(ph, s, whole)
        c = Candidate(model, solved_fraction=chk.report.get("solved_fraction"))
        tried.append(c)
        c.reason, c.final = _judge(c, chk, tried[:-1], s)
        if c.reason is None:
            stage = _light_stage(torch, ph, chk, model, s, progress)
            c.lights = stage.lights
            if stage.found is not None:
                c.ambient_share, c.distance_radii, c.loss_ratio = (
                    stage.found[k] for k in ("ambient_share", "light_distance_radii", "loss_ratio"))
            c.reason, c.final = _judge(c, chk, tried[:-1], s)
            if c.reason is not None:
                stage.bar.close()
            else:
                result = _finish(torch, ph, maps, chk, stage, s, t_start)
                if model == "glossy":
                    c.ambient_share = result.report["ambient_share"]
                    c.reason, c.final = _judge(c, chk, tried[:-1], s)
                if c.reason is None:
                    return _accepted(result, tried)
        if c.final:
            break
    kept = _finish(torch, ph, maps, checks[True], _light_stage(torch, ph, checks[True], tried[0].model, s, progress),
                   s, t_start)
    return _kept(kept, tried)


def _accepted(result: RefineResult, tried: list[Candidate]) -> RefineResult:
    """``result``, the fit of the accepted candidate ``tried[-1]``, with the candidates before it in fit.json
    ``linear`` (``check``, ``reason_lambertian``, what the refused later ones found, ``reason_near``)."""
    c, first, refused = tried[-1], tried[0], tried[1:-1]
    if c is not first:
        lin = result.report["linear"]
        near = [e.reason for e in refused if e.model == "near"]
        result.report["linear"] = {**lin, "check": CHECK_NAMES[c.model], "reason_lambertian": first.reason,
                                   **_records(refused), **({"reason_near": near[-1]} if near else {})}
    result.candidates = tried
    return result


def _kept(result: RefineResult, tried: list[Candidate]) -> RefineResult:
    """``result``, the networks' maps kept under the first candidate's lights, with every refused later
    candidate's reason once in fit.json ``linear`` ``reason`` and what they found."""
    later = tried[1:]
    if later:
        lin = result.report["linear"]
        extra = [r for r in dict.fromkeys(e.reason for e in later) if r and r not in lin["reason"]]
        result.report["linear"] = {**lin, **({"reason": f"{lin['reason']}; without that part of the check: "
                                                         + "; ".join(extra)} if extra else {}), **_records(later)}
    result.candidates = tried
    return result


def _records(later: list[Candidate]) -> dict[str, Any]:
    """fit.json ``linear`` entries of refused later candidates that had findings of their own: a fit, or the
    check's solved fraction (not those refused on an earlier candidate's findings before any fit)."""
    return {RECORD_KEYS[e.model]: e.record() for e in later if e.lights is not None or e.final}


def _finish(torch, ph: _Photos, maps: MaterialMaps, chk: _Check, stage: _LightStage, s: RefineSettings,
            t_start: float) -> RefineResult:
    """The per-pixel stage (:func:`_solve_maps`; none where the maps are kept) and the outputs (:func:`_outputs`)
    under the lights of ``stage``, and fit.json; ``t_start``: the fit's start (``timings`` ``total_s``)."""
    mask, scale = ph.mask, ph.scale
    timings: dict[str, float] = {"lights_s": stage.seconds}
    t0 = time.perf_counter()
    coarse_iters, fine_iters = (s.pixels.coarse_iters, s.pixels.fine_iters) if stage.trusted else (0, 0)
    full, px_full, mixing, iters_done = _solve_maps(torch, ph.obs, mask, stage.arrays, ph.weight, ph.sat_level,
                                            stage.start, stage.lights, s, stage.bar, coarse_iters, fine_iters)
    timings["maps_s"] = time.perf_counter() - t0
    stage.bar.close()
    t0 = time.perf_counter()
    out = _outputs(torch, full, px_full, stage.lights, s, scale, maps, keep=not stage.trusted, mixing=mixing)
    timings["outputs_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    report = {
        "psnr_db": [round(p, 3) for p in out.psnr],
        "psnr_db_mean": round(float(np.mean(out.psnr)), 3),
        "residual_mean": round(float(np.nanmean(out.residual)), 5),
        "iterations": {"lights": stage.iters, **iters_done},
        "pixels": int(mask.sum()),
        "images": ph.obs.shape[0],
        "normal_change_deg_mean": round(out.normal_change_deg, 3),
        "light_variation": {"threshold": s.loss.variation_threshold, "weak_fraction": round(ph.weak_fraction, 4),
                            "warning": ph.warning},
        "photo_scale": scale,
        "linear": dict(chk.report),
        "kept_network_maps": not stage.trusted,
        "ambient_share": round(out.ambient_share, 4),
        "outline": _outline_record(torch, mixing),
        **({"light_distance_median": stage.distance} if stage.near else {}),
        **({"near_lamps": stage.found} if stage.found is not None else {}),
        "timings": {k: round(v, 3) for k, v in timings.items()},
        "settings": asdict(s),
    }
    return RefineResult(out.maps, lights_to_entries(stage.lights, scale), report, out.residual, ph.variation,
                        ph.warning, out.prediction)


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
    full = _Problem(torch, obs, mask, arrays, weight, sat_level, device, start=start, shadow=shadow)
    px_full = PixelParams.from_maps(full.ns, full.b0, full.r0, full.m0)
    iters_done = {"coarse": 0, "fine": 0}
    if coarse_iters > 0 and max(h, w) > 128:
        hw_c = (max(8, h // 2), max(8, w // 2))
        obs_c, mask_c, arr_c = _downsample(obs, mask, arrays if start is None else dict(arrays, start=start), hw_c)
        coarse = _Problem(torch, obs_c, mask_c, arr_c, _resize(weight, hw_c), sat_level, device,
                          start=arr_c.get("start"), shadow=shadow)
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





@dataclass
class _Outputs:
    """The last stage's results: maps (the fitted ones, or the networks' where kept); residual (H, W) RMS
    re-render error / the photos' mean (NaN off-mask); psnr per photo (dB); prediction (K, H, W, 3) re-renders in
    photo units; ambient_share (see :func:`ambient_share`); normal_change_deg: mean angle to the networks';
    shadowed_share: share of the observations taken as cast shadow (``loss.shadow``), which, like clipped ones,
    add no error where the re-render exceeds them."""

    maps: MaterialMaps
    residual: np.ndarray
    psnr: list[float]
    prediction: np.ndarray
    ambient_share: float
    normal_change_deg: float
    shadowed_share: float


def _outputs(torch, full: _Problem, px, lights, s: RefineSettings, scale: float, maps: MaterialMaps,
             keep: bool = False, mixing: "_Mixing | None" = None) -> _Outputs:
    """Re-render the photos under the fitted ``lights`` and maps ``px`` of the pixels ``full`` (the outline's
    pixels mixed with what lies behind them, ``mixing``) and assemble the output maps (``keep``: the networks'
    maps, bit for bit, while the residual still describes the fit)."""
    mask = np.asarray(maps.mask, bool)
    h, w = mask.shape
    k_count = full.obs.shape[0]
    n_img = np.zeros((h, w, 3), np.float32)
    base = np.zeros((h, w, 3), np.float32)
    rough = np.zeros((h, w), np.float32)
    metal = np.zeros((h, w), np.float32)
    with torch.no_grad():
        n_img[full.rows, full.cols] = px.normal().cpu().numpy()
        base[full.rows, full.cols] = px.base().cpu().numpy()
        rough[full.rows, full.cols] = (px.rough() if s.model.fit_brdf else full.r0).cpu().numpy()
        metal[full.rows, full.cols] = (px.metal() if s.model.fit_brdf else full.m0).cpu().numpy()
    # re-rendered chunk by chunk of pixels: the photos' size of memory once (the prediction), not once per step
    prediction = np.zeros((k_count, h, w, 3), np.float32)
    residual = np.full((h, w), np.nan, np.float32)
    squared = np.zeros(k_count, np.float64)  # per photo: the sum of squared residuals
    peaks = np.zeros((k_count, len(full)), np.float32)  # per photo and pixel: the brightest channel observed
    shadowed, ambient, direct = 0, 0.0, 0.0
    mix = None if mixing is None else mixing.mixer(torch, len(full))
    for i in range(0, len(full), s.pixels.chunk):
        sl = slice(i, i + s.pixels.chunk)
        part, part_px = full.part(sl), px.take(sl)
        pred = _predict(torch, part, part_px, lights, s)  # (K, n, 3) fit units
        if mix is not None:
            pred = mix(pred, sl)
        obs_px = part.obs.cpu().numpy()
        err = pred - obs_px
        upper = part.upper.cpu().numpy()
        # a clipped observation (upper 0) only bounds the model from below, a shadowed one from above
        over = err > upper
        shadowed += int((over & (upper > 0)).sum())
        err[over] = 0.0
        residual[part.rows, part.cols] = np.sqrt((err ** 2).mean(axis=(0, 2))) / 0.5
        squared += (err.astype(np.float64) ** 2).sum(axis=(1, 2))
        peaks[:, sl] = obs_px.max(axis=2)
        prediction[:, part.rows, part.cols] = pred / scale
        with torch.no_grad():
            a, d = _irradiance_parts(torch, lights, part.pos, part_px.normal())
        ambient, direct = ambient + a, direct + d
    psnr = []
    for k in range(k_count):
        peak = float(np.percentile(peaks[k], 99.9))
        mse = float(squared[k] / max(3 * len(full), 1))
        psnr.append(10.0 * math.log10(peak ** 2 / max(mse, 1e-12)) if peak > 0 else float("nan"))
    share = ambient / max(ambient + direct, 1e-12)
    shadowed_share = shadowed / max(k_count * len(full) * 3, 1)
    if keep:  # the photos cannot correct the networks' maps: they are kept, bit for bit
        n_img = np.asarray(maps.normal, np.float32).copy()
        kept = maps.with_defaults()
        base, rough, metal = (np.asarray(v, np.float32).copy() for v in (kept.base_color, kept.roughness,
                                                                        kept.metallic))
    refined = MaterialMaps(normal=n_img, mask=mask, base_color=base,
                           roughness=rough if (maps.roughness is not None or s.model.fit_brdf) else None,
                           metallic=metal if (maps.metallic is not None or s.model.fit_brdf) else None,
                           height=None, meta=dict(maps.meta))
    network = _maps_arrays(maps)["normal"]
    change = np.degrees(np.arccos(np.clip((n_img[mask] * network[mask]).sum(-1), -1, 1)))
    return _Outputs(refined, residual, psnr, prediction, share, float(change.mean()), shadowed_share)


def _median_distance(lights) -> float:
    """Median distance of near lights from the object's centre, in half-widths of the framing plane (inf: at
    None: at least half of them are distant, farther than 10^6)."""
    u = float(lights.inv_distance.clamp(min=0.0).median())
    return round(1.0 / u, 3) if u > 1e-6 else None


def ambient_share(torch, lights, pos, normal) -> float:
    """Share of the object's irradiance (luminance, mean over pixels and photos) that the fixed SH ambient gives
    against the photos' own lights: near 0 for one lamp per photo in a dark room, large for environment light.

    lights: :class:`matcap.refine.model.LightParams`; pos (N, 3) plane positions; normal (N, 3) unit normals."""
    a, d = _irradiance_parts(torch, lights, pos, normal)
    return a / max(a + d, 1e-12)


def _irradiance_parts(torch, lights, pos, normal) -> tuple[float, float]:
    """(ambient, direct): the luminance irradiance of the SH ambient and of the photos' own lights at the pixels
    ``pos`` (N, 3) with ``normal`` (N, 3), each summed over the pixels and averaged over the photos."""
    from matcap.refine.model import sh_irradiance

    luma = torch.tensor(LUMA, dtype=normal.dtype, device=normal.device)
    amb = (sh_irradiance(normal, lights.sh) * luma).sum(-1).clamp(min=0.0)  # (K|1, N)
    wo, irr = lights.incident(pos)
    direct = (normal[None] * wo).sum(-1).clamp(min=0.0) * (irr * luma).sum(-1)  # (K, N)
    return float(amb.mean(0).sum()), float(direct.mean(0).sum())


class _Stopped(Exception):
    """A chunk of the per-pixel solve abandoned because another one failed or the fit was interrupted."""


@contextlib.contextmanager
def _one_thread(torch):
    """torch's operations on one thread inside the block (its own setting restored after): the fit's operations are
    many and small, and a team of OpenMP threads meets at a barrier after each; where another job holds a core, the
    team waits for the thread it lost at every operation (and spins while it waits)."""
    was = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield was
    finally:
        torch.set_num_threads(was)


def _workers(threads: int) -> int:
    """Threads for the per-pixel solve's chunks: torch's thread count, at most the CPUs this process may use."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return max(1, min(threads, cpus))


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

    theta, residuals, jacobian, unpack = _pixel_residuals(torch, part, start, s)
    theta = levenberg_marquardt(lambda t, rows: residuals(t, rows, lights), theta, part.weight / 3.0, c, iters,
                                on_step=on_step, tol=s.pixels.tol, jacobian=lambda t, rows: jacobian(t, rows, lights))
    return unpack(theta)


def _pixel_residuals(torch, part: _Problem, start, s):
    """:func:`_loss` of the pixels ``part`` as residuals for Levenberg-Marquardt: the same data term (Cauchy,
    clipped highlights a lower bound only, weighted per pixel and averaged over the colour channels) and the same
    priors. ``start``: the four :class:`PixelParams` tensors, and where the pixels mix the object with what lies
    behind them (``part.backdrop``) their coverage logits. Such a pixel's model is coverage x the Principled model
    + (1 - coverage) x the backdrop, with a prior (``priors.cover``) on 1 - coverage.

    Returns (theta (N, P): the parameters as one array; residuals(theta, rows, lights) -> (robust (n, K * 3),
    entry k * 3 + c photo k's channel c; quadratic); jacobian(theta, rows, lights, state=False) -> those with
    their derivatives (:func:`matcap.refine.solve.levenberg_marquardt`'s ``jacobian``), and with ``state`` a
    fifth value, the model's pieces {"normal", "base", "metal" (n,), "pred" (K, n, 3), "free" (K, n, 3) 0 / 1,
    "d_level" (n, Q): the priors' derivatives by ``level``}; unpack(theta) -> the tensors of ``start``). ``level``
    (a scalar tensor, or None for 0): the log of a factor on the networks' base colour in its prior.)"""
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

    def jacobian(t, rows, lights, state=False, level=None):
        sub, px, nrm, b, r, m = pixels(t, rows)
        count = len(t)
        # the unit normal's derivatives by its gradient parameters: (e_x - n n_x) / |v|, (e_y - n n_y) / |v|
        size = torch.cat([px.grad, torch.ones_like(px.grad[:, :1])], 1).norm(dim=-1, keepdim=True)
        axes = torch.eye(3, dtype=t.dtype, device=t.device)[:2, None, :]
        tangents = (axes - nrm[None] * nrm.T[:2, :, None]) / size[None]
        wo, irr = lights.incident(sub.pos)
        pred, d_n, d_b, d_r, d_m = shade_jacobian(nrm, b, r, m, wo, irr, lights.sh, tangents)
        if mixed:  # coverage a: the model's derivatives scale by a; d/d logit(a) = (pred - backdrop) a (1 - a)
            a = torch.sigmoid(t[:, ci])
            d_a = (pred - sub.backdrop) * (a * (1.0 - a))[None, :, None]
            a3 = a[None, :, None]
            pred, d_n, d_b, d_r, d_m = mix(t, sub, pred), d_n * a3[None], d_b * a3, d_r * a3, d_m * a3
        res = pred - sub.obs
        # a clipped observation the model exceeds: zero residual, no derivative (a product, not torch.where: the
        # model's values and derivatives are finite, and a product of floats is several times faster)
        free = _free(sub, res).to(t.dtype)
        flat = lambda x: (x * free).permute(1, 0, 2).reshape(count, -1)  # noqa: E731
        robust = flat(res)
        q = priors(sub, nrm, b, r, m, t, level)
        q_width = q.shape[1]
        jr = [flat(d_n[0]), flat(d_n[1])]
        jq = [torch.cat([roots[0] * tangents[i], t.new_zeros(count, q_width - 3)], 1) for i in range(2)]
        sb = b * (1.0 - b)  # sigmoid's derivative
        d_b = d_b * sb[None]
        for c in range(3):
            jr.append(flat(d_b * (channel == c).to(t.dtype)))
            col = t.new_zeros(count, q_width)
            col[:, 3 + c] = roots[1] * sb[:, c] / (b[:, c] + 0.02)
            jq.append(col)
        if brdf:
            for i, (d, v) in enumerate(((d_r, r), (d_m, m))):
                sv = v * (1.0 - v)
                jr.append(flat(d * sv[None, :, None]))
                col = t.new_zeros(count, q_width)
                col[:, 6 + i] = roots[2 + i] * sv
                jq.append(col)
        if mixed:
            jr.append(flat(d_a))
            col = t.new_zeros(count, q_width)
            col[:, q_width - 1] = -roots[4] * a * (1.0 - a)
            jq.append(col)
        if state:
            b0 = prior_base(sub, level)
            d_level = t.new_zeros(count, q_width)  # the base prior's derivative by the log of its level
            d_level[:, 3:6] = -roots[1] * b0 / (b0 + 0.02)
            return robust, q, jr, jq, {"normal": nrm, "base": b, "metal": m, "pred": pred, "free": free,
                                       "d_level": d_level}
        return robust, q, jr, jq

    def unpack(theta):
        out = [theta[:, 0:2], theta[:, 2:5]]
        out += [theta[:, 5], theta[:, 6]] if brdf else [rough_logit, metal_logit]
        out += [theta[:, ci]] if mixed else []
        return [t.contiguous() for t in out]

    channel = torch.arange(3, device=theta.device)
    return theta, residuals, jacobian, unpack


def _free(sub: _Problem, res):
    """(K, P, 3) True where an observation adds a residual: not a clipped one the model exceeds (a clipped photo
    only bounds the model from below) and not a cast-shadowed one the model exceeds enough (``sub.upper``)."""
    return res <= sub.upper


def _predict(torch, prob: _Problem, px, lights, s) -> np.ndarray:
    outs = []
    with torch.no_grad():
        for i in range(0, len(prob), s.pixels.chunk):
            sl = slice(i, i + s.pixels.chunk)
            part = prob.part(sl)
            r = px.rough()[sl] if s.model.fit_brdf else part.r0
            m = px.metal()[sl] if s.model.fit_brdf else part.m0
            outs.append(_shade(lights, part.pos, px.normal()[sl], px.base()[sl], r, m).cpu().numpy())
    return np.concatenate(outs, axis=1)


def lights_to_entries(lights, scale: float) -> list[dict[str, Any]]:
    """lights.json ``images`` entries (without index/file) in photo units from fitted :class:`LightParams`."""
    out = []
    inten = (lights.log_intensity.exp() / scale).detach().cpu().numpy()
    sh = (lights.sh / scale).detach().cpu().numpy()
    kinds = [lights.kind] * len(inten)
    vec = (lights.directions() if lights.kind in ("directional", "near") else lights.vec).detach().cpu().numpy()
    if lights.kind == "near":  # a point light at centre + direction / u (intensity: irradiance there * distance^2)
        u = lights.inv_distance.detach().cpu().numpy().clip(0.0, None)[:, None]
        near = u > 1e-6  # 0: the fit left the lamp infinitely far, a distant light
        ud = np.maximum(u, 1e-6)
        vec = np.where(near, lights.centre.detach().cpu().numpy()[None] + vec / ud, vec)
        inten = np.where(near, inten / ud ** 2, inten)
        kinds = ["point" if v else "directional" for v in near[:, 0]]
    for k in range(len(inten)):
        e = {"kind": kinds[k]}
        e["direction" if kinds[k] == "directional" else "position"] = [float(v) for v in vec[k]]
        e["intensity"] = [float(v) for v in inten[k]]
        e["sh"] = [[float(v) for v in row] for row in sh[min(k, len(sh) - 1)]]
        out.append(e)
    return out


class _Bar:
    """The fit's progress (``networks.progress``: a bar on a terminal, one line per stage in logs, with the stage's
    last loss), or a callback ``progress(label, done, total, loss)``. A stage is a run of steps with one label
    ("lights", "point lights", "maps 1/2", "maps")."""

    def __init__(self, progress, s: RefineSettings, near: bool = False, total: int | None = None):
        self.cb = progress if callable(progress) else None
        self.show = progress is True
        self.done = 0
        self.total = s.lights.iters * (2 if near else 1) if total is None else total
        self.stage = None
        self.bar = None
        self.loss = float("nan")

    def add_total(self, n: int) -> None:
        self.total += n

    def step(self, label: str, loss: float) -> None:
        self.done += 1
        if self.show:
            if label != self.stage:
                self._close_stage()
                from networks.progress import progress

                self.stage = label
                self.bar = progress(total=None, desc=f"fit {label}", unit="it")
            self.loss = loss
            self.bar.update(1)
        if self.cb is not None:
            self.cb(label, self.done, self.total, loss)

    def _close_stage(self) -> None:
        if self.bar is not None:
            if math.isfinite(self.loss):
                self.bar.set_postfix(loss=f"{self.loss:.4g}")
            self.bar.close()
            self.bar = None

    def close(self) -> None:
        self._close_stage()
        self.stage = None


def fit_light_only(image: np.ndarray, maps: MaterialMaps, settings: RefineSettings | None = None) -> dict[str, Any]:
    """Fit only the light of one photo (H, W, 3) to frozen ``maps`` (e.g. refined on the other photos): the
    held-out check. The light is fitted and the PSNR taken over the mask less its outline (``pixels.outline``:
    the maps describe the object alone, not its mixture with what lies behind it there). Returns {"psnr_db",
    "light": lights.json entry (photo units)}."""
    import torch

    s = settings or RefineSettings()
    mask = np.asarray(maps.mask, bool)
    stack = check_inputs([image, image], mask)[:1]
    mask = mask & ~outline_zone(mask, s.pixels.outline)
    if not mask.any():
        raise MatcapError("the mask is no wider than its outline: no pixel to check the light on")
    device = torch.device(s.device)
    torch.manual_seed(s.seed)
    scale = 0.5 / float(stack[:, mask].mean())
    obs = stack * scale
    sat = np.where(obs[0][mask].max(axis=0) > 0, obs[0][mask].max(axis=0) * 0.999, np.inf)[None].astype(np.float32)
    arrays = _maps_arrays(maps)
    full = _Problem(torch, obs, mask, arrays, np.ones(mask.shape, np.float32), sat, device)
    from matcap.refine.model import PixelParams

    px = PixelParams.from_maps(full.ns, full.b0, full.r0, full.m0)
    rng = np.random.default_rng(s.seed)
    idx = np.sort(rng.choice(len(full), size=min(len(full), 4 * s.lights.pixels), replace=False))
    sub = full.part(idx)
    px_sub = PixelParams(*(t[torch.from_numpy(idx)] for t in px.tensors()))
    lights = _init_lights(torch, sub, s, device)
    params = [lights.vec, lights.log_intensity] + ([lights.sh] if s.model.ambient != "none" else [])
    for t in params:
        t.requires_grad_(True)
    opt = _Adam(torch, [(params, s.lights.lr)])
    for _ in range(s.lights.iters):
        opt.zero_grad()
        per, _ = _loss(torch, sub, px_sub, lights, s, s.loss.cauchy, s.model.fit_brdf)
        per.mean().backward()
        opt.step()
    lights = lights.detached()
    pred = _predict(torch, full, px, lights, s)
    err = pred - full.obs.cpu().numpy()
    peak = float(np.percentile(full.obs.cpu().numpy()[0].max(axis=1), 99.9))
    psnr = 10.0 * math.log10(peak ** 2 / max(float((err ** 2).mean()), 1e-12))
    return {"psnr_db": psnr, "light": lights_to_entries(lights, scale)[0]}

"""The fit's light stage: each photo's light, known or estimated, fitted on a downsampled copy of the photos.

* known lights (a light file, a mirror ball): the directions held, each photo's intensity and one shared ambient
  fitted (:func:`known_irradiance`, :func:`_fit_intensities`); lamps found on a flat sample are placed again with
  the maps (:func:`_place_lamps`);
* estimated lights: the Lambertian factorization and its check (:func:`_check`, :mod:`matcap.refine.linear`),
  then the candidate light models of :func:`candidate_models` in order (:func:`_light_stage`), each a joint robust
  fit of the lights and of the maps of a pixel subsample (:func:`_fit_lights`), judged by one rule
  (:func:`_judge`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from matcap.errors import MatcapError
from matcap.refine.photos import (
    LUMA, _Bar, _Photos, _Problem, _centre, _loss, _luminance, _maps_arrays, _median_distance, _one_thread,
    _plane_normals, _predict, _workers, ambient_share, check_inputs, lights_to_entries,
)
from matcap.refine.pixel_stage import _known_subsample, _pixel_residuals, _stage_subsample, outline_zone
from matcap.refine.settings import RefineSettings
from scenes.materialmaps import MaterialMaps


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


@dataclass
class _KnownLightStage:
    """What the known lights' stage hands on: the lights and the per-pixel solve's start and priors.

    lights: :class:`matcap.refine.model.LightParams` in fit units, the directions (and positions) as given;
    arrays / arrays_copy: the priors of the full-size photos and of the light-fit copy (the networks' maps, the base
    colour at ``level``); start (H, W, 3) / start_copy: unit normals from calibrated photometric stereo; shadow:
    the cast-shadow rule's level (0: off); the rest as fit.json ``lights`` records them."""

    lights: Any
    arrays: dict[str, np.ndarray]
    start: np.ndarray
    arrays_copy: dict[str, np.ndarray]
    start_copy: np.ndarray
    shadow: float
    fitted: bool  # intensities (or their level) and ambient fitted, not taken as given
    ambient_free: bool
    ambient: str  # "fitted", "given" or "none"
    level: float  # the factor on the networks' base colour that the photos set (1: none)
    level_free: bool
    tilt_held: bool  # a flat sample's mean normal held to the camera axis
    power_held: bool
    iters: int
    solved_fraction: float


def _known_light_stage(torch, ph: _Photos, copy: tuple, known, flat: dict | None, s: RefineSettings, bar, rng,
                       device) -> _KnownLightStage:
    """The known lights' stage: the given directions (and point-light positions) held, each photo's intensity (or,
    where the file gives relative intensities, one overall scale, their colours held) and the low orders of one
    ambient shared by every photo fitted, first by least squares, then jointly with a subsample's maps under the
    Principled model (:func:`_fit_intensities`). On a flat sample whose given lights come without intensities the
    subsample's mean normal is held to the camera axis (``lights.flat_mean_held``) and the ambient as given; on one
    whose lights come with relative intensities the photos set their overall power, one factor on the networks'
    base colour solved with them (``lights.flat_level_free``; under distant lights the ambient held as given). On an
    object, distant lights whose intensities the file gives are taken as they are, at the least-squares scale, with
    the file's ambient (a ``lights.json``'s ``sh``; else none) at that scale. The per-pixel solve starts from
    semi-calibrated Lambertian normals (:func:`known_irradiance`, :func:`_photo_normals`).

    ph: the prepared photos (fit units); copy: ``ph.light_copy(s.lights.side)``, the light-fit copy ((h, w),
    (obs (K, h, w, 3), mask, priors, weight)); known: :class:`matcap.lightfiles.KnownLights`, one per photo; flat:
    what :func:`matcap.refine.flat.flat_lights` found, None for an object; rng: draws the pixel subsample."""
    hw_l, (obs_l, mask_l, arr_l, w_l) = copy
    mask, obs, arrays, sat_level, scale = ph.mask, ph.obs, ph.arrays, ph.sat_level, ph.scale
    h, w = mask.shape
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
    return _KnownLightStage(lights, arrays, start, arr_l, start_l, shadow, fitted, ambient_free, ambient, level,
                            level_free, tilt_held, power_held, light_iters, photo_report["solved_fraction"])


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

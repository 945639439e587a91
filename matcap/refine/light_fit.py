"""The light stage's fits that known and estimated lights share, on a downsampled copy of the photos: each
photo's light to start from (:func:`_init_lights`), the photos' calibrated normals under given lights
(:func:`_photo_normals`), a joint robust fit of the lights and of the maps of a pixel subsample (:func:`_fit_lights`)
and the intensities (and ambient) of lights whose directions are known (:func:`_fit_intensities`).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from matcap.errors import MatcapError
from matcap.refine.photos import LUMA, _Problem, _centre, _loss, _luminance, _one_thread, _workers
from matcap.refine.pixel_stage import _pixel_residuals
from matcap.refine.settings import RefineSettings


def _photo_normals(obs, mask, network, s_lum, report=None, positions=None, chunk: int = 1 << 18,
                   max_misfit: float | None = None, ambient: np.ndarray | None = None):
    """Calibrated photometric-stereo normals (H, W, 3) of the photos ``obs`` (K, H, W, 3) under the lights
    ``s_lum`` (K, 3: direction times luminance irradiance at the object's centre): robust Lambertian least squares
    where a pixel is lit in 4 photos or more (and, given ``max_misfit``, where the Lambertian model's RMS misfit
    over the photos that light it is at most that share of its mean brightness), the networks' normals
    ``network`` elsewhere. ``positions`` (K, 3): the lamps' positions on the framing plane's world units (near
    lamps): each pixel then gets its own direction toward each lamp and the irradiance falls off with the squared
    distance; ``ambient`` (4,): a room's light that every photo shares (see
    :func:`matcap.refine.linear.solve_normals`), or None. They are both the start and the prior of the per-pixel
    stage. Returns (normals, report:
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
        n, albedo, solved = solve_normals(lum, lights, network[r, c], ambient=ambient)
        if max_misfit is not None:
            room = 0.0 if ambient is None else (ambient[0] + n.astype(np.float64) @ ambient[1:])[None]
            shade = (np.clip(lambertian_shading(lights, n), 0.0, None) + room) * albedo[None]
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


def _median_angle_deg(torch, before, after) -> float:
    """Median angle (degrees) between two sets of lights' directions (K, 3), seen from their centre."""
    cos = (before.directions() * after.directions()).sum(-1).clamp(-1.0, 1.0)
    return round(float(torch.rad2deg(torch.arccos(cos)).median()), 3)


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
    theta, residuals, jacobian, _, _ = _pixel_residuals(torch, prob, px.tensors(), s)
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

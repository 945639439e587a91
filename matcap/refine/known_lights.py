"""The light stage with known lights (a light file, a mirror ball, the lamps found on a flat sample): the
directions held, each photo's intensity and one shared ambient fitted (:func:`known_irradiance`,
:func:`_known_light_stage`); lamps found on a flat sample are placed again with the maps (:func:`_place_lamps`) and
their intensities fitted again (:func:`_refit_intensities`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from matcap.refine.light_fit import _fit_intensities, _fit_lights, _init_lights, _photo_normals, _to_near
from matcap.refine.photos import LUMA, _Photos, _Problem, _centre, _luminance, _plane_normals
from matcap.refine.pixel_stage import _known_subsample, _stage_subsample
from matcap.refine.settings import RefineSettings


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


def known_irradiance(luminance: np.ndarray, directions: np.ndarray, normal: np.ndarray,
                     relative: np.ndarray | None = None, rounds: int = 4, ambient_order: int | None = 1,
                     pixels: int = 2048, min_share: float = 0.0) -> tuple[np.ndarray, np.ndarray, float | None]:
    """Per-photo irradiance (K,) of lights whose directions are known, and a room's light that every photo shares,
    as the start of the light fit. The room's light first (:func:`_room_light`, on up to ``pixels`` pixels
    solved under equal lamps); then robust Lambertian normals under the lights and that room's light
    (:func:`matcap.refine.linear.solve_normals`: shadows and highlights weigh little) alternated ``rounds`` times
    with each photo's irradiance by least squares over the pixels it lights, the room's part taken off. From equal
    lamps this moves little; the joint Principled fit that follows finds each photo's intensity.

    luminance: (K, P) photo luminance; directions: (K, 3) unit; normal: (P, 3) start normals (the networks');
    relative: (K,) given relative irradiances (only their overall scale is found, and no room light) or None;
    ambient_order: the room's irradiance at a normal n is ``a[0]`` (order 0) or ``a[0] + a[1:] . n`` (order 1),
    or None: none (a flat sample's photos cannot tell it from each photo's intensity); min_share: a room's light
    whose ``a[0]`` is below this share of the mean irradiance is taken as none. The overall scale is fixed
    so that the mean irradiance is the photos' mean luminance times pi (the albedo absorbs the rest). Returns
    (irradiance (K,), the room's light ``a`` (4,) in the irradiance's units (zeros where none), the share of the
    mean irradiance that the room's light found had, ``a[0]`` over it, before ``min_share`` (None: not estimated)).
    """
    from matcap.refine.linear import solve_normals

    y = np.asarray(luminance, np.float64)
    d = np.asarray(directions, np.float64)
    level = max(float(y.mean()) * math.pi, 1e-9)
    room, share = np.zeros(4), None
    if relative is not None:
        rel = np.asarray(relative, np.float64)
        return rel * level / max(float(rel.mean()), 1e-12), room, share
    e = np.full(len(d), level)
    n, alb, solved = solve_normals(y, d * e[:, None], normal)
    if ambient_order is not None and solved.sum() >= 16:
        pick = np.flatnonzero(solved)[::max(1, int(solved.sum()) // pixels)]
        room = _room_light(y[:, pick], d, n[pick] * alb[pick, None], level, (1, 4)[min(ambient_order, 1)])
        share = float(room[0]) / level
        if share < min_share:
            room = np.zeros(4)
        else:
            n, alb, solved = solve_normals(y, d * e[:, None], normal, ambient=room)
    for i in range(rounds):
        if i > 0:  # the first round's normals: those under equal lamps (and the room's light) above
            n, alb, solved = solve_normals(y, d * e[:, None], normal, ambient=room if room.any() else None)
        if solved.sum() < 16:
            break
        n64, alb64 = n[solved].astype(np.float64), alb[solved].astype(np.float64)
        shading = np.clip((n64 @ d.T), 0.0, None).T * alb64[None]  # (K, P) per unit irradiance
        lit = shading > 0.05 * np.maximum(shading.max(axis=1, keepdims=True), 1e-12)
        lamp = y[:, solved] - (alb64 * (room[0] + n64 @ room[1:]))[None]  # the room's part taken off
        num = (lamp * shading * lit).sum(1)
        den = (shading ** 2 * lit).sum(1)
        e_new = np.clip(np.where(den > 1e-12, num / np.maximum(den, 1e-12), e), 1e-6, None)
        factor = level / e_new.mean()
        e, room = e_new * factor, room * factor
    return e, room, share


def _room_light(y: np.ndarray, d: np.ndarray, b: np.ndarray, level: float, terms: int,
                iters: int = 30) -> np.ndarray:
    """A room's light shared by every photo, ``a`` (4,) (its first ``terms`` entries fitted, the rest 0), fitted
    together with each photo's irradiance e (K,) and each pixel's b (albedo times normal) by robust Gauss-Newton
    (Cauchy weights of scale a fifth of the mean luminance, refreshed each iteration; Levenberg-Marquardt damping;
    the pixels eliminated through their 3x3 blocks) on the Lambertian model
    ``y_kp = e_k max(b_p . d_k, 0) + a[0] |b_p| + a[1:] . b_p``.

    y: (K, P) luminance; d: (K, 3) unit directions; b: (P, 3) start; level: the mean of e, held (the albedo takes
    the rest). The room's light is kept at most ``a[0]`` from its mean (light from every side cannot be negative
    anywhere) and ``a[0]`` at least 0. The irradiances serve the room's light only: unlike it, they follow
    whatever the Lambertian model misses (a highlight, an interreflection), and the caller finds them again.
    """
    k_count, p_count = y.shape
    g_count = k_count + terms
    e = np.full(k_count, level)
    amb = np.zeros(4)
    scale = 0.2 * max(float(y.mean()), 1e-12)
    lam = 1e-3
    photo = np.arange(k_count)

    def model(e, amb, b):
        size = np.linalg.norm(b, axis=1)
        cos = d @ b.T  # (K, P)
        return e[:, None] * np.clip(cos, 0.0, None) + (amb[0] * size + b @ amb[1:])[None], cos, size

    def cost(e, amb, b, w):
        return float((w * (y - model(e, amb, b)[0]) ** 2).sum())

    def feasible(a):
        a = a.copy()
        a[0] = max(a[0], 0.0)
        tilt = float(np.linalg.norm(a[1:]))
        if tilt > a[0]:
            a[1:] *= a[0] / max(tilt, 1e-30)
        return a

    pred, cos, size = model(e, amb, b)
    for _ in range(iters):
        w = 1.0 / (1.0 + ((y - pred) / scale) ** 2)
        r = y - pred
        # d pred / d b_p = lit_kp d_k + c_p (lit = e_k where b_p faces light k, else 0; c_p the room's part, the
        # same in every photo); d pred / d e_k: photo k's own column; d pred / d a: the room's terms (P, terms)
        lit = e[:, None] * (cos > 0)
        c = amb[1:] + amb[0] * (b / np.maximum(size, 1e-12)[:, None])  # (P, 3)
        room = np.concatenate([size[:, None], b], 1)[:, :terms]
        je = np.clip(cos, 0.0, None)
        outer = (d[:, :, None] * d[:, None, :]).reshape(k_count, 9)
        w_sum, w_lit_d = w.sum(0), (w * lit).T @ d  # (P,), (P, 3): sum_k w lit d_k
        h_pp = ((w * lit ** 2).T @ outer).reshape(-1, 3, 3) + w_lit_d[:, :, None] * c[:, None, :] \
            + c[:, :, None] * w_lit_d[:, None, :] + w_sum[:, None, None] * c[:, :, None] * c[:, None, :]
        w_je = w * je
        h_pk = (w_je * lit).T[:, None, :] * d.T[None] + c[:, :, None] * w_je.T[:, None, :]  # (P, 3, K)
        w_jb = w_lit_d + w_sum[:, None] * c  # sum_k w d pred / d b_p, (P, 3)
        h_pg = np.concatenate([h_pk, w_jb[:, :, None] * room[:, None, :]], 2)
        h_gg = np.zeros((g_count, g_count))
        h_gg[photo, photo] = (w_je * je).sum(1)
        h_gg[:k_count, k_count:] = w_je @ room
        h_gg[k_count:, :k_count] = h_gg[:k_count, k_count:].T
        h_gg[k_count:, k_count:] = (room * w_sum[:, None]).T @ room
        wr = w * r
        g_p = (wr * lit).T @ d + wr.sum(0)[:, None] * c
        g_g = np.concatenate([(wr * je).sum(1), wr.sum(0) @ room])
        flat_pg = h_pg.reshape(-1, g_count)
        base = cost(e, amb, b, w)
        for _ in range(8):  # damping raised until the step lowers the weighted cost
            inv = np.linalg.inv(h_pp + lam * (np.trace(h_pp, axis1=1, axis2=2)[:, None, None] / 3.0 + 1e-12)
                                * np.eye(3))
            q = np.matmul(inv, h_pg)  # H_pp^-1 H_pg, (P, 3, G)
            flat_q = q.reshape(-1, g_count)
            reduced = h_gg + lam * np.diag(np.diag(h_gg) + 1e-12) - flat_pg.T @ flat_q
            step = np.linalg.lstsq(reduced, g_g - flat_q.T @ g_p.reshape(-1), rcond=None)[0]
            e_new = np.clip(e + step[:k_count], 1e-9, None)
            amb_new = amb.copy()
            amb_new[:terms] += step[k_count:]
            amb_new = feasible(amb_new)
            b_new = b + np.matmul(inv, g_p[:, :, None])[:, :, 0] - q @ step
            f = level / e_new.mean()  # the gauge: the mean irradiance held, the albedo taking the rest
            e_new, amb_new, b_new = e_new * f, amb_new * f, b_new / f
            if cost(e_new, amb_new, b_new, w) < base:
                e, amb, b = e_new, amb_new, b_new
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 10.0
        else:
            break
        pred, cos, size = model(e, amb, b)
    return amb


def _lights_with_room(torch, prob: _Problem, lights, irr: np.ndarray, room: np.ndarray):
    """``lights`` (directions as given) with each photo's intensity and the shared ambient taken from the Lambertian
    estimate (:func:`known_irradiance`: irradiances ``irr`` (K,) and the room's light ``room`` (4,), in luminance
    units), brought to fit units by one factor per colour channel: least squares of the subsample's photos
    ``prob.obs`` (K, N, 3) against the networks' base colour over pi times that irradiance at the start normals.
    The room's light becomes the SH ambient's orders 0 and 1 (grey)."""
    from matcap.refine.model import SH_A, SH_C0, SH_C1

    n = prob.ns.double()
    d = lights.vec.double() / lights.vec.double().norm(dim=-1, keepdim=True)
    e = torch.as_tensor(irr, dtype=torch.float64, device=n.device)
    a = torch.as_tensor(room, dtype=torch.float64, device=n.device)
    shading = e[:, None] * (n @ d.T).clamp(min=0.0).T + (a[0] + n @ a[1:])[None]  # (K, N)
    basis = prob.b0.double()[None] / math.pi * shading[..., None]  # (K, N, 3)
    w = prob.weight.double()[None, :, None]
    factor = (w * basis * prob.obs.double()).sum((0, 1)) / (w * basis ** 2).sum((0, 1)).clamp(min=1e-12)  # (3,)
    factor = factor.clamp(min=1e-6)
    log_i = torch.log(e[:, None] * factor[None]).to(lights.log_intensity.dtype)
    sh = torch.zeros_like(lights.sh)
    per_term = torch.stack([a[0] / (SH_A[0] * SH_C0), a[2] / (SH_A[1] * SH_C1), a[3] / (SH_A[2] * SH_C1),
                            a[1] / (SH_A[3] * SH_C1)])  # the basis' order: 1, y, z, x
    sh[:, :4] = (per_term[:, None] * factor[None]).to(sh.dtype)
    return replace(lights, log_intensity=log_i, sh=sh)


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
    room_share: float | None  # the room's light the start found, over the lamps' mean irradiance (None: not sought)
    room_kept: bool  # at least lights.room_share: the start, the normals and the light fit took it


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
    # a room's light (the photos' shared part): an object's only, a plane's photos cannot tell it from the lamps'
    room_order = None if flat is not None or s.model.ambient == "none" else s.lights.known_ambient_order
    irr, room, room_share = known_irradiance(_luminance(obs_l, rows_l, cols_l), directions, guess_l[rows_l, cols_l],
                                 None if given is None else given @ luma, ambient_order=room_order,
                                 min_share=s.lights.room_share)
    room_found = bool(room.any())
    s_lum = directions * irr[:, None]
    # a flat sample keeps the misfit Lambertian normals: the networks' are a poorer fallback on a swatch's relief
    misfit = s.priors.lambertian_misfit if flat is None else None
    start, photo_report = _photo_normals(obs, mask, guess, s_lum, positions=known.positions, max_misfit=misfit,
                                         ambient=room if room_found else None)
    arrays = dict(arrays, normal=start)
    if hw_l == (h, w):
        arr_l, start_l = arrays, start
    else:
        start_l, _ = _photo_normals(obs_l, mask_l, guess_l, s_lum, photo_report, positions=known.positions,
                                    max_misfit=misfit, ambient=room if room_found else None)
        arr_l = dict(arr_l, normal=start_l)
    idx = _known_subsample(mask_l, s, rng)
    # no cast-shadow rule for a flat sample (a plane facing the camera shades itself only through its small
    # relief) nor for found lamps (their errors would pass for shadow)
    shadow = 0.0 if known.source == "estimated" or flat is not None else s.loss.shadow
    prob = _Problem(torch, obs_l, mask_l, arr_l, w_l, sat_level, device, idx, start_l,
                    shadow=0.0 if room_found else s.loss.shadow_light_fit if shadow > 0 else 0.0)
    lights = _init_lights(torch, prob, s, device, directions)
    if given is None and room_found:  # each photo's intensity and the room's light: the Lambertian's
        lights = _lights_with_room(torch, prob, lights, irr, room)
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
    if shadow > 0 and room_found:  # the cast-shadow rule of the per-pixel stage, the ambient's part at its start
        prob = _Problem(torch, obs_l, mask_l, arr_l, w_l, sat_level, device, idx, start_l, shadow=shadow,
                        ambient_sh=lights.sh)
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
                            level_free, tilt_held, power_held, light_iters, photo_report["solved_fraction"],
                            None if room_share is None else round(room_share, 4), room_found)

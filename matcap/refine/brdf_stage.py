"""The fit's material stage: roughness and metallic per material, after the per-pixel solve.

Pixels are grouped by base colour; a roughness grid scored per pixel (:mod:`matcap.refine.roughness`) lets the
pixels that see a highlight decide their material's roughness (:func:`_roughness_stage`), the undecided ones keep
their material's value, and each group votes for metal or dielectric (:func:`_metallic_vote`). With known lights
each pixel then takes its window's median roughness and metallic where its own photos allow them
(:func:`_pool_brdf`).
"""
from __future__ import annotations

import numpy as np

from matcap.refine.photos import _Problem, _one_thread, _shade, _workers
from matcap.refine.pixel_stage import _Mixing, _solve_pixels, _stage_sample, window_median
from matcap.refine.settings import RefineSettings


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


def _pool_brdf(torch, full: _Problem, px, lights, hw: tuple[int, int], s: RefineSettings, outputs: bool):
    """Known lights, after the roughness stage: each pixel's roughness and metallic become the median of their
    ``roughness.pool`` x ``roughness.pool`` window among the fitted pixels ``full`` (of an ``hw`` frame) where its
    own photos allow those values (their cost, :func:`matcap.refine.roughness.value_scores`, within
    ``roughness.tolerance`` of its cost at its fitted ones), and, where these maps are the fit's ``outputs``,
    wherever the model does not explain its photos at its fitted ones (cost per observation above
    ``roughness.explained``; maps that place found lamps keep such a pixel's own values, the ones that explain its
    photos best): a surface's finish varies far more slowly than one pixel's photos pin it down where they show no
    highlight, and the median keeps the edges between materials.
    Each channel of such a pixel's base colour moves by as much as its closed-form base colour (the one scored, at
    its fitted normal) changes from the fitted roughness and metallic to the pooled ones, so that the maps still
    explain the photos (a shift, not a factor: a glossy pixel's closed-form base colour can be near 0); the normals
    keep their fit.
    Returns (the new :class:`PixelParams`, the share of pixels that took the pooled values)."""
    from matcap.refine.model import PixelParams, _logit
    from matcap.refine.roughness import explained, value_scores

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
        # a pixel the model does not explain at its own values (a mixed pixel at an edge between materials) has
        # no preference among values worth keeping: it takes its window's
        unexplained = ~explained(scores[0, 0], 3 * full.obs.shape[0], s.roughness) & outputs
        take = torch.from_numpy((scores[1, 0] - scores[0, 0] <= s.roughness.tolerance) | unexplained).to(rough.device)
        shift = torch.from_numpy((scores[1, 1:] - scores[0, 1:]).T.copy()).to(base.device)
        new_base = torch.where(take[:, None], base + shift, base).clamp(0.01, 0.99)
    params = PixelParams(px.grad.detach().clone(), torch.where(take[:, None], _logit(new_base), px.base_logit.detach()),
                         torch.where(take, pooled[:, 0], px.rough_logit.detach()),
                         torch.where(take, pooled[:, 1], px.metal_logit.detach()))
    return params, float(take.float().mean())


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

"""The light stage with lights estimated from the photos: the Lambertian factorization and its check
(:func:`_check`, :mod:`matcap.refine.linear`), then the candidate light models of :func:`candidate_models` in order
(:func:`_light_stage`), each a joint robust fit of the lights and of the maps of a pixel subsample
(:func:`matcap.refine.light_fit._fit_lights`), judged by one rule (:func:`_judge`); and the held-out check, one
photo's light fitted to frozen maps (:func:`fit_light_only`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from matcap.errors import MatcapError
from matcap.refine.light_fit import _Adam, _fit_lights, _init_lights, _photo_normals, _to_near
from matcap.refine.photos import (
    LUMA, _Bar, _Photos, _Problem, _centre, _loss, _luminance, _maps_arrays, _median_distance, _predict,
    ambient_share, check_inputs, clipping_level, lights_to_entries,
)
from matcap.refine.pixel_stage import outline_zone
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

    from matcap.refine.linear import integrable_ambiguity, solve_normals, twin_ratio

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
    prior_weight = np.where(on, share, 1.0) * mask
    a = integrable_ambiguity(b_img, ok, prior, prior_weight, s_lum, equal_lights)
    if a is None or not np.isfinite(a).all() or abs(np.linalg.det(a)) < 1e-12:  # nothing to choose it by
        return fit
    s_new = s_lum @ np.linalg.inv(a)
    b = (fit.normal * fit.albedo[:, None]) @ a.T
    size = np.linalg.norm(b, axis=1)
    irr = np.linalg.norm(s_new, axis=1)
    ratio = twin_ratio(a, b_img, ok, prior, prior_weight)
    return dataclasses.replace(fit, directions=s_new / np.maximum(irr, 1e-12)[:, None], irradiance=irr,
                               normal=b / np.maximum(size, 1e-12)[:, None], albedo=size, twin_ratio=ratio)


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
                      inliers=round(linear.inliers, 4), spread=round(linear.spread, 5),
                      twin_ratio=None if np.isnan(linear.twin_ratio) else round(linear.twin_ratio, 4))
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
    sat = clipping_level(obs[0], mask)[None]
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

"""Photo-consistent refinement: fit per-image lights and per-pixel SVBRDF to the photos of one capture.

Starting from the networks' maps (the *initialisation* and a *prior*), minimise

    sum_p w_p sum_k mean_c rho((I_kc(p) - photo_kc(p)) / c)  +  prior(p)

where ``I`` is :func:`matcap.refine.model.shade` (Principled BSDF * light + order-2 SH ambient), ``rho`` the
Cauchy loss (shadows, interreflections and highlights the model cannot explain are outliers), ``w_p`` the
light-variation weight (:func:`light_variation`), and the prior pulls normals, base colour, roughness and metallic
toward the network's values (this is what stops the drift into the generalized bas-relief family).

The fit's stages (the photos' decoding, :mod:`matcap.photos`, and the networks, :mod:`matcap.estimate`, run
before; :mod:`matcap.capture` runs them all), one module each; this module runs them (:func:`refine`:
:func:`_refine_known` or :func:`_refine_estimated`) and writes the outputs:
  1. photos (:mod:`matcap.refine.photos`): :func:`_prepare` (checks, fit units, clipping levels, light variation);
  2. lights, on a downsampled copy of the photos: known (:mod:`matcap.refine.known_lights`: a light file or a
     mirror ball; the directions held) or estimated (:mod:`matcap.refine.estimated_lights`: the Lambertian
     factorization of :mod:`matcap.refine.linear` and its check, then the candidate light models of
     ``candidate_models`` in order, judged by one rule, ``_judge``); each a joint robust fit of the lights and of the
     maps of a pixel subsample (``_fit_lights`` of :mod:`matcap.refine.light_fit`, what both share);
  3. per pixel (:mod:`matcap.refine.pixel_stage`): with the lights fixed every pixel is an independent problem:
     Levenberg-Marquardt on all pixels at once (in chunks; :mod:`matcap.refine.solve`), on a half-size copy first,
     whose corrections are upsampled as the start of the full-size solve; then each material's roughness and
     metallic (:mod:`matcap.refine.brdf_stage`);
  4. outputs (:func:`_outputs`): the maps, re-renders, residual, fit.json.
Photos are scaled so that their mean over the mask is 0.5 (the fit's units); lights are reported in photo units.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from matcap.errors import MatcapError
from matcap.normals import unit_normals
from matcap.refine.brdf_stage import _pool_brdf, _roughness_stage
from matcap.refine.estimated_lights import (
    CHECK_NAMES, Candidate, RECORD_KEYS, _Check, _LightStage, _check, _judge, _light_stage, candidate_models,
)
from matcap.refine.known_lights import _known_light_stage, _place_lamps, _refit_intensities
from matcap.refine.light_fit import _median_angle_deg
from matcap.refine.photos import (
    _Bar, _Photos, _Problem, _irradiance_parts, _maps_arrays, _plane_normals, _predict, _prepare, _resize,
    lights_to_entries,
)
from matcap.refine.pixel_stage import _Mixing, _neighbour_restarts, _outline_record, _plane_detail, _solve_maps
from matcap.refine.settings import RefineSettings
from scenes.materialmaps import MaterialMaps

if TYPE_CHECKING:
    from matcap.refine.flat import FlatLights


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
    normals, every one the camera axis (the plane's own; on rendered flat samples the networks' normals came out
    further from the truth than that, on every one), and the base colour, the photos' mean
    (:func:`matcap.refine.flat.plane_base_color`). ``found_lamps``: what :func:`matcap.refine.flat.flat_lights`
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
                # their normals, which are the plane's own (the camera axis), and their base colour's pattern,
                # which is the photos' own
                from matcap.refine.flat import plane_base_color

                plane = replace(maps, normal=np.where(maps.mask[..., None], _plane_normals(maps.mask), 0.0),
                                base_color=plane_base_color(images, maps.mask, maps.with_defaults().base_color))
                result = _refine_estimated(torch, images, plane, s, progress, keep=FLAT_DISTANT)
                result.report["flat"] = {**found, "base_color": FLAT_DISTANT_BASE}
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

    Stages: (1) lights (:func:`_known_light_stage`): the given directions held, the intensities and ambient fitted
    or taken as given; (2) the per-pixel solve (:func:`_per_pixel_stage`) from calibrated photometric-stereo
    normals, with the roughness stage; lamps found from a flat sample's falloff first go through rounds on the
    light-fit copy, each followed by the lamps placed again with its maps (:func:`_place_lamps`) and the
    intensities refitted to them (:func:`_refit_intensities`); (3) outputs. With the lights known there is no
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
    light_copy = ph.light_copy(s.lights.side)
    hw_l, (obs_l, mask_l, _, w_l) = light_copy
    stage = _known_light_stage(torch, ph, light_copy, known, flat, s, bar, rng, device)
    lights, arrays, start, arr_l, start_l, shadow = (stage.lights, stage.arrays, stage.start, stage.arrays_copy,
                                                     stage.start_copy, stage.shadow)
    fitted, ambient_free, light_iters = stage.fitted, stage.ambient_free, stage.iters
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
                                                         lights_found=found, outputs=False)
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
        lights_found=found, outputs=True)
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
        "lights": {**known.record(), "directions": "held", "ambient": stage.ambient,
                   "mean_normal_held": stage.tilt_held,
                   "base_level": round(stage.level, 4) if stage.level_free else None,
                   "power_held": stage.power_held, "solved_fraction": stage.solved_fraction,
                   "room_share": stage.room_share, "room_kept": stage.room_kept,
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
                     s: RefineSettings, bar, shadow: float, plane: bool, lights_found: bool, outputs: bool):
    """Known lights' per-pixel stage under the fixed ``lights``: the solve (:func:`_solve_maps`: photos ``obs``
    (K, H, W, 3) in fit units, ``mask`` (H, W), ``weight`` (H, W), ``sat_level`` (K, 3), priors ``arrays``, start
    normals ``start`` (H, W, 3) or None), the neighbour restarts, the roughness stage (``plane``, ``lights_found``:
    see :func:`_roughness_stage`) and the pooling (``outputs``: these maps are the fit's, not a round's that places
    found lamps; see :func:`matcap.refine.brdf_stage._pool_brdf`). Returns (problem, params, outline mixing,
    iterations, restarts record, roughness choice or None, pooled share, roughness stage seconds)."""
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
        px_full, pooled_share = _pool_brdf(torch, full, px_full, lights, mask.shape, s, outputs)
        rough_s = time.perf_counter() - t_r
    return full, px_full, mixing, iters_done, restarts, choice, pooled_share, rough_s


#: Why a flat sample under distant lamps keeps the networks' maps (fit.json ``linear`` ``reason``).
FLAT_DISTANT = ("a flat sample under distant lamps: its photos hold its relief only up to the relief's sign and "
                "depth (the lamps' falloff over it did not place them), so its normal map is the plane's (the camera "
                "axis) and its base colour the photos' mean")
#: Where such a sample's base colour comes from (fit.json ``flat`` ``base_color``).
FLAT_DISTANT_BASE = ("the photos' mean, each photo over its median luminance (the plane's irradiance), at the "
                     "networks' level")


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

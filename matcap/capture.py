"""From a folder of photos (one camera, several unknown lights) to SVBRDF maps: :func:`capture` runs the stages.

The stages: the photos (:mod:`matcap.photos`: the folder read, its mask and light file) -> the networks
(:mod:`matcap.estimate`: normal + BRDF maps) -> the lights and the fit (a mirror ball's lights,
:mod:`matcap.calibrate`; the colour decision for 8-bit photos; the fit, :mod:`matcap.refine`) -> the result folder
(:mod:`matcap.results`, then relight and export).
"""
from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from matcap import imageio
from matcap.errors import MatcapError
from matcap.estimate import network_maps
from matcap.photos import (Capture, check_max_side, load_capture, photo_names, pick_images, read_lights_for,
                           shrink_image)
from matcap.refine.flat import flat_choice
from scenes.materialmaps import MaterialMaps, check_constant

if TYPE_CHECKING:
    from matcap.refine.flat import FlatLights

#: Whether `matcap capture` refines the maps when neither --refine nor --no-refine is given (docs/refine.md).
REFINE_BY_DEFAULT = True


def _relight_requests(relight) -> list[dict[str, Any]]:
    """``relight`` of :func:`capture` as a list of keyword dicts for :func:`matcap.relight.plan`."""
    if relight is None:
        return []
    if isinstance(relight, (str, os.PathLike, dict)):
        relight = [relight]
    out = []
    for item in relight:
        if isinstance(item, dict):
            out.append(dict(item))
        elif isinstance(item, (str, os.PathLike)):
            out.append({"env": item})
        else:
            raise MatcapError(f"relight entries must be an environment map path or a dict of relight settings, "
                              f"got {type(item).__name__}")
    return out


def _export_request(export, out: Path, overwrite: bool) -> dict[str, Any] | None:
    """``export`` of :func:`capture` as keyword arguments of :func:`matcap.export.export` (``out`` included)."""
    if export is None:
        return None
    request = {"out": export} if isinstance(export, (str, os.PathLike)) else dict(export)
    if "out" not in request:
        raise MatcapError("export settings need an output folder: export={'out': DIR, ...}")
    request.setdefault("name", Path(out).name)
    request.setdefault("overwrite", overwrite)
    return request


def capture(
    folder: str | os.PathLike,
    out: str | os.PathLike,
    *,
    mask: str | os.PathLike | None = None,
    linear: bool | None = False,
    contrast: float = 1.0,
    overwrite: bool = False,
    constants: dict[str, float] | None = None,
    max_side: int | None = None,
    relight=None,
    export=None,
    refine: bool = False,
    refine_settings=None,
    lights: str | os.PathLike | None = None,
    ball: str | os.PathLike | None = None,
    flat: bool | None = None,
    lamp_off: str | os.PathLike | None = None,
    on_fit=None,
    **estimate_kwargs,
) -> tuple[MaterialMaps, Path]:
    """Read ``folder``, estimate the maps and write a result folder (see :mod:`matcap.results`); then, optionally,
    relight and export them: the whole chain of ``matcap capture``.

    ``constants`` (e.g. ``{"metallic": 0.0}``) replaces estimated roughness / metallic maps by constants on the mask
    (recorded in ``capture.json`` as ``constant_maps``). ``max_side`` shrinks the photos first so that their
    longer side is at most that many pixels (a quick pass over large photos; maps come out at that size).
    ``linear=None`` with ``refine``: 8-bit photos are decoded as the fit decides (:func:`decide_colour`; recorded
    in capture.json ``colour_decision``); ``contrast`` > 1: sRGB after undoing a camera tone curve of that
    contrast (:func:`matcap.imageio.tone_curve`; not with ``linear=True``; nothing is decided then).
    ``refine`` fits lights and maps to the photos after the networks (:mod:`matcap.refine`; ``refine_settings``
    a :class:`matcap.refine.RefineSettings`) and adds lights.json, fit.json, residual.png, light_variation.png;
    ``lights``: a light file (:mod:`matcap.lightfiles`) whose lights the fit holds instead of estimating them;
    ``ball``: "auto" or a mask file of a mirror ball inside the photos: the lights come from its highlights
    (:mod:`matcap.calibrate`), the ball is kept out of the object's mask and ``calibration.png`` is written.
    ``lamp_off``: a photo taken with the lamp off, outside ``folder``, subtracted from every photo (the light of
    the room that stays on: :func:`matcap.photos.load_capture`); recorded in capture.json ``lamp_off_file``.
    ``flat``: the photos show a flat sample facing the camera (True), not (False), or decide from the networks'
    normals (None: :func:`matcap.refine.flat.check_flat`); a flat sample's lamps, unless given, are found from
    their falloff over the plane (recorded in capture.json as ``flat``).
    ``on_fit(result, settings)``: called once the fit is done (:func:`refine_maps`).
    ``relight``: an environment map path, or a dict of :func:`matcap.relight.relight` settings (``env``,
    ``point``, ``spp``, ``size`` ...), or a list of them; each renders ``relight_<name>.exr/.png`` into the result
    folder. ``export``: a folder, or a dict of :func:`matcap.export.export` settings with ``out`` (``preset``,
    ``normal`` ...; ``name`` defaults to the result folder's name, ``overwrite`` to this call's). Every setting
    (env maps read once, spp, preset, output folders) is checked before the networks run.
    Returns the maps and the result folder.
    """
    from matcap import relight as relighting
    from matcap.export import check_options
    from matcap.export import export as export_maps
    from matcap.results import check_not_replacing_inputs, check_output_dir, write_result

    constants = {name: check_constant(name, value) for name, value in (constants or {}).items()}
    contrast = imageio.check_contrast(contrast)
    linear_given = linear is not None or contrast != 1.0  # --linear / --srgb / --tone-curve said it
    if contrast != 1.0:  # a tone curve given: sRGB photos, nothing left to decide
        if linear:
            raise MatcapError("--tone-curve undoes a camera's curve over sRGB; it contradicts --linear")
        linear = False
    if max_side is not None:
        check_max_side(max_side)  # fail before the expensive part
    max_images = estimate_kwargs.pop("max_images", None)
    seed = estimate_kwargs.get("seed", 0)
    known = None
    if lights is not None or ball is not None:
        if not refine:
            raise MatcapError(f"{'a light file' if lights is not None else 'a mirror ball'} gives the fit its lights; "
                              f"it has no use without the fit")
        if lights is not None and ball is not None:
            raise MatcapError("a light file and a mirror ball both give the lights; choose one")
    if flat and not refine:
        raise MatcapError("a flat sample's lamps are found by the fit of the photos; without the fit there is nothing "
                          "to take as flat")
    picked = pick_images(len(photo_names(folder)), max_images, seed)  # as load_capture picks them
    if flat and lights is None and ball is None and len(picked) < 3:
        raise MatcapError(f"a flat sample's lamps are found from at least 3 photos, got {len(picked)}")
    if lights is not None:
        known = read_lights_for(lights, folder, picked)
    check_output_dir(out, overwrite)  # fail before the expensive part
    check_not_replacing_inputs(out, folder, mask)  # --overwrite replaces the out folder: never the photos in it
    plans = [relighting.plan(**request) for request in _relight_requests(relight)]
    names = [name for p in plans for name in p.names]
    if len(set(names)) != len(names):
        raise MatcapError("two relight renders have the same name; rename an environment map")
    export_request = _export_request(export, Path(out), overwrite)
    if export_request is not None:
        check_options(**export_request)
    # --max-side and --max-images act while reading: photos are shrunk one by one and unused ones never decoded
    calibration = ball_region = None
    if ball is not None:
        known, calibration, ball_region = ball_lights(folder, ball, linear, contrast, max_side, max_images, seed,
                                                      lamp_off)
    colour_decision, cap, maps, lamps = None, None, None, None
    if refine and linear is None:  # neither --linear nor --srgb: let the fit decide for 8-bit photos
        t0 = time.perf_counter()
        linear, colour_decision, cap, maps, lamps = decide_colour(folder, mask, max_side, refine_settings,
                                                                  dict(estimate_kwargs, max_images=max_images),
                                                                  known, exclude=ball_region, flat=flat,
                                                                  lamp_off=lamp_off)
        if colour_decision is not None:
            colour_decision["seconds"] = round(time.perf_counter() - t0, 3)
    linear = bool(linear)  # None without the fit: sRGB, the default
    if cap is None:
        cap = without_region(load_capture(folder, mask=mask, linear=linear, max_side=max_side, max_images=max_images,
                                          seed=seed, contrast=contrast, lamp_off=lamp_off), ball_region)
    original_wh = list(cap.photo_size_wh)
    if flat:
        from matcap.refine.flat import check_plane_mask

        check_plane_mask(cap.mask if cap.mask is not None else np.ones(cap.images[0].shape[:2], bool))
    if maps is None:
        maps = network_maps(cap.images, cap.mask, flat, refine, **estimate_kwargs)
    else:  # the decision's sRGB prediction: the same call, made once
        maps = dataclasses.replace(maps, meta=dict(maps.meta))
    flat_record = None
    if refine:
        flat, flat_record = flat_choice(flat, maps)
    maps = maps.with_constants(constants)
    if colour_decision is not None:  # its quick fits ran before the networks' timed call
        maps.meta["timings"] = dict(maps.meta.get("timings", {}), colour_decision_s=colour_decision["seconds"])
    used = [cap.files[i] for i in maps.meta["images_used"]]
    refine_writer = None
    if refine:
        used_lights = None if known is None else known.subset(maps.meta["images_used"])
        found = None if lamps is None or not flat else lamps.of(maps.meta["images_used"], maps.mask)
        maps, refine_writer = refine_maps(maps, [cap.images[i] for i in maps.meta["images_used"]], used,
                                          cap.colour, refine_settings, constants,
                                          progress=bool(estimate_kwargs.get("progress")), seed=seed,
                                          device=estimate_kwargs.get("device", "cpu"), lights=used_lights,
                                          flat=flat, found_lamps=found, on_fit=on_fit)
    maps.meta["images_used"] = [cap.picked[i] for i in maps.meta["images_used"]]  # indices among all the photos
    maps.meta.update(
        {
            "tool": "matcap capture",
            "input_folder": str(Path(folder).resolve()),
            "inputs": used,
            "mask_file": cap.mask_file,
            "lamp_off_file": cap.lamp_off_file,
            "skipped_files": cap.skipped,
            "colour_handling": cap.colour,
            "decoding": decoding_record(cap, linear, "fit" if colour_decision else "flag" if linear_given else
                                        "default", contrast),
            **({"tone_curve_contrast": contrast} if contrast != 1.0 and "8-bit" in cap.colour else {}),
            **({"colour_decision": colour_decision} if colour_decision else {}),
            "image_size_wh": [cap.images[0].shape[1], cap.images[0].shape[0]],
            "photo_size_wh": original_wh,  # image_size_wh differs from it after --max-side
            **({"ball": calibration.document_fields()["ball"]} if calibration is not None else {}),
            **({"flat": flat_record} if flat_record is not None else {}),
        }
    )

    def finish(folder: Path) -> list[str]:
        """Runs before the result folder is swapped into place: the refinement's files and the renders are part
        of the atomic result, and the export is done (itself atomically) before the result appears, so a run
        killed at any point leaves either nothing or everything."""
        written = list(refine_writer(folder)) if refine_writer is not None else []
        if calibration is not None:
            from matcap.calibrate import DIAGNOSTIC, diagnostic_image

            imageio.write_png(folder / DIAGNOSTIC, diagnostic_image(calibration, cap.images), bits=8)
            written.append(DIAGNOSTIC)
        for p in plans:
            relighting.render_plan(maps, p, out=folder, overwrite=True)
        if export_request is not None:
            export_maps(maps, **export_request)
        return written + [f"relight_{name}{suffix}" for p in plans for name in p.names for suffix in (".exr", ".png")]

    write_result(maps, out, overwrite=overwrite, extra_files=finish)
    return maps, Path(out)


def without_region(cap: Capture, region: np.ndarray | None) -> Capture:
    """``cap`` with the pixels ``region`` (H, W) bool kept out of its mask (a mirror ball in the frame)."""
    if region is None:
        return cap
    if region.shape != cap.images[0].shape[:2]:
        raise MatcapError(f"the ball's region is {region.shape[1]}x{region.shape[0]} but the photos are "
                          f"{cap.images[0].shape[1]}x{cap.images[0].shape[0]}")
    base = cap.mask if cap.mask is not None else np.ones(region.shape, bool)
    mask = base & ~region
    if not mask.any():
        raise MatcapError("the mask holds nothing but the mirror ball")
    return dataclasses.replace(cap, mask=mask)


def ball_lights(folder, ball: str | os.PathLike, linear: bool | None, contrast: float, max_side: int | None,
                max_images: int | None, seed: int, lamp_off: str | os.PathLike | None = None):
    """(KnownLights of the photos read, :class:`matcap.calibrate.Calibration`, the ball's region (H, W) bool) from
    a mirror ball inside the capture's own photos (``ball``: "auto", or a mask file of the ball). The highlights
    are found on the photos as decoded (8-bit as linear unless --srgb: the decoding moves no highlight); the
    relative intensities are kept only where the photos are linear."""
    from matcap.calibrate import calibrate, read_ball_mask
    from matcap.lightfiles import KnownLights

    cap = load_capture(folder, linear=linear is not False, max_side=max_side, max_images=max_images, seed=seed,
                       contrast=contrast, lamp_off=lamp_off)
    ball_mask = None
    if str(ball) != "auto":
        full = cap.photo_size_wh[::-1]
        ball_mask = read_ball_mask(ball, full)
        if tuple(full) != cap.images[0].shape[:2]:
            ball_mask = shrink_image(ball_mask.astype(np.float32), cap.images[0].shape[1::-1]) > 0.5
    cal = calibrate(cap.images, ball_mask=ball_mask, names=cap.files)
    linear_photos = "8-bit sRGB" not in cap.colour
    known = KnownLights(cal.directions, cal.intensities if linear_photos else None, "ball",
                        f"mirror ball in {Path(folder).name}", "order")
    return known, cal, cal.ball_mask()


def decoding_record(cap: Capture, linear: bool | None, chosen_by: str, contrast: float = 1.0) -> dict[str, Any]:
    """capture.json ``decoding``: how the photos became linear light, as fields. ``8bit``: "linear" or "srgb"
    (None when no photo is 8-bit); ``tone_curve_contrast``: the camera curve undone (1: none); ``chosen_by``:
    "flag" (--linear / --srgb / --tone-curve), "fit" (the colour decision) or "default" (sRGB)."""
    eight = "8-bit" in cap.colour
    return {"8bit": ("linear" if linear else "srgb") if eight else None,
            "tone_curve_contrast": contrast if eight else 1.0, "chosen_by": chosen_by if eight else "flag"}


@dataclass(frozen=True)
class FoundLamps:
    """A flat sample's lamps found from its photos: ``result``, what :func:`matcap.refine.flat.flat_lights`
    returned (:class:`matcap.refine.flat.FlatLights`) for the photos ``images`` (indices among those read) over
    ``mask`` ((H, W) bool)."""

    result: FlatLights
    images: tuple[int, ...]
    mask: np.ndarray

    def of(self, images: Sequence[int], mask: np.ndarray) -> FlatLights | None:
        """``result`` where it was found from the photos ``images`` over ``mask``, else None."""
        return self.result if tuple(images) == self.images and np.array_equal(mask, self.mask) else None


def decide_colour(folder, mask, max_side, settings, estimate_kwargs, known=None, pixels: int = 6000,
                  exclude: np.ndarray | None = None, flat: bool | None = None, lamp_off=None):
    """(linear?, record, capture, maps, lamps) for 8-bit photos given neither --linear nor --srgb: run the networks
    on the sRGB-decoded photos, fit both decodings (a quick fit on ``pixels`` random object pixels) and keep the one
    whose re-render is closer to the photos *as stored* (RMS in 8-bit units / 255). ``capture`` is the photos read
    the chosen way; ``maps`` the networks' maps when they were made from those photos (sRGB chosen), else None, so
    the caller reads and predicts nothing twice. 16-bit and float photos: (False, None, capture, None, None).
    ``known``: the :class:`matcap.lightfiles.KnownLights` of the photos read, held by both quick fits; ``exclude``:
    (H, W) pixels kept out of the mask (a mirror ball); ``flat``: as :func:`capture` (a flat sample's lamps are
    found from each decoding's photos over the whole sample, then held by its quick fit). ``lamps``: the chosen
    decoding's :class:`FoundLamps` where they were found, else None, so that the fit need not find them again."""
    from matcap.refine import RefineSettings, refine
    from networks.progress import progress as progress_bar

    shown = estimate_kwargs.get("progress") is True
    kwargs = dict(estimate_kwargs)  # the networks' stages show their own progress, as in any capture
    max_images = kwargs.pop("max_images", None)
    caps = {lin: without_region(load_capture(folder, mask=mask, linear=lin, max_side=max_side, max_images=max_images,
                                             seed=kwargs.get("seed", 0), lamp_off=lamp_off), exclude)
            for lin in (False, True)}
    if "8-bit" not in caps[False].colour:
        return False, None, caps[False], None, None
    maps = network_maps(caps[False].images, caps[False].mask, flat, True, **kwargs)
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(maps.mask)
    pick = rng.choice(len(ys), size=min(len(ys), pixels), replace=False)
    sub = np.zeros_like(maps.mask)
    sub[ys[pick], xs[pick]] = True
    maps_sub = dataclasses.replace(maps, mask=sub)
    base = settings if settings is not None else RefineSettings()
    quick = base.replace({"lights.iters": min(base.lights.iters, 200), "pixels.coarse_iters": 0,
                          "pixels.fine_iters": min(base.pixels.fine_iters, 10)})
    rmse, found = {}, {}
    flat, _ = flat_choice(flat, maps)
    bar = progress_bar(total=len(caps), desc="colour decision", unit="decoding", enabled=shown)
    for lin, cap in caps.items():
        images = [cap.images[i] for i in maps.meta["images_used"]]
        held = None if known is None else known.subset(maps.meta["images_used"])
        if held is None and flat:
            from matcap.refine.flat import flat_lights

            lamps_bar = progress_bar(total=3, desc=f"flat lamps ({'linear' if lin else 'sRGB'})", unit="step",
                                     enabled=shown)
            found[lin] = FoundLamps(flat_lights(images, maps.mask, on_stage=lambda: lamps_bar.update(1)),
                                    tuple(maps.meta["images_used"]), maps.mask)
            lamps_bar.close()
            held = found[lin].result.lights
        res = refine(images, maps_sub, quick, lights=held)
        pred = np.clip(res.prediction[:, sub], 0.0, 1.0)
        photo = np.stack([im[sub] for im in images])
        if not lin:
            pred, photo = imageio.linear_to_srgb(pred), imageio.linear_to_srgb(np.clip(photo, 0.0, 1.0))
        rmse[lin] = float(np.sqrt(((pred - photo) ** 2).mean()))
        bar.update(1)
    bar.close()
    linear = rmse[True] < rmse[False]
    record = {"chosen": "linear" if linear else "srgb", "rms_8bit_linear": round(rmse[True], 5),
              "rms_8bit_srgb": round(rmse[False], 5),
              "how": "quick refinement of both decodings on a pixel subsample; RMS of the re-render against the "
                     "stored 8-bit values / 255"}
    return linear, record, caps[linear], None if linear else maps, found.get(linear)


def refine_maps(maps: MaterialMaps, images: list[np.ndarray], files: list[str], colour: str, settings=None,
                constants: dict[str, float] | None = None, *, progress: bool = False, seed: int = 0,
                device: str = "cpu", lights=None, flat: bool = False, found_lamps: FlatLights | None = None,
                on_fit=None):
    """Run :func:`matcap.refine.refine` on ``maps`` (the networks' output) and the photos they came from.

    Returns ``(refined maps, writer)``: ``writer(folder)`` writes lights.json / fit.json / residual.png /
    light_variation.png and returns their names. The network maps stay recorded only in capture.json's summary
    (``refine.normal_change_deg_mean``); the ``constants`` maps stay constant.
    ``lights``: :class:`matcap.lightfiles.KnownLights` of ``images`` (held by the fit), or None (estimated).
    ``on_fit(result, settings)``: called with the :class:`matcap.refine.RefineResult` (its warning, the reasons in
    its report, the candidate light models judged) and the settings it ran with, as soon as the fit is done.
    ``flat``, ``found_lamps``: a flat sample (:func:`matcap.refine.refine`'s).
    """
    from matcap.refine import RefineSettings, refine
    from matcap.refine.outputs import write_refine_outputs

    s = settings if settings is not None else RefineSettings(seed=seed, device=device)
    held: dict[str, float | int] = {f"priors.{'metal' if k == 'metallic' else 'rough'}": 1e4
                                     for k in (constants or {})}
    if "roughness" in (constants or {}):
        held["roughness.choose"] = False  # no roughness to choose (the metallic vote stays)
    if "metallic" in (constants or {}):
        held["roughness.metallic_hold"] = 0.0  # no metallic to vote on
    if held:  # constant maps stay where the caller put them
        s = s.replace(held)
    result = refine(images, maps, s, progress=progress, lights=lights, flat=flat, found_lamps=found_lamps)
    if on_fit is not None:
        on_fit(result, s)
    lin = result.report.get("linear") or {}
    refined = result.maps.with_constants(constants or {})
    refined.meta = dict(maps.meta)
    r = result.report
    refined.meta["refine"] = {
        # the fit's record of the lights it held (known, from a ball, or a flat sample's found lamps): what the
        # file gave and what the fit did with it (its ambient given, fitted or none)
        "lights": r.get("lights", {"source": "estimated"}),
        "psnr_db_mean": r["psnr_db_mean"], "normal_change_deg_mean": r["normal_change_deg_mean"],
        "light_model": (r["lights"]["kind"] if "lights" in r else
                        "point" if lin.get("check") == "near lamps" else s.model.light),  # what was fitted
        "seconds": r["timings"]["total_s"],
        "weak_light_variation_fraction": r["light_variation"]["weak_fraction"],
        "kept_network_maps": r["kept_network_maps"],
        **({"flat_lamps": r["flat"]["lamps"]} if "flat" in r and "lamps" in r["flat"] else {}),
        "files": ["lights.json", "fit.json", "residual.png", "light_variation.png"],
    }
    refined.meta["timings"] = dict(maps.meta.get("timings", {}), refine_s=r["timings"]["total_s"])

    def writer(folder):
        return write_refine_outputs(folder, result, files, colour,
                                    source=lights.source if lights is not None else "estimated")

    return refined, writer


def parse_constants(items: list[str] | None) -> dict[str, float]:
    """``["metallic=0", "roughness=0.4"]`` -> ``{"metallic": 0.0, "roughness": 0.4}`` (``--constant``)."""
    out: dict[str, float] = {}
    for item in items or []:
        name, _, text = item.partition("=")
        try:
            out[name.strip()] = check_constant(name.strip(), float(text))
        except ValueError:
            raise MatcapError(f"--constant {item!r}: expected roughness=V or metallic=V with V in [0, 1]") from None
    return out

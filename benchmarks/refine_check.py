"""Photo-consistent refinement (matcap.refine), before -> after, lights unknown. Prints Markdown tables.

    python benchmarks/refine_check.py sphere              # ToyPS sphere vs its analytic normals (K=16, --linear)
    python benchmarks/refine_check.py uw [--max-side 256]  # UW captures without chrome: vs least squares with the
                                                           # true lights; light directions vs lights.txt; held-out
    python benchmarks/refine_check.py synthetic --data SPLIT  # a `matcap synth` split: normal MAE, BRDF RMSE
    python benchmarks/refine_check.py timing [--side 512]  # one fit at side^2, K=16: seconds, peak RSS (subprocess;
                                                           # --glossy: the slowest path, every look run)
    python benchmarks/refine_check.py dome                 # a glossy and a matte textured dome under 16 known
                                                           # lights: as the check decides, and always fitted
                                                           # (--roughness 0.4,0.9 --dome-light dir|point|env|dir+env,
                                                           # --lamp-distance 3: point lamps' distance)
    python benchmarks/refine_check.py samples              # a flat wood sample and 6 bumpy planes, rendered with
                                                           # Mitsuba under 12 known lights: is the fit trusted,
                                                           # which of a plane's two readings does it choose?
    python benchmarks/refine_check.py detail [--crops docs/images/detail_crops.png]  # a dome carrying a CC0 normal
                                                           # map's fine detail: is it brought back? (crops figure)
    ... --set lights.iters=0 --set priors.normal=0.1      # any RefineSettings field ("group.field")

Every row runs the bundled networks first (the "before"), then :func:`matcap.refine.refine` (the "after").
``--threads`` sets torch's CPU threads (default: torch's own choice).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = REPO.parent / "shared" / "data" / "captures"


def _models(args):
    """The networks of ``--weights`` (as ``matcap capture --weights``: a candidate scored before it is installed),
    else the installed defaults."""
    from matcap.estimate import load_networks

    return load_networks(args.weights)


def _settings(args):
    """RefineSettings(seed=0) with the ``--set KEY=VALUE`` overrides (KEY "group.field", e.g. lights.iters; values
    read as Python literals)."""
    import ast

    from matcap.refine import RefineSettings

    over = {}
    for item in args.set or []:
        key, _, text = item.partition("=")
        try:
            over[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            over[key] = text
    return RefineSettings(seed=0).replace(over)


def _check(res) -> str:
    """The fit's check (fit.json ``linear``): residual / inliers / spread / solved fraction / twin ratio, then where the
    Lambertian part failed the near-lamp look (lamp distance in object radii, ambient share, loss against distant
    lamps) and the Principled (glossy) look's ambient share, and kept or fitted."""
    lin = res.report.get("linear") or {}
    vals = [lin.get(k) for k in ("residual", "inliers", "spread", "solved_fraction", "twin_ratio")]
    text = " / ".join("-" if v is None else f"{v:.3f}" for v in vals)

    def near(radii, share, ratio):
        return (f", near: {'inf' if radii is None else f'{radii:.1f}'} radii, ambient {share:.3f}"
                + ("" if ratio is None else f", loss ratio {ratio:.2f}"))

    if lin.get("check") == "near lamps":
        found = res.report["near_lamps"]
        text += near(found["light_distance_radii"], found["ambient_share"], found["loss_ratio"])
    for key, label in (("near_fit", "near"), ("principled_fit", "Principled")):
        tried = lin.get(key)
        if tried is None:
            continue
        if tried.get("ambient_share") is None:
            text += f", {label}: solved {tried['solved_fraction']:.3f}"
        elif key == "near_fit":
            text += near(tried["light_distance_radii"], tried["ambient_share"], tried.get("loss_ratio"))
        else:
            text += f", Principled: ambient {tried['ambient_share']:.3f}"
    if lin.get("check") == "principled":
        text += f", Principled: ambient {res.report['ambient_share']:.3f}"
    return f"{text}: {'kept' if res.report['kept_network_maps'] else 'fitted'}"


def _mean_err(n, gt, m) -> float:
    from matcap.evaluation.metrics import angular_error_map

    return float(angular_error_map(n, gt, m)[m].mean())


def _angle(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def sphere(args) -> None:
    from matcap.estimate import estimate
    from matcap.evaluation.metrics import analytic_sphere
    from matcap.photos import load_capture
    from matcap.refine import refine

    cap = load_capture(args.capture or SHARED / "toyps_sphere", linear=True)
    truth, scored = analytic_sphere(cap.mask)
    print("| ToyPS sphere, K=16 (--linear, seed 0) | mean deg | median deg | re-render PSNR dB | s | check |")
    print("|---|---:|---:|---:|---:|---|")
    t0 = time.perf_counter()
    maps = estimate(cap.images, cap.mask, models=_models(args), max_images=16, seed=0)
    t_net = time.perf_counter() - t0
    from matcap.evaluation.metrics import angular_error_map

    scored = scored & maps.mask  # both rows on the same pixels
    e0 = angular_error_map(maps.normal, truth, scored)[scored]
    print(f"| network | {e0.mean():.2f} | {np.median(e0):.2f} | | {t_net:.1f} | |", flush=True)
    imgs = [cap.images[i] for i in maps.meta["images_used"]]
    t0 = time.perf_counter()
    res = refine(imgs, maps, _settings(args))
    e1 = angular_error_map(res.maps.normal, truth, scored & res.maps.mask)[scored & res.maps.mask]
    print(f"| network + refine | {e1.mean():.2f} | {np.median(e1):.2f} | {res.report['psnr_db_mean']:.2f} | "
          f"{time.perf_counter() - t0:.1f} | {_check(res)} |", flush=True)


def uw(args) -> None:
    from matcap.estimate import estimate
    from matcap.evaluation.baselines import least_squares_ps
    from matcap.evaluation.datasets import load_uw_object
    from matcap.photos import downscale_arrays, upscale_normals
    from matcap.refine import refine

    models = _models(args)
    names = args.objects.split(",")
    print(f"UW captures (8-bit taken as linear, all 12 images, --max-side {args.max_side}); normals vs least "
          f"squares with the true lights (mean deg); light directions vs lights.txt (median deg); re-render PSNR; "
          f"held-out: refine on all photos but one, fit only that photo's light with the maps frozen (--held-out: "
          f"{args.held_out or 'the last'})")
    print("| capture | network | refined | light dir median | light dir max | PSNR dB | held-out PSNR dB | refine s | "
          "check: residual / inliers / spread / solved / twin ratio (then the near-lamp and Principled looks) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    rows = []
    rooms = []  # the room's light each known-lights start found (fit.json lights.room_share)
    for name in names:
        obj = load_uw_object(SHARED / f"uw_{name}")
        ref = least_squares_ps(obj.images, obj.light_dirs, obj.mask, obj.light_intensities).normal
        images, mask = downscale_arrays(list(obj.images), obj.mask, args.max_side)
        maps = estimate(images, mask, models=models, seed=0)
        m = obj.mask

        def score(n):
            up = upscale_normals(n, m.shape, m)
            return _mean_err(up, ref, m & (np.linalg.norm(up, axis=-1) > 0.5))

        before = score(maps.normal)
        known = None
        if args.lights:
            from matcap.photos import read_lights_for

            folder = SHARED / f"uw_{name}"
            known = read_lights_for(folder / "lights.txt" if args.lights == "txt" else args.lights, folder)
        t0 = time.perf_counter()
        res = refine(images, maps, _settings(args), lights=known)
        secs = time.perf_counter() - t0
        if known is not None:
            rooms.append(f"{name} {res.report['lights']['room_share']}")
        after = score(res.maps.normal)
        d = [_angle(_towards(e), l) for e, l in zip(res.lights, obj.light_dirs)]
        ho = float(np.mean([_held_out(images, j, maps, known, _settings(args))
                            for j in args.held_out or [len(images) - 1]]))
        row = (name, before, after, float(np.median(d)), float(np.max(d)), res.report["psnr_db_mean"], ho, secs)
        rows.append(row)
        print("| {} | {:.2f} | {:.2f} | {:.2f} | {:.2f} | {:.2f} | {:.2f} | {:.1f} | {} |".format(*row, _check(res)),
              flush=True)
    a = np.array([r[1:] for r in rows], float)
    print("| **mean** | {:.2f} | {:.2f} | {:.2f} | {:.2f} | {:.2f} | {:.2f} | {:.1f} | |".format(*a.mean(0)))
    if rooms:
        print(f"\nthe room's light the start found, over the lamps' mean irradiance (fit.json lights.room_share): "
              f"{', '.join(rooms)}")


def _held_out(images, j: int, maps, known, s) -> float:
    """PSNR (dB) of photo ``j`` predicted from the fit of the others (settings ``s``): the maps refined on every photo
    but ``j`` (under their lights, where ``known``), then only photo j's light fitted to them with the maps frozen."""
    from matcap.refine import refine
    from matcap.refine.estimated_lights import fit_light_only

    keep = [i for i in range(len(images)) if i != j]
    held = refine([images[i] for i in keep], maps, s, lights=None if known is None else known.subset(keep))
    return fit_light_only(images[j], held.maps, s)["psnr_db"]


def synthetic(args) -> None:
    """Normal MAE and BRDF RMSE before -> after the fit on a synthetic split; ``--given-lights``: scenes lit by
    one directional light per photo get their true directions and relative intensities (the known-lights fit)."""
    from matcap.estimate import estimate
    from matcap.evaluation.datasets import load_synthetic_scene
    from matcap.refine import refine
    from matcap.results import read_result

    models = _models(args)
    if not args.data:
        sys.exit("synthetic: give --data SPLIT (e.g. `matcap synth --out SPLIT --scenes 48 --resolution 128 --seed 7 "
                 "--assets ../shared/data --split test`)")
    root = Path(args.data)
    scenes = sorted(p for p in root.iterdir() if p.name.startswith("scene_"))[: args.scenes]
    print(f"`{root}` first {len(scenes)} scenes (all images): normal MAE deg; BRDF RMSE (base colour after a "
          f"per-scene exposure fit, roughness, metallic) on the mask")
    print("| scene | group | normal before | normal after | base before | base after | rough before | "
          "rough after | metal before | metal after | check |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    acc = []
    truths = []
    parts = []  # per scene with a backdrop: normal MAE before, after on its objects, then on the backdrop
    for sc in scenes:
        obj = load_synthetic_scene(sc)
        if args.given_only and obj.light_dirs is None:
            continue
        gt = read_result(sc)
        maps = estimate(obj.images, obj.mask, models=models, seed=0)
        known = None
        if args.given_lights and obj.light_dirs is not None:  # one directional light per photo: give it
            from matcap.lightfiles import KnownLights

            known = KnownLights(np.asarray(obj.light_dirs, float),
                                None if obj.light_intensities is None or args.directions_only else
                                np.broadcast_to(np.asarray(obj.light_intensities, float).reshape(len(obj.images), -1),
                                                (len(obj.images), 3)).copy(), "file", str(sc), "order")
        res = refine(obj.images, maps, _settings(args), lights=known)
        m = obj.mask & maps.mask
        truths.append((gt.roughness[m], gt.metallic[m], obj.group, known is not None))

        def brdf(mp):
            b, bt = mp.base_color[m], gt.base_color[m]
            s = float((b * bt).sum() / max((b * b).sum(), 1e-9))  # exposure-aligned base colour
            return (float(np.sqrt(((s * b - bt) ** 2).mean())), float(np.sqrt(((mp.roughness[m] - gt.roughness[m]) ** 2).mean())),
                    float(np.sqrt(((mp.metallic[m] - gt.metallic[m]) ** 2).mean())))

        b0, b1 = brdf(maps.with_defaults()), brdf(res.maps)
        row = [_mean_err(maps.normal, obj.normal_gt, m), _mean_err(res.maps.normal, obj.normal_gt, m),
               b0[0], b1[0], b0[1], b1[1], b0[2], b1[2]]
        acc.append(row)
        objects = np.load(sc / "data.npz")["object_mask"] & m  # the scene's objects, without the backdrop
        if objects.any() and (m & ~objects).any():
            parts.append([_mean_err(x, obj.normal_gt, part) for part in (objects, m & ~objects)
                          for x in (maps.normal, res.maps.normal)])
        how = "lights given" if known is not None else _check(res)
        print(f"| {sc.name} | {obj.group} | " + " | ".join(f"{v:.3f}" for v in row) + f" | {how} |", flush=True)
    print("| **mean** | | " + " | ".join(f"{v:.3f}" for v in np.mean(acc, 0)) + " | |")
    given = [i for i, t in enumerate(truths) if t[3]]
    if given:
        print("| **mean, lights given** | | " + " | ".join(f"{v:.3f}" for v in np.mean([acc[i] for i in given], 0))
              + f" | {len(given)} scenes |")
    if parts:
        p = np.mean(parts, 0)
        print(f"\nnormals of the {len(parts)} scenes with a backdrop, scene means: objects {p[0]:.2f} -> "
              f"{p[1]:.2f} deg, backdrop {p[2]:.2f} -> {p[3]:.2f} deg")
    r_const = float(np.mean(np.concatenate([t[0] for t in truths])))
    m_const = float(np.mean(np.concatenate([t[1] for t in truths])))
    rc = np.mean([np.sqrt(((t[0] - r_const) ** 2).mean()) for t in truths])
    mc = np.mean([np.sqrt(((t[1] - m_const) ** 2).mean()) for t in truths])
    print(f"\nbest constant over the split: roughness {r_const:.3f} (RMSE {rc:.3f}), metallic {m_const:.3f} "
          f"(RMSE {mc:.3f})")


def samples(args) -> None:
    """Material samples filling the frame (no occluding contour): flat wood (CC0 `wood_table_worn` colours, all
    normals +z) and planes with smooth random bumps (``--bumps`` height fields), rendered under 12 directional
    lights in a 45-degree cone. With no outline and lights not given, a bumpy plane and its twin (every tilt
    mirrored, the lights turned half a turn) give the same photos: each plane's row says which reading the fit chose
    (the truth's or the twin's, whichever its normals are nearer) and the prior's twin ratio; the last row the mean."""
    from scipy import ndimage

    from matcap.estimate import estimate
    from matcap.formats import load_maps
    from matcap.refine import refine
    from matcap.refine import synthetic as S
    from scenes.materialmaps import MaterialMaps

    models = _models(args)
    wood = load_maps(SHARED.parent / "textures" / "wood_table_worn", max_side=256).with_defaults()
    side = 192
    yy, xx = np.mgrid[0:side, 0:side] / side

    def bumpy(seed):
        height = ndimage.gaussian_filter(np.random.default_rng(seed).normal(size=(side, side)), 6)
        gy, gx = np.gradient(height / height.std() * 2.0)
        n = np.dstack([-gx, gy, np.ones_like(gx)])
        return MaterialMaps(normal=(n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32),
                            mask=np.ones((side, side), bool),
                            base_color=np.dstack([0.5 + 0.2 * np.sin(9 * xx), 0.4 + 0.1 * np.cos(7 * yy),
                                                  0.3 + 0 * xx]).astype(np.float32),
                            roughness=np.full((side, side), 0.6, np.float32),
                            metallic=np.zeros((side, side), np.float32))

    lights = S.known_lights(12, seed=3, max_angle_deg=45.0)
    print("| sample | flat normals | network | after the fit | light dir median | trusted | reading | twin ratio | "
          "reason |")
    print("|---|---:|---:|---:|---:|---|---|---:|---|")
    planes = []
    samples_ = [("flat wood 256^2", wood)] + [(f"bumpy plane 192^2, heights {k}", bumpy(k))
                                              for k in range(args.bumps)]
    for name, truth in samples_:
        photos = S.render_capture(truth, lights, ambient=0.02, spp=16)
        maps = estimate(photos, truth.mask, models=models, seed=0)
        res = refine(photos, maps, _settings(args))
        m = truth.mask
        flat = np.zeros(m.shape + (3,), np.float32)
        flat[..., 2] = 1.0
        errs = [_mean_err(x, truth.normal, m) for x in (flat, maps.normal, res.maps.normal)]
        d = np.median([_angle(_towards(e), _towards(l)) for e, l in zip(res.lights, lights)])
        lin = res.report["linear"]
        twin = _mean_err(res.maps.normal, truth.normal * np.array([-1.0, -1.0, 1.0], np.float32), m)
        reading = "-" if name.startswith("flat") else ("truth" if errs[2] <= twin else "twin")
        ratio = lin.get("twin_ratio")
        if reading != "-":
            planes.append(errs + [reading == "truth"])
        print(f"| {name} | {errs[0]:.2f} | {errs[1]:.2f} | {errs[2]:.2f} | {d:.1f} | {lin['trusted']} | {reading} | "
              f"{'-' if ratio is None else f'{ratio:.2f}'} | {lin.get('reason', '')} |", flush=True)
    if planes:
        a = np.array(planes, float)
        print(f"| bumpy planes, mean of {len(a)} | {a[:, 0].mean():.2f} | {a[:, 1].mean():.2f} | "
              f"{a[:, 2].mean():.2f} | | | truth {int(a[:, 3].sum())} of {len(a)} | | |")


def dome(args) -> None:
    """The capture the refinement is made for: one object, one light moved around it in a dark room. A sphere up
    to its contour carrying the detail and colours of the CC0 `wood_table_worn` set, glossy (roughness 0.4) and
    matte (0.9) (``--roughness``), rendered with Mitsuba under 16 known directional lights in a 45-degree cone
    plus a faint ambient (``--dome-light``: or point lights, an environment map, both); the fit as the check
    decides, and trusted whatever the check's residual / inliers say (``checks.residual=inf``, ``checks.inliers=0``)."""
    from matcap.estimate import estimate
    from matcap.formats import load_maps
    from matcap.refine import refine
    from matcap.refine import synthetic as S

    models = _models(args)
    wood = load_maps(SHARED.parent / "textures" / "wood_table_worn", max_side=args.side)
    lights = S.known_lights(16, seed=3, max_angle_deg=45.0, kind="point" if args.dome_light == "point" else
                            "directional", distance=args.lamp_distance)
    lamp = f" at {args.lamp_distance:g}" if args.dome_light == "point" else ""
    print(f"Textured dome, {args.side}^2, 16 photos, light {args.dome_light}{lamp}: normals vs the truth (mean deg); "
          "light directions (median deg)")
    print("| roughness | network | fit (check decides) | light dir | kept? | fit, residual check off | light dir | "
          "check: residual / inliers / spread / solved / twin ratio (then the near-lamp and Principled looks) |")
    print("|---:|---:|---:|---:|---|---:|---:|---|")
    decomposed = []  # --decompose: (roughness, the lamps' decomposition, the given directions' normal error)
    for rough in args.roughness:
        truth = S.textured_dome(args.side, wood, roughness=rough)
        if args.dome_light in ("dir", "point"):
            photos = S.render_capture(truth, lights, ambient=0.02, spp=32)
        else:
            photos = _env_photos(truth, lights if args.dome_light == "dir+env" else None, args.env_fixed)
        if args.lamp_off:  # a photo of the room's light alone, subtracted as `matcap capture --lamp-off` does
            from matcap.photos import subtract_lamp_off

            (off,) = _env_photos(truth, [], True, count=1)
            photos = [subtract_lamp_off(p, off) for p in photos]
        maps = estimate(photos, truth.mask, models=models, seed=0)
        s = _settings(args)
        checked = refine(photos, maps, s)
        forced = refine(photos, maps, s.replace({"checks.residual": float("inf"), "checks.inliers": 0.0}))
        cells = [f"{_mean_err(maps.normal, truth.normal, truth.mask):.2f}"]
        for res in (checked, forced):
            d = "-" if args.dome_light == "env" else (  # light directions at the centre (none under the map alone)
                f"{np.median([_angle(_towards(e), _towards(l)) for e, l in zip(res.lights, lights)]):.1f}")
            cells += [f"{_mean_err(res.maps.normal, truth.normal, truth.mask):.2f}", d]
            if res is checked:
                cells.append("kept" if res.report["kept_network_maps"] else "fitted")
        print(f"| {rough} | {' | '.join(cells)} | {_check(checked)} |", flush=True)
        if args.decompose and args.dome_light in ("dir", "dir+env"):
            decomposed.append((rough, _decompose(checked.lights, lights), _given_directions(photos, maps, s, lights,
                                                                                            truth)))
    if decomposed:
        print("\nThe lamps found (checked fit) as the true lamps' irradiance vectors times one factor plus one common "
              "vector c (least squares); the fit given the true directions alone (each photo's intensity fitted)")
        print("| roughness | factor | c, share of the lamps' irradiance | lamps found, median angle | the same minus c "
              "| given directions: normals |")
        print("|---:|---:|---:|---:|---:|---:|")
        for rough, d, given in decomposed:
            print(f"| {rough} | {d['factor']:.3f} | {d['share']:.1%} | {d['angle']:.2f}° | {d['angle_minus_c']:.2f}° | "
                  f"{given:.2f}° |", flush=True)


def _decompose(found: list[dict], true) -> dict:
    """The lamps ``found`` (lights.json entries, distant) against the ``true`` DirectionalLights: their irradiance
    vectors (direction times mean intensity) fitted as ``factor * true + c`` by least squares (one factor, one
    common 3-vector ``c``). Returns factor, share (``|c|`` over the mean length of ``factor * true``), angle (the
    found lamps' median angle to the true ones, degrees) and angle_minus_c (the same for ``found - c``)."""
    f = np.array([np.asarray(e["direction"], float) * np.mean(e["intensity"]) for e in found])
    t = np.array([np.asarray(light.direction, float) * np.mean(light.irradiance) for light in true])
    k = len(t)
    a = np.zeros((3 * k, 4))
    a[:, 0] = t.ravel()
    a[:, 1:] = np.tile(np.eye(3), (k, 1))
    sol = np.linalg.lstsq(a, f.ravel(), rcond=None)[0]
    factor, c = float(sol[0]), sol[1:]
    return {"factor": factor, "share": float(np.linalg.norm(c) / np.linalg.norm(factor * t, axis=1).mean()),
            "angle": float(np.median([_angle(x, y) for x, y in zip(f, t)])),
            "angle_minus_c": float(np.median([_angle(x - c, y) for x, y in zip(f, t)]))}


def _given_directions(photos, maps, s, lights, truth) -> float:
    """Mean normal error (degrees) of the fit given the true lamps' directions alone (their intensities fitted)."""
    from matcap.lightfiles import KnownLights
    from matcap.refine import refine

    known = KnownLights(np.array([light.direction for light in lights], float), None, "file", "dome", "order")
    return _mean_err(refine(photos, maps, s, lights=known).maps.normal, truth.normal, truth.mask)


def detail(args) -> None:
    """Fine detail: the dome of ``dome`` (16 directional lights, 45-degree cone, faint ambient, 256^2, Mitsuba,
    32 spp), its surface carrying the relief of a CC0 Poly Haven set's normal map (``--texture``, default
    painted_wooden_stool: planks, grooves and chipped paint), integrated into a height field
    (:func:`matcap.refine.synthetic.relief_dome`; ``--baked``: the normal map as it is, which no surface has).
    Normals vs the truth, whole and their fine detail only (high-pass: minus a Gaussian blur of sigma 1.5 px, on
    the mask eroded by 6 px): mean error of the
    high-pass vectors, the correlation of their x, y with the truth's and their strength against it
    (:func:`matcap.evaluation.metrics.detail_scores`); the grid: the share of that detail at periods up to 1.1 x
    side / 128 px (:func:`matcap.evaluation.metrics.fine_energy_share`). ``--crops PNG``: photo / normals /
    n.l shading under a grazing light, network / fit / truth, one row per roughness."""
    from matcap.estimate import estimate
    from matcap.evaluation.metrics import detail_scores, fine_energy_share
    from matcap.formats import load_maps
    from matcap.refine import refine
    from matcap.refine import synthetic as S

    models = _models(args)
    tex = load_maps(SHARED.parent / "textures" / args.texture, max_side=args.side)
    lights = S.known_lights(16, seed=3, max_angle_deg=45.0)
    grid = round(1.1 * args.side / 128, 2)  # the networks' interleaved 128 px tiles: a grid of period side / 128 px
    make = S.textured_dome if args.baked else S.relief_dome
    print(f"Detailed dome ({args.texture} {'normal map' if args.baked else 'relief'} x{args.strength:g}), "
          f"{args.side}^2, 16 photos, distant lights: normals vs the truth (mean deg), fine detail (high-pass error; "
          "correlation with the truth's)")
    print("| roughness | network | fit | detail error network / fit (truth's size) | detail correlation network / "
          f"fit | detail amplitude network / fit | grid: detail at periods <= {grid:g} px, network / fit (truth) | "
          "light dir | check |")
    print("|---:|---:|---:|---|---|---|---|---:|---|")
    rows = []
    for rough in args.roughness:
        truth = make(args.side, tex, strength=args.strength, roughness=rough)
        photos = S.render_capture(truth, lights, ambient=0.02, spp=32)
        maps = estimate(photos, truth.mask, models=models, seed=0)
        res = refine(photos, maps, _settings(args))
        m = truth.mask
        before, after = (detail_scores(n, truth.normal, m) for n in (maps.normal, res.maps.normal))
        d = np.median([_angle(_towards(e), _towards(l)) for e, l in zip(res.lights, lights)])
        shares = ([f"{fine_energy_share(n, m, grid):.0%}" for n in (maps.normal, res.maps.normal, truth.normal)]
                  if grid >= 2 else ["-"] * 3)  # at 128^2 and less the tiles do not interleave: no grid
        print(f"| {rough} | {_mean_err(maps.normal, truth.normal, m):.2f} | "
              f"{_mean_err(res.maps.normal, truth.normal, m):.2f} | {before['error']:.3f} / {after['error']:.3f} "
              f"({after['truth_size']:.3f}) | "
              f"{before['correlation']:.2f} / {after['correlation']:.2f} | {before['amplitude']:.2f} / "
              f"{after['amplitude']:.2f} | {shares[0]} / {shares[1]} ({shares[2]}) | {d:.1f} | "
              f"{_check(res)} |", flush=True)
        rows.append((rough, photos, maps.normal, res.maps.normal, truth.normal))
    if args.crops:
        _detail_figure(args.crops, rows, args.side)


def _detail_figure(path, rows, side: int, crop: int = 80, zoom: int = 3) -> None:
    """One row per roughness: a photo, then network / fit / truth normals (RGB = n * 0.5 + 0.5), then their n.l
    shading under a grazing light from the upper left; a ``crop``-px square from the dome's centre, ``zoom``x."""
    import cv2

    from matcap.imageio import linear_to_srgb, write_png

    y0 = x0 = (side - crop) // 2
    sl = (slice(y0, y0 + crop), slice(x0, x0 + crop))
    grazing = np.array([-0.6, 0.6, 0.53]) / np.linalg.norm([-0.6, 0.6, 0.53])
    labels = ["photo", "network", "fit", "truth", "network n.l", "fit n.l", "truth n.l"]
    tile = crop * zoom
    out = []
    for rough, photos, *normals in rows:
        photo = photos[0][sl]
        tiles = [linear_to_srgb(photo / max(float(np.percentile(photo, 99.5)), 1e-6))]
        tiles += [np.clip(np.asarray(n[sl], np.float32) * 0.5 + 0.5, 0, 1) for n in normals]
        tiles += [np.repeat(np.clip(np.asarray(n[sl], np.float64) @ grazing, 0, 1)[..., None], 3, -1)
                  for n in normals]
        big = [np.asarray(t, np.float32).repeat(zoom, 0).repeat(zoom, 1) for t in tiles]
        row = np.concatenate([np.pad(b, ((0, 0), (2, 2), (0, 0)), constant_values=1.0) for b in big], 1)
        head = np.full((22, row.shape[1], 3), 255, np.uint8)  # OpenCV draws text on 8-bit images only
        for i, text in enumerate(labels):
            cv2.putText(head, f"{text}" + (f" (roughness {rough:g})" if i == 0 else ""), (i * (tile + 4) + 6, 16),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        out += [head.astype(np.float32) / 255.0, row]
    write_png(path, np.concatenate(out, 0), bits=8)
    print(f"wrote {path}")


def _towards(light) -> np.ndarray:
    """Direction toward a light (a lights.json entry or a scenes.lights light) from the frame's centre."""
    if isinstance(light, dict):
        return np.asarray(light["direction"] if "direction" in light else light["position"], float)
    return np.asarray(getattr(light, "direction", None) or light.position, float)


def _env_photos(truth, lights=None, fixed: bool = False, count: int = 16):
    """16 photos of ``truth`` under Blender's studio, interior, courtyard and forest maps in turn, turned by 22.5
    degrees from photo to photo (``fixed``: the studio map alone, never turned: a room's light); with ``lights``,
    each photo's directional light plus the map at 0.3 (``lights`` empty: the map at 0.3 alone, the lamp off);
    the first ``count`` of them."""
    from matcap.refine import synthetic as S
    from matcap.relight import load_envmap
    from renderers.relight import render
    from scenes.lights import EnvironmentLight

    names = ["blender_studio"] if fixed else ["blender_studio", "blender_interior", "blender_courtyard",
                                              "blender_forest"]
    env = {n: load_envmap(SHARED.parent / "envmaps" / f"{n}.exr") for n in names}  # only the maps it shows
    full = S.extend_maps(truth)
    photos = []
    for i in range(count):
        e = EnvironmentLight(source=names[i % len(names)], rotation_deg=0.0 if fixed else 22.5 * i,
                             scale=1.0 if lights is None else 0.3)
        img = render(full, [e] if lights is None else [*lights[i:i + 1], e], env, spp=32, seed=i)
        photos.append(np.where(truth.mask[..., None], img, 0.0).astype(np.float32))
    return photos


def timing(args) -> None:
    """One refine at side^2 with K=16 in a fresh subprocess: seconds and peak RSS (``--set`` applies;
    ``--given-lights``: the known-lights fit, given the photos' true directions)."""
    settings = json.dumps(dataclasses.asdict(_settings(args)))
    code = f"""
import json, resource, time, numpy as np, torch
{'torch.set_num_threads(%d)' % args.threads if args.threads else ''}
from matcap.refine import RefineSettings, refine
from matcap.refine import synthetic as S
side, k = {args.side}, 16
truth = S.sphere_maps(side)
rng = np.random.default_rng(0)
# photos from the torch forward model itself (no Mitsuba: only the fit is timed)
import torch as T
from matcap.refine.model import shade_directional
from matcap.evaluation.toy import cone_lights
m = truth.mask
n = T.from_numpy(truth.normal[m]); b = T.from_numpy(truth.base_color[m]); r = T.from_numpy(truth.roughness[m])
if {args.glossy}:
    r = T.full_like(r, 0.2)
L = T.from_numpy(cone_lights(k, 50.0, seed=1)).float()
with T.no_grad():
    px = shade_directional(n, b, r, T.zeros(len(n)), L, T.full((k, 3), 2.5), T.zeros(1, 9, 3)).numpy()
photos = np.zeros((k, side, side, 3), np.float32); photos[:, m] = px
start = S.perturb(truth)
known = None
if {args.given_lights}:
    from matcap.lightfiles import KnownLights
    known = KnownLights(L.numpy().astype(float), None, "file", "timing", "order")
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
res = refine(list(photos), start, RefineSettings.from_dict(json.loads({settings!r})), lights=known)
lin = res.report["linear"] or {{}}
path = ("known lights" if known is not None else "first check: " + ("fitted" if lin.get("trusted") else "kept")
        if "check" not in lin else lin["check"] + " look kept")
print(json.dumps({{"seconds": time.perf_counter() - t0, "pixels": int(m.sum()), "timings": res.report["timings"],
                  "path": path,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "rss_before_fit_mb": rss0 / 1024}}))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                         env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    if out.returncode:
        print(out.stderr[-2000:])
        raise SystemExit(1)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"| fit at {args.side}^2, K=16 ({r['pixels']} object pixels{', glossy' if args.glossy else ''}) | seconds "
          f"| peak RSS MB | path |")
    print("|---|---:|---:|---|")
    print(f"| the final look's lights {r['timings']['lights_s']:.1f} s + maps {r['timings']['maps_s']:.1f} s | "
          f"{r['seconds']:.1f} | {r['peak_rss_mb']:.0f} | {r['path']} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("sphere", "uw", "synthetic", "timing", "samples", "dome", "detail"))
    ap.add_argument("--capture", help="ToyPS sphere folder (sphere)")
    ap.add_argument("--objects", default="buddha,cat,gray,horse,owl,rock", help="UW objects (uw)")
    ap.add_argument("--max-side", type=int, default=256, help="photo side for the UW rows (uw; default 256)")
    ap.add_argument("--data", help="synthetic split (synthetic): a folder written by `matcap synth`")
    ap.add_argument("--given-lights", action="store_true",
                    help="synthetic, timing: give the fit the true lights (the known-lights fit)")
    ap.add_argument("--given-only", action="store_true",
                    help="synthetic, with --given-lights: only the scenes whose lights are given")
    ap.add_argument("--directions-only", action="store_true",
                    help="synthetic, with --given-lights: give the directions alone (each photo's intensity is "
                         "fitted, as after a calibration with clipped highlights)")
    ap.add_argument("--lights", metavar="txt|FILE",
                    help="uw: give the fit known lights: 'txt' each capture's lights.txt, or a light file (e.g. "
                         "the rig.json of `matcap calibrate uw_chrome`)")
    ap.add_argument("--held-out", type=lambda v: [int(x) for x in v.split(",")], default=None,
                    help="uw: the photos held out in turn (0-based, comma-separated), the held-out PSNR their mean "
                         "(default: the last photo alone)")
    ap.add_argument("--scenes", type=int, default=8, help="first N scenes (synthetic)")
    ap.add_argument("--side", type=int, default=None, help="image side (timing; dome: default 256)")
    ap.add_argument("--bumps", type=int, default=6, help="samples: how many bumpy planes (random height fields)")
    ap.add_argument("--lamp-off", action="store_true",
                    help="dome with --env-fixed: a photo of the room's light alone subtracted from every photo")
    ap.add_argument("--roughness", type=lambda v: [float(x) for x in v.split(",")], default=[0.4, 0.9],
                    help="dome roughness values, comma-separated (dome; default 0.4,0.9)")
    ap.add_argument("--dome-light", choices=("dir", "point", "env", "dir+env"), default="dir",
                    help="dome: 16 directional lights plus a faint ambient (default), point lights instead "
                         "(--lamp-distance), a turning environment map alone, or directional lights and the map at 0.3")
    ap.add_argument("--decompose", action="store_true",
                    help="dome with directional lamps: the lamps found as the true ones times one factor plus one "
                         "common vector (its share, the lamps' angles with and without it), and the fit given the "
                         "true directions alone")
    ap.add_argument("--env-fixed", action="store_true",
                    help="dome with --dome-light env or dir+env: one map (studio) that never turns, as a room's light")
    ap.add_argument("--lamp-distance", type=float, default=3.0,
                    help="dome with --dome-light point: the lamps' distance from the dome's centre in half-widths of "
                         "the frame (the dome's radius is 0.94 of them; default 3)")
    ap.add_argument("--glossy", action="store_true",
                    help="timing: a glossy sphere (roughness 0.2) whose highlights fail the Lambertian check, so the "
                         "near-lamp and glossy looks run too (the slowest path); default: a capture the check trusts")
    ap.add_argument("--texture", default="painted_wooden_stool",
                    help="detail: the texture set under ../shared/data/textures whose normal map the dome carries")
    ap.add_argument("--strength", type=float, default=1.0, help="detail: scale of that normal map's x, y (default 1)")
    ap.add_argument("--crops", help="detail: write the crops figure to this PNG")
    ap.add_argument("--baked", action="store_true",
                    help="detail: the normal map laid on the dome as it is (textured_dome), not integrated into a "
                         "relief")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    ap.add_argument("--weights", action="append", metavar="FILE",
                    help="network weights instead of the installed ones, as `matcap capture --weights` (repeatable: "
                         "a normal and a BRDF model), e.g. a training run's best.safetensors")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help="a RefineSettings field for the fit, group.field=value (repeatable), e.g. lights.iters=0")
    args = ap.parse_args(argv)
    if args.side is None:
        args.side = 256 if args.what in ("dome", "detail") else 512
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    {"sphere": sphere, "uw": uw, "synthetic": synthetic, "timing": timing, "samples": samples,
     "dome": dome, "detail": detail}[args.what](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

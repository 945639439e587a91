"""Benchmark runner: methods on datasets, the K-images x N-trials protocol, Markdown/JSON tables, error maps.

Protocol (SDM-UniPS, Ikehata CVPR 2023, for image subsets): for every object and trial t = 0..N-1, K images are
drawn without replacement by ``numpy.random.default_rng([seed, t, K, crc32(object name)])`` -- the subset depends
on the object, K, the trial and the seed only, never on the method, so every method sees the same subsets. The
object's numbers are the means over the trials (the table also gives the spread of the mean angular error). With
all images (no ``max_images``, or K >= the object's image count) there is a single trial. A learned method gets
``seed + t`` as its own seed.

Scoring: against the ground-truth normals (``reference=None``) or, for data without ground truth, against another
method run on **all** the object's images (``reference="least-squares"`` for example); see
:mod:`matcap.evaluation.metrics` for the error definition. Seconds per object are the mean wall time of one
trial of the method (model loading excluded; it is reported once as ``load_s``).
"""
from __future__ import annotations

import json
import math
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from matcap.errors import MatcapError
from matcap.evaluation import baselines, metrics
from matcap.evaluation.datasets import PSObject, discover

CONVENTION = "camera space: x right, y up, z toward the camera; row 0 at the top"


# ----------------------------------------------------------------------------------------------- methods


@dataclass
class MethodContext:
    """Settings shared by all calls of a method during one evaluation."""

    weights: list[str] | None = None
    device: str = "cpu"
    views: int = 1  # test-time augmentation of the network (matcap.estimate.estimate(views=...))
    max_side: int | None = None  # network input shrunk to this longer side, normals scaled back (capture --max-side)
    linear: bool = False  # 8-bit images go to the network as stored (capture --linear), not sRGB-decoded
    state: dict[str, Any] | None = None  # lazily loaded things (networks), kept across objects


@dataclass(frozen=True)
class Method:
    """A normal estimator: ``run(obj, indices, seed, ctx) -> (H, W, 3) normals`` in our camera convention."""

    name: str
    needs_lights: bool
    min_images: int
    description: str
    run: Callable[[PSObject, np.ndarray, int, MethodContext], np.ndarray]


def _run_least_squares(obj: PSObject, idx: np.ndarray, seed: int, ctx: MethodContext) -> np.ndarray:
    return baselines.least_squares_ps([obj.images[i] for i in idx], obj.light_dirs[idx], obj.mask,
                                      obj.light_intensities[idx]).normal


def _run_robust(obj: PSObject, idx: np.ndarray, seed: int, ctx: MethodContext) -> np.ndarray:
    return baselines.robust_least_squares_ps([obj.images[i] for i in idx], obj.light_dirs[idx], obj.mask,
                                             obj.light_intensities[idx]).normal


def _network_maps(obj: PSObject, idx: np.ndarray, seed: int, ctx: MethodContext):
    """The images the network sees (after --linear / --max-side) and its maps for them."""
    from matcap import estimate  # lazy: torch and the networks load only when this method is used
    from matcap.photos import downscale_arrays

    state = ctx.state if ctx.state is not None else {}
    kwargs: dict[str, Any] = {}
    if hasattr(estimate, "load_networks"):
        if "models" not in state:
            t0 = time.perf_counter()
            state["models"] = estimate.load_networks(ctx.weights, ctx.device)
            state["load_s"] = time.perf_counter() - t0
        kwargs["models"] = state["models"]
    images, mask = obj.network_images(idx, decode_srgb=not ctx.linear), obj.mask
    if ctx.max_side is not None:
        images, mask = downscale_arrays(images, mask, ctx.max_side)
    maps = estimate.estimate(images, mask, weights=ctx.weights, max_images=None, seed=seed,
                             device=ctx.device, views=ctx.views, progress=False, **kwargs)
    return images, maps


def _full_size_normals(obj: PSObject, maps) -> np.ndarray:
    """The maps' normals, scored at the object's own size like every other method."""
    normal = np.asarray(maps.normal, dtype=np.float32)
    if normal.shape[:2] != obj.mask.shape:
        from matcap.photos import upscale_normals

        normal = upscale_normals(normal, obj.mask.shape, obj.mask)
    return normal


def _run_sdm_unips(obj: PSObject, idx: np.ndarray, seed: int, ctx: MethodContext) -> np.ndarray:
    return _full_size_normals(obj, _network_maps(obj, idx, seed, ctx)[1])


def _refine_and_record(images: list[np.ndarray], maps, seed: int, ctx: MethodContext):
    """Run the photo-consistent fit (``matcap.refine``) on the network's maps; keep the estimated light
    directions (one unit vector per image, toward the light) in ``ctx.state["light_dirs"]``; return the maps."""
    try:
        from matcap.refine.fit import RefineSettings, refine
    except ImportError:  # matcap.refine.fit and its stage modules
        raise MatcapError("--refine needs the refinement stage (matcap.refine.fit), which this matcap lacks") from None
    result = refine(images, maps, RefineSettings(seed=seed, device=ctx.device))
    dirs = []
    for entry in result.lights:
        v = np.asarray(entry["direction"] if entry["kind"] == "directional" else entry["position"], np.float64)
        dirs.append(v / max(float(np.linalg.norm(v)), 1e-12))  # a point light: seen from the plane's centre
    if ctx.state is not None:
        ctx.state["light_dirs"] = np.asarray(dirs)
    return result.maps


def _run_sdm_unips_refined(obj: PSObject, idx: np.ndarray, seed: int, ctx: MethodContext) -> np.ndarray:
    """sdm-unips, then the photo-consistent fit of lights and maps to the same images (``--refine``)."""
    images, maps = _network_maps(obj, idx, seed, ctx)
    return _full_size_normals(obj, _refine_and_record(images, maps, seed, ctx))


def _run_flat(obj: PSObject, idx: np.ndarray, seed: int, ctx: MethodContext) -> np.ndarray:
    """Every pixel faces the camera: the score any method has to beat."""
    normal = np.zeros(obj.mask.shape + (3,), np.float32)
    normal[..., 2] = 1.0
    return normal


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("flat", False, 1, "constant (0, 0, 1): every pixel faces the camera (the trivial anchor)", _run_flat),
        Method("least-squares", True, 3, "Lambertian least squares over all images (Woodham 1980)",
               _run_least_squares),
        Method("least-squares-robust", True, 3,
               f"least squares without the darkest {baselines.DEFAULT_DARK_FRAC:.0%} and brightest "
               f"{baselines.DEFAULT_BRIGHT_FRAC:.0%} observations per pixel", _run_robust),
        Method("sdm-unips", False, 2, "SDM-UniPS network via matcap.estimate.estimate (lights unknown to it)",
               _run_sdm_unips),
    )
}


#: ``--method sdm-unips --refine``: the network, then the photo-consistent fit (lights unknown to both).
REFINED = Method("sdm-unips+refine", False, 2,
                 "SDM-UniPS network, then matcap.refine's fit of lights and maps to the photos (lights unknown)",
                 _run_sdm_unips_refined)
REFINABLE = ("sdm-unips",)


def get_method(name: str, refine: bool = False) -> Method:
    if name not in METHODS:
        raise MatcapError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
    if refine:
        if name not in REFINABLE:
            raise MatcapError(f"--refine refines the network's maps: it needs --method {' or '.join(REFINABLE)}")
        return REFINED
    return METHODS[name]


def light_angles(estimated: np.ndarray, calibrated: np.ndarray) -> np.ndarray:
    """Degrees between estimated and calibrated light directions, (K, 3) each (normalised here)."""
    a = np.asarray(estimated, np.float64)
    b = np.asarray(calibrated, np.float64)
    a = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


# ----------------------------------------------------------------------------------------------- protocol


def trial_subsets(name: str, n_images: int, max_images: int | None, trials: int, seed: int) -> list[np.ndarray]:
    """The sorted image indices of each trial (see the module docstring)."""
    if max_images is None or max_images >= n_images:
        return [np.arange(n_images)]
    subsets = []
    for t in range(trials):
        rng = np.random.default_rng([seed, t, max_images, zlib.crc32(name.encode("utf-8"))])
        subsets.append(np.sort(rng.choice(n_images, size=max_images, replace=False)))
    return subsets


def _status_for(obj: PSObject, method: Method, reference: Method | None) -> str | None:
    if reference is None and obj.normal_gt is None:
        return "n/a: no ground-truth normals (use --reference)"
    if method.needs_lights and not obj.calibrated:
        return "n/a: no calibrated lights"
    if reference is not None and reference.needs_lights and not obj.calibrated:
        return "n/a: reference needs calibrated lights"
    for m in (method, reference):
        if m is not None and len(obj.images) < m.min_images:
            return f"n/a: {m.name} needs {m.min_images} images, object has {len(obj.images)}"
    return None


def write_error_map(path: str | Path, err: np.ndarray, max_deg: float = 90.0) -> None:
    """Write an 8-bit PNG of the colour-mapped error (0..``max_deg`` deg, black off-mask) with a colour bar."""
    from matcap import imageio

    h = err.shape[0]
    rgb = metrics.colorize_error(err, max_deg)
    gap = np.zeros((h, 4, 3), np.float32)
    bar = metrics.colorbar(h, 12, max_deg)
    imageio.write_png(path, np.concatenate([rgb, gap, bar], axis=1), bits=8)


def evaluate_object(obj: PSObject, method: Method, reference: Method | None = None, *,
                    max_images: int | None = None, trials: int = 10, seed: int = 0,
                    ctx: MethodContext | None = None, error_map: str | Path | None = None) -> dict[str, Any]:
    """Run the protocol on one loaded object; returns its table row (a JSON-ready dict)."""
    ctx = ctx or MethodContext()
    h, w = obj.shape
    row: dict[str, Any] = {
        "object": obj.name, "group": obj.group, "kind": obj.kind, "method": method.name,
        "against": reference.name if reference else "ground truth", "images_available": len(obj.images),
        "resolution": f"{w}x{h}", "mask_pixels": int(obj.mask.sum()), "bit_depth": obj.bit_depth,
        "notes": list(obj.notes),
    }
    status = _status_for(obj, method, reference)
    if status:
        row["status"] = status
        return row
    subsets = trial_subsets(obj.name, len(obj.images), max_images, trials, seed)
    if reference is None:
        target = obj.normal_gt
    else:
        t0 = time.perf_counter()
        target = reference.run(obj, np.arange(len(obj.images)), seed, ctx)
        row["reference_seconds"] = time.perf_counter() - t0
    per_trial, seconds, light_errs = [], [], []
    for t, idx in enumerate(subsets):
        if ctx.state is not None:
            ctx.state.pop("light_dirs", None)
        t0 = time.perf_counter()
        pred = method.run(obj, idx, seed + t, ctx)
        seconds.append(time.perf_counter() - t0)
        est = ctx.state.pop("light_dirs", None) if ctx.state is not None else None
        if est is not None and obj.light_dirs is not None and len(est) == len(idx):
            light_errs.append(light_angles(est, obj.light_dirs[idx]))
        err = metrics.angular_error_map(pred, target, obj.mask)
        per_trial.append(metrics.summarize_errors(err))
        if t == 0 and error_map is not None:
            write_error_map(error_map, err)
            row["error_map"] = str(error_map)
    maes = [s["mae"] for s in per_trial]
    row.update({
        "status": "ok",
        "images_used": int(len(subsets[0])),
        "trials": len(subsets),
        "mae": float(np.mean(maes)),
        "mae_std": float(np.std(maes)),
        "median": float(np.mean([s["median"] for s in per_trial])),
        "under10": float(np.mean([s["under10"] for s in per_trial])),
        "under20": float(np.mean([s["under20"] for s in per_trial])),
        "under30": float(np.mean([s["under30"] for s in per_trial])),
        "pixels": int(per_trial[0]["pixels"]),
        "seconds": float(np.mean(seconds)),
        "trial_mae": maes,
    })
    if light_errs:  # estimated vs calibrated light directions (a method that estimates lights, e.g. --refine)
        row["light_median"] = float(np.mean([np.median(e) for e in light_errs]))
        row["light_mean"] = float(np.mean([np.mean(e) for e in light_errs]))
        row["light_max"] = float(np.mean([np.max(e) for e in light_errs]))
        row["light_angles"] = [float(v) for v in light_errs[0]]
    return row


def summarize_groups(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per group (and ``"all"``): mean over the evaluated objects of MAE, median and shares; object counts."""
    out: dict[str, dict[str, Any]] = {}
    groups = sorted({r["group"] for r in rows})
    for g in groups + ["all"]:
        members = [r for r in rows if g == "all" or r["group"] == g]
        ok = [r for r in members if r.get("status") == "ok"]
        entry: dict[str, Any] = {"objects": len(members), "evaluated": len(ok)}
        if ok:
            for key in ("mae", "median", "under10", "under20", "under30", "seconds"):
                entry[key] = float(np.mean([r[key] for r in ok]))
        out[g] = entry
    if len(groups) == 1:
        out.pop("all")
    return out


def evaluate(dataset: str | Path, method: str = "least-squares", reference: str | None = None, *,
             objects: list[str] | None = None, max_images: int | None = None, trials: int = 10, seed: int = 0,
             weights: list[str] | None = None, device: str = "cpu", views: int = 1, max_side: int | None = None,
             linear: bool = False, error_map_dir: str | Path | None = None,
             split: str | None = "test", command: str | None = None,
             log: Callable[[str], None] | None = None, refine: bool = False) -> dict[str, Any]:
    """Evaluate ``method`` on every object under ``dataset``; returns the report (see :func:`to_markdown`).
    ``refine``: follow the network (``method="sdm-unips"``) by the photo-consistent fit; objects with calibrated
    lights then also get the angles between estimated and calibrated light directions."""
    m = get_method(method, refine)
    ref = get_method(reference) if reference else None
    if ref is not None and ref.name == m.name:
        raise MatcapError("--reference must differ from --method")
    if trials < 1:
        raise MatcapError(f"--trials must be at least 1, got {trials}")
    if max_images is not None and max_images < m.min_images:
        raise MatcapError(f"--max-images must be at least {m.min_images} for {m.name}, got {max_images}")
    sources, notes = discover(dataset, split=split)
    if objects:
        names = {s.name for s in sources}
        missing = [o for o in objects if o not in names]
        if missing:
            raise MatcapError(f"unknown object(s) {', '.join(missing)}; found: {', '.join(sorted(names))}")
        sources = [s for s in sources if s.name in set(objects)]
    if max_side is not None:
        from matcap.photos import check_max_side  # no torch

        check_max_side(max_side)
    network = ("sdm-unips", REFINED.name)
    if max_side is not None and not {m.name, ref.name if ref else None} & set(network):
        raise MatcapError("--max-side shrinks the network's input: it needs --method or --reference sdm-unips")
    if linear and not {m.name, ref.name if ref else None} & set(network):
        raise MatcapError("--linear changes what the network sees: it needs --method or --reference sdm-unips")
    ctx = MethodContext(weights=weights, device=device, views=views, max_side=max_side, linear=linear, state={})
    rows = []
    t_start = time.perf_counter()
    for i, src in enumerate(sources):
        obj = src.load()
        emap = Path(error_map_dir) / f"{obj.name}.png" if error_map_dir is not None else None
        row = evaluate_object(obj, m, ref, max_images=max_images, trials=trials, seed=seed, ctx=ctx,
                              error_map=emap)
        rows.append(row)
        if log:
            what = (f"{row['mae']:.2f} deg mean, {row['seconds']:.2f} s" if row["status"] == "ok"
                    else row["status"])
            if "light_median" in row:
                what += f", lights {row['light_median']:.2f} deg median"
            log(f"[{i + 1}/{len(sources)}] {obj.name} ({obj.group}): {what}")
        del obj
    report = {
        "command": command,
        "dataset": str(dataset),
        "method": m.name,
        "method_description": m.description,
        "against": ref.name if ref else "ground truth",
        "protocol": {
            "max_images": max_images, "trials": trials, "seed": seed, "views": views, "max_side": max_side,
            "network_8bit": "as stored (linear)" if linear else "sRGB-decoded", "refine": bool(refine),
            "subset_rng": "numpy.random.default_rng([seed, trial, K, crc32(object)])",
            "reference_uses": "all images" if ref else None,
        },
        "robust_thresholds": {"dark_frac": baselines.DEFAULT_DARK_FRAC,
                              "bright_frac": baselines.DEFAULT_BRIGHT_FRAC},
        "convention": CONVENTION,
        "error": "degrees between unit normals inside the mask; zero-length predictions count 90",
        "objects": rows,
        "groups": summarize_groups(rows),
        "skipped_folders": notes,
        "load_s": (ctx.state or {}).get("load_s"),
        "total_seconds": time.perf_counter() - t_start,
    }
    return report


# ----------------------------------------------------------------------------------------------- tables


def _deg(x: float | None) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.2f}"


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.1f}%"


def to_markdown(report: dict[str, Any]) -> str:
    """The report as Markdown: a header, one row per object, one row per group."""
    p = report["protocol"]
    k = p["max_images"]
    lines = [
        f"### `{report['method']}` vs {report['against']}",
        "",
    ]
    if report.get("command"):
        lines += [f"Command: `{report['command']}`", ""]
    lines += [
        f"Dataset `{report['dataset']}`; "
        + (f"K = {k} random images x {p['trials']} trials (seed {p['seed']})" if k else "all images, 1 trial")
        + (f"; reference `{report['against']}` on all images" if p.get("reference_uses") else "")
        + f". Normals in {report['convention']}. Angles in degrees.",
        "",
        "| object | group | images | resolution | mean | median | <10° | <20° | <30° | s/object |",
        "|---|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["objects"]:
        if r.get("status") != "ok":
            lines.append(f"| {r['object']} | {r['group']} | {r['images_available']} | {r['resolution']} | "
                         f"{r['status']} | | | | | |")
            continue
        mean = _deg(r["mae"]) + (f" ± {r['mae_std']:.2f}" if r["trials"] > 1 else "")
        lines.append(f"| {r['object']} | {r['group']} | {r['images_used']} | {r['resolution']} | {mean} | "
                     f"{_deg(r['median'])} | {_pct(r['under10'])} | {_pct(r['under20'])} | {_pct(r['under30'])} | "
                     f"{r['seconds']:.2f} |")
    lines += ["", "| group | objects (evaluated) | mean | median | <10° | <20° | <30° | s/object |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for g, e in report["groups"].items():
        if e["evaluated"]:
            lines.append(f"| {g} | {e['objects']} ({e['evaluated']}) | {_deg(e['mae'])} | {_deg(e['median'])} | "
                         f"{_pct(e['under10'])} | {_pct(e['under20'])} | {_pct(e['under30'])} | "
                         f"{e['seconds']:.2f} |")
        else:
            lines.append(f"| {g} | {e['objects']} (0) | n/a | n/a | n/a | n/a | n/a | n/a |")
    lit = [r for r in report["objects"] if r.get("status") == "ok" and "light_median" in r]
    if lit:
        lines += ["", "Estimated vs calibrated light directions (degrees, per object; mean over trials):", "",
                  "| object | lights | median | mean | max |", "|---|---:|---:|---:|---:|"]
        for r in lit:
            lines.append(f"| {r['object']} | {len(r['light_angles'])} | {_deg(r['light_median'])} | "
                         f"{_deg(r['light_mean'])} | {_deg(r['light_max'])} |")
        lines.append(f"| all ({len(lit)}) | | {_deg(float(np.mean([r['light_median'] for r in lit])))} | "
                     f"{_deg(float(np.mean([r['light_mean'] for r in lit])))} | |")
    if report.get("skipped_folders"):
        lines += ["", "Skipped: " + "; ".join(report["skipped_folders"])]
    return "\n".join(lines) + "\n"


def to_json(report: dict[str, Any]) -> str:
    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list):
            return [clean(v) for v in x]
        if isinstance(x, (np.floating, np.integer)):
            return clean(x.item())
        return x

    return json.dumps(clean(report), indent=2) + "\n"


def evaluate_to_files(dataset: str | Path, method: str = "least-squares", reference: str | None = None, *,
                      out: str | Path | None = None, json_path: str | Path | None = None,
                      markdown_path: str | Path | None = None, overwrite: bool = False,
                      **evaluate_kwargs: Any) -> tuple[dict[str, Any], str]:
    """:func:`evaluate` and write its tables: ``out`` (a new or empty folder unless ``overwrite``) receives
    ``results.md``, ``results.json`` and ``error_maps/<object>.png``, built in a temporary folder that replaces
    ``out`` only when the evaluation is complete; ``json_path`` / ``markdown_path`` receive the JSON report / the
    Markdown table (refused if they exist, unless ``overwrite``). All writes are atomic. Returns the report and
    its Markdown table."""
    import contextlib

    from matcap.imageio import write_text_atomic
    from matcap.results import output_dir

    for flag, name in (("--json", json_path), ("--markdown", markdown_path)):
        if name and Path(name).is_dir():
            raise MatcapError(f"{flag} {name} is a folder; give a file name")
        if name and Path(name).exists() and not overwrite:
            raise MatcapError(f"{flag} {name} already exists; pass --overwrite to replace it")
    out = Path(out) if out is not None else None
    with contextlib.ExitStack() as stack:
        tmp = stack.enter_context(output_dir(out, overwrite)) if out is not None else None
        report = evaluate(dataset, method, reference, error_map_dir=(tmp / "error_maps") if tmp is not None else None,
                          **evaluate_kwargs)
        for row in report["objects"]:  # name the error maps where they will be, not in the temporary folder
            if "error_map" in row:
                row["error_map"] = str(out / "error_maps" / Path(row["error_map"]).name)
        md, js = to_markdown(report), to_json(report)
        if tmp is not None:
            write_text_atomic(tmp / "results.md", md)
            write_text_atomic(tmp / "results.json", js)
    if json_path:
        write_text_atomic(json_path, js)
    if markdown_path:
        write_text_atomic(markdown_path, md)
    return report, md


def stderr_log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)

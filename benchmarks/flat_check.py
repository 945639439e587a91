"""Flat material samples: how well does `matcap capture` recover a swatch photographed flat? Prints a table.

    python benchmarks/flat_check.py                          # all 11 CC0 texture sets, near and far lights,
                                                             # every method this matcap offers, 256 px
    python benchmarks/flat_check.py --sets curtain,sofa_03 --size 128 --conditions near --methods default,lights
    python benchmarks/flat_check.py --work W --json out.json  # W keeps the renders and results: a second run
                                                             # reuses them (resumable)

Each texture set of ``shared/data/textures`` (base colour, OpenGL normal map, roughness / metallic from ``arm`` /
``orm`` (G, B) or ``roughness``; a missing map is the constant :data:`DEFAULT_ROUGHNESS` / :data:`DEFAULT_METALLIC`,
a missing normal map is +z) is centre-cropped square, area-resampled to ``--size`` and rendered with Mitsuba as the
framing plane of :mod:`renderers.plane` (x in [-1, 1]: one sample width is 2 world units) facing the camera, one
texel per pixel, under ``--photos`` lights of one condition:

- ``near``: point lamps 1-3 sample widths from the sample's centre, elevations 25-70 degrees, azimuths spread
  around the circle (a hand-held lamp: the light falls off across the sample);
- ``far``: distant (directional) lights, elevations 30-70 degrees.

Each lamp's strength is set so that the brightest point of the plane receives an irradiance of
:data:`PEAK_IRRADIANCE` (a photographer's exposure), so a white diffuse sample peaks at 0.8; speculars may clip at
1. No ambient light. Photos are 16-bit linear PNGs. The work folder holds per set and condition::

    <set>_<cond>/photos/00.png ...   the photos
    <set>_<cond>/lights.json         the true lights (matcap's lights.json, intensities in the photos' units)
    <set>_<cond>/gt/normal.exr basecolor.exr roughness.exr metallic.exr   the truth (linear)
    <set>_<cond>/sample.json         what was rendered (size, seed, spp, photos, render seconds)
    <set>_<cond>/results/<method>/   `matcap capture`'s result folder
    <set>_<cond>/results/<method>.run.json   the capture command and its wall seconds

The renders use the Mitsuba variant ``renderers.variant.choose_variant`` picks (``MATCAP_MITSUBA_VARIANT=scalar_rgb``
forces the scalar one).

Methods: ``default`` (``matcap capture photos --out R --quiet``), ``lights`` (the same with ``--lights lights.json``,
the true lights in the photos' units), ``relative-lights`` (``--lights`` with their intensities marked relative, as a
calibration's are), ``flat`` and ``flat+lights`` (with ``--flat``; "not available" while ``matcap capture --help`` does
not list it), ``flat+directions`` (``--flat --lights directions.txt``, the distant lights' directions alone, so that the
fit finds each photo's intensity; far lights only), ``flat+guessed-directions`` (the same with directions as a user
who noted only which way each lamp stood would write them: every elevation 45 degrees, each azimuth off by a random
15 degrees, standard deviation; far lights only). The row ``flat plane`` is the baseline that takes every normal to be
the camera axis.

Scores over the whole frame: mean angular normal error (degrees); base colour RMSE in linear RGB after one
least-squares scale per channel (the lights' absolute intensity is unknown to a capture without ``--lights``, so
the colour's overall scale is not scored), and as "% below const." how much lower that is than the RMSE of the
truth's own mean (the best constant); "base level": the result's base colour over the truth's, as the factor
that one least-squares scale over all channels would undo (a mean row gives the typical factor it is off by,
either way, as a value of at least 1); roughness RMSE (no scale) and its % below the best constant, left out
("-") for sets whose roughness is a constant (standard deviation under :data:`CONSTANT_STD`). A mean row
averages each RMSE over the sets that have it and gives "% below const." of that mean RMSE against the mean of
the best constants' RMSEs over the same sets. "light (deg)": the median angle between the lights the result's
lights.json holds and the true ones, seen from the sample's centre; "lamps off (%)": where both are point lights,
the median distance between a found lamp and the true one, in per cent of the true lamp's distance; "fit": whether
the fit of the photos was kept ("fitted", with its light model) or the networks' maps were ("kept networks"); in a
mean row, how many were fitted.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
TEXTURES = REPO.parent / "shared" / "data" / "textures"

CONDITIONS = ("near", "far")
METHODS = ("default", "lights", "relative-lights", "flat", "flat+lights", "flat+directions",
           "flat+guessed-directions")
#: ``flat+guessed-directions``: every light's elevation written as this (degrees above the sample's plane) ...
GUESSED_ELEVATION_DEG = 45.0
#: ... and its azimuth off the true one by a normal random error of this standard deviation (degrees)
GUESSED_AZIMUTH_SD_DEG = 15.0
#: Constants for maps a texture set lacks.
DEFAULT_ROUGHNESS = 0.6
DEFAULT_METALLIC = 0.0
#: Irradiance at the most brightly lit point of the plane (normal +z) in every photo.
PEAK_IRRADIANCE = 2.5
#: Light placement ranges: near lamps' distance from the sample's centre in sample widths (2 world units each),
#: and the elevations (degrees above the sample's plane) of both conditions.
NEAR_DISTANCE_WIDTHS = (1.0, 3.0)
NEAR_ELEVATION_DEG = (25.0, 70.0)
FAR_ELEVATION_DEG = (30.0, 70.0)
SAMPLE_WIDTH = 2.0  # world units: the framing plane spans x in [-1, 1]
#: A truth map whose standard deviation is below this counts as a constant (its "% below const." is not scored).
CONSTANT_STD = 0.01
DEFAULT_SPP = 16  # the lights are points and directions and the texels are nearest: little noise to average
FLAT_NORMAL = (0.0, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------- samples


def texture_sets(root: Path = TEXTURES) -> list[str]:
    """Names of the texture-set folders under ``root`` (sorted)."""
    return sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))


def centre_square(arr: np.ndarray) -> np.ndarray:
    """The largest centred square of an (H, W, ...) array."""
    h, w = arr.shape[:2]
    s = min(h, w)
    top, left = (h - s) // 2, (w - s) // 2
    return arr[top:top + s, left:left + s]


def resample(arr: np.ndarray, size: int) -> np.ndarray:
    """(S, S, ...) -> (size, size, ...) float32 by area averaging (bilinear when enlarging)."""
    import cv2

    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if arr.shape[0] == size:
        return arr
    interp = cv2.INTER_AREA if arr.shape[0] > size else cv2.INTER_LINEAR
    return cv2.resize(arr, (size, size), interpolation=interp)


def load_sample(folder: str | os.PathLike, size: int):
    """A texture set as a square ``size`` x ``size`` flat sample: (MaterialMaps, names of the maps that are
    constants because the set lacks them). Base colour linear (sRGB decoded by ``matcap.formats``), normals
    renormalised after resampling, roughness / metallic filled with the defaults where missing."""
    from matcap.formats import read_texture_set
    from scenes.materialmaps import MaterialMaps

    src = read_texture_set(folder)
    constant = []
    n = resample(centre_square(src.normal), size)
    n /= np.linalg.norm(n, axis=2, keepdims=True).clip(1e-6)
    base = resample(centre_square(src.base_color), size) if src.base_color is not None else None
    if base is None:
        base = np.full((size, size, 3), 0.5, np.float32)
        constant.append("base_color")
    maps = {}
    for name, default in (("roughness", DEFAULT_ROUGHNESS), ("metallic", DEFAULT_METALLIC)):
        arr = getattr(src, name)
        if arr is None:
            maps[name] = np.full((size, size), default, np.float32)
            constant.append(name)
        else:
            maps[name] = resample(centre_square(arr), size)
    if not any(k in src.meta.get("files", {}) for k in ("normal_gl", "normal_dx")):
        constant.append("normal")
    return MaterialMaps(normal=n.astype(np.float32), mask=np.ones((size, size), bool),
                        base_color=np.clip(base, 0.0, 1.0), roughness=np.clip(maps["roughness"], 0.0, 1.0),
                        metallic=np.clip(maps["metallic"], 0.0, 1.0),
                        meta={"source": str(folder), "constant": constant}), constant


# ----------------------------------------------------------------------------------------------- lights


def _spread_azimuths(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` azimuths (radians) spread evenly around the circle from a random start, each jittered by up to a
    quarter step, in a random order."""
    step = 2.0 * np.pi / n
    az = rng.uniform(0, 2 * np.pi) + step * np.arange(n) + rng.uniform(-0.25, 0.25, n) * step
    return rng.permutation(az % (2 * np.pi))


def _unit(elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors at ``elevation`` above the z = 0 plane and ``azimuth`` from +x toward +y."""
    ce = np.cos(elevation)
    return np.stack([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)], axis=1)


def plane_points(size: int) -> np.ndarray:
    """(size * size, 3) world positions of the pixel centres of a square ``size`` framing plane."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)  # row 0 is the top (y = +1)
    return np.stack([x.ravel(), y.ravel(), np.zeros(size * size)], axis=1)


def point_irradiance(position, points: np.ndarray, intensity: float = 1.0) -> np.ndarray:
    """Irradiance on the z = 0 plane (normal +z) at ``points`` (N, 3) from an isotropic lamp of radiant
    ``intensity`` at ``position``: I cos(theta) / r^2 = I z / r^3."""
    d = np.asarray(position, np.float64)[None, :] - points
    r = np.linalg.norm(d, axis=1)
    return intensity * np.clip(d[:, 2], 0.0, None) / r**3


def make_lights(condition: str, n: int, seed: int, size: int = 64):
    """``n`` lights of ``condition`` ("near": PointLight, "far": DirectionalLight), each scaled so that the most
    brightly lit point of the plane (sampled at ``size`` x ``size``) receives :data:`PEAK_IRRADIANCE`."""
    from scenes.lights import DirectionalLight, PointLight

    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {CONDITIONS}, got {condition!r}")
    rng = np.random.default_rng([seed, CONDITIONS.index(condition)])
    az = _spread_azimuths(n, rng)
    lo, hi = NEAR_ELEVATION_DEG if condition == "near" else FAR_ELEVATION_DEG
    el = np.radians(rng.uniform(lo, hi, n))
    dirs = _unit(el, az)
    lights = []
    if condition == "far":
        for d in dirs:
            e = PEAK_IRRADIANCE / d[2]  # irradiance on a surface facing the light; the plane gets e * cos
            lights.append(DirectionalLight(tuple(float(v) for v in d), (e, e, e)))
        return lights
    dist = rng.uniform(*NEAR_DISTANCE_WIDTHS, n) * SAMPLE_WIDTH
    pts = plane_points(size)
    for d, r in zip(dirs, dist):
        pos = d * r
        i = PEAK_IRRADIANCE / float(point_irradiance(pos, pts).max())
        lights.append(PointLight(tuple(float(v) for v in pos), (i, i, i)))
    return lights


def light_entries(lights, files: list[str]) -> list[dict]:
    """matcap lights.json ``images`` entries for ``lights`` (one per photo ``files``), no ambient (SH zero)."""
    from scenes.lights import DirectionalLight

    out = []
    for i, (light, name) in enumerate(zip(lights, files)):
        e = {"index": i, "file": name, "sh": [[0.0, 0.0, 0.0]] * 9}
        if isinstance(light, DirectionalLight):
            e.update(kind="directional", direction=list(light.direction), intensity=list(light.irradiance))
        else:
            e.update(kind="point", position=list(light.position), intensity=list(light.intensity))
        out.append(e)
    return out


# ----------------------------------------------------------------------------------------------- rendering


def render_photos(maps, lights, spp: int = DEFAULT_SPP, seed: int = 0, specular: float | None = None) -> list:
    """One (H, W, 3) linear float32 photo per light: ``maps`` on the framing plane, one texel per pixel
    (``nearest`` texture filter, so the truth is exactly the maps), ``specular``: Principled's (default 0.5)."""
    from renderers.relight import DEFAULT_SPECULAR, render

    spec = DEFAULT_SPECULAR if specular is None else specular
    return [render(maps, [light], spp=spp, seed=seed * 1000 + k, specular=spec, texture_filter="nearest")
            for k, light in enumerate(lights)]


def write_sample(folder: Path, maps, lights, photos: list, info: dict) -> None:
    """Photos (16-bit linear PNG), lights.json, the truth (EXR) and sample.json into ``folder``."""
    from matcap.imageio import write_exr, write_png
    from matcap.refine.lightfile import write_lights
    from scenes.atomic import write_json_atomic

    (folder / "photos").mkdir(parents=True, exist_ok=True)
    (folder / "gt").mkdir(exist_ok=True)
    files = [f"{k:02d}.png" for k in range(len(photos))]
    for name, img in zip(files, photos):
        write_png(folder / "photos" / name, img, bits=16)
    write_lights(folder / "lights.json", light_entries(lights, files), intensity_units="photos",
                 note="true lights of a rendered flat sample (benchmarks/flat_check.py)")
    write_exr(folder / "gt" / "normal.exr", maps.normal)
    write_exr(folder / "gt" / "basecolor.exr", maps.base_color)
    write_exr(folder / "gt" / "roughness.exr", maps.roughness)
    write_exr(folder / "gt" / "metallic.exr", maps.metallic)
    clipped = float(np.mean([np.mean(np.asarray(p) >= 1.0) for p in photos]))
    write_json_atomic(folder / "sample.json", {**info, "clipped_fraction": clipped}, indent=1)


def read_truth(folder: Path) -> dict[str, np.ndarray]:
    from matcap.imageio import read_exr

    return {k: read_exr(folder / "gt" / f"{k}.exr") for k in ("normal", "basecolor", "roughness", "metallic")}


# ----------------------------------------------------------------------------------------------- scores


def mean_angular_error(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean angle (degrees) between the normals ``pred`` and ``gt`` (..., 3) over every pixel; a zero ``pred``
    counts as 90 degrees."""
    from matcap.evaluation.metrics import angular_error_map

    return float(np.nanmean(angular_error_map(pred, gt)))


def rmse(pred: np.ndarray, gt: np.ndarray) -> float:
    d = np.asarray(pred, np.float64) - np.asarray(gt, np.float64)
    return float(np.sqrt(np.mean(d * d)))


def scaled_rmse(pred: np.ndarray, gt: np.ndarray) -> tuple[float, list[float]]:
    """RMSE of ``pred`` (H, W, C) against ``gt`` after the least-squares scale per channel that fits it best:
    (rmse, scales)."""
    p = np.asarray(pred, np.float64).reshape(-1, pred.shape[-1])
    t = np.asarray(gt, np.float64).reshape(-1, gt.shape[-1])
    den = np.sum(p * p, axis=0)
    s = np.where(den > 0, np.sum(p * t, axis=0) / np.where(den > 0, den, 1.0), 0.0)
    return rmse(p * s, t), [float(v) for v in s]


def base_level(pred: np.ndarray, gt: np.ndarray) -> float | None:
    """The overall level of a base colour ``pred`` (H, W, 3) against the truth ``gt``: the factor that one
    least-squares scale over every channel would undo (``pred`` is ``gt`` times this); None where ``pred`` is black."""
    p, t = np.asarray(pred, np.float64).ravel(), np.asarray(gt, np.float64).ravel()
    cross = float(np.sum(p * t))
    return float(np.sum(p * p)) / cross if cross > 0 else None


def constant_rmse(gt: np.ndarray) -> float:
    """RMSE of the best constant prediction (the mean, per channel for (H, W, C))."""
    g = np.asarray(gt, np.float64)
    mean = g.reshape(-1, g.shape[-1]).mean(0) if g.ndim == 3 else g.mean()
    return rmse(np.broadcast_to(mean, g.shape), g)


def below(value: float, reference: float) -> float | None:
    """How much lower ``value`` is than ``reference``, in percent of ``reference`` (None for a zero reference)."""
    return None if reference <= 0 else 100.0 * (1.0 - value / reference)


def score(result, truth: dict[str, np.ndarray], rough_constant: bool) -> dict:
    """Scores of a capture's MaterialMaps ``result`` against ``truth`` (read_truth's dict)."""
    out = {"normal_deg": mean_angular_error(result.normal, truth["normal"])}
    if result.base_color is not None:
        err, scales = scaled_rmse(result.base_color, truth["basecolor"])
        ref = constant_rmse(truth["basecolor"])
        out.update(base_rmse=err, base_scale=scales, base_level=base_level(result.base_color, truth["basecolor"]),
                   base_const_rmse=ref, base_below_pct=below(err, ref))
    if result.roughness is not None and not rough_constant:
        err = rmse(result.roughness, truth["roughness"])
        ref = constant_rmse(truth["roughness"])
        out.update(rough_rmse=err, rough_const_rmse=ref, rough_below_pct=below(err, ref))
    elif result.roughness is not None:
        out["rough_rmse"] = rmse(result.roughness, truth["roughness"])
    if result.metallic is not None:
        out["metal_rmse"] = rmse(result.metallic, truth["metallic"])
    return out


def light_directions(doc: dict) -> dict[int, np.ndarray]:
    """Unit direction toward each photo's light from the sample's centre (the origin), by image index, from a
    lights.json document: a point light's position, a distant light's direction."""
    out = {}
    for e in doc["images"]:
        v = np.asarray(e["position"] if e["kind"] == "point" else e["direction"], np.float64)
        out[e["index"]] = v / max(float(np.linalg.norm(v)), 1e-12)
    return out


def fit_summary(result_dir: Path, true_lights: Path) -> dict:
    """What the fit of a result did (capture.json ``refine``): light model, whether it kept the networks' maps,
    mean re-render PSNR, and the median angle (degrees) between its lights and the true ones (seen from the
    sample's centre)."""
    info = json.loads((result_dir / "capture.json").read_text()).get("refine") or {}
    out = {"light_model": info.get("light_model"), "kept_network_maps": info.get("kept_network_maps"),
           "psnr_db": info.get("psnr_db_mean"), "lights_source": (info.get("lights") or {}).get("source")}
    if (result_dir / "lights.json").is_file():
        got_doc, want_doc = json.loads((result_dir / "lights.json").read_text()), json.loads(true_lights.read_text())
        got, want = light_directions(got_doc), light_directions(want_doc)
        angles = [math.degrees(math.acos(float(np.clip(got[k] @ want[k], -1.0, 1.0)))) for k in want if k in got]
        out["light_deg"] = float(np.median(angles)) if angles else None
        got_p, want_p = lamp_positions(got_doc), lamp_positions(want_doc)
        off = [100.0 * float(np.linalg.norm(got_p[k] - want_p[k]) / max(np.linalg.norm(want_p[k]), 1e-12))
               for k in want_p if k in got_p]
        out["lamp_off_pct"] = float(np.median(off)) if off else None
    return out


def lamp_positions(doc: dict) -> dict[int, np.ndarray]:
    """Each point light's position (the sample's centre is the origin), by image index, from a lights.json
    document; distant lights have none."""
    return {e["index"]: np.asarray(e["position"], np.float64) for e in doc["images"] if e["kind"] == "point"}


def flat_baseline(truth: dict[str, np.ndarray]) -> dict:
    n = np.zeros_like(truth["normal"])
    n[..., :] = FLAT_NORMAL
    return {"normal_deg": mean_angular_error(n, truth["normal"])}


# ----------------------------------------------------------------------------------------------- capture


def flat_available() -> bool:
    """Whether this matcap's ``capture`` has the ``--flat`` option (its --help lists it)."""
    run = subprocess.run([sys.executable, "-m", "matcap", "capture", "--help"], capture_output=True, text=True,
                         env=_env(), cwd=REPO)
    return re.search(r"(?<![\w-])--flat(?![\w-])", run.stdout) is not None


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def capture_args(method: str, folder: Path) -> list[str]:
    args = []
    if method.startswith("flat"):
        args.append("--flat")
    if method in ("lights", "flat+lights"):
        args += ["--lights", str(folder / "lights.json")]
    if method == "flat+directions":
        args += ["--lights", str(write_directions(folder))]
    if method == "flat+guessed-directions":
        args += ["--lights", str(write_guessed_directions(folder))]
    if method == "relative-lights":
        args += ["--lights", str(write_relative(folder))]
    return args


def write_relative(folder: Path) -> Path:
    """``folder``/relative.json: the true lights with their intensities marked relative (their ratios alone, as a
    calibration knows them), so that the fit sets their power from the photos."""
    doc = json.loads((folder / "lights.json").read_text())
    doc["intensity_units"] = "relative"
    path = folder / "relative.json"
    path.write_text(json.dumps(doc, indent=1))
    return path


def write_directions(folder: Path) -> Path:
    """``folder``/directions.txt: the true distant lights' directions alone, one ``x y z`` row per photo in the
    photos' order (a plain light table: each photo's intensity is left to the fit)."""
    doc = json.loads((folder / "lights.json").read_text())
    return _write_table(folder / "directions.txt", [e["direction"] for e in doc["images"]])


def _write_table(path: Path, rows) -> Path:
    """``path``: a plain light table, one ``x y z`` row per photo (``rows`` (K, 3)), in the photos' order."""
    path.write_text("".join(" ".join(f"{v:.9f}" for v in r) + "\n" for r in rows))
    return path


def guessed_directions(directions: np.ndarray, seed: int) -> np.ndarray:
    """(K, 3) unit directions as a user who noted only which way each lamp stood would write them: each true
    direction's azimuth (``directions`` (K, 3), unit, z up) off by a normal random error of
    :data:`GUESSED_AZIMUTH_SD_DEG` (seeded by ``seed``), every elevation :data:`GUESSED_ELEVATION_DEG`."""
    d = np.asarray(directions, np.float64)
    rng = np.random.default_rng([seed, 45])
    az = np.arctan2(d[:, 1], d[:, 0]) + np.radians(rng.normal(0.0, GUESSED_AZIMUTH_SD_DEG, len(d)))
    return _unit(np.full(len(d), np.radians(GUESSED_ELEVATION_DEG)), az)


def write_guessed_directions(folder: Path) -> Path:
    """``folder``/guessed_directions.txt: :func:`guessed_directions` of the true distant lights, one ``x y z`` row per
    photo in the photos' order, seeded by the sample's folder name (the same guesses on every run)."""
    doc = json.loads((folder / "lights.json").read_text())
    seed = zlib.crc32(folder.name.encode())
    rows = guessed_directions(np.array([e["direction"] for e in doc["images"]]), seed)
    return _write_table(folder / "guessed_directions.txt", rows)


def run_capture(method: str, folder: Path) -> tuple[Path, float | None, str | None]:
    """``matcap capture`` of ``folder``/photos by ``method`` into ``folder``/results/<method> unless a result is
    there already: (result folder, wall seconds of the command, error line or None). The command and its seconds
    are kept in ``results/<method>.run.json`` (so a reused result still reports them)."""
    from scenes.atomic import write_json_atomic

    out = folder / "results" / method
    record = folder / "results" / f"{method}.run.json"
    if (out / "capture.json").is_file():
        secs = json.loads(record.read_text()).get("seconds") if record.is_file() else None
        return out, secs, None
    cmd = [sys.executable, "-m", "matcap", "capture", str(folder / "photos"), "--out", str(out), "--quiet",
           "--overwrite"] + capture_args(method, folder)
    t0 = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=REPO)
    secs = time.perf_counter() - t0
    if run.returncode != 0:
        lines = [ln for ln in (run.stderr or run.stdout).strip().splitlines() if ln.strip()]
        return out, secs, lines[-1] if lines else f"exit {run.returncode}"
    write_json_atomic(record, {"command": ["python"] + cmd[1:], "seconds": secs}, indent=1)
    return out, secs, None


# ----------------------------------------------------------------------------------------------- table


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def table(rows: list[dict]) -> str:
    """Markdown table of the scored rows, then one mean row per condition and method."""
    head = ("| set | cond | method | normal (deg) | base RMSE* | base % below const. | base level | rough RMSE | "
            "rough % below const. | light (deg) | lamps off (%) | fit | capture s |")
    lines = [head, "|" + "---|" * 3 + "---:|" * 8 + "---|---:|"]

    def line(r: dict) -> str:
        if r.get("status") and r["status"] != "ok":
            return f"| {r['set']} | {r['condition']} | {r['method']} | {r['status']} | | | | | | | | | |"
        s, fit = r.get("scores", {}), r.get("fit", {})
        how = "-" if not fit else ("kept networks" if fit.get("kept_network_maps") else
                                   f"fitted, {fit.get('light_model')}")
        return (f"| {r['set']} | {r['condition']} | {r['method']} | {_fmt(s.get('normal_deg'), '.2f')} | "
                f"{_fmt(s.get('base_rmse'), '.4f')} | {_fmt(s.get('base_below_pct'), '.0f')} | "
                f"{_fmt(s.get('base_level'), '.2f')} | "
                f"{_fmt(s.get('rough_rmse') if 'rough_below_pct' in s else None, '.4f')} | "
                f"{_fmt(s.get('rough_below_pct'), '.0f')} | {_fmt(fit.get('light_deg'), '.1f')} | "
                f"{_fmt(fit.get('lamp_off_pct'), '.1f')} | {how} | "
                f"{_fmt(r.get('capture_s'), '.0f')} |")

    lines += [line(r) for r in rows]
    for m in means(rows):
        lines.append(line(m))
    return "\n".join(lines)


def means(rows: list[dict]) -> list[dict]:
    """Mean rows per (condition, method) over the sets scored (roughness over the sets that have a map)."""
    out = []
    keys = []
    for r in rows:
        if (r["condition"], r["method"]) not in keys:
            keys.append((r["condition"], r["method"]))
    for cond, method in keys:
        group = [r for r in rows if r["condition"] == cond and r["method"] == method and r.get("status") == "ok"]
        if not group:
            continue
        agg = {}
        for k in ("normal_deg", "metal_rmse"):
            vals = [r["scores"][k] for r in group if r["scores"].get(k) is not None]
            if vals:
                agg[k] = float(np.mean(vals))
        for part in ("base", "rough"):
            have = [r["scores"] for r in group if r["scores"].get(f"{part}_below_pct") is not None]
            if have:
                err = float(np.mean([x[f"{part}_rmse"] for x in have]))
                ref = float(np.mean([x[f"{part}_const_rmse"] for x in have]))
                agg.update({f"{part}_rmse": err, f"{part}_const_rmse": ref, f"{part}_below_pct": below(err, ref),
                            f"{part}_sets": len(have)})
        levels = [r["scores"]["base_level"] for r in group if r["scores"].get("base_level")]
        if levels:  # the typical factor by which the base colour's level is off, either way
            agg["base_level"] = float(np.exp(np.mean(np.abs(np.log(levels)))))
        secs = [r["capture_s"] for r in group if r.get("capture_s") is not None]
        light = [r["fit"]["light_deg"] for r in group if (r.get("fit") or {}).get("light_deg") is not None]
        off = [r["fit"]["lamp_off_pct"] for r in group if (r.get("fit") or {}).get("lamp_off_pct") is not None]
        kept = sum(bool((r.get("fit") or {}).get("kept_network_maps")) for r in group)
        fit = {"light_deg": float(np.mean(light)) if light else None,
               "lamp_off_pct": float(np.mean(off)) if off else None, "kept_network_maps": None,
               "light_model": f"{len(group) - kept} of {len(group)}"} if any(r.get("fit") for r in group) else {}
        out.append({"set": f"mean of {len(group)}", "condition": cond, "method": method, "status": "ok",
                    "scores": agg, "fit": fit, "capture_s": float(np.mean(secs)) if secs else None, "mean": True})
    return out


# ----------------------------------------------------------------------------------------------- main


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2
        sys.stderr.write(f"flat_check.py: error: {message}\n")
        raise SystemExit(2)


def _names(text: str, allowed, what: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in allowed]
    if not items or bad:
        raise argparse.ArgumentTypeError(f"unknown {what} {', '.join(bad) or repr(text)} "
                                         f"(choose from {', '.join(allowed)})")
    return items


def parse_args(argv=None) -> argparse.Namespace:
    sets = texture_sets() if TEXTURES.is_dir() else []
    p = _Parser(description=__doc__.split("\n")[0])
    p.add_argument("--sets", type=lambda t: _names(t, sets, "set"), default=sets,
                   help="comma-separated texture sets (default: all)")
    p.add_argument("--size", type=int, default=256, help="sample side in pixels (default 256)")
    p.add_argument("--conditions", type=lambda t: _names(t, CONDITIONS, "condition"), default=list(CONDITIONS),
                   help="near,far (default both)")
    p.add_argument("--methods", type=lambda t: _names(t, METHODS, "method"), default=list(METHODS),
                   help=f"{','.join(METHODS)} (default all)")
    p.add_argument("--photos", type=int, default=16, help="photos per sample (default 16)")
    p.add_argument("--spp", type=int, default=DEFAULT_SPP, help=f"samples per pixel (default {DEFAULT_SPP})")
    p.add_argument("--seed", type=int, default=0, help="seed of the lights and the renders (default 0)")
    p.add_argument("--work", help="folder for the renders and results; reused when run again (default: a new "
                                  "temporary folder)")
    p.add_argument("--json", help="also write the rows as JSON here")
    args = p.parse_args(argv)
    if not sets:
        p.error(f"no texture sets in {TEXTURES}")
    if not 16 <= args.size <= 4096:
        p.error(f"--size must be between 16 and 4096, got {args.size}")
    if not 2 <= args.photos <= 256:
        p.error(f"--photos must be between 2 and 256, got {args.photos}")
    if args.spp < 1:
        p.error(f"--spp must be at least 1, got {args.spp}")
    if args.seed < 0:
        p.error(f"--seed must be 0 or more, got {args.seed}")
    return args


def prepare(folder: Path, set_name: str, condition: str, args) -> tuple[float | None, list[str], bool]:
    """Render ``set_name`` under ``condition`` into ``folder`` unless sample.json says it is there already with
    these settings: (render seconds, constant maps, reused)."""
    info = {"set": set_name, "condition": condition, "size": args.size, "photos": args.photos, "spp": args.spp,
            "seed": args.seed}
    meta = folder / "sample.json"
    if meta.is_file():
        old = json.loads(meta.read_text())
        if all(old.get(k) == v for k, v in info.items()):
            return old.get("render_s"), old.get("constant", []), True
        import shutil

        shutil.rmtree(folder)  # other settings: the old results do not belong to the new photos
    maps, constant = load_sample(TEXTURES / set_name, args.size)
    lights = make_lights(condition, args.photos, args.seed)
    t0 = time.perf_counter()
    photos = render_photos(maps, lights, spp=args.spp, seed=args.seed)
    secs = time.perf_counter() - t0
    write_sample(folder, maps, lights, photos, {**info, "constant": constant, "render_s": secs})
    return secs, constant, False


def main(argv=None) -> int:
    args = parse_args(argv)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="flat_check-"))
    work.mkdir(parents=True, exist_ok=True)
    wants_flat = any(m.startswith("flat") for m in args.methods)
    has_flat = flat_available() if wants_flat else False
    print(f"work folder {work}" + (f"; --flat {'available' if has_flat else 'not available'} in matcap capture"
                                   if wants_flat else ""), flush=True)
    from matcap.formats import read_result

    rows: list[dict] = []
    for set_name in args.sets:
        for cond in args.conditions:
            folder = work / f"{set_name}_{cond}"
            secs, constant, reused = prepare(folder, set_name, cond, args)
            print(f"{set_name} {cond}: {args.photos} photos " + ("reused" if reused else "rendered")
                  + ("" if secs is None else f" (render {secs:.1f} s)"), flush=True)
            truth = read_truth(folder)
            rough_const = "roughness" in constant or float(np.std(truth["roughness"])) < CONSTANT_STD
            rows.append({"set": set_name, "condition": cond, "method": "flat plane", "status": "ok",
                         "scores": flat_baseline(truth), "capture_s": None, "render_s": secs})
            for method in args.methods:
                row = {"set": set_name, "condition": cond, "method": method, "capture_s": None}
                skipped = ("not applicable" if method.endswith("directions") and cond != "far" else
                           "not available" if method.startswith("flat") and not has_flat else None)
                if skipped:
                    row["status"] = skipped
                    rows.append(row)
                    why = " (its lights are lamps, not directions)" if skipped == "not applicable" else ""
                    print(f"{set_name} {cond} {method}: {skipped}{why}", flush=True)
                    continue
                reused = (folder / "results" / method / "capture.json").is_file()
                out, csecs, error = run_capture(method, folder)
                row["capture_s"] = csecs
                if error is not None:
                    row["status"] = f"failed: {error}"
                    print(f"{set_name} {cond} {method}: failed: {error}", flush=True)
                else:
                    row["status"] = "ok"
                    row["scores"] = score(read_result(out), truth, rough_const)
                    row["fit"] = fit_summary(out, folder / "lights.json")
                    print(f"{set_name} {cond} {method}: normal {row['scores']['normal_deg']:.2f} deg"
                          + (" (result reused)" if reused else f" ({csecs:.0f} s)"), flush=True)
                rows.append(row)
            if args.json:
                _write_json(args, work, rows)
    print()
    print("base RMSE*: linear RGB after one least-squares scale per channel (the lights' absolute intensity is "
          "unknown to a capture); % below const.: lower than the RMSE of the truth's mean by this much; base level: "
          "the result's base colour over the truth's (mean rows: the typical factor off, either way); rough: "
          "'-' where the set's roughness is a constant; light: median angle of the result's lights from the true ones")
    print(table(rows))
    if args.json:
        _write_json(args, work, rows)
    return 0


def _write_json(args, work: Path, rows: list[dict]) -> None:
    from scenes.atomic import write_json_atomic

    doc = {"settings": {k: getattr(args, k) for k in ("sets", "size", "conditions", "methods", "photos", "spp",
                                                       "seed")},
           "work": str(work), "rows": rows, "means": means(rows)}
    write_json_atomic(args.json, doc, indent=1)


if __name__ == "__main__":
    sys.exit(main())

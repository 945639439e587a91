"""Mirror-ball light calibration (`matcap calibrate`) against known lights.

    python benchmarks/calibrate_check.py [--uw ../shared/data/captures/uw_chrome] [--example examples/ball]
                                         [--size 256] [--spp 64]

(a) UW chrome ball (12 photos, 8-bit, 512x340): `matcap calibrate uw_chrome` (ball found automatically, and with
    `--ball-mask chrome.mask.png`) against the folder's `lights.txt` (in `names.txt` order). The floor of that
    comparison is printed too: the circle that best maps the calibration's highlight positions onto `lights.txt`
    (3 free parameters fitted to the answer) still leaves this much, so `lights.txt` was not made from these
    highlight centres with an orthographic ball.
(b) The rendered example scene (Spot and a chrome ball, 16 lights, `renderers.ballscene.example_scene`): rendered
    as float (no clipping) and calibrated with the ball found automatically; the same scene through a pinhole
    camera (focal 400 px at 256 px, 4 units away) calibrated with `focal_px` (and, for contrast, as if
    orthographic); then the bundled `examples/ball` photos (16-bit, clipped highlights) against their
    `lights.json`.
Prints a Markdown table of median / max angular error in degrees and the time of each calibration.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(axis=1), -1, 1)))


def row(label: str, err: np.ndarray, seconds: float, extra: str = "") -> None:
    print(f"| {label} | {np.median(err):.2f} | {err.max():.2f} | {seconds:.1f} | {extra} |", flush=True)


def run_cli(photos: Path, out: Path, *more: str) -> tuple[dict, float]:
    import contextlib
    import io

    from matcap.cli import main

    t = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):  # keep the table clean
        code = main(["calibrate", str(photos), "--out", str(out), "--overwrite", *more])
    if code != 0:
        raise SystemExit(f"matcap calibrate {photos} failed ({code})")
    return json.loads(out.read_text()), time.perf_counter() - t


def uw(folder: Path, tmp: Path) -> None:
    from scipy.optimize import least_squares

    from matcap.calibrate import reflect

    names = (folder / "names.txt").read_text().split()
    truth = np.loadtxt(folder / "lights.txt", skiprows=1)
    for label, more in (("UW chrome, ball found", ()), ("UW chrome, `--ball-mask chrome.mask.png`",
                                                         ("--ball-mask", str(folder / "chrome.mask.png")))):
        doc, secs = run_cli(folder, tmp / "uw" / "rig.json", *more)
        by_name = {e["file"]: e for e in doc["images"]}
        dirs = np.array([by_name[n]["direction"] for n in names])
        err = angles(dirs, truth)
        cx, cy, r = doc["ball"]["circle_px"]
        row(label, err, secs, f"circle ({cx:.1f}, {cy:.1f}, r {r:.1f}); per photo " +
            " ".join(f"{e:.1f}" for e in err))
    # the floor: the circle fitted to lights.txt itself, given the highlight positions
    hl = np.array([by_name[n]["highlight_px"] for n in names])
    size = tuple(doc["ball"]["image_size_wh"][::-1])

    def resid(p):
        d, _ = reflect(hl[:, 0], hl[:, 1], tuple(p), size)
        return (d - truth).ravel()

    best = least_squares(resid, np.array(doc["ball"]["circle_px"], dtype=float)).x
    d, _ = reflect(hl[:, 0], hl[:, 1], tuple(best), size)
    row("UW floor: circle fitted to `lights.txt`", angles(d, truth), 0.0,
        f"circle ({best[0]:.1f}, {best[1]:.1f}, r {best[2]:.1f})")


def rendered(size: int, spp: int, example: Path, tmp: Path) -> None:
    import trimesh

    from matcap.calibrate import calibrate
    from renderers.ballscene import example_scene, render

    mesh = trimesh.load(REPO.parent / "shared" / "data" / "meshes" / "spot.ply", force="mesh", process=False)
    scene = example_scene((np.asarray(mesh.vertices), np.asarray(mesh.faces)))
    t = time.perf_counter()
    r = render(scene, size=size, spp=spp, seed=0)
    t_render = time.perf_counter() - t
    t = time.perf_counter()
    cal = calibrate(list(r.images))
    secs = time.perf_counter() - t
    circle_err = float(np.abs(np.array(cal.circle) - np.array(r.circle)).max())
    inten = ""
    if cal.intensities is not None:
        true = r.irradiance[:, 0] / r.irradiance[:, 0].mean()
        est = cal.intensities.mean(axis=1) / cal.intensities.mean()
        inten = f"; relative intensity error max {100 * np.abs(est / true - 1).max():.0f} %"
    row(f"render {size}px float, {spp} spp, ball found", angles(cal.directions, r.directions), secs,
        f"circle off by {circle_err:.2f} px{inten}; render {t_render:.0f} s")
    # the same scene through a pinhole 4 units away (focal 400 px: 35 deg across), calibrated with --focal-px
    scene.focal_px, scene.camera_distance = 400.0, 4.0
    r = render(scene, size=size, spp=spp, seed=0)
    for focal, label in ((400.0, "perspective model, f = 400 px"), (None, "orthographic model (wrong here)")):
        t = time.perf_counter()
        cal = calibrate(list(r.images), focal_px=focal)
        row(f"render {size}px through a pinhole 4 units away, {label}", angles(cal.directions, r.directions),
            time.perf_counter() - t)
    if (example / "lights.json").is_file():
        truth = json.loads((example / "lights.json").read_text())
        doc, secs = run_cli(example, tmp / "ex" / "rig.json")
        got = {e["file"]: e["direction"] for e in doc["images"]}
        err = angles(np.array([got[e["file"]] for e in truth["images"]]),
                     np.array([e["direction"] for e in truth["images"]]))
        row(f"`{example.relative_to(REPO) if example.is_relative_to(REPO) else example}` (16-bit PNG), ball found",
            err, secs, f"intensity known: {doc['intensity_known']}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--uw", default=str(REPO.parent / "shared" / "data" / "captures" / "uw_chrome"))
    ap.add_argument("--example", default=str(REPO / "examples" / "ball"))
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    args = ap.parse_args(argv)
    print("| lights | median deg | max deg | s | notes |")
    print("|---|---:|---:|---:|---|")
    with tempfile.TemporaryDirectory() as tmp:
        if Path(args.uw).is_dir():
            uw(Path(args.uw), Path(tmp))
        else:
            print(f"| UW chrome: {args.uw} missing | | | | |")
        rendered(args.size, args.spp, Path(args.example).resolve(), Path(tmp))
    return 0


if __name__ == "__main__":
    sys.exit(main())

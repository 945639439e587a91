"""`matcap capture --refine / --no-refine` and `matcap refine RESULT PHOTOS`: outputs, bit-for-bit network maps
without refinement, no silent replacement, one-line errors."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from matcap import imageio
from conftest import sphere_photos
from tests.test_capture import assert_one_line_error, run_cli


# The network maps computed in a fresh interpreter, as the CLI runs: inside pytest another test module may have
# changed torch's thread count, and a different thread count changes the float rounding of the network.
_NETWORK_MAPS = (
    "import sys, numpy as np\n"
    "from matcap.estimate import estimate\n"
    "from matcap.photos import load_capture\n"
    "cap = load_capture(sys.argv[1])\n"
    "maps = estimate(cap.images, cap.mask, weights=[sys.argv[2]], seed=0)\n"
    "np.save(sys.argv[3], np.where(maps.mask[..., None], maps.normal, 0))\n"
)


def test_no_refine_gives_the_network_maps_bit_for_bit(tiny_weights, tmp_path):
    folder = sphere_photos(tmp_path / "photos")
    out = tmp_path / "plain"
    r = run_cli("capture", str(folder), "--out", str(out), "--weights", str(tiny_weights), "--quiet", "--no-refine")
    assert r.returncode == 0, r.stderr
    expected = tmp_path / "network_normal.npy"
    subprocess.run([sys.executable, "-c", _NETWORK_MAPS, str(folder), str(tiny_weights), str(expected)], check=True,
                   timeout=600)
    assert np.array_equal(imageio.read_exr(out / "normal.exr"), np.load(expected))
    assert not (out / "lights.json").exists() and not (out / "fit.json").exists()
    assert "refine" not in json.loads((out / "capture.json").read_text())


def test_capture_refine_writes_lights_fit_and_diagnostics_and_refine_reruns(tiny_weights, tmp_path):
    folder = sphere_photos(tmp_path / "photos", n=5)
    out = tmp_path / "refined"
    r = run_cli("capture", str(folder), "--out", str(out), "--weights", str(tiny_weights), "--quiet", "--refine")
    assert r.returncode == 0, r.stderr
    for name in ("lights.json", "fit.json", "residual.png", "light_variation.png", "normal.exr", "capture.json"):
        assert (out / name).exists(), name
    lights = json.loads((out / "lights.json").read_text())
    assert lights["version"] == 1 and len(lights["images"]) == 5
    first = lights["images"][0]
    assert first["file"] == "img_00.png" and first["kind"] == "directional" and len(first["sh"]) == 9
    fit = json.loads((out / "fit.json").read_text())
    assert len(fit["psnr_db"]) == 5 and fit["settings"]["seed"] == 0 and fit["settings"]["candidates"]["glossy"]
    # tiny random-weight networks: their normals cannot fix the factorization's ambiguity, the check says so and
    # the maps are kept (no per-pixel iterations), with the reason in fit.json
    assert fit["kept_network_maps"] and fit["iterations"]["fine"] == 0 and fit["linear"]["reason"]
    info = json.loads((out / "capture.json").read_text())
    assert {"lights.json", "fit.json"} <= set(info["files"]) and info["refine"]["kept_network_maps"]
    assert np.isfinite(info["refine"]["psnr_db_mean"])  # the random maps, kept, re-rendered under the fitted lights
    # matcap refine: refuses to replace the result without --overwrite, leaves it intact, then replaces it
    before = (out / "normal.exr").read_bytes()
    r2 = run_cli("refine", str(out), str(folder), "--quiet")
    assert_one_line_error(r2, "--overwrite")
    assert (out / "normal.exr").read_bytes() == before
    r3 = run_cli("refine", str(out), str(folder), "--quiet", "--overwrite", "--light-model", "point", "--no-glossy")
    assert r3.returncode == 0, r3.stderr
    entries = json.loads((out / "lights.json").read_text())["images"]
    assert all(("position" if e["kind"] == "point" else "direction") in e for e in entries)  # a lamp left
    fit = json.loads((out / "fit.json").read_text())  # infinitely far by the fit is a directional entry
    assert not fit["settings"]["candidates"]["glossy"] and fit["settings"]["model"]["light"] == "point"
    assert "light_distance_median" in fit  # the lamps' distances were fitted
    assert json.loads((out / "capture.json").read_text())["tool"] == "matcap refine"


def test_refine_bad_input_is_one_line_exit_2(tiny_weights, tmp_path):
    folder = sphere_photos(tmp_path / "photos")
    r = run_cli("refine", str(tmp_path / "nothing"), str(folder), "--out", str(tmp_path / "o"), "--quiet")
    assert_one_line_error(r, "not a result folder")
    r = run_cli("refine", str(tmp_path / "nothing"), str(folder), "--quiet")  # no --out: same, not "--overwrite"
    assert_one_line_error(r, "not a result folder")
    out = tmp_path / "res"
    assert run_cli("capture", str(folder), "--out", str(out), "--weights", str(tiny_weights), "--quiet").returncode == 0
    dark = tmp_path / "dark"
    dark.mkdir()
    for i in range(4):
        imageio.write_png(dark / f"img_{i:02d}.png", np.zeros((40, 56, 3), np.float32), bits=16)
    (dark / "mask.png").write_bytes((folder / "mask.png").read_bytes())
    r = run_cli("refine", str(out), str(dark), "--out", str(tmp_path / "o2"), "--quiet")
    assert_one_line_error(r, "black")
    r = run_cli("refine", str(out), str(folder), "--out", str(tmp_path / "o3"), "--linear", "--srgb")
    assert_one_line_error(r, "not allowed with")

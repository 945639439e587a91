"""8-bit decoding by evidence: a camera's S-shaped tone curve over sRGB (`matcap.imageio.tone_curve`), reading
photos with it undone, and `matcap.capture.decide_colour` choosing among linear, sRGB and tone curves."""
from __future__ import annotations

import json

import numpy as np
import pytest

from matcap import imageio
from matcap.capture import decide_colour
from matcap.errors import MatcapError
from matcap.photos import load_capture
from conftest import sphere_geometry, sphere_photos
from tests.test_capture import assert_one_line_error, run_cli


def test_tone_curve_is_an_s_curve_and_its_inverse_undoes_it():
    x = np.linspace(0.0, 1.0, 1001)
    assert np.array_equal(imageio.tone_curve(x, 1.0), x)
    for c in (1.25, 1.5, 2.0, 3.7):
        y = imageio.tone_curve(x, c)
        assert y[0] == 0.0 and y[-1] == 1.0 and abs(y[500] - 0.5) < 1e-15  # 0, 0.5 and 1 stay put
        assert np.all(np.diff(y) > 0)  # monotone
        assert y[200] < x[200] and y[800] > x[800]  # darker shadows, brighter highlights: more contrast
        assert np.abs(imageio.undo_tone_curve(y, c) - x).max() < 1e-9


def test_contrast_outside_1_to_4_is_refused():
    assert imageio.check_contrast("1.5") == 1.5
    for bad in (0.9, 4.5, float("nan"), "steep", None):
        with pytest.raises(MatcapError, match="tone-curve contrast"):
            imageio.check_contrast(bad)


def _sphere(folder, encode, n: int = 8):
    """A Lambertian sphere (albedo 0.6, black around it) under n distant lights, written as 8-bit PNGs through
    ``encode`` (linear values -> stored values in [0, 1]) with its mask."""
    return sphere_photos(folder, n=n, bits=8, albedo=0.6, background=0.0, spread=0.7, seed=3, encode=encode)


def test_reading_with_a_tone_curve_undoes_it_before_srgb(tmp_path):
    folder = _sphere(tmp_path / "p", lambda v: imageio.tone_curve(imageio.linear_to_srgb(v), 1.5), n=2)
    raw = load_capture(folder, linear=True)
    cap = load_capture(folder, contrast=1.5)
    expect = imageio.srgb_to_linear(imageio.undo_tone_curve(raw.images[0], 1.5))
    assert np.abs(cap.images[0] - expect).max() < 1e-6
    assert "tone curve of contrast 1.50" in cap.colour
    with pytest.raises(MatcapError, match="tone-curve contrast"):
        load_capture(folder, contrast=0.5)


def test_the_fit_keeps_linear_photos_linear(tmp_path):
    """The decision between linear and sRGB (no tone curve is decided: the quick fit's re-render error, measured
    in stored units, favours steeper curves wherever the fit is imperfect; docs/refine.md)."""
    folder = _sphere(tmp_path / "p", lambda v: v)
    linear, record, cap, maps, lamps = decide_colour(folder, None, None, None, {"seed": 0})
    assert linear and record["chosen"] == "linear" and maps is None and lamps is None and len(cap.images) == 8
    assert record["rms_8bit_linear"] < 0.01 and record["rms_8bit_srgb"] > 2 * record["rms_8bit_linear"], record


def _normal_error(result) -> float:
    from matcap.formats import load_maps

    x, y, truth = sphere_geometry()
    maps = load_maps(result)
    m = maps.mask & (x**2 + y**2 < 0.8)
    return float(np.degrees(np.arccos(np.clip((maps.normal[m] * truth[m]).sum(-1), -1, 1))).mean())


def test_undoing_the_cameras_tone_curve_fits_the_photos_better(tmp_path):
    """Photos stored through a tone curve of contrast 1.5: with it undone the fit's normals are closer to the
    sphere's than with plain sRGB decoding (measured 2.4 against 3.6 degrees)."""
    folder = _sphere(tmp_path / "p", lambda v: imageio.tone_curve(imageio.linear_to_srgb(v), 1.5))
    errors = {}
    for c in ("1", "1.5"):
        out = tmp_path / f"r{c}"
        r = run_cli("capture", str(folder), "--out", str(out), "--quiet", "--srgb", "--tone-curve", c)
        assert r.returncode == 0, r.stderr
        errors[c] = _normal_error(out)
        assert not json.loads((out / "fit.json").read_text())["kept_network_maps"]
    assert errors["1.5"] < errors["1"] - 0.5 and errors["1.5"] < 3.0, errors


def test_tone_curve_flags_reach_capture_json_and_contradict_linear(tmp_path):
    folder = _sphere(tmp_path / "p", lambda v: imageio.tone_curve(imageio.linear_to_srgb(v), 1.5), n=4)
    out = tmp_path / "res"
    r = run_cli("capture", str(folder), "--out", str(out), "--quiet", "--tone-curve", "1.5", "--no-refine")
    assert r.returncode == 0, r.stderr
    info = json.loads((out / "capture.json").read_text())
    assert info["tone_curve_contrast"] == 1.5 and "contrast 1.50" in info["colour_handling"]
    assert "colour_decision" not in info  # given, not decided
    r = run_cli("capture", str(folder), "--out", str(tmp_path / "r2"), "--quiet", "--tone-curve", "1.5", "--linear")
    assert_one_line_error(r, "contradicts --linear")
    r = run_cli("capture", str(folder), "--out", str(tmp_path / "r3"), "--quiet", "--tone-curve", "9")
    assert_one_line_error(r, "between 1 (none) and 4")
    r = run_cli("refine", str(out), str(folder), "--out", str(tmp_path / "r4"), "--quiet", "--tone-curve", "2",
                "--linear")
    assert_one_line_error(r, "contradicts --linear")

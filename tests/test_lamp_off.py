"""A photo taken with the lamp off (`--lamp-off`): subtracted from every photo as decoded, clipped observations
kept clipped, bad input one line and exit 2, recorded in capture.json."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from matcap import imageio
from matcap.errors import MatcapError
from matcap.photos import load_capture, subtract_lamp_off


def _folder(tmp_path, room: float = 0.1, bits: int = 16, encode=None):
    """Three lamp photos of a ramp plus a room light that stays on; the lamp-off photo (the room alone) beside the
    folder. Returns (folder, lamp-off file, the lamps' light alone (K, H, W, 3))."""
    folder = tmp_path / "photos"
    folder.mkdir(parents=True)
    h, w = 12, 20
    ramp = np.linspace(0.1, 0.6, w, dtype=np.float32)[None, :, None] * np.ones((h, 1, 3), np.float32)
    lamps = np.stack([ramp * s for s in (0.5, 0.8, 1.0)])
    lamps[2, 0, 0] = 0.95  # with the room's light, above what a PNG holds: clipped
    code = (lambda x: x) if encode is None else encode
    for i, lamp in enumerate(lamps):
        imageio.write_png(folder / f"p{i}.png", code(lamp + room), bits=bits)
    imageio.write_png(tmp_path / "off.png", code(np.full((h, w, 3), room, np.float32)), bits=bits)
    return folder, tmp_path / "off.png", lamps


def test_the_lamp_off_photo_is_subtracted_in_linear_light(tmp_path):
    folder, off, lamps = _folder(tmp_path)
    cap = load_capture(folder, lamp_off=off)
    got = np.stack(cap.images)
    assert np.all(got[2, 0, 0] == got[2].reshape(-1, 3).max(axis=0))  # clipped: kept at the photo's top
    got[2, 0, 0] = lamps[2, 0, 0]
    assert np.abs(got - lamps).max() < 2e-4  # 16-bit quantisation
    srgb_folder, srgb_off, _ = _folder(tmp_path / "srgb", bits=8, encode=imageio.linear_to_srgb)
    decoded = load_capture(srgb_folder)
    dark = imageio.to_linear_float(imageio.read_image(srgb_off))[0]
    got = load_capture(srgb_folder, lamp_off=srgb_off)
    for a, b in zip(got.images, decoded.images):
        np.testing.assert_allclose(a, subtract_lamp_off(b, dark), atol=1e-6)
    steps = np.stack(got.images) - lamps
    steps[2, 0, 0] = 0.0
    assert np.abs(steps).max() < 0.02  # 8-bit sRGB steps


def test_a_clipped_observation_stays_at_the_top_after_the_subtraction():
    photo = np.full((4, 4, 3), 0.5, np.float32)
    photo[0, 0] = 1.0  # clipped
    photo[1, 1] = 0.9
    room = np.zeros_like(photo)
    room[0, 0] = 0.3  # the room lit the clipped pixel more than the one beside it
    out = subtract_lamp_off(photo, room)
    assert np.all(out[0, 0] == out.reshape(-1, 3).max(axis=0)) and np.allclose(out[1, 1], 0.9)
    assert np.allclose(out[2, 2], 0.5) and out.min() >= 0.0
    assert np.allclose(subtract_lamp_off(np.full((2, 2, 3), 0.2, np.float32), np.full((2, 2, 3), 0.3)), 0.0)


def test_bad_lamp_off_photos_are_one_line(tmp_path):
    folder, off, _ = _folder(tmp_path)
    imageio.write_png(folder / "dark.png", np.zeros((12, 20, 3), np.float32))
    with pytest.raises(MatcapError, match="in the photos' folder"):
        load_capture(folder, lamp_off=folder / "dark.png")
    (folder / "dark.png").unlink()
    imageio.write_png(tmp_path / "small.png", np.zeros((6, 10, 3), np.float32))
    with pytest.raises(MatcapError, match="lamp-off photo is 10x6, the photos 20x12"):
        load_capture(folder, lamp_off=tmp_path / "small.png")
    nan = np.zeros((12, 20, 3), np.float32)
    nan[0, 0] = np.nan
    imageio.write_exr(tmp_path / "nan.exr", nan)
    with pytest.raises(MatcapError, match="NaN or Inf"):
        load_capture(folder, lamp_off=tmp_path / "nan.exr")
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(folder), "--lamp-off",
                        str(tmp_path / "missing.png"), "--out", str(tmp_path / "out"), "--no-refine", "--quiet"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "missing.png" in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


def test_capture_records_the_lamp_off_photo(tmp_path, tiny_weights):
    folder, off, _ = _folder(tmp_path)
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(folder), "--lamp-off", str(off), "--out",
                        str(out), "--weights", str(tiny_weights), "--no-refine", "--quiet"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "capture.json").read_text())["lamp_off_file"] == str(off.resolve())

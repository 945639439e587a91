"""`matcap capture --ball`: the lights from a mirror ball inside the capture's own photos (the bundled
`examples/ball`), the ball kept out of the object's mask, and the known lights through the fit."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from matcap import imageio

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "ball"


def _angle(a, b) -> np.ndarray:
    a = np.asarray(a, float) / np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.asarray(b, float) / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


@pytest.mark.skipif(not EXAMPLE.is_dir(), reason="examples/ball is not in this checkout")
def test_capture_with_the_ball_in_the_photos(tmp_path, tiny_weights):
    out = tmp_path / "res"
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(EXAMPLE), "--ball", "auto", "--out", str(out),
                        "--weights", str(tiny_weights), "--linear", "--quiet"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    info = json.loads((out / "capture.json").read_text())
    assert info["refine"]["lights"]["source"] == "ball" and "ball" in info
    doc = json.loads((out / "lights.json").read_text())
    truth = json.loads((EXAMPLE / "lights.json").read_text())
    assert doc["source"] == "ball"
    by_name = {e["file"]: e["direction"] for e in truth["images"]}
    err = _angle([e["direction"] for e in doc["images"]], [by_name[e["file"]] for e in doc["images"]])
    assert np.median(err) < 0.5 and err.max() < 1.0, err
    assert (out / "calibration.png").is_file()
    mask = imageio.read_image(out / "mask.png").pixels[..., 0] > 127
    ball = imageio.read_image(EXAMPLE / "mask_ball.png").pixels[..., 0] > 127
    assert mask.any() and not (mask & ball).any()


def test_ball_and_lights_together_are_refused(tmp_path):
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(tmp_path), "--ball", "auto", "--lights",
                        str(tmp_path / "x.txt"), "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr

"""The `flat` anchor method: its error equals the angle between each true normal and the viewing axis."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from matcap.evaluation import toy


def test_flat_method_error_is_the_tilt_of_the_plane(tmp_path):
    lights = toy.cone_lights(4, 30.0, seed=1)
    normal = np.array([0.3, -0.2, 0.9])
    n, m = toy.plane_normals(16, normal=tuple(normal))
    toy.write_diligent_object(tmp_path / "planePNG", toy.render_lambertian(n, m, lights), m, n, lights)
    out = tmp_path / "flat.json"
    r = subprocess.run([sys.executable, "-m", "matcap", "eval", str(tmp_path), "--method", "flat", "--quiet",
                        "--json", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    tilt = np.degrees(np.arccos(normal[2] / np.linalg.norm(normal)))
    [obj] = json.loads(out.read_text())["objects"]
    assert obj["method"] == "flat" and abs(obj["mae"] - tilt) < 0.05  # normals pass through 16-bit PNG
    assert obj["under10"] == 0.0 and obj["under30"] == 1.0

"""The bundled normal model on data with known geometry: the ToyPS sphere (../shared, SDPS-Net renders).

The sphere's ground truth is analytic: the mask is a disc, so n = ((x - cx) / r, -(y - cy) / r, sqrt(1 - ...)).
The ToyPS images are linear renders stored as 8-bit PNGs, so they are read with ``linear=True`` (what `matcap
capture --linear` does). Decoding them as sRGB photos distorts the shading: the bundled network measures 4.19°
read as linear and 4.39° read as sRGB, so the right decoding must stay the better one and the wrong one must not
break the network.
"""
from __future__ import annotations

import numpy as np
import pytest

from matcap.estimate import estimate
from matcap.evaluation.metrics import analytic_sphere, angular_error_map
from matcap.photos import load_capture
from tests.conftest import REPO, shared_path

NORMAL_WEIGHTS = REPO / "networks" / "weights" / "normal_small.safetensors"


def sphere_error(linear: bool) -> float:
    cap = load_capture(shared_path("data", "captures", "toyps_sphere"), linear=linear)
    maps = estimate(cap.images, cap.mask, weights=[NORMAL_WEIGHTS], max_images=16, seed=0)
    truth, scored = analytic_sphere(cap.mask)
    return float(angular_error_map(maps.normal, truth, scored)[scored].mean())


def test_analytic_sphere_matches_a_drawn_disc():
    mask = np.zeros((64, 64), bool)
    yy, xx = np.mgrid[0:64, 0:64]
    mask[(xx - 30) ** 2 + (yy - 33) ** 2 <= 20 ** 2] = True
    normal, scored = analytic_sphere(mask)
    assert np.allclose(np.linalg.norm(normal[scored], axis=1), 1, atol=1e-6)
    assert np.allclose(normal[33, 30], [0, 0, 1], atol=0.03)  # the centre faces the camera
    assert normal[33, 45, 0] > 0.6 and normal[20, 30, 1] > 0.5  # right of centre: +x; above: +y (y up)
    _, inner = analytic_sphere(mask, rim=0.9)  # the rim band is left out of the scored pixels
    assert mask[33, 50] and scored[33, 50] and not inner[33, 50] and inner[33, 30]
    with pytest.raises(ValueError, match="non-empty"):
        analytic_sphere(np.zeros((8, 8), bool))


@pytest.mark.slow
def test_shipped_normal_model_recovers_the_toyps_sphere():
    linear = sphere_error(linear=True)
    assert linear < 6.0, linear  # python benchmarks/sphere_check.py measures all 50 images
    srgb = sphere_error(linear=False)
    assert linear < srgb < 6.0, (srgb, linear)  # reading linear renders as sRGB photos distorts them

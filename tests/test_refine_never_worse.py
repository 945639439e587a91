"""The estimated-lights fit is never worse than the networks on a matte ball (issue: a real 16-bit matte ball under
16 lamps of unequal power went 3.72 -> 5.57 degrees). The cause measured on rendered balls
(``benchmarks/matte_ball_check.py``): the factorization's lights were right up to a bas-relief, and the
equal-irradiance term of the bas-relief choice bent a good network prior toward lamps more equal than the rig's."""
from __future__ import annotations

import numpy as np
import pytest

from matcap.evaluation.toy import sphere_normals
from matcap.refine import linear as L
from matcap.refine.synthetic import ball_lights


def _angles(a, b) -> np.ndarray:
    a = np.asarray(a, float) / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    b = np.asarray(b, float) / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


def _ball_case(seed: int):
    """A ball's pseudo-normals through a random 3x3 (what a factorization leaves), its lamps (+-30 % power) in the
    same frame, and a network-like prior: 3.7 degrees off (local noise and a small tilt)."""
    n, mask = sphere_normals(96, radius_frac=0.45, max_angle_deg=85.0)
    n = n.astype(np.float64)
    rng = np.random.default_rng(seed)
    dirs, irr = ball_lights(16, seed, unequal=0.3)
    lights = dirs * irr.mean(1, keepdims=True)
    albedo = 0.5 + 0.1 * rng.random(mask.shape)
    a_true = np.eye(3) + rng.normal(0, 0.3, (3, 3))
    b_seen = (n * albedo[..., None]) @ np.linalg.inv(a_true).T
    prior = n + rng.normal(0, 0.05, n.shape)
    prior[..., 1] -= 0.03 * prior[..., 2]
    prior /= np.linalg.norm(prior, axis=-1, keepdims=True)
    return n, mask, b_seen, lights @ a_true, prior


def test_unequal_lamps_leave_a_good_prior_its_bas_relief(monkeypatch):
    """Six balls: the prior alone picks a member 1.0-1.1 degrees from the truth; the equal-irradiance term, free to
    act on lamps that are unequal by design, bent it to 4.5 and 3.9 degrees on two of them (worse than the prior's
    own 3.7). Its bas-relief removes at most a few percent of their log-irradiance variance, so the prior chooses."""
    errs = {"gated": [], "always": []}
    for seed in range(6):
        n, mask, b_seen, lights, prior = _ball_case(seed)
        assert 3.5 < _angles(prior, n)[mask].mean() < 4.0
        for key in errs:
            with monkeypatch.context() as m:
                if key == "always":  # the choice before the gate
                    m.setattr(L, "_explains_inequality", lambda *a: True)
                a = L.integrable_ambiguity(b_seen, mask, prior, mask.astype(float), lights=lights,
                                           equal_lights=150.0, sigma=0.0)
            errs[key].append(float(_angles(b_seen @ a.T, n)[mask].mean()))
    assert max(errs["gated"]) < 1.2, errs
    assert max(errs["always"]) > 3.5, errs  # the failure the gate removes
    # the case equal irradiance is for (equal lamps, a flattened prior) keeps it: tests/test_refine_linear.py::
    # test_equal_irradiance_picks_the_bas_relief_a_flat_prior_misses


@pytest.mark.slow
def test_the_fit_is_not_worse_than_the_networks_on_a_rendered_matte_ball(tmp_path):
    """The whole path on a rendered matte ball (128^2, 16 lamps of +-30 % power, photon and read noise, 16-bit
    linear PNGs): the bundled networks, then the estimated-lights fit, against the analytic sphere (measured:
    networks 3.60, fit 3.30 degrees; 4.67 before the equal-irradiance gate)."""
    import torch

    from matcap.estimate import estimate, load_networks
    from matcap.evaluation.metrics import analytic_sphere, angular_error_map
    from matcap.photos import load_capture
    from matcap.refine import RefineSettings, refine
    from matcap.refine.synthetic import matte_ball

    torch.set_num_threads(1)
    matte_ball(tmp_path / "ball", side=128, seed=0)
    cap = load_capture(tmp_path / "ball", linear=True)
    maps = estimate(cap.images, cap.mask, models=load_networks(None), seed=0)
    truth, scored = analytic_sphere(cap.mask)
    scored &= maps.mask
    res = refine(cap.images, maps, RefineSettings(seed=0))
    net = float(angular_error_map(maps.normal, truth, scored)[scored].mean())
    fit = float(angular_error_map(res.maps.normal, truth, scored)[scored].mean())
    print(f"matte ball 128: networks {net:.2f}, fit {fit:.2f} deg")
    assert not res.report["kept_network_maps"]
    assert fit <= net, (net, fit)

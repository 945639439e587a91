"""The roughness stage of a fit with known lights (:mod:`matcap.refine.roughness`): the choice among the values a
pixel's photos allow, and a rendered two-material swatch whose glossy half the per-pixel solve alone leaves matte."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path

from matcap.refine.roughness import (choose_roughness, follow_targets, group_metallic, held_metallic, material_groups,
                                     object_targets)
from matcap.refine.settings import RoughnessSettings

GRID = RoughnessSettings().grid


def _costs(n_px: int, allowed: list[float], sharp: float = 50.0) -> np.ndarray:
    """(G, n_px) costs: 0 at the grid values in ``allowed``, ``sharp`` elsewhere."""
    c = np.full((len(GRID), n_px), sharp, np.float32)
    for v in allowed:
        c[GRID.index(v)] = 0.0
    return c


def test_decided_pixels_keep_their_own_roughness_and_set_their_groups():
    s = RoughnessSettings(min_decided=5)
    # 40 red pixels decided at 0.1, 40 blue ones decided at 0.75; 20 of each ambiguous between 0.06 and 0.75
    red, blue = np.array([0.8, 0.1, 0.1]), np.array([0.1, 0.1, 0.8])
    costs = np.concatenate([_costs(40, [0.1]), _costs(40, [0.75]), _costs(20, [0.06, 0.75]),
                            _costs(20, [0.06, 0.75])], axis=1)
    base = np.concatenate([np.tile(red, (40, 1)), np.tile(blue, (40, 1)), np.tile(red, (20, 1)),
                           np.tile(blue, (20, 1))])
    choice = choose_roughness(costs, base, np.full(120, 0.5), s, seed=0)
    assert choice.decided[:80].all() and not choice.decided[80:].any()
    np.testing.assert_allclose(choice.rough[:40], 0.1, rtol=0.05)  # a parabola's vertex near the grid value
    np.testing.assert_allclose(choice.rough[40:80], 0.75, rtol=0.05)
    np.testing.assert_allclose(choice.rough[80:100], 0.06, rtol=1e-5)  # the red group's target is 0.1
    np.testing.assert_allclose(choice.rough[100:], 0.75, rtol=1e-5)  # the blue group's is 0.75
    assert choice.record()["decided_share"] == round(80 / 120, 4)


def test_a_decided_pixel_lands_between_grid_values():
    """A cost parabola in log roughness centred at 0.21, between the grid's 0.2 and 0.25: its vertex."""
    lg = np.log(np.asarray(GRID))
    costs = (400.0 * (lg - np.log(0.21)) ** 2)[:, None].astype(np.float32)
    choice = choose_roughness(costs, np.full((1, 3), 0.5), np.full(1, 0.5), RoughnessSettings(), seed=0)
    assert choice.decided[0] and abs(choice.rough[0] - 0.21) < 1e-3, choice.rough


def test_no_decided_pixel_keeps_the_fitted_roughness():
    costs = _costs(30, [0.06, 0.75])
    fitted = np.linspace(0.2, 0.6, 30)
    choice = choose_roughness(costs, np.random.default_rng(0).random((30, 3)), fitted, RoughnessSettings(), seed=0)
    np.testing.assert_allclose(choice.rough, fitted, rtol=1e-6)
    assert not choice.decided.any()


def _valleys(n_px: int, narrow: float, broad: float, depth: float = 30.0) -> np.ndarray:
    """(G, n_px) costs of pixels whose photos show no highlight: two valleys, lowest at ``narrow`` (cost 1) and at
    ``broad`` (cost 0), rising by ``depth`` per unit of log roughness away from each."""
    lg = np.log(np.asarray(GRID))
    c = np.minimum(depth * np.abs(lg - np.log(narrow)) + 1.0, depth * np.abs(lg - np.log(broad)))
    return np.repeat(c[:, None], n_px, axis=1).astype(np.float32)


def test_a_rarely_decided_roughness_counts_for_the_pixels_that_did_not_decide_it():
    """One glaze: 10 pixels saw a lamp's reflection and decided 0.04, 30 at a boundary decided a broad 0.58, 100 saw
    none. Counted alike, the 0.58s set the target and the undecided pixels take a broad lobe; weighed by how rarely
    each value is decided (0.04 on 3% of the pixels, 0.58 on 30%), the target is the glaze's."""
    s = RoughnessSettings(min_decided=5)
    costs = np.concatenate([_costs(10, [0.04]), _costs(30, [0.58]), _valleys(100, 0.04, 0.66)], axis=1)
    base = np.full((140, 3), 0.6)
    rates = np.full(len(GRID), 0.3)
    rates[GRID.index(0.04)] = 0.03
    equal = choose_roughness(costs, base, np.full(140, 0.5), s, seed=0)
    weighed = choose_roughness(costs, base, np.full(140, 0.5), s, seed=0, rates=rates)
    assert abs(equal.targets[0] - 0.58) < 0.01 and np.all(equal.rough[40:] >= 0.58), equal.targets
    assert abs(weighed.targets[0] - 0.04) < 0.005, weighed.targets
    np.testing.assert_allclose(weighed.rough[40:], 0.04, rtol=1e-5)
    np.testing.assert_allclose(weighed.rough[:10], 0.04, rtol=0.05)  # decided pixels keep their own


def test_an_undecided_pixel_settles_at_the_bottom_of_the_valley_the_target_picks():
    """Target 0.5 (its decided pixels); undecided pixels whose broad valley is lowest at 0.85 end at 0.85, not at
    the allowed value nearest the target."""
    s = RoughnessSettings(min_decided=5, tolerance=8.0)
    costs = np.concatenate([_costs(20, [0.5]), _valleys(30, 0.04, 0.85, depth=12.0)], axis=1)
    choice = choose_roughness(costs, np.full((50, 3), 0.4), np.full(50, 0.3), s, seed=0)
    assert abs(choice.targets[0] - 0.5) < 0.01
    np.testing.assert_allclose(choice.rough[20:], 0.85, rtol=1e-5)


def test_an_undecided_pixel_takes_the_valley_its_materials_decided_pixels_are_in():
    """A colour group holding two finishes: 30 pixels decided 0.25, 25 decided 0.85. Their median, 0.25, lies nearer
    the narrow valley (0.1) of the undecided pixels, whose valleys are at 0.1 and 0.85, but the material's decided
    pixels as a whole lie nearer the broad one (mean distance 0.67 against 1.20 in log roughness): they take it."""
    s = RoughnessSettings(min_decided=5, tolerance=8.0)
    costs = np.concatenate([_costs(30, [0.25]), _costs(25, [0.85]), _valleys(40, 0.1, 0.85, depth=30.0)], axis=1)
    choice = choose_roughness(costs, np.full((95, 3), 0.4), np.full(95, 0.5), s, seed=0)
    assert abs(choice.targets[0] - 0.25) < 0.01, choice.targets
    np.testing.assert_allclose(choice.rough[55:], 0.85, rtol=1e-5)


def test_decided_pixels_the_model_does_not_explain_set_no_target():
    """20 pixels decided at 0.1 but with a lowest cost of 40 over 48 observations (not explained) and 20 decided at
    0.43 with cost 2: only the explained ones set the target, where the observation count is given."""
    s = RoughnessSettings(min_decided=5)
    costs = np.concatenate([_costs(20, [0.1], sharp=90.0) + 40.0, _costs(20, [0.43]) + 2.0,
                            _valleys(20, 0.06, 0.5)], axis=1)
    base = np.full((60, 3), 0.3)
    assert choose_roughness(costs, base, np.full(60, 0.3), s, seed=0, observations=48).targets[0] == pytest.approx(
        0.43, rel=0.02)
    counted = choose_roughness(costs, base, np.full(60, 0.3), s, seed=0).targets[0]
    assert counted < 0.43


def test_decision_rates_of_a_plane_under_near_lamps_are_highest_between_the_ends():
    """A plane under the 16 lamps 1-3 widths away of benchmarks/flat_check.py, seen by the fit's own model: a
    middling lobe is decided on many pixels, a mirror-like one only where a lamp's reflection falls, a very broad
    one hardly anywhere."""
    import sys

    import torch

    from matcap.refine.model import LightParams
    from matcap.refine.roughness import decision_rates

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import flat_check as F

    pos = torch.from_numpy(F.plane_points(24)).float()
    n_px = len(pos)
    normal = torch.tensor([0.0, 0.0, 1.0]).repeat(n_px, 1)
    lamps = F.make_lights("near", 16, seed=0, size=24)
    lights = LightParams("point", torch.tensor([l.position for l in lamps]).float(),
                         torch.tensor([l.intensity for l in lamps]).float().log(), torch.zeros(1, 9, 3))
    rates = decision_rates(torch, pos, normal, torch.full((n_px, 3), 0.5), torch.zeros(n_px), lights,
                           RoughnessSettings())
    assert rates.shape == (len(GRID),) and np.all((rates >= 0) & (rates <= 1))
    peak = rates.max()
    assert 0.2 < peak and 0.1 < GRID[int(rates.argmax())] < 0.6, rates
    assert rates[0] < peak / 3 and rates[-1] < peak / 3, rates


def test_an_objects_targets_come_from_its_own_decided_pixels_and_the_typical_from_all():
    s = RoughnessSettings(min_decided=5)
    # group 0: 6 pixels decided at 0.3 and 10 ambiguous; group 1: 6 decided at 0.1; group 2: 3 decided at 0.06
    # (too few for a target of its own) and 10 ambiguous; the typical roughness: the median of all 15, 0.1
    costs = np.concatenate([_costs(6, [0.3]), _costs(10, [0.06, 0.75]), _costs(6, [0.1]), _costs(3, [0.06]),
                            _costs(10, [0.06, 0.75])], axis=1)
    groups = np.array([0] * 16 + [1] * 6 + [2] * 13)
    targets, typical, decided = object_targets(costs, groups, 3, s)
    assert decided[:6].all() and not decided[6:16].any() and decided[16:25].all() and not decided[25:].any()
    assert abs(targets[0] - 0.3) < 0.015 and abs(targets[1] - 0.1) < 0.005 and np.isnan(targets[2]), targets
    assert abs(typical - 0.1) < 0.005, typical
    # too few decided pixels in the whole sample: no target at all
    targets, typical, _ = object_targets(costs[:, 22:], groups[22:] - 2, 1, s)
    assert np.isnan(targets).all() and np.isnan(typical), (targets, typical)


def test_an_objects_decided_pixels_keep_their_fit_and_the_others_follow_their_target():
    costs = np.concatenate([_costs(4, [0.1]), _costs(4, [0.06, 0.66, 0.75])], axis=1)
    fitted = np.array([0.13, 0.2, 0.09, 0.3, 0.3, 0.3, 0.3, 0.3])
    rough, decided = follow_targets(costs, fitted, np.full(8, 0.7), np.ones(8, bool), RoughnessSettings())
    assert decided[:4].all() and not decided[4:].any()
    np.testing.assert_allclose(rough[:4], fitted[:4], rtol=1e-6)  # their own fit, not the grid's 0.1
    np.testing.assert_allclose(rough[4:], 0.66, rtol=1e-6)  # the allowed value nearest 0.7 in log roughness


def test_the_typical_roughness_is_followed_only_where_the_photos_allow_it():
    # a material without a target of its own follows the object's typical 0.3: pixels allowing 0.3 take it; pixels
    # whose photos allow a narrow or a broad lobe but not 0.3 (a rough pixel that saw a broad highlight) keep their
    # fit; a pixel of a material with its own target 0.3 takes the allowed value nearest it even so
    costs = np.concatenate([_costs(2, [0.06, 0.3, 0.75]), _costs(2, [0.06, 0.75]), _costs(1, [0.06, 0.75])], axis=1)
    fitted = np.array([0.7, 0.7, 0.7, 0.66, 0.7])
    own = np.array([False, False, False, False, True])
    rough, decided = follow_targets(costs, fitted, np.full(5, 0.3), own, RoughnessSettings())
    assert not decided.any()
    np.testing.assert_allclose(rough, [0.3, 0.3, 0.7, 0.66, 0.75], rtol=1e-6)


def test_material_groups_split_two_colours():
    base = np.concatenate([np.full((50, 3), 0.8), np.full((50, 3), 0.05)])
    lab = material_groups(base, 2, seed=0)
    assert len(set(lab[:50])) == 1 and len(set(lab[50:])) == 1 and lab[0] != lab[-1]


@pytest.mark.slow
def test_a_glossy_glaze_under_known_lamps_gets_its_roughness():
    """The CC0 tea_set_01 texture set (a glaze of roughness about 0.09) as a 64-pixel flat sample, rendered by
    Mitsuba under 16 lamps 1-3 widths away (benchmarks/flat_check.py's near lights, their file with intensities),
    started from a network-like roughness 0.45: the per-pixel solve alone ends on a broad lobe; the stage finds
    the glaze's."""
    import sys

    from matcap.lightfiles import KnownLights
    from matcap.refine import RefineSettings, refine
    from scenes.materialmaps import MaterialMaps

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import flat_check as F

    truth, _ = F.load_sample(shared_path("data", "textures", "tea_set_01"), 64)
    lamps = F.make_lights("near", 16, seed=0, size=64)
    photos = F.render_photos(truth, lamps, spp=4)
    pos = np.array([l.position for l in lamps])
    known = KnownLights(pos / np.linalg.norm(pos, axis=1, keepdims=True), np.array([l.intensity for l in lamps]),
                        "file", "test", "order", positions=pos)
    shape = truth.mask.shape
    start = MaterialMaps(normal=np.dstack([np.zeros(shape + (2,), np.float32), np.ones(shape + (1,), np.float32)]),
                         mask=truth.mask, base_color=np.full(shape + (3,), 0.5, np.float32),
                         roughness=np.full(shape, 0.45, np.float32), metallic=np.zeros(shape, np.float32))
    rmse = {}
    for iters in (0, RoughnessSettings().iters):
        res = refine(photos, start, RefineSettings(seed=0).replace({"roughness.iters": iters}), lights=known,
                     flat=True)
        rmse[iters] = float(np.sqrt(((res.maps.roughness - truth.roughness) ** 2).mean()))
    assert rmse[0] > 0.3, rmse  # measured 0.51
    assert rmse[RoughnessSettings().iters] < 0.12, rmse  # measured 0.094


def test_shade_base_linear_splits_the_model():
    """shade_fast = const + base x per_base for any base colour, metallic or not, distant or point lights."""
    import torch

    from matcap.refine.model import LightParams, shade_base_linear, shade_fast

    g = torch.Generator().manual_seed(0)
    n_px, k = 400, 6
    normal = torch.nn.functional.normalize(torch.randn(n_px, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 1.0]),
                                           dim=-1)
    base, rough, metal = torch.rand(n_px, 3, generator=g), torch.rand(n_px, generator=g), torch.rand(n_px, generator=g)
    sh = torch.randn(1, 9, 3, generator=g) * 0.05
    pos = torch.cat([torch.rand(n_px, 2, generator=g) * 2 - 1, torch.zeros(n_px, 1)], 1)
    for kind, vec in (("directional", torch.randn(k, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 1.0])),
                      ("point", torch.randn(k, 3, generator=g) + torch.tensor([0.0, 0.0, 4.0]))):
        lights = LightParams(kind, vec, torch.zeros(k, 3), sh)
        wo, irr = lights.incident(pos)
        full = shade_fast(normal, base, rough, metal, wo, irr, sh)
        const, per_base = shade_base_linear(normal, rough, metal, wo, irr, sh)
        assert const.shape == per_base.shape == full.shape
        torch.testing.assert_close(const + base[None] * per_base, full, rtol=1e-4, atol=1e-5)


def _votes(n_px: int, held: float, free: float) -> np.ndarray:
    """(4, n_px) metal_costs rows whose metal-minus-dielectric difference is ``held`` (roughness held) and ``free``
    (roughness free) for every pixel."""
    c = np.zeros((4, n_px), np.float32)
    c[1], c[3] = held, free
    return c


def test_group_metallic_follows_the_photos_where_both_votes_agree():
    s = RoughnessSettings(min_decided=5)
    groups = np.repeat([0, 1, 2, 3], 20)
    costs = np.concatenate([_votes(20, -30, -30),  # metal, held and free
                            _votes(20, 30, 30),  # dielectric
                            _votes(20, 30, -30),  # the votes disagree: no decision
                            _votes(20, 1, -1)], axis=1)  # within the tolerance: no votes, the fitted median
    fitted = np.concatenate([np.full(20, 0.2), np.full(20, 0.7), np.full(20, 0.5), np.full(20, 0.8)])
    out = group_metallic(costs, groups, 5, fitted, s)
    assert out[0] == 1 and out[1] == 0 and np.isnan(out[2]) and out[3] == 1, out
    assert np.isnan(out[4])  # a group without pixels
    # a minority of contrary votes does not turn a group
    c = np.concatenate([_votes(15, -30, -30), _votes(5, 30, 30)], axis=1)
    assert group_metallic(c, np.zeros(20, int), 1, np.zeros(20), s)[0] == 1
    rec = choose_roughness(_costs(3, [0.1]), np.full((3, 3), 0.5), np.full(3, 0.5), s, seed=0)
    rec.metallic = out
    assert rec.record()["group_metallic"] == [1, 0, None, 1, None]


def test_metal_costs_tell_a_rendered_metal_from_a_dielectric():
    """Pixels shaded by the fit's own model under 12 distant lights, half gold metal, half a dielectric of the same
    colour: at their true normals and roughness, each is cheaper as what it is, held and free."""
    import torch

    from matcap.refine import synthetic as S
    from matcap.refine.model import LightParams, shade_fast
    from matcap.refine.roughness import metal_costs

    g = torch.Generator().manual_seed(0)
    n_px = 400
    normal = torch.nn.functional.normalize(torch.randn(n_px, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 1.0]),
                                           dim=-1)
    rough = torch.full((n_px,), 0.3)
    metal = (torch.arange(n_px) < n_px // 2).float()
    base = torch.tensor([0.9, 0.7, 0.4]).expand(n_px, 3)
    dirs = torch.tensor(np.array([l.direction for l in S.known_lights(12)]), dtype=torch.float32)
    lights = LightParams("directional", dirs, torch.zeros(12, 3), torch.zeros(1, 9, 3))
    pos = torch.zeros(n_px, 3)
    wo, irr = lights.incident(pos)
    obs = shade_fast(normal, base, rough, metal, wo, irr, lights.sh)
    upper = torch.full_like(obs, float("inf"))
    c = metal_costs(torch, obs, upper, pos, normal, rough, lights, GRID, 0.04)
    assert c.shape == (4, n_px)
    is_metal = metal.numpy() > 0.5
    for dielectric, metal_row in ((0, 1), (2, 3)):
        d = c[metal_row] - c[dielectric]
        assert (d[is_metal] < -8).mean() > 0.9 and (d[~is_metal] > 8).mean() > 0.9, (d[is_metal], d[~is_metal])


def test_held_metallic_is_the_vote_where_there_is_one_else_the_networks():
    groups = np.array([0, 1, 2, 2, 1, 0])
    prior = np.float32([0.1, 0.6, 0.3, 0.9, 0.2, 0.4])  # the networks' metallic per pixel
    held = held_metallic(np.float32([1.0, np.nan, 0.0]), groups, prior)
    assert held.dtype == np.float32 and held.shape == (6,)
    np.testing.assert_array_equal(held, np.float32([1.0, 0.6, 0.0, 0.0, 0.2, 1.0]))


def test_pooling_takes_the_neighbourhoods_roughness_where_the_photos_allow_it():
    """A dome of one grey material (roughness 0.6) under 12 distant lights, rendered with the fit's own model. A
    third of its pixels (three in every 3 x 3 window) start from a wrong roughness (0.3 or 0.9) with the base colour
    that fits it, and one pixel, whose normal is the half vector of a light (a highlight), is truly glossy (0.1).
    After pooling the wrong values are the neighbourhood's 0.6, their base colour shifted so that the photos are
    explained about as well as where the start was right, and the glossy pixel, whose highlight rules 0.6 out,
    keeps its own. A mixed pixel (half of it a glossy facet turned toward another light), which no single material
    explains (it starts as the broad metal lobe that comes nearest), takes the neighbourhood's values in the fit's
    outputs and keeps its own in maps that place lamps."""
    import torch

    from matcap.refine.brdf_stage import _pool_brdf
    from matcap.refine.photos import _Problem
    from matcap.refine.model import LightParams, PixelParams, shade_base_linear, shade_fast
    from matcap.refine.roughness import _least_squares_base
    from matcap.refine.settings import RefineSettings

    side = 24
    yy, xx = (np.mgrid[0:side, 0:side] + 0.5) / side * 2 - 1
    normal = np.dstack([0.6 * xx, -0.6 * yy, np.ones_like(xx)])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(12, 3))
    d[:, 2] = np.abs(d[:, 2]) + 1.0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    half = d[0] + np.float64([0, 0, 1])
    normal[12, 12] = half / np.linalg.norm(half)  # the glossy pixel faces the half vector of light 0
    rough = np.full((side, side), 0.6)
    rough[12, 12] = 0.1
    base = np.full((side, side, 3), 0.5)
    lights = LightParams("directional", torch.tensor(d, dtype=torch.float32), torch.full((12, 3), float(np.log(2.0))),
                         torch.zeros(1, 9, 3))
    def t(a):  # (side, side[, 3]) -> (N[, 3]) torch
        a = np.asarray(a, np.float32)
        return torch.from_numpy(a.reshape(side * side, *a.shape[2:]).copy())

    with torch.no_grad():
        wo, irr = lights.incident(None)
        obs = shade_fast(t(normal), t(base), t(rough), torch.zeros(side * side), wo, irr, lights.sh)
    stack = obs.numpy().reshape(12, side, side, 3).copy()
    facet = d[3] + np.float64([0, 0, 1])
    with torch.no_grad():
        glossy = shade_fast(torch.tensor(facet / np.linalg.norm(facet), dtype=torch.float32)[None],
                            torch.full((1, 3), 0.5), torch.full((1,), 0.1), torch.zeros(1), wo, irr, lights.sh)
    stack[:, 5, 5] = 0.5 * stack[:, 5, 5] + 0.5 * glossy[:, 0].numpy()  # a mixed pixel
    mask = np.ones((side, side), bool)
    start = rough.copy()
    ii, jj = np.mgrid[0:side, 0:side]
    wrong = (ii + jj) % 3 == 0  # three in every 3 x 3 window
    wrong[12, 12] = False
    start[wrong] = np.where(ii % 2 == 0, 0.3, 0.9)[wrong]
    start[5, 5] = 0.9  # a broad metal lobe explains the glossy half best, the rest not at all
    metal = np.zeros((side, side), np.float32)
    metal[5, 5] = 1.0
    arrays = {"normal": normal.astype(np.float32), "base": base.astype(np.float32),
              "rough": start.astype(np.float32), "metal": metal}
    prob = _Problem(torch, stack, mask, arrays, np.ones((side, side), np.float32), np.full((12, 3), 1e9, np.float32),
                    torch.device("cpu"))
    with torch.no_grad():  # each pixel's base colour as a fit at its start roughness gives it: least squares
        p0, a = shade_base_linear(prob.n0, prob.r0, prob.m0, *lights.incident(prob.pos), lights.sh)
        fitted_base = _least_squares_base(p0, a, prob.obs, torch.ones_like(prob.obs))
    px = PixelParams.from_maps(prob.n0, fitted_base.clamp(0.0, 1.0), prob.r0, prob.m0)
    pooled, share = _pool_brdf(torch, prob, px, lights, (side, side), RefineSettings(), outputs=True)
    for_lamps, _ = _pool_brdf(torch, prob, px, lights, (side, side), RefineSettings(), outputs=False)
    with torch.no_grad():
        got = pooled.rough().numpy().reshape(side, side)
        kept = for_lamps.rough().numpy().reshape(side, side)
    assert abs(got[5, 5] - 0.6) < 1e-3 and abs(kept[5, 5] - 0.9) < 1e-3, (got[5, 5], kept[5, 5])
    assert pooled.metal()[5 * side + 5] < 0.05 and for_lamps.metal()[5 * side + 5] > 0.95
    mixed = np.zeros((side, side), bool)
    mixed[5, 5] = True
    assert np.abs(kept[~mixed] - got[~mixed]).max() < 1e-6  # elsewhere the same
    with torch.no_grad():
        err = lambda p: (shade_fast(p.normal(), p.base(), p.rough(), p.metal(), wo, irr, lights.sh) - obs).abs()  # noqa
        before, after = err(px).mean(dim=(0, 2)).numpy(), err(pooled).mean(dim=(0, 2)).numpy()
    inner = np.zeros((side, side), bool)
    inner[1:-1, 1:-1] = True
    fixed = wrong & inner
    fixed[11:14, 11:14] = False
    assert np.abs(got[fixed] - 0.6).max() < 1e-3, np.abs(got[fixed] - 0.6).max()
    assert abs(got[12, 12] - 0.1) < 1e-3, got[12, 12]  # its highlight rules the neighbourhood's 0.6 out
    after, before = after.reshape(side, side), before.reshape(side, side)
    assert after[fixed].mean() < 0.6 * before[fixed].mean(), (after[fixed].mean(), before[fixed].mean())
    # about as well as the pixels that started right (measured 0.0078 against 0.0055)
    right = ~wrong & inner & ~mixed
    assert after[fixed].mean() < 2.0 * after[right].mean(), (after[fixed].mean(), after[right].mean())
    assert 0.3 < share < 1.0

"""Photo-consistent refinement (matcap.refine): recovers known lights and maps of a capture rendered by our own
Mitsuba relighting path, starting from perturbed ("network-like") maps; diagnostics; bad input."""
from __future__ import annotations

import numpy as np
import pytest

from matcap.errors import MatcapError
from matcap.evaluation.metrics import angular_error_map
from matcap.refine import RefineSettings, light_variation, refine
from matcap.refine import synthetic as S


def _angle(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


@pytest.fixture(scope="module")
def scene():
    truth = S.sphere_maps(48)
    lights = S.known_lights(12)
    photos = S.render_capture(truth, lights)
    return truth, lights, photos


@pytest.fixture(scope="module")
def fitted(scene):
    truth, lights, photos = scene
    start = S.perturb(truth)
    return start, refine(photos, start, RefineSettings(seed=0))


@pytest.mark.slow
def test_recovers_normals_lights_and_glossy_roughness(scene, fitted):
    truth, lights, photos = scene
    start, res = fitted
    m = truth.mask
    before = angular_error_map(start.normal, truth.normal, m)[m].mean()
    after = angular_error_map(res.maps.normal, truth.normal, m)[m].mean()
    assert before > 5.0  # the start is really off
    assert after < 3.0, (before, after)
    errs = [_angle(l.direction, e["direction"]) for l, e in zip(lights, res.lights)]
    assert np.median(errs) < 3.0 and max(errs) < 5.0, errs
    # roughness where the photos show the glossy material's highlight (elsewhere it is not observable)
    gloss = m & (truth.roughness < 0.5)
    seen = S.highlighted(truth.normal[gloss], lights, 6.0)
    assert seen.sum() > 30
    r_err = np.abs(res.maps.roughness[gloss] - truth.roughness[gloss])[seen].mean()
    r_start = np.abs(start.roughness[gloss] - truth.roughness[gloss])[seen].mean()
    assert r_err < 0.1 < r_start, (r_err, r_start)
    assert res.report["psnr_db_mean"] > 30


def test_outputs_and_determinism(scene, fitted):
    truth, lights, photos = scene
    start, res = fitted
    assert len(res.lights) == len(photos)
    for e in res.lights:
        assert e["kind"] == "directional" and len(e["sh"]) == 9 and all(len(r) == 3 for r in e["sh"])
        assert abs(np.linalg.norm(e["direction"]) - 1) < 1e-5
    assert np.isnan(res.residual[~truth.mask]).all() and np.isfinite(res.residual[truth.mask]).all()
    quick = RefineSettings(seed=0).replace({"lights.iters": 30, "pixels.coarse_iters": 0, "pixels.fine_iters": 10})
    again = refine(photos, start, quick)
    again2 = refine(photos, start, quick)
    assert np.array_equal(again.maps.normal, again2.maps.normal)
    assert again.lights == again2.lights


@pytest.fixture(scope="module")
def near_lit():
    """A sphere under 10 lamps 3 half-widths of the frame from its centre (3.2 object radii) plus a uniform
    ambient (about a tenth of the irradiance), and a perturbed start (3.7 degrees)."""
    truth = S.sphere_maps(48)
    lights = S.known_lights(10, kind="point", distance=3.0)
    return truth, lights, S.render_capture(truth, lights), S.perturb(truth, normal_deg=5.0)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["directional", "point"])
def test_near_lamps(near_lit, model):
    """Lamps a few object radii away: their falloff fails the distant-light check. By default the near-lamp check
    then fits their distances and keeps that fit (their loss is a fraction of distant lamps'), as `--refine-light
    point` does: measured 3.69 -> 1.94 degrees, light directions 1.7 degrees (median), distances 3.37."""
    truth, lights, photos, start = near_lit
    s = RefineSettings().replace({"model.light": model, "lights.iters": 250, "pixels.fine_iters": 100})
    res = refine(photos, start, s)
    lin = res.report["linear"]
    assert not res.report["kept_network_maps"] and lin["check"] == "near lamps", lin
    assert "diffuse surface" in lin["reason_lambertian"]
    m = truth.mask
    after = angular_error_map(res.maps.normal, truth.normal, m)[m].mean()
    before = angular_error_map(start.normal, truth.normal, m)[m].mean()
    assert before > 3.5 and after < 2.5, (before, after)
    assert all(e["kind"] == "point" for e in res.lights)
    errs = [_angle(l.position, e["position"]) for l, e in zip(lights, res.lights)]  # the sphere's centre is 0
    assert np.median(errs) < 3.0, errs
    dist = np.median([np.linalg.norm(e["position"]) for e in res.lights])
    assert 2.5 < dist < 3.6 and res.report["light_distance_median"] == pytest.approx(dist, rel=0.05), dist
    found = res.report["near_lamps"]  # the near-lamp check's findings, made before the per-pixel fit
    assert found["light_distance_radii"] < 5.0 and found["ambient_share"] < 0.2
    if model == "directional":
        assert found["loss_ratio"] < 0.8
    else:
        assert found["loss_ratio"] is None  # --refine-light point: only the ambient counts


def test_near_lamps_are_named_in_one_line(near_lit, capsys):
    """`matcap capture` / `matcap refine` say in one line that the lamps were found near, and how near."""
    from matcap.capture import refine_maps
    from matcap.commands.capture import print_fit_notes

    truth, lights, photos, start = near_lit
    names = [f"p{i}.png" for i in range(len(photos))]
    s = RefineSettings().replace({"lights.iters": 250, "pixels.coarse_iters": 0, "pixels.fine_iters": 10})
    refined, _ = refine_maps(start, photos, names, "linear", s, on_fit=print_fit_notes)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lamps were near the object" in err[0] and "object radii away" in err[0], err
    assert refined.meta["refine"]["light_model"] == "point"  # capture.json says what was fitted


def test_light_variation_flags_a_fixed_light():
    rng = np.random.default_rng(0)
    mask = np.ones((20, 20), bool)
    moving = [rng.uniform(0.2, 1.0, (20, 20, 1)) * np.ones(3) for _ in range(6)]
    fixed = [np.full((20, 20, 3), 5.0) + 0.05 * im for im in moving]
    assert np.nanmedian(light_variation(np.stack(moving), mask)) > 0.2
    assert np.nanmedian(light_variation(np.stack(fixed), mask)) < 0.01


@pytest.mark.parametrize("case, needle", [
    ("one", "at least 2 photos"), ("dark", "black"), ("nan", "NaN"),
])
def test_bad_input_is_one_line(case, needle):
    maps = S.sphere_maps(16)
    photos = [np.full((16, 16, 3), 0.3, np.float32) for _ in range(3)]
    if case == "one":
        photos = photos[:1]
    elif case == "dark":
        photos = [p * 0 for p in photos]
    else:
        photos[1][3, 4, 0] = np.nan
    with pytest.raises(MatcapError, match=needle) as exc:
        refine(photos, maps)
    assert "\n" not in str(exc.value)


def test_held_out_light_fit(scene):
    """One photo's light fitted to frozen true maps: the re-render matches it; a mask no wider than its outline
    is one line."""
    import dataclasses

    from matcap.refine.estimated_lights import fit_light_only

    truth, lights, photos = scene
    out = fit_light_only(photos[3], truth)
    assert out["psnr_db"] > 30.0 and _angle(out["light"]["direction"], lights[3].direction) < 3.0
    speck = np.zeros(truth.mask.shape, bool)
    speck[20:22, 20:22] = True
    with pytest.raises(MatcapError, match="no wider than its outline") as exc:
        fit_light_only(photos[3], dataclasses.replace(truth, mask=speck))
    assert "\n" not in str(exc.value)


def _detail(size: int, relief: float):
    """A texture set (size^2) whose normal map is smooth random relief (``relief`` 0: flat), grey base colour."""
    from scipy import ndimage

    from scenes.materialmaps import MaterialMaps

    h = ndimage.gaussian_filter(np.random.default_rng(0).normal(size=(size, size)), 2.0)
    gy, gx = np.gradient(h / h.std() * relief)
    n = np.dstack([-gx, gy, np.ones_like(gx)])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return MaterialMaps(normal=n.astype(np.float32), mask=np.ones((size, size), bool),
                        base_color=np.full((size, size, 3), 0.5, np.float32))


def test_textured_dome_carries_the_detail_in_the_sphere_frame():
    from matcap.evaluation.toy import sphere_normals

    sphere, mask = sphere_normals(40, radius_frac=0.47, max_angle_deg=89.0)
    flat = S.textured_dome(40, _detail(40, 0.0), strength=1.0, roughness=0.3)
    assert np.array_equal(flat.mask, mask)
    assert np.abs(flat.normal - sphere).max() < 1e-5  # a flat normal map leaves the sphere as it is
    detail = _detail(40, 0.5)
    dome = S.textured_dome(40, detail, strength=1.0)
    m = dome.mask
    assert np.allclose(np.linalg.norm(dome.normal[m], axis=-1), 1.0, atol=1e-5)
    # the tangent frame is orthonormal: each pixel's tilt from the sphere is its detail normal's tilt from +z
    tilt = np.degrees(np.arccos(np.clip((dome.normal * sphere).sum(-1), -1, 1)))[m]
    want = np.degrees(np.arccos(np.clip(detail.normal[..., 2], -1, 1)))[m]
    assert np.abs(tilt - want).max() < 0.05 and want.mean() > 5.0
    assert np.all(dome.roughness[m] == np.float32(0.4)) and not dome.normal[~m].any()
    with pytest.raises(ValueError, match="smaller"):
        S.textured_dome(64, detail)


def test_height_from_normals_integrates_a_height_field():
    """The normals of a periodic height field (slopes by central differences, as np.gradient takes them inside
    the image) give the height back, exactly up to its mean; a field with curl loses that part."""
    size = 48
    yy, xx = np.mgrid[0:size, 0:size] * (2 * np.pi / size)
    h = 2.0 * np.sin(xx) * np.cos(2 * yy) + 0.5 * np.cos(3 * xx + yy)
    dh_drow = (np.roll(h, -1, 0) - np.roll(h, 1, 0)) / 2
    dh_dcol = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) / 2
    n = np.dstack([-dh_dcol, dh_drow, np.ones_like(h)])  # y up: dz/dy = -dz/drow
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    got = S.height_from_normals(n)
    assert np.abs(got - (h - h.mean())).max() < 1e-9
    curl = np.dstack([np.sin(yy) * 0.3, np.sin(xx) * 0.3, np.ones_like(h)])  # dz/dx = 0.3 sin y: no height has it
    curl /= np.linalg.norm(curl, axis=-1, keepdims=True)
    assert np.abs(S.height_from_normals(curl)).max() < 1e-9


def test_relief_dome_is_one_height_field():
    """relief_dome: the sphere where the relief is flat; with a textured relief, finite-difference curl of its
    slopes ~0 (textured_dome's baked normal map: far from it), and the detail tilts the sphere's normals."""
    from matcap.evaluation.toy import sphere_normals

    sphere, mask = sphere_normals(40, radius_frac=0.47, max_angle_deg=89.0)
    flat = S.relief_dome(40, _detail(40, 0.0), roughness=0.3)
    assert np.array_equal(flat.mask, mask)
    inner = mask & (sphere[..., 2] > 0.2)
    assert np.abs(flat.normal[inner] - sphere[inner]).max() < 1e-4
    assert np.all(flat.roughness[mask] == np.float32(0.3)) and not flat.normal[~mask].any()

    def curl_ratio(n):
        from scipy import ndimage

        m = ndimage.binary_erosion(inner, iterations=2)
        nz = np.where(mask, n[..., 2], 1.0)  # off the mask the normals are 0
        p, q = -n[..., 0] / nz, -n[..., 1] / nz
        curl = -np.gradient(p, axis=0) - np.gradient(q, axis=1)
        grad = np.abs(np.gradient(p, axis=1)) + np.abs(np.gradient(q, axis=0))
        return float(np.abs(curl[m]).mean() / grad[m].mean())

    rough = _detail(40, 0.5)
    rough.normal[..., 1] *= -1  # a detail field with curl (y flipped), so that integrating it changes it
    relief = S.relief_dome(40, rough, strength=2.0)
    tilt = np.degrees(np.arccos(np.clip((relief.normal * sphere).sum(-1), -1, 1)))[inner]
    assert tilt.mean() > 2.0
    assert curl_ratio(relief.normal.astype(np.float64)) < 0.02
    assert curl_ratio(S.textured_dome(40, rough, strength=2.0).normal.astype(np.float64)) > 0.1


@pytest.mark.slow
def test_a_glossy_textured_dome_is_fitted():
    """One object, one light moved around it, faint ambient (the capture the fit is for; benchmarks/refine_check.py
    dome at 256^2): from perturbed normals (5.9 degrees) to under 2.5 (measured 1.94), lights within 3 degrees."""
    truth = S.textured_dome(96, _detail(96, 0.5), strength=1.0, roughness=0.3)
    lights = S.known_lights(16, seed=3, max_angle_deg=45.0)
    photos = S.render_capture(truth, lights, ambient=0.02, spp=16)
    start = S.perturb(truth)
    res = refine(photos, start, RefineSettings(seed=0))
    m = truth.mask
    before = angular_error_map(start.normal, truth.normal, m)[m].mean()
    after = angular_error_map(res.maps.normal, truth.normal, m)[m].mean()
    assert not res.report["kept_network_maps"]
    assert before > 5.0 and after < 2.5, (before, after)
    errs = [_angle(l.direction, e["direction"]) for l, e in zip(lights, res.lights)]
    assert np.median(errs) < 3.0, errs


@pytest.mark.slow
def test_the_fit_brings_back_detail_the_start_smoothed_away():
    """The networks' failure on fine detail (benchmarks/refine_check.py detail): start from the truth's normals
    blurred (sigma 3 px), as smooth as the network's; the fit takes each pixel's normal from the photos, so the
    detail returns at nearly full strength (high-pass amplitude against the truth's 0.09 -> 0.94, correlation
    0.63 -> 0.99, error 0.079 -> 0.012, measured)."""
    from matcap.evaluation.metrics import detail_scores, high_pass
    from scenes.materialmaps import MaterialMaps

    truth = S.textured_dome(96, _detail(96, 0.5), strength=1.0, roughness=0.3)
    lights = S.known_lights(16, seed=3, max_angle_deg=45.0)
    photos = S.render_capture(truth, lights, ambient=0.02, spp=16)
    m = truth.mask
    blur = truth.normal - high_pass(truth.normal, m, 3.0)  # the low-pass over the mask
    blur = np.where(m[..., None], blur / np.linalg.norm(blur, axis=-1, keepdims=True).clip(1e-9), 0.0)
    perturbed = S.perturb(truth)
    start = MaterialMaps(normal=blur.astype(np.float32), mask=m, base_color=perturbed.base_color,
                         roughness=perturbed.roughness, metallic=perturbed.metallic)
    res = refine(photos, start, RefineSettings(seed=0))
    assert not res.report["kept_network_maps"]
    before, after = detail_scores(start.normal, truth.normal, m), detail_scores(res.maps.normal, truth.normal, m)
    assert before["amplitude"] < 0.15 and after["amplitude"] > 0.8, (before, after)
    assert after["error"] < 0.3 * before["error"] and after["correlation"] > 0.95, (before, after)


def test_detail_scores():
    """Exact on constructed cases: the truth scores itself perfectly, a smooth map carries no detail."""
    from matcap.evaluation.metrics import detail_scores, high_pass

    truth = S.textured_dome(48, _detail(48, 0.5), strength=1.0)
    m = truth.mask
    same = detail_scores(truth.normal, truth.normal, m)
    assert same["error"] == 0.0
    assert same["correlation"] == pytest.approx(1.0) and same["amplitude"] == pytest.approx(1.0)
    flat = np.where(m[..., None], np.float32([0, 0, 1]), 0).astype(np.float32)
    none = detail_scores(flat, truth.normal, m)
    assert none["amplitude"] == pytest.approx(0.0, abs=1e-9)
    assert none["error"] == pytest.approx(none["truth_size"]) and none["truth_size"] > 0.02
    assert np.abs(high_pass(flat, m)[m]).max() < 1e-9  # a constant map has no detail, even at the mask's edge
    with pytest.raises(ValueError, match="do not match"):
        high_pass(flat[:40], m)
    with pytest.raises(ValueError, match="too small"):
        detail_scores(flat, truth.normal, np.eye(48, dtype=bool))


@pytest.mark.parametrize("radii, share, ratio, model, needle", [
    (3.2, 0.036, 0.50, "directional", None),  # a near-lit glossy dome (measured)
    (6.2, 0.007, 0.89, "directional", None),  # lamps at 6.4 radii, glossy: its loss barely moves, the room is dark
    (10.3, 0.005, 0.95, "directional", None),  # lamps at 10.6 radii, glossy, a dark room (measured)
    (10.7, 0.080, 0.97, "directional", "explain little"),  # synthetic scene 20 (directional + environment)
    (13.9, 0.061, 0.95, "directional", "explain little"),  # a dir + turning environment glossy dome (measured)
    (22.2, 0.003, 0.77, "directional", "22.2 object radii"),  # synthetic scene 39: distant lights (the glossy look)
    (None, 0.004, 1.05, "directional", "infinitely far"),
    (5.0, 0.30, 0.50, "directional", "ambient of 30%"),
    (5.0, 0.08, 0.97, "directional", "explain little"),
    (None, 0.10, None, "point", None),  # --refine-light point: the lamps may be far, only the ambient counts
    (2.0, 0.25, None, "point", "ambient of 25%"),
])
def test_near_lamp_verdict(radii, share, ratio, model, needle):
    from matcap.refine.estimated_lights import _near_verdict

    found = {"light_distance_radii": radii, "ambient_share": share, "loss_ratio": ratio}
    why = _near_verdict(found, RefineSettings().replace({"model.light": model}))
    assert (why is None) if needle is None else (needle in why), why


@pytest.mark.parametrize("radii, near_share, glossy_share, trust, want_looks, want_check", [
    (22.0, 0.003, 0.006, 0.05, ["near", "glossy"], "principled"),  # far lamps in a dark room (synthetic scene 39)
    (22.0, 0.003, 0.079, 0.05, ["near", "glossy"], None),  # the distant fit needs an ambient: kept
    (14.0, 0.061, 0.040, 0.05, ["near"], None),  # a turning environment map: the near fit's share stops the glossy look
    (95.0, 0.081, 0.079, 0.05, ["near", "glossy"], "principled"),  # a fixed room light: lamps far, up to 10 %
    (95.0, 0.120, 0.079, 0.05, ["near"], None),  # too much ambient even so
    (22.0, 0.003, 0.006, 0.0, ["near"], None),  # --no-refine-glossy
])
def test_second_looks_run_in_order_and_gate(monkeypatch, radii, near_share, glossy_share, trust, want_looks,
                                            want_check):
    """Control flow of :func:`refine` where the Lambertian check alone fails: the near-lamp candidate first (its
    lamps come out ``radii`` object radii away, beyond the near limit or explaining little: not kept), then glossy
    distant lamps only where the near fit's ambient share is within ``candidates.glossy_ambient``
    (``glossy_ambient_far`` where the lamps stayed ``far_distance`` away), kept where its own is."""
    from matcap.refine import fit as F

    ran = []

    def check(ph, s, whole):  # the first candidate fails the Lambertian part alone; the later ones pass the rest
        report = {"solved_fraction": 0.9, "trusted": not whole,
                  **({"reason": "not Lambertian", "lambertian_only": True} if whole else {})}
        return F._Check(whole, None, None, None, report, "not Lambertian" if whole else None, whole)

    def light_stage(torch, ph, chk, model, s, progress):
        if not chk.whole:
            ran.append(model)
        found = {"light_distance_radii": radii, "ambient_share": near_share, "loss_ratio": 0.99,
                 "solved_fraction": 0.9} if model == "near" else None
        return F._LightStage(object(), chk.reason is None, {}, None, model == "near", None, found, 0,
                             F._Bar(None, s, total=0), 0.0)

    def finish(torch, ph, maps, chk, stage, s, t_start):
        rep = {"linear": dict(chk.report), "ambient_share": glossy_share, "kept_network_maps": not stage.trusted}
        return F.RefineResult(maps=maps, lights=[], report=rep, residual=None, variation=None)

    monkeypatch.setattr(F, "_prepare", lambda images, maps, s: None)
    monkeypatch.setattr(F, "_check", check)
    monkeypatch.setattr(F, "_light_stage", light_stage)
    monkeypatch.setattr(F, "_finish", finish)
    res = F.refine([], None, RefineSettings().replace({"candidates.glossy": trust > 0,
                                                         "candidates.glossy_ambient": trust}))
    assert ran == want_looks
    lin = res.report["linear"]
    assert lin.get("check") == want_check
    if want_check is None:
        assert res.report["kept_network_maps"] and lin["reason"].startswith("not Lambertian; without"), lin
        assert ("ambient of 6%" in lin["reason"]) == (near_share == 0.061), lin["reason"]
    else:
        assert lin["near_fit"]["ambient_share"] == near_share and lin["reason_near"]


def test_settings_replace_checks_each_value_against_its_setting():
    from matcap.refine import RefineSettings

    s = RefineSettings().replace({"lights.iters": 200, "loss.shadow": 0, "candidates.glossy": "false",
                                  "roughness.choose": False, "roughness.grid": [0.1, 0.5], "seed": 3})
    assert s.lights.iters == 200 and s.loss.shadow == 0.0 and isinstance(s.loss.shadow, float)
    assert s.candidates.glossy is False and s.roughness.choose is False and s.roughness.grid == (0.1, 0.5)
    assert s.seed == 3 and RefineSettings().replace({"candidates.glossy": "True"}).candidates.glossy is True
    for key, value, words in (("roughness.choose", "no", "true or false"), ("lights.iters", 2.5, "a whole number"),
                              ("model.light", 3, "a string"), ("loss.cauchy", True, "a number"),
                              ("roughness.grid", ["a"], "a list of numbers")):
        with pytest.raises(MatcapError, match=f"fit setting '{key}' takes {words}"):
            RefineSettings().replace({key: value})
    with pytest.raises(MatcapError, match="no fit setting 'lights.nope'"):
        RefineSettings().replace({"lights.nope": 1})


def test_the_light_fits_adam_steps_as_torch_optim_adam():
    """The light fit's Adam (torch's functional update, without the optimizer class) equals torch.optim.Adam bit
    for bit: two groups at their own step sizes, a parameter without a gradient left as it is."""
    import torch

    from matcap.refine.light_fit import _Adam

    def run(make):
        g = torch.Generator().manual_seed(0)
        a = torch.randn(5, 3, generator=g).requires_grad_(True)
        b = torch.randn(7, generator=g).requires_grad_(True)
        c = torch.randn(2, generator=g).requires_grad_(True)  # not in the loss
        opt = make([a, c], b)
        for i in range(60):
            opt.zero_grad()
            loss = ((a - 1.5) ** 2).sum() * (1 + i % 3) + (b.sin() ** 2).sum()
            loss.backward()
            opt.step()
        return a.detach(), b.detach(), c.detach()

    ours = run(lambda ac, b: _Adam(torch, [(ac, 0.02), ([b], 0.05)]))
    theirs = run(lambda ac, b: torch.optim.Adam([{"params": ac, "lr": 0.02}, {"params": [b], "lr": 0.05}]))
    assert all(torch.equal(p, q) for p, q in zip(ours, theirs))
    assert not torch.equal(ours[0], torch.randn(5, 3, generator=torch.Generator().manual_seed(0)))

"""benchmarks/flat_check.py: its lights, renders, light file and scores on small, checkable cases."""
from __future__ import annotations

import json
import math
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import flat_check as F  # noqa: E402

pytest.importorskip("mitsuba")


def _uniform(size: int, base: float = 0.5, rough: float = 1.0):
    from scenes.materialmaps import MaterialMaps

    n = np.zeros((size, size, 3), np.float32)
    n[..., 2] = 1.0
    return MaterialMaps(normal=n, mask=np.ones((size, size), bool),
                        base_color=np.full((size, size, 3), base, np.float32),
                        roughness=np.full((size, size), rough, np.float32),
                        metallic=np.zeros((size, size), np.float32))


def _disney_diffuse(light_dirs: np.ndarray, roughness: float) -> np.ndarray:
    """Principled (Disney) diffuse factor relative to Lambert for a view along the normal +z: (1 - F_l / 2) +
    R_R F_l with F_l = (1 - cos l)^5 and R_R = 2 roughness cos^2(theta_d), theta_d between l and the half vector."""
    h = light_dirs + np.array([0.0, 0.0, 1.0])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    cos_d = np.sum(light_dirs * h, axis=1)
    fl = (1.0 - light_dirs[:, 2]) ** 5
    return (1.0 - 0.5 * fl) + 2.0 * roughness * cos_d**2 * fl


def test_point_lamp_falloff_matches_inverse_square_times_cosine():
    """A flat diffuse patch (normal +z, no specular lobe) under a near lamp: every pixel's brightness relative to
    the pixel under the lamp is I cos / r^2 (times the Principled diffuse factor) within 3 %."""
    size, rough = 40, 1.0
    from scenes.lights import PointLight

    lamp = PointLight((0.5, 0.25, 0.8), (3.0, 3.0, 3.0))
    img = F.render_photos(_uniform(size, rough=rough), [lamp], spp=4, specular=0.0)[0][..., 0].ravel()
    pts = F.plane_points(size)
    to_lamp = np.asarray(lamp.position)[None] - pts
    to_lamp /= np.linalg.norm(to_lamp, axis=1, keepdims=True)
    expect = F.point_irradiance(lamp.position, pts) * _disney_diffuse(to_lamp, rough)
    under = int(np.argmin(np.linalg.norm(pts[:, :2] - np.asarray(lamp.position[:2]), axis=1)))
    corner = (size - 1) * size  # the bottom-left pixel: the farthest from a lamp at +x, +y
    got = img[under] / img[corner]
    want = expect[under] / expect[corner]
    assert want > 3.0  # the falloff is strong enough to be checked
    assert got == pytest.approx(want, rel=0.03)
    ratio = (img / expect) / (img[under] / expect[under])
    assert np.all(np.abs(ratio - 1.0) < 0.03)
    # absolute level: radiance = albedo / pi * E at the pixel under the lamp
    assert img[under] == pytest.approx(0.5 / math.pi * 3.0 * expect[under], rel=0.03)


def test_distant_light_lights_the_plane_evenly():
    from scenes.lights import DirectionalLight

    d = np.array([0.3, -0.4, 0.866])
    d /= np.linalg.norm(d)
    light = DirectionalLight(tuple(d), (2.0, 2.0, 2.0))
    img = F.render_photos(_uniform(32), [light], spp=4, specular=0.0)[0][..., 1]
    expect = 0.5 / math.pi * 2.0 * d[2] * _disney_diffuse(d[None], 1.0)[0]
    assert np.allclose(img, expect, rtol=0.01)


def test_lights_are_placed_as_asked():
    near = F.make_lights("near", 6, seed=3)
    far = F.make_lights("far", 6, seed=3)
    pts = F.plane_points(64)
    for lamp in near:
        p = np.asarray(lamp.position)
        dist = np.linalg.norm(p) / F.SAMPLE_WIDTH
        elev = math.degrees(math.asin(p[2] / np.linalg.norm(p)))
        assert F.NEAR_DISTANCE_WIDTHS[0] <= dist <= F.NEAR_DISTANCE_WIDTHS[1]
        assert F.NEAR_ELEVATION_DEG[0] <= elev <= F.NEAR_ELEVATION_DEG[1]
        assert F.point_irradiance(p, pts, lamp.intensity[0]).max() == pytest.approx(F.PEAK_IRRADIANCE)
    for light in far:
        d = np.asarray(light.direction)
        assert np.linalg.norm(d) == pytest.approx(1.0)
        assert F.FAR_ELEVATION_DEG[0] <= math.degrees(math.asin(d[2])) <= F.FAR_ELEVATION_DEG[1]
        assert light.irradiance[0] * d[2] == pytest.approx(F.PEAK_IRRADIANCE)
    az = sorted(math.atan2(lamp.position[1], lamp.position[0]) % (2 * math.pi) for lamp in near)
    gaps = np.diff(az + [az[0] + 2 * math.pi])
    assert gaps.max() < 2 * (2 * math.pi / 6)  # spread around: no gap over two even steps
    assert [lamp.position for lamp in F.make_lights("near", 6, seed=3)] == [lamp.position for lamp in near]


def test_written_sample_reads_back(tmp_path):
    """Photos, truth and a lights.json that matcap's light-file reader matches to the photos by name, holding the
    true positions / directions."""
    from matcap.imageio import read_exr, read_image, to_linear_float
    from matcap.lightfiles import read_light_file

    maps = _uniform(16, base=0.25)
    for cond in ("near", "far"):
        lights = F.make_lights(cond, 4, seed=1)
        photos = F.render_photos(maps, lights, spp=1)
        folder = tmp_path / cond
        F.write_sample(folder, maps, lights, photos, {"condition": cond})
        files = sorted(p.name for p in (folder / "photos").iterdir())
        assert files == ["00.png", "01.png", "02.png", "03.png"]
        back, _ = to_linear_float(read_image(folder / "photos" / "02.png"))
        assert np.allclose(back, np.clip(photos[2], 0, 1), atol=1 / 65535)
        known = read_light_file(folder / "lights.json", [str(folder / "photos" / f) for f in files])
        assert known.matched == "name"
        if cond == "near":
            assert np.allclose(known.positions, [lamp.position for lamp in lights])
        else:
            assert known.positions is None
            assert np.allclose(known.directions, [light.direction for light in lights])
            alone = read_light_file(F.write_directions(folder), [str(folder / "photos" / f) for f in files])
            assert alone.intensities is None and alone.matched == "order"
            assert np.allclose(alone.directions, known.directions, atol=1e-8)
        assert np.allclose(known.intensities[:, 0], [(lamp.intensity if cond == "near" else lamp.irradiance)[0]
                                                     for lamp in lights])
        assert np.array_equal(read_exr(folder / "gt" / "normal.exr"), maps.normal)
        assert np.array_equal(read_exr(folder / "gt" / "roughness.exr"), maps.roughness)
        assert json.loads((folder / "sample.json").read_text())["condition"] == cond


def test_guessed_directions_keep_the_side_and_guess_the_height(tmp_path):
    """flat+guessed-directions: every elevation 45 degrees, each azimuth off by a seeded random error of 15 degrees
    (standard deviation), the same file on every run."""
    true = F.make_lights("far", 400, seed=3)
    d = np.array([light.direction for light in true])
    guess = F.guessed_directions(d, seed=7)
    assert np.allclose(np.linalg.norm(guess, axis=1), 1.0)
    assert np.allclose(np.degrees(np.arcsin(guess[:, 2])), F.GUESSED_ELEVATION_DEG)
    off = np.degrees(np.angle(np.exp(1j * (np.arctan2(guess[:, 1], guess[:, 0]) - np.arctan2(d[:, 1], d[:, 0])))))
    assert abs(off.mean()) < 2.5 and 13.5 < off.std() < 16.5, (off.mean(), off.std())
    assert np.array_equal(guess, F.guessed_directions(d, seed=7))
    assert not np.allclose(guess, F.guessed_directions(d, seed=8))
    folder = tmp_path / "set_far"
    F.write_sample(folder, _uniform(8, base=0.25), true[:4], [np.zeros((8, 8, 3), np.float32)] * 4,
                   {"condition": "far"})
    rows = np.loadtxt(F.write_guessed_directions(folder))
    assert rows.shape == (4, 3) and np.allclose(rows, F.guessed_directions(d[:4], zlib.crc32(b"set_far")), atol=1e-8)
    assert F.capture_args("flat+guessed-directions", folder) == ["--flat", "--lights",
                                                                 str(folder / "guessed_directions.txt")]


def test_scores_on_constructed_maps():
    from scenes.materialmaps import MaterialMaps

    size = 8
    gt_n = np.zeros((size, size, 3), np.float32)
    gt_n[..., 2] = 1.0
    tilt = math.radians(12.0)
    pred_n = np.zeros_like(gt_n)
    pred_n[..., 0], pred_n[..., 2] = math.sin(tilt), math.cos(tilt)
    assert F.mean_angular_error(pred_n, gt_n) == pytest.approx(12.0, abs=1e-4)
    assert F.mean_angular_error(np.zeros_like(gt_n), gt_n) == pytest.approx(90.0)

    half = np.zeros((size, size), np.float32)
    half[:, : size // 2] = 1.0  # values 0 and 1 in equal parts: the best constant 0.5 is off by 0.5 everywhere
    assert F.constant_rmse(half) == pytest.approx(0.5)
    assert F.rmse(np.full_like(half, 0.75), half) == pytest.approx(math.sqrt(0.5 * 0.75**2 + 0.5 * 0.25**2))

    rng = np.random.default_rng(0)
    base = rng.uniform(0.1, 0.9, (size, size, 3)).astype(np.float32)
    err, scales = F.scaled_rmse(base * np.float32([0.5, 2.0, 4.0]), base)  # a per-channel scale is not scored
    assert err == pytest.approx(0.0, abs=1e-6)
    assert scales == pytest.approx([2.0, 0.5, 0.25], rel=1e-5)
    assert F.below(0.25, 1.0) == pytest.approx(75.0)

    truth = {"normal": gt_n, "basecolor": base, "roughness": half, "metallic": np.zeros_like(half)}
    result = MaterialMaps(normal=pred_n, mask=np.ones((size, size), bool), base_color=base * 3,
                          roughness=np.full_like(half, 0.5), metallic=np.zeros_like(half))
    s = F.score(result, truth, rough_constant=False)
    assert s["normal_deg"] == pytest.approx(12.0, abs=1e-4)
    assert s["base_rmse"] == pytest.approx(0.0, abs=1e-6) and s["base_below_pct"] == pytest.approx(100.0)
    assert s["base_level"] == pytest.approx(3.0, rel=1e-5)  # the result's base colour is 3x the truth's
    assert F.base_level(base * np.float32([2.0, 2.0, 0.0]), base) > 1.0 and F.base_level(0 * base, base) is None
    assert s["rough_rmse"] == pytest.approx(0.5) and s["rough_below_pct"] == pytest.approx(0.0, abs=1e-9)
    assert "rough_below_pct" not in F.score(result, truth, rough_constant=True)
    assert F.flat_baseline({"normal": pred_n})["normal_deg"] == pytest.approx(12.0, abs=1e-4)


def test_means_and_table():
    rows = [{"set": s, "condition": "near", "method": "default", "status": "ok", "capture_s": 10.0,
             "scores": {"normal_deg": v, "base_rmse": 0.1, "base_const_rmse": 0.2, "base_below_pct": 50.0}}
            for s, v in (("a", 2.0), ("b", 4.0))]
    rows.append({"set": "a", "condition": "near", "method": "flat", "status": "not available", "capture_s": None})
    rows[0]["scores"]["base_level"], rows[1]["scores"]["base_level"] = 2.0, 0.5  # off by 2x either way
    (m,) = F.means(rows)
    assert m["scores"]["normal_deg"] == pytest.approx(3.0) and m["set"] == "mean of 2"
    assert m["scores"]["base_level"] == pytest.approx(2.0)
    assert m["scores"]["base_below_pct"] == pytest.approx(50.0)
    text = F.table(rows)
    assert "| a | near | flat | not available |" in text and "| mean of 2 | near | default | 3.00 |" in text
    assert "| a | near | default | 2.00 | 0.1000 | 50 | 2.00 |" in text


def test_fit_summary_scores_found_lamps_by_angle_and_position(tmp_path):
    """A result's lamps against the true ones: the median angle seen from the centre and the median distance
    between them in per cent of the true lamp's distance (only where both are point lights)."""
    def doc(positions):
        return {"images": [{"index": i, "kind": "point", "position": list(p)} for i, p in enumerate(positions)]}

    true = [(0.0, 0.0, 4.0), (3.0, 0.0, 4.0), (0.0, -2.0, 2.0)]
    got = [(0.0, 0.0, 4.2), (3.0, 0.0, 4.0), (0.0, -2.0, 2.0 + 0.5)]  # 5 %, 0 %, 0.5 / 2.83 = 17.7 % off
    (tmp_path / "result").mkdir()
    (tmp_path / "result" / "capture.json").write_text(json.dumps({"refine": {"light_model": "point"}}))
    (tmp_path / "result" / "lights.json").write_text(json.dumps(doc(got)))
    (tmp_path / "true.json").write_text(json.dumps(doc(true)))
    fit = F.fit_summary(tmp_path / "result", tmp_path / "true.json")
    assert fit["lamp_off_pct"] == pytest.approx(5.0)
    assert fit["light_deg"] == pytest.approx(0.0, abs=1e-6)  # lamp 0 is off along its own direction: no angle
    (tmp_path / "result" / "lights.json").write_text(json.dumps(
        {"images": [{"index": i, "kind": "directional", "direction": [0.0, 0.0, 1.0]} for i in range(3)]}))
    assert F.fit_summary(tmp_path / "result", tmp_path / "true.json")["lamp_off_pct"] is None


@pytest.mark.parametrize("argv", [["--size", "4"], ["--sets", "nope"], ["--conditions", "dim"],
                                  ["--methods", "magic"], ["--seed", "-1"], ["--photos", "1"]])
def test_bad_arguments_exit_2_with_one_line(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        F.parse_args(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("flat_check.py: error:")


def test_a_swatch_and_its_twin_under_distant_lights_give_the_same_photos():
    """benchmarks/flat_twin.py: the relief turned inside out under the lights turned half a turn renders the same
    photos (to float rounding), while the relief turned alone does not."""
    import flat_twin

    maps = _uniform(16, rough=0.4)
    rng = np.random.default_rng(0)
    t = rng.normal(0.0, 0.2, (16, 16, 2)).astype(np.float32)
    n = np.concatenate([t, np.ones((16, 16, 1), np.float32)], -1)
    maps.normal = n / np.linalg.norm(n, axis=-1, keepdims=True)
    lights = F.make_lights("far", 2, 0, 16)
    twin_maps, twin_lights = flat_twin.twin(maps, lights)
    assert np.allclose(twin_maps.normal[..., :2], -maps.normal[..., :2])
    assert [tuple(v.direction) for v in twin_lights] == [(-v.direction[0], -v.direction[1], v.direction[2])
                                                        for v in lights]
    photos = F.render_photos(maps, lights, spp=4, seed=1)
    assert flat_twin.psnr(photos, F.render_photos(twin_maps, twin_lights, spp=4, seed=1)) > 110.0
    assert flat_twin.psnr(photos, F.render_photos(twin_maps, lights, spp=4, seed=1)) < 60.0

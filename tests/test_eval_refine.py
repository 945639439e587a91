"""`matcap eval --method sdm-unips --refine`: plumbing and the light-direction report (stand-in network and fit)."""
import json
import sys
import types

import numpy as np
import pytest

import matcap
from matcap import imageio
from matcap.cli import main
from matcap.evaluation import runner, toy

TILT = 5.0  # degrees the stand-in fit turns every light by (about x)


@pytest.fixture()
def uw_like(tmp_path):
    root = tmp_path / "uw" / "uw_ball"
    root.mkdir(parents=True)
    n, m = toy.sphere_normals(24, max_angle_deg=80.0)
    lights = toy.cone_lights(6, 40.0, seed=5)
    for k, img in enumerate(toy.render_lambertian(n, m, lights)):
        imageio.write_png(root / f"ball.{k}.png", img, bits=8)
    imageio.write_png(root / "ball.mask.png", m.astype(np.float32), bits=8)
    (root / "lights.txt").write_text("6\n" + "\n".join(" ".join(f"{v:.6f}" for v in l) for l in lights) + "\n")
    return root.parent, lights


def _rotate_x(v: np.ndarray, deg: float) -> np.ndarray:
    a = np.radians(deg)
    rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    return v @ rot.T


@pytest.fixture()
def stand_ins(monkeypatch, uw_like):
    """A stand-in network (flat normals) and fit (the calibrated lights tilted by TILT degrees, normals +z)."""
    _, lights = uw_like
    calls = []

    def estimate(images, mask, *, weights=None, max_images=None, seed=0, device="cpu", views=1, progress=False):
        return types.SimpleNamespace(normal=np.where(mask[:, :, None], [0.3, 0.0, 0.954], 0.0), mask=mask)

    def refine(images, maps, settings=None, progress=False):
        calls.append((len(images), settings.seed, settings.device))
        entries = [{"kind": "directional", "direction": list(d), "intensity": [1, 1, 1], "sh": [[0, 0, 0]] * 9}
                   for d in _rotate_x(lights, TILT)]
        entries[0] = dict(entries[0], kind="point", position=list(3.0 * np.asarray(entries[0]["direction"])))
        refined = types.SimpleNamespace(normal=np.where(maps.mask[:, :, None], [0.0, 0.0, 1.0], 0.0))
        return types.SimpleNamespace(maps=refined, lights=entries)

    fake_estimate = types.ModuleType("matcap.estimate")
    fake_estimate.estimate = estimate
    monkeypatch.setitem(sys.modules, "matcap.estimate", fake_estimate)
    monkeypatch.setattr(matcap, "estimate", fake_estimate, raising=False)
    fake_fit = types.ModuleType("matcap.refine.fit")
    fake_fit.refine = refine
    fake_fit.RefineSettings = lambda seed=0, device="cpu": types.SimpleNamespace(seed=seed, device=device)
    monkeypatch.setitem(sys.modules, "matcap.refine.fit", fake_fit)
    return calls


def test_refine_reports_light_direction_errors(uw_like, stand_ins, tmp_path, capsys):
    root, lights = uw_like
    angles = runner.light_angles(_rotate_x(lights, TILT), lights)  # up to TILT (less off the y-z plane)
    assert 2.0 < angles.min() and angles.max() <= TILT + 1e-9
    js = tmp_path / "r.json"
    assert main(["eval", str(root), "--method", "sdm-unips", "--refine", "--reference", "least-squares",
                 "--seed", "3", "--json", str(js), "--quiet"]) == 0
    md = capsys.readouterr().out
    report = json.loads(js.read_text())
    (row,) = report["objects"]
    assert stand_ins == [(6, 3, "cpu")]
    assert report["method"] == "sdm-unips+refine" and "--refine" in report["command"]
    assert report["protocol"]["refine"] is True
    assert row["light_median"] == pytest.approx(np.median(angles), abs=1e-3)
    assert row["light_max"] == pytest.approx(angles.max(), abs=1e-3)
    assert row["light_angles"] == pytest.approx(angles, abs=1e-3)
    assert len(row["light_angles"]) == 6
    assert "Estimated vs calibrated light directions" in md
    assert f"| uw_ball | 6 | {np.median(angles):.2f} | {angles.mean():.2f} | {angles.max():.2f} |" in md
    # the refined normals (+z) are scored, not the network's (tilted 17.5 deg)
    flat = tmp_path / "flat.json"
    assert main(["eval", str(root), "--method", "flat", "--reference", "least-squares", "--json", str(flat),
                 "--quiet"]) == 0
    assert row["mae"] == pytest.approx(json.loads(flat.read_text())["objects"][0]["mae"], abs=1e-6)


def test_refine_with_image_subsets(uw_like, stand_ins, tmp_path):
    """With --max-images the fit's lights (one per image it saw) are compared with those images' lights."""
    root, lights = uw_like

    def refine(images, maps, settings=None, progress=False):  # lights of the images seen, found by brightness
        return types.SimpleNamespace(maps=maps, lights=[{"kind": "directional", "direction": [0.0, 0.0, 1.0]}
                                                        for _ in images])

    sys.modules["matcap.refine.fit"].refine = refine
    js = tmp_path / "r.json"
    assert main(["eval", str(root), "--method", "sdm-unips", "--refine", "--reference", "least-squares",
                 "--max-images", "3", "--trials", "2", "--json", str(js), "--quiet"]) == 0
    (row,) = json.loads(js.read_text())["objects"]
    subsets = runner.trial_subsets("uw_ball", 6, 3, 2, 0)
    expected = np.mean([np.median(runner.light_angles(np.tile([0, 0, 1.0], (3, 1)), lights[idx])) for idx in subsets])
    assert row["light_median"] == pytest.approx(expected, abs=1e-4) and len(row["light_angles"]) == 3


def test_plain_methods_report_no_light_angles(uw_like, tmp_path):
    root, _ = uw_like
    js = tmp_path / "r.json"
    assert main(["eval", str(root), "--method", "flat", "--reference", "least-squares", "--json", str(js),
                 "--quiet"]) == 0
    (row,) = json.loads(js.read_text())["objects"]
    assert "light_median" not in row


def test_refine_needs_the_network(uw_like, capsys):
    root, _ = uw_like
    assert main(["eval", str(root), "--method", "least-squares", "--refine", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--refine refines the network's maps: it needs --method sdm-unips" in err[0]


def test_light_angles():
    a = np.array([[0, 0, 1.0], [1, 0, 0], [0, 2, 0]])
    b = np.array([[0, 0, 2.0], [0, 1, 0], [0, -1, 0]])
    np.testing.assert_allclose(runner.light_angles(a, b), [0.0, 90.0, 180.0], atol=1e-9)

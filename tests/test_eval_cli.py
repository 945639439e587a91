"""`matcap eval` end to end on small analytic objects (no network needed)."""
import json
import sys
import types

import numpy as np
import pytest

import matcap
from matcap import imageio
from matcap.cli import main
from matcap.evaluation import runner, toy


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    lights = toy.cone_lights(8, 35.0, seed=2)
    n, m = toy.sphere_normals(32, max_angle_deg=50.0)
    toy.write_diligent_object(root / "spherePNG", toy.render_lambertian(n, m, lights), m, n, lights)
    n2, m2 = toy.plane_normals(16)
    toy.write_diligent_object(root / "planePNG", toy.render_lambertian(n2, m2, lights), m2, n2, lights)
    return root


@pytest.fixture(scope="module")
def uw_like(tmp_path_factory):
    """A UW-layout capture (8-bit, lights.txt with a count line, no ground truth)."""
    root = tmp_path_factory.mktemp("uw") / "uw_ball"
    root.mkdir()
    n, m = toy.sphere_normals(32, max_angle_deg=80.0)
    lights = toy.cone_lights(12, 40.0, seed=5)
    for k, img in enumerate(toy.render_lambertian(n, m, lights)):
        imageio.write_png(root / f"ball.{k}.png", img, bits=8)
    imageio.write_png(root / "ball.mask.png", m.astype(np.float32), bits=8)
    (root / "lights.txt").write_text("12\n" + "\n".join(" ".join(f"{v:.6f}" for v in l) for l in lights) + "\n")
    return root


def test_least_squares_tables_and_error_maps(dataset, tmp_path, capsys):
    out = tmp_path / "report"
    js = tmp_path / "r.json"
    rc = main(["eval", str(dataset), "--method", "least-squares", "--out", str(out), "--json", str(js), "--quiet"])
    assert rc == 0
    md = capsys.readouterr().out
    assert "| object | group | images | resolution | mean | median |" in md
    assert "Command: `matcap eval " in md and "--method least-squares" in md
    report = json.loads(js.read_text())
    assert report == json.loads((out / "results.json").read_text())
    assert (out / "results.md").read_text() == md
    rows = {r["object"]: r for r in report["objects"]}
    assert set(rows) == {"spherePNG", "planePNG"}
    for r in rows.values():
        assert r["status"] == "ok" and r["mae"] < 0.5 and r["under10"] == 1.0
        assert r["images_used"] == 8 and r["trials"] == 1 and r["seconds"] >= 0
    assert rows["spherePNG"]["resolution"] == "32x32"
    assert report["groups"]["diligent"]["evaluated"] == 2
    emap = imageio.read_image(out / "error_maps" / "spherePNG.png").pixels
    assert emap.dtype == np.uint8 and emap.shape == (32, 32 + 16, 3)
    assert rows["spherePNG"]["error_map"] == str(out / "error_maps" / "spherePNG.png")  # the final place


def test_eval_out_is_replaced_only_by_a_complete_evaluation(dataset, tmp_path, monkeypatch, capsys):
    from matcap.evaluation import runner

    out = tmp_path / "report"
    assert main(["eval", str(dataset), "--method", "least-squares", "--out", str(out), "--quiet"]) == 0
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    first = runner.evaluate_object

    def second_object_fails(obj, *args, **kwargs):
        if obj.name == "spherePNG":
            raise ValueError("disk full")
        return first(obj, *args, **kwargs)

    monkeypatch.setattr(runner, "evaluate_object", second_object_fails)
    assert main(["eval", str(dataset), "--method", "flat", "--out", str(out), "--overwrite", "--quiet"]) == 2
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before  # the earlier evaluation, untouched
    assert "--method least-squares" in (out / "results.md").read_text()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".report")]  # no temporary folder left


def test_image_subsets_protocol(dataset, tmp_path, capsys):
    js = tmp_path / "r.json"
    rc = main(["eval", str(dataset), "--method", "least-squares-robust", "--objects", "spherePNG",
               "--max-images", "5", "--trials", "3", "--json", str(js), "--quiet"])
    assert rc == 0
    (row,) = json.loads(js.read_text())["objects"]
    assert row["images_used"] == 5 and row["trials"] == 3 and len(row["trial_mae"]) == 3
    a = runner.trial_subsets("spherePNG", 8, 5, 3, seed=0)
    assert [list(x) for x in a] == [list(x) for x in runner.trial_subsets("spherePNG", 8, 5, 3, seed=0)]
    assert all(len(x) == 5 and list(x) == sorted(x) for x in a)
    assert len({tuple(x) for x in a}) > 1
    assert len(runner.trial_subsets("spherePNG", 8, None, 3, seed=0)) == 1


def test_reference_mode_without_ground_truth(uw_like, tmp_path, capsys):
    js = tmp_path / "r.json"
    assert main(["eval", str(uw_like), "--json", str(js), "--quiet"]) == 0
    assert "no ground-truth normals" in json.loads(js.read_text())["objects"][0]["status"]
    rc = main(["eval", str(uw_like), "--method", "least-squares-robust", "--reference", "least-squares",
               "--json", str(js), "--overwrite", "--quiet"])
    assert rc == 0
    (row,) = json.loads(js.read_text())["objects"]
    assert row["status"] == "ok" and row["against"] == "least-squares" and row["group"] == "uw"
    assert row["mae"] < 5.0  # two baselines on a (shadowed, 8-bit) Lambertian sphere roughly agree


def _fake_estimate(monkeypatch, record) -> types.ModuleType:
    """Install a stand-in ``matcap.estimate`` whose ``estimate`` calls ``record(images, mask, weights, seed, views)``
    and returns flat normals (the evaluation runner imports the real one lazily)."""

    def estimate(images, mask, *, weights=None, max_images=None, seed=0, device="cpu", views=1, progress=False):
        record(images, mask, weights, seed, views)
        return types.SimpleNamespace(normal=np.where(mask[:, :, None], [0.0, 0.0, 1.0], 0.0))

    fake = types.ModuleType("matcap.estimate")
    fake.estimate = estimate
    monkeypatch.setitem(sys.modules, "matcap.estimate", fake)
    monkeypatch.setattr(matcap, "estimate", fake, raising=False)
    return fake


def test_learned_method_gets_images_lazily(dataset, tmp_path, monkeypatch, capsys):
    calls = []
    _fake_estimate(monkeypatch, lambda images, mask, weights, seed, views: calls.append((len(images), seed, weights)))
    js = tmp_path / "r.json"
    rc = main(["eval", str(dataset), "--method", "sdm-unips", "--objects", "planePNG", "--max-images", "4",
               "--trials", "2", "--weights", "w.safetensors", "--json", str(js), "--quiet"])
    assert rc == 0
    assert calls == [(4, 0, ["w.safetensors"]), (4, 1, ["w.safetensors"])]
    (row,) = json.loads(js.read_text())["objects"]
    tilt = np.degrees(np.arccos(0.9 / np.linalg.norm([0.3, -0.2, 0.9])))  # plane normal vs (0, 0, 1)
    assert row["mae"] == pytest.approx(tilt, abs=1e-3)


def test_max_side_feeds_the_network_small_images_and_scores_at_full_size(dataset, tmp_path, monkeypatch):
    shapes = []
    _fake_estimate(monkeypatch, lambda images, mask, weights, seed, views: shapes.append(
        (images[0].shape, mask.shape, views)))
    js = tmp_path / "r.json"
    rc = main(["eval", str(dataset), "--method", "sdm-unips", "--objects", "spherePNG", "--max-side", "16",
               "--views", "2", "--json", str(js), "--quiet"])
    assert rc == 0
    assert shapes == [((16, 16, 3), (16, 16), 2)]  # the 32x32 sphere, halved
    report = json.loads(js.read_text())
    assert report["protocol"]["max_side"] == 16 and "--max-side 16" in report["command"]
    assert "--views 2" in report["command"]
    (row,) = report["objects"]
    # flat normals scored at 32x32 against the sphere's: the same error as flat normals at full size
    rc = main(["eval", str(dataset), "--method", "flat", "--objects", "spherePNG", "--json", str(js), "--quiet"])
    assert row["mae"] == pytest.approx(json.loads(js.read_text())["objects"][0]["mae"], abs=1e-6)


def test_upscale_normals_keeps_unit_length_and_the_mask():
    from matcap.photos import upscale_normals

    small = np.zeros((4, 4, 3), np.float32)
    small[1:3, 1:3] = np.float32([0.6, 0.0, 0.8])
    mask = np.zeros((8, 8), bool)
    mask[2:6, 2:6] = True
    up = upscale_normals(small, (8, 8), mask)
    assert up.shape == (8, 8, 3) and np.all(up[~mask] == 0)
    np.testing.assert_allclose(up[mask], np.tile([0.6, 0.0, 0.8], (16, 1)), atol=1e-6)
    # no normal nearby: faces the camera
    assert np.allclose(upscale_normals(np.zeros((2, 2, 3), np.float32), (4, 4)), [0, 0, 1])


@pytest.mark.parametrize("argv, message", [
    (["--objects", "nope"], "unknown object(s) nope"),
    (["--reference", "least-squares"], "--reference must differ"),
    (["--method", "least-squares", "--max-images", "2"], "at least 3"),
    (["--method", "sdm-unips", "--max-side", "8"], "--max-side must be at least 16"),
    (["--method", "least-squares", "--max-side", "64"], "needs --method or --reference sdm-unips"),
])
def test_bad_input_is_one_line_exit_2(dataset, capsys, argv, message):
    assert main(["eval", str(dataset), "--quiet", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("matcap eval: error: ") and message in err and err.count("\n") == 1


def test_missing_folder_is_exit_2(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "nothing")]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_linear_gives_the_network_8bit_uw_values_as_stored(tmp_path, monkeypatch):
    """UW captures are linear 8-bit data: with --linear the network sees value / 255, without it the sRGB decode."""
    from matcap import imageio

    folder = tmp_path / "uw" / "uw_box"
    folder.mkdir(parents=True)
    for i in range(3):
        imageio.write_png(folder / f"box.{i}.png", np.full((8, 8, 3), 128 / 255, np.float32), bits=8)
    imageio.write_png(folder / "box.mask.png", np.ones((8, 8), np.float32), bits=8)
    (folder / "lights.txt").write_text("3\n0 0 1\n0.5 0 0.866\n0 0.5 0.866\n")
    seen = []
    _fake_estimate(monkeypatch, lambda images, mask, weights, seed, views: seen.append(float(images[0][0, 0, 0])))
    js = tmp_path / "r.json"
    for extra in ([], ["--linear"]):
        assert main(["eval", str(tmp_path / "uw"), "--method", "sdm-unips", "--reference", "least-squares", "--json",
                     str(js), "--overwrite", "--quiet", *extra]) == 0
    assert seen[0] == pytest.approx(float(imageio.srgb_to_linear(np.float32(128 / 255))), abs=1e-6)
    assert seen[1] == pytest.approx(128 / 255, abs=1e-6)
    report = json.loads(js.read_text())
    assert "--linear" in report["command"] and report["protocol"]["network_8bit"] == "as stored (linear)"
    # without a network in the comparison the flag means nothing: a one-line usage error
    assert main(["eval", str(tmp_path / "uw"), "--method", "least-squares", "--linear", "--quiet"]) == 2

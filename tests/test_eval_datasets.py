"""Loaders: DiLiGenT layout (16 bits kept, all ground-truth formats), UW captures, our synthetic split."""
import json
from pathlib import Path

import numpy as np
import pytest

from matcap import imageio
from matcap.errors import MatcapError
from matcap.evaluation import datasets, toy

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


def _diligent(root, name="ballPNG", normal_format="mat", count=5):
    n, m = toy.sphere_normals(24, max_angle_deg=60.0)
    lights = toy.cone_lights(count, 30.0)
    images = toy.render_lambertian(n, m, lights)
    return toy.write_diligent_object(root / name, images, m, n, lights, normal_format=normal_format), n, m, lights


def test_loader_keeps_16_bits(tmp_path):
    folder, n, m, lights = _diligent(tmp_path)
    px = imageio.read_image(folder / "001.png").pixels.copy()
    px[3, 4] = (12345, 1, 65534)  # none of these is a multiple of 257: 8 bits cannot hold them
    imageio.write_png(folder / "001.png", px.astype(np.float64) / 65535.0, bits=16)
    obj = datasets.load_diligent_object(folder)
    assert obj.bit_depth == "16bit" and not obj.srgb_8bit
    assert obj.images[0].dtype == np.float32
    np.testing.assert_array_equal(np.round(obj.images[0][3, 4] * 65535.0), [12345, 1, 65534])
    assert obj.light_dirs.shape == (5, 3) and obj.calibrated
    np.testing.assert_allclose(obj.light_dirs, lights, atol=1e-7)


@pytest.mark.parametrize("fmt", ["mat", "txt", "png"])
def test_ground_truth_formats_agree(tmp_path, fmt):
    folder, n, m, _ = _diligent(tmp_path, normal_format=fmt)
    obj = datasets.load_diligent_object(folder)
    assert obj.normal_gt.dtype == np.float32
    np.testing.assert_allclose(obj.normal_gt[m], n[m], atol=1e-4)  # 16-bit PNG encoding: ~3e-5
    assert not obj.normal_gt[~m].any()


def test_normal_txt_in_column_major_order_is_recognised(tmp_path):
    folder, n, m, _ = _diligent(tmp_path, normal_format="txt")
    n2, m2 = toy.plane_normals(24, margin=0)
    m2[:, 16:] = False  # a mask that is not symmetric under transposition
    imageio.write_png(folder / "mask.png", m2.astype(np.float32), bits=8)
    gt = np.where(m2[:, :, None], n2, 0.0)
    np.savetxt(folder / "normal.txt", gt.transpose(1, 0, 2).reshape(-1, 3), fmt="%.8f")  # MATLAB order
    obj = datasets.load_diligent_object(folder)
    np.testing.assert_allclose(obj.normal_gt, gt, atol=1e-6)


def test_known_bad_images_are_dropped(tmp_path):
    folder, *_ = _diligent(tmp_path, name="bearPNG", count=24)
    assert len(datasets.load_diligent_object(folder).images) == 4
    assert len(datasets.load_diligent_object(folder, exclude_known_bad=False).images) == 24


def test_inconsistent_files_give_one_line_errors(tmp_path):
    folder, *_ = _diligent(tmp_path)
    np.savetxt(folder / "light_directions.txt", np.ones((4, 3)))
    with pytest.raises(MatcapError, match="5 images, 4 light directions"):
        datasets.load_diligent_object(folder)
    with pytest.raises(MatcapError, match="no such folder"):
        datasets.discover(tmp_path / "missing")


@pytest.mark.skipif(not (SHARED / "data/captures/uw_cat").is_dir(), reason="shared/data/captures/uw_cat missing")
def test_uw_loader_on_cat():
    obj = datasets.load_uw_object(SHARED / "data/captures/uw_cat")
    assert len(obj.images) == 12 and obj.images[0].shape == (340, 512, 3)
    assert obj.light_dirs.shape == (12, 3)
    np.testing.assert_allclose(np.linalg.norm(obj.light_dirs, axis=1), 1.0)
    np.testing.assert_allclose(obj.light_dirs[0], [0.403259, 0.480808, 0.778592], atol=1e-5)
    assert obj.normal_gt is None and obj.srgb_8bit and obj.bit_depth == "8bit"
    assert 0.1 < obj.mask.mean() < 0.9
    # 8-bit values are taken as linear for the baselines, sRGB-decoded for the networks
    assert obj.images[0].max() <= 1.0 and np.allclose(obj.images[0] * 255, np.round(obj.images[0] * 255))
    assert obj.network_images([0])[0].mean() < obj.images[0].mean()


def _synthetic_scene(folder, group, directional):
    folder.mkdir(parents=True)
    n, m = toy.sphere_normals(16, max_angle_deg=60.0)
    lights = toy.cone_lights(4, 30.0)
    for k, img in enumerate(toy.render_lambertian(n, m, lights)):
        imageio.write_png(folder / f"{k:03d}.png", img, bits=16)
    imageio.write_png(folder / "mask.png", m.astype(np.float32), bits=8)
    imageio.write_exr(folder / "normal.exr", n)
    (folder / "spec.json").write_text(json.dumps({"split": "test", "lighting_group": group}))
    basis = [{"kind": "directional", "direction": list(l), "irradiance": [2.0, 2.0, 2.0]} for l in lights]
    if not directional:
        basis.append({"kind": "environment", "source": "procedural:1", "rotation_deg": 0.0, "scale": 1.0})
    images = [{"image": f"{k:03d}.png", "weights": [float(j == k) for j in range(4)] + ([] if directional else [1.0]),
               "exposure": 0.5} for k in range(4)]
    (folder / "lights.json").write_text(json.dumps({"basis": basis, "images": images}))


def test_synthetic_split_groups_and_lights(tmp_path):
    _synthetic_scene(tmp_path / "scene_000000", "directional", True)
    _synthetic_scene(tmp_path / "scene_000001", "both", False)
    (tmp_path / "manifest.json").write_text(json.dumps({
        "split": "test", "scenes": ["scene_000000", "scene_000001"],
        "lighting_groups": {"scene_000000": "directional", "scene_000001": "both"}}))
    sources, notes = datasets.discover(tmp_path)
    assert [(s.name, s.group) for s in sources] == [("scene_000000", "directional"), ("scene_000001", "both")]
    a, b = (s.load() for s in sources)
    assert a.calibrated and not b.calibrated
    np.testing.assert_allclose(a.light_intensities, 1.0)  # irradiance 2 x weight 1 x exposure 0.5
    assert a.normal_gt.shape == (16, 16, 3) and a.bit_depth == "16bit"
    with pytest.raises(MatcapError, match="pass --split test"):
        datasets.discover(tmp_path, split="train")

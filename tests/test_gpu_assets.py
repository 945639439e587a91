"""docs/recipes/make_gpu_assets.py: the train split's assets, trimmed for a lent GPU call, load as the generator
loads the full folder, without colour-science."""
from __future__ import annotations

import importlib.util
import sys
import tarfile

import numpy as np
import pytest

from conftest import REPO, shared_path


def _recipe():
    spec = importlib.util.spec_from_file_location("make_gpu_assets", REPO / "docs/recipes/make_gpu_assets.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def trimmed(tmp_path_factory):
    assets = shared_path("data")
    out = tmp_path_factory.mktemp("gpu_assets")
    archive = _recipe().build(assets, out / "carry", env_height=16)
    with tarfile.open(archive) as tar:
        tar.extractall(out / "A", filter="data")
    return assets, out / "A", archive


def test_the_train_split_and_nothing_held_out(trimmed):
    from matcap.synth import catalog_from_dir
    from scenes.synth_spec import _stem

    full, small, _ = trimmed
    want = catalog_from_dir(full).for_split("train")
    got = catalog_from_dir(small)
    assert got.for_split("test").envmaps == [] and got.for_split("test").meshes == []
    assert got.for_split("test").textures == []
    train = got.for_split("train")
    for kind in ("meshes", "envmaps", "textures", "normal_maps"):
        assert sorted(map(_stem, getattr(train, kind))) == sorted(map(_stem, getattr(want, kind))), kind
    for kind in ("meshes", "envmaps", "textures"):
        assert (small / kind / "SOURCES.md").exists()


def test_maps_load_as_the_full_ones_without_colour_science(trimmed, monkeypatch):
    from matcap.synth import AssetCache

    full, small, _ = trimmed
    name = "textures/tea_set_01"  # base colour, normal map and packed ARM
    want = AssetCache(full).texture_set(name)  # decoded with colour-science
    monkeypatch.setitem(sys.modules, "colour", None)  # `import colour` now fails
    got = AssetCache(small).texture_set(name)
    assert np.abs(got["basecolor"] - want["basecolor"]).max() < 2e-5  # 16-bit linear
    assert np.abs(got["normal"] - want["normal"]).max() < 0.6 / 255  # re-quantised to the 8 bits it had
    assert np.abs(got["roughness"] - want["roughness"]).max() < 0.6 / 255
    env = AssetCache(small).envmap("envmaps/blender_studio.exr")
    assert env.shape == (16, 32, 3)
    h = env.shape[0]
    w = np.sin((np.arange(h) + 0.5) / h * np.pi)[:, None, None]
    assert abs(float((env * w).sum() / (w.sum() * env.shape[1] * 3)) - 1.0) < 1e-2  # unit mean radiance


def test_a_carried_folder_unpacks_where_the_call_runs(trimmed, tmp_path):
    """The rest of a call's carried folder (Mitsuba, the wheels but colour-science, the validation set as one
    pack), then gpu_train's first stage on the lent machine: the archive and the pack unpacked into its work
    folder and used."""
    from argparse import Namespace

    from test_datapack import _synth_like_dataset

    _, small, archive = trimmed
    val_data = _synth_like_dataset(tmp_path / "val_data", scenes=3, size=16)
    carry = tmp_path / "carry"
    for name in ("mitsuba/m.tar.xz", "wheels/openexr-1-py3-none-any.whl", "wheels/trimesh-1-py3-none-any.whl",
                 "wheels/colour_science-1-py3-none-any.whl"):
        (carry / name).parent.mkdir(parents=True, exist_ok=True)
        (carry / name).write_bytes(b"x")
    root = tmp_path / "carry_gpu"
    (root / "assets").mkdir(parents=True)
    (root / "assets" / archive.name).write_bytes(archive.read_bytes())
    _recipe().carry_rest(carry, val_data, root)
    assert sorted(p.name for p in (root / "wheels").iterdir()) == ["openexr-1-py3-none-any.whl",
                                                                    "trimesh-1-py3-none-any.whl"]
    assert (root / "mitsuba" / "m.tar.xz").exists() and [p.name for p in (root / "val").iterdir()] == ["pack_000.npz"]

    spec = importlib.util.spec_from_file_location("gpu_train", REPO / "docs/recipes/gpu_train.py")
    gpu_train = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gpu_train)
    a = Namespace(work=str(tmp_path / "work"), out=str(tmp_path / "out"), call=1, val_scenes=32,
                  assets=str(root / "assets" / archive.name), val_pack=str(root / "val" / "pack_000.npz"))
    call = gpu_train.Call(a)
    call.setup_carried_data()
    scenes = sorted(p.parent.name for p in val_data.glob("*/data.npz"))
    assert a.val_scenes == len(scenes) and sorted(
        p.parent.name for p in (tmp_path / "work" / "val").glob("*/data.npz")) == scenes
    assert sorted(p.name for p in (tmp_path / "work" / "assets" / "meshes").glob("*.ply")) == sorted(
        p.name for p in (small / "meshes").glob("*.ply"))
    assert a.assets == str(tmp_path / "work" / "assets")

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
    return assets, out / "A"


def test_the_train_split_and_nothing_held_out(trimmed):
    from matcap.synth import catalog_from_dir
    from scenes.synth_spec import _stem

    full, small = trimmed
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

    full, small = trimmed
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

"""`matcap synth` and renderers.synth in both Mitsuba variants: ``llvm_ad_rgb`` and the ``scalar_rgb`` fallback a
fresh install without libLLVM >= 17 gets (``mi.Float(ndarray)`` is a Python float in scalar variants)."""
from __future__ import annotations

import json

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")


@pytest.fixture
def mitsuba_variant(monkeypatch):
    """Force a Mitsuba variant for one test, restoring the process's choice afterwards.

    Local on purpose: it only needs ``renderers.variant``'s cache (``_chosen``) and ``MATCAP_MITSUBA_VARIANT``, so
    it can be replaced by the general variant fixture of tests/conftest.py by renaming it there.
    """
    import renderers.variant as V

    before = V.choose_variant(quiet=True)

    def force(name: str) -> str:
        if name not in mi.variants():
            pytest.skip(f"Mitsuba variant {name} is not built into this wheel")
        monkeypatch.setenv("MATCAP_MITSUBA_VARIANT", name)
        V._chosen = None
        return V.choose_variant()

    yield force
    V._chosen = None
    monkeypatch.delenv("MATCAP_MITSUBA_VARIANT", raising=False)
    V.choose_variant(before)


def _tiny_scene():
    from scenes import procedural as P
    from scenes.synth_build import RenderObject

    g = P.make_sphere(16).transformed(np.eye(3), 0.6, (0.1, 0.0, 0.0))
    tex = np.full((8, 8, 3), 0.5, np.float32)
    rough = np.full((8, 8), 0.4, np.float32)
    rough[:, 4:] = 0.8
    obj = RenderObject(g, tex, rough, np.zeros((8, 8), np.float32), 0.5, 1.0)
    return [obj]


@pytest.mark.parametrize("variant", ["scalar_rgb", "llvm_ad_rgb"])
def test_render_scene_in_variant(mitsuba_variant, variant):
    from renderers.synth import render_object_index, render_scene
    from scenes import procedural as P
    from scenes.lights import DirectionalLight, EnvironmentLight, PointLight

    if variant == "llvm_ad_rgb":
        import renderers.variant as V

        V._chosen = None
        if V.choose_variant(quiet=True) != "llvm_ad_rgb":
            pytest.skip("llvm_ad_rgb does not work on this machine (needs libLLVM >= 17)")
    assert mitsuba_variant(variant) == variant
    assert mi.variant() == variant
    env = {"procedural:1": P.procedural_sky(1, 16)}
    lights = [DirectionalLight((0.2, 0.3, 0.93)), DirectionalLight((-0.4, 0.1, 0.9)), PointLight((0.5, 0.5, 2.5)),
              EnvironmentLight("procedural:1", 30.0)]
    r = render_scene(_tiny_scene(), lights, env, 24, spp=4, seed=2)
    assert r.basis.shape == (4, 24, 24, 3) and np.isfinite(r.basis).all()
    assert r.basis[0][r.object_mask].mean() > 0.05
    assert abs(r.object_mask.mean() - np.pi * 0.3**2) < 0.05  # a sphere of radius 0.6 in a 2 x 2 view
    n = r.normal[r.mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-4)
    rough = r.roughness[r.object_mask]
    assert 0.39 < rough.min() < 0.41 and rough.max() < 0.81 and rough.std() > 0.02  # the two halves of the map
    idx = render_object_index(_tiny_scene(), 24)
    assert np.array_equal(idx >= 0, r.object_mask)


def test_synth_cli_in_scalar_variant(mitsuba_variant, tmp_path):
    """`matcap synth` as a new user runs it, at a smaller size, in the scalar fallback."""
    from matcap.synth import run_synth

    mitsuba_variant("scalar_rgb")
    out = tmp_path / "D"
    stats = run_synth(out, 2, resolution=32, seed=11, spp=2, progress=False)
    assert stats["rendered"] + stats["failed"] == 2 and stats["rendered"] >= 1
    manifest = json.loads((out / "manifest.json").read_text())
    assert len(manifest["scenes"]) == stats["rendered"]
    with np.load(out / manifest["scenes"][0] / "data.npz") as z:
        assert z["images"].shape == (10, 32, 32, 3) and float(z["images"].max()) > 0.1

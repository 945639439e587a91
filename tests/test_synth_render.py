"""Rendering: linear light combination, ground truth conventions, determinism, validity checks."""
import numpy as np
import pytest

pytest.importorskip("mitsuba")

from renderers.synth import SceneRenderer, render_object_index, render_scene
from scenes import procedural as P
from scenes.lights import DirectionalLight, EnvironmentLight, PointLight
from scenes.synth_build import RenderObject, check_scene, finalize_normals


def _objects():
    g = P.make_sphere(24).transformed(np.eye(3), 0.6, (0.2, 0.1, 0.0))
    tex = np.full((8, 8, 3), 0.6, np.float32)
    tex[:, :4] = (0.2, 0.5, 0.8)
    sphere = RenderObject(g, tex, np.full((8, 8), 0.4, np.float32), np.zeros((8, 8), np.float32), 0.5, 1.0)
    plane = P.make_backdrop(4.0, 0.0, 0).transformed(np.eye(3), 1.0, (0, 0, -0.8))
    back = RenderObject(plane, np.full((8, 8, 3), 0.5, np.float32), np.full((8, 8), 0.9, np.float32),
                        np.zeros((8, 8), np.float32), 0.2, 1.0, is_background=True)
    return [sphere, back]


ENV = {"procedural:3": P.procedural_sky(3, 32)}
LIGHTS = [DirectionalLight((0.3, 0.4, 0.866)), PointLight((-0.8, 0.5, 2.5), (20.0, 20.0, 20.0)),
          EnvironmentLight("procedural:3", 40.0)]


def _block(x, k=4):
    h, w = x.shape[0] // k, x.shape[1] // k
    return x[: h * k, : w * k].reshape(h, k, w, k, -1).mean(axis=(1, 3))


def test_combined_basis_equals_direct_render():
    r = SceneRenderer(_objects(), 48, spp=64, seed=3)
    basis = np.stack([r.render([light], ENV) for light in LIGHTS])
    weights = [0.7, 0.4, 0.5]
    combined = np.tensordot(np.float32(weights), basis, axes=1)
    direct = r.render(LIGHTS, ENV, weights)
    a, b = _block(combined), _block(direct)
    rel = np.sqrt(((a - b) ** 2).mean()) / b.mean()
    assert rel < 0.035, rel  # measured 0.021 (fixed seeds): Monte Carlo noise only
    assert abs(a.mean() / b.mean() - 1) < 0.01
    # and the sum is not trivially equal to one component
    assert np.sqrt(((_block(basis[0] * 0.7) - b) ** 2).mean()) / b.mean() > 0.2


def test_reused_scene_renders_what_a_fresh_one_does():
    """Basis lights of one kind share a loaded scene (only the emitter is updated): same pixels as a new scene."""
    objs = _objects()
    lights = [DirectionalLight((0.3, 0.4, 0.866), (3.0, 2.0, 1.0)), DirectionalLight((-0.5, 0.1, 0.86)),
              PointLight((-0.8, 0.5, 2.5), (20.0, 20.0, 20.0)), PointLight((0.9, -0.4, 2.0), (5.0, 9.0, 9.0)),
              EnvironmentLight("procedural:3", 40.0), EnvironmentLight("procedural:3", 160.0, scale=0.5),
              EnvironmentLight("procedural:4", 10.0)]
    env = {**ENV, "procedural:4": P.procedural_sky(4, 32)}
    shared = SceneRenderer(objs, 24, spp=4, seed=3)
    reused = [shared.render([light], env) for light in lights]
    assert len(shared._single) == 4  # directional, point, and one per env map
    for light, image in zip(lights, reused):
        fresh = SceneRenderer(objs, 24, spp=4, seed=3).render([light], env)
        np.testing.assert_allclose(image, fresh, rtol=1e-5, atol=1e-6)
    # and the lights did change between renders
    assert np.abs(reused[0] - reused[1]).mean() > 0.01 and np.abs(reused[4] - reused[5]).mean() > 0.01


def test_ground_truth_and_determinism():
    objs = _objects()
    r1 = render_scene(objs, LIGHTS[:2], ENV, 32, spp=4, seed=5)
    r2 = render_scene(objs, LIGHTS[:2], ENV, 32, spp=4, seed=5)
    assert np.abs(r1.basis - r2.basis).max() <= 1 / 65535
    assert np.array_equal(r1.normal, r2.normal)
    assert r1.mask.all()  # background plane fills the view
    n = r1.normal[r1.mask]
    assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-4) and n[:, 2].min() >= 0
    # the sphere (centre at +0.2, +0.1) is to the right and up: its right side's normal points +x (image right)
    obj = r1.object_mask
    assert 0.1 < obj.mean() < 0.4
    ys, xs = np.nonzero(obj)
    assert xs.mean() > 16 and ys.mean() < 16  # row 0 = top
    right = r1.normal[ys[xs == xs.max()][0], xs.max()]
    assert right[0] > 0.5
    # ground-truth BRDF maps: background roughness 0.9, sphere 0.4; base colour from the texture
    assert np.allclose(r1.roughness[~obj & r1.mask], 0.9, atol=1e-3)
    assert np.allclose(r1.roughness[obj], 0.4, atol=1e-3)
    assert np.allclose(r1.base_color[~obj & r1.mask], 0.5, atol=1e-3)
    assert r1.stats["mask_agreement"] == 1.0



def test_object_index_matches_the_ground_truth_masks():
    objs = _objects()
    gt = SceneRenderer(objs, 32, spp=1, seed=5).ground_truth()
    index = render_object_index(objs, 32)
    assert index.shape == (32, 32) and index.dtype == np.int16
    assert np.array_equal(index == 0, gt["object_mask"])  # the sphere
    assert np.array_equal(index == 1, gt["mask"] & ~gt["object_mask"])  # the backdrop
    # nothing behind the shapes: -1 where the view is empty
    index = render_object_index(objs[:1], 32)
    assert set(np.unique(index)) == {-1, 0} and np.array_equal(index == 0, gt["object_mask"])


# ----------------------------------------------------------------------------------------------- checks


def _good_scene(h=32):
    yy, xx = np.mgrid[:h, :h]
    r2 = ((xx - h / 2 + 0.5) ** 2 + (yy - h / 2 + 0.5) ** 2) / (h / 3) ** 2
    mask = r2 < 1
    normal = np.zeros((h, h, 3), np.float32)
    nx, ny = (xx - h / 2 + 0.5) / (h / 3), -(yy - h / 2 + 0.5) / (h / 3)
    nz = np.sqrt(np.clip(1 - nx**2 - ny**2, 0, 1))
    normal[mask] = np.stack([nx, ny, nz], -1)[mask]
    normal[mask] /= np.linalg.norm(normal[mask], axis=1, keepdims=True)
    raw = np.zeros((3, h, h, 3), np.float32)
    for k, light in enumerate([(0, 0, 1), (0.5, 0, 0.86), (0, 0.5, 0.86)]):
        raw[k][mask] = np.clip(normal[mask] @ np.float32(light), 0.05, None)[:, None] * 0.5
    images = raw / raw.max() * 0.8
    return images, normal, mask, raw


def test_check_accepts_a_good_scene():
    images, normal, mask, raw = _good_scene()
    assert check_scene(images, normal, mask, mask, raw, ["b", "b", "c"]) == []


@pytest.mark.parametrize("defect", ["flipped", "black", "saturated", "outside", "length", "tiny", "nan", "backfaces"])
def test_check_rejects_bad_scenes(defect):
    images, normal, mask, raw = _good_scene()
    stats = None
    if defect == "flipped":
        normal[mask] *= -1
    elif defect == "black":
        images[1] *= 0.001
    elif defect == "saturated":
        images[2] = np.where(mask[..., None], 1.0, 0.0)
    elif defect == "outside":  # light where the mask says there is nothing: mask misses geometry
        raw[0][0:4, 0:4] = 0.3
    elif defect == "length":
        normal[mask] *= 0.8
    elif defect == "tiny":
        mask = np.zeros_like(mask)
        mask[15:17, 15:17] = True
        normal[~mask] = 0
    elif defect == "nan":
        images[0][10, 10] = np.nan
    elif defect == "backfaces":
        stats = {"back_face_fraction": 0.6, "clamped_fraction": 0.0}
    problems = check_scene(images, normal, mask, mask, raw, ["b", "b", "c"], stats)
    assert problems, defect


def test_finalize_normals_flips_back_faces_and_clamps():
    sh = np.float32([[[0, 0, -1], [0.6, 0, -0.1], [0, 0.6, 0.8], [0, 0, 0]]])
    geo = np.float32([[[0, 0, -1], [0.6, 0, 0.8], [0, 0.6, 0.8], [0, 0, 0]]])
    hit = np.array([[True, True, True, False]])
    n, stats = finalize_normals(sh, geo, hit)
    assert np.allclose(n[0, 0], [0, 0, 1])
    assert np.allclose(n[0, 1], [1, 0, 0], atol=1e-6)
    assert np.allclose(np.linalg.norm(n[0, :3], axis=1), 1) and np.all(n[0, 3] == 0)
    assert stats["back_face_fraction"] == pytest.approx(1 / 3)


def test_ctrl_c_during_a_render_raises_instead_of_returning_a_partial_image(monkeypatch):
    """Mitsuba takes SIGINT during a render: it cancels the integrator and returns early. Simulate exactly that
    (the real render, then the cancel its signal handler would make) and expect KeyboardInterrupt, not an image."""
    import mitsuba as mi

    from renderers.variant import render_array

    r = SceneRenderer(_objects(), 16, spp=2, seed=0)
    normal = r.render([LIGHTS[0]], ENV)  # not interrupted: an image
    assert normal.shape == (16, 16, 3) and normal.mean() > 0
    real_render = mi.render

    def render_then_cancel(scene, integrator=None, **kw):
        image = real_render(scene, integrator=integrator, **kw)
        (integrator or scene.integrator()).cancel()  # what Mitsuba's SIGINT handler does mid-render
        return image

    monkeypatch.setattr(mi, "render", render_then_cancel)
    with pytest.raises(KeyboardInterrupt):
        r.render([LIGHTS[1]], ENV)
    with pytest.raises(KeyboardInterrupt):
        r.ground_truth()
    monkeypatch.setattr(mi, "render", real_render)
    scene = mi.load_dict({"type": "scene", "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 4,
                                                                                       "height": 4}},
                          "shape": {"type": "rectangle"}, "light": {"type": "constant"},
                          "integrator": {"type": "path"}})
    assert render_array(scene, spp=1).shape == (4, 4, 3)  # the scene's own integrator, nothing cancelled


def test_an_interrupt_wrapped_by_drjit_is_recognised():
    """SIGTERM inside mi.render reaches Python as RuntimeError raised from the handler's KeyboardInterrupt."""
    from renderers.variant import interrupted_by

    def wrapped(inner: BaseException) -> RuntimeError:
        try:
            try:
                raise inner
            except BaseException as exc:
                raise RuntimeError("drjit.custom(...): error while performing a custom differentiable operation") from exc
        except RuntimeError as outer:
            return outer

    assert interrupted_by(wrapped(KeyboardInterrupt("signal 15")))
    assert interrupted_by(KeyboardInterrupt())
    assert not interrupted_by(wrapped(ValueError("a real rendering error")))
    assert not interrupted_by(RuntimeError("plain"))


def test_persistent_renderer_equals_fresh_scenes():
    """One BasisRenderer reused across scenes (buffers overwritten through mi.traverse, unused slots parked) renders
    what fresh Mitsuba scenes render: same sampler seeds, so equal up to float rounding (well inside the noise)."""
    from renderers.synth import BasisRenderer

    objs = _objects()
    other = [RenderObject(P.make_box((0.5, 0.4, 0.3)).transformed(np.eye(3), 0.5, (-0.3, 0.2, 0.1)),
                          np.full((8, 8, 3), 0.3, np.float32), np.full((8, 8), 0.2, np.float32),
                          np.ones((8, 8), np.float32), 0.5, 2.0)] + objs
    objs[0].uv_scale = 3.0  # the texture repeat goes through the uv, not the texture's transform
    env = {**ENV, "procedural:4": P.procedural_sky(4, 32)}
    lights = LIGHTS + [EnvironmentLight("procedural:4", 100.0, 0.5)]
    shared = BasisRenderer(24, slots=4)
    for scene in (objs, other, objs):
        new = render_scene(scene, lights, env, 24, spp=4, seed=9, renderer=shared)
        old = render_scene(scene, lights, env, 24, spp=4, seed=9, persistent=False)
        diff = np.abs(new.basis - old.basis)  # measured: 0.3 % of values differ, by at most 1e-4 (float rounding)
        assert diff.mean() < 1e-5 and np.quantile(diff, 0.99) < 1e-4 and diff.max() < 0.05 * old.basis.max()
        for key in ("normal", "base_color", "roughness", "metallic"):
            np.testing.assert_allclose(getattr(new, key), getattr(old, key), atol=1e-5)
        assert np.array_equal(new.mask, old.mask) and np.array_equal(new.object_mask, old.object_mask)
    assert len(shared._scenes) == 4  # envmap, directional, point, params: loaded once for all three scenes
    # more objects than slots: the scenes are rebuilt with more slots
    many = render_scene(other + other[:2], lights[:1], env, 24, spp=2, seed=1, renderer=shared)
    assert shared.slots == 5 and many.basis.shape == (1, 24, 24, 3)

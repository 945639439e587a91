"""Relighting correctness against closed-form answers (Mitsuba, small images)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from renderers.relight import build_scene, cull_back_hemisphere, render  # noqa: E402
from scenes.lights import DirectionalLight, EnvironmentLight  # noqa: E402
from scenes.materialmaps import MaterialMaps  # noqa: E402

N = 16


def flat(normal=(0.0, 0.0, 1.0), albedo=0.6, roughness=1.0, metallic=0.0, size=N) -> MaterialMaps:
    n = np.broadcast_to(np.asarray(normal, np.float32) / np.linalg.norm(normal), (size, size, 3)).copy()
    return MaterialMaps(normal=n, mask=np.ones((size, size), bool),
                        base_color=np.full((size, size, 3), albedo, np.float32),
                        roughness=np.full((size, size), roughness, np.float32),
                        metallic=np.full((size, size), metallic, np.float32))


def tilted(deg: float, axis: str = "x") -> tuple[float, float, float]:
    t = np.radians(deg)
    return (np.sin(t), 0.0, np.cos(t)) if axis == "x" else (0.0, np.sin(t), np.cos(t))


@pytest.mark.parametrize("deg,axis", [(0, "x"), (25, "x"), (40, "y"), (-35, "x")])
def test_lambertian_plane_tilted_by_normal_map(deg, axis):
    """albedo * E * cos(theta) / pi within 2 % (light along the view axis, normal map tilts the plane)."""
    albedo, E = 0.6, 2.5
    img = render(flat(tilted(deg, axis), albedo), [DirectionalLight((0, 0, 1), (E, E, E))], spp=2, specular=0.0)
    expected = albedo * E * np.cos(np.radians(deg)) / np.pi
    assert img.shape == (N, N, 3) and img.dtype == np.float32
    assert np.abs(img / expected - 1).max() < 0.02


def test_default_specular_layer_adds_a_few_percent_only():
    """With the default 4 % Fresnel layer the same plane is brighter, but by less than 4 % of the diffuse."""
    albedo, E = 0.6, 2.5
    img = render(flat(tilted(25), albedo), [DirectionalLight((0, 0, 1), (E, E, E))], spp=2)
    ratio = img.mean() / (albedo * E * np.cos(np.radians(25)) / np.pi)
    assert 1.0 < ratio < 1.04


def test_normal_map_tilt_direction():
    """A normal tilted toward a light from the right (+x) is brighter than one tilted away; same for +y (up)."""
    for axis, light in (("x", (0.5, 0.0, 1.0)), ("y", (0.0, 0.5, 1.0))):
        lights = [DirectionalLight(light, (1, 1, 1))]
        toward = render(flat(tilted(30, axis)), lights, spp=1).mean()
        away = render(flat(tilted(-30, axis)), lights, spp=1).mean()
        assert toward > 1.5 * away


def test_image_orientation_and_mask():
    """Row 0 is the top, column 0 the left; masked-out pixels are black."""
    h, w = 12, 20
    base = np.zeros((h, w, 3), np.float32)
    base[..., 0] = np.linspace(0.05, 0.95, w)[None, :]
    base[..., 1] = np.linspace(0.05, 0.95, h)[:, None]
    base[..., 2] = 0.5
    n = np.zeros((h, w, 3), np.float32)
    n[..., 2] = 1
    mask = np.ones((h, w), bool)
    mask[:, :3] = False
    maps = MaterialMaps(normal=n, mask=mask, base_color=base, roughness=np.ones((h, w)), metallic=np.zeros((h, w)))
    img = render(maps, [DirectionalLight((0, 0, 1), (np.pi,) * 3)], spp=4, specular=0.0)
    assert img.shape == (h, w, 3)
    err = np.abs(img - base)
    assert err[1:-1, 4:-1].max() < 0.01  # interior: bilinear lookups average back to the texel value
    assert err[:, 3:].max() < 0.02  # clamped borders are off by a fraction of one texel step
    assert (img[:, :3] == 0).all()


def test_constant_white_environment_gives_known_radiance():
    """Constant radiance L on a white roughness-1 Principled plane (specular 0), viewed head-on.

    Lambertian would give L; Mitsuba's Principled diffuse is Burley's (Disney 2012) model, whose hemispherical
    albedo at normal view with roughness r is 1 + 2 * int_0^1 (1-u)^5 u (r (1+u) - 1/2) du = 1 + (10 r - 4) / 168,
    i.e. 1 + 1/28 for r = 1.
    """
    L = 1.5
    env = np.full((16, 32, 3), L, np.float32)
    for r in (1.0, 0.5):
        img = render(flat(albedo=1.0, roughness=r, size=24), [EnvironmentLight("white")], {"white": env},
                     spp=64, specular=0.0)
        expected = L * (1 + (10 * r - 4) / 168)
        assert abs(img.mean() / expected - 1) < 0.005, (r, img.mean(), expected)


def _studio():
    from matcap.relight import default_envmap_path, load_envmap

    return load_envmap(default_envmap_path())


def test_rotating_environment_by_360_degrees_gives_the_same_image():
    env = _studio()
    maps = flat(tilted(20), albedo=0.5, roughness=0.4)
    a = render(maps, [EnvironmentLight("s", 0.0)], {"s": env}, spp=16, seed=3)
    b = render(maps, [EnvironmentLight("s", 360.0)], {"s": env}, spp=16, seed=3)
    c = render(maps, [EnvironmentLight("s", 90.0)], {"s": env}, spp=16, seed=3)
    assert np.abs(a - b).mean() / a.mean() < 0.005
    assert np.abs(a - c).mean() / a.mean() > 0.1  # and rotation does something


def test_rotation_convention_matches_rolling_the_map():
    """rotate=+90 deg (about +y) equals shifting the equirectangular texels by -W/4 columns."""
    env = _studio()
    maps = flat(tilted(20), albedo=0.5, roughness=0.4)
    w = env.shape[1]
    rotated = render(maps, [EnvironmentLight("s", 90.0)], {"s": env}, spp=64)
    rolled = render(maps, [EnvironmentLight("s", 0.0)], {"s": np.roll(env, -w // 4, axis=1)}, spp=64)
    wrong = render(maps, [EnvironmentLight("s", 0.0)], {"s": np.roll(env, w // 4, axis=1)}, spp=64)
    assert abs(rotated.mean() / rolled.mean() - 1) < 0.01
    assert abs(wrong.mean() / rolled.mean() - 1) > 0.2


def test_exposure_scales_the_environment():
    env = np.full((8, 16, 3), 0.5, np.float32)
    maps = flat(roughness=1.0)
    a = render(maps, [EnvironmentLight("c", 0.0, 1.0)], {"c": env}, spp=8, seed=1)
    b = render(maps, [EnvironmentLight("c", 0.0, 2.0 ** 1.5)], {"c": env}, spp=8, seed=1)
    np.testing.assert_allclose(b, a * 2.0 ** 1.5, rtol=1e-4)


def test_negative_and_nonfinite_texels_are_clamped_with_a_warning(monkeypatch):
    from renderers import emitters

    monkeypatch.setattr(emitters, "_warned", set())
    env = np.full((8, 16, 3), 1.0, np.float32)
    env[1, 2] = -50.0
    env[2, 3, 1] = np.nan
    env[3, 4, 2] = np.inf
    with pytest.warns(UserWarning, match="clamped"):
        img = render(flat(), [EnvironmentLight("bad")], {"bad": env}, spp=4)
    assert np.isfinite(img).all() and img.min() >= 0


def test_a_few_small_negative_texels_are_clamped_silently_and_a_bad_map_is_named_once(monkeypatch):
    """DWAB-compressed maps hold a few tiny negatives: clamped without a word. A map whose negatives matter is
    named once per process, however often it is rendered."""
    from renderers import emitters

    monkeypatch.setattr(emitters, "_warned", set())
    env = np.full((8, 16, 3), 1.0, np.float32)
    env[1, 2] = -1e-4
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clean = emitters.sanitize_envmap(env, "dwab")
    assert clean.min() == 0 and clean[1, 2].max() == 0
    env[1, 2] = -5.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            emitters.sanitize_envmap(env, "studio.exr")
    assert len(caught) == 1 and "studio.exr: 1 texel(s)" in str(caught[0].message)


def test_back_hemisphere_culling_only_drops_unseen_texels():
    env = np.ones((64, 128, 3), np.float32)
    culled = cull_back_hemisphere(env, 0.0)
    # row 0 is the zenith; column W/2 (u = 0.5) faces +z (toward the camera), columns 0 / W-1 face -z
    assert culled[32, 64].min() == 1 and culled[32, 0].max() == 0 and culled[0, 0].min() == 1
    sin_theta = np.sin(np.pi * (np.arange(64) + 0.5) / 64)[:, None]
    kept_solid_angle = ((culled[..., 0] > 0) * sin_theta).sum() / (sin_theta.sum() * 128)
    assert 0.5 <= kept_solid_angle < 0.56
    # turning the map turns the kept half with it
    assert cull_back_hemisphere(env, 90.0)[32, 32].min() == 1 or cull_back_hemisphere(env, 90.0)[32, 96].min() == 1


def test_build_scene_is_a_plain_dict_with_one_light_per_input():
    from renderers.variant import choose_variant

    choose_variant()
    scene = build_scene(flat(), [DirectionalLight(), EnvironmentLight("c")], {"c": np.ones((8, 16, 3), np.float32)},
                        spp=4, size=(8, 8))
    assert scene["type"] == "scene" and scene["sensor"]["film"]["width"] == 8
    assert scene["surface"]["bsdf"]["type"] == "normalmap"
    assert scene["surface"]["bsdf"]["bsdf"]["type"] == "principled"
    assert scene["light_0"]["type"] == "directional" and scene["light_1"]["type"] == "envmap"
    with pytest.raises(ValueError):
        build_scene(flat(), [], None, spp=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match="aspect"):
            build_scene(flat(), [DirectionalLight()], None, spp=4, size=(16, 8))

"""matcap.refine.lightfile: lights.json validation, SH helpers, conversion to relight lights."""
from __future__ import annotations

import json

import numpy as np
import pytest

from matcap.errors import MatcapError
from matcap.refine import lightfile as lf
from scenes.lights import DirectionalLight, EnvironmentLight, PointLight

SH = np.array([[2.0, 1.6, 1.2], [0.3, 0.2, 0.1], [0.5, 0.4, 0.5], [-0.2, 0.1, 0.3],
               [0.1, -0.05, 0.0], [0.15, 0.1, 0.05], [0.2, 0.2, 0.1], [-0.1, 0.05, 0.1], [0.05, 0.1, -0.1]])


def _entries():
    return [
        {"index": 0, "file": "001.png", "kind": "directional", "direction": [0.0, 0.6, 0.8],
         "intensity": [1.0, 2.0, 3.0], "sh": SH.tolist(), "psnr": 31.5},
        {"index": 1, "file": "002.png", "kind": "point", "position": [0.2, 0.1, 3.0],
         "intensity": [5.0, 5.0, 5.0], "sh": np.zeros((9, 3)).tolist()},
    ]


def _sphere_quadrature(h: int, w: int):
    d = lf.envmap_directions(h, w)
    theta = np.pi * (np.arange(h) + 0.5) / h
    d_omega = np.broadcast_to(((2 * np.pi / w) * (np.pi / h) * np.sin(theta))[:, None], (h, w))
    return d, d_omega


def test_envmap_directions_are_the_renderers():
    """The SH env map's texel directions are the ones relight culls with: one function, in scenes.lights."""
    import renderers.relight

    assert lf.envmap_directions is renderers.relight.envmap_directions


def test_sh_round_trip_of_an_sh_environment():
    """An environment made of known SH coefficients projects back onto them."""
    assert lf.sh_radiance(SH, lf.envmap_directions(64, 128)).min() > 0  # nothing clamped
    env = lf.sh_to_envmap(SH, 128, 256)
    back = lf.project_sh(env)
    assert np.abs(back - SH).max() < 2e-3 * np.abs(SH).max()


def test_sh_irradiance_of_a_smooth_environment():
    """Project a smooth (not band-limited) sky, reconstruct the irradiance: within 3 % of brute force."""
    h, w = 96, 192
    d, d_omega = _sphere_quadrature(h, w)
    a = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
    env = (0.4 + 2.0 * np.exp(3.0 * (d @ a - 1.0)))[..., None] * np.array([1.0, 0.8, 0.6])
    sh = lf.project_sh(env)
    rng = np.random.default_rng(0)
    n = rng.normal(size=(64, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cos = np.clip(np.einsum("nk,hwk->nhw", n, d), 0, None)
    brute = np.einsum("nhw,hwc,hw->nc", cos, env, d_omega)
    err = np.abs(lf.sh_irradiance(sh, n) - brute) / brute
    assert err.max() < 0.03, err.max()


def test_write_read_round_trip(tmp_path):
    path = tmp_path / "lights.json"
    doc = lf.write_lights(path, _entries(), method="test")
    back = lf.read_lights(path)
    assert back["version"] == 1 and back["method"] == "test" and back["images"][0]["psnr"] == 31.5
    assert back == json.loads(json.dumps(doc))
    assert back["images"][0]["direction"] == pytest.approx([0.0, 0.6, 0.8])
    assert lf.entry_for_image(back, 1)["kind"] == "point"


@pytest.mark.parametrize("mutate,message", [
    (lambda d: d.pop("version"), "unsupported version"),
    (lambda d: d.update(images=[]), "non-empty list"),
    (lambda d: d["images"][0].pop("direction"), "missing 'direction'"),
    (lambda d: d["images"][1].pop("position"), "missing 'position'"),
    (lambda d: d["images"][0].update(intensity=[1.0, 2.0]), "list of 3 numbers"),
    (lambda d: d["images"][0].update(intensity=[1.0, float("nan"), 2.0]), "finite"),
    (lambda d: d["images"][0].update(intensity=[1.0, -1.0, 2.0]), "negative"),
    (lambda d: d["images"][0].update(sh=SH[:4].tolist()), "9 rows"),
    (lambda d: d["images"][0].update(direction=[0, 0, 0]), "zero vector"),
    (lambda d: d["images"][0].update(kind="spot"), "'kind' must be one of"),
    (lambda d: d["images"][1].update(index=0), "more than once"),
    (lambda d: d["images"][1].update(index=-2), "non-negative integer"),
    (lambda d: d["images"][1].update(position=[0, 0, -1]), "in front of the plane"),
])
def test_bad_documents_are_one_line_errors(tmp_path, mutate, message):
    doc = {"version": 1, "images": _entries()}
    mutate(doc)
    path = tmp_path / "lights.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(MatcapError, match=message) as exc:
        lf.read_lights(path)
    assert "\n" not in str(exc.value)


def test_unreadable_files(tmp_path):
    with pytest.raises(MatcapError, match="no such file"):
        lf.read_lights(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{\"version\": 1, ")
    with pytest.raises(MatcapError, match="not valid JSON"):
        lf.read_lights(tmp_path / "bad.json")
    doc = lf.lights_document(_entries())
    with pytest.raises(MatcapError, match=r"no light for image 7 \(it has images 0..1\)"):
        lf.entry_for_image(doc, 7)


def test_entry_to_lights():
    doc = lf.lights_document(_entries())
    lights, env = lf.entry_to_lights(doc["images"][0])
    assert isinstance(lights[0], DirectionalLight) and lights[0].irradiance == (1.0, 2.0, 3.0)
    assert isinstance(lights[1], EnvironmentLight) and lights[1].rotation_deg == 0 and lights[1].scale == 1
    pixels = env[lights[1].source]
    assert pixels.shape == (lf.ENV_SIZE[1], lf.ENV_SIZE[0], 3) and pixels.dtype == np.float32
    lights, env = lf.entry_to_lights(doc["images"][1])  # zero SH: no environment
    assert len(lights) == 1 and isinstance(lights[0], PointLight) and not env
    assert lights[0].position == (0.2, 0.1, 3.0)
    negative = dict(doc["images"][0], sh=(-SH).tolist())
    _, env = lf.entry_to_lights(negative)
    assert next(iter(env.values())).min() == 0.0  # negative radiance clamped


def test_relit_white_plane_gets_the_sh_irradiance():
    """A white diffuse plane (specular 0, roughness 0.5: Burley diffuse within ~1 % of Lambert here) relit under
    the converted light: radiance = (E_directional + E_sh(+z)) / pi within 3 % (render noise)."""
    pytest.importorskip("mitsuba")
    from renderers.relight import render
    from scenes.materialmaps import MaterialMaps

    entry = lf.lights_document([{"index": 0, "kind": "directional", "direction": [0.0, 0.0, 1.0],
                                 "intensity": [0.2, 0.3, 0.4], "sh": SH.tolist()}])["images"][0]
    lights, env = lf.entry_to_lights(entry)
    s = 8
    maps = MaterialMaps(normal=np.broadcast_to(np.float32([0, 0, 1]), (s, s, 3)).copy(), mask=np.ones((s, s), bool),
                        base_color=np.ones((s, s, 3), np.float32), roughness=np.full((s, s), 0.5, np.float32),
                        metallic=np.zeros((s, s), np.float32))
    img = render(maps, lights, env, spp=256, specular=0.0)
    expected = (np.array([0.2, 0.3, 0.4]) + lf.sh_irradiance(SH, np.array([0.0, 0.0, 1.0]))) / np.pi
    got = img.reshape(-1, 3).mean(0)
    print("relit plane vs SH irradiance formula:", got / expected - 1)
    assert np.abs(got / expected - 1).max() < 0.03, (got, expected)
    # the SH part alone is most of it: the check is not dominated by the directional light
    assert lf.sh_irradiance(SH, np.array([0.0, 0.0, 1.0])).min() > 3 * 0.4

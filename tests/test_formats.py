"""matcap.formats: one table of map files, one loader (result, export, foreign texture set, .glb, synthetic scene),
round trips result -> export -> relight -> export again; scenes.atomic; the library capture chain."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from matcap import formats, imageio
from matcap.errors import MatcapError
from matcap.export import PRESETS, export
from matcap.results import read_result, write_result

PNG_TOP = {8: 255, 16: 65535}


def stored(path: Path) -> np.ndarray:
    """The integer codes of a PNG (alpha kept) or the floats of an EXR."""
    import cv2

    if path.suffix == ".exr":
        return imageio.read_exr(path)
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return arr.astype(np.int64)


def compare_sets(a: Path, b: Path, name: str) -> list[str]:
    """Compare every file of two exports named ``name`` (PNG codes within 1, EXR within 1e-5); returns the files."""
    files = sorted(p.name for p in a.iterdir() if p.name.startswith(name) and p.suffix in (".png", ".exr"))
    assert files == sorted(p.name for p in b.iterdir() if p.name.startswith(name) and p.suffix in (".png", ".exr"))
    for f in files:
        x, y = stored(a / f), stored(b / f)
        assert x.shape == y.shape, f
        if f.endswith(".exr"):
            np.testing.assert_allclose(x, y, atol=1e-5, err_msg=f)
        else:
            assert np.abs(x - y).max() <= 1, (f, np.abs(x - y).max())
    return files


def assert_same_maps(a, b, *, normal_deg: float, base: float, brdf: float) -> None:
    assert a.shape == b.shape and (a.mask == b.mask).all()
    m = a.mask
    chord = np.linalg.norm(a.normal[m].astype(np.float64) - b.normal[m], axis=-1)
    assert np.degrees(2 * np.arcsin(np.clip(chord / 2, 0, 1))).max() <= normal_deg
    for key, tol in (("base_color", base), ("roughness", brdf), ("metallic", brdf)):
        x, y = getattr(a, key), getattr(b, key)
        assert (x is None) == (y is None), key
        if x is not None:
            assert np.abs(x[m] - y[m]).max() <= tol, (key, np.abs(x[m] - y[m]).max())


# ------------------------------------------------------------------------------------------------ the table
def test_every_written_file_is_a_row_of_the_table(tmp_path, sphere_maps):
    maps = sphere_maps(16, varied=True)
    res = write_result(maps, tmp_path / "res")
    rows = {spec.file for spec in formats.LAYOUTS["result"].values()}
    assert {p.name for p in res.iterdir()} <= rows
    info = json.loads((res / "capture.json").read_text())
    assert info["files"] == ["normal.exr", "normal.png", "mask.png", "basecolor.png", "roughness.png",
                             "metallic.png", "capture.json"]
    # the encodings the table names: 16-bit sRGB base colour, 16-bit linear roughness, 8-bit mask, camera normals
    base = stored(res / "basecolor.png")[..., ::-1]
    assert base.dtype == np.int64 and base.max() <= 65535
    expect = np.round(imageio.linear_to_srgb(maps.base_color) * 65535)
    assert np.abs(base - expect).max() <= 1
    assert np.abs(stored(res / "roughness.png") - np.round(maps.roughness * 65535)).max() <= 1
    assert set(np.unique(stored(res / "mask.png"))) == {0, 255}
    n = stored(res / "normal.png")[..., ::-1] / 65535.0
    assert (n[~maps.mask] == 0).all()
    np.testing.assert_allclose(n[maps.mask] * 2 - 1, maps.normal[maps.mask], atol=2e-5)
    tex = tmp_path / "tex"
    export(res, tex, preset="unity-hdrp", normal="dx", mesh=True)
    patterns = {spec.file.format(name="res") for spec in formats.LAYOUTS["export"].values()}
    assert {p.name for p in tex.iterdir()} <= patterns
    assert len(list(tex.iterdir())) == 13


def test_normal_conventions_encode_and_decode():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(5, 7, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    gl, dx = formats.encode_normal(n, "gl"), formats.encode_normal(n, "dx")
    np.testing.assert_allclose(gl[..., 1], 1 - dx[..., 1], atol=1e-7)
    np.testing.assert_allclose(gl[..., [0, 2]], dx[..., [0, 2]])
    np.testing.assert_allclose(formats.decode_normal(dx, "dx"), n, atol=1e-6)
    np.testing.assert_allclose(formats.decode_normal(gl, "gl"), n, atol=1e-6)
    mask = np.zeros((5, 7), bool)
    mask[1:4, 2:5] = True
    enc = formats.encode_normal(n, mask=mask)
    assert (enc[~mask] == 0).all()
    assert (formats.decode_normal(enc, mask=mask)[~mask] == 0).all()
    with pytest.raises(ValueError, match="'gl' or 'dx'"):
        formats.encode_normal(n, "camera")


# ------------------------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("convention", ["gl", "dx"])
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_result_export_relight_export_round_trip(tmp_path, sphere_maps, preset, convention):
    """capture result -> export -> load it as relight does -> export again: the same files (within one code)."""
    from matcap.relight import load_maps

    maps = sphere_maps(24, varied=True)
    res = write_result(maps, tmp_path / "mat")
    first, second = tmp_path / "tex1", tmp_path / "tex2"
    export(res, first, preset=preset, normal=convention)
    loaded = load_maps(first)  # what `matcap relight TEX/` reads
    assert loaded.meta["kind"] == "export"
    # the export holds the result's maps: 16-bit normals / roughness / metallic, 8-bit sRGB base colour
    assert_same_maps(read_result(res), loaded, normal_deg=0.01, base=0.004, brdf=1.5 / 65535)
    export(loaded, second, name="mat", preset=preset, normal=convention)
    files = compare_sets(first, second, "mat")
    assert ("mat_normal_dx.png" in files) == (convention == "dx")
    assert_same_maps(loaded, load_maps(second), normal_deg=0.01, base=1e-6, brdf=1.5 / 65535)
    # the DirectX map alone (the OpenGL one gone) gives the same normals
    if convention == "dx":
        info = json.loads((second / "mat.json").read_text())
        del info["files"]["normal"]
        (second / "mat.json").write_text(json.dumps(info))
        (second / "mat_normal.png").unlink()
        assert_same_maps(loaded, load_maps(second), normal_deg=0.01, base=1e-6, brdf=1.5 / 65535)


def test_fit_frame_round_trip(tmp_path, sphere_maps):
    maps = sphere_maps(24, varied=True)
    maps.normal[maps.mask] = formats.tangent_to_camera(maps.normal, maps.mask, formats.tangent_frame(
        np.tile([0.3, 0.1, 0.95], (24, 24, 1)), np.ones((24, 24), bool), "fit"))[maps.mask]
    export(maps, tmp_path / "a", name="m", frame="fit")
    loaded = formats.load_maps(tmp_path / "a" / "m.json")
    assert_same_maps(maps, loaded, normal_deg=0.02, base=0.004, brdf=1.5 / 65535)
    export(loaded, tmp_path / "b", name="m", frame="fit")
    compare_sets(tmp_path / "a", tmp_path / "b", "m")


def test_relight_command_on_an_export(tmp_path, sphere_maps, capsys):
    """The user bug: `matcap relight TEX/` on the output of `matcap export ... --out TEX/`."""
    from matcap.cli import main

    res = write_result(sphere_maps(16, varied=True), tmp_path / "res")
    tex = tmp_path / "tex"
    assert main(["export", str(res), "--out", str(tex), "--preset", "unreal"]) == 0
    assert main(["relight", str(tex), "--spp", "1", "--size", "8", "--quiet"]) == 0, capsys.readouterr().err
    exr = imageio.read_exr(tex / "relight_studio_small_03.exr")
    assert exr.shape == (8, 8, 3) and exr[4, 4].mean() > 0 and (exr[0, 0] == 0).all()
    # the renders written into TEX/ do not confuse the next load; the export re-exports from its own folder
    assert formats.identify(tex)[0] == "export"
    assert main(["export", str(tex), "--out", str(tmp_path / "again"), "--preset", "unreal"]) == 0
    compare_sets(tex, tmp_path / "again", "res")


def test_relight_renders_an_export_like_its_result(tmp_path, sphere_maps):
    from matcap.relight import relight

    res = write_result(sphere_maps(16, varied=True), tmp_path / "res")
    export(res, tmp_path / "tex", normal="dx")
    a, b = relight(res, spp=4, seed=1)[0], relight(tmp_path / "tex", spp=4, seed=1)[0]
    assert np.abs(a - b).mean() < 0.01 * a.mean()


# ------------------------------------------------------------------------------------------------ foreign sets
@pytest.mark.parametrize("name, role", [
    ("Wood_BaseColor.png", ("base_color", "wood")),
    ("Wood_Base_Color.png", ("base_color", "wood")),
    ("Wood_Normal_OpenGL.png", ("normal_gl", "wood")),
    ("Wood_Normal_DirectX.png", ("normal_dx", "wood")),
    ("Wood_OcclusionRoughnessMetallic.png", ("arm", "wood")),
    ("Wood_Roughness.png", ("roughness", "wood")),
    ("Wood_Metallic.png", ("metallic", "wood")),
    ("brick_wall_diff_2k.jpg", ("base_color", "brick_wall")),
    ("brick_wall_nor_gl_2k.exr", ("normal_gl", "brick_wall")),
    ("brick_wall_nor_dx_2k.png", ("normal_dx", "brick_wall")),
    ("brick_wall_arm_4k.png", ("arm", "brick_wall")),
    ("brick_wall_rough_1k.png", ("roughness", "brick_wall")),
    ("Bricks076_1K-PNG_Color.png", ("base_color", "bricks076")),
    ("Bricks076_1K-PNG_NormalGL.png", ("normal_gl", "bricks076")),
    ("Bricks076_1K-PNG_NormalDX.png", ("normal_dx", "bricks076")),
    ("Bricks076_1K-PNG_Metalness.png", ("metallic", "bricks076")),
    ("basecolor.png", ("base_color", "")),
    ("normal_gl.png", ("normal_gl", "")),
    ("mat_orm.png", ("arm", "mat")),
    ("Wood_Height.png", None),
    ("Wood_Mixed_AO.png", None),
    ("relight_studio_small_03.png", None),
    ("img_00.png", None),
])
def test_foreign_names(name, role):
    assert formats.foreign_role(name) == role


def write_substance_set(folder: Path, h: int = 12, w: int = 20) -> dict[str, np.ndarray]:
    """A Substance-named set: 8-bit sRGB base colour, DirectX normal (tilted up), packed ORM, ignored extras."""
    folder.mkdir(parents=True)
    base = np.zeros((h, w, 3), np.float32)
    base[...] = (0.6, 0.3, 0.1)
    imageio.write_png(folder / "Wood_BaseColor.png", base, bits=8)
    up = np.array([0.0, 0.5, 1.0]) / np.linalg.norm([0.0, 0.5, 1.0])
    imageio.write_png(folder / "Wood_Normal_DirectX.png", formats.encode_normal(np.tile(up, (h, w, 1)), "dx"),
                      bits=8)
    orm = np.zeros((h, w, 3), np.float32)
    orm[...] = (0.9, 0.7, 0.2)
    imageio.write_png(folder / "Wood_OcclusionRoughnessMetallic.png", orm, bits=8)
    imageio.write_png(folder / "Wood_Height.png", np.full((h, w), 0.5), bits=16)
    imageio.write_png(folder / "Wood_Mixed_AO.png", np.full((h, w), 0.8), bits=8)
    return {"base": base, "up": up}


def test_substance_texture_set_loads(tmp_path):
    made = write_substance_set(tmp_path / "wood")
    maps = formats.load_maps(tmp_path / "wood")
    assert maps.meta["kind"] == "texture set" and maps.shape == (12, 20) and maps.mask.all()
    expect = imageio.srgb_to_linear(np.round(made["base"] * 255) / 255)
    np.testing.assert_allclose(maps.base_color, expect, atol=1e-6)  # decoded once
    assert abs(maps.roughness.mean() - round(0.7 * 255) / 255) < 1e-6
    assert abs(maps.metallic.mean() - round(0.2 * 255) / 255) < 1e-6
    assert maps.height is None  # displacement of unknown units is not read as pixel heights
    # the DirectX green was flipped back: the normal tilts up (+y), as it was made
    np.testing.assert_allclose(maps.normal[0, 0], made["up"], atol=0.01)
    assert maps.normal[0, 0, 1] > 0.4


def test_poly_haven_set_with_mixed_sizes_and_16_bit_base(tmp_path):
    folder = tmp_path / "ph"
    folder.mkdir()
    imageio.write_png(folder / "rock_diff_2k.png", np.full((16, 32, 3), 0.5), bits=16)  # 16-bit: still sRGB
    imageio.write_png(folder / "rock_nor_gl_2k.png", np.tile([0.5, 0.5, 1.0], (16, 32, 1)), bits=8)
    arm = np.zeros((8, 16, 3), np.float32)
    arm[...] = (1.0, 0.25, 0.0)
    imageio.write_png(folder / "rock_arm_1k.png", arm, bits=8)
    maps = formats.load_maps(folder, max_side=16)
    assert maps.shape == (8, 16)
    np.testing.assert_allclose(maps.base_color, imageio.srgb_to_linear(np.full((8, 16, 3), 0.5)), atol=1e-4)
    np.testing.assert_allclose(maps.roughness, round(0.25 * 255) / 255, atol=1e-6)
    np.testing.assert_allclose(maps.normal[..., 2], 1.0, atol=1e-3)


def test_two_sets_in_one_folder_and_nothing_to_load_are_one_line_errors(tmp_path):
    folder = tmp_path / "two"
    folder.mkdir()
    for stem in ("a_basecolor", "b_basecolor"):
        imageio.write_png(folder / f"{stem}.png", np.full((4, 4, 3), 0.5), bits=8)
    with pytest.raises(MatcapError, match="2 files hold the base color map"):
        formats.load_maps(folder)
    empty = tmp_path / "photos"
    empty.mkdir()
    imageio.write_png(empty / "img_00.png", np.full((4, 4, 3), 0.5), bits=8)
    with pytest.raises(MatcapError, match="not a capture result or texture set"):
        formats.load_maps(empty)
    with pytest.raises(MatcapError, match="no such folder"):
        formats.load_maps(tmp_path / "missing")


# ------------------------------------------------------------------------------------------------ glb
def test_glb_loads_as_a_file_and_as_a_folder(tmp_path, sphere_maps):
    maps = sphere_maps(24, varied=True)
    paths = export(maps, tmp_path / "tex", name="ball")
    from_file = formats.load_maps(paths["glb"])
    assert from_file.meta["kind"] == "glb"
    # 8-bit textures inside: normals within ~0.5 degree, base colour within an 8-bit sRGB step
    assert_same_maps(maps, from_file, normal_deg=0.6, base=0.005, brdf=0.5 / 255 + 1e-6)
    alone = tmp_path / "only_glb"
    alone.mkdir()
    shutil.copy(paths["glb"], alone / "ball.glb")
    assert formats.identify(alone) == ("glb", alone / "ball.glb")
    assert_same_maps(from_file, formats.load_maps(alone), normal_deg=0, base=0, brdf=0)


# ------------------------------------------------------------------------------------------------ synthetic scenes
def write_scene(folder: Path, sphere_maps) -> np.ndarray:
    maps = sphere_maps(16, varied=True)
    folder.mkdir()
    formats.write_scene_maps(folder, normal=maps.normal, mask=maps.mask, base_color=maps.base_color,
                             roughness=maps.roughness, metallic=maps.metallic)
    formats.write_scene_image(folder, 0, np.full((16, 16, 3), 0.25))
    formats.write_json(folder / "spec.json", {"lighting_group": "directional"})
    return maps.base_color


def test_synthetic_scene_base_color_is_decoded_once(tmp_path, sphere_maps):
    base = write_scene(tmp_path / "scene_000000", sphere_maps)
    # stored linear: the 16-bit codes are the linear values, not sRGB-encoded ones
    codes = stored(tmp_path / "scene_000000" / "basecolor.png")[..., ::-1]
    assert np.abs(codes - np.round(base * 65535)).max() <= 1
    for maps in (formats.load_maps(tmp_path / "scene_000000"), read_result(tmp_path / "scene_000000")):
        assert maps.meta["kind"] == "synthetic scene"
        np.testing.assert_allclose(maps.base_color, base, atol=1 / 65535)  # not srgb_to_linear(base)
    # a result folder's basecolor.png is sRGB: the same numbers come back from the other encoding
    res = write_result(formats.load_maps(tmp_path / "scene_000000"), tmp_path / "res")
    np.testing.assert_allclose(read_result(res).base_color, base, atol=2e-4)


def test_rendered_synthetic_scene_matches_its_training_arrays(tmp_path):
    """A scene rendered by `matcap synth` (procedural assets): its map files read back as its training arrays."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "matcap", "synth", "--out", str(tmp_path / "data"), "--scenes", "1",
                        "--resolution", "64", "--seed", "0", "--quiet"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    scenes = sorted((tmp_path / "data").glob("scene_*/data.npz"))
    assert len(scenes) == 1
    folder = scenes[0].parent
    maps = formats.load_maps(folder)
    with np.load(folder / "data.npz") as z:
        np.testing.assert_allclose(maps.base_color, z["base_color"].astype(np.float32), atol=2e-3)
        np.testing.assert_allclose(maps.roughness, z["roughness"].astype(np.float32), atol=2e-3)


# ------------------------------------------------------------------------------------------------ atomic writes
def test_atomic_writes_keep_the_old_file_and_give_usual_modes(tmp_path):
    from scenes.atomic import atomic_dir, atomic_path, write_json_atomic

    path = tmp_path / "a.json"
    write_json_atomic(path, {"x": np.float32(0.5), "n": np.arange(3), "p": Path("/x")})
    assert json.loads(path.read_text()) == {"x": 0.5, "n": [0, 1, 2], "p": "/x"}
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            Path(tmp).write_text("half")
            raise RuntimeError("interrupted")
    assert json.loads(path.read_text())["x"] == 0.5 and [p.name for p in tmp_path.iterdir()] == ["a.json"]
    folder = tmp_path / "dir"
    with atomic_dir(folder) as tmp:
        (tmp / "f").write_text("1")
    assert (folder / "f").read_text() == "1" and folder.stat().st_mode & 0o777 == 0o777 & ~umask
    with pytest.raises(RuntimeError):
        with atomic_dir(folder) as tmp:
            (tmp / "f").write_text("2")
            raise RuntimeError("interrupted")
    assert (folder / "f").read_text() == "1" and sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "dir"]


def test_refinement_outputs_are_rows_of_the_table(tmp_path, sphere_maps):
    from matcap.evaluation.metrics import colorize_error

    values = np.linspace(0, 1, 20).reshape(4, 5)
    values[0, 0] = np.nan  # background
    path = formats.write_visual(tmp_path, "residual", values, vmax=0.5)
    assert path.name == "residual.png"
    codes = stored(path)[..., ::-1]
    assert codes.shape == (4, 5, 3) and (codes[0, 0] == 0).all()
    np.testing.assert_array_equal(codes, np.round(colorize_error(values, max_deg=0.5) * 255))
    assert (codes[-1, -1] == codes[2, 0]).all()  # clipped at vmax: 1.0 and ~0.53 both full red
    assert formats.write_visual(tmp_path, "light_variation", values, vmax=1).name == "light_variation.png"
    formats.write_json(tmp_path / formats.LAYOUTS["result"]["lights"].file, {"lights": [np.float32(1)]})
    assert json.loads((tmp_path / "lights.json").read_text()) == {"lights": [1.0]}
    # written inside a result folder before it is renamed into place, and listed in capture.json
    res = write_result(sphere_maps(8), tmp_path / "res", extra_files=lambda tmp: [
        formats.write_json(tmp / "fit.json", {"psnr": 30}).name,
        formats.write_visual(tmp, "residual", np.zeros((8, 8)), vmax=1).name])
    assert json.loads((res / "capture.json").read_text())["files"][-3:] == ["fit.json", "residual.png",
                                                                             "capture.json"]
    assert read_result(res).shape == (8, 8)


# ------------------------------------------------------------------------------------------------ library chain
def test_library_capture_relights_and_exports_reading_the_env_map_once(tmp_path, monkeypatch):
    import torch

    import matcap.relight
    from matcap.capture import capture
    from networks.checkpoint import save_weights
    from networks.config import get_config
    from networks.model import SDMUniPS

    weights = tmp_path / "w"
    torch.manual_seed(0)
    for target in ("normal", "brdf"):
        cfg = get_config("tiny", target)
        save_weights(weights / f"{target}.safetensors", SDMUniPS(cfg), cfg, {"name": target})
    reads = []
    real = matcap.relight.load_envmap
    monkeypatch.setattr(matcap.relight, "load_envmap", lambda p: reads.append(p) or real(p))
    env = matcap.relight.default_envmap_path()
    photos = tmp_path / "photos"
    yy, xx = np.mgrid[0:24, 0:32]
    x, y = (xx - 16) / 10, (12 - yy) / 10
    inside = x**2 + y**2 < 1
    normal = np.dstack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, 1))])
    for i, light in enumerate(([0.3, 0.2, 1.0], [-0.4, 0.1, 1.0], [0.0, -0.4, 1.0])):
        shade = np.clip(normal @ (np.array(light) / np.linalg.norm(light)), 0, 1)
        imageio.write_png(photos / f"img_{i:02d}.png", np.where(inside[..., None], 0.7 * shade[..., None], 0.05)
                          * np.ones(3), bits=16)
    imageio.write_png(photos / "mask.png", inside.astype(np.float32), bits=8)
    with pytest.raises(MatcapError, match="unknown preset 'bogus'"):  # checked before the networks run
        capture(photos, tmp_path / "bad", weights=[weights], relight=env, export={"out": tmp_path / "x",
                                                                                 "preset": "bogus"})
    assert not (tmp_path / "bad").exists()
    reads.clear()
    maps, out = capture(photos, tmp_path / "res", weights=[weights], relight=[{"env": env, "spp": 1},
                                                                              {"point": (0, 0, 3), "spp": 1}],
                        export={"out": tmp_path / "tex", "preset": "unreal"})
    assert reads == [env]
    assert (out / "relight_studio_small_03.exr").is_file() and (out / "relight_point_0_0_3.png").is_file()
    assert (tmp_path / "tex" / "res_normal_dx.png").is_file()
    export(out, tmp_path / "again", preset="unreal")
    compare_sets(tmp_path / "tex", tmp_path / "again", "res")


def test_plain_names_are_a_texture_set_not_a_result(tmp_path):
    """basecolor.png + normal.png (no normal.exr, mask or capture.json) is a texture set whose normal is OpenGL."""
    folder = tmp_path / "plain"
    folder.mkdir()
    imageio.write_png(folder / "basecolor.png", np.full((6, 6, 3), 0.5), bits=8)
    imageio.write_png(folder / "normal.png", np.tile([0.5, 0.75, 1.0], (6, 6, 1)), bits=8)
    assert formats.identify(folder) == ("texture set", folder)
    maps = formats.load_maps(folder)
    assert maps.mask.all() and maps.normal[0, 0, 1] > 0.4
    imageio.write_png(folder / "mask.png", np.ones((6, 6)), bits=8)  # now laid out as a result (normal.png only)
    assert formats.identify(folder) == ("result", folder)

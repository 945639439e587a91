"""`matcap relight` and `matcap.relight`: inputs (result folder, texture set), outputs, errors."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from matcap.cli import main  # noqa: E402
from matcap.imageio import read_exr, read_image, write_png  # noqa: E402


@pytest.fixture()
def texture_set(tmp_path):
    d = tmp_path / "tex"
    h, w = 16, 24
    base = np.zeros((h, w, 3), np.float32)
    base[...] = (0.5, 0.25, 0.75)
    write_png(d / "basecolor.png", base, bits=8)
    orm = np.zeros((h, w, 3), np.float32)
    orm[...] = (1.0, 0.6, 0.2)
    write_png(d / "orm.png", orm, bits=8)
    nrm = np.zeros((h, w, 3), np.float32)
    nrm[...] = (0.5, 0.75, 1.0)  # (0, 0.5, 1) normalised: tilted up (+y, OpenGL)
    write_png(d / "normal_gl.png", nrm, bits=8)
    return d


def test_maps_from_texture_set(texture_set):
    from matcap.imageio import srgb_to_linear
    from matcap.relight import maps_from_texture_set

    maps = maps_from_texture_set(texture_set)
    assert maps.shape == (16, 24) and maps.mask.all()
    np.testing.assert_allclose(maps.base_color[0, 0], srgb_to_linear(np.round(np.array([0.5, 0.25, 0.75]) * 255) / 255),
                               atol=1e-6)
    assert abs(maps.roughness.mean() - 153 / 255) < 1e-6 and abs(maps.metallic.mean() - 51 / 255) < 1e-6
    n = maps.normal[0, 0]
    assert n[1] > 0.4 and abs(n[0]) < 0.01 and abs(np.linalg.norm(n) - 1) < 1e-5
    small = maps_from_texture_set(texture_set, max_size=12)
    assert small.shape == (8, 12)


def test_relight_library_writes_exr_and_png(tmp_path, sphere_maps):
    from matcap import relight

    maps = sphere_maps()
    images = relight(maps, env=None, spp=4, out=tmp_path)
    assert len(images) == 1 and images[0].shape == (24, 24, 3)
    exr = read_exr(tmp_path / "relight_studio_small_03.exr")
    np.testing.assert_allclose(exr, images[0], rtol=1e-6)
    png = read_image(tmp_path / "relight_studio_small_03.png")  # RGBA -> RGB; alpha checked via cv2 below
    assert png.pixels.dtype == np.uint8
    import cv2

    rgba = cv2.imread(str(tmp_path / "relight_studio_small_03.png"), cv2.IMREAD_UNCHANGED)
    assert rgba.shape[2] == 4 and rgba[0, 0, 3] == 0 and rgba[12, 12, 3] == 255
    assert (exr[0, 0] == 0).all() and exr[12, 12].mean() > 0
    # second call refuses to overwrite
    from matcap.errors import MatcapError

    with pytest.raises(MatcapError, match="overwrite"):
        relight(maps, spp=1, out=tmp_path)


def test_relight_point_light_names_and_size(tmp_path, sphere_maps):
    from matcap.relight import relight

    maps = sphere_maps()
    maps.roughness[:] = 1.0  # near-Lambertian: the centre pixel is then close to albedo * E / pi
    imgs = relight(maps, point="0,0,3", spp=1, size="12x12", out=tmp_path)
    assert imgs[0].shape == (12, 12, 3)
    assert (tmp_path / "relight_point_0_0_3.exr").is_file()
    # default intensity pi*|P|^2 gives irradiance pi at the centre: radiance ~ albedo * cos(0) there
    assert abs(imgs[0][5:7, 5:7].mean() / 0.5 - 1) < 0.06


def test_cli_relight_result_folder(tmp_path, capsys, sphere_maps):
    from matcap.results import write_result

    maps = sphere_maps()
    write_result(maps, tmp_path / "result")
    env = tmp_path / "white.hdr"
    import cv2

    cv2.imwrite(str(env), np.full((8, 16, 3), 1.0, np.float32))
    code = main(["relight", str(tmp_path / "result"), "--env", str(env), "--spp", "2", "--rotate", "30",
                 "--exposure", "-1", "--quiet"])
    assert code == 0
    img = read_exr(tmp_path / "result" / "relight_white.exr")
    assert img.shape == (24, 24, 3) and img.max() > 0
    # refuses to overwrite, one line, exit 2
    assert main(["relight", str(tmp_path / "result"), "--env", str(env), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "overwrite" in err[0]
    assert main(["relight", str(tmp_path / "result"), "--env", str(env), "--overwrite", "--spp", "1", "--quiet",
                 "--out", str(tmp_path / "o"), "--point", "1,1,2", "--intensity", "5"]) == 0


@pytest.mark.parametrize("argv,word", [
    (["--point", "1,2"], "X,Y,Z"),
    (["--env", "missing.exr"], "no such"),
    (["--spp", "0"], "spp"),
    (["--size", "abc"], "size"),
    (["--intensity", "3"], "point"),
])
def test_cli_relight_bad_input_is_one_line_exit_2(tmp_path, capsys, texture_set, argv, word):
    code = main(["relight", str(texture_set), "--out", str(tmp_path / "o"), "--quiet", *argv])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("matcap relight: error:") and word in err[0]


def test_cli_relight_not_a_result(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["relight", str(tmp_path / "empty")]) == 2
    assert "texture set" in capsys.readouterr().err


def test_cli_relight_with_a_constant_metallic(tmp_path, sphere_maps):
    """--constant metallic=0 renders the maps as a dielectric: the same as rendering maps whose metallic is 0."""
    from matcap.results import write_result

    maps = sphere_maps()
    maps.metallic[maps.mask] = 1.0  # a metal: dark under a white sky wherever its base color is dark
    write_result(maps, tmp_path / "result")
    dielectric = maps.with_constant("metallic", 0.0)
    write_result(dielectric, tmp_path / "dielectric")
    env = tmp_path / "white.hdr"
    import cv2

    cv2.imwrite(str(env), np.full((8, 16, 3), 1.0, np.float32))
    for folder, extra in (("result", ["--constant", "metallic=0"]), ("dielectric", []), ("metal", [])):
        src = tmp_path / ("result" if folder == "metal" else folder)
        assert main(["relight", str(src), "--env", str(env), "--spp", "4", "--quiet", "--out", str(tmp_path / f"o_{folder}"),
                     *extra]) == 0
    got, want, metal = (read_exr(tmp_path / f"o_{k}" / "relight_white.exr") for k in ("result", "dielectric", "metal"))
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.abs(got - metal).mean() > 0.01
    assert main(["relight", str(tmp_path / "result"), "--env", str(env), "--constant", "shiny=1"]) == 2

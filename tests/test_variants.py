"""Every command that renders works in both Mitsuba variants: ``llvm_ad_rgb`` and the ``scalar_rgb`` fallback
a new machine gets without libLLVM >= 17. Each test runs once per variant (``mitsuba_variant``)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from conftest import sphere_photos  # noqa: E402
from matcap.cli import main  # noqa: E402
from matcap.imageio import read_exr, read_image  # noqa: E402


def test_choose_variant_honours_the_forced_variant(mitsuba_variant):
    import mitsuba as mi

    from renderers.variant import choose_variant

    assert choose_variant() == mitsuba_variant == mi.variant()
    r = subprocess.run([sys.executable, "-c", "from renderers.variant import choose_variant; print(choose_variant())"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == mitsuba_variant, r.stderr


def test_relight_point_light_gives_the_lambertian_radiance(mitsuba_variant, sphere_maps, tmp_path):
    """Near-Lambertian sphere, point light on the axis: the centre is close to albedo (see test_relight_cli)."""
    from matcap.relight import relight

    maps = sphere_maps()
    maps.roughness[:] = 1.0
    img = relight(maps, point="0,0,3", spp=4, size="12x12", out=tmp_path)[0]
    assert img.shape == (12, 12, 3) and np.isfinite(img).all()
    assert abs(img[5:7, 5:7].mean() / 0.5 - 1) < 0.06
    assert (img[0, 0] == 0).all()


def test_relight_white_environment_gives_the_albedo(mitsuba_variant, sphere_maps, tmp_path):
    """Under a uniform white sky of radiance 1 a Lambertian surface reflects its albedo at every normal."""
    import cv2

    from matcap.results import write_result

    maps = sphere_maps()
    maps.roughness[:] = 1.0
    write_result(maps, tmp_path / "result")
    env = tmp_path / "white.hdr"
    cv2.imwrite(str(env), np.full((8, 16, 3), 1.0, np.float32))
    assert main(["relight", str(tmp_path / "result"), "--env", str(env), "--spp", "16", "--quiet",
                 "--out", str(tmp_path / "o")]) == 0
    img = read_exr(tmp_path / "o" / "relight_white.exr")
    centre = img[9:15, 9:15].mean()
    assert abs(centre / 0.5 - 1) < 0.08, centre


def test_gallery_in_both_variants(mitsuba_variant, sphere_maps, tmp_path):
    from matcap import gallery

    info = gallery(sphere_maps(16, varied=True), envs=None, orbit=2, out=tmp_path / "g", size=16, spp=1,
                   orbit_spp=1, progress=False)
    assert (tmp_path / "g" / "index.html").is_file() and (tmp_path / "g" / "orbit.gif").is_file()
    meta = json.loads((tmp_path / "g" / "gallery.json").read_text())
    assert meta and info is not None
    sheet = read_image(tmp_path / "g" / "orbit_sheet.png").pixels
    assert sheet.max() > 0


def test_capture_relight_export_in_both_variants(mitsuba_variant, tiny_weights, tmp_path):
    """The whole user path in one command, as a subprocess that inherits the forced variant."""
    from matcap.relight import default_envmap_path

    photos = sphere_photos(tmp_path / "photos", h=24, w=32)
    out, tex = tmp_path / "result", tmp_path / "tex"
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(photos), "--out", str(out), "--weights",
                        str(tiny_weights), "--quiet", "--relight", str(default_envmap_path()), "--point", "0,0,3",
                        "--spp", "2", "--export", str(tex)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    relit = read_exr(out / f"relight_{default_envmap_path().stem}.exr")
    assert relit.shape == (24, 32, 3) and np.isfinite(relit).all() and relit.max() > 0
    assert (out / "relight_point_0_0_3.png").is_file()
    assert (tex / "result.glb").is_file() and (tex / "result_normal.png").is_file()
    files = json.loads((out / "capture.json").read_text())["files"]  # the renders are part of the result
    assert sorted(files) == sorted(p.name for p in out.iterdir()) and "relight_point_0_0_3.exr" in files

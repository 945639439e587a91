"""`matcap capture`: folder reading, colour handling, geometry (pad / crop / scalable), outputs, bad input."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from matcap import imageio
from matcap.estimate import _from_square, _plan, _to_square, estimate
from matcap.photos import load_capture
from conftest import sphere_photos




def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "matcap", *args], capture_output=True, text=True, timeout=600)


def assert_one_line_error(r: subprocess.CompletedProcess, needle: str) -> None:
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0], r.stderr


# ------------------------------------------------------------------------------------------ reading


def test_load_capture_colour_handling_and_skips(tmp_path):
    folder = sphere_photos(tmp_path / "a", bits=8)
    imageio.write_png(folder / "normal_gt.png", np.zeros((40, 56, 3)), bits=8)
    cap = load_capture(folder)
    assert len(cap.images) == 4 and cap.mask.shape == (40, 56)
    assert cap.skipped == ["normal_gt.png"] and cap.colour == "8-bit sRGB decoded to linear"
    raw = imageio.read_image(folder / "img_00.png").pixels
    assert np.allclose(cap.images[0], imageio.srgb_to_linear(raw / 255.0), atol=1e-6)
    assert load_capture(folder, linear=True).colour == "8-bit taken as linear"
    cap16 = load_capture(sphere_photos(tmp_path / "b", bits=16))
    assert cap16.colour == "16-bit taken as linear"
    raw16 = imageio.read_image(tmp_path / "b" / "img_01.png").pixels
    assert np.array_equal(cap16.images[1], raw16.astype(np.float32) / 65535)


@pytest.mark.parametrize("case", ["empty", "one", "mixed", "unreadable", "nan", "mask"])
def test_bad_input_is_one_line_exit_2(tmp_path, case):
    folder = tmp_path / "in"
    folder.mkdir()
    if case == "empty":
        needle = "no images found"
    elif case == "one":
        sphere_photos(folder, n=1, mask=False)
        needle = "only one image"
    elif case == "mixed":
        sphere_photos(folder, n=2, mask=False)
        imageio.write_png(folder / "img_09.png", np.zeros((41, 56, 3)))
        needle = "all images must share one size"
    elif case == "unreadable":
        sphere_photos(folder, n=2, mask=False)
        (folder / "img_05.png").write_bytes(b"not a png at all")
        needle = "cannot read image"
    elif case == "nan":
        sphere_photos(folder, n=2, mask=False)
        bad = np.ones((40, 56, 3), np.float32)
        bad[3, 4] = np.nan
        imageio.write_exr(folder / "img_07.exr", bad)
        needle = "NaN or Inf"
    else:
        sphere_photos(folder, n=3, mask=False)
        imageio.write_png(folder / "mask.png", np.ones((20, 20)), bits=8)
        needle = "mask is 20x20 but the images are 56x40"
    r = run_cli("capture", str(folder), "--out", str(tmp_path / "out"), "--weights", str(tmp_path))
    assert_one_line_error(r, needle)
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------ geometry


@pytest.mark.parametrize("shape,native", [((40, 56), 64), ((150, 90), 64), ((64, 64), 64)])
def test_pad_and_crop_back_is_exact_where_not_resized(shape, native):
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    img = np.dstack([np.sin(xx / 7.0), np.cos(yy / 5.0), (xx + yy) / (shape[0] + shape[1])]).astype(np.float32)
    fr = _plan(shape, None, native)
    sq = _to_square(img, fr, "cubic")
    assert sq.shape == (fr.size, fr.size, 3) and fr.size % native == 0
    back = _from_square(sq, fr, shape)
    if fr.size == fr.side:  # padded, not resized: exact
        assert np.array_equal(back, img)
    else:
        err = np.abs(back - img)  # smooth content survives the resize round trip; the outermost pixels see the padding
        assert err[2:-2, 2:-2].max() < 0.02 and err.mean() < 0.01


# ------------------------------------------------------------------------------------------ end to end


def test_capture_writes_every_output(tiny_weights, tmp_path):
    folder = sphere_photos(tmp_path / "photos")
    out = tmp_path / "result"
    r = run_cli("capture", str(folder), "--out", str(out), "--weights", str(tiny_weights), "--quiet")
    assert r.returncode == 0, r.stderr
    for name in ("normal.exr", "normal.png", "mask.png", "basecolor.png", "roughness.png", "metallic.png", "capture.json"):
        assert (out / name).exists(), name
    normal = imageio.read_exr(out / "normal.exr")
    mask = imageio.read_image(out / "mask.png").pixels[..., 0] > 0
    assert normal.shape == (40, 56, 3)
    assert np.all(normal[~mask] == 0)
    assert np.allclose(np.linalg.norm(normal[mask], axis=1), 1.0, atol=1e-4)
    png = imageio.read_image(out / "normal.png")
    assert png.kind == "16bit"
    assert np.abs(png.pixels[mask] / 65535.0 - (normal[mask] + 1) / 2).max() <= 0.5 / 65535 + 1e-7
    info = json.loads((out / "capture.json").read_text())
    assert info["colour_handling"] == "16-bit taken as linear"
    assert info["inputs"] == [f"img_{i:02d}.png" for i in range(4)]
    assert set(info["models"]) == {"normal", "brdf"} and info["timings"]["total_s"] > 0
    # refuses to overwrite, and leaves the old result intact
    before = (out / "normal.exr").read_bytes()
    r2 = run_cli("capture", str(folder), "--out", str(out), "--weights", str(tiny_weights), "--quiet")
    assert_one_line_error(r2, "already holds files")
    assert (out / "normal.exr").read_bytes() == before


def test_capture_is_deterministic_for_a_seed_and_scalable_for_large_inputs(tiny_weights):
    rng = np.random.default_rng(1)
    images = [rng.random((150, 100, 3)).astype(np.float32) for _ in range(3)]
    normal_only = [tiny_weights / "normal_tiny.safetensors"]
    a = estimate(images, None, weights=normal_only, seed=3, pixel_samples=500)
    b = estimate(images, None, weights=normal_only, seed=3, pixel_samples=500)
    assert np.array_equal(a.normal, b.normal)
    assert a.normal.shape == (150, 100, 3) and a.base_color is None
    assert a.meta["models"]["normal"]["scalable"] is True  # 150 > native 64 -> padded to 192, 3x3 polyphase
    assert a.meta["models"]["normal"]["input_side"] == 192


def test_no_default_model_message(monkeypatch, tmp_path):
    import matcap.estimate as est

    monkeypatch.setattr(est, "DEFAULT_WEIGHTS", {"normal": tmp_path / "none.safetensors",
                                                 "brdf": tmp_path / "none2.safetensors"})
    with pytest.raises(est.MatcapError, match="no trained default model is installed.*matcap weights import"):
        est.resolve_weights(None)


def test_capture_relight_and_export_in_one_go(tiny_weights, tmp_path):
    from matcap.relight import default_envmap_path

    folder = sphere_photos(tmp_path / "photos")
    out, tex = tmp_path / "result", tmp_path / "textures"
    r = run_cli("capture", str(folder), "--out", str(out), "--weights", str(tiny_weights), "--quiet",
                "--relight", str(default_envmap_path()), "--point", "0,0,3", "--spp", "4", "--export", str(tex))
    assert r.returncode == 0, r.stderr
    relit = imageio.read_exr(out / f"relight_{default_envmap_path().stem}.exr")
    assert relit.shape == (40, 56, 3) and np.isfinite(relit).all() and relit.max() > 0
    assert (out / "relight_point_0_0_3.png").exists()
    assert (tex / "result.glb").exists() and (tex / "result_normal.png").exists()
    exported = imageio.read_image(tex / "result_normal.png").pixels / 65535.0
    mask = imageio.read_image(out / "mask.png").pixels[..., 0] > 0
    normal = imageio.read_exr(out / "normal.exr")
    from matcap.normals import camera_to_tangent

    expected = (camera_to_tangent(normal, mask) + 1) / 2  # the export of exactly the maps capture wrote
    assert np.abs(exported[mask] - expected[mask]).max() < 1e-4


def test_views_average_mirrored_predictions_and_are_recorded(tiny_weights, tmp_path):
    """--views 2 differs from one view, keeps unit normals and BRDF maps in range, and lands in capture.json."""
    from matcap.estimate import estimate

    images = [np.random.default_rng(i).uniform(0.05, 1, (40, 56, 3)).astype(np.float32) for i in range(3)]
    one = estimate(images, None, weights=[tiny_weights], seed=1)
    two = estimate(images, None, weights=[tiny_weights], seed=1, views=2)
    inside = two.mask
    assert np.allclose(np.linalg.norm(two.normal[inside], axis=-1), 1.0, atol=1e-5)
    assert np.degrees(np.arccos(np.clip((one.normal * two.normal).sum(-1)[inside], -1, 1))).mean() > 0.01
    assert 0.0 <= two.roughness.min() and two.roughness.max() <= 1.0
    assert two.meta["views"] == 2
    folder = sphere_photos(tmp_path / "photos")
    r = run_cli("capture", str(folder), "--out", str(tmp_path / "out"), "--weights", str(tiny_weights), "--quiet",
                "--views", "4")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "out" / "capture.json").read_text())["views"] == 4
    bad = run_cli("capture", str(folder), "--out", str(tmp_path / "out3"), "--weights", str(tiny_weights), "--views", "3")
    assert bad.returncode == 2 and "invalid choice" in bad.stderr


def test_constant_maps_replace_estimates_on_the_mask(tiny_weights, tmp_path):
    folder = sphere_photos(tmp_path / "photos")
    out = tmp_path / "result"
    r = run_cli("capture", str(folder), "--out", str(out), "--weights", str(tiny_weights), "--quiet",
                "--constant", "metallic=0", "--constant", "roughness=0.25")
    assert r.returncode == 0, r.stderr
    mask = imageio.read_image(out / "mask.png").pixels[..., 0] > 0
    metallic = imageio.read_image(out / "metallic.png").pixels[..., 0]
    roughness = imageio.read_image(out / "roughness.png").pixels[..., 0] / 65535.0  # 16-bit, linear
    assert mask.any() and np.all(metallic == 0)
    assert np.abs(roughness[mask] - 0.25).max() <= 0.5 / 65535 + 1e-7 and np.all(roughness[~mask] == 0)
    info = json.loads((out / "capture.json").read_text())
    assert info["constant_maps"] == {"metallic": 0.0, "roughness": 0.25}
    # the estimated base color is untouched: not constant on the mask
    base = imageio.read_image(out / "basecolor.png").pixels
    assert base[mask].std() > 0


@pytest.mark.parametrize("item", ["metallic=2", "albedo=0.5", "roughness", "metallic=abc"])
def test_bad_constant_is_one_line_exit_2_before_any_work(tiny_weights, tmp_path, item):
    folder = sphere_photos(tmp_path / "photos")
    r = run_cli("capture", str(folder), "--out", str(tmp_path / "out"), "--weights", str(tiny_weights),
                "--constant", item)
    assert_one_line_error(r, f"--constant {item!r}")
    assert not (tmp_path / "out").exists()


def test_with_constant_numerics_and_checks():
    from scenes.materialmaps import MaterialMaps

    mask = np.zeros((3, 4), bool)
    mask[1:, 1:3] = True
    maps = MaterialMaps(np.dstack([np.zeros((3, 4, 2)), np.ones((3, 4))]), mask,
                        metallic=np.full((3, 4), 0.7, np.float32))
    out = maps.with_constant("metallic", 0.0).with_constant("roughness", 0.5)
    assert np.all(out.metallic == 0) and out.roughness.dtype == np.float32
    np.testing.assert_array_equal(out.roughness, np.where(mask, 0.5, 0.0))
    assert np.all(maps.metallic == 0.7)  # a copy: the original is unchanged
    with pytest.raises(ValueError, match="only roughness and metallic"):
        maps.with_constant("base_color", 0.5)
    with pytest.raises(ValueError, match=r"\[0, 1\], got 1.5"):
        maps.with_constant("roughness", 1.5)


@pytest.mark.parametrize("args, needle", [
    (["capture", "photos", "--views", "3"], "argument --views: invalid choice: 3"),
    (["capture"], "the following arguments are required: photos"),
    (["export", "res", "--out", "tex", "--preset", "nope"], "argument --preset: invalid choice: 'nope'"),
    (["synth", "--out", "d", "--scenes", "x"], "argument --scenes: invalid int value: 'x'"),
    (["nosuchcommand"], "argument COMMAND: invalid choice: 'nosuchcommand'"),
])
def test_usage_mistakes_are_one_line_exit_2(args, needle, capsys):
    from matcap.cli import main

    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and "usage:" not in err and "--help" in err


def test_max_side_shrinks_photos_and_mask_first(tiny_weights, tmp_path):
    folder = sphere_photos(tmp_path / "photos")  # 56 x 40
    out = tmp_path / "result"
    r = run_cli("capture", str(folder), "--out", str(out), "--weights", str(tiny_weights), "--quiet",
                "--max-side", "28")
    assert r.returncode == 0, r.stderr
    normal = imageio.read_exr(out / "normal.exr")
    assert normal.shape == (20, 28, 3)
    info = json.loads((out / "capture.json").read_text())
    assert info["image_size_wh"] == [28, 20] and info["photo_size_wh"] == [56, 40]
    # area averaging in linear light: the shrunk photo's mean equals the original's
    from matcap.photos import downscale, load_capture

    cap = load_capture(folder)
    small = downscale(cap, 28)
    assert small.images[0].shape == (20, 28, 3) and small.mask.shape == (20, 28)
    np.testing.assert_allclose(small.images[0].mean(), cap.images[0].mean(), rtol=1e-4)
    assert abs(small.mask.mean() - cap.mask.mean()) < 0.03
    assert downscale(cap, 56) is cap  # already fits
    bad = run_cli("capture", str(folder), "--out", str(tmp_path / "bad"), "--weights", str(tiny_weights),
                  "--max-side", "8")
    assert_one_line_error(bad, "--max-side must be at least 16")


def test_phone_jpegs_are_turned_upright_by_their_exif_orientation(tmp_path):
    """A portrait phone photo is stored landscape with EXIF Orientation 6 (rotate 90 deg clockwise to view)."""
    from PIL import Image

    pixels = np.zeros((10, 20, 3), np.uint8)
    pixels[:, :5] = 255  # stored: the left quarter is white
    exif = Image.Exif()
    exif[0x0112] = 6
    folder = tmp_path / "phone"
    folder.mkdir()
    for i in range(2):
        Image.fromarray(pixels).save(folder / f"IMG_{i}.jpg", exif=exif, quality=100)
    cap = load_capture(folder)
    upright = cap.images[0]
    assert upright.shape == (20, 10, 3)  # portrait, as a viewer shows it
    # rotated clockwise: the stored left edge is now the top
    assert upright[:4].mean() > 0.9 and upright[6:].mean() < 0.05


def test_an_odd_first_image_is_the_one_blamed(tmp_path):
    from matcap import imageio
    from matcap.errors import MatcapError
    from matcap.photos import load_capture

    imageio.write_png(tmp_path / "a.png", np.full((12, 20, 3), 0.5, np.float32), bits=8)  # the odd one
    for name in ("b.png", "c.png", "d.png"):
        imageio.write_png(tmp_path / name, np.full((10, 10, 3), 0.5, np.float32), bits=8)
    with pytest.raises(MatcapError) as exc:
        load_capture(tmp_path)
    assert str(exc.value) == "a.png is 20x12 but 3 of the 4 images are 10x10; all images must share one size"


def test_bf16_on_a_cpu_without_bf16_instructions_warns_in_one_line(tiny_weights, monkeypatch, capsys):
    """bf16 is emulated (several times slower than fp32) on CPUs without AVX512-BF16 / AMX: say so, still run."""
    import torch

    import networks.inference as inference

    assert inference.bf16_is_native("cuda") is True
    assert inference.bf16_is_native("cpu") == bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    images = [np.random.default_rng(i).uniform(0.05, 1, (24, 24, 3)).astype(np.float32) for i in range(2)]
    monkeypatch.setattr(inference, "bf16_is_native", lambda device="cpu": False)
    maps = estimate(images, None, weights=[tiny_weights], seed=1, bf16=True)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(lines) == 1 and "--bf16" in lines[0] and "emulated" in lines[0]
    assert maps.meta["bf16"] is True and np.isfinite(maps.normal[maps.mask]).all()
    monkeypatch.setattr(inference, "bf16_is_native", lambda device="cpu": True)
    estimate(images, None, weights=[tiny_weights], seed=1, bf16=True)
    assert "warning:" not in capsys.readouterr().err

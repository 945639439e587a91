"""Mirror-ball light calibration (`matcap.calibrate`, `matcap calibrate`): the ball found and the lights recovered
on a Mitsuba render (with and without a mask), the perspective model on a ray-traced ball, the outputs, and every
bad input as one line with exit code 2."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from matcap.calibrate import Calibration, calibrate, direction_to_pixel, reflect
from matcap.errors import MatcapError

SIZE = 128


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(axis=1), -1, 1)))


@pytest.fixture(scope="module")
def ball_render():
    """12 photos (128 px) of a glossy sphere and a chrome ball of radius 38.4 px, linear float."""
    pytest.importorskip("mitsuba")
    from renderers.ballscene import BallScene, default_lights, render

    scene = BallScene(directions=default_lights(12, seed=1), object_centre=(-0.68, 0.62, 0.0), object_radius=0.28,
                      ball_centre=(0.3, -0.3, 0.0), ball_radius=0.6)
    return render(scene, size=SIZE, spp=16, seed=0)


@pytest.fixture(scope="module")
def photo_folder(ball_render, tmp_path_factory):
    """The render as 16-bit linear PNGs (exposed so that the ball's highlights clip, as in a real capture)."""
    from matcap.imageio import write_png

    folder = tmp_path_factory.mktemp("ball") / "photos"
    folder.mkdir()
    for k, img in enumerate(ball_render.images):
        write_png(folder / f"img_{k + 1:02d}.png", np.clip(img * 2.0, 0, 1), bits=16)
    return folder


def test_render_ground_truth(ball_render):
    cx, cy, r = ball_render.circle
    assert (cx, cy, r) == pytest.approx((83.2 - 0.5, 83.2 - 0.5, 38.4))
    assert abs(ball_render.ball_mask.sum() - math.pi * r * r) < 0.01 * math.pi * r * r
    obj = ball_render.object_mask
    assert abs(obj.sum() - math.pi * (0.28 * SIZE / 2) ** 2) < 0.03 * obj.sum()
    assert not (obj & ball_render.ball_mask).any()
    n = ball_render.normal[obj]
    assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-3) and (n[:, 2] > -0.05).all()


@pytest.mark.parametrize("with_mask", [False, True])
def test_ball_found_and_lights_within_half_a_degree(ball_render, with_mask):
    mask = ball_render.ball_mask if with_mask else None
    cal = calibrate(list(ball_render.images), ball_mask=mask)
    assert cal.circle_source == ("mask" if with_mask else "auto")
    true = np.array(ball_render.circle)
    assert np.abs(np.array(cal.circle) - true).max() < 0.15  # pixels
    err = _angles(cal.directions, ball_render.directions)
    assert err.max() < 0.5, err
    assert np.median(err) < 0.3, err
    # every light has the same irradiance: relative intensities near 1 (highlight energy, render noise ~10 %)
    assert cal.intensities is not None and cal.intensities.shape == (12, 3)
    assert np.abs(cal.intensities - 1).max() < 0.25
    # the highlight positions are where the directions reflect
    for k in (0, 5):
        d, hit = reflect(cal.highlights[k:k + 1, 0], cal.highlights[k:k + 1, 1], cal.circle, cal.size)
        assert hit[0] and _angles(d, cal.directions[k:k + 1])[0] < 1e-3


def test_relative_intensities(ball_render):
    """Photos scaled by known factors come back with intensities in those ratios (the highlight's energy)."""
    scale = np.linspace(0.5, 2.0, 12)
    base = calibrate(list(ball_render.images))
    scaled = calibrate([img * s for img, s in zip(ball_render.images, scale)])
    ratio = scaled.intensities[:, 1] / base.intensities[:, 1]
    ratio /= ratio.mean()
    assert np.abs(ratio - scale / scale.mean()).max() < 0.01
    assert _angles(scaled.directions, base.directions).max() < 0.15  # the median image moves the circle a little


def test_ball_mask_keeps_the_ball_out(ball_render):
    cal = calibrate(list(ball_render.images))
    mask = cal.ball_mask()
    assert mask.shape == (SIZE, SIZE) and mask.dtype == bool
    assert mask[ball_render.ball_mask].all()  # the whole disc, with its margin
    assert not (mask & ball_render.object_mask).any()
    assert mask.sum() < 1.25 * ball_render.ball_mask.sum()


def _perspective_ball(focal: float, centre: np.ndarray, lights: np.ndarray, size: int = 160, ss: int = 4):
    """Photos (K, size, size, 3) of a mirror ball of radius 1 at ``centre`` seen by a pinhole of ``focal`` px
    (principal point at the image centre): a Gaussian highlight (sigma 1.5 deg) about each light's mirror
    direction over a dim reflection, on a bright background; ``ss`` x ``ss`` samples per pixel."""
    off = (np.arange(ss) + 0.5) / ss - 0.5
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    u = np.broadcast_to(xx[..., None, None] + off[None, None, None, :], (size, size, ss, ss)).reshape(-1)
    v = np.broadcast_to(yy[..., None, None] + off[None, None, :, None], (size, size, ss, ss)).reshape(-1)
    c = (size - 1) / 2
    d = np.stack([(u - c) / focal, -(v - c) / focal, -np.ones_like(u)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = d @ centre
    disc = b * b - (centre @ centre - 1)
    hit = disc > 0
    t = b - np.sqrt(np.clip(disc, 0, None))
    n = d * t[:, None] - centre
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    refl = d - 2 * np.sum(d * n, axis=1, keepdims=True) * n
    photos = []
    sigma = math.radians(1.5)
    for light in lights:
        ang = np.arccos(np.clip(refl @ light, -1, 1))
        val = np.where(hit, 0.02 + 40 * np.exp(-0.5 * (ang / sigma) ** 2), 0.4)
        img = val.reshape(size, size, ss * ss).mean(axis=2)
        photos.append(np.repeat(img[..., None], 3, axis=2).astype(np.float32))
    return photos


@pytest.mark.parametrize("centre", [(0.9, -0.6, -7.0), (-1.2, -1.0, -6.5)])  # the second is cut by the border
@pytest.mark.parametrize("with_mask", [False, True])
def test_perspective_model(centre, with_mask):
    rng = np.random.default_rng(3)
    lights = rng.normal(size=(6, 3)) * [0.4, 0.4, 0.0] + [0, 0, 1]
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    focal = 250.0
    photos = _perspective_ball(focal, np.array(centre), lights)
    mask = photos[0].mean(axis=2) < 0.21 if with_mask else None  # ball 0.02, background 0.4: half-way
    cal = calibrate(photos, focal_px=focal, ball_mask=mask)
    assert cal.camera.startswith("perspective f=250")
    assert abs(math.degrees(cal.cone[1]) - math.degrees(math.asin(1 / np.linalg.norm(centre)))) < 0.03
    err = _angles(cal.directions, lights)
    assert err.max() < 0.3, err
    ortho = calibrate(photos, ball_mask=mask)  # the orthographic model on a perspective photo is off by degrees
    assert np.median(_angles(ortho.directions, lights)) > 3 * np.median(err) + 1
    # inverse mapping
    for k in range(3):
        x, y = direction_to_pixel(cal.directions[k], cal.circle, cal.size, focal, cal.cone)
        d, _ = reflect(np.array([x]), np.array([y]), cal.circle, cal.size, focal, cal.cone)
        assert _angles(d, cal.directions[k:k + 1])[0] < 1e-3


def test_cli_writes_rig_and_diagnostic(photo_folder, ball_render, tmp_path, capsys):
    from matcap.cli import main
    from matcap.imageio import read_image
    from matcap.refine.lightfile import read_lights

    out = tmp_path / "rig" / "rig.json"
    assert main(["calibrate", str(photo_folder), "--out", str(out)]) == 0
    doc = read_lights(out)
    raw = json.loads(out.read_text())
    assert raw["source"] == "ball" and raw["camera"] == "orthographic"
    assert raw["intensity_known"] is False  # the 16-bit highlights are clipped
    assert [e["file"] for e in doc["images"]] == [f"img_{k + 1:02d}.png" for k in range(12)]
    dirs = np.array([e["direction"] for e in doc["images"]])
    assert _angles(dirs, ball_render.directions).max() < 0.5
    assert all(e["intensity"] == [1.0, 1.0, 1.0] for e in doc["images"])
    # the diagnostic picture: the photos' max, enlarged, with the green circle and red highlight marks
    pic = read_image(out.parent / "calibration.png").pixels
    scale = pic.shape[0] // SIZE
    assert pic.shape == (SIZE * scale, SIZE * scale, 3) and scale >= 2
    green = (pic[..., 1] > 200) & (pic[..., 0] < 80) & (pic[..., 2] < 80)
    red = (pic[..., 0] > 200) & (pic[..., 1] < 120) & (pic[..., 2] < 120)
    cx, cy = ((v + 0.5) * scale - 0.5 for v in ball_render.circle[:2])  # pixel centres on the enlarged canvas
    r = ball_render.circle[2] * scale
    gy, gx = np.nonzero(green)
    assert green.sum() > 2 * r and np.abs(np.hypot(gx - cx, gy - cy) - r).max() < 2.5
    ry, rx = np.nonzero(red)
    assert red.sum() > 12 and (np.hypot(rx - cx, ry - cy) < r).all()
    # refused without --overwrite, accepted with it
    assert main(["calibrate", str(photo_folder), "--out", str(out)]) == 2
    capsys.readouterr()
    assert main(["calibrate", str(photo_folder), "--out", str(out), "--overwrite", "--quiet"]) == 0
    assert capsys.readouterr().out == ""


def _one_line_exit_2(capsys, argv, *words):
    from matcap.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("matcap calibrate: error:"), err
    for w in words:
        assert w in err, err
    return err


def test_bad_inputs(photo_folder, ball_render, tmp_path, capsys):
    import shutil

    from matcap.imageio import write_png

    out = str(tmp_path / "out" / "rig.json")
    # one photo
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(photo_folder / "img_01.png", one / "img_01.png")
    _one_line_exit_2(capsys, ["calibrate", str(one), "--out", out], "only one image")
    # an unreadable photo
    broken = tmp_path / "broken"
    shutil.copytree(photo_folder, broken)
    (broken / "img_03.png").write_bytes(b"not a png")
    _one_line_exit_2(capsys, ["calibrate", str(broken), "--out", out], "img_03.png")
    # no ball: smooth photos without any circle
    plain = tmp_path / "plain"
    plain.mkdir()
    yy, xx = np.mgrid[0:64, 0:64] / 64.0
    for k in range(3):
        write_png(plain / f"p{k}.png", np.repeat((0.2 + 0.3 * xx * (k + 1) / 3)[..., None], 3, axis=2), bits=16)
    _one_line_exit_2(capsys, ["calibrate", str(plain), "--out", out], "--ball-mask")
    # a ball mask of the wrong size
    small = tmp_path / "small_mask.png"
    write_png(small, np.ones((40, 50)), bits=8)
    _one_line_exit_2(capsys, ["calibrate", str(photo_folder), "--out", out, "--ball-mask", str(small)], "50x40")
    # a photo without a highlight (the ball's pixels replaced by the ball's median)
    nohl = tmp_path / "nohl"
    shutil.copytree(photo_folder, nohl)
    img = np.clip(ball_render.images[4] * 2.0, 0, 1)
    disc = ball_render.ball_mask
    img[disc] = np.median(img[disc], axis=0)
    write_png(nohl / "img_05.png", img, bits=16)
    _one_line_exit_2(capsys, ["calibrate", str(nohl), "--out", out], "img_05.png", "no highlight")
    # a photo over-exposed into a large clipped highlight
    blob = tmp_path / "blob"
    shutil.copytree(photo_folder, blob)
    write_png(blob / "img_07.png", np.clip(ball_render.images[6] * 3000.0, 0, 1), bits=16)
    _one_line_exit_2(capsys, ["calibrate", str(blob), "--out", out], "img_07.png", "clipped")
    # --out inside the photos folder, or not a .json
    _one_line_exit_2(capsys, ["calibrate", str(photo_folder), "--out", str(photo_folder / "rig.json")],
                     "photos folder")
    _one_line_exit_2(capsys, ["calibrate", str(photo_folder), "--out", str(tmp_path / "rig.txt")], ".json")
    assert not (tmp_path / "out").exists()


def test_library_errors(ball_render):
    imgs = list(ball_render.images)
    with pytest.raises(MatcapError, match="at least 2"):
        calibrate(imgs[:1])
    with pytest.raises(MatcapError, match="64x64"):
        calibrate(imgs, ball_mask=np.ones((64, 64), bool))
    with pytest.raises(MatcapError, match="not a disc"):
        square = np.zeros((SIZE, SIZE), bool)
        square[10:40, 10:100] = True
        calibrate(imgs, ball_mask=square)
    with pytest.raises(MatcapError, match="focal"):
        calibrate(imgs, focal_px=-3.0)
    assert isinstance(calibrate(imgs[:3], names=["a", "b", "c"]), Calibration)

"""Huge inputs: sizes come from the image headers, so a capture too large for the memory is refused in
one line before anything is decoded, and --max-side / --max-images keep a large capture within bounded memory.
Everything here uses small fakes: PNGs whose header claims 12,000 x 9,000 pixels, and a memory limit set through
MATCAP_MEMORY_GB."""
from __future__ import annotations

import json
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from conftest import sphere_photos
from matcap import imageio
from matcap.errors import MatcapError
from matcap.photos import check_memory, load_capture, memory_needed


def fake_big_png(path: Path, w: int, h: int) -> Path:
    """A tiny PNG whose IHDR claims w x h (the pixel data is that of a 4x4 image: decoding it fails)."""
    imageio.write_png(path, np.full((4, 4, 3), 0.5, np.float32), bits=8)
    data = bytearray(path.read_bytes())
    ihdr = data[12:29]  # b"IHDR" + 13 bytes
    ihdr[4:12] = struct.pack(">II", w, h)
    data[12:29] = ihdr
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(ihdr)) & 0xFFFFFFFF)
    path.write_bytes(bytes(data))
    return path


def test_image_size_reads_headers_like_read_image(tmp_path):
    import cv2
    from PIL import Image

    img = (np.random.default_rng(0).random((30, 50, 3)) * 255).astype(np.uint8)
    files = {}
    for suffix in (".png", ".tif", ".jpg"):
        files[suffix] = tmp_path / f"a{suffix}"
        cv2.imwrite(str(files[suffix]), img)
    files[".exr"] = tmp_path / "a.exr"
    imageio.write_exr(files[".exr"], img.astype(np.float32))
    files[".hdr"] = tmp_path / "a.hdr"
    cv2.imwrite(str(files[".hdr"]), img.astype(np.float32))
    rotated = tmp_path / "rot.jpg"  # EXIF orientation 6: the photo is shown (and read) turned by 90 degrees
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(img).save(rotated, exif=exif)
    files["rotated"] = rotated
    for key, path in files.items():
        assert imageio.image_size(path) == imageio.read_image(path).pixels.shape[:2], key
    assert imageio.image_size(rotated) == (50, 30)
    assert imageio.image_size(fake_big_png(tmp_path / "big.png", 12000, 9000)) == (9000, 12000)
    (tmp_path / "junk.png").write_bytes(b"not an image")
    assert imageio.image_size(tmp_path / "junk.png") is None


def test_memory_estimate_and_message(monkeypatch):
    monkeypatch.setenv("MATCAP_MEMORY_GB", "24")
    need = memory_needed(200, (9000, 12000))
    assert need > 1e12  # 200 x 108 Mpx: about 2.1 TB
    with pytest.raises(MatcapError) as err:
        check_memory(200, (9000, 12000))
    msg = str(err.value)
    assert "\n" not in msg and "200 photos of 12000x9000" in msg and "than the 22 GB that can be spared" in msg
    assert "use --max-side 1088" in msg
    check_memory(16, (1024, 1024))  # a normal capture passes
    side = int(msg.split("--max-side ")[1].split()[0])
    check_memory(200, (side * 3 // 4, side), (9000, 12000))  # the suggested --max-side fits


def test_200_huge_photos_are_refused_before_decoding(tmp_path, monkeypatch):
    folder = tmp_path / "photos"
    folder.mkdir()
    first = fake_big_png(folder / "p000.png", 12000, 9000)
    for i in range(1, 200):
        (folder / f"p{i:03d}.png").write_bytes(first.read_bytes())
    monkeypatch.setenv("MATCAP_MEMORY_GB", "24")

    def no_decoding(path):
        raise AssertionError(f"decoded {path}")

    monkeypatch.setattr(imageio, "read_image", no_decoding)
    with pytest.raises(MatcapError, match=r"200 photos of 12000x9000 would need about \d+ GB"):
        load_capture(folder)
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(folder), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=300, env={**__import__("os").environ,
                                                                           "MATCAP_MEMORY_GB": "24"})
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--max-side" in lines[0], r.stderr
    assert not (tmp_path / "o").exists()


def test_one_huge_photo_among_small_ones_is_named_before_decoding(tmp_path, monkeypatch):
    folder = sphere_photos(tmp_path / "photos", h=24, w=32, n=3, mask=False)
    fake_big_png(folder / "img_03.png", 12000, 9000)
    monkeypatch.setattr(imageio, "read_image", lambda p: (_ for _ in ()).throw(AssertionError(p)))
    with pytest.raises(MatcapError, match="img_03.png"):
        load_capture(folder)


def test_max_side_and_max_images_bound_memory_while_reading(tmp_path, monkeypatch, tiny_weights):
    """Photos too large for the (simulated) memory at full size fit with --max-side: each is shrunk as it is read,
    and --max-images photos that are not used are never decoded."""
    folder = sphere_photos(tmp_path / "photos", h=600, w=800, n=6)
    from matcap.photos import MEMORY_FRACTION

    limit_gb = str((memory_needed(6, (600, 800)) - 5e7) / MEMORY_FRACTION / 1e9)  # full size just does not fit
    monkeypatch.setenv("MATCAP_MEMORY_GB", limit_gb)
    with pytest.raises(MatcapError, match="--max-side"):
        load_capture(folder)
    decoded = []
    real = imageio.read_image
    monkeypatch.setattr(imageio, "read_image", lambda p: decoded.append(Path(p).name) or real(p))
    cap = load_capture(folder, max_side=80, max_images=3, seed=5)
    assert cap.images[0].shape == (60, 80, 3) and cap.mask.shape == (60, 80)
    assert cap.photo_size_wh == (800, 600) and len(cap.files) == 3
    assert sorted(n for n in decoded if n != "mask.png") == sorted(cap.files)
    # shrunk while reading == shrunk after reading (the previous behaviour)
    from matcap.photos import downscale_arrays

    monkeypatch.delenv("MATCAP_MEMORY_GB")
    full = load_capture(folder)
    ref, ref_mask = downscale_arrays([full.images[i] for i in cap.picked], full.mask, 80)
    np.testing.assert_array_equal(cap.images[1], ref[1])
    np.testing.assert_array_equal(cap.mask, ref_mask)
    # the whole command, within the simulated memory
    out = tmp_path / "result"
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(folder), "--out", str(out), "--weights",
                        str(tiny_weights), "--max-side", "80", "--max-images", "3", "--seed", "5", "--quiet"],
                       capture_output=True, text=True, timeout=600,
                       env={**__import__("os").environ, "MATCAP_MEMORY_GB": limit_gb})
    assert r.returncode == 0, r.stderr
    info = json.loads((out / "capture.json").read_text())
    assert info["photo_size_wh"] == [800, 600] and info["image_size_wh"] == [80, 60]
    assert info["inputs"] == cap.files and info["images_used"] == cap.picked


def test_8bit_decoding_by_table_equals_decoding_every_pixel():
    """8-bit photos are decoded through a 256-entry table (no float64 copies of a huge photo): same values."""
    from matcap.imageio import StoredImage, srgb_to_linear, to_linear_float

    a = np.random.default_rng(0).integers(0, 256, (50, 60, 3)).astype(np.uint8)
    got, how = to_linear_float(StoredImage(a, "x.png"))
    assert how == "srgb-decoded" and got.dtype == np.float32
    np.testing.assert_array_equal(got, srgb_to_linear(a.astype(np.float32) / 255.0))
    np.testing.assert_array_equal(to_linear_float(StoredImage(a, "x.png"), False)[0], a.astype(np.float32) / 255.0)
    b = np.random.default_rng(1).integers(0, 65536, (5, 6, 3)).astype(np.uint16)
    np.testing.assert_array_equal(to_linear_float(StoredImage(b, "y.png"))[0], b.astype(np.float32) / 65535.0)


@pytest.mark.parametrize("command", ["relight", "gallery"])
def test_a_huge_render_size_is_refused_before_rendering(tmp_path, sphere_maps, capsys, command):
    from matcap.cli import main
    from matcap.results import write_result

    write_result(sphere_maps(16), tmp_path / "result")
    extra = ["--out", str(tmp_path / "g")] if command == "gallery" else []
    assert main([command, str(tmp_path / "result"), "--size", "100000", "--quiet", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "100000x100000 render is 10000 megapixels" in err[0] and "--size" in err[0]
    assert not (tmp_path / "g").exists() and not list((tmp_path / "result").glob("relight_*"))

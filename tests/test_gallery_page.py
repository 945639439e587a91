"""`matcap gallery`: files, animation, contact sheets, and index.html loaded in headless Chromium."""
from __future__ import annotations

import json
import re
import shutil
import subprocess

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from matcap.cli import main  # noqa: E402

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run"]


@pytest.fixture(scope="module")
def built(tmp_path_factory, sphere_maps):
    import cv2

    from matcap import gallery

    root = tmp_path_factory.mktemp("gallery")
    envdir = root / "envs"
    envdir.mkdir()
    sky = np.zeros((8, 16, 3), np.float32)
    sky[:4] = (0.4, 0.6, 1.0)
    sky[4:] = (0.3, 0.25, 0.2)
    cv2.imwrite(str(envdir / "sky.hdr"), sky[..., ::-1].copy())
    from matcap.relight import default_envmap_path

    shutil.copy(default_envmap_path(), envdir / "studio.exr")
    out = root / "g"
    info = gallery(sphere_maps(40, varied=True), envs=envdir, orbit=6, out=out, size=32, spp=2, orbit_spp=1, progress=False)
    return out, info


def test_gallery_files(built):
    from PIL import Image

    out, info = built
    for name in ("index.html", "envs.png", "orbit.gif", "orbit_sheet.png", "gallery.json",
                 "maps/normal.png", "maps/basecolor.png", "maps/roughness.png", "maps/metallic.png",
                 "renders/sky.png", "renders/sky.exr", "renders/studio.png", "renders/studio.exr"):
        assert (out / name).is_file(), name
    assert (out / "orbit.mp4").is_file() or (out / "orbit.webp").is_file()
    gif = Image.open(out / "orbit.gif")
    assert gif.n_frames == 6 and gif.size == (32, 32)
    frames = []
    for i in range(gif.n_frames):
        gif.seek(i)
        frames.append(np.asarray(gif.convert("RGB"), np.float32))
    # the light moves: frames differ, and the lit side follows it (frame 0: light from the right)
    assert np.abs(frames[0] - frames[3]).mean() > 5
    assert frames[0][:, 20:28].mean() > frames[0][:, 4:12].mean()
    sheet = np.asarray(Image.open(out / "envs.png"))
    assert sheet.shape[1] > 2 * 32  # two labelled tiles side by side
    assert json.loads((out / "gallery.json").read_text())["orbit"]["frames"] == 6
    assert [r["name"] for r in info["renders"]] == ["sky", "studio"]


def test_gallery_refuses_existing_folder(built, capsys):
    out, _ = built
    assert main(["gallery", str(out), "--out", str(out), "--quiet"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_gallery_cli_texture_set(tmp_path):
    from matcap.imageio import write_png

    tex = tmp_path / "tex"
    write_png(tex / "basecolor.png", np.full((16, 16, 3), 0.5, np.float32), bits=8)
    code = main(["gallery", str(tex), "--orbit", "2", "--size", "16", "--spp", "1", "--orbit-spp", "1",
                 "--out", str(tmp_path / "g"), "--quiet"])
    assert code == 0 and (tmp_path / "g" / "index.html").is_file()


CHECK = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); })
                .map(function (i) { return i.getAttribute('src'); });
  var r = document.createElement('pre');
  r.id = 'matcap-check';
  r.textContent = 'IMAGES ' + imgs.length + ' BROKEN ' + JSON.stringify(bad);
  document.body.appendChild(r);
});
</script>"""


def test_index_html_loads_every_image_in_headless_chromium(built, tmp_path):
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("chromium is not installed (apt-get install -y chromium); cannot load index.html headless")
    out, _ = built
    page = (out / "index.html").read_text(encoding="utf-8")
    n_img = len(re.findall(r"<img\b", page))
    assert n_img >= 4 + 2 + 1 + 2  # maps, renders, env sheet, gif + orbit sheet
    assert "http://" not in page and "https://" not in page  # static files only
    probe = out / "_check.html"  # same folder, so the relative paths resolve exactly as for index.html
    probe.write_text(page.replace("</body>", CHECK + "</body>"), encoding="utf-8")
    try:
        proc = subprocess.run(
            [exe, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=10000",
             "--dump-dom", probe.as_uri()],
            capture_output=True, text=True, timeout=120,
        )
    finally:
        probe.unlink()
    m = re.search(r"IMAGES (\d+) BROKEN (\[.*?\])", proc.stdout)
    assert m, f"no result from chromium (rc {proc.returncode}): {proc.stderr[-800:]}"
    assert int(m.group(1)) == n_img
    assert json.loads(m.group(2)) == [], f"images that did not load: {m.group(2)}"

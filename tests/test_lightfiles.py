"""Light files (`matcap.lightfiles`): every format, matching rows to photos, and every malformed case."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from matcap.errors import MatcapError
from matcap.lightfiles import read_light_file
from matcap.refine.lightfile import write_lights
from conftest import sphere_photos

PHOTOS = [f"img{i}.png" for i in (1, 2, 10, 3)]  # the capture's order; natural order is 1, 2, 3, 10
DIRS = np.array([[0.3, 0.2, 1.0], [-0.4, 0.1, 0.9], [0.0, -0.5, 0.8], [0.2, 0.6, 0.7]])
UNIT = DIRS / np.linalg.norm(DIRS, axis=1, keepdims=True)
NATURAL = [0, 1, 3, 2]  # row n of an order-matched file belongs to the n-th photo in natural order


def _table(rows, count=False, extra=None) -> str:
    lines = ([str(len(rows))] if count else []) + [" ".join(f"{v:.6f}" for v in r) for r in rows]
    return "\n".join(lines + (extra or [])) + "\n"


def test_plain_table_in_natural_order(tmp_path):
    """Without a names list the rows follow the photos' natural file-name order (2 before 10)."""
    f = tmp_path / "lights.txt"
    f.write_text(_table(DIRS * 3.0))  # not unit: normalised on reading
    known = read_light_file(f, PHOTOS)
    expect = np.empty_like(UNIT)
    expect[NATURAL] = UNIT  # photo NATURAL[n] takes row n
    np.testing.assert_allclose(known.directions, expect, atol=1e-6)
    assert known.intensities is None and known.matched == "order" and known.source == "file"


def test_count_line_and_intensities(tmp_path):
    f = tmp_path / "lights.txt"
    rows = np.concatenate([DIRS, np.array([[1, 1, 1], [2, 2, 2], [1, 0.5, 0.25], [3, 3, 3]])], axis=1)
    f.write_text(_table(rows, count=True))
    known = read_light_file(f, sorted(PHOTOS, key=lambda n: int(n[3:-4])))
    np.testing.assert_allclose(known.directions, UNIT, atol=1e-6)
    np.testing.assert_allclose(known.intensities[2], [1, 0.5, 0.25])


def test_names_list_beside_the_table(tmp_path):
    """A names.txt beside the file gives each row's photo (the UW convention)."""
    names = ["img10.png", "img1.png", "img3.png", "img2.png"]
    (tmp_path / "names.txt").write_text("\n".join(names) + "\n")
    f = tmp_path / "lights.txt"
    f.write_text(_table(DIRS, count=True))
    known = read_light_file(f, PHOTOS)
    for i, photo in enumerate(PHOTOS):
        np.testing.assert_allclose(known.directions[i], UNIT[names.index(photo)], atol=1e-6)
    assert known.matched == "names.txt"


def test_diligent_two_files(tmp_path):
    """light_directions.txt picks up light_intensities.txt and filenames.txt beside it."""
    names = ["img1.png", "img2.png", "img3.png", "img10.png"]
    (tmp_path / "filenames.txt").write_text("\n".join(names) + "\n")
    (tmp_path / "light_directions.txt").write_text(_table(DIRS))
    ints = np.array([[1.0, 0.9, 0.8], [0.5, 0.5, 0.5], [2.0, 2.1, 2.2], [1.0, 1.0, 1.0]])
    (tmp_path / "light_intensities.txt").write_text(_table(ints))
    known = read_light_file(tmp_path / "light_directions.txt", PHOTOS)
    assert known.matched == "filenames.txt"
    for i, photo in enumerate(PHOTOS):
        np.testing.assert_allclose(known.intensities[i], ints[names.index(photo)])


def test_lp_file_by_name(tmp_path):
    """An RTI .lp file: a count line, then 'filename x y z', matched by name (paths and case ignored, and the
    extension where the photos were converted)."""
    lp = tmp_path / "rig.lp"
    order = [3, 0, 2, 1]
    lines = [str(len(order))] + [f"C:\\rti\\{PHOTOS[i].replace('.png', '.JPG')} " + " ".join(map(str, DIRS[i]))
                                 for i in order]
    lp.write_text("\n".join(lines) + "\n")
    known = read_light_file(lp, PHOTOS)
    np.testing.assert_allclose(known.directions, UNIT, atol=1e-6)
    assert known.matched == "name"


def test_lights_json_round_trip_and_order_fallback(tmp_path):
    """Our lights.json matches by its file names; a calibration's (other names) by order."""
    entries = [{"index": i, "file": PHOTOS[i], "kind": "directional", "direction": list(DIRS[i]),
                "intensity": [1.0 + i, 1.0, 1.0], "sh": [[0.0, 0.0, 0.0]] * 9} for i in range(4)]
    write_lights(tmp_path / "lights.json", entries[::-1], source="ball")
    known = read_light_file(tmp_path / "lights.json", PHOTOS)
    np.testing.assert_allclose(known.directions, UNIT, atol=1e-6)
    np.testing.assert_allclose(known.intensities[:, 0], [1, 2, 3, 4])
    assert known.source == "ball" and known.matched == "name"
    assert known.ambient.shape == (4, 9, 3) and not known.ambient.any()  # the file's ambient: none
    assert known.subset([1]).ambient.shape == (1, 9, 3)
    other = [f"chrome.{i}.png" for i in range(4)]
    cal = [dict(e, file=other[i]) for i, e in enumerate(entries)]
    write_lights(tmp_path / "rig.json", cal)
    known = read_light_file(tmp_path / "rig.json", ["owl.0.png", "owl.1.png", "owl.2.png", "owl.3.png"])
    np.testing.assert_allclose(known.directions, UNIT, atol=1e-6)
    assert known.matched == "order" and known.source == "file"


def test_lights_json_ambient_only_beside_intensities(tmp_path):
    """A lights.json's SH ambient is read, by photo, where the file gives intensities; a calibration that could
    not tell the intensities (``intensity_known`` false) gives no ambient either."""
    entries = [{"index": i, "file": PHOTOS[i], "kind": "directional", "direction": list(DIRS[i]),
                "intensity": [2.0, 2.0, 2.0], "sh": [[0.1 * (i + 1)] * 3] + [[0.0] * 3] * 8} for i in range(4)]
    write_lights(tmp_path / "lights.json", entries)
    known = read_light_file(tmp_path / "lights.json", PHOTOS)
    np.testing.assert_allclose(known.ambient[:, 0, 0], [0.1, 0.2, 0.3, 0.4])
    assert known.record()["ambient"] == "given"
    write_lights(tmp_path / "rig.json", entries, intensity_known=False)
    rig = read_light_file(tmp_path / "rig.json", PHOTOS)
    assert rig.intensities is None and rig.ambient is None and rig.record()["ambient"] == "fitted"


def test_lights_json_says_what_its_intensities_are(tmp_path):
    """``intensity_units``: "photos" (the photos' own units, power included) is read and kept through a pick of the
    photos; a file without the key is relative; any other value is one line naming it."""
    entries = [{"index": i, "file": PHOTOS[i], "kind": "directional", "direction": list(DIRS[i]),
                "intensity": [2.0, 2.0, 2.0], "sh": [[0.0] * 3] * 9} for i in range(4)]
    write_lights(tmp_path / "abs.json", entries, intensity_units="photos")
    known = read_light_file(tmp_path / "abs.json", PHOTOS)
    assert known.intensity_units == "photos" and known.subset([1, 0]).intensity_units == "photos"
    assert known.record()["intensity_units"] == "photos"
    write_lights(tmp_path / "rel.json", entries)
    assert read_light_file(tmp_path / "rel.json", PHOTOS).intensity_units == "relative"
    doc = json.loads((tmp_path / "abs.json").read_text())
    doc["intensity_units"] = "watts"
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(MatcapError, match="'intensity_units' must be one of relative, photos, got \"watts\""):
        read_light_file(tmp_path / "bad.json", PHOTOS)


def test_subset_follows_the_pick(tmp_path):
    f = tmp_path / "lights.txt"
    f.write_text(_table(DIRS))
    photos = sorted(PHOTOS, key=lambda n: int(n[3:-4]))
    known = read_light_file(f, photos).subset([2, 0])
    np.testing.assert_allclose(known.directions, UNIT[[2, 0]], atol=1e-6)


@pytest.mark.parametrize("text, needle", [
    ("0.1 0.2 0.9\n0 0 1\n0.3 0.1 0.9\n", "3 lights but the capture has 4 photos"),
    ("5\n" + "0 0 1\n" * 4, "says 5 lights but 4 rows follow"),
    ("0 0 1\n0 0 0\n0 0 1\n0 0 1\n", "line 2: light direction is zero"),
    ("0 0 1\n0 0 1\nnan 0 1\n0 0 1\n", "line 3: light [nan, 0.0, 1.0] is not finite"),
    ("0 0 1\n0 0 1\n0 0 1\n0.5 0 -0.2\n", "line 4: light [0.5, 0.0, -0.2] is behind the object's plane"),
    ("0 0 1\n0 0 1 1 1 1\n0 0 1\n0 0 1\n", "some rows give intensities"),
    ("0 0 1\n0 0 1\n0 0 1 1 -1 1\n0 0 1 1 1 1\n", "some rows give intensities"),
    ("0 0 1 1 1 1\n0 0 1 1 1 1\n0 0 1 1 -1 1\n0 0 1 1 1 1\n", "line 3: intensity"),
    ("0 0\n0 0 1\n0 0 1\n0 0 1\n", "line 1: expected 'x y z' or 'x y z r g b', got 2 values"),
    ("0 0 1\nx 0 1\n0 0 1\n0 0 1\n", "line 2: expected numbers"),
])
def test_malformed_tables(tmp_path, text, needle):
    f = tmp_path / "lights.txt"
    f.write_text(text)
    with pytest.raises(MatcapError) as e:
        read_light_file(f, PHOTOS)
    msg = str(e.value)
    assert needle in msg and "lights.txt" in msg and "\n" not in msg, msg


def test_name_mismatches(tmp_path):
    (tmp_path / "names.txt").write_text("a.png\nb.png\nc.png\nd.png\n")
    f = tmp_path / "lights.txt"
    f.write_text(_table(DIRS))
    with pytest.raises(MatcapError, match=r"lights.txt names no light for photo img1.png \(and 3 more\); its rows "
                                          r"follow names.txt"):
        read_light_file(f, PHOTOS)
    (tmp_path / "names.txt").write_text("a.png\nb.png\n")
    with pytest.raises(MatcapError, match="names.txt lists 2 photos but lights.txt has 4 lights"):
        read_light_file(f, PHOTOS)
    lp = tmp_path / "x.lp"
    lp.write_text("2\nimg1.png 0 0 1\nimg2.png 0 0.1 1\n")
    with pytest.raises(MatcapError, match="x.lp names no light for photo img10.png"):
        read_light_file(lp, PHOTOS)
    with pytest.raises(MatcapError, match="does not exist"):
        read_light_file(tmp_path / "missing.txt", PHOTOS)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(MatcapError, match="not valid JSON"):
        read_light_file(bad, PHOTOS)


def test_capture_refuses_a_bad_light_file_before_the_networks(tmp_path, tiny_weights):
    """One line, exit 2, nothing written; --lights with --no-refine is refused too."""
    photos = sphere_photos(tmp_path / "photos", n=4)
    n = len([p for p in photos.iterdir() if p.name.startswith("img")])
    bad = tmp_path / "lights.txt"
    bad.write_text("0 0 1\n" * (n + 1))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "matcap", "capture", str(photos), "--out", str(out), "--weights",
           str(tiny_weights), "--quiet", "--linear"]
    r = subprocess.run(cmd + ["--lights", str(bad)], capture_output=True, text=True)
    assert r.returncode == 2 and not out.exists(), r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{n + 1} lights but the capture has {n} photos" in lines[0], r.stderr
    good = tmp_path / "good.txt"
    good.write_text("0 0 1\n" * n)
    r = subprocess.run(cmd + ["--lights", str(good), "--no-refine"], capture_output=True, text=True)
    assert r.returncode == 2 and "no use with --no-refine" in r.stderr and not out.exists(), r.stderr

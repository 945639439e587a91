"""examples/readme_figure.py writes into the current folder by default and never replaces a file unasked."""
from __future__ import annotations

import importlib.util

import numpy as np

from conftest import REPO, sphere_photos


def _load():
    spec = importlib.util.spec_from_file_location("readme_figure", REPO / "examples" / "readme_figure.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_default_output_is_in_the_current_folder_and_never_overwritten(tmp_path, monkeypatch, sphere_maps, capsys):
    from matcap.imageio import read_image
    from matcap.results import write_result

    photos = sphere_photos(tmp_path / "photos", h=24, w=24)
    maps = sphere_maps(24, varied=True)
    maps.meta["input_folder"] = str(photos)
    write_result(maps, tmp_path / "bunny-maps")
    monkeypatch.chdir(tmp_path)
    fig = _load()
    assert fig.cli([]) == 0
    out = tmp_path / "bunny_capture.png"
    img = read_image(out).pixels
    assert img.shape[0] == 24 and img.shape[1] == 24 * 8 + 4 * 7  # 4 photos, normal, base, rough, metal
    before = out.read_bytes()
    assert fig.cli([]) == 2 and "--overwrite" in capsys.readouterr().err
    assert out.read_bytes() == before
    assert fig.cli(["bunny-maps", "bunny_capture.png", "--overwrite"]) == 0
    assert fig.cli(["missing", "x.png"]) == 2 and not (tmp_path / "x.png").exists()
    assert np.array_equal(read_image(out).pixels, img)

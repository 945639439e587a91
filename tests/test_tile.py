"""matcap tile: periodic output for every map, one cut shared by all maps, a periodic height consistent with the
normals, the 3 x 3 preview, export --tileable (glb with REPEAT samplers), bad input as one line and exit 2."""
from __future__ import annotations

import json
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from matcap import MaterialMaps
from matcap.errors import MatcapError
from matcap.results import read_result, write_result
from matcap.tile import cut_energy, largest_square, seam_energy, tile, tile_maps

ROOT = Path(__file__).resolve().parents[1]
N = 96  # input side: the default tile is 64 (+ 8 texels of overlap)


def _field(rng, n: int, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    f = gaussian_filter(rng.standard_normal((n, n)), sigma)
    return (f - f.mean()) / f.std()


def swatch(n: int = N, seed: int = 0) -> MaterialMaps:
    """A non-periodic bumpy swatch: smooth noise plus ramps, so every map jumps at its wrapped borders."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:n, 0:n] / n
    h = 2.0 * _field(rng, n, 3.0) + 6.0 * c  # height with a slope: the normals jump where the tile wraps
    gy, gx = np.gradient(h)
    nrm = np.stack([-gx, gy, np.ones_like(h)], axis=2)
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    base = np.clip(np.stack([0.4 + 0.1 * _field(rng, n, 2.0) + 0.3 * r, 0.3 + 0.1 * _field(rng, n, 2.0),
                             0.2 + 0.3 * c], axis=2), 0, 1)
    rough = np.clip(0.5 + 0.1 * _field(rng, n, 2.5) + 0.3 * (r - 0.5), 0, 1)
    metal = np.clip(0.3 + 0.1 * _field(rng, n, 4.0) + 0.4 * c, 0, 1)
    return MaterialMaps(normal=nrm, mask=np.ones((n, n), bool), base_color=base, roughness=rough, metallic=metal,
                        meta={"kind": "test swatch"})


@pytest.fixture(scope="module")
def tiled():
    maps = swatch()
    out, info = tile_maps(maps)
    return maps, out, info


def test_largest_square_is_exact_and_central():
    mask = np.zeros((40, 60), bool)
    mask[5:30, 10:50] = True  # 25 x 40: the largest square is 25
    mask[12, 30] = False  # a hole splits it: the squares of side 25 must avoid column 30 at row 12
    row, col, side = largest_square(mask)
    # brute force
    best = max(k for k in range(1, 26) if any(mask[r:r + k, c:c + k].all() for r in range(41 - k)
                                              for c in range(61 - k)))
    assert side == best == 20  # right of the hole: columns 31 .. 50
    assert mask[row:row + side, col:col + side].all()


def test_every_map_is_periodic(tiled):
    maps, out, info = tiled
    assert out.shape == (64, 64) and info["size"] == 64 and out.mask.all()
    for name in ("normal", "base_color", "roughness", "metallic", "height"):
        after = seam_energy(getattr(out, name))
        # the input wrapped by half its size has a jump far above its interior's; the tile has none
        if name != "height":
            before = seam_energy(getattr(maps, name)[:64, :64])
            assert before["ratio"] > 15.0, (name, before)  # measured 20 .. 290
        # one line of this noise varies by itself by about +-20 %: measured 0.28 .. 1.17
        assert after["ratio"] < 1.3, (name, after)
        # the cut inside the tile: no jump either (the Poisson blend removes the step); measured 0.70 .. 1.01
        assert info["cut_energy"][name]["ratio"] < 1.2, (name, info["cut_energy"][name])
    # the recorded numbers are these
    assert info["seam_energy"]["normal"]["ratio"] == pytest.approx(seam_energy(out.normal)["ratio"], rel=1e-5)


def test_all_maps_share_one_cut():
    """Maps that are equal before tiling stay equal: one arrangement and one (linear) blend for every map."""
    maps = swatch(seed=3)
    same = MaterialMaps(normal=maps.normal, mask=maps.mask, base_color=np.repeat(maps.roughness[..., None], 3, 2),
                        roughness=maps.roughness, metallic=maps.roughness)
    out, info = tile_maps(same)
    assert np.abs(out.roughness - out.metallic).max() < 1e-6
    assert np.abs(out.roughness - out.base_color[..., 0]).max() < 1e-6
    # and the tile is a re-arrangement: every texel away from the cut is a texel of the input (shifted by 0 or P)
    assert sum(info["cut"]["texels_per_shift"].values()) == 64 * 64
    assert set(info["cut"]["texels_per_shift"]) <= {"0,0", "0,64", "64,0", "64,64"}


def test_height_is_periodic_and_matches_the_normals(tiled):
    _, out, _ = tiled
    h = out.height.astype(np.float64)
    assert abs(h.mean()) < 1e-4
    # forward differences on the torus against the normals' slopes (trapezoid: mean of the two texels)
    n = out.normal.astype(np.float64)
    gx, gr = -n[..., 0] / n[..., 2], n[..., 1] / n[..., 2]
    dx = np.roll(h, -1, axis=1) - h
    dr = np.roll(h, -1, axis=0) - h
    tx = 0.5 * (gx + np.roll(gx, -1, axis=1))
    tr = 0.5 * (gr + np.roll(gr, -1, axis=0))
    scale = np.sqrt(np.mean(tx ** 2 + tr ** 2))
    rms = np.sqrt(np.mean((dx - tx) ** 2 + (dr - tr) ** 2))
    assert rms < 0.25 * scale, (rms, scale)
    # the wrapped pairs fit as well as the others
    wrap = np.sqrt(np.mean((dx[:, -1] - tx[:, -1]) ** 2 + (dr[-1] - tr[-1]) ** 2))
    assert wrap < 2.0 * rms + 1e-3
    assert np.abs(np.linalg.norm(n, axis=2) - 1).max() < 1e-5  # renormalised after the blend


def test_tile_folder_preview_and_json(tmp_path, tiled):
    maps, _, _ = tiled
    src = write_result(maps, tmp_path / "res")
    info = tile(src, tmp_path / "tiled", spp=4)
    back = read_result(tmp_path / "tiled")
    assert back.shape == (64, 64) and back.mask.all() and back.height is not None
    assert seam_energy(back.base_color)["ratio"] < 1.6  # survives 16-bit sRGB storage
    meta = json.loads((tmp_path / "tiled" / "capture.json").read_text())
    assert meta["tiling"]["size"] == 64 and meta["tiling"]["crop"]["side"] == 72
    assert "preview_3x3.png" in meta["files"] and meta["kind"] == "test swatch"
    from matcap.imageio import read_image

    pic = read_image(tmp_path / "tiled" / "preview_3x3.png").pixels
    assert pic.shape == (192, 192, 3) and info["preview"]["size"] == 192
    # the preview repeats: the middle copy matches its right and lower neighbours (up to render noise) far better
    # than the same texture a few texels off
    g = pic.astype(np.float64).mean(axis=2)
    mid = g[64:128, 64:128].ravel()

    def corr(other):
        return np.corrcoef(mid, other.ravel())[0, 1]

    assert corr(g[64:128, 128:192]) > 0.8 and corr(g[128:192, 64:128]) > 0.8
    assert corr(g[64:128, 128:192]) > corr(g[64:128, 77:141]) + 0.3


def glb_json(path: Path) -> dict:
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])


def test_export_tileable_writes_a_repeating_glb(tmp_path, tiled):
    from matcap.export import export

    maps, _, _ = tiled
    paths = export(maps, tmp_path / "tex", name="sw", tileable=True)
    tree = glb_json(Path(paths["glb"]))
    assert tree["samplers"] == [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}]
    assert all(t["sampler"] == 0 for t in tree["textures"])
    uv_acc = tree["accessors"][tree["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]]
    assert uv_acc["max"] == [3.0, 3.0] and uv_acc["min"] == [0.0, 0.0]
    info = json.loads(Path(paths["json"]).read_text())
    assert info["resolution"] == {"width": 64, "height": 64} and info["tiling"]["size"] == 64
    from matcap.imageio import read_exr, read_image

    height = read_exr(paths["height"])
    assert seam_energy(height[..., 0] if height.ndim == 3 else height)["ratio"] < 1.6
    occ = read_image(paths["occlusion"]).pixels.astype(np.float64)
    assert seam_energy(occ)["ratio"] < 2.0  # occlusion baked with the height wrapped around
    node = shutil.which("node")
    if node and (ROOT / "tools" / "node" / "node_modules" / "gltf-validator").is_dir():
        proc = subprocess.run([node, str(ROOT / "tools" / "node" / "validate.mjs"), paths["glb"]],
                              capture_output=True, text=True, timeout=120)
        report = json.loads(proc.stdout.splitlines()[0])
        assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "MATCAP_PROGRESS": "off"}
    return subprocess.run([sys.executable, "-m", "matcap", *args], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=120)


def test_bad_input_is_one_line_exit_2(tmp_path, tiled):
    maps, _, _ = tiled
    src = write_result(maps, tmp_path / "res")
    thin = maps.mask.copy()
    thin[:, :] = False
    thin[10:20, :] = True  # a strip 10 texels high: no 16 x 16 square
    strip = write_result(MaterialMaps(normal=np.where(thin[..., None], maps.normal, 0), mask=thin),
                         tmp_path / "strip")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x.txt").write_text("x")
    cases = [
        (("tile", str(tmp_path / "missing"), "--out", str(tmp_path / "o1")), "no such result folder"),
        (("tile", str(strip), "--out", str(tmp_path / "o2")), "no square"),
        (("tile", str(src), "--out", str(tmp_path / "o3"), "--size", "48"), "power of two"),
        (("tile", str(src), "--out", str(tmp_path / "o4"), "--size", "128"), "larger than the largest square"),
        (("tile", str(src), "--out", str(tmp_path / "busy")), "--overwrite"),
        (("export", str(src), "--out", str(tmp_path / "o5"), "--tile-size", "64"), "--tileable"),
    ]
    for args, words in cases:
        proc = _cli(*args, cwd=tmp_path)
        assert proc.returncode == 2, (args, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0], (args, proc.stderr)
    assert not (tmp_path / "o4").exists()
    with pytest.raises(MatcapError, match="power of two"):
        tile_maps(maps, size=100)


def test_a_given_size_keeps_the_whole_square():
    """--size N: all of the sample, resampled to N (+ the overlap); the default crops at the maps' resolution."""
    maps = swatch()
    out, info = tile_maps(maps, size=32)
    assert out.shape == (32, 32)
    assert info["crop"]["side"] == N and info["crop"]["resampled_to"] == 40
    assert seam_energy(out.base_color)["ratio"] < 1.6 and seam_energy(out.normal)["ratio"] < 1.6


def test_cut_energy_sees_a_hard_cut():
    """The cut measure flags a step: two halves of different constant level give a ratio far above 1."""
    rng = np.random.default_rng(1)
    x = _field(rng, 64, 2.0) * 0.05
    ids = np.zeros((64, 64), int)
    ids[:, 20:40] = 1
    stepped = x + 0.5 * ids
    assert cut_energy(stepped, ids)["ratio"] > 10
    assert cut_energy(x, ids)["ratio"] < 1.6


def test_the_blend_removes_the_step_of_the_hard_cut():
    """The same cut without the gradient-domain blend (the source texels as they are) jumps across the cut; the
    blend brings every map back to its neighbours' level."""
    from matcap.tile import _stack, blend, cut_shifts, overlap

    maps = swatch()
    p, k = 64, overlap(64)
    sq = MaterialMaps(**{name: getattr(maps, name)[:p + k, :p + k]
                         for name in ("normal", "mask", "base_color", "roughness", "metallic")})
    stack, groups = _stack(sq)
    scale = {name: float(np.var(stack[..., sl])) for name, sl in groups.items()}
    src_r, src_c, _ = cut_shifts(stack, p, groups, scale)
    shift_id = (src_r - np.arange(p)[:, None]) * 2 + (src_c - np.arange(p)[None, :])
    hard, soft = stack[src_r, src_c], blend(stack, src_r, src_c)
    for name, sl in groups.items():
        assert cut_energy(hard[..., sl], shift_id)["ratio"] > 5.0, name  # measured 8.7 .. 87
        assert cut_energy(soft[..., sl], shift_id)["ratio"] < 1.2, name  # measured 0.58 .. 1.07


def test_cli_tile_then_export_tileable(tmp_path, tiled):
    maps, _, _ = tiled
    src = write_result(maps, tmp_path / "res")
    proc = _cli("tile", str(src), "--out", str(tmp_path / "t"), "--no-preview", "--quiet", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "tiled 64 x 64" in proc.stdout and proc.stderr.strip() == ""
    proc = _cli("export", str(tmp_path / "t"), "--out", str(tmp_path / "tex"), "--tileable", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    info = json.loads((tmp_path / "tex" / "t.json").read_text())
    assert info["tiling"]["done"].startswith("before the export")  # the tiled input is used as it is
    assert not (tmp_path / "t" / "preview_3x3.png").exists()

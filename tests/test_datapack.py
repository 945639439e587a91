"""networks.datapack: pack / unpack round trip within the 8-bit quantisation, clear errors."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from conftest import lambertian_scene

from networks.datapack import pack, unpack


def _synth_like_dataset(root, scenes=3, size=32):
    rng = np.random.default_rng(0)
    for i in range(scenes):
        s = lambertian_scene(rng, size)
        basis = s["basis"].astype(np.float32)
        weights = rng.uniform(0, 1, (10, len(basis))).astype(np.float32)
        exposure = rng.uniform(0.5, 2.0, 10).astype(np.float32)
        s["images"] = np.clip(np.tensordot(weights, basis, axes=1) * exposure[:, None, None, None], 0, 1)
        s.update(weights=weights, exposure=exposure, object_mask=s["mask"].copy())
        d = root / f"scene_{i:06d}"
        d.mkdir(parents=True)
        np.savez(d / "data.npz", **s)
        (d / "spec.json").write_text(json.dumps({"lighting_group": "directional"}))
    return root


def test_round_trip_is_within_quantisation(tmp_path):
    data = _synth_like_dataset(tmp_path / "data")
    packs = pack(data, tmp_path / "packs", max_mb=0.01)  # a limit below two scenes: the packs split
    assert len(packs) > 1
    assert unpack(packs, tmp_path / "out") == 3
    for i in range(3):
        a = np.load(data / f"scene_{i:06d}" / "data.npz")
        b = np.load(tmp_path / "out" / f"scene_{i:06d}" / "data.npz")
        assert json.loads((tmp_path / "out" / f"scene_{i:06d}" / "spec.json").read_text())["lighting_group"] == "directional"
        assert np.array_equal(a["mask"], b["mask"]) and np.array_equal(a["basis_kind"], b["basis_kind"])
        m = a["mask"] & (np.linalg.norm(a["normal"].astype(np.float32), axis=2) > 0.5)
        na, nb = a["normal"].astype(np.float32)[m], b["normal"].astype(np.float32)[m]
        cos = (na * nb).sum(1) / np.linalg.norm(na, axis=1) / np.linalg.norm(nb, axis=1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.5
        for key in ("base_color", "roughness", "metallic"):
            truth = np.clip(a[key].astype(np.float32), 0, 1)  # maps are [0, 1] (this toy albedo can exceed 1)
            assert np.abs(truth - b[key].astype(np.float32)).max() <= 0.5 / 255 + 1e-3, key
        scale = np.percentile(a["basis"].astype(np.float32).reshape(len(a["basis"]), -1), 99.9, axis=1)
        err = np.abs(a["basis"].astype(np.float32) - b["basis"].astype(np.float32)) / scale[:, None, None, None]
        assert np.median(err) < 0.01
        assert np.abs(a["images"].astype(np.float32) - b["images"].astype(np.float32)).mean() < 0.01


def test_a_scene_without_synth_fields_is_a_clear_error(tmp_path):
    d = tmp_path / "data" / "scene_000000"
    d.mkdir(parents=True)
    np.savez(d / "data.npz", **lambertian_scene(np.random.default_rng(0), 16))
    r = subprocess.run([sys.executable, "-m", "networks.datapack", "pack", str(tmp_path / "data"), str(tmp_path / "p")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "not a `matcap synth` scene" in r.stderr and "Traceback" not in r.stderr


def test_lossy_webp_basis_is_smaller_and_close(tmp_path):
    data = _synth_like_dataset(tmp_path / "data", scenes=2, size=64)
    lossless = pack(data, tmp_path / "p0")
    lossy = pack(data, tmp_path / "p95", quality=95)
    assert sum(p.stat().st_size for p in lossy) < 0.8 * sum(p.stat().st_size for p in lossless)
    assert unpack(lossy, tmp_path / "out") == 2
    for i in range(2):
        a = np.load(data / f"scene_{i:06d}" / "data.npz")
        b = np.load(tmp_path / "out" / f"scene_{i:06d}" / "data.npz")
        assert b["basis"].shape == a["basis"].shape and np.array_equal(a["mask"], b["mask"])
        scale = np.percentile(a["basis"].astype(np.float32).reshape(len(a["basis"]), -1), 99.9, axis=1)
        err = np.abs(a["basis"].astype(np.float32) - b["basis"].astype(np.float32)) / scale[:, None, None, None]
        assert np.median(err) < 0.02 and np.abs(a["images"].astype(np.float32) - b["images"].astype(np.float32)).mean() < 0.015
    r = subprocess.run([sys.executable, "-m", "networks.datapack", "pack", str(data), str(tmp_path / "bad"),
                        "--quality", "101"], capture_output=True, text=True)
    assert r.returncode == 2 and "quality must be" in r.stderr and "Traceback" not in r.stderr

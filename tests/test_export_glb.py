"""NAME.glb: Khronos glTF validator (no errors), 8-bit textures that read back within quantisation, UV / tangent
orientation, and a Mitsuba render of the glb's material matching the render of the original maps."""
from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from matcap import MaterialMaps
from matcap.export import export, maps_from_glb
from matcap.imageio import linear_to_srgb

ROOT = Path(__file__).resolve().parents[1]
NODE_TOOLS = ROOT / "tools" / "node"
H, W = 48, 64
Q8 = 0.5 / 255 + 1e-6
RENDER_PSNR_DB = 40.0  # glb (8-bit) vs original (float) maps, same light, spp and seed; measured ≈ 49 dB


def bumpy_maps(mask_border: bool = True) -> MaterialMaps:
    r, c = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = c, -r
    hx, hy = np.zeros((H, W)), np.zeros((H, W))
    for cx, cy, amp, s in [(20, -20, 5.0, 7.0), (45, -30, -4.0, 8.0)]:
        g = amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        hx, hy = hx - g * (x - cx) / s**2, hy - g * (y - cy) / s**2
    n = np.stack([-hx, -hy, np.ones((H, W))], axis=2)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    mask = np.ones((H, W), bool)
    if mask_border:
        mask[:, :4] = False
    n[~mask] = 0
    base = np.stack([0.2 + 0.6 * c / W, 0.3 + 0.4 * r / H, np.full((H, W), 0.5)], axis=2)
    return MaterialMaps(normal=n, mask=mask, base_color=base, roughness=0.3 + 0.5 * c / W,
                        metallic=0.8 * (r > H / 2))


@pytest.fixture(scope="module")
def glb_files(tmp_path_factory):
    out = tmp_path_factory.mktemp("glb")
    maps = bumpy_maps()
    full = export(maps, out, name="full", height=False)
    normal_only = export(MaterialMaps(normal=maps.normal, mask=np.ones((H, W), bool)), out, name="nrm", height=False)
    return maps, Path(full["glb"]), Path(normal_only["glb"])


def glb_json(path: Path) -> dict:
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])


def test_khronos_validator_reports_no_errors(glb_files):
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: the Khronos glTF validator (npm gltf-validator) needs Node.js")
    assert (NODE_TOOLS / "node_modules" / "gltf-validator").is_dir(), (
        "gltf-validator is not installed: run `npm ci --prefix tools/node`")
    _, full, normal_only = glb_files
    proc = subprocess.run([node, str(NODE_TOOLS / "validate.mjs"), str(full), str(normal_only)],
                          capture_output=True, text=True, timeout=120)
    reports = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(reports) == 2, proc.stderr
    for rep in reports:
        issues = rep["issues"]
        errors = [m for m in issues["messages"] if m["severity"] == 0]
        assert issues["numErrors"] == 0, errors
        assert issues["numWarnings"] == 0, issues["messages"]
    assert proc.returncode == 0


def test_glb_material_layout_and_orientation(glb_files):
    _, full, normal_only = glb_files
    tree = glb_json(full)
    mat = tree["materials"][0]
    pbr = mat["pbrMetallicRoughness"]
    assert {"baseColorTexture", "metallicRoughnessTexture"} <= set(pbr) and "normalTexture" in mat
    assert mat["alphaMode"] == "MASK"  # mask in base colour alpha
    assert all(img["mimeType"] == "image/png" for img in tree["images"])
    prim = tree["meshes"][0]["primitives"][0]
    assert {"POSITION", "NORMAL", "TEXCOORD_0", "TANGENT"} <= set(prim["attributes"])
    # UV = image axes, V up: the top-left corner (-x, +y) samples image texel (0, 0) (glTF uv origin top-left)
    data = full.read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    binary = data[20 + json_len + 8:]

    def accessor(i, comps):
        acc = tree["accessors"][i]
        view = tree["bufferViews"][acc["bufferView"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        return np.frombuffer(binary, "<f4", acc["count"] * comps, start).reshape(-1, comps)

    pos, uv = accessor(prim["attributes"]["POSITION"], 3), accessor(prim["attributes"]["TEXCOORD_0"], 2)
    tangent = accessor(prim["attributes"]["TANGENT"], 4)
    top_left = np.argmin(pos[:, 0] - pos[:, 1])
    assert np.allclose(uv[top_left], [0, 0]) and np.allclose(pos[:, 2], 0)
    assert np.allclose(tangent, [1, 0, 0, 1])  # T = +x, bitangent = N x T * w = +y (OpenGL normal map)
    assert (np.ptp(pos[:, 1]) / np.ptp(pos[:, 0])) == pytest.approx(H / W)
    # normal-only result: constant factors instead of made-up textures
    pbr = glb_json(normal_only)["materials"][0]["pbrMetallicRoughness"]
    assert "baseColorTexture" not in pbr and "metallicRoughnessTexture" not in pbr
    assert pbr["roughnessFactor"] == 0.5 and pbr["metallicFactor"] == 0.0


def test_glb_reads_back_within_8bit_quantisation(glb_files):
    maps, full, _ = glb_files
    back = maps_from_glb(full)
    assert (back.mask == maps.mask).all()
    m = maps.mask
    assert np.abs(linear_to_srgb(back.base_color) - linear_to_srgb(maps.base_color))[m].max() <= Q8 + 1e-5
    assert np.abs(back.roughness - maps.roughness)[m].max() <= Q8
    assert np.abs(back.metallic - maps.metallic)[m].max() <= Q8
    # 8-bit normals: each component within one code of (n + 1) / 2 after renormalising
    assert np.abs(back.normal - maps.normal)[m].max() <= 2 * 2 * Q8


def test_glb_material_renders_like_the_original_maps(glb_files):
    pytest.importorskip("mitsuba")
    relight = pytest.importorskip("renderers.relight", reason="renderers.relight (Mitsuba relighting) not available")
    from scenes.lights import DirectionalLight

    maps, full, _ = glb_files
    lights = [DirectionalLight(direction=(0.4, 0.3, 1.0), irradiance=(3.0, 3.0, 3.0))]
    ref = relight.render(maps, lights, spp=16, seed=0)
    got = relight.render(maps_from_glb(full), lights, spp=16, seed=0)

    def psnr(a, b):
        return 10 * np.log10(ref.max() ** 2 / np.mean((a - b) ** 2))

    assert psnr(ref, got) >= RENDER_PSNR_DB
    # the test can tell a wrong convention: the same maps with DirectX normals read as OpenGL fail it
    flipped = maps_from_glb(full)
    flipped.normal[..., 1] *= -1
    assert psnr(ref, relight.render(flipped, lights, spp=16, seed=0)) < RENDER_PSNR_DB - 10

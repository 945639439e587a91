"""Loose texture set: round trip within each encoding's quantisation, DX vs GL, preset channel layouts, missing maps,
provenance, and the `matcap export` command."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from matcap import MaterialMaps
from matcap.errors import MatcapError
from matcap.export import PRESETS, export, read_texture_set
from matcap.imageio import linear_to_srgb, read_exr

H, W = 24, 32
Q16 = 0.5 / 65535 + 1e-7  # 16-bit linear: half a code
Q8 = 0.5 / 255 + 1e-7  # 8-bit: half a code (in the encoded domain)
SRGB_DECODE_SLOPE = 2.4 / 1.055  # max d(linear)/d(sRGB) on [0, 1], reached at 1


def raw(path) -> np.ndarray:
    """Stored PNG codes, channels in R, G, B(, A) order (alpha kept)."""
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert arr is not None, path
    if arr.ndim == 3:
        arr = arr[:, :, [2, 1, 0, 3][: arr.shape[2]]]
    return arr


def random_maps(seed: int = 0, **drop) -> MaterialMaps:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(H, W, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.5
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    mask = np.ones((H, W), bool)
    mask[:3, :5] = False
    n[~mask] = 0
    maps = dict(base_color=rng.random((H, W, 3)), roughness=rng.random((H, W)), metallic=rng.random((H, W)),
                height=rng.normal(size=(H, W)))
    for k in drop:
        maps[k] = None
    maps["height"] = None if maps["height"] is None else np.where(mask, maps["height"], 0.0)
    meta = {"models": {"normal": {"weights": "sdm_unips_small.safetensors",
                                  "card": {"preset": "small", "license": "MIT (test fixture)"}}}}
    return MaterialMaps(normal=n, mask=mask, meta=meta, **maps)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("tex")
    maps = random_maps()
    return maps, export(maps, out, name="mat", normal="dx", glb=False)


def test_round_trip_within_quantisation(exported):
    maps, paths = exported
    # 8-bit sRGB base colour: stored codes are the rounded sRGB encoding; decoded values within the bound
    base = raw(paths["basecolor"])
    assert base.dtype == np.uint8
    assert np.abs(base / 255.0 - linear_to_srgb(maps.base_color)).max() <= Q8
    back = read_texture_set(paths["json"])
    assert np.abs(back.base_color - maps.base_color).max() <= SRGB_DECODE_SLOPE * Q8
    # 16-bit linear roughness / metallic
    for key in ("roughness", "metallic"):
        stored = raw(paths[key])
        assert stored.dtype == np.uint16 and stored.ndim == 2
        assert np.abs(stored / 65535.0 - getattr(maps, key)).max() <= Q16
        assert np.abs(getattr(back, key) - getattr(maps, key)).max() <= Q16
    # 16-bit normals: each stored component within half a code of (n + 1) / 2; off-mask texels flat
    normal = raw(paths["normal"])
    assert normal.dtype == np.uint16
    enc = (maps.normal + 1) / 2
    assert np.abs(normal / 65535.0 - enc)[maps.mask].max() <= Q16
    assert np.abs(normal[~maps.mask] / 65535.0 - [0.5, 0.5, 1.0]).max() <= Q16
    assert np.abs(back.normal - maps.normal).max() <= 4 * Q16 * 2  # renormalising at most doubles the error
    assert (back.mask == maps.mask).all()
    # float height is exact, mask exact
    assert np.array_equal(read_exr(paths["height"]), maps.height.astype(np.float32))
    assert set(np.unique(raw(paths["mask"]))) == {0, 255}


def test_dx_is_gl_with_green_flipped(exported):
    _, paths = exported
    gl, dx = raw(paths["normal"]).astype(int), raw(paths["normal_dx"]).astype(int)
    assert np.array_equal(gl[..., [0, 2]], dx[..., [0, 2]])
    assert np.abs(gl[..., 1] + dx[..., 1] - 65535).max() <= 1  # G_dx = 1 - G_gl (one code at exact ties)


def test_orm_layout(exported):
    _, paths = exported
    orm = raw(paths["orm"])
    assert orm.dtype == np.uint16 and orm.shape == (H, W, 3)
    assert np.array_equal(orm[..., 0], raw(paths["occlusion"]))  # R = ambient occlusion baked from the height
    assert raw(paths["occlusion"]).min() < 65535  # random normals make a rough surface: some texels are occluded
    assert np.array_equal(orm[..., 1], raw(paths["roughness"]))
    assert np.array_equal(orm[..., 2], raw(paths["metallic"]))


def test_json_describes_files_and_provenance(exported):
    _, paths = exported
    info = json.loads(open(paths["json"]).read())
    assert info["resolution"] == {"width": W, "height": H}
    assert info["files"]["basecolor"]["colorspace"] == "sRGB" and info["files"]["basecolor"]["bits"] == 8
    assert all(info["files"][k]["colorspace"] == "linear" for k in ("normal", "roughness", "metallic", "orm"))
    assert info["files"]["normal"]["bits"] == 16
    assert info["model"]["normal"] == {"model": "sdm_unips_small.safetensors", "license": "MIT (test fixture)"}
    assert info["missing"] == [] and info["filled"] == {}
    assert info["normal_convention"].startswith("DirectX")


def test_unity_hdrp_mask_map(tmp_path):
    maps = random_maps(1)
    paths = export(maps, tmp_path, name="u", preset="unity-hdrp", glb=False, height=False, occlusion=False)
    assert "occlusion" not in paths and "height" not in paths
    mm = raw(paths["maskmap"])
    assert mm.dtype == np.uint16 and mm.shape == (H, W, 4)
    assert np.abs(mm[..., 0] / 65535.0 - maps.metallic).max() <= Q16  # R metallic
    assert (mm[..., 1] == 65535).all()  # G occlusion (1: not baked)
    assert (mm[..., 2] == 65535).all()  # B detail mask (1)
    assert np.abs(mm[..., 3] / 65535.0 - (1 - maps.roughness)).max() <= Q16  # A smoothness = 1 - roughness
    assert "normal_dx" not in paths  # Unity is OpenGL
    info = json.loads(open(paths["json"]).read())
    assert info["preset"]["slots"]["Mask Map"]["file"] == "u_maskmap.png"


def test_unreal_and_blender_presets(tmp_path):
    maps = random_maps(2)
    ue = export(maps, tmp_path / "ue", name="m", preset="unreal", glb=False, height=False)
    assert "normal_dx" in ue and "orm" in ue  # Unreal: DirectX normals by default + ORM
    slots = json.loads(open(ue["json"]).read())["preset"]["slots"]
    assert slots["Normal"]["file"] == "m_normal_dx.png"
    assert slots["Ambient Occlusion / Roughness / Metallic"]["file"] == "m_orm.png"
    bl = export(maps, tmp_path / "bl", name="m", preset="blender", glb=False, height=False)
    assert "normal_dx" not in bl
    slots = json.loads(open(bl["json"]).read())["preset"]["slots"]
    assert slots["Roughness"]["setting"].endswith("Non-Color") and slots["Base Color"]["setting"].endswith("sRGB")
    # presets are data: every slot names a file that the preset writes
    for name, preset in PRESETS.items():
        keys = {"basecolor", "normal", "roughness", "metallic", "orm", "mask", "height"}
        keys |= {t.key for t in preset.extra} | ({"normal_dx"} if preset.normal == "dx" else set())
        assert {v[0] for v in preset.slots.values()} <= keys, name


def test_normal_only_result(tmp_path):
    maps = random_maps(3, base_color=None, roughness=None, metallic=None, height=None)
    paths = export(maps, tmp_path, name="n")
    assert set(paths) == {"normal", "occlusion", "mask", "height", "glb", "json"}
    info = json.loads(open(paths["json"]).read())
    assert info["missing"] == ["base_color", "roughness", "metallic"]
    # one BRDF map present: ORM written, the missing channel filled with the documented constant
    maps = random_maps(4, metallic=None)
    paths = export(maps, tmp_path, name="r", glb=False, height=False)
    assert "orm" in paths and "metallic" not in paths
    assert (raw(paths["orm"])[..., 2] == 0).all()
    assert json.loads(open(paths["json"]).read())["filled"] == {"orm": ["metallic = 0.0"]}


def test_refuses_existing_files(tmp_path):
    maps = random_maps(5)
    export(maps, tmp_path, name="a", glb=False, height=False)
    from matcap.errors import MatcapError

    with pytest.raises(MatcapError, match="overwrite"):
        export(maps, tmp_path, name="a", glb=False, height=False)
    export(maps, tmp_path, name="a", glb=False, height=False, overwrite=True)
    export(maps, tmp_path, name="b", glb=False, height=False)  # another name in the same folder is fine


def test_cli_from_result_folder(tmp_path, capsys):
    from matcap.cli import main
    from matcap.results import write_result

    maps = random_maps(6, height=None)
    write_result(maps, tmp_path / "res")
    assert main(["export", str(tmp_path / "res"), "--out", str(tmp_path / "tex"), "--preset", "unreal",
                 "--no-glb"]) == 0
    info = json.loads((tmp_path / "tex" / "res.json").read_text())
    assert info["model"]["normal"]["license"] == "MIT (test fixture)"
    back = read_texture_set(tmp_path / "tex" / "res.json")
    # result folder stores base colour as 16-bit sRGB; the export re-encodes 8-bit sRGB
    assert np.abs(linear_to_srgb(back.base_color) - linear_to_srgb(maps.base_color)).max() <= Q8 + 1e-4
    capsys.readouterr()
    assert main(["export", str(tmp_path / "res"), "--out", str(tmp_path / "tex"), "--no-glb"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("matcap export: error:") and "--overwrite" in err and "\n" not in err
    assert main(["export", str(tmp_path / "nothing"), "--out", str(tmp_path / "t2")]) == 2


def test_cli_constant_maps(tmp_path, capsys):
    from matcap.cli import main
    from matcap.results import read_result, write_result

    maps = random_maps(7, height=None)
    write_result(maps, tmp_path / "res")
    before = (tmp_path / "res" / "metallic.png").read_bytes()
    assert main(["export", str(tmp_path / "res"), "--out", str(tmp_path / "tex"), "--no-glb", "--no-ao",
                 "--constant", "metallic=0", "--constant", "roughness=0.5"]) == 0
    back = read_texture_set(tmp_path / "tex" / "res.json")  # named after the result folder, as without --constant
    assert np.all(back.metallic[maps.mask] == 0)
    assert np.abs(back.roughness[maps.mask] - 0.5).max() <= Q16
    # base color and normals come from the result as before; the result folder itself is not touched
    assert np.abs(linear_to_srgb(back.base_color) - linear_to_srgb(maps.base_color)).max() <= Q8 + 1e-4
    assert (tmp_path / "res" / "metallic.png").read_bytes() == before
    info = json.loads((tmp_path / "tex" / "res.json").read_text())
    assert info["constant_maps"] == {"metallic": 0.0, "roughness": 0.5}
    assert read_result(tmp_path / "res").metallic[maps.mask].std() > 0.1
    capsys.readouterr()
    assert main(["export", str(tmp_path / "res"), "--out", str(tmp_path / "t2"), "--constant", "metal=0"]) == 2
    assert "--constant 'metal=0'" in capsys.readouterr().err


def test_cli_choices_match_library_tables():
    from matcap.commands.export import HEIGHT_METHODS, PRESET_NAMES
    from matcap.height import METHODS

    assert tuple(PRESETS) == PRESET_NAMES and METHODS == HEIGHT_METHODS


def test_occlusion_is_baked_into_every_occlusion_channel(tmp_path):
    maps = random_maps(3)
    paths = export(maps, tmp_path, name="o", preset="unity-hdrp", height=False, ao_radius=6)
    occ = raw(paths["occlusion"])
    assert occ.dtype == np.uint16 and occ.shape == (H, W)
    assert np.array_equal(raw(paths["maskmap"])[..., 1], occ)
    assert np.array_equal(raw(paths["orm"])[..., 0], occ)
    info = json.loads(open(paths["json"]).read())
    assert info["occlusion"]["radius_px"] == 6 and 0 < info["occlusion"]["mean"] < 1
    with pytest.raises(MatcapError, match="occlusion radius must be at least 1 pixel"):
        export(maps, tmp_path / "bad", ao_radius=0.5)

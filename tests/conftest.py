"""Shared fixtures: tiny datasets made with numpy (fast, no Mitsuba), paths to shared assets, tiny weights, and
``mitsuba_variant``, which runs a test once per Mitsuba variant (``llvm_ad_rgb`` and the ``scalar_rgb`` fallback)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"

torch.set_num_threads(2)


def shared_path(*parts: str) -> Path:
    """A path under ../shared; skips the test when it is not there."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared asset {p} is not available")
    return p


def _sphere_maps(size: int = 24, varied: bool = False):
    """MaterialMaps of a sphere of radius 0.9 (image half-widths) centred in a size x size image.

    ``varied``: base color ramps across the image and the right half is metallic (roughness 0.35); otherwise
    uniform grey base color 0.5, roughness 0.4, metallic 0.
    """
    from scenes.materialmaps import MaterialMaps

    yy, xx = np.mgrid[0:size, 0:size]
    x = (xx + 0.5) / size * 2 - 1
    y = 1 - (yy + 0.5) / size * 2
    mask = x**2 + y**2 < 0.81
    z = np.sqrt(np.clip(0.81 - x**2 - y**2, 0, None))
    n = np.stack([x, y, z], 2) / 0.9
    n[~mask] = 0
    if not varied:
        return MaterialMaps(normal=n, mask=mask, base_color=np.full((size, size, 3), 0.5),
                            roughness=np.full((size, size), 0.4), metallic=np.zeros((size, size)))
    base = np.stack([0.2 + 0.6 * (xx / size), np.full(xx.shape, 0.4), 0.8 - 0.6 * (yy / size)], 2)
    return MaterialMaps(normal=n, mask=mask, base_color=base, roughness=np.full((size, size), 0.35),
                        metallic=(xx > size // 2).astype(np.float32), meta={"source": "test sphere"})


def lambertian_scene(rng: np.random.Generator, size: int) -> dict[str, np.ndarray]:
    """A sphere (random centre/radius/albedo) on a background plane, rendered Lambertian in numpy.

    Basis: 4 directional lights, 1 ambient "env" (irradiance (1 + n_z) / 2), 1 point light.
    """
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    x = (xx + 0.5) / size * 2 - 1
    y = 1 - (yy + 0.5) / size * 2
    cx, cy = rng.uniform(-0.3, 0.3, 2)
    r = rng.uniform(0.35, 0.6)
    d2 = (x - cx) ** 2 + (y - cy) ** 2
    inside = d2 < r * r
    nz = np.sqrt(np.clip(r * r - d2, 0, None)) / r
    normal = np.stack([(x - cx) / r, (y - cy) / r, nz], axis=2)
    normal[~inside] = (0, 0, 1)
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    albedo = np.where(inside[..., None], rng.uniform(0.2, 0.9, 3), rng.uniform(0.2, 0.9, 3)).astype(np.float32)
    albedo *= 1 + 0.2 * np.sin(xx * rng.uniform(0.1, 0.5))[..., None]
    basis, kinds = [], []
    for _ in range(4):
        L = rng.normal(size=3)
        L[2] = abs(L[2]) + 0.5
        L /= np.linalg.norm(L)
        basis.append(albedo * np.clip(normal @ L, 0, None)[..., None])
        kinds.append("directional")
    basis.append(albedo * ((1 + normal[..., 2]) / 2)[..., None])
    kinds.append("env")
    P = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 2.0])
    pos = np.stack([x, y, np.where(inside, cy * 0 + nz * r, 0)], axis=2)
    v = P - pos
    dist = np.linalg.norm(v, axis=2, keepdims=True)
    basis.append(albedo * np.clip((normal * v / dist).sum(2), 0, None)[..., None] * 4 / dist**2)
    kinds.append("point")
    basis = np.stack(basis).astype(np.float32)
    images = np.stack([basis[i % 4] + 0.3 * basis[4] for i in range(10)])
    mask = np.ones((size, size), bool)
    return {
        "basis": basis.astype(np.float16), "basis_kind": np.array(kinds), "images": images.astype(np.float16),
        "normal": normal.astype(np.float16), "mask": mask, "base_color": albedo.astype(np.float16),
        "roughness": np.ones((size, size), np.float16), "metallic": np.zeros((size, size), np.float16),
    }


def make_dataset(root: Path, scenes: int, size: int, seed: int = 0, groups=("directional",)) -> Path:
    rng = np.random.default_rng(seed)
    names = []
    for i in range(scenes):
        name = f"scene_{i:06d}"
        d = root / name
        d.mkdir(parents=True)
        np.savez(d / "data.npz", **lambertian_scene(rng, size))
        (d / "spec.json").write_text(json.dumps({"lighting_group": groups[i % len(groups)]}))
        names.append(name)
    (root / "manifest.json").write_text(json.dumps({"scenes": names, "resolution": size}))
    return root


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """6 numpy-rendered Lambertian scenes at 64x64 (train) ."""
    return make_dataset(tmp_path_factory.mktemp("tinydata"), 6, 64, seed=1)


@pytest.fixture(scope="session")
def tiny_val_dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("tinyval"), 2, 64, seed=2, groups=("directional", "environment"))


@pytest.fixture(scope="session")
def sphere_maps():
    """Factory ``sphere_maps(size=24, varied=False) -> MaterialMaps`` of a centred sphere (see ``_sphere_maps``)."""
    return _sphere_maps


@pytest.fixture(params=["llvm_ad_rgb", "scalar_rgb"])
def mitsuba_variant(request):
    """Run the test once per Mitsuba variant: the variant is set for this process (``renderers.variant``) and
    exported as ``MATCAP_MITSUBA_VARIANT`` for the commands a test starts as subprocesses. ``llvm_ad_rgb`` is
    skipped (with the reason) where it cannot render, e.g. without libLLVM >= 17.

    To run the whole suite in one variant instead: ``MATCAP_MITSUBA_VARIANT=scalar_rgb python -m pytest -q``.
    """
    pytest.importorskip("mitsuba")
    import mitsuba as mi
    import renderers.variant as rv

    variant = request.param
    if variant == "llvm_ad_rgb" and not rv.llvm_works():
        pytest.skip("llvm_ad_rgb does not render here (needs libLLVM >= 17, e.g. apt-get install libllvm19)")
    old_env, old_chosen = os.environ.get("MATCAP_MITSUBA_VARIANT"), rv._chosen
    os.environ["MATCAP_MITSUBA_VARIANT"] = variant
    rv._chosen = None
    assert rv.choose_variant() == variant and mi.variant() == variant
    try:
        yield variant
    finally:
        if old_env is None:
            os.environ.pop("MATCAP_MITSUBA_VARIANT", None)
        else:
            os.environ["MATCAP_MITSUBA_VARIANT"] = old_env
        rv._chosen = old_chosen
        if old_chosen is not None:
            mi.set_variant(old_chosen)


@pytest.fixture(scope="session")
def tiny_weights(tmp_path_factory) -> Path:
    """A folder with untrained ``tiny`` normal and BRDF networks (seed 0): fast stand-ins for the bundled models."""
    from networks.checkpoint import save_weights
    from networks.config import get_config
    from networks.model import SDMUniPS

    folder = tmp_path_factory.mktemp("weights")
    for target in ("normal", "brdf"):
        torch.manual_seed(0)
        cfg = get_config("tiny", target)
        save_weights(folder / f"{target}_tiny.safetensors", SDMUniPS(cfg), cfg, {"name": f"{target}_tiny"})
    return folder


def sphere_geometry(h: int = 40, w: int = 56) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sphere of :func:`sphere_photos` in an h x w image: (x, y) (H, W) its disc coordinates (radius 1),
    normal (H, W, 3) unit (camera frame)."""
    yy, xx = np.mgrid[0:h, 0:w]
    r = min(h, w) * 0.4
    x, y = (xx - w / 2) / r, (h / 2 - yy) / r
    return x, y, np.dstack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, 1))])


def sphere_photos(folder: Path, h: int = 40, w: int = 56, n: int = 4, bits: int = 16, mask: bool = True, *,
                  albedo: float = 0.7, background: float = 0.05, spread: float = 0.5, seed: int = 0,
                  encode=None) -> Path:
    """A Lambertian sphere (``albedo``) under n directional lights (x and y of each direction uniform in
    +-``spread`` before normalising), written as PNGs through ``encode`` (linear values -> stored values in [0, 1];
    default: as they are) (+ mask.png): a capture folder."""
    from matcap import imageio

    folder.mkdir(parents=True, exist_ok=True)
    x, y, normal = sphere_geometry(h, w)
    inside = x**2 + y**2 < 1
    rng = np.random.default_rng(seed)
    for i in range(n):
        L = np.array([rng.uniform(-spread, spread), rng.uniform(-spread, spread), 1.0])
        L /= np.linalg.norm(L)
        img = np.where(inside[..., None], albedo * np.clip(normal @ L, 0, 1)[..., None], background) * np.ones(3)
        imageio.write_png(folder / f"img_{i:02d}.png", img if encode is None else encode(img), bits=bits)
    if mask:
        imageio.write_png(folder / "mask.png", inside.astype(np.float32), bits=8)
    return folder

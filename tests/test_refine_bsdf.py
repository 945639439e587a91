"""matcap.refine.bsdf (torch) against Mitsuba's own ``normalmap(principled)`` as ``matcap relight`` builds it."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from matcap.refine.bsdf import principled_eval

REL_TOL = 0.01  # contract: within 1 %
ABS_FLOOR = 1e-3  # relative error is taken against max(|mitsuba|, ABS_FLOOR): values are O(0.01 .. 1e3)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _hemisphere(rng, n: int, min_z: float = 0.0) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + min_z
    return _unit(v)


def random_cases(seed: int = 0, n: int = 480) -> dict[str, np.ndarray]:
    """Random normals (camera space, z >= 0 as relighting's maps), view and light directions and materials.

    Mixed in: view along +z (the camera), light mirrored about the normal (highlight peaks, +-1 deg), light below
    the geometric horizon, light below the shading normal only, grazing normals, a view direction equal to the
    normal, rough 1.0, smooth 0.05-0.1, metallic 0, 1 and between.
    """
    rng = np.random.default_rng(seed)
    normal = _hemisphere(rng, n, 0.05)
    wi = _hemisphere(rng, n, 0.02)
    wo = _hemisphere(rng, n, 0.02)
    q = n // 8
    wi[:2 * q] = (0.0, 0.0, 1.0)  # the orthographic camera
    mirror = slice(2 * q, 4 * q)  # near the specular peak
    wo[mirror] = _unit(2 * np.sum(wi[mirror] * normal[mirror], 1, keepdims=True) * normal[mirror] - wi[mirror]
                       + rng.normal(scale=0.015, size=(2 * q, 3)))
    wo[4 * q:4 * q + q // 2, 2] *= -1  # below the geometric horizon
    normal[5 * q:5 * q + q // 2] = _unit(normal[5 * q:5 * q + q // 2] * (1, 1, 0.05))  # grazing normals
    wi[5 * q + q // 2:6 * q] = normal[5 * q + q // 2:6 * q]  # view along the normal
    roughness = rng.choice([0.05, 0.07, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0], n)
    metallic = rng.choice([0.0, 1.0, 0.25, 0.5, 0.9], n)
    base_color = rng.uniform(0.02, 1.0, (n, 3))
    return dict(normal=normal, wi=wi, wo=wo, base_color=base_color, roughness=roughness, metallic=metallic)


def _torch_eval(case: dict, dtype=torch.float64) -> np.ndarray:
    args = [torch.tensor(case[k], dtype=dtype) for k in ("normal", "wi", "wo", "base_color", "roughness", "metallic")]
    return principled_eval(*args).numpy().astype(np.float64)


def _variants() -> list[str]:
    pytest.importorskip("mitsuba")
    from renderers.variant import choose_variant

    return ["scalar_rgb"] + (["llvm_ad_rgb"] if choose_variant(quiet=True) == "llvm_ad_rgb" else [])


@pytest.mark.parametrize("variant", ["scalar_rgb", "llvm_ad_rgb"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matches_mitsuba_bsdf_eval(variant, dtype):
    if variant not in _variants():
        pytest.skip(f"Mitsuba variant {variant} does not work here")
    from renderers.bsdf_eval import eval_surface_bsdf

    case = random_cases(seed=1)
    ref = eval_surface_bsdf(variant=variant, **case).astype(np.float64)
    ours = _torch_eval(case, dtype)
    assert np.isfinite(ours).all()
    rel = np.abs(ours - ref) / np.maximum(np.abs(ref), ABS_FLOOR)
    # both sides agree on where the value is zero (below the surface, back of the microfacets)
    assert np.array_equal(ref.max(1) > 0, ours.max(1) > 0)
    assert (ref.max(1) > 0).mean() > 0.5 and ref.max() > 100  # the set does contain sharp highlights
    assert rel.max() < REL_TOL, f"max relative error {rel.max():.4f} at {np.unravel_index(rel.argmax(), rel.shape)}"
    print(f"{variant} {dtype}: max relative error {rel.max():.2e}, mean {rel.mean():.2e}")
    assert rel.mean() < 1e-3


def test_zero_below_the_surface_and_broadcasting():
    n = torch.tensor([0.0, 0.0, 1.0])
    wi = torch.tensor([0.0, 0.0, 1.0])
    wo = torch.tensor([[0.6, 0.0, 0.8], [0.6, 0.0, -0.8]])
    out = principled_eval(n, wi, wo, torch.full((3,), 0.5), torch.tensor(0.5), torch.tensor(0.0))
    assert out.shape == (2, 3)
    assert (out[0] > 0).all() and (out[1] == 0).all()
    # light above the plane but behind a tilted shading normal
    tilted = torch.tensor([0.8, 0.0, 0.6])
    out = principled_eval(tilted, wi, torch.tensor([-0.8, 0.0, 0.6]), torch.full((3,), 0.5), 0.5, 0.0)
    assert (out == 0).all()
    # roughness / metallic broadcast against (H, W) maps
    maps = principled_eval(n.expand(4, 5, 3), wi, torch.tensor([0.0, 0.6, 0.8]), torch.full((4, 5, 3), 0.3),
                           torch.full((4, 5), 0.4), torch.zeros(4, 5))
    assert maps.shape == (4, 5, 3) and torch.allclose(maps, maps[0, 0].expand(4, 5, 3))


def test_gradients_finite_in_degenerate_configurations():
    """No NaN / inf gradients at roughness 0, grazing directions, normal == view == light, horizon lights."""
    z = [0.0, 0.0, 1.0]
    g = [0.9999, 0.0, 0.01414]  # grazing
    normals = [z, z, z, g, [0.6, 0.0, 0.8], [1.0, 0.0, 0.0], z, [0.3, 0.4, 0.866]]
    wis = [z, z, g, z, z, z, [0.0, 1.0, 0.0], [0.3, 0.4, 0.866]]
    wos = [z, [1.0, 0.0, 0.0], g, z, [0.6, 0.0, 0.8], [0.0, 0.0, -1.0], z, [0.3, 0.4, 0.866]]
    for rough in (0.0, 1e-4, 0.05, 1.0):
        for metal in (0.0, 1.0):
            normal = torch.tensor(normals, dtype=torch.float32, requires_grad=True)
            wi = torch.tensor(wis, dtype=torch.float32, requires_grad=True)
            wo = torch.tensor(wos, dtype=torch.float32, requires_grad=True)
            base = torch.full((len(normals), 3), 0.5, requires_grad=True)
            r = torch.full((len(normals),), rough, requires_grad=True)
            m = torch.full((len(normals),), metal, requires_grad=True)
            out = principled_eval(normal, wi, wo, base, r, m)
            assert torch.isfinite(out).all()
            out.sum().backward()
            for t in (normal, wi, wo, base, r, m):
                assert torch.isfinite(t.grad).all(), (rough, metal, t.grad)


def test_gradient_matches_finite_differences():
    torch.manual_seed(0)
    normal = torch.nn.functional.normalize(torch.tensor([[0.2, -0.1, 0.9], [-0.4, 0.3, 0.8]], dtype=torch.float64), dim=-1)
    wi = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.2, 0.97]], dtype=torch.float64)
    wi = torch.nn.functional.normalize(wi, dim=-1)
    wo = torch.nn.functional.normalize(torch.tensor([[0.5, -0.2, 0.8], [-0.7, 0.5, 0.5]], dtype=torch.float64), dim=-1)
    args = (normal.requires_grad_(), wi, wo, torch.tensor([[0.7, 0.4, 0.2], [0.1, 0.5, 0.9]], dtype=torch.float64,
            requires_grad=True), torch.tensor([0.3, 0.6], dtype=torch.float64, requires_grad=True),
            torch.tensor([0.2, 0.7], dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(lambda n, b, r, m: principled_eval(n, wi, wo, b, r, m),
                                    (args[0], args[3], args[4], args[5]))


# ------------------------------------------------------------------------------ end to end: relight render


def _block_maps(specs, block: int = 6, rows: int = 5):
    """MaterialMaps of vertical blocks ``block`` pixels wide, one (normal, base, roughness, metallic) each."""
    from scenes.materialmaps import MaterialMaps

    w = block * len(specs)
    normal = np.zeros((rows, w, 3), np.float32)
    base = np.zeros((rows, w, 3), np.float32)
    rough = np.zeros((rows, w), np.float32)
    metal = np.zeros((rows, w), np.float32)
    for i, (n, b, r, m) in enumerate(specs):
        cols = slice(i * block, (i + 1) * block)
        normal[:, cols] = _unit(np.asarray(n, np.float64))
        base[:, cols] = b
        rough[:, cols] = r
        metal[:, cols] = m
    maps = MaterialMaps(normal=normal, mask=np.ones((rows, w), bool), base_color=base, roughness=rough,
                        metallic=metal)
    inner = np.zeros(w, bool)  # columns whose bilinear footprint stays inside their block
    for i in range(len(specs)):
        inner[i * block + 1:(i + 1) * block - 1] = True
    return maps, inner


SPECS = [
    ((0.0, 0.0, 1.0), (0.6, 0.5, 0.4), 0.5, 0.0),
    ((0.4, 0.1, 0.9), (0.2, 0.4, 0.8), 0.3, 0.0),
    ((-0.5, 0.3, 0.8), (0.9, 0.7, 0.3), 0.6, 1.0),
    ((0.2, -0.45, 0.85), (0.5, 0.5, 0.5), 1.0, 0.5),
    ((0.6, 0.6, 0.5), (0.8, 0.2, 0.2), 0.2, 0.3),
    ((0.15, 0.05, 0.98), (0.7, 0.7, 0.7), 0.4, 1.0),
]


def _pixel_centres(h: int, w: int) -> np.ndarray:
    """World positions (H, W, 3) of the pixel centres on renderers.plane's framing plane (z = 0)."""
    from renderers.plane import plane_half_extent

    hx, hy = plane_half_extent(w, h)
    x = -hx + (np.arange(w) + 0.5) * 2 * hx / w
    y = hy - (np.arange(h) + 0.5) * 2 * hy / h
    yy, xx = np.meshgrid(y, x, indexing="ij")
    return np.stack([xx, yy, np.zeros_like(xx)], -1)


@pytest.mark.parametrize("kind", ["directional", "point"])
def test_relight_render_matches_torch_shading(kind):
    pytest.importorskip("mitsuba")
    from renderers.relight import render
    from scenes.lights import DirectionalLight, PointLight

    maps, inner = _block_maps(SPECS)
    h, w = maps.shape
    if kind == "directional":
        d, e = _unit(np.array([0.3, 0.45, 0.85])), np.array([2.0, 1.5, 1.0])
        light = DirectionalLight(tuple(d), tuple(e))
        wo = np.broadcast_to(d, (h, w, 3))
        scale = np.broadcast_to(e, (h, w, 3))
    else:
        p, intensity = np.array([0.4, 0.3, 2.5]), np.array([8.0, 6.0, 5.0])
        light = PointLight(tuple(p), tuple(intensity))
        delta = p - _pixel_centres(h, w)
        dist2 = np.sum(delta**2, -1, keepdims=True)
        wo = delta / np.sqrt(dist2)
        scale = intensity / dist2
    img = render(maps, [light], spp=16)
    t = lambda a: torch.tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
    ours = principled_eval(t(maps.normal), t(np.broadcast_to([0.0, 0.0, 1.0], (h, w, 3))), t(wo),
                           t(maps.base_color), t(maps.roughness), t(maps.metallic)).numpy() * scale
    sel = np.broadcast_to(inner[None, :], (h, w))
    rel = np.abs(img[sel] - ours[sel]) / np.maximum(ours[sel], 1e-3)
    print(f"{kind}: max relative difference {rel.max():.2e}, mean {rel.mean():.2e}")
    assert ours[sel].min() > 0.01  # every block is lit
    assert rel.max() < 0.01, f"{kind}: max relative difference {rel.max():.4f}"

"""The refinement's forward model: the fast directional path equals the general one (principled_eval), the SH
ambient term is the Ramamoorthi-Hanrahan irradiance."""
from __future__ import annotations

import math

import torch

from matcap.refine.model import SH_C0, shade, shade_directional, sh_irradiance


def test_fast_directional_path_equals_principled_eval():
    g = torch.Generator().manual_seed(0)
    n_px, k = 500, 7
    n = torch.randn(n_px, 3, generator=g, dtype=torch.float64)
    n[:, 2] = n[:, 2].abs() + 0.05
    n = n / n.norm(dim=-1, keepdim=True)
    base = torch.rand(n_px, 3, generator=g, dtype=torch.float64)
    rough = torch.rand(n_px, generator=g, dtype=torch.float64)
    metal = torch.rand(n_px, generator=g, dtype=torch.float64)
    l = torch.randn(k, 3, generator=g, dtype=torch.float64)
    l[:, 2] = l[:, 2].abs() + 0.1
    l = l / l.norm(dim=-1, keepdim=True)
    irr = torch.rand(k, 3, generator=g, dtype=torch.float64) + 0.5
    sh = torch.randn(1, 9, 3, generator=g, dtype=torch.float64) * 0.1
    ref = shade(n, base, rough, metal, l[:, None, :], irr[:, None, :], sh)
    fast = shade_directional(n, base, rough, metal, l, irr, sh)
    assert ref.abs().max() > 0.5
    assert torch.allclose(fast, ref, rtol=1e-6, atol=1e-9), (fast - ref).abs().max()


def test_constant_sh_radiance_gives_pi_times_radiance():
    sh = torch.zeros(1, 9, 3)
    sh[0, 0] = 0.3 / SH_C0  # uniform radiance 0.3
    n = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    e = sh_irradiance(n, sh)
    assert torch.allclose(e, torch.full_like(e, 0.3 * math.pi), rtol=1e-5)


def test_near_lights_span_distant_and_point_lights():
    """A near light (direction and irradiance at a centre, inverse distance u) is exactly the distant light at
    u = 0, and the point light at centre + direction / u with intensity irradiance / u^2 otherwise; lights.json
    entries say so."""
    import numpy as np

    from matcap.refine.photos import lights_to_entries
    from matcap.refine.model import LightParams

    torch.manual_seed(0)
    pos = torch.rand(50, 3) * 2 - 1
    pos[:, 2] = 0
    centre = torch.tensor([0.1, -0.2, 0.0])
    d = torch.tensor([[0.3, 0.2, 0.9], [-0.5, 0.1, 0.8]])
    d = d / d.norm(dim=-1, keepdim=True)
    log_e = torch.log(torch.tensor([[1.0, 2.0, 3.0], [0.5, 0.5, 0.5]]))
    sh = torch.zeros(1, 9, 3)
    u = torch.tensor([0.0, 0.25])
    near = LightParams("near", d, log_e, sh, u, centre)
    wo, irr = near.incident(pos)
    far_wo, far_irr = LightParams("directional", d, log_e, sh).incident(pos)
    assert torch.equal(wo[0], far_wo[0].expand(50, 3)) and torch.equal(irr[0], far_irr[0].expand(50, 3))
    point = LightParams("point", (centre + d[1] / 0.25)[None], log_e[1:] - 2 * math.log(0.25), sh)
    p_wo, p_irr = point.incident(pos)
    assert torch.allclose(wo[1], p_wo[0], atol=1e-6) and torch.allclose(irr[1], p_irr[0], rtol=1e-5)
    entries = lights_to_entries(near, scale=2.0)
    assert entries[0]["kind"] == "directional" and np.allclose(entries[0]["direction"], d[0].numpy())
    assert np.allclose(entries[0]["intensity"], [0.5, 1.0, 1.5])
    assert entries[1]["kind"] == "point" and np.allclose(entries[1]["position"], (centre + 4 * d[1]).numpy())
    assert np.allclose(entries[1]["intensity"], [0.25 * 16] * 3, rtol=1e-5)


def test_closed_form_jacobian_equals_forward_mode_autodiff():
    """shade_jacobian's derivatives (normal along tangents, base colour per channel, roughness, metallic) against
    torch.func.jvp of shade_fast, for distant lights (K, 1, 3) and per-pixel ones (K, N, 3)."""
    from matcap.refine.model import shade_fast, shade_jacobian

    g = torch.Generator().manual_seed(1)
    dt = torch.float64
    n_px, k = 300, 5
    n = torch.randn(n_px, 3, generator=g, dtype=dt)
    n[:, 2] = n[:, 2].abs() + 0.3
    n = n / n.norm(dim=-1, keepdim=True)
    base = torch.rand(n_px, 3, generator=g, dtype=dt)
    rough = torch.rand(n_px, generator=g, dtype=dt) * 0.9 + 0.05
    metal = torch.rand(n_px, generator=g, dtype=dt)
    sh = torch.randn(1, 9, 3, generator=g, dtype=dt) * 0.1
    tangents = torch.randn(2, n_px, 3, generator=g, dtype=dt)
    for m in (1, n_px):
        wo = torch.randn(k, m, 3, generator=g, dtype=dt)
        wo[..., 2] = wo[..., 2].abs() + 0.2
        wo = wo / wo.norm(dim=-1, keepdim=True)
        irr = torch.rand(k, m, 3, generator=g, dtype=dt) + 0.5
        pred, d_n, d_b, d_r, d_m = shade_jacobian(n, base, rough, metal, wo, irr, sh, tangents)
        assert torch.allclose(pred, shade(n, base, rough, metal, wo, irr, sh), rtol=1e-9, atol=1e-12)

        def along(tn, tb, tr, tm):
            f = lambda *x: shade_fast(*x, wo, irr, sh)  # noqa: E731
            return torch.func.jvp(f, (n, base, rough, metal), (tn, tb, tr, tm))[1]

        zn, zb, z = torch.zeros_like(n), torch.zeros_like(base), torch.zeros_like(rough)
        for i in range(2):
            assert torch.allclose(d_n[i], along(tangents[i], zb, z, z), rtol=1e-9, atol=1e-9)
        assert torch.allclose(d_r, along(zn, zb, torch.ones_like(rough), z), rtol=1e-9, atol=1e-9)
        assert torch.allclose(d_m, along(zn, zb, z, torch.ones_like(metal)), rtol=1e-9, atol=1e-9)
        for c in range(3):
            tb = zb.clone()
            tb[:, c] = 1.0
            ref = along(zn, tb, z, z)
            assert torch.allclose(d_b[..., c], ref[..., c], rtol=1e-9, atol=1e-9)
            assert ref[..., [j for j in range(3) if j != c]].abs().max() == 0

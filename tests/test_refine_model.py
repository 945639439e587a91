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

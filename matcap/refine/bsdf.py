"""Mitsuba 3.9.1's ``normalmap(principled)`` BSDF ``eval`` in torch (differentiable, any device / dtype).

This is the surface that ``matcap relight`` renders (``renderers.relight.surface_bsdf``): a ``principled`` BSDF
with ``specular`` 0.5 and every other parameter at its default (no spec_trans, clearcoat, sheen, spec_tint,
anisotropy, flatness), wrapped in ``normalmap`` on the framing plane, whose geometric normal is +z in camera
space (camera space = the plane's tangent space: x right, y up, z toward the camera).

What Mitsuba does, step by step (``src/bsdfs/normalmap.cpp``, ``principled.cpp``, ``principledhelpers.h``,
``include/mitsuba/render/microfacet.h`` / ``fresnel.h``), and this module repeats:

normalmap (``flip_invalid_normals`` and ``use_shadowing_function`` both on by default since 3.7.1)
  * flip: where ``wi.z * dot(wi, n) <= 0`` the shading normal becomes ``(-n.x, -n.y, n.z)``; then normalised.
  * the nested BSDF is evaluated in the perturbed frame; the result is zero unless ``wo.z * dot(wo, n) > 0``
    (``wo`` on the same side of the geometric and of the shading normal).
  * the value is multiplied by the shadow-terminator term of Conty Estevez et al. 2019:
    ``2 / (1 + sqrt(1 + a2 tan^2(wo)))`` with ``a2 = min(tan^2(n) / 8, 1)``, both angles to the geometric +z.

principled (front side only: ``bsdf = (1 - metallic) * spec_trans = 0``, so nothing reflects from the back)
  * ``eta = 2 / (1 - sqrt(0.08 specular)) - 1`` (1.5 for specular 0.5: F0 = 4 %).
  * GGX (Trowbridge-Reitz) with ``alpha = max(0.001, roughness^2)``,
    ``D(h) = 1 / (pi a^2 ((h_x^2 + h_y^2) / a^2 + h_z^2)^2)`` (zero where D h_z <= 1e-20),
    separable Smith ``G = G1(wi) G1(wo)``, ``G1(v) = 2 / (1 + sqrt(1 + a^2 tan^2 v))`` (zero when ``v`` sees the
    back of the microfacet).
  * ``h = normalize(wi + wo)``; reflection needs ``cos_i cos_o > 0``, ``cos_i > 0`` and ``dot(wi, h)``,
    ``dot(wo, h) > 0``.
  * Fresnel: ``(1 - metallic) F_dielectric(dot(wi, h), eta) + metallic Schlick(base_color, dot(wi, h))``
    (exact unpolarised dielectric Fresnel; Schlick ``F0 + (1 - F0) (1 - c)^5`` with F0 = base colour).
  * specular lobe ``F D G / (4 cos_i)`` (= BRDF times cos_o).
  * diffuse lobe (Burley): ``(1 - metallic) base_color / pi cos_o (f_diff + f_retro)``,
    ``f_diff = (1 - Fi/2)(1 - Fo/2)``, ``f_retro = Rr (Fo + Fi + Fo Fi (Rr - 1))``, ``Rr = 2 roughness
    dot(h, wo)^2``, ``F* = (1 - cos*)^5`` ("fake subsurface" off: flatness 0).

Tangential components (``h_x^2 + h_y^2``) are computed as ``|h x n|^2``, not ``1 - h_z^2``, so a sharp peak
(roughness 0.05: alpha^2 = 6e-6) stays accurate in float32. Every division and square root is guarded so that
gradients stay finite at roughness 0, grazing angles, and ``normal == wi == wo``.
"""
from __future__ import annotations

import math

import torch

DEFAULT_SPECULAR = 0.5  # as renderers.relight.DEFAULT_SPECULAR (matcap/refine must not import renderers)
_INV_PI = 1.0 / math.pi
_TINY = 1e-12


def specular_to_eta(specular: float) -> float:
    """Mitsuba principled's relative IOR for ``specular`` (0.5 -> 1.5)."""
    return 2.0 / (1.0 - math.sqrt(0.08 * float(specular))) - 1.0


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _normalize(v: torch.Tensor) -> torch.Tensor:
    return v * torch.rsqrt((v * v).sum(-1, keepdim=True).clamp(min=_TINY))


def _cross2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|a x b|^2 (= sin^2 of the angle for unit vectors, without the cancellation of 1 - cos^2)."""
    c = torch.linalg.cross(a, b, dim=-1)
    return (c * c).sum(-1)


def _schlick_weight(c: torch.Tensor) -> torch.Tensor:
    m = (1.0 - c).clamp(0.0, 1.0)
    m2 = m * m
    return m2 * m2 * m


def _fresnel_dielectric(cos_i: torch.Tensor, eta: float) -> torch.Tensor:
    """Unpolarised Fresnel reflectance, light arriving from outside (``cos_i >= 0``) at relative IOR ``eta``."""
    cos_i = cos_i.clamp(0.0, 1.0)
    cos_t2 = 1.0 - (1.0 - cos_i * cos_i) / (eta * eta)
    cos_t = cos_t2.clamp(min=_TINY).sqrt()
    a_s = (cos_i - eta * cos_t) / (cos_i + eta * cos_t).clamp(min=_TINY)
    a_p = (cos_t - eta * cos_i) / (cos_t + eta * cos_i).clamp(min=_TINY)
    r = 0.5 * (a_s * a_s + a_p * a_p)
    if eta == 1.0:
        return torch.zeros_like(r)
    return torch.where(cos_i > 0, r, torch.ones_like(r))


def _tan2(sin2: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    return sin2 / (cos * cos).clamp(min=_TINY)


def _smith_g1(v: torch.Tensor, cos_v: torch.Tensor, sin2_v: torch.Tensor, m: torch.Tensor, alpha2: torch.Tensor):
    g = 2.0 / (1.0 + (1.0 + alpha2 * _tan2(sin2_v, cos_v)).sqrt())
    return torch.where(_dot(v, m) * cos_v > 0, g, torch.zeros_like(g))


def principled_eval(
    normal: torch.Tensor,
    wi: torch.Tensor,
    wo: torch.Tensor,
    base_color: torch.Tensor,
    roughness: torch.Tensor,
    metallic: torch.Tensor,
    specular: float = DEFAULT_SPECULAR,
) -> torch.Tensor:
    """Mitsuba's ``normalmap(principled)`` ``bsdf.eval``: BSDF value times cos(shading normal, wo).

    normal: (..., 3) shading normal in camera space (the plane's geometric normal is +z); wi: (..., 3) unit
    vector toward the viewer; wo: (..., 3) unit vector toward the light; base_color: (..., 3) linear RGB;
    roughness, metallic: (...,) in [0, 1]; all broadcast together. Returns (..., 3), zero where ``wo`` or
    ``wi`` is below the (geometric or shading) surface. Differentiable in every tensor argument.
    """
    eta = specular_to_eta(specular)
    roughness = torch.as_tensor(roughness)
    metallic = torch.as_tensor(metallic)
    normal, wi, wo, base_color = torch.broadcast_tensors(normal, wi, wo, base_color)
    roughness, metallic = torch.broadcast_tensors(roughness, metallic)
    shape = torch.broadcast_shapes(normal.shape[:-1], roughness.shape)
    normal, wi, wo, base_color = (t.expand(*shape, 3) for t in (normal, wi, wo, base_color))
    roughness, metallic = roughness.expand(shape), metallic.expand(shape)

    # normalmap: flip invalid normals, normalise, the two-sided visibility test, shadow terminator
    gi, go = wi[..., 2], wo[..., 2]
    flip = (gi * _dot(wi, normal) <= 0)[..., None]
    n = _normalize(torch.where(flip, normal * normal.new_tensor([-1.0, -1.0, 1.0]), normal))
    ci, co = _dot(wi, n), _dot(wo, n)
    sin2_i, sin2_o = _cross2(wi, n), _cross2(wo, n)
    # principled: front-side reflection only
    active = (go * co > 0) & (ci > 0) & (co > 0)

    alpha = (roughness * roughness).clamp(min=0.001)
    alpha2 = alpha * alpha
    h = _normalize(wi + wo)
    h = h * torch.where(_dot(h, n) < 0, -1.0, 1.0).to(h.dtype)[..., None]
    ch, sin2_h = _dot(h, n), _cross2(h, n)
    cih, coh = _dot(wi, h), _dot(wo, h)
    spec_active = active & (cih > 0) & (coh > 0)

    # GGX normal distribution
    denom = sin2_h / alpha2 + ch * ch
    d = 1.0 / (math.pi * alpha2 * (denom * denom).clamp(min=_TINY))
    d = torch.where(d * ch > 1e-20, d, torch.zeros_like(d))
    g = _smith_g1(wi, ci, sin2_i, h, alpha2) * _smith_g1(wo, co, sin2_o, h, alpha2)
    f_dielectric = _fresnel_dielectric(cih, eta)
    spec_active = spec_active & (f_dielectric > 0)
    w_h = _schlick_weight(cih.abs())[..., None]
    f_metal = w_h + (1.0 - w_h) * base_color
    m3 = metallic[..., None]
    fresnel = (1.0 - m3) * f_dielectric[..., None] + m3 * f_metal
    ci_safe = torch.where(active, ci, torch.ones_like(ci))
    spec = fresnel * (d * g / (4.0 * ci_safe))[..., None]
    spec = torch.where(spec_active[..., None], spec, torch.zeros_like(spec))

    # Burley diffuse with retro-reflection
    fo, fi = _schlick_weight(co.abs()), _schlick_weight(ci.abs())
    f_diff = (1.0 - 0.5 * fi) * (1.0 - 0.5 * fo)
    rr = 2.0 * roughness * coh * coh
    f_retro = rr * (fo + fi + fo * fi * (rr - 1.0))
    diff = ((1.0 - metallic) * co * _INV_PI * (f_diff + f_retro))[..., None] * base_color
    diff_active = active & (1.0 - metallic > 0)
    diff = torch.where(diff_active[..., None], diff, torch.zeros_like(diff))

    # shadow terminator (normalmap): angles to the geometric normal +z
    n_z = n[..., 2]
    tan2_n = (n[..., 0] ** 2 + n[..., 1] ** 2) / (n_z * n_z).clamp(min=_TINY)
    a2 = (0.125 * tan2_n).clamp(max=1.0)
    tan2_wo = (wo[..., 0] ** 2 + wo[..., 1] ** 2) / (go * go).clamp(min=_TINY)
    terminator = 2.0 / (1.0 + (1.0 + a2 * tan2_wo).sqrt())
    return (spec + diff) * terminator[..., None]

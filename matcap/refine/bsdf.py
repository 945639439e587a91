"""Mitsuba 3.9.1's ``normalmap(principled)`` BSDF ``eval`` in torch (differentiable, any device / dtype).

This is the surface that ``matcap relight`` renders (``renderers.relight.surface_bsdf``): a ``principled`` BSDF
with ``specular`` 0.5 and every other parameter at its default (no spec_trans, clearcoat, sheen, spec_tint,
anisotropy, flatness), wrapped in ``normalmap`` on the framing plane, whose geometric normal is +z in camera
space (camera space = the plane's tangent space: x right, y up, z toward the camera).

What Mitsuba does, step by step (``src/bsdfs/normalmap.cpp``, ``principled.cpp``, ``principledhelpers.h``,
``include/mitsuba/render/microfacet.h`` / ``fresnel.h``), and this module repeats:

normalmap (``flip_invalid_normals`` on, ``use_shadowing_function`` off: relighting turns off the shadow-terminator
darkening that Mitsuba applies to normal maps by default, since the normals stand for a surface that really turns)
  * flip: where ``wi.z * dot(wi, n) <= 0`` the shading normal becomes ``(-n.x, -n.y, n.z)``; then normalised.
  * the nested BSDF is evaluated in the perturbed frame; the result is zero unless ``wo.z * dot(wo, n) > 0``
    (``wo`` on the same side of the geometric and of the shading normal).

principled (front side only: ``bsdf = (1 - metallic) * spec_trans = 0``, so nothing reflects from the back)
  * ``eta = 2 / (1 - sqrt(0.08 specular)) - 1`` (1.5 for specular 0.5: F0 = 4 %).
  * GGX (Trowbridge-Reitz) with ``alpha = max(0.001, roughness^2)``,
    ``D(h) = 1 / (pi a^2 ((h_x^2 + h_y^2) / a^2 + h_z^2)^2)`` (Mitsuba zeroes D h_z <= 1e-20: never reached),
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


def _cross_norm2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|a x b|^2, broadcasting (torch.linalg.cross needs equal ranks)."""
    ax, ay, az = a.unbind(-1)
    bx, by, bz = b.unbind(-1)
    x, y, z = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return x * x + y * y + z * z


def _schlick_weight(c: torch.Tensor) -> torch.Tensor:
    m = (1.0 - c).clamp(0.0, 1.0)
    m2 = m * m
    return m2 * m2 * m


def _fresnel_dielectric(cos_i: torch.Tensor, eta: float) -> torch.Tensor:
    """Unpolarised Fresnel reflectance, light arriving from outside (``cos_i`` in (0, 1]) at relative IOR ``eta``."""
    if eta == 1.0:
        return torch.zeros_like(cos_i)
    cos_i = cos_i.clamp(_TINY, 1.0)
    cos_t = (1.0 - (1.0 - cos_i * cos_i) / (eta * eta)).clamp(min=_TINY).sqrt()
    a_s = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    a_p = (cos_t - eta * cos_i) / (cos_t + eta * cos_i)
    return 0.5 * (a_s * a_s + a_p * a_p)


def _smith_g1(cos_v: torch.Tensor, alpha2: torch.Tensor) -> torch.Tensor:
    """GGX Smith masking of a direction at ``cos_v`` (> 0) to the shading normal (the microfacet-side test is
    implied by the callers' masks)."""
    c2 = (cos_v * cos_v).clamp(min=_TINY)
    return 2.0 / (1.0 + (1.0 + alpha2 * ((1.0 - c2).clamp(min=0.0) / c2)).sqrt())


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

    Quantities are computed at the smallest broadcast shape they need (per pixel, per light), so a (K, 1, 3)
    light direction against (1, N, 3) maps costs little more than the (K, N) terms themselves.
    """
    eta = specular_to_eta(specular)
    roughness = torch.as_tensor(roughness, dtype=base_color.dtype, device=base_color.device)
    metallic = torch.as_tensor(metallic, dtype=base_color.dtype, device=base_color.device)

    # normalmap: flip shading normals that face away from wi, normalise
    flip = (wi[..., 2] * _dot(wi, normal) <= 0)[..., None]
    n = torch.where(flip, normal * normal.new_tensor([-1.0, -1.0, 1.0]), normal)
    n = n * torch.rsqrt((n * n).sum(-1, keepdim=True).clamp(min=_TINY))
    ci = _dot(wi, n)  # per pixel for an orthographic view
    co = _dot(wo, n)
    go = wo[..., 2]
    # principled reflects on the front side only (no spec_trans: its back side is black); normalmap needs wo
    # above both the geometric and the shading normal
    active = (go > 0) & (co > 0) & (ci > 0)

    # half vector h = (wi + wo) / |wi + wo|: dot(wi, h) = dot(wo, h) = sqrt((1 + wi.wo) / 2), per light for
    # directional lights; |h x n|^2 from the cross product keeps sharp peaks exact in float32
    s = wi + wo
    len2 = (s * s).sum(-1).clamp(min=_TINY)
    ch = (ci + co) * torch.rsqrt(len2)
    sin2_h = _cross_norm2(s, n) / len2
    c_ih = (0.5 * (1.0 + _dot(wi, wo))).clamp(min=_TINY).sqrt()

    alpha = (roughness * roughness).clamp(min=0.001)
    alpha2 = alpha * alpha
    t = sin2_h + alpha2 * ch * ch
    d = alpha2 / (math.pi * (t * t).clamp(min=_TINY))  # GGX: 1 / (pi a^2 (sin^2/a^2 + cos^2)^2)
    ci_safe = ci.clamp(min=1e-6)
    g = _smith_g1(ci_safe, alpha2) * _smith_g1(co, alpha2)
    spec = d * g / (4.0 * ci_safe)

    # Fresnel = f_s + f_m * base_color: (1 - m) dielectric + m Schlick(base_color)
    w_h = _schlick_weight(c_ih)
    f_m = metallic * (1.0 - w_h)
    f_s = (1.0 - metallic) * _fresnel_dielectric(c_ih, eta) + metallic * w_h

    # Burley diffuse with retro-reflection (flatness 0)
    fo, fi = _schlick_weight(co), _schlick_weight(ci)
    rr = 2.0 * roughness * c_ih * c_ih
    f_diffuse = (1.0 - 0.5 * fi) * (1.0 - 0.5 * fo) + rr * (fo + fi + fo * fi * (rr - 1.0))
    diffuse = (1.0 - metallic) * co.clamp(min=0.0) * _INV_PI * f_diffuse

    grey = torch.where(active, spec * f_s, 0.0)
    tint = torch.where(active, spec * f_m + diffuse, 0.0)
    return grey[..., None] + tint[..., None] * base_color

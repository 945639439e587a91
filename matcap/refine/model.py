"""The forward model of the photo-consistent fit (torch, differentiable, any device).

Camera space (x right, y up, z toward the camera); orthographic view, so the direction toward the viewer is +z
at every pixel. One photo k at pixel p::

    I_k(p) = principled_eval(n_p, +z, l_k(p), base_p, rough_p, metal_p) * E_k(p)          (the moving light)
           + (1 - metal_p) * base_p / pi * sum_j A_j L_kj Y_j(n_p)                       (order-2 SH ambient)

``l_k(p)``/``E_k(p)``: a directional light (unit direction, RGB irradiance), a point light (position on the
framing plane's world units, RGB intensity / distance^2), or a near light: a point light given by its direction and
irradiance at the object's centre and its inverse distance (0: the directional light; what the fit optimises).
The ambient term is the diffuse part of the Principled BSDF under an order-2 SH radiance (Ramamoorthi & Hanrahan
2001 irradiance; its specular part is left out).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from matcap.refine.bsdf import principled_eval

#: Real SH constants, basis order Y00, Y1-1, Y10, Y11, Y2-2, Y2-1, Y20, Y21, Y22 (lights.json order).
SH_C0, SH_C1, SH_C2, SH_C3, SH_C4 = 0.282095, 0.488603, 1.092548, 0.315392, 0.546274
#: Convolution of radiance with the clamped cosine, per band (R&H 2001): A0 = pi, A1 = 2pi/3, A2 = pi/4.
SH_A = (math.pi,) + (2.0 * math.pi / 3.0,) * 3 + (math.pi / 4.0,) * 5


def sh_basis(n: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit vectors -> (..., 9) real SH basis values."""
    x, y, z = n.unbind(-1)
    return torch.stack(
        [torch.full_like(x, SH_C0), SH_C1 * y, SH_C1 * z, SH_C1 * x, SH_C2 * x * y, SH_C2 * y * z,
         SH_C3 * (3.0 * z * z - 1.0), SH_C2 * x * z, SH_C4 * (x * x - y * y)], dim=-1)


def sh_irradiance(n: torch.Tensor, sh: torch.Tensor) -> torch.Tensor:
    """Irradiance from an SH radiance: n (N, 3), sh (K, 9, 3) -> (K, N, 3) (K may be 1)."""
    # elementwise on purpose (no BLAS): matrix products may round differently from run to run (MKL takes other
    # code paths for differently aligned buffers), and the fit must be bit-for-bit repeatable for a seed
    return _sh_sum(sh_basis(n), sh)


def plane_positions(rows: torch.Tensor, cols: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """World positions (N, 3) of pixel centres on :mod:`renderers.plane`'s framing plane (z = 0, x in [-1, 1])."""
    x = -1.0 + (cols.to(torch.float32) + 0.5) * 2.0 / width
    y = height / width - (rows.to(torch.float32) + 0.5) * 2.0 / width
    return torch.stack([x, y, torch.zeros_like(x)], dim=-1)


@dataclass
class LightParams:
    """Per-image light parameters (free tensors, optimised). K images.

    kind "directional": ``vec`` (K, 3) direction (normalised on use); "point": ``vec`` (K, 3) position; "near":
    ``vec`` (K, 3) direction from ``centre`` and ``log_intensity`` the log irradiance there, at distance
    ``1 / inv_distance`` (``inv_distance`` 0: exactly the directional light, so the fit can move a lamp in from
    infinity).
    ``log_intensity`` (K, 3): log RGB irradiance (directional) or radiant intensity (point); ``sh`` (K, 9, 3), or
    (1, 9, 3) for one ambient shared by every photo.
    """

    kind: str
    vec: torch.Tensor
    log_intensity: torch.Tensor
    sh: torch.Tensor
    inv_distance: torch.Tensor | None = None  # "near": (K,) 1 / distance from ``centre`` (0: a distant light)
    centre: torch.Tensor | None = None  # "near": (3,) the point the directions and irradiances refer to

    def tensors(self) -> list[torch.Tensor]:
        return [self.vec, self.log_intensity, self.sh] + ([self.inv_distance] if self.kind == "near" else [])

    def detached(self) -> "LightParams":
        """A copy of these lights (their own tensors) that carries no gradient."""
        return LightParams(self.kind, *(t.detach().clone() for t in self.tensors()[:3]),
                           None if self.inv_distance is None else self.inv_distance.detach().clone(), self.centre)

    def directions(self) -> torch.Tensor:
        return self.vec / self.vec.norm(dim=-1, keepdim=True).clamp(min=1e-8)

    def incident(self, pos: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(wo (K, N|1, 3), irradiance (K, N|1, 3)) at plane positions ``pos`` (N, 3) (point lights need them)."""
        inten = self.log_intensity.exp()
        if self.kind == "directional":
            return self.directions()[:, None, :], inten[:, None, :]
        if self.kind == "near":  # light at centre + direction / u; irradiance at the centre = inten
            u = self.inv_distance.clamp(min=0.0)[:, None, None]
            q = self.directions()[:, None, :] - u * (pos - self.centre)[None]
            r2 = (q * q).sum(-1, keepdim=True).clamp(min=1e-6)
            return q / r2.sqrt(), inten[:, None, :] / r2
        d = self.vec[:, None, :] - pos[None, :, :]
        r2 = (d * d).sum(-1, keepdim=True).clamp(min=1e-6)
        return d / r2.sqrt(), inten[:, None, :] / r2


@dataclass
class PixelParams:
    """Per-pixel parameters (free tensors) of N pixels: normal as a gradient (n = normalise(a, b, 1), so it always
    faces the camera), base colour / roughness / metallic as logits."""

    grad: torch.Tensor  # (N, 2)
    base_logit: torch.Tensor  # (N, 3)
    rough_logit: torch.Tensor  # (N,)
    metal_logit: torch.Tensor  # (N,)

    def tensors(self) -> list[torch.Tensor]:
        return [self.grad, self.base_logit, self.rough_logit, self.metal_logit]

    def normal(self) -> torch.Tensor:
        n = torch.cat([self.grad, torch.ones_like(self.grad[:, :1])], dim=-1)
        return n / n.norm(dim=-1, keepdim=True)

    def base(self) -> torch.Tensor:
        return torch.sigmoid(self.base_logit)

    def rough(self) -> torch.Tensor:
        return torch.sigmoid(self.rough_logit)

    def metal(self) -> torch.Tensor:
        return torch.sigmoid(self.metal_logit)

    @staticmethod
    def from_maps(normal, base, rough, metal, min_nz: float = 0.08) -> "PixelParams":
        """From map values (N, 3), (N, 3), (N,), (N,) (torch); values are clipped away from 0 / 1."""
        nz = normal[:, 2:3].clamp(min=min_nz)
        grad = normal[:, :2] / nz
        lim = 1.0 / min_nz
        grad = grad.clamp(-lim, lim)
        return PixelParams(grad.clone(), _logit(base.clamp(0.01, 0.99)), _logit(rough.clamp(0.03, 0.97)),
                           _logit(metal.clamp(0.02, 0.98)))

    def take(self, idx: torch.Tensor) -> "PixelParams":
        return PixelParams(*(t[idx].detach().clone() for t in self.tensors()))


def _logit(x: torch.Tensor) -> torch.Tensor:
    return torch.log(x) - torch.log1p(-x)


def shade(normal, base, rough, metal, wo, irradiance, sh) -> torch.Tensor:
    """Predicted radiance (K, N, 3) of N pixels in K images.

    normal (N, 3) unit; base (N, 3); rough, metal (N,); wo / irradiance (K, N|1, 3); sh (K, 9, 3).
    """
    view = torch.zeros_like(normal)
    view[:, 2] = 1.0
    f = principled_eval(normal[None], view[None], wo.expand(-1, normal.shape[0], -1), base[None], rough[None],
                        metal[None])
    direct = f * irradiance
    ambient = sh_irradiance(normal, sh) * ((1.0 - metal)[:, None] * base / math.pi)[None]
    return direct + ambient


def _dots(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(K, M, 3) x (N, 3) -> (K, N) dot products (M = 1 or N), elementwise (repeatable, unlike BLAS; see
    :func:`sh_irradiance`)."""
    b = b[None]
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def shade_directional(normal, base, rough, metal, directions, irradiance, sh, specular: float = 0.5) -> torch.Tensor:
    """:func:`shade` for directional lights: :func:`shade_fast` with directions (K, 3) unit and irradiance (K, 3)."""
    return shade_fast(normal, base, rough, metal, directions[:, None, :], irradiance[:, None, :], sh, specular)


def shade_fast(normal, base, rough, metal, wo, irradiance, sh, specular: float = 0.5) -> torch.Tensor:
    """:func:`shade` seen along +z for normals facing the camera (n_z > 0, so normalmap never flips them), with
    everything that depends only on the light (half vector, Fresnel of the dielectric) computed at the light's own
    shape: the same numbers as ``principled_eval``
    (tests/test_refine_model.py) at about a third of the work for directional lights.

    normal (N, 3) unit; base (N, 3); rough, metal (N,); wo / irradiance (K, N|1, 3); sh (K|1, 9, 3).
    """
    return _shade_terms(normal, base, rough, metal, wo, irradiance, sh, specular, None)[0]


def shade_base_linear(normal, rough, metal, wo, irradiance, sh, specular: float = 0.5):
    """:func:`shade_fast` as ``const + base * per_base``: it is linear in the base colour at a fixed normal,
    roughness and metallic. Shapes as :func:`shade_fast` (no ``base``); returns (const, per_base), each (K, N, 3)."""
    return _shade_terms(normal, None, rough, metal, wo, irradiance, sh, specular, None)


def shade_jacobian(normal, base, rough, metal, wo, irradiance, sh, tangents, specular: float = 0.5):
    """:func:`shade_fast` and its derivatives, in closed form (the per-pixel solve's Jacobian).

    tangents (T, N, 3): directions in which the normal moves (e.g. the derivatives of a unit normal by its free
    parameters). Returns (pred (K, N, 3), d_normal (T, K, N, 3): pred's derivative along each tangent, d_base
    (K, N, 3): channel c's derivative by base colour c (the others' is 0), d_rough (K, N, 3), d_metal (K, N, 3)).
    """
    return _shade_terms(normal, base, rough, metal, wo, irradiance, sh, specular, tangents)


def _schlick_d(c: torch.Tensor) -> torch.Tensor:
    """Derivative of ``bsdf._schlick_weight`` (c in [0, 1])."""
    m = (1.0 - c).clamp(0.0, 1.0)
    m2 = m * m
    return -5.0 * m2 * m2


def _sh_basis_d(n: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Derivative of :func:`sh_basis` at unit vectors n (..., 3) along t (..., 3) -> (..., 9)."""
    x, y, z = n.unbind(-1)
    tx, ty, tz = t.unbind(-1)
    return torch.stack(
        [torch.zeros_like(tx), SH_C1 * ty, SH_C1 * tz, SH_C1 * tx, SH_C2 * (tx * y + x * ty),
         SH_C2 * (ty * z + y * tz), SH_C3 * 6.0 * z * tz, SH_C2 * (tx * z + x * tz),
         SH_C4 * 2.0 * (x * tx - y * ty)], dim=-1)


def _sh_sum(basis: torch.Tensor, sh: torch.Tensor) -> torch.Tensor:
    """sum_j A_j sh_j basis_j: basis (..., N, 9), sh (K, 9, 3) -> (..., K, N, 3), elementwise (see
    :func:`sh_irradiance`)."""
    out = None
    for j in range(9):
        term = basis[..., None, :, j, None] * (SH_A[j] * sh[:, j])[:, None, :]
        out = term if out is None else out + term
    return out


def _shade_terms(normal, base, rough, metal, wo, irradiance, sh, specular, tangents):
    from matcap.refine import bsdf as B

    eta = 2.0 / (1.0 - math.sqrt(0.08 * specular)) - 1.0
    l = wo  # (K, M, 3), M = 1 (directional) or N
    h = l + torch.tensor([0.0, 0.0, 1.0], dtype=l.dtype, device=l.device)
    h = h / h.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    cos_d = (h * l).sum(-1).clamp(0.0, 1.0)  # (K, M)
    w_d = B._schlick_weight(cos_d)
    f_die = B._fresnel_dielectric(cos_d, eta)
    # per pixel
    ci = normal[:, 2].clamp(min=1e-6)
    fi = B._schlick_weight(ci)
    alpha = (rough * rough).clamp(min=1e-3)
    a2 = alpha * alpha
    tan2_i = (1.0 - ci * ci) / (ci * ci)
    sq_i = (1.0 + a2 * tan2_i).sqrt()
    g_i = 2.0 / (1.0 + sq_i)
    # per photo and pixel (K, N)
    co_raw = _dots(l, normal)
    ch_raw = _dots(h, normal)
    co = co_raw.clamp(min=1e-6)
    ch = ch_raw.clamp(min=1e-6)
    fo = B._schlick_weight(co)
    rr = 2.0 * rough[None] * (cos_d * cos_d)
    diff_shape = (1.0 - 0.5 * fi)[None] * (1.0 - 0.5 * fo) + rr * (fo + fi[None] + fo * fi[None] * (rr - 1.0))
    dielectric = ((1.0 - metal) / math.pi)[None]
    diff = diff_shape * co * dielectric
    denom = ch * ch * (a2[None] - 1.0) + 1.0
    d = a2[None] / (math.pi * denom * denom)
    tan2_o = (1.0 - co * co) / (co * co)
    sq_o = (1.0 + a2[None] * tan2_o).sqrt()
    g_o = 2.0 / (1.0 + sq_o)
    gi4 = (g_i / (4.0 * ci))[None]
    spec = d * gi4 * g_o
    valid = (co_raw > 1e-6) & (ch_raw > 0) & (normal[:, 2] > 1e-6)[None] & (l[..., 2] > 0)
    zero = torch.zeros((), dtype=co.dtype, device=co.device)
    diff_b = torch.where(valid, diff, zero)
    spec_b = torch.where(valid, spec, zero)
    if base is None:  # shade_base_linear: the model's two parts, constant and proportional to the base colour
        basis = sh_basis(normal)
        sh_e = _sh_sum(basis, sh)
        mw = metal[None] * w_d
        const = (spec_b * ((1.0 - metal)[None] * f_die + mw))[..., None] * irradiance
        per_base = (diff_b + spec_b * (metal[None] - mw))[..., None] * irradiance
        return const, per_base + sh_e * ((1.0 - metal) / math.pi)[None, :, None]
    # colour: diffuse * base + spec * F, F = (1 - m) F_dielectric + m Schlick(base)
    fres = ((1.0 - metal)[None] * f_die)[..., None] + metal[None, :, None] * (
        base[None] + (1.0 - base)[None] * w_d[..., None])
    irr = irradiance
    direct = (diff_b[..., None] * base[None] + spec_b[..., None] * fres) * irr
    basis = sh_basis(normal)
    sh_e = _sh_sum(basis, sh)  # (K|1, N, 3)
    albedo = (1.0 - metal)[:, None] * base / math.pi
    pred = direct + sh_e * albedo[None]
    if tangents is None:
        return pred, None, None, None, None

    # d/d base colour (channel by channel) and d/d metallic
    metal_w = metal[None, :, None] * w_d[..., None]
    d_base = (diff_b[..., None] + spec_b[..., None] * (metal[None, :, None] - metal_w)) * irr
    d_base = d_base + sh_e * ((1.0 - metal) / math.pi)[None, :, None]
    diff_nom = torch.where(valid, diff_shape * co / math.pi, zero)  # diffuse without the (1 - m) factor
    d_fres_m = (base[None] + (1.0 - base)[None] * w_d[..., None]) - f_die[..., None]
    d_metal = (spec_b[..., None] * d_fres_m - diff_nom[..., None] * base[None]) * irr - sh_e * (base / math.pi)[None]

    # d/d roughness: through alpha^2 (D, G) and the retro-reflection's Rr
    dalpha = torch.where(rough * rough > 1e-3, 2.0 * rough, zero)
    da2 = (2.0 * alpha * dalpha)[None]
    drr = 2.0 * (cos_d * cos_d)
    d_diff_shape_rr = fo + fi[None] + fo * fi[None] * (2.0 * rr - 1.0)
    ddiff_r = drr * d_diff_shape_rr * co * dielectric
    dd_r = d * (da2 / a2[None] - 2.0 * ch * ch * da2 / denom)
    dgi_r = -0.25 * g_i[None] * g_i[None] * tan2_i[None] * da2 / sq_i[None]
    dgo_r = -0.25 * g_o * g_o * tan2_o * da2 / sq_o
    dspec_r = dd_r * gi4 * g_o + d * (dgi_r / (4.0 * ci)[None]) * g_o + d * gi4 * dgo_r
    ddiff_r = torch.where(valid, ddiff_r, zero)
    dspec_r = torch.where(valid, dspec_r, zero)
    base_irr, fres_irr = base[None] * irr, fres * irr  # (K, N, 3): what the diffuse and specular terms scale
    d_rough = torch.addcmul(ddiff_r[..., None] * base_irr, dspec_r[..., None], fres_irr)

    # d/d normal along each tangent (T, K, N): the model depends on the normal through ci = n_z, co = l.n, ch = h.n
    # and the ambient's SH basis; the diffuse and specular terms' partial derivatives by ci, co and ch are (K, N)
    # coefficients of the tangents' (T, K, N) changes of them
    t = tangents
    dci = t[..., 2][:, None]  # (T, 1, N)
    dco = _dots_t(l, t)
    dch = _dots_t(h, t)
    s_fi = _schlick_d(ci)[None]  # (1, N): d fi / d ci
    s_fo = _schlick_d(co)  # d fo / d co
    shape_fi = -0.5 * (1.0 - 0.5 * fo) + rr * (1.0 + fo * (rr - 1.0))  # d diff_shape / d fi
    shape_fo = -0.5 * (1.0 - 0.5 * fi)[None] + rr * (1.0 + fi[None] * (rr - 1.0))  # d diff_shape / d fo
    q_i = (-2.0 / (ci * ci * ci))[None]  # d tan2_i / d ci
    gi4_ci = (-0.25 * g_i * g_i * a2 / sq_i / (4.0 * ci))[None] * q_i - gi4 / ci[None]  # d gi4 / d ci
    go_co = -0.25 * g_o * g_o * a2[None] * (-2.0 / (co * co * co)) / sq_o  # d g_o / d co
    dd_ch = -4.0 * d * ch * (a2[None] - 1.0) / denom  # d D / d ch
    diff_co = torch.where(valid, (s_fo * shape_fo * co + diff_shape) * dielectric, zero)
    diff_ci = torch.where(valid, s_fi * shape_fi * co * dielectric, zero)
    spec_co = torch.where(valid, d * gi4 * go_co, zero)
    spec_ci = torch.where(valid, d * gi4_ci * g_o, zero)
    spec_ch = torch.where(valid & (ch_raw > 1e-6), dd_ch * gi4 * g_o, zero)
    ddiff = diff_co * dco + diff_ci * dci  # (T, K, N)
    dspec = spec_co * dco + spec_ci * dci + spec_ch * dch
    d_sh = _sh_sum(_sh_basis_d(normal[None], t), sh)  # (T, K|1, N, 3)
    d_normal = torch.addcmul(ddiff[..., None] * base_irr, dspec[..., None], fres_irr) + d_sh * albedo[None]
    return pred, d_normal, d_base, d_rough, d_metal


def _dots_t(a: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(K, M, 3) x (T, N, 3) -> (T, K, N) dot products, elementwise."""
    a = a[None]
    t = t[:, None]
    return a[..., 0] * t[..., 0] + a[..., 1] * t[..., 1] + a[..., 2] * t[..., 2]

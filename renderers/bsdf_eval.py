"""Evaluate the relight surface BSDF (``renderers.relight.surface_bsdf``) point-wise with Mitsuba's ``bsdf.eval``.

Reference for ``matcap.refine.bsdf`` (its torch twin): each sample i gets its own texel of a 1 x N set of
material maps, built by the very function relighting uses, and is evaluated at that texel's centre on the
framing plane (shading frame = camera space: s = +x, t = +y, n = +z).
"""
from __future__ import annotations

import numpy as np

from scenes.materialmaps import MaterialMaps


def surface_bsdf_dict(normal, base_color, roughness, metallic, specular: float | None = None) -> dict:
    """The ``normalmap(principled)`` dict of ``renderers.relight.surface_bsdf`` for N samples laid out as a
    1 x N texture: normal (N, 3) camera space, base_color (N, 3) linear, roughness / metallic (N,).
    The maps go through ``prepare_maps`` as in relighting (normals with z < 0 are clamped to z = 0)."""
    from renderers.relight import DEFAULT_SPECULAR, prepare_maps, surface_bsdf

    normal = np.asarray(normal, dtype=np.float32).reshape(1, -1, 3)
    n = normal.shape[1]
    maps = MaterialMaps(
        normal=normal,
        mask=np.ones((1, n), dtype=bool),
        base_color=np.asarray(base_color, dtype=np.float32).reshape(1, n, 3),
        roughness=np.asarray(roughness, dtype=np.float32).reshape(1, n),
        metallic=np.asarray(metallic, dtype=np.float32).reshape(1, n),
    )
    return surface_bsdf(prepare_maps(maps), DEFAULT_SPECULAR if specular is None else float(specular))


def eval_surface_bsdf(
    normal, wi, wo, base_color, roughness, metallic, specular: float | None = None, variant: str | None = None
) -> np.ndarray:
    """Mitsuba's ``bsdf.eval`` (BSDF times cosine) of the relight surface: (N, 3) float32.

    normal, wi (toward the viewer), wo (toward the light): (N, 3) camera space; base_color (N, 3); roughness,
    metallic (N,). ``variant``: a Mitsuba variant to use (default: ``renderers.variant.choose_variant()``);
    scalar variants loop over the samples in Python, vectorised ones evaluate them at once.
    """
    import mitsuba as mi

    from renderers.variant import choose_variant

    chosen = choose_variant()
    variant = variant or chosen
    previous = mi.variant()
    mi.set_variant(variant)
    try:
        return _eval(mi, variant, normal, wi, wo, base_color, roughness, metallic, specular)
    finally:
        if previous and previous != variant:
            mi.set_variant(previous)


def _eval(mi, variant, normal, wi, wo, base_color, roughness, metallic, specular) -> np.ndarray:
    wi = np.asarray(wi, dtype=np.float32).reshape(-1, 3)
    wo = np.asarray(wo, dtype=np.float32).reshape(-1, 3)
    n = wi.shape[0]
    bsdf = mi.load_dict(surface_bsdf_dict(normal, base_color, roughness, metallic, specular))
    ctx = mi.BSDFContext()
    u = ((np.arange(n) + 0.5) / n).astype(np.float32)
    if variant.startswith("scalar"):
        out = np.zeros((n, 3), dtype=np.float32)
        for i in range(n):
            si = mi.SurfaceInteraction3f()
            si.p = mi.Point3f(0.0, 0.0, 0.0)
            si.n = mi.Normal3f(0.0, 0.0, 1.0)
            si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
            si.uv = mi.Point2f(float(u[i]), 0.5)
            si.wi = mi.Vector3f(*(float(x) for x in wi[i]))
            value = bsdf.eval(ctx, si, mi.Vector3f(*(float(x) for x in wo[i])))
            out[i] = np.array(value, dtype=np.float32).reshape(-1)[:3]
        return out
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.uv = mi.Point2f(mi.Float(u), mi.Float(np.full(n, 0.5, dtype=np.float32)))
    si.wi = mi.Vector3f(mi.Float(wi[:, 0]), mi.Float(wi[:, 1]), mi.Float(wi[:, 2]))
    wo_v = mi.Vector3f(mi.Float(wo[:, 0]), mi.Float(wo[:, 1]), mi.Float(wo[:, 2]))
    value = bsdf.eval(ctx, si, wo_v)
    return np.stack([np.array(value[c], dtype=np.float32) for c in range(3)], axis=-1)

"""From a :class:`~scenes.synth_spec.SceneSpec` (plus loaded asset arrays) to renderable numpy data, and the
post-render ground-truth fix-ups and validity checks. numpy only.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenes import procedural as P
from scenes.synth_spec import MaterialSpec, ObjectSpec, SceneSpec, TextureSpec

TEXTURE_SIZE = 256


@dataclass
class RenderObject:
    """One shape ready for a renderer: world-space geometry and its SVBRDF texture maps (linear, in [0, 1])."""

    geometry: P.Geometry
    base_color: np.ndarray  # (S, S, 3)
    roughness: np.ndarray  # (S, S)
    metallic: np.ndarray  # (S, S)
    specular: float
    uv_scale: float
    is_background: bool = False
    normal_map: np.ndarray | None = None  # (S, S, 3) tangent-space normals encoded (n + 1) / 2, OpenGL (+y = +v)


def normalise_mesh(vertices: np.ndarray) -> np.ndarray:
    """Centre a mesh on its bounding-box centre and scale it into the unit ball."""
    v = np.asarray(vertices, np.float64)
    v = v - (v.min(0) + v.max(0)) / 2
    return (v / max(np.linalg.norm(v, axis=1).max(), 1e-12)).astype(np.float32)


def object_geometry(obj: ObjectSpec, mesh: P.Geometry | None = None) -> P.Geometry:
    """World-space geometry of an object (``mesh``: the normalised asset mesh for ``shape == "mesh"``)."""
    p = obj.params
    if obj.shape == "sphere":
        g = P.make_sphere()
    elif obj.shape == "box":
        g = P.make_box((p["ex"], p["ey"], p["ez"]))
    elif obj.shape == "torus":
        g = P.make_torus(p["minor"])
    elif obj.shape == "superquadric":
        g = P.make_superquadric(p["e1"], p["e2"])
    elif obj.shape == "bumpy_sphere":
        g = P.make_bumpy_sphere(p["amplitude"], int(p["seed"]))
    elif obj.shape == "bumpy_torus":
        g = P.make_bumpy_torus(p["minor"], p["amplitude"], int(p["seed"]))
    elif obj.shape == "backdrop":
        g = P.make_backdrop(p["size"], p["bump"], int(p["seed"]))
    elif obj.shape == "mesh":
        if mesh is None:
            raise ValueError(f"object needs mesh {obj.mesh!r}")
        g = mesh
    else:
        raise ValueError(f"unknown shape {obj.shape!r}")
    if p.get("disp_amp"):
        g = displace(g, p["disp_amp"], int(p["disp_seed"]), p["disp_freq"])
    return g.transformed(np.asarray(obj.rotation), obj.scale, obj.position)


def _sample(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear, wrapped lookup of an (S, S) map at (N, 2) uv (row 0 at v = 0)."""
    s = tex.shape[0]
    x, y = (uv[:, 0] % 1.0) * s - 0.5, (uv[:, 1] % 1.0) * s - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    x0, y0, x1, y1 = x0 % s, y0 % s, (x0 + 1) % s, (y0 + 1) % s
    return (tex[y0, x0] * (1 - fx) * (1 - fy) + tex[y0, x1] * fx * (1 - fy) + tex[y1, x0] * (1 - fx) * fy
            + tex[y1, x1] * fx * fy)


def displace(g: P.Geometry, amplitude: float, seed: int, freq: float) -> P.Geometry:
    """Data v2 relief: vertices moved along their normals by ``amplitude`` x a smooth noise height (in [-0.5, 0.5]
    of the unit-ball object) looked up at their uv; normals recomputed from the displaced surface."""
    if g.normals is None:
        g = P.Geometry(g.vertices, g.faces, P.smooth_normals(g.vertices, g.faces), g.uv)
    h = P.pattern("noise", seed, 128, freq, 0.0)
    d = (_sample(h, np.asarray(g.uv, np.float64)) - 0.5) * amplitude
    v = (g.vertices + g.normals * d[:, None]).astype(np.float32)
    return P.Geometry(v, g.faces, P.smooth_normals(v, g.faces), g.uv)


def normal_map(mat: MaterialSpec, pbr_sets: dict | None = None, size: int = TEXTURE_SIZE) -> np.ndarray | None:
    """(S, S, 3) tangent-space normal map of a material, encoded (n + 1) / 2 (OpenGL: +y along +v), or None.

    A PBR set's ``normal`` map, or the relief of a procedural pattern taken as a height field; tangent x and y
    are scaled by ``normal_strength`` and the normal renormalised."""
    tex = mat.normal_tex
    if tex is None:
        return None
    if tex.pattern == "pbr":
        sets = pbr_sets or {}
        if tex.pbr_set not in sets or sets[tex.pbr_set].get("normal") is None:
            raise ValueError(f"texture set {tex.pbr_set!r} has no normal map loaded")
        n = np.asarray(sets[tex.pbr_set]["normal"], np.float32) * 2 - 1
        if n.shape[0] != size:
            n = n[:: max(1, n.shape[0] // size), :: max(1, n.shape[1] // size)][:size, :size]
    else:
        h = P.pattern(tex.pattern, tex.seed, size, tex.freq, tex.angle).astype(np.float64)
        k = 0.6 * size / (2 * np.pi * max(tex.freq, 1.0))  # slope scale: relief of about one texel per cycle
        du = (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1)) / 2  # along u (columns)
        dv = (np.roll(h, -1, axis=0) - np.roll(h, 1, axis=0)) / 2  # along v (rows, row 0 at v = 0)
        n = np.stack([-du * k, -dv * k, np.ones_like(h)], -1)
    n = np.asarray(n, np.float64).copy()
    n[..., :2] *= mat.normal_strength
    n[..., 2] = np.maximum(n[..., 2], 0.05)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return ((n + 1) / 2).astype(np.float32)


def _texture(tex: TextureSpec, pbr_sets: dict, want: str, size: int) -> np.ndarray:
    if tex.pattern != "pbr":
        return P.pattern(tex.pattern, tex.seed, size, tex.freq, tex.angle)
    if tex.pbr_set not in pbr_sets:
        raise ValueError(f"texture set {tex.pbr_set!r} not loaded")
    s = pbr_sets[tex.pbr_set]
    if want == "color":
        return np.asarray(s["basecolor"], np.float32)
    r = s.get("roughness")
    if r is None:  # no roughness map: use the colour's luminance as a pattern
        r = np.asarray(s["basecolor"], np.float32) @ np.float32([0.2126, 0.7152, 0.0722])
    r = np.asarray(r, np.float32)
    return (r - r.min()) / max(float(r.max() - r.min()), 1e-6)


def material_maps(mat: MaterialSpec, pbr_sets: dict | None = None, size: int = TEXTURE_SIZE):
    """(base_color (S,S,3), roughness (S,S), metallic (S,S)) linear maps of a material."""
    pbr_sets = pbr_sets or {}
    a, b = np.float32(mat.color_a), np.float32(mat.color_b)
    if mat.color_tex is None:
        base = np.broadcast_to(a, (size, size, 3))
    elif mat.color_tex.pattern == "pbr":
        base = _texture(mat.color_tex, pbr_sets, "color", size) * a
    else:
        t = _texture(mat.color_tex, pbr_sets, "color", size)[..., None]
        base = a * (1 - t) + b * t

    def scalar(rng_pair, tex):
        lo, hi = rng_pair
        if tex is None:
            return np.full((size, size), hi, np.float32)
        t = _texture(tex, pbr_sets, "scalar", size)
        if t.shape != (size, size):
            t = t[:: max(1, t.shape[0] // size), :: max(1, t.shape[1] // size)][:size, :size]
        return lo + (hi - lo) * t

    rough = scalar(mat.roughness, mat.roughness_tex)
    metal = scalar(mat.metallic, mat.metallic_tex)
    return (np.clip(base, 0, 1).astype(np.float32), np.clip(rough, 0.02, 1).astype(np.float32),
            np.clip(metal, 0, 1).astype(np.float32))


def build_render_objects(spec: SceneSpec, meshes: dict | None = None, pbr_sets: dict | None = None) -> list[RenderObject]:
    """Everything a renderer needs about the shapes of a scene (background last)."""
    meshes = meshes or {}
    out = []
    items = [(o, False) for o in spec.objects] + ([(spec.background, True)] if spec.background else [])
    for obj, bg in items:
        g = object_geometry(obj, meshes.get(obj.mesh) if obj.shape == "mesh" else None)
        base, rough, metal = material_maps(obj.material, pbr_sets)
        out.append(RenderObject(g, base, rough, metal, obj.material.specular, obj.material.uv_scale, bg,
                                normal_map(obj.material, pbr_sets)))
    return out


# ----------------------------------------------------------------------------------------------- ground truth


def finalize_normals(sh_normal: np.ndarray, geo_normal: np.ndarray, hit: np.ndarray):
    """Camera-facing unit normals from raw shading/geometric normals (world = camera space).

    Back faces (geometric normal pointing away, e.g. inside an open mesh; shaded two-sided) are flipped; shading
    normals that still point slightly away (interpolation at silhouettes) get z clamped to 0 and are
    renormalised. Returns (normal, stats) with zeros outside ``hit``.
    """
    n = np.asarray(sh_normal, np.float32).copy()
    g = np.asarray(geo_normal, np.float32)
    hit = np.asarray(hit, bool)
    back = hit & (g[..., 2] < 0)
    n[back] *= -1
    neg = hit & (n[..., 2] < 0)
    n[..., 2] = np.where(neg, 0.0, n[..., 2])
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(norm > 1e-6, n / np.maximum(norm, 1e-6), np.float32([0, 0, 1]))
    n[~hit] = 0
    count = max(int(hit.sum()), 1)
    return n.astype(np.float32), {"back_face_fraction": float(back.sum()) / count,
                                  "clamped_fraction": float(neg.sum()) / count}


def auto_exposure(image: np.ndarray, mask: np.ndarray, target: float = 0.85, percentile: float = 99.0) -> float:
    """Scale so that the given percentile of the brightest channel (over the mask, or all pixels) maps to target."""
    m = image.max(axis=-1)
    vals = m[mask] if mask.sum() > 16 else m.ravel()
    ref = float(np.percentile(vals, percentile)) if vals.size else 0.0
    return target / ref if ref > 1e-8 else 1.0


def dilate(mask: np.ndarray, radius: int = 1) -> np.ndarray:
    """Binary dilation by a (2r+1)^2 square (numpy only)."""
    m = np.asarray(mask, bool)
    out = m.copy()
    h, w = m.shape
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            ys, yd = slice(max(dy, 0), h + min(dy, 0)), slice(max(-dy, 0), h + min(-dy, 0))
            xs, xd = slice(max(dx, 0), w + min(dx, 0)), slice(max(-dx, 0), w + min(-dx, 0))
            out[yd, xd] |= m[ys, xs]
    return out


SPOT_CONFIGS = "fh"  # images lit mostly by a narrow spot: most of the view may stay dark by design


def check_scene(images: np.ndarray, normal: np.ndarray, mask: np.ndarray, object_mask: np.ndarray,
                raw_images: np.ndarray | None = None, configs: list[str] | None = None,
                stats: dict | None = None, mask_agreement: float = 1.0) -> list[str]:
    """Validity checks of a rendered scene; returns a list of problems (empty = valid).

    images: (N,H,W,3) exposed images in [0,1]; normal (H,W,3); mask (H,W) foreground incl. background surface;
    object_mask (H,W) objects only; raw_images (N,H,W,3) linear before exposure (for the geometry check);
    configs: per image configuration letters; stats: from :func:`finalize_normals`; mask_agreement: fraction of
    pixels where the separately rendered ground-truth passes agree on the mask.
    """
    problems = []
    _h, _w = mask.shape
    if not np.isfinite(images).all() or not np.isfinite(normal).all():
        problems.append("non-finite pixels")
        return problems
    if object_mask.mean() < 0.02:
        problems.append(f"objects cover only {object_mask.mean():.3%} of the image")
    if (object_mask & ~mask).any():
        problems.append("object pixels outside the mask")
    nn = np.linalg.norm(normal, axis=-1)
    if mask.any():
        bad_len = np.abs(nn[mask] - 1) > 1e-3
        if bad_len.mean() > 1e-3:
            problems.append(f"{bad_len.mean():.2%} of normals are not unit length")
        if (normal[..., 2][mask] < -1e-6).any():
            problems.append("normals facing away from the camera")
    if (nn[~mask] > 0).any():
        problems.append("non-zero normals outside the mask")
    if stats and stats.get("back_face_fraction", 0) > 0.25:
        problems.append(f"{stats['back_face_fraction']:.0%} of visible surface is back faces (broken geometry)")
    if stats and stats.get("clamped_fraction", 0) > 0.05:
        problems.append(f"{stats['clamped_fraction']:.0%} of normals point away before clamping")
    if mask_agreement < 0.995:
        problems.append(f"ground-truth passes disagree on {1 - mask_agreement:.2%} of the mask")
    for k, img in enumerate(images):
        fg = img[mask] if mask.any() else img.reshape(-1, 3)
        lum = fg.mean(axis=-1)
        spot = configs is not None and configs[k] in SPOT_CONFIGS
        if (lum.mean() < (0.005 if spot else 0.02)) or (lum > 0.01).mean() < (0.03 if spot else 0.2):
            problems.append(f"image {k} is (nearly) black")
        if (fg >= 1.0).any(axis=-1).mean() > 0.05:
            problems.append(f"image {k} is saturated ({(fg >= 1.0).any(axis=-1).mean():.0%} of pixels)")
    grown = dilate(mask, 1)  # images are antialiased: pixels next to the mask may be partly covered
    if raw_images is not None and configs is not None and (~grown).any():
        # Geometry check: without an environment map, nothing outside the mask may receive or emit light.
        for k, (raw, cfg) in enumerate(zip(raw_images, configs)):
            if cfg in "bcfg":  # (m may have an environment map as its fixed light: not checked)
                outside = raw[~grown].max()
                inside = max(float(np.percentile(raw[mask].max(-1), 99)), 1e-8) if mask.any() else 1.0
                if outside > 1e-3 * inside:
                    problems.append(f"image {k}: light outside the mask (mask misses geometry)")
                    break
    return problems

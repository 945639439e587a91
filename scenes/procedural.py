"""Procedural geometry, textures and skies for synthetic scenes (numpy only, deterministic from explicit seeds).

Geometry is returned as :class:`Geometry` (float32 vertices/normals/uv, int32 faces) in the object's own frame,
roughly inside the unit ball. Textures are (S, S) float32 arrays in [0, 1]. Skies are equirectangular
(H, 2H, 3) float32 radiance maps in Mitsuba's convention (row 0 = +y, up).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Geometry:
    """A triangle mesh. ``normals`` None means flat shading (face normals)."""

    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int32
    normals: np.ndarray | None  # (V, 3) float32 or None
    uv: np.ndarray  # (V, 2) float32

    def transformed(self, rotation: np.ndarray, scale: float, translation) -> Geometry:
        r = np.asarray(rotation, np.float64).reshape(3, 3)
        v = (self.vertices.astype(np.float64) * float(scale)) @ r.T + np.asarray(translation, np.float64)
        n = None if self.normals is None else (self.normals.astype(np.float64) @ r.T)
        if n is not None:
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return Geometry(v.astype(np.float32), self.faces, None if n is None else n.astype(np.float32), self.uv)


# ----------------------------------------------------------------------------------------------- geometry helpers


def smooth_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, averaged over vertices that share a position (closes UV seams)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], fn)
    key = np.round(v / (np.abs(v).max() + 1e-12) * 1e6).astype(np.int64)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    welded = np.zeros((inverse.max() + 1, 3))
    np.add.at(welded, inverse, acc)
    n = welded[inverse]
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(norm > 1e-20, n / np.maximum(norm, 1e-20), np.array([0.0, 0.0, 1.0]))
    return n.astype(np.float32)


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def _grid(points: np.ndarray, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate a (nv+1, nu+1, 3) grid of points; returns vertices, faces, uv."""
    ii, jj = np.meshgrid(np.arange(nv), np.arange(nu), indexing="ij")
    a = (ii * (nu + 1) + jj).ravel()
    b, c, d = a + 1, a + nu + 1, a + nu + 2
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)]).astype(np.int32)
    u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1))
    uv = np.stack([u.ravel(), 1.0 - v.ravel()], 1).astype(np.float32)
    return points.reshape(-1, 3).astype(np.float32), faces, uv


def _outward(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    return f[:, ::-1].copy() if signed_volume(v, f) < 0 else f


def _parametric(fn, nu: int, nv: int) -> Geometry:
    u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1))
    verts, faces, uv = _grid(fn(u, v), nu, nv)
    faces = _outward(verts, faces)
    return Geometry(verts, faces, smooth_normals(verts, faces), uv)


def _sphere_points(u, v):
    th, ph = v * np.pi, u * 2 * np.pi
    return np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1)


def _displace(points: np.ndarray, normals_fn, amplitude: float, seed: int, waves: int = 12) -> np.ndarray:
    """Displace points along normals by a sum of random 3-D sinusoids (smooth, band-limited bumps)."""
    rng = np.random.default_rng(seed)
    p = points.reshape(-1, 3)
    h = np.zeros(len(p))
    for k in range(waves):
        freq = rng.normal(size=3)
        freq *= rng.uniform(2.0, 9.0) / np.linalg.norm(freq)
        h += np.sin(p @ freq + rng.uniform(0, 2 * np.pi)) / (1.0 + 0.3 * k)
    h *= amplitude / (np.abs(h).max() + 1e-9)
    return (p + normals_fn(p) * h[:, None]).reshape(points.shape)


def make_sphere(res: int = 64) -> Geometry:
    return _parametric(_sphere_points, res * 2, res)


def make_torus(minor: float = 0.35, res: int = 64) -> Geometry:
    major = 1.0 - minor

    def fn(u, v):
        ph, t = u * 2 * np.pi, v * 2 * np.pi
        r = major + minor * np.cos(t)
        return np.stack([r * np.cos(ph), minor * np.sin(t), r * np.sin(ph)], -1)

    return _parametric(fn, res * 2, res)


def make_superquadric(e1: float, e2: float, res: int = 64) -> Geometry:
    """Superellipsoid (e near 0: box-like, 1: sphere, 2: octahedron-like)."""

    def spow(x, e):
        return np.sign(x) * np.abs(x) ** e

    def fn(u, v):
        th, ph = v * np.pi - np.pi / 2, u * 2 * np.pi
        return np.stack([spow(np.cos(th), e1) * spow(np.cos(ph), e2), spow(np.sin(th), e1),
                         spow(np.cos(th), e1) * spow(np.sin(ph), e2)], -1) * np.array([1, -1, 1])

    g = _parametric(fn, res * 2, res)
    g.vertices /= np.linalg.norm(g.vertices, axis=1).max()
    return g


def make_bumpy_sphere(amplitude: float, seed: int, res: int = 96) -> Geometry:
    def fn(u, v):
        p = _sphere_points(u, v)
        return _displace(p, lambda q: q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-9), amplitude, seed)

    g = _parametric(fn, res * 2, res)
    g.vertices /= np.linalg.norm(g.vertices, axis=1).max()
    return g


def make_bumpy_torus(minor: float, amplitude: float, seed: int, res: int = 96) -> Geometry:
    major = 1.0 - minor

    def fn(u, v):
        ph, t = u * 2 * np.pi, v * 2 * np.pi
        r = major + minor * np.cos(t)
        p = np.stack([r * np.cos(ph), minor * np.sin(t), r * np.sin(ph)], -1)
        n = np.stack([np.cos(t) * np.cos(ph), np.sin(t), np.cos(t) * np.sin(ph)], -1).reshape(-1, 3)
        return _displace(p, lambda q: n, amplitude * minor, seed)

    g = _parametric(fn, res * 2, res)
    g.vertices /= np.linalg.norm(g.vertices, axis=1).max()
    return g


def make_box(extents=(1.0, 1.0, 1.0), subdiv: int = 2) -> Geometry:
    """An axis-aligned box centred at 0, flat shaded, one [0,1]^2 UV square per face."""
    e = np.asarray(extents, np.float64) / 2
    verts, faces, uvs = [], [], []
    offset = 0
    t = np.linspace(-1, 1, subdiv + 1)
    a, b = np.meshgrid(t, t)
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.zeros(a.shape + (3,))
            i1, i2 = [k for k in range(3) if k != axis]
            p[..., axis] = sign
            p[..., i1] = a
            p[..., i2] = b
            v, f, uv = _grid(p * e, subdiv, subdiv)
            normal = np.zeros(3)
            normal[axis] = sign
            fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
            if (fn @ normal).mean() < 0:
                f = f[:, ::-1]
            verts.append(v)
            faces.append(f + offset)
            uvs.append(uv)
            offset += len(v)
    v = np.concatenate(verts).astype(np.float32)
    v /= np.linalg.norm(v, axis=1).max()
    return Geometry(v, np.concatenate(faces).astype(np.int32), None, np.concatenate(uvs).astype(np.float32))


def make_backdrop(size: float, bump_amplitude: float, seed: int, res: int = 64) -> Geometry:
    """A square height-field patch in the xy plane (normal +z), side ``size``, optional smooth bumps."""
    u, v = np.meshgrid(np.linspace(0, 1, res + 1), np.linspace(0, 1, res + 1))
    p = np.stack([(u - 0.5) * size, (0.5 - v) * size, np.zeros_like(u)], -1)
    if bump_amplitude > 0:
        p = _displace(p, lambda q: np.tile([0.0, 0.0, 1.0], (len(q), 1)), bump_amplitude, seed, waves=8)
    verts, faces, uv = _grid(p, res, res)
    fn = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    if fn[:, 2].mean() < 0:
        faces = faces[:, ::-1].copy()
    normals = smooth_normals(verts, faces) if bump_amplitude > 0 else np.tile(np.float32([0, 0, 1]), (len(verts), 1))
    return Geometry(verts, faces, normals, uv)


def spherical_uv(vertices: np.ndarray) -> np.ndarray:
    """UVs by spherical projection about the origin (for meshes that have none)."""
    p = np.asarray(vertices, np.float64)
    r = np.maximum(np.linalg.norm(p, axis=1), 1e-9)
    u = np.arctan2(p[:, 0], p[:, 2]) / (2 * np.pi) + 0.5
    v = 1.0 - np.arccos(np.clip(p[:, 1] / r, -1, 1)) / np.pi
    return np.stack([u, v], 1).astype(np.float32)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed rotation matrix (from a random unit quaternion)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


# ----------------------------------------------------------------------------------------------- textures


def _smoothstep(t):
    return t * t * (3 - 2 * t)


def value_noise(rng: np.random.Generator, size: int, cells: int, octaves: int = 4) -> np.ndarray:
    """Fractal value noise in [0, 1], (size, size)."""
    out = np.zeros((size, size))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        c = cells * (2 ** o)
        grid = rng.random((c + 1, c + 1))
        x = np.linspace(0, c, size, endpoint=False)
        i = np.minimum(x.astype(int), c - 1)
        t = _smoothstep(x - i)
        rows = grid[i] * (1 - t)[:, None] + grid[i + 1] * t[:, None]
        layer = rows[:, i] * (1 - t)[None, :] + rows[:, i + 1] * t[None, :]
        out += amp * layer
        total += amp
        amp *= 0.5
    out /= total
    lo, hi = out.min(), out.max()
    return ((out - lo) / max(hi - lo, 1e-9)).astype(np.float32)


def _rotated_coords(size: int, angle: float):
    y, x = np.meshgrid(np.linspace(0, 1, size, endpoint=False), np.linspace(0, 1, size, endpoint=False), indexing="ij")
    c, s = np.cos(angle), np.sin(angle)
    return c * x - s * y, s * x + c * y


def stripes(size: int, freq: float, angle: float, softness: float) -> np.ndarray:
    a, _ = _rotated_coords(size, angle)
    s = np.sin(2 * np.pi * freq * a)
    return (0.5 + 0.5 * np.tanh(s / max(softness, 1e-3))).astype(np.float32)


def checkers(size: int, freq: float, angle: float) -> np.ndarray:
    a, b = _rotated_coords(size, angle)
    return ((np.floor(a * freq) + np.floor(b * freq)) % 2).astype(np.float32)


def cells(rng: np.random.Generator, size: int, count: int, mode: str = "id") -> np.ndarray:
    """Voronoi cells: ``id`` gives a random value per cell, ``edge`` the distance to the nearest point."""
    pts = rng.random((count, 2))
    y, x = np.meshgrid(np.linspace(0, 1, size, endpoint=False), np.linspace(0, 1, size, endpoint=False), indexing="ij")
    best = np.full((size, size), np.inf)
    arg = np.zeros((size, size), int)
    for k, (px, py) in enumerate(pts):  # toroidal distance: tiles seamlessly
        dx = np.abs(x - px)
        dy = np.abs(y - py)
        d = np.minimum(dx, 1 - dx) ** 2 + np.minimum(dy, 1 - dy) ** 2
        closer = d < best
        best = np.where(closer, d, best)
        arg = np.where(closer, k, arg)
    if mode == "id":
        return rng.random(count)[arg].astype(np.float32)
    d = np.sqrt(best)
    return (d / max(d.max(), 1e-9)).astype(np.float32)


PATTERNS = ("noise", "stripes", "checkers", "cells", "cells_edge")


def pattern(kind: str, seed: int, size: int, freq: float, angle: float) -> np.ndarray:
    """One procedural pattern in [0, 1] from its descriptor."""
    rng = np.random.default_rng(seed)
    if kind == "noise":
        return value_noise(rng, size, max(1, round(freq)))
    if kind == "stripes":
        return stripes(size, freq, angle, softness=rng.uniform(0.05, 0.6))
    if kind == "checkers":
        return checkers(size, freq, angle)
    if kind == "cells":
        return cells(rng, size, max(2, int(freq * freq)), "id")
    if kind == "cells_edge":
        return cells(rng, size, max(2, int(freq * freq)), "edge")
    raise ValueError(f"unknown pattern {kind!r}")


# ----------------------------------------------------------------------------------------------- sky


def procedural_sky(seed: int, height: int = 128) -> np.ndarray:
    """A sky-like equirectangular HDR map (height, 2*height, 3): gradient sky, clouds, sun, ground.

    Normalised to unit mean radiance over the sphere (solid-angle weighted).
    """
    rng = np.random.default_rng(seed)
    w = 2 * height
    theta = (np.arange(height) + 0.5) / height * np.pi  # 0 = +y (up)
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], -1)
    elev = d[..., 1]
    zenith = rng.uniform([0.15, 0.3, 0.6], [0.4, 0.55, 1.0])
    horizon = rng.uniform([0.6, 0.6, 0.6], [1.0, 0.95, 1.0])
    ground = rng.uniform([0.1, 0.08, 0.05], [0.45, 0.4, 0.35])
    t = np.clip(elev, 0, 1)[..., None] ** 0.5
    sky = horizon * (1 - t) + zenith * t
    clouds = value_noise(rng, max(height, w), 4, 5)[:height, :w]
    cover = rng.uniform(0.0, 0.8)
    cloud_mask = np.clip((clouds - (1 - cover)) * 4, 0, 1)[..., None] * (elev > 0)[..., None]
    sky = sky * (1 - cloud_mask) + cloud_mask * rng.uniform(0.7, 1.1)
    img = np.where(elev[..., None] > 0, sky, ground * (0.6 + 0.4 * clouds[..., None]))
    sun_el = np.deg2rad(rng.uniform(10, 75))
    sun_az = rng.uniform(0, 2 * np.pi)
    sun = np.array([np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el), -np.cos(sun_el) * np.cos(sun_az)])
    cosang = d @ sun
    width = np.deg2rad(rng.uniform(2.0, 6.0))
    glow = np.exp(-(np.arccos(np.clip(cosang, -1, 1)) / width) ** 2)
    sun_color = rng.uniform([0.95, 0.8, 0.6], [1.0, 1.0, 0.95])
    img = img + glow[..., None] * sun_color * rng.uniform(20, 80) * (1 - 0.8 * cloud_mask)
    weight = np.sin(th)[..., None]
    img = img / ((img * weight).sum() / (weight.sum() * 3))
    return img.astype(np.float32)

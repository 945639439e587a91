"""Height from normals: integrate a normal map into a height (depth) map, and turn heights into a mesh.

Conventions (the same as :class:`matcap.MaterialMaps`): normals are in camera space, x right, y up, z toward the
camera; image row 0 is the top. Heights are along +z (toward the camera) in **pixel units**: a 45° slope rises
one unit per pixel. For a surface ``z = h(x, y)`` with x = column and y = up (= -row),

    n ∝ (-∂h/∂x, -∂h/∂y, 1)   so   ∂h/∂column = -n_x / n_z   and   ∂h/∂row = +n_y / n_z.

Two integrators:

* ``"frankot-chellappa"`` (default): the least-squares integrable surface by projection onto Fourier bases
  (Frankot & Chellappa 1988), with the discrete forward-difference operator (so planes come back exactly). The
  gradient field is first mirror-extended (even in h, odd in the gradient across each border), so the periodic
  FFT solution has no wrap-around artefacts; this is the same as a DCT/Neumann Poisson solve. Fast (scipy.fft)
  and smooth, but it integrates across the mask edge and across depth discontinuities (gradients outside the
  mask are taken as 0).
* ``"periodic"``: the same Fourier projection on the grid itself, taken as a torus (no mirror extension), for a
  tileable normal map (``matcap tile``): the height then tiles too, and a gradient field with a net slope (which
  no periodic height has) loses only that mean slope.
* ``"poisson-masked"``: weighted least squares on the masked pixels only (scipy.sparse + spsolve). Each pair of
  4-neighbours inside the mask gives one equation ``h_b - h_a = mean of their gradients``; pairs whose slopes are
  steeper than ``max_slope`` (silhouettes) or whose gradients jump by more than ``jump`` (creases, occlusion
  edges) get a tiny weight, so depth discontinuities are not smeared over the surface. Disconnected parts are
  each given zero mean height.

Both return heights with zero mean over the mask and 0 outside it.
"""
from __future__ import annotations

import numpy as np

METHODS = ("frankot-chellappa", "poisson-masked", "periodic")


def normals_to_gradients(normal: np.ndarray, mask: np.ndarray | None = None, max_slope: float = 20.0):
    """(∂h/∂column, ∂h/∂row) from camera-space normals, slopes clipped to ±``max_slope``; 0 outside
    ``mask``."""
    n = np.asarray(normal, dtype=np.float64)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normal must be (H, W, 3), got {n.shape}")
    mask = np.ones(n.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != n.shape[:2]:
        raise ValueError(f"mask must be {n.shape[:2]}, got {mask.shape}")
    nz = np.maximum(n[..., 2], 1.0 / max_slope)
    gx = np.clip(-n[..., 0] / nz, -max_slope, max_slope)
    gr = np.clip(n[..., 1] / nz, -max_slope, max_slope)
    ok = mask & np.isfinite(gx) & np.isfinite(gr) & (np.linalg.norm(n, axis=2) > 0)
    return np.where(ok, gx, 0.0), np.where(ok, gr, 0.0)


def frankot_chellappa(gx: np.ndarray, gr: np.ndarray, periodic: bool = False) -> np.ndarray:
    """Integrate gradients (∂h/∂column, ∂h/∂row) by Fourier projection on the mirror-extended domain
    (``periodic``: on the grid itself as a torus, for tileable maps)."""
    from scipy import fft

    h, w = gx.shape
    if periodic:
        gx_e, gr_e = gx, gr
    else:
        # even extension of h  =>  ∂/∂column is odd across vertical borders, even across horizontal ones (and vice
        # versa)
        gx_e = np.block([[gx, -gx[:, ::-1]], [gx[::-1, :], -gx[::-1, ::-1]]])
        gr_e = np.block([[gr, gr[:, ::-1]], [-gr[::-1, :], -gr[::-1, ::-1]]])
    eh, ew = gx_e.shape
    # forward differences h[c+1] - h[c] should equal the mean gradient of the two pixels (trapezoid rule);
    # least squares in the Fourier basis of the periodic extended grid: H = Σ conj(D) T / Σ |D|²
    tx = 0.5 * (gx_e + np.roll(gx_e, -1, axis=1))
    tr = 0.5 * (gr_e + np.roll(gr_e, -1, axis=0))
    dx = np.exp(2j * np.pi * fft.fftfreq(ew))[None, :] - 1.0
    dr = np.exp(2j * np.pi * fft.fftfreq(eh))[:, None] - 1.0
    denom = np.abs(dx) ** 2 + np.abs(dr) ** 2
    denom[0, 0] = 1.0
    spec = (np.conj(dx) * fft.fft2(tx, workers=-1) + np.conj(dr) * fft.fft2(tr, workers=-1)) / denom
    spec[0, 0] = 0.0
    return np.real(fft.ifft2(spec, workers=-1))[:h, :w]


def poisson_masked(gx: np.ndarray, gr: np.ndarray, mask: np.ndarray, max_slope: float = 20.0,
                   jump: float = 1.0) -> np.ndarray:
    """Weighted least-squares integration on ``mask`` only, down-weighting discontinuities (see module doc)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    mask = np.asarray(mask, bool)
    h, w = mask.shape
    index = -np.ones((h, w), np.int64)
    index[mask] = np.arange(int(mask.sum()))
    n = int(mask.sum())
    if n == 0:
        return np.zeros((h, w))
    rows_a, rows_b, rhs, weight = [], [], [], []
    for g, (a_sl, b_sl) in (
        (gx, ((slice(None), slice(0, w - 1)), (slice(None), slice(1, w)))),  # right neighbour
        (gr, ((slice(0, h - 1), slice(None)), (slice(1, h), slice(None)))),  # lower neighbour
    ):
        both = mask[a_sl] & mask[b_sl]
        ga, gb = g[a_sl][both], g[b_sl][both]
        # jump of the whole gradient vector between the two pixels (a discontinuity may run along the edge)
        dg = np.hypot(gx[a_sl][both] - gx[b_sl][both], gr[a_sl][both] - gr[b_sl][both])
        wgt = np.ones_like(ga)
        wgt[(dg > jump) | (np.maximum(np.abs(ga), np.abs(gb)) >= max_slope * 0.999)] = 1e-4
        rows_a.append(index[a_sl][both])
        rows_b.append(index[b_sl][both])
        rhs.append(0.5 * (ga + gb))
        weight.append(wgt)
    ia, ib = np.concatenate(rows_a), np.concatenate(rows_b)
    b = np.concatenate(rhs)
    wgt = np.concatenate(weight)
    m = len(b)
    eq = np.arange(m)
    a_mat = sp.csr_matrix(
        (np.concatenate([-np.ones(m), np.ones(m)]), (np.concatenate([eq, eq]), np.concatenate([ia, ib]))),
        shape=(m, n),
    )
    aw = a_mat.T.multiply(wgt[None, :]).tocsr()
    # a tiny ridge term fixes each connected part's free constant (to ≈ zero mean) without biasing the shape
    lhs = (aw @ a_mat + 1e-9 * sp.identity(n, format="csr")).tocsc()
    sol = spsolve(lhs, aw @ b)
    out = np.zeros((h, w))
    out[mask] = sol
    # exact zero mean per connected part (the ridge only gets it approximately)
    from scipy.ndimage import label

    labels, count = label(mask)
    for k in range(1, count + 1):
        part = labels == k
        out[part] -= out[part].mean()
    return out


def integrate_normals(normal: np.ndarray, mask: np.ndarray | None = None, method: str = "frankot-chellappa", *,
                      max_slope: float = 20.0, jump: float = 1.0) -> np.ndarray:
    """Height map (H, W) float32 in pixel units from camera-space normals (H, W, 3).

    method: ``"frankot-chellappa"`` (default), ``"periodic"`` (tileable maps) or ``"poisson-masked"`` (respects
    the mask edge and depth discontinuities; ``jump`` is the gradient change between neighbours, in height units
    per pixel, above which two pixels are treated as disconnected). Zero mean over ``mask``, 0 outside it.
    """
    n = np.asarray(normal)
    mask = np.ones(n.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    gx, gr = normals_to_gradients(n, mask, max_slope)
    if method == "frankot-chellappa":
        height = frankot_chellappa(gx, gr)
    elif method == "periodic":
        height = frankot_chellappa(gx, gr, periodic=True)
    elif method == "poisson-masked":
        height = poisson_masked(gx, gr, mask, max_slope=max_slope, jump=jump)
    else:
        raise ValueError(f"unknown integration method {method!r}; choose one of {', '.join(METHODS)}")
    if mask.any():
        height = height - height[mask].mean()
    return np.where(mask, height, 0.0).astype(np.float32)


def height_mesh(height: np.ndarray, mask: np.ndarray | None = None, base_color: np.ndarray | None = None):
    """A ``trimesh.Trimesh`` of the surface: one vertex per masked pixel centre, two triangles per fully masked
    2×2 block, facing +z. Units: pixels; x right, y up, origin at the image centre, z = height.
    ``base_color`` (H, W, 3) linear gives sRGB 8-bit vertex colours."""
    import trimesh

    hgt = np.asarray(height, dtype=np.float64)
    h, w = hgt.shape
    mask = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    index = -np.ones((h, w), np.int64)
    index[mask] = np.arange(int(mask.sum()))
    rr, cc = np.nonzero(mask)
    vertices = np.stack([cc - (w - 1) / 2.0, (h - 1) / 2.0 - rr, hgt[rr, cc]], axis=1)
    a, b = index[:-1, :-1], index[:-1, 1:]  # top-left, top-right
    d, e = index[1:, :-1], index[1:, 1:]  # bottom-left, bottom-right
    full = (a >= 0) & (b >= 0) & (d >= 0) & (e >= 0)
    faces = np.concatenate([np.stack([a[full], d[full], e[full]], 1), np.stack([a[full], e[full], b[full]], 1)])
    kwargs = {}
    if base_color is not None:
        from matcap.imageio import linear_to_srgb

        rgb = np.round(linear_to_srgb(np.asarray(base_color)[rr, cc]) * 255).astype(np.uint8)
        kwargs["vertex_colors"] = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False, **kwargs)


def ambient_occlusion(height: np.ndarray, mask: np.ndarray | None = None, *, radius: float = 16.0,
                      directions: int = 16, steps: int = 16, wrap: bool = False) -> np.ndarray:
    """Cosine-weighted ambient occlusion (H, W) float32 in [0, 1] (1 = unoccluded) of a height field, by horizon
    search (the heightfield form of horizon-based AO).

    height: (H, W) in pixel units (as from :func:`integrate_normals`); mask: (H, W) bool, pixels outside it neither
    receive nor cast occlusion (AO = 1 there). For each of ``directions`` azimuths the highest horizon within
    ``radius`` pixels (``steps`` samples, denser near the pixel) is measured *relative to the local tangent plane*
    (so a tilted but flat surface is unoccluded), and a slice whose horizon rises by elevation ``e`` keeps
    ``cos(e)^2`` of its cosine-weighted sky. AO is the mean over azimuths. ``wrap``: the height field tiles
    (occluders are searched across the borders, slopes taken periodically), so the occlusion tiles too. For the
    floor of a long trench of width ``w`` and depth ``d`` this gives ``1 / sqrt(1 + (2 d / w)^2)`` exactly in the
    continuum limit.
    """
    h = np.asarray(height, np.float64)
    if h.ndim != 2:
        raise ValueError(f"height must be (H, W), got {h.shape}")
    mask = np.ones(h.shape, bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != h.shape:
        raise ValueError(f"mask shape {mask.shape} does not match height {h.shape}")
    if radius < 1 or directions < 1 or steps < 1:
        raise ValueError(f"radius, directions and steps must be >= 1, got {radius}, {directions}, {steps}")
    rows, cols = h.shape
    pad = int(np.ceil(radius)) + 1
    if wrap:
        hp = np.pad(np.where(mask, h, -np.inf), pad, mode="wrap")
    else:
        hp = np.full((rows + 2 * pad, cols + 2 * pad), -np.inf)
        hp[pad:pad + rows, pad:pad + cols] = np.where(mask, h, -np.inf)
    # local slope along each azimuth from central differences (height 0 outside the mask)
    inside = np.where(mask, h, 0.0)
    if wrap:
        g_col = 0.5 * (np.roll(inside, -1, axis=1) - np.roll(inside, 1, axis=1))
        g_up = -0.5 * (np.roll(inside, -1, axis=0) - np.roll(inside, 1, axis=0))  # d h / d y with y up = -row
    else:
        g_col = np.gradient(inside, axis=1)
        g_up = -np.gradient(inside, axis=0)  # d h / d y with y up = -row
    distances = np.unique(np.round(np.geomspace(1.0, radius, steps) * 4) / 4)
    total = np.zeros(h.shape)
    for k in range(directions):
        phi = 2 * np.pi * (k + 0.5) / directions
        dx, dy = np.cos(phi), np.sin(phi)  # x right, y up
        best = np.full(h.shape, -np.inf)
        for t in distances:
            oc, orow = int(round(t * dx)), int(round(-t * dy))
            if oc == 0 and orow == 0:
                continue
            dist = float(np.hypot(oc, orow))
            shifted = hp[pad + orow:pad + orow + rows, pad + oc:pad + oc + cols]
            np.maximum(best, (shifted - h) / dist, out=best)
        tangent = g_col * dx + g_up * dy
        elevation = np.arctan(best) - np.arctan(tangent)  # best = -inf (no occluder) gives -pi/2
        total += np.cos(np.clip(elevation, 0.0, np.pi / 2)) ** 2
    ao = total / directions
    return np.where(mask, np.clip(ao, 0.0, 1.0), 1.0).astype(np.float32)

"""Lights of an uncalibrated capture: Lambertian factorization, its linear ambiguity resolved by the network.

Under distant lights a Lambertian pixel ``p`` in photo ``k`` has luminance ``Y_kp = b_p . s_k`` (``b_p`` = albedo
times normal, ``s_k`` = irradiance times direction toward the light). The photos fix ``b`` and ``s`` only up to an
invertible 3x3 matrix ``A`` (``b -> A b``, ``s -> A^-T s``: every product stays the same); uncalibrated photometric
stereo is exactly the problem of choosing ``A``. Measured on the UW captures (benchmarks/refine_check.py): the
normals this factorization gives are within 3-8 degrees of least squares with the true lights *up to one such A*,
while the network's normals are 6-31 degrees off, mostly in local detail (the best A brings them only to 5-27).

So the photos decide everything but ``A``. :func:`factorize` takes ``A`` (nine numbers for the whole capture) from
prior knowledge, by linear least squares of ``A b_p`` against ``|b_p| n_p``; :func:`integrable_ambiguity` then
takes six of the nine from the photos again (their normals must form one surface), leaving the prior only the
three numbers of a bas-relief (chosen as ``RefineSettings.factorization`` says). The priors:

- the network's normals ``n_p`` on the object, and
- the occluding contour: on the mask's edge, where the network agrees the surface turns away (``n_z`` below
  ``contour_gate``), the normal lies almost in the image plane, pointing out of the mask. The networks' normals are
  too flat (too much ``z``) on every UW capture; the contour is the geometric cue that fixes the depth scale.

Alternation (robust: Cauchy weights, attached shadows ``b . s <= 0`` dropped; outliers are cast shadows,
highlights, interreflections): lights from the pixels, pixels from the lights, then ``A``; a few dozen rounds of
3x3 solves, well under a second at 256 px.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

@dataclass
class LinearFit:
    """Result of :func:`factorize` for P object pixels and K photos.

    directions: (K, 3) unit vectors toward the lights (camera frame); irradiance: (K,) luminance irradiance in the
    units of ``luminance``; normal: (P, 3) unit; albedo: (P,) luminance albedo (``|b_p|``); weight: (K, P) final
    robust weights (0: shadowed or an outlier); contour_pixels: how many pixels the contour cue used;
    residual: RMS of the robust fit's residual over the weighted observations, relative to the mean luminance;
    inliers: the mean robust weight. Together they say whether distant lights on a Lambertian-like surface explain
    the photos at all (docs/refine.md has the measured values); spread: the third singular value of ``luminance``
    over the first: near 0 when the photos are (nearly) rank 1, as those of a flat sample are, whose one normal
    cannot tell the lights' directions apart (a flat wood sample: 0.003; the UW captures: 0.07-0.09);
    twin_ratio: after integrability chose the bas-relief (:func:`twin_ratio`), the prior's misfit of the surface
    chosen over that of its twin, which explains the photos as well (NaN: not measured).
    """

    directions: np.ndarray
    irradiance: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    weight: np.ndarray
    contour_pixels: int
    residual: float = float("nan")
    inliers: float = float("nan")
    spread: float = float("nan")
    twin_ratio: float = float("nan")


def contour_normals(mask: np.ndarray, normal: np.ndarray, gate: float = 0.6, nz: float = 0.1,
                    ring: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Occluding-contour normals on the mask's edge.

    mask: (H, W) bool; normal: (H, W, 3) the network's normals. Returns (selected (H, W) bool, normals (H, W, 3)):
    pixels within ``ring`` of the mask's edge (not the image border) where the network's ``n_z`` is below
    ``gate``, and there the unit vector pointing out of the mask in the image plane, lifted to ``n_z = nz`` (a
    pixel centre lies half a pixel inside the contour).
    """
    import cv2

    mask = np.asarray(mask, bool)
    padded = np.pad(mask, ring, mode="edge").astype(np.uint8)  # the image border is not a contour
    inner = cv2.erode(padded, np.ones((3, 3), np.uint8), iterations=ring)[ring:-ring, ring:-ring].astype(bool)
    edge = mask & ~inner
    blur = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 2.0)
    gy, gx = np.gradient(blur)
    out2 = np.stack([-gx, gy], axis=-1)  # x right, y up: out of the mask
    norm = np.linalg.norm(out2, axis=-1, keepdims=True)
    out2 = out2 / np.maximum(norm, 1e-9)
    lifted = np.concatenate([out2 * np.sqrt(1.0 - nz * nz), np.full(mask.shape + (1,), nz)], axis=-1)
    sel = edge & (np.asarray(normal)[..., 2] < gate) & (norm[..., 0] > 1e-6)
    return sel, lifted.astype(np.float32)


def _solve3(a: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Batched 3x3 solves (N, 3, 3) x (N, 3), lightly regularised."""
    tr = np.trace(a, axis1=1, axis2=2)[:, None, None]
    a = a + np.eye(3)[None] * (1e-9 * tr + 1e-12)
    return np.linalg.solve(a, r[..., None])[..., 0]


def _outer_sum(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """sum_j w[i, j] v_j v_j^T for every row i: (M, N) x (N, 3) -> (M, 3, 3), as one matrix product."""
    outer = (v[:, :, None] * v[:, None, :]).reshape(len(v), 9)
    return (w @ outer).reshape(-1, 3, 3)


def lambertian_shading(lights: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K, P) ``lights`` · ``b``, unclipped: lights (K, 3) irradiance times direction, or (K, P, 3) one such vector
    per pixel; b (P, 3) albedo times normal (or a unit normal: the shading per unit albedo)."""
    return np.einsum("kpi,pi->kp", lights, b) if lights.ndim == 3 else lights @ b.T


def _weights(y: np.ndarray, shading: np.ndarray, c: float, shadow: float,
             lamp: np.ndarray | None = None) -> np.ndarray:
    """(K, P) robust weights of the observations ``y`` against the model's ``shading``: Cauchy of scale ``c``, and
    0 where the lamp's own part ``lamp`` (None: the whole shading) is below ``shadow`` times its largest (an
    attached shadow)."""
    res = y - shading
    w = 1.0 / (1.0 + (res / c) ** 2)
    lamp = shading if lamp is None else lamp
    return w * (lamp > shadow * max(float(lamp.max()), 1e-12))


def _resolve(b: np.ndarray, s: np.ndarray, prior: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the A with A b_p ~ |b_p| prior_p (weights q): b -> A b, s -> A^-T s. Unchanged when ill-posed."""
    size = np.linalg.norm(b, axis=1)
    m = (b * q[:, None]).T @ b
    ev = np.linalg.eigvalsh(m)
    if not np.isfinite(ev).all() or ev[0] <= 1e-9 * max(ev[-1], 1e-30):
        return b, s
    a = np.linalg.solve(m, (b * q[:, None]).T @ (size[:, None] * prior)).T
    if not np.isfinite(a).all() or abs(np.linalg.det(a)) < 1e-12:
        return b, s
    return b @ a.T, s @ np.linalg.inv(a)


def factorize(luminance: np.ndarray, normal: np.ndarray, albedo: np.ndarray, contour: np.ndarray | None = None,
              contour_normal: np.ndarray | None = None, contour_weight: float = 1.0, rounds: int = 20,
              cauchy: float = 0.1, shadow: float = 0.02, init: str = "svd") -> LinearFit:
    """Lights and Lambertian normals of P pixels in K photos, the ambiguity resolved by the priors.

    luminance: (K, P) linear, scaled so that its mean is about 0.5 (``cauchy`` is in those units); normal: (P, 3)
    the network's unit normals; albedo: (P,) the network's luminance albedo (a start only); contour: (P,) bool
    pixels on the occluding contour with their normals ``contour_normal`` (P, 3), weighing ``contour_weight``
    times the rest of the object in all. ``init`` "svd": the factorization starts from the singular vectors of
    the pixels lit in every photo (independent of the network; the prior only picks A), "network": from the
    network's normals (also the fallback when fewer than 32 pixels are lit in every photo).
    """
    if init not in ("svd", "network"):
        raise ValueError(f"init must be 'svd' or 'network', got {init!r}")
    y = np.asarray(luminance, np.float64)
    k_count, p_count = y.shape
    if normal.shape != (p_count, 3):
        raise ValueError(f"normal must be ({p_count}, 3), got {normal.shape}")
    singular = np.linalg.svd(y, compute_uv=False)
    spread = float(singular[2] / singular[0]) if len(singular) >= 3 and singular[0] > 0 else 0.0
    network = np.asarray(normal, np.float64)
    network = network / np.maximum(np.linalg.norm(network, axis=1, keepdims=True), 1e-9)
    prior = network
    if contour is not None and contour.any() and contour_weight > 0:
        contour = np.asarray(contour, bool)
        prior = np.where(contour[:, None], np.asarray(contour_normal, np.float64), prior)
        share = contour_weight * (~contour).sum() / contour.sum()
        prior_w = np.where(contour, share, 1.0)
        n_contour = int(contour.sum())
    else:
        prior_w = np.ones(p_count)
        n_contour = 0
    w = (y > shadow * np.percentile(y, 95, axis=1, keepdims=True)).astype(np.float64)  # not in shadow
    b = s = None
    lit = w.all(axis=0)
    if init == "svd" and lit.sum() >= 32 and k_count >= 3:  # exact for Lambertian pixels lit in every photo
        u, sv, vt = np.linalg.svd(y[:, lit], full_matrices=False)
        s = u[:, :3] * np.sqrt(sv[:3])
        b = _solve3(_outer_sum(w.T, s), (w * y).T @ s)
        b, s = _resolve(b, s, prior, prior_w * (w.sum(0) >= 3.5))
    if b is None or not np.isfinite(b).all():
        b = np.clip(np.asarray(albedo, np.float64), 0.02, None)[:, None] * network
        w = np.ones((k_count, p_count))
    solved = np.zeros(p_count, bool)  # pixels whose b came from the photos (only they may decide A)
    for _ in range(rounds):
        for _ in range(2):  # lights, pixels fixed
            s = _solve3(_outer_sum(w, b), (w * y) @ b)
            w = _weights(y, s @ b.T, cauchy, shadow)
        for _ in range(2):  # pixels, lights fixed (pixels lit in fewer than 4 photos keep their value)
            b_new = _solve3(_outer_sum(w.T, s), (w * y).T @ s)
            ok = (w.sum(0) >= 3.5) & np.isfinite(b_new).all(axis=1)
            solved |= ok
            b = np.where(ok[:, None], b_new, b)
            w = _weights(y, s @ b.T, cauchy, shadow)
        # the ambiguity: A b_p ~ |b_p| prior_p, weighted by how well each pixel is observed
        b, s = _resolve(b, s, prior, np.minimum(w.sum(0), k_count) / k_count * prior_w * solved)
    size = np.linalg.norm(b, axis=1)
    n = b / np.maximum(size, 1e-12)[:, None]
    n[n[:, 2] < 0, 2] *= -1.0
    irr = np.linalg.norm(s, axis=1)
    dirs = s / np.maximum(irr, 1e-12)[:, None]
    pred = np.clip(s @ b.T, 0.0, None)
    residual = float(np.sqrt((w * (pred - y) ** 2).sum() / max(w.sum(), 1e-12)) / max(float(y.mean()), 1e-12))
    return LinearFit(dirs, irr, n, size, w, n_contour, residual, float(w.mean()), spread)


def solve_normals(luminance: np.ndarray, lights: np.ndarray, normal: np.ndarray, rounds: int = 4,
                  cauchy: float = 0.1, shadow: float = 0.02,
                  ambient: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust Lambertian normals of P pixels given the lights: calibrated photometric stereo.

    luminance: (K, P); lights: (K, 3) irradiance times direction (as :class:`LinearFit` gives them, in the units
    of ``luminance``), or (K, P, 3) one such vector per pixel (lamps near enough for it to change across the
    object); normal: (P, 3) start (kept where a pixel is lit in fewer than 4 photos); ambient: (4,) a room's light
    shared by every photo, its irradiance at a normal n being ``ambient[0] + ambient[1:] . n`` (in the lights'
    units; :func:`matcap.refine.known_lights.known_irradiance` finds it), or None (none): a pixel's luminance in a
    photo that lights it is then ``|b| ambient[0] + b . (s_k + ambient[1:])``. Returns (normal (P, 3) unit,
    albedo (P,), solved (P,) bool).
    """
    y = np.asarray(luminance, np.float64)
    s = np.asarray(lights, np.float64)
    n0 = np.asarray(normal, np.float64)
    amb = np.zeros(4) if ambient is None else np.asarray(ambient, np.float64)
    lit_by = s + amb[1:]  # the lamp and the room's linear part: what b multiplies
    # the lamp's own part, for the attached-shadow test: the whole shading where there is no room's light
    lamp = (lambda b: None) if ambient is None else (lambda b: lambertian_shading(s, b))  # noqa: E731
    shade = lambda b: lambertian_shading(lit_by, b) + amb[0] * np.linalg.norm(b, axis=1)[None]  # noqa: E731
    if s.ndim == 3:
        normal_eq = lambda w, t: (np.einsum("kp,kpi,kpj->pij", w, lit_by, lit_by),  # noqa: E731
                                  np.einsum("kp,kp,kpi->pi", w, t, lit_by))
    else:
        normal_eq = lambda w, t: (_outer_sum(w.T, lit_by), (w * t).T @ lit_by)  # noqa: E731
    b = n0 * np.maximum(np.mean(y, axis=0) / np.maximum(np.mean(np.abs(shade(n0)), axis=0), 1e-9), 1e-6)[:, None]
    w = _weights(y, shade(b), cauchy, shadow, lamp(b))
    solved = np.zeros(len(n0), bool)
    for _ in range(rounds):
        # the room's constant part, |b| ambient[0], taken at the last round's albedo: the rest is linear in b
        b_new = _solve3(*normal_eq(w, y - amb[0] * np.linalg.norm(b, axis=1)[None]))
        ok = (w.sum(0) >= 3.5) & np.isfinite(b_new).all(axis=1) & (b_new[:, 2] > 0)
        solved = ok
        b = np.where(ok[:, None], b_new, b)
        w = _weights(y, shade(b), cauchy, shadow, lamp(b))
    size = np.linalg.norm(b, axis=1)
    n = np.where(solved[:, None], b / np.maximum(size, 1e-12)[:, None], n0)
    return n.astype(np.float32), size.astype(np.float32), solved


def align(source: np.ndarray, target: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """The 3x3 matrix G with G source_p ~ target_p in least squares (unit vectors (P, 3)): the global linear
    difference between two normal maps (e.g. the network's flattening, measured against the photos' normals)."""
    src = np.asarray(source, np.float64)
    tgt = np.asarray(target, np.float64)
    q = np.ones(len(src)) if weight is None else np.asarray(weight, np.float64)
    g = np.linalg.solve((src * q[:, None]).T @ src + 1e-9 * np.eye(3), (src * q[:, None]).T @ tgt).T
    return g


def _gradients(b_img: np.ndarray, ok: np.ndarray, sigma: float):
    """Smoothed pseudo-normals and their image derivatives (x right, y up) at pixels whose 3x3 neighbourhood is
    usable: (e, e_x, e_y) each (N, 3)."""
    import cv2

    ok = np.asarray(ok, bool)
    b = np.asarray(b_img, np.float64) * ok[..., None]
    if sigma > 0:
        wsum = cv2.GaussianBlur(ok.astype(np.float64), (0, 0), sigma)
        b = np.stack([cv2.GaussianBlur(b[..., i], (0, 0), sigma) for i in range(3)], axis=-1)
        b = b / np.maximum(wsum, 1e-9)[..., None]
    ex = np.zeros_like(b)
    ey = np.zeros_like(b)
    ex[:, 1:-1] = (b[:, 2:] - b[:, :-2]) / 2.0
    ey[1:-1] = -(b[2:] - b[:-2]) / 2.0  # rows run down, y up
    good = cv2.erode(ok.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0).astype(bool)
    good[[0, -1]] = False
    good[:, [0, -1]] = False
    return b[good], ex[good], ey[good]


def integrable_ambiguity(b_img: np.ndarray, ok: np.ndarray, prior: np.ndarray, prior_weight: np.ndarray,
                         lights: np.ndarray | None = None, equal_lights: float = 0.0, sigma: float = 1.0,
                         rounds: int = 5) -> np.ndarray | None:
    """The 3x3 ``A`` that makes the pseudo-normals ``A b`` integrable (the normals of one height field), its
    remaining generalized bas-relief freedom (3 numbers and a scale) taken from the prior.

    b_img: (H, W, 3) pseudo-normals (albedo times normal) up to any invertible 3x3, as a factorization gives them;
    ok: (H, W) bool where they were solved; prior: (H, W, 3) unit normals (the network's, the contour's);
    prior_weight: (H, W) their weights. Returns ``A`` (3, 3), to apply as ``b -> A b``, ``s -> A^-T s``, with the
    surface facing the camera (median ``(A b)_z > 0``); None when fewer than 64 pixels have usable neighbours or
    the system is degenerate.

    Integrability of ``n`` (``d(n_x/n_z)/dy = d(n_y/n_z)/dx``) holds for any albedo. With ``b = A e`` and the rows
    ``a_i`` of ``A`` it reads ``(a3 x a1) . (e x e_y) - (a3 x a2) . (e x e_x) = 0`` at every pixel: linear in the six
    numbers ``c = (a3 x a1, a3 x a2)``, whose robust null vector (Cauchy-reweighted SVD; depth edges and cast
    shadows are its outliers) fixes ``A`` up to ``b -> (al b1 + be b3, al b2 + ga b3, de b3)``, the bas-relief
    family (Belhumeur, Kriegman and Yuille 1999). That family is fitted to ``|b| prior`` by linear least squares,
    then (Nelder-Mead on its three shape numbers) to the prior's unit normals (their misfit relative to the
    least-squares fit's) plus ``equal_lights`` times the
    variance of the log irradiances of ``lights`` (K, 3), in the frame of ``b_img``: one lamp moved around at a
    similar distance gives every photo about the same irradiance, and a wrong bas-relief gives them different ones
    (Hayakawa 1994); the photos themselves cannot tell the members of the family apart.
    Measured on the UW captures at 160 px (docs/refine.md).
    """
    e, ex, ey = _gradients(b_img, ok, sigma)
    if len(e) < 64:
        return None
    m = np.concatenate([np.cross(e, ey), -np.cross(e, ex)], axis=1)
    m /= np.maximum((e * e).sum(1), 1e-12)[:, None]  # every pixel counts alike, whatever its albedo
    w = np.ones(len(m))
    for _ in range(rounds):
        _, _, vt = np.linalg.svd(m * np.sqrt(w)[:, None], full_matrices=False)
        r = m @ vt[-1]
        scale = 1.4826 * np.median(np.abs(r)) + 1e-12
        w = 1.0 / (1.0 + (r / (2.0 * scale)) ** 2)
    c1, c2 = vt[-1][:3], vt[-1][3:]
    u = np.cross(c1, c2)
    if np.linalg.norm(u) < 1e-9:
        return None
    u /= np.linalg.norm(u)
    a0 = np.stack([np.cross(c1, u), np.cross(c2, u), u])  # a3 x a1 = c1, a3 x a2 = c2
    if abs(np.linalg.det(a0)) < 1e-12:
        return None
    sel = np.asarray(ok, bool)
    seen = np.asarray(b_img, np.float64)[sel]
    b = seen @ a0.T
    pr = np.asarray(prior, np.float64)[sel]
    t = np.linalg.norm(seen, axis=1)[:, None] * pr
    q = np.asarray(prior_weight, np.float64)[sel]
    zero = np.zeros(len(b))
    rows = np.concatenate([np.stack([b[:, 0], b[:, 2], zero], 1), np.stack([b[:, 1], zero, b[:, 2]], 1)])
    qq = np.sqrt(np.concatenate([q, q]))
    al, be, ga = np.linalg.lstsq(rows * qq[:, None], np.concatenate([t[:, 0], t[:, 1]]) * qq, rcond=None)[0]
    de = float((q * b[:, 2] * t[:, 2]).sum() / max((q * b[:, 2] ** 2).sum(), 1e-12))
    g = np.array([[al, 0.0, be], [0.0, al, ga], [0.0, 0.0, de]])
    a = g @ a0
    if not np.isfinite(a).all() or abs(np.linalg.det(a)) < 1e-12:
        return None
    return _shape_fit(a, seen, pr, q, lights, equal_lights)  # a finite bas-relief of a: finite, invertible


def twin_ratio(a: np.ndarray, b_img: np.ndarray, ok: np.ndarray, prior: np.ndarray,
               prior_weight: np.ndarray) -> float:
    """How much better the surface ``A b`` fits the prior than its twin ``D A b`` (``D`` = diag(-1, -1, 1)): the
    prior's weighted mean squared distance of unit normals for the one over the other's.

    Under distant lights and an orthographic camera the twin (every tilt mirrored: bumps become dents) with the
    lights turned half a turn about the camera axis gives the same photos, and it is a member of the bas-relief
    family that integrability leaves. Only the prior tells them apart: an occluding contour, whose normals point
    out of the object, does by far; a sample with no outline has only the networks' tilts. Near 1: the prior
    cannot tell the two apart. Arguments as :func:`integrable_ambiguity`'s, ``a`` (3, 3) its result."""
    sel = np.asarray(ok, bool)
    b = np.asarray(b_img, np.float64)[sel] @ np.asarray(a, np.float64).T
    n = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    pr = np.asarray(prior, np.float64)[sel]
    q = np.asarray(prior_weight, np.float64)[sel]
    twin = n * np.array([-1.0, -1.0, 1.0])
    own = float((q * ((n - pr) ** 2).sum(1)).sum())
    other = float((q * ((twin - pr) ** 2).sum(1)).sum())
    return own / max(other, 1e-12)


def _gbr(p: np.ndarray) -> np.ndarray:
    return np.array([[1.0, 0.0, p[0]], [0.0, 1.0, p[1]], [0.0, 0.0, np.exp(p[2])]])


def _shape_fit(a: np.ndarray, b: np.ndarray, prior: np.ndarray, q: np.ndarray, lights: np.ndarray | None,
               equal_lights: float, min_drop: float = 0.3) -> np.ndarray:
    """``G a`` with the bas-relief ``G`` (shear p0, p1; depth scale exp(p2)) that best fits the unit normals of
    ``G a b`` to ``prior`` (weights ``q``) plus ``equal_lights`` times the variance of log |lights (G a)^-1|.

    The prior's misfit is measured relative to its value at the start (``a`` itself, the least-squares bas-relief
    fit to the prior): a prior that fits well (a good network) is not given up for equal irradiances that
    tinted or unequal lamps never had, one that fits poorly leaves the choice to them.
    Where the member so chosen removes less than ``min_drop`` of the lamps' log-irradiance variance
    (:func:`_explains_inequality`: the lamps are unequal in a way no bas-relief explains), the prior alone chooses.
    """
    from scipy.optimize import minimize

    b1 = b @ a.T
    if np.median(b1[:, 2]) < 0:
        a, b1 = -a, -b1
    s1 = None if lights is None else np.asarray(lights, np.float64) @ np.linalg.inv(a)
    q = q / max(q.sum(), 1e-12)

    def misfit(p):
        bb = b1 @ _gbr(p).T
        nn = bb / np.maximum(np.linalg.norm(bb, axis=1, keepdims=True), 1e-12)
        return float((q * ((nn - prior) ** 2).sum(1)).sum())

    start = max(misfit(np.zeros(3)), 1e-6)

    def cost(p):
        c = misfit(p) / start
        if s1 is not None and equal_lights > 0:
            c += equal_lights * _log_irradiance_var(s1, p)
        return c

    res = minimize(cost, np.zeros(3), method="Nelder-Mead", options={"xatol": 1e-5, "fatol": 1e-10,
                                                                      "maxiter": 2000})
    p = res.x if np.isfinite(res.x).all() and res.fun <= cost(np.zeros(3)) else np.zeros(3)
    if s1 is not None and equal_lights > 0 and not _explains_inequality(s1, p, min_drop):
        return _shape_fit(a, b, prior, q, None, 0.0)  # the prior alone chooses
    return _gbr(p) @ a


def _log_irradiance_var(s1: np.ndarray, p: np.ndarray) -> float:
    """Variance over the photos of log |s1 G(p)^-1|: how unequal the lamps are in the bas-relief ``p``."""
    return float(np.var(np.log(np.maximum(np.linalg.norm(s1 @ np.linalg.inv(_gbr(p)), axis=1), 1e-12))))


def _explains_inequality(s1: np.ndarray, p: np.ndarray, min_drop: float) -> bool:
    """Whether the bas-relief ``p`` removes at least ``min_drop`` of the lamps' log-irradiance variance in the
    prior's own member (``p`` = 0): a wrong member of equal lamps does (UW 0.39-0.85 at ``equal_lights`` 150);
    lamps of truly unequal power (a rig's LEDs, +-30 %) leave most of it (matte balls 0.01-0.09), and there the
    few percent the family can remove by chance only bend a good prior's surface (a ball 1.9 -> 3.7 degrees)."""
    v0 = _log_irradiance_var(s1, np.zeros(3))
    return v0 > 0 and 1.0 - _log_irradiance_var(s1, p) / v0 >= min_drop

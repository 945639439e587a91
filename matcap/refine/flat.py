"""Flat samples: a material swatch taken as a plane facing the camera, and the lamps that lit it.

A plane's mean normal is the camera axis, so a lamp a few sample widths away shows itself in the photos' falloff:
photo k's irradiance at plane point x is ``I_k * h_k / |p_k - x|^3`` (a lamp at ``p_k``, ``h_k`` its height above
the plane), and the ratio of two photos at one pixel cancels the albedo. :func:`plane_lamps` fits every lamp's
position and relative intensity to those ratios (log domain, robust, the per-pixel albedo profiled out; a coloured
pixel's highlights taken out by its channels' spread, :func:`_diffuse_channel`), then to the photos under the fit's
own Principled BSDF where the plane explains them that way (its highlights place the lamps). From far away the
falloff is flat and tells nothing (:attr:`PlaneLamps.near` is false): the photos of one
plane under distant lights cannot tell those lights apart, so :func:`flat_lights` returns none and the lights must be
given (a light file, a mirror ball).

:func:`check_flat` says whether a capture looks like a flat sample (the networks' normals close to the camera axis
over most of a well-filled frame). Positions are in the framing plane's world units (:mod:`renderers.plane`: the
plane z = 0, x from -1 to 1 across the image), as ``lights.json`` stores point lights.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, NamedTuple

import numpy as np

from matcap.errors import MatcapError
from matcap.refine.photos import LUMA, clipping_level

if TYPE_CHECKING:
    from matcap.lightfiles import KnownLights
    from scenes.materialmaps import MaterialMaps


@dataclass
class FlatCheck:
    """Whether the networks' normals describe a flat sample (:func:`check_flat`).

    flat: the verdict; coverage: share of the frame inside the mask; tilt_mean_deg: angle between the mean normal
    and the camera axis; tilt_p90_deg: 90th percentile of the per-pixel angle to the camera axis."""

    flat: bool
    coverage: float
    tilt_mean_deg: float
    tilt_p90_deg: float

    def describe(self) -> str:
        return (f"the networks' normals lie within {self.tilt_p90_deg:.0f} degrees of the camera axis on 90% of "
                f"{self.coverage:.0%} of the frame")


#: check_flat's rule: the sample fills at least this share of the frame ...
FLAT_COVERAGE = 0.5
#: ... its mean normal is within this many degrees of the camera axis ...
FLAT_MEAN_TILT = 15.0
#: ... and 90 % of its normals within this many (the networks take a near lamp's falloff over a swatch for a bend of
#: up to about 45 degrees; an object's silhouette turns its normals to 90).
FLAT_P90_TILT = 50.0


def check_flat(normal: np.ndarray, mask: np.ndarray) -> FlatCheck:
    """normal: (H, W, 3) unit camera-space normals (the networks'); mask: (H, W) bool. A flat sample fills at least
    ``FLAT_COVERAGE`` of the frame, its mean normal within ``FLAT_MEAN_TILT`` degrees of the camera axis and 90 % of
    its normals within ``FLAT_P90_TILT``: an object's silhouette bends its normals away from the camera."""
    mask = np.asarray(mask, bool)
    n = np.asarray(normal, np.float64)[mask]
    coverage = float(mask.mean())
    if len(n) == 0:
        return FlatCheck(False, 0.0, 90.0, 90.0)
    tilt = np.degrees(np.arccos(np.clip(n[:, 2] / np.maximum(np.linalg.norm(n, axis=1), 1e-12), -1.0, 1.0)))
    mean = n.mean(0)
    mean_tilt = float(np.degrees(np.arccos(np.clip(mean[2] / max(np.linalg.norm(mean), 1e-12), -1.0, 1.0))))
    p90 = float(np.percentile(tilt, 90))
    flat = coverage >= FLAT_COVERAGE and mean_tilt <= FLAT_MEAN_TILT and p90 <= FLAT_P90_TILT
    return FlatCheck(flat, round(coverage, 4), round(mean_tilt, 3), round(p90, 3))


#: A capture is taken as a flat sample without being told only where it has at least this many photos.
FLAT_MIN_PHOTOS = 4


def flat_choice(flat: bool | None, maps: MaterialMaps) -> tuple[bool, dict]:
    """(whether the fit takes the capture as a flat sample, capture.json ``flat``): ``flat`` as given (True / False:
    the user said it), or, for None, :func:`check_flat` on the networks' normals (and at least
    ``FLAT_MIN_PHOTOS`` photos)."""
    found = check_flat(maps.normal, maps.mask)
    detected = found.flat and len(maps.meta.get("images_used", ())) >= FLAT_MIN_PHOTOS
    record = {"flat": bool(detected if flat is None else flat), "chosen_by": "detection" if flat is None else "flag",
              "coverage": found.coverage, "tilt_mean_deg": found.tilt_mean_deg, "tilt_p90_deg": found.tilt_p90_deg}
    if flat is None:
        record["why"] = found.describe()
    return record["flat"], record


def check_plane_mask(mask: np.ndarray) -> None:
    """A flat sample's mask must be one region of the frame, not scattered pieces (one line otherwise)."""
    import cv2

    mask = np.asarray(mask, bool)
    if mask.sum() < 64:
        raise MatcapError(f"a flat sample needs at least 64 pixels inside its mask, got {int(mask.sum())}")
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    if (areas >= 0.05 * mask.sum()).sum() > 1:
        raise MatcapError(f"the mask holds {(areas >= 0.05 * mask.sum()).sum()} separate regions; a flat sample is "
                          f"one plane (mask one region, or leave out --flat)")


@dataclass
class PlaneLamps:
    """The lamps of a flat sample's photos (:func:`plane_lamps`).

    positions: (K, 3) lamp positions, world units of the framing plane (z = height above it); directions: (K, 3)
    unit vectors from ``centre`` toward each lamp; distance: (K,) distances from ``centre``, world units;
    intensity: (K,) relative luminance irradiance at ``centre`` on a surface facing the lamp (mean 1); centre:
    (3,) the mask's centroid on the plane; width: the sample's width (world units: the longer side of the mask's
    bounding box); residual: median absolute relative residual of the near-light photometric stereo (0.01: 1 %);
    residual_distant: the same with every lamp taken as distant (a directional light): where it is not larger,
    the falloff did not place the lamps (:attr:`near`); residual_plane: the same (on the same copy) of the plane
    under the Principled BSDF (step 3 of :func:`plane_lamps`; NaN where near lamps were not found), whose lamps these
    are where :attr:`plane_placed`; residual_bright: step 2's lamps' residual on the photos' brightest channel, as
    step 3 sees them (``residual`` is on their diffuse light); roughness: that plane's one roughness."""

    positions: np.ndarray
    directions: np.ndarray
    distance: np.ndarray
    intensity: np.ndarray
    centre: np.ndarray
    width: float
    residual: float
    residual_distant: float
    residual_plane: float
    roughness: float
    residual_bright: float

    @property
    def near(self) -> bool:
        """Whether the falloff placed the lamps: distant lamps leave a residual of at least ``NEAR_FLOOR`` and the
        lamps' distances cut it to at most ``NEAR_GAIN`` of that."""
        return _placed(self.residual, self.residual_distant)

    @property
    def plane_placed(self) -> bool:
        """Whether the Principled plane placed the lamps (its residual at most :data:`PLANE_GAIN` of step 2's lamps',
        both on the brightest channel)."""
        return _plane_better(self.residual_plane, self.residual_bright)

    @property
    def distance_widths(self) -> np.ndarray:
        """(K,) distances in sample widths."""
        return self.distance / self.width


def plane_base_color(images, mask: np.ndarray, level: np.ndarray) -> np.ndarray:
    """A flat sample's base colour under distant lamps whose directions are not known.

    images: K (H, W, 3) linear RGB photos; mask: (H, W) bool, the sample; level: (H, W, 3) linear RGB, a base colour
    whose overall level is kept (the networks'). Returns (H, W, 3) float32: each pixel's mean over the photos, each
    photo divided by its median luminance over the sample (a distant lamp lights the whole plane alike, so that
    median is the photo's irradiance), observations at a photo's clipping level (0.999 of its maximum in a channel)
    left out; then one least-squares scale over every channel onto ``level``, and clipped to [0, 1]. With the lamps
    around the sample, the relief's own shading (brighter on the side facing each lamp) averages out over the
    photos; the photos cannot say more here, as they hold the relief only up to its sign and depth. Outside the
    mask: ``level``.
    """
    mask = np.asarray(mask, bool)
    total = np.zeros(mask.shape + (3,), np.float64)
    count = np.zeros(mask.shape + (1,), np.float64)
    luma = np.asarray(LUMA, np.float32)
    for im in images:
        im = np.asarray(im, np.float32)
        irradiance = float(np.median(im[mask] @ luma))
        if not irradiance > 0:
            continue
        seen = ~(im >= clipping_level(im, mask)).any(-1, keepdims=True) & mask[..., None]
        total += np.where(seen, im / irradiance, 0.0)
        count += seen
    ref = np.asarray(level, np.float64)
    mean = np.where(count > 0, total / np.maximum(count, 1.0), 0.0)
    den = float((mean[mask] ** 2).sum())
    if not den > 0:
        return np.asarray(level, np.float32)
    mean *= float((mean[mask] * ref[mask]).sum()) / den
    return np.clip(np.where(mask[..., None] & (count > 0), mean, ref), 0.0, 1.0).astype(np.float32)


def _dominant_channel(images) -> np.ndarray:
    """(K, H, W) each pixel's brightest colour channel (over the photos' mean): the channel where the surface's own
    colour is strongest, so a white highlight weighs least against its diffuse light."""
    stack = np.stack([np.asarray(im, np.float32) for im in images])
    pick = stack.mean(0).argmax(-1)
    return np.take_along_axis(stack, pick[None, ..., None], -1)[..., 0]


#: :func:`_diffuse_channel` takes a pixel's highlights out where its mean colour's saturation, (max - min) / max over
#: its channels, is at least this; a paler pixel keeps too little of its diffuse light in the spread.
DIFFUSE_SATURATION = 0.3


def _diffuse_channel(images, mask: np.ndarray, bright: np.ndarray) -> np.ndarray:
    """(K, H, W) each pixel's diffuse light alone where its colour allows, for placing the lamps.

    images: K (H, W, 3) linear RGB photos; mask: (H, W) bool, the sample; bright: (K, H, W) their brightest channel
    (:func:`_dominant_channel`). A dielectric's highlight has the lamp's colour (white after white balance) and adds
    alike to every channel, so the spread of a pixel's channels, max - min, holds its diffuse part alone (the
    shading times its base colour's own spread) and is Lambertian in every photo. Used where the pixel's mean colour
    over the photos has a saturation of at least :data:`DIFFUSE_SATURATION`; elsewhere ``bright``. An observation
    clipped in any channel (:func:`matcap.refine.photos.clipping_level`) is 0 there, which :func:`_log_obs` leaves
    out. The photos are read one at a time (no second stack of them)."""
    mean = sum(np.asarray(im, np.float32) for im in images) / len(images)
    coloured = (mean.max(-1) - mean.min(-1)) / np.maximum(mean.max(-1), 1e-12) >= DIFFUSE_SATURATION
    out = np.array(bright, np.float32)
    for k, im in enumerate(images):
        im = np.asarray(im, np.float32)
        spread = np.where((im >= clipping_level(im, mask)).any(-1), 0.0, im.max(-1) - im.min(-1))
        out[k] = np.where(coloured, spread, out[k])
    return out


def _small(lum: np.ndarray, mask: np.ndarray, side: int):
    """(K, h, w) luminance and (h, w) mask of a copy whose longer side is at most ``side`` (area average; a pixel
    counts where its whole area lies inside the mask)."""
    import cv2

    k, h, w = lum.shape
    f = min(1.0, side / max(h, w))
    hw = (max(4, round(h * f)), max(4, round(w * f)))
    if hw == (h, w):
        return lum, np.asarray(mask, bool)
    m = cv2.resize(np.asarray(mask, np.float32), hw[::-1], interpolation=cv2.INTER_AREA)
    out = np.stack([cv2.resize(np.ascontiguousarray(x * mask), hw[::-1], interpolation=cv2.INTER_AREA) for x in lum])
    keep = m > 0.999
    return out / np.maximum(m, 1e-6)[None], keep


def _log_obs(lum: np.ndarray, mask: np.ndarray):
    """Log luminance (K, P) and its weights (K, P) at the mask's pixels: clipped and black observations weigh 0."""
    y = lum[:, mask].astype(np.float64)
    top = y.max(axis=1, keepdims=True)
    floor = 1e-4 * max(float(np.percentile(y, 99)), 1e-12)
    w = ((y > floor) & (y < 0.98 * top)).astype(np.float64)
    return np.log(np.maximum(y, floor)), w


def _lamp_lm(torch, theta, fn, y, w, cauchy: float, steps: int):
    """Levenberg-Marquardt for K independent lamps: theta (K, Q) parameters, fn(theta_k (Q,), k) -> (P,) model log
    luminance, y / w (K, P) observations and their weights; Cauchy loss of scale ``cauchy`` by reweighting.
    Returns theta (K, Q)."""
    k_count, q_count = theta.shape
    ks = torch.arange(k_count)
    jac_fn = torch.func.vmap(torch.func.jacfwd(fn), in_dims=(0, 0))
    model_fn = torch.func.vmap(fn, in_dims=(0, 0))
    lam = torch.full((k_count,), 1e-3, dtype=theta.dtype)
    eye = torch.eye(q_count, dtype=theta.dtype)
    for _ in range(steps):
        e = y - model_fn(theta, ks)
        wr = w / (1.0 + (e / cauchy) ** 2)
        jac = jac_fn(theta, ks)  # (K, P, Q)
        jtj = torch.einsum("kpi,kp,kpj->kij", jac, wr, jac)
        jtr = torch.einsum("kpi,kp,kp->ki", jac, wr, e)
        cost = (wr * e * e).sum(1)
        damp = jtj + lam[:, None, None] * torch.diag_embed(torch.diagonal(jtj, dim1=1, dim2=2).clamp(min=1e-12))
        step = torch.linalg.solve(damp + 1e-12 * eye, jtr[..., None])[..., 0]
        trial = theta + step
        e_new = y - model_fn(trial, ks)
        new_cost = (wr * e_new * e_new).sum(1)
        better = torch.isfinite(new_cost) & (new_cost < cost)
        theta = torch.where(better[:, None], trial, theta)
        lam = torch.where(better, (lam / 3.0).clamp(min=1e-9), (lam * 4.0).clamp(max=1e9))
        if float(step.abs().max()) < 1e-8:
            break
    return theta


def _varpro_model(torch, vectors, y_lin, k_count: int):
    """The residuals of :func:`_varpro` and their Jacobian in closed form: (residual(theta (K * 5,), weight (K, P))
    -> (K * P,), jacobian(theta, weight) -> (K * P, K * 5), lights_b(theta, weight) -> (light vectors (K, P, 3),
    b (P, 3), the normal matrices (P, 3, 3))); y_lin (K, P) the observations."""
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)

    def light_of(t):  # (K, 5) -> light vectors (K, P, 3)
        q, r2 = vectors(t)
        return t[:, 3].exp()[:, None, None] * q / r2[..., None] ** 1.5 + t[:, 4].exp()[:, None, None] * ez

    def lights_b(theta, weight):
        light = light_of(theta.reshape(k_count, 5))
        wl = weight / y_lin ** 2
        a = torch.einsum("kp,kpi,kpj->pij", wl, light, light)
        r = torch.einsum("kp,kp,kpi->pi", wl, y_lin, light)
        tr = torch.diagonal(a, dim1=1, dim2=2).sum(-1)[:, None, None]
        a = a + torch.eye(3, dtype=a.dtype) * (1e-9 * tr + 1e-30)
        return light, torch.linalg.solve(a, r[..., None])[..., 0], a

    def residual(theta, weight):
        light, b, _ = lights_b(theta, weight)
        pred = torch.einsum("kpi,pi->kp", light, b)
        return (weight.sqrt() * (y_lin - pred) / y_lin).reshape(-1)

    one_lamp = torch.func.vmap(torch.func.jacfwd(lambda t: light_of(t[None])[0]))  # (K, 5) -> (K, P, 3, 5)

    def jacobian(theta, weight):
        # r_kp = s_kp (y_kp - L_kp . b_p) / y_kp; lamp m moves L_mp itself and b_p through A_p b_p = R_p:
        # db_p / dtheta_mc = A_p^-1 wl_mp (e_mp dL_mp,c - L_mp (dL_mp,c . b_p) - 2e-9 (dL_mp,c . L_mp) b_p),
        # e = y - L . b
        light, b, a = lights_b(theta, weight)
        d_light = one_lamp(theta.reshape(k_count, 5))  # (K, P, 3, 5)
        wl = weight / y_lin ** 2
        e = y_lin - torch.einsum("kpi,pi->kp", light, b)
        dlb = torch.einsum("kpic,pi->kpc", d_light, b)  # dL_kp,c . b_p
        g = wl[..., None, None] * (e[..., None, None] * d_light - light[..., None] * dlb[:, :, None, :])
        # the regularisation 1e-9 tr(A) moves with the lamps too
        dll = 2e-9 * wl[..., None] * torch.einsum("kpic,kpi->kpc", d_light, light)  # (K, P, 5)
        g = g - dll[:, :, None, :] * b[None, :, :, None]
        db = torch.einsum("pij,mpjc->mpci", torch.linalg.inv(a), g)  # (M, P, 5, 3)
        total = torch.einsum("kpj,mpcj->kpmc", light, db)  # (K, P, M, 5): through b
        idx = torch.arange(k_count)
        total[idx, :, idx, :] += dlb  # and directly, photo k by its own lamp
        scale = -(weight.sqrt() / y_lin)[..., None, None]
        return (scale * total).reshape(k_count * y_lin.shape[1], k_count * 5)

    return residual, jacobian, lights_b


def _varpro(torch, lamp, vectors, y_np, w_np, cauchy: float, steps: int):
    """Levenberg-Marquardt on the lamps (K, 5: x, y, log height, log intensity, log room light) with every pixel's
    albedo times normal ``b`` (3,) solved by weighted least squares for them at each evaluation (variable
    projection): photo k at pixel x is ``b(x) . (I_k (p_k - x) / |p_k - x|^3 + A_k z)``. ``vectors(lamp)`` gives
    (p_k - x (K, P, 3), |p_k - x|^2 (K, P)); y_np / w_np (K, P) log luminance and its weights; relative residuals
    under a Cauchy loss of scale ``cauchy``; the Jacobian in closed form (:func:`_varpro_model`). Returns (lamps,
    median absolute relative residual (highlights and shadows, which no lamp explains, do not move it), b (P, 3)
    for them)."""
    k_count = lamp.shape[0]
    y_lin = torch.from_numpy(np.exp(y_np))
    w_obs = torch.from_numpy(w_np)
    residual, jacobian, lights_b = _varpro_model(torch, vectors, y_lin, k_count)

    def solve_b(theta):
        e = residual(theta, w_obs).reshape(k_count, -1)
        return lights_b(theta, w_obs / (1.0 + (e / w_obs.sqrt().clamp(min=1e-9) / cauchy) ** 2))[1].numpy()

    theta = lamp.reshape(-1).clone()
    lam = 1e-3
    for _ in range(steps):
        e = residual(theta, w_obs).reshape(k_count, -1)
        irls = w_obs / (1.0 + (e / w_obs.sqrt().clamp(min=1e-9) / cauchy) ** 2)
        r = residual(theta, irls)
        jac = jacobian(theta, irls)
        jtj, jtr = jac.T @ jac, jac.T @ r
        cost = float(r @ r)
        while lam < 1e9:
            step = torch.linalg.solve(jtj + lam * torch.diag(torch.diag(jtj).clamp(min=1e-12)), -jtr)
            new = residual(theta + step, irls)
            if torch.isfinite(new).all() and float(new @ new) < cost:
                theta, lam = theta + step, max(lam / 3.0, 1e-9)
                break
            lam *= 4.0
        if lam >= 1e9 or cost - float(new @ new) < 1e-6 * cost:  # no step left that lowers the loss noticeably
            break
    e = (residual(theta, w_obs) / w_obs.reshape(-1).sqrt().clamp(min=1e-9))[w_obs.reshape(-1) > 0]
    return theta.reshape(k_count, 5), float(e.abs().median()), solve_b(theta)


class _PlaneModel(NamedTuple):
    """The functions of :func:`_plane_principled_model`."""

    residual: Callable
    parts: Callable
    residual_of: Callable
    jacobian_of: Callable


def _plane_principled_model(torch, pos, y_lin, k_count: int):
    """Photo k at plane point x under the fit's own Principled BSDF, normal +z, dielectric (metallic 0), one
    roughness for the whole sample: ``y_k(x) = c_k(x) + a(x) d_k(x)`` with ``c_k`` the specular part (the
    Principled default's, F0 0.04, as the fit takes it) and ``d_k`` the diffuse part per unit base colour
    (:func:`matcap.refine.model.shade_base_linear`) of a point lamp at ``p_k`` of intensity ``I_k`` (irradiance
    ``I_k / |p_k - x|^2``), plus a room light ``A_k`` on the diffuse part, and ``a(x)`` each pixel's base colour
    solved by weighted least squares for them. C independent sets of lamps and roughness at once. pos (P, 3) plane
    points; y_lin (K, P) the observations. Returns a :class:`_PlaneModel`: residual(theta (C, K, 5), rho (C,),
    weight (C, K, P)) -> ((C, K, P) relative residuals, a (C, P)), rho = logit(roughness); parts(theta, rho) -> (c,
    d), each (C, K, P), the BSDF evaluated once per point, with residual_of(c, d, weight), the residual from those
    parts, and jacobian_of(theta, rho, c, d, weight) -> (C, K * P, K * 5 + 1): each lamp moves its own photo and
    every base colour, the BSDF's derivatives by forward-mode autodiff, their way through the base colours'
    least-squares solve in closed form."""
    from matcap.refine.model import shade_base_linear

    n_pix = pos.shape[0]
    no_sh = torch.zeros(1, 9, 3, dtype=torch.float64)

    def parts(theta, rho):  # (C, K, 5) lamps (x, y, log height, log intensity, log room light) -> c, d (C, K, P)
        c_count = theta.shape[0]
        t = theta.reshape(-1, 5)
        q = torch.cat([t[:, None, :2] - pos[None, :, :2], t[:, 2].exp()[:, None, None].expand(-1, n_pix, 1)], -1)
        r2 = (q * q).sum(-1)
        count = q.shape[0] * n_pix  # every lamp and pixel as one pixel of one light (a roughness per combination)
        normal = torch.zeros(count, 3, dtype=torch.float64)
        normal[:, 2] = 1.0
        rough = torch.sigmoid(rho)[:, None].expand(c_count, k_count * n_pix).reshape(-1)
        irradiance = (t[:, 3].exp()[:, None] / r2).reshape(1, count, 1).expand(1, count, 3)
        const, per_base = shade_base_linear(normal, rough, torch.zeros(count, dtype=torch.float64),
                                            (q * r2.rsqrt()[..., None]).reshape(1, count, 3), irradiance, no_sh)
        shape = (c_count, k_count, n_pix)
        return const[0, :, 0].reshape(shape), per_base[0, :, 0].reshape(shape) + t[:, 4].exp().reshape(
            c_count, k_count, 1)

    def derivatives(theta, rho):  # -> dc, dd (6, C, K, P): by each lamp's 5 parameters, then by rho
        eye = torch.eye(6, dtype=torch.float64)
        tangents = eye[:, None, None, :5].expand(6, *theta.shape), eye[:, 5, None].expand(6, *rho.shape)
        return torch.func.vmap(lambda tt, tr: torch.func.jvp(parts, (theta, rho), (tt, tr))[1])(*tangents)

    def base_of(const, per, weight):
        wl = weight / y_lin ** 2
        return ((wl * (y_lin - const) * per).sum(1) / (wl * per * per).sum(1).clamp(min=1e-30)).clamp(min=0.0)

    def residual_of(const, per, weight):
        a = base_of(const, per, weight)
        return weight.sqrt() * (y_lin - const - a[:, None] * per) / y_lin, a

    def residual(theta, rho, weight):
        return residual_of(*parts(theta, rho), weight)

    def jacobian_of(theta, rho, const, per, weight):
        # r_jx = s_jx (y_jx - c_jx - a_x d_jx) / y_jx; lamp k moves c_k, d_k and a_x = N_x / D_x through
        # dN_x = wl_kx ((y_kx - c_kx) dd_kx - d_kx dc_kx), dD_x = 2 wl_kx d_kx dd_kx (where a_x > 0)
        c_count = theta.shape[0]
        a = base_of(const, per, weight)
        dc, dd = (d.permute(1, 2, 3, 0) for d in derivatives(theta, rho))  # (C, K, P, 6)
        wl = weight / y_lin ** 2
        den = (wl * per * per).sum(1).clamp(min=1e-30)
        free = (a > 0).to(a.dtype)
        g = wl[..., None] * ((y_lin - const)[..., None] * dd - per[..., None] * dc
                             - 2.0 * a[:, None, :, None] * per[..., None] * dd)  # (C, K, P, 6)
        da = g / den[:, None, :, None] * free[:, None, :, None]  # da_x / d(parameter of lamp k), and of rho
        da_rho = da[..., 5].sum(1)  # (C, P): rho moves every photo
        s = -(weight.sqrt() / y_lin)
        own = s[..., None] * (dc + a[:, None, :, None] * dd)  # (C, K, P, 6): photo k by its own lamp (and rho)
        jac = (s * per)[..., None, None] * da[..., :5].permute(0, 2, 1, 3)[:, None]  # (C, K, P, K, 5)
        jac = jac + own[:, :, :, None, :5] * torch.eye(k_count, dtype=torch.float64)[None, :, None, :, None]
        j_rho = own[..., 5] + s * per * da_rho[:, None]
        return torch.cat([jac.reshape(c_count, -1, k_count * 5), j_rho.reshape(c_count, -1, 1)], -1)

    return _PlaneModel(residual, parts, residual_of, jacobian_of)


def _plane_principled(torch, lamps, rough, pos, y_np, w_np, cauchy: float, steps: int,
                      hold_roughness: bool = False):
    """Levenberg-Marquardt on C independent starts at once, each the lamps (K, 5: x, y, log height, log intensity,
    log room light) and one roughness under :func:`_plane_principled_model`, relative residuals under a Cauchy loss
    of scale ``cauchy`` (by reweighting); ``hold_roughness``: the roughness stays. lamps (C, K, 5), rough (C,) start
    roughnesses. Returns (lamps (C, K, 5), logit(roughness) (C,), the mean Cauchy loss per weighted observation (C,),
    infinite where it is not finite)."""
    c_count, k_count = lamps.shape[:2]
    y_lin = torch.from_numpy(np.exp(y_np))
    w_obs = torch.from_numpy(w_np)
    model = _plane_principled_model(torch, pos, y_lin, k_count)
    scale = w_obs.sqrt().clamp(min=1e-9)
    w_all = w_obs.expand(c_count, -1, -1)
    theta = lamps.clone()
    rough = torch.as_tensor(rough, dtype=torch.float64)
    rho = torch.log(rough / (1.0 - rough))
    lam = torch.full((c_count,), 1e-3, dtype=torch.float64)
    done = torch.zeros(c_count, dtype=torch.bool)
    const, per = model.parts(theta, rho)  # the BSDF's parts at the current lamps, kept from an accepted trial
    for _ in range(steps):
        irls = w_obs / (1.0 + (model.residual_of(const, per, w_all)[0] / scale / cauchy) ** 2)
        r = model.residual_of(const, per, irls)[0].reshape(c_count, -1)
        jac = model.jacobian_of(theta, rho, const, per, irls)  # (C, K * P, K * 5 + 1)
        if hold_roughness:
            jac[..., -1] = 0.0
        jtj, jtr = jac.transpose(1, 2) @ jac, (jac.transpose(1, 2) @ r[..., None])[..., 0]
        cost = (r * r).sum(1)
        lost = ~(torch.isfinite(jtj).flatten(1).all(1) & torch.isfinite(jtr).all(1) & torch.isfinite(cost))
        done |= lost  # a start that ran off to infinities stops there (its loss says so)
        jtj = torch.where(lost[:, None, None], torch.eye(jtj.shape[1], dtype=jtj.dtype), jtj)
        jtr = torch.where(lost[:, None], 0.0, jtr)
        damp = lam[:, None, None] * torch.diag_embed(torch.diagonal(jtj, dim1=1, dim2=2).clamp(min=1e-12))
        step = torch.linalg.solve(jtj + damp, -jtr[..., None])[..., 0]
        trial_theta, trial_rho = theta + step[:, :-1].reshape(c_count, k_count, 5), rho + step[:, -1]
        trial_parts = model.parts(trial_theta, trial_rho)
        trial = model.residual_of(*trial_parts, irls)[0].reshape(c_count, -1)
        new_cost = (trial * trial).sum(1)
        better = torch.isfinite(new_cost) & (new_cost < cost) & ~done
        theta = torch.where(better[:, None, None], trial_theta, theta)
        rho = torch.where(better, trial_rho, rho)
        const, per = (torch.where(better[:, None, None], t, c) for t, c in zip(trial_parts, (const, per)))
        lam = torch.where(better, (lam / 3.0).clamp(min=1e-9), lam * 4.0)
        # a start is done where no step is left that lowers its loss noticeably
        done |= (lam >= 1e9) | (better & (cost - new_cost < 1e-7 * cost))
        if bool(done.all()):
            break
    e = model.residual_of(const, per, w_all)[0] / scale
    loss = (w_obs * torch.log1p((e / cauchy) ** 2)).sum((1, 2)) / w_obs.sum().clamp(min=1.0)
    return theta, rho, torch.where(torch.isfinite(loss), loss, torch.full_like(loss, math.inf))


def _principled_lamps(torch, lum, mask, lamp, centre, width: float, side: int, widths: tuple[float, ...],
                      roughness: tuple[float, ...], cauchy: float, steps: int, check_side: int):
    """Step 3 of :func:`plane_lamps`: lum (K, H, W) the photos' dominant channel, lamp (K, 5) step 2's lamps.

    Levenberg-Marquardt (:func:`_plane_principled`) from step 2's lamps and from their feet (x, y) at ``widths``
    sample widths from the centre, each with every start roughness of ``roughness`` held for ``steps`` steps (a
    roughness free from the start runs off to 1, where a glossy sample's highlights pass for outliers), then free
    for ``2 * steps``. Returns (lamps (K, 5), roughness) of the start that ends with the lowest loss, and their
    median absolute relative residual on a copy whose longer side is ``check_side`` (base colours re-solved
    there)."""
    from matcap.refine.model import plane_positions

    def copy(longer: int):
        small, keep = _small(lum, mask, longer)
        y_np, w_np = _log_obs(small, keep)
        rows, cols = np.nonzero(keep)
        return plane_positions(torch.from_numpy(rows), torch.from_numpy(cols), *keep.shape).double(), y_np, w_np

    pos, y_np, w_np = copy(side)
    starts = [lamp.clone()]
    level = torch.from_numpy(np.median(np.exp(y_np), axis=1))
    for sw in widths:
        dist = sw * width
        start = lamp.clone()
        off2 = ((start[:, :2] - centre[:2]) ** 2).sum(1)
        start[:, 2] = 0.5 * torch.log(torch.clamp(dist ** 2 - off2, min=(0.3 * dist) ** 2))
        start[:, 3] = torch.log(4.0 * level * dist ** 2)  # a mid-grey plane's level at that distance
        starts.append(start)
    for start in starts:
        start[:, 4] = start[:, 3] - 8.0  # a faint room light
    lamps = torch.stack([start for start in starts for _ in roughness])
    rough = torch.tensor([r0 for _ in starts for r0 in roughness], dtype=torch.float64)
    held = _plane_principled(torch, lamps, rough, pos, y_np, w_np, cauchy, steps, hold_roughness=True)
    lamps, rho, loss = _plane_principled(torch, held[0], rough, pos, y_np, w_np, cauchy, 2 * steps)
    best = int(loss.argmin())
    lamp, rho = lamps[best], rho[best]
    pos, y_np, w_np = copy(check_side)
    w_obs = torch.from_numpy(w_np)
    residual = _plane_principled_model(torch, pos, torch.from_numpy(np.exp(y_np)), lamp.shape[0]).residual
    e = residual(lamp[None], rho[None], w_obs[None])[0][0] / w_obs.sqrt().clamp(min=1e-9)
    return lamp, float(torch.sigmoid(rho)), float(e[w_obs > 0].abs().median())


def plane_lamps(images, mask: np.ndarray, *, side: int = 32, steps: int = 30, cauchy: float = 0.05,
                starts_widths: tuple[float, ...] = (0.75, 1.5, 3.0, 6.0), principled_side: int = 16,
                principled_widths: tuple[float, ...] = (3.0,),
                principled_roughness: tuple[float, ...] = (0.15, 0.5), on_stage=None) -> PlaneLamps:
    """The lamp of every photo of a flat sample, from the falloff of its light over the plane.

    images: K (H, W, 3) linear RGB photos (any common scale); mask: (H, W) bool, the sample. Steps 1 and 2 see each
    pixel's diffuse light (:func:`_diffuse_channel`: a coloured pixel's channel spread, free of its highlights;
    a pale one's brightest channel), step 3 the brightest channel, highlights and all. Fitted on a copy whose
    longer side is ``side`` pixels, in two stages, each by Levenberg-Marquardt per lamp with a Cauchy loss of scale
    ``cauchy`` (log units: highlights and cast shadows weigh little); clipped and black observations left out.

    1. The plane: every normal the camera axis (+z); photo k's log luminance at plane point x is
       ``a(x) + log(I_k h_k / |p_k - x|^3 + A_k)``: a per-pixel log albedo ``a`` shared by the photos (re-solved as
       the weighted mean between steps), a lamp at ``p_k`` (``h_k`` its height) of intensity ``I_k``, a faint room
       light ``A_k``. From several start distances (``starts_widths``, in sample widths; every lamp above the
       brightest part of its photo relative to the others); each photo keeps its best.
    2. Near-light photometric stereo: the lamps (and their room light) again, now with every pixel's albedo times
       normal solved by least squares under the lamps' per-pixel light vectors at each step (variable projection:
       the surface's small tilts, which shade every photo differently, are no longer taken for falloff). At most
       ``4 * steps`` steps; the residuals are relative, so every photo weighs alike. The same with every lamp
       distant gives ``residual_distant``: distant lamps leave no falloff to place them.
    3. The plane under the fit's own Principled BSDF (:func:`_plane_principled`, on a copy whose longer side is
       ``principled_side``): normals +z, each pixel's base colour solved for the lamps, one roughness, so that a
       glossy sample's highlight places its lamp and the diffuse falloff is Burley's, not Lambert's. (Step 2's free
       normals leave the lamps' elevations weakly held: a tilt of every normal and a lower lamp explain a
       Lambertian falloff about alike.) Started from step 2's lamps and from their feet at ``principled_widths``
       sample widths, each at every roughness of ``principled_roughness`` (:func:`_principled_lamps`); the start
       that ends with the lowest loss gives the positions where the plane explains the photos about as closely as
       step 2's free normals do (median absolute relative residual on step 2's copy at most :data:`PLANE_GAIN`
       times that of step 2's lamps, both on the brightest channel); elsewhere (a sample whose tilts shade it
       visibly) step 2's lamps stay.

    ``on_stage()``, where given, is called as each of the three steps ends (progress).
    """
    import torch

    from matcap.refine.model import plane_positions

    mask = np.asarray(mask, bool)
    k_count = len(images)
    if k_count < 3:
        raise MatcapError(f"finding the lamps of a flat sample needs at least 3 photos, got {k_count}")
    lum = _dominant_channel(images)
    if lum.shape[1:] != mask.shape:
        raise MatcapError(f"the mask is {mask.shape[1]}x{mask.shape[0]} but the photos {lum.shape[2]}x{lum.shape[1]}")
    h, w = mask.shape
    small, keep = _small(_diffuse_channel(images, mask, lum), mask, side)
    if keep.sum() < 16:
        raise MatcapError("the flat sample's mask is too small to find its lamps (fewer than 16 pixels at "
                          f"{small.shape[2]}x{small.shape[1]})")
    y_np, w_np = _log_obs(small, keep)
    rows, cols = np.nonzero(keep)
    pos = plane_positions(torch.from_numpy(rows), torch.from_numpy(cols), *keep.shape).double()
    full_rows, full_cols = np.nonzero(mask)
    centre = plane_positions(torch.from_numpy(full_rows), torch.from_numpy(full_cols), h, w).double().mean(0)
    xy = pos[:, :2]
    width = float(max((xy[:, 0].max() - xy[:, 0].min()), (xy[:, 1].max() - xy[:, 1].min()))) + 2.0 / keep.shape[1]
    y = torch.from_numpy(y_np)
    w_obs = torch.from_numpy(w_np)

    def vectors(lamp, distant: bool = False):  # (K, 5) lamps -> (K, P, 3) p_k - x, (K, P) |p_k - x|^2
        xy_k = lamp[:, None, :2] - (0.0 if distant else pos[None, :, :2])
        q = torch.cat([xy_k.expand(-1, len(pos), 2), lamp[:, 2].exp()[:, None, None].expand(-1, len(pos), 1)], -1)
        return q, (q * q).sum(-1)

    # ---- 1. the plane
    ratio = y_np - (y_np * w_np).sum(0) / np.maximum(w_np.sum(0), 1e-9)
    ratio = np.where(w_np > 0, ratio, -np.inf)
    top = np.argsort(ratio, axis=1)[:, -max(4, len(rows) // 50):]
    foot = torch.from_numpy(np.stack([xy.numpy()[t].mean(0) for t in top]))  # (K, 2)
    alpha = torch.zeros(len(pos), dtype=torch.float64)

    def plane_fn(t, k):  # t: x, y, log height, log intensity, log ambient
        q = torch.cat([t[:2] - pos[:, :2], t[2].exp().expand(len(pos), 1)], -1)
        direct = t[3] + torch.log(q[:, 2]) - 1.5 * torch.log((q * q).sum(-1))
        return alpha + torch.logaddexp(direct, t[4].expand_as(direct))

    def plane_model(theta):  # (K, 5) -> (K, P)
        return torch.func.vmap(plane_fn, in_dims=(0, 0))(theta, torch.arange(k_count))

    def per_photo_loss(theta):
        e = y - plane_model(theta)
        return (w_obs * torch.log1p((e / cauchy) ** 2)).sum(1) / w_obs.sum(1).clamp(min=1.0)

    tried = []
    for sw in starts_widths:
        dist = sw * width
        height = torch.sqrt(torch.clamp(dist ** 2 - ((foot - centre[:2]) ** 2).sum(1), min=(0.3 * dist) ** 2))
        theta = torch.cat([foot, torch.log(height)[:, None], torch.zeros(k_count, 2, dtype=torch.float64)], 1)
        alpha = torch.zeros(len(pos), dtype=torch.float64)
        for it in range(4):
            if it == 0:  # start: intensities at the mean level, a room light 5 log units fainter
                theta[:, 4] = -60.0
                theta[:, 3] = ((y - plane_model(theta)) * w_obs).sum(1) / w_obs.sum(1)
                theta[:, 4] = theta[:, 3] - 3.0 * torch.log(torch.tensor(dist)) - 5.0
            theta = _lamp_lm(torch, theta, plane_fn, y, w_obs, cauchy, steps)
            model = plane_model(theta) - alpha
            alpha = ((y - model) * w_obs).sum(0) / w_obs.sum(0).clamp(min=1e-9)
        tried.append((theta, per_photo_loss(theta), alpha))
    losses = torch.stack([lo for _, lo, _ in tried])

    best = losses.argmin(0)
    lamp = torch.stack([tried[int(b)][0][k] for k, b in enumerate(best)])
    alpha = tried[int(losses.sum(1).argmin())][2]

    stage_done = on_stage if on_stage is not None else (lambda: None)
    stage_done()
    # ---- 2. near-light photometric stereo: the lamps with every pixel's albedo times normal solved for them
    lamp, resid, _ = _varpro(torch, lamp, vectors, y_np, w_np, cauchy, 4 * steps)
    _, resid_distant, _ = _varpro(torch, lamp, lambda t: vectors(t, distant=True), y_np, w_np, cauchy, 4 * steps)
    resid_bright = _varpro(torch, lamp, vectors, *_log_obs(*_small(lum, mask, side)), cauchy, 0)[1]  # as step 3 sees
    stage_done()
    # ---- 3. the plane under the Principled BSDF (where the falloff placed the lamps at all)
    rough, resid_plane = math.nan, math.nan
    if _placed(resid, resid_distant):
        plane, rough, resid_plane = _principled_lamps(torch, lum, mask, lamp, centre, width, principled_side,
                                                      principled_widths, principled_roughness, cauchy,
                                                      2 * steps, side)
        if _plane_better(resid_plane, resid_bright):
            lamp = plane
    stage_done()
    positions = torch.cat([lamp[:, :2], lamp[:, 2:3].exp()], 1)
    rel = positions - centre
    dist = rel.norm(dim=1)
    irr = torch.exp(lamp[:, 3]) / dist ** 2  # at the centre, on a surface facing the lamp (relative)
    irr = irr / irr.mean()
    return PlaneLamps(positions.numpy(), (rel / dist[:, None]).numpy(), dist.numpy(), irr.numpy(), centre.numpy(),
                      width, resid, resid_distant, resid_plane, rough, resid_bright)



#: The falloff placed the lamps where their distances cut the residual of distant lamps to at most this share of it
#: (rendered swatches: 0.03-0.6 under lamps 1-3 widths away, 0.87 or more under distant lights)
NEAR_GAIN = 0.7
#: ... and that residual (relative RMS) is at least this: a falloff that shows above the photos' noise.
NEAR_FLOOR = 0.005


#: Step 3 of :func:`plane_lamps` (the plane under the Principled BSDF, normals +z) places the lamps where its
#: residual is at most this multiple of step 2's, whose free normals explain a visibly tilted sample's shading.
PLANE_GAIN = 1.3


def _plane_better(residual_plane: float, residual: float) -> bool:
    """Whether step 3's lamps replace step 2's (:attr:`PlaneLamps.plane_placed`; false where step 3 did not run:
    NaN)."""
    return bool(residual_plane <= PLANE_GAIN * residual)


def _placed(residual: float, residual_distant: float) -> bool:
    """Whether near lamps explain the photos clearly better than distant ones (:attr:`PlaneLamps.near`)."""
    return residual_distant >= NEAR_FLOOR and residual <= NEAR_GAIN * residual_distant


class FlatLights(NamedTuple):
    """What :func:`flat_lights` found for a flat sample's photos."""

    lights: KnownLights | None
    """:class:`matcap.lightfiles.KnownLights` of point lights (intensities left to the fit), to be held by the fit;
    None where the falloff did not place them (:attr:`PlaneLamps.near`: distant lamps)."""
    record: dict
    """fit.json's ``flat`` record: how the lamps were found, their distances in sample widths."""


def flat_lights(images, mask: np.ndarray, on_stage=None) -> FlatLights:
    """The lamps of a flat sample's photos (``images``: K (H, W, 3) linear RGB; ``mask``: (H, W) bool, the sample),
    from the falloff of their light over the plane (:func:`plane_lamps`). ``on_stage``: as :func:`plane_lamps`."""
    from matcap.lightfiles import KnownLights

    lamps = plane_lamps(images, mask, on_stage=on_stage)
    widths = lamps.distance_widths
    record = {"lamps": "near" if lamps.near else "distant", "found_from": "the falloff over the plane",
              "residual": round(lamps.residual, 5), "residual_distant_lamps": round(lamps.residual_distant, 5)}
    if not lamps.near:
        return FlatLights(None, record)
    record.update({"distance_widths_median": round(float(np.median(widths)), 3),
                   "distance_widths": [round(float(v), 3) for v in widths], "sample_width": round(lamps.width, 5),
                   "placed_by": "the plane under the Principled BSDF" if lamps.plane_placed else
                   "near-light photometric stereo", "residual_plane": round(lamps.residual_plane, 5),
                   "residual_bright_channel": round(lamps.residual_bright, 5),
                   "plane_roughness": round(lamps.roughness, 3)})
    known = KnownLights(lamps.directions.astype(np.float64), None, "estimated", "", "order",
                        lamps.positions.astype(np.float64))
    return FlatLights(known, record)

"""What every stage of the fit works on: the photos in the fit's units, the pixels' problems and loss, progress.

* :func:`_prepare` (the fit's first stage): checks, the photos scaled so that their mean over the mask is 0.5 (the
  fit's units), each photo's clipping level, the light-variation weight (:func:`light_variation`); the light
  stage's downsampled copy of the photos comes from :meth:`_Photos.light_copy`;
* :class:`_Problem`: the observations (K, N, 3) of N pixels with their priors and bounds, and :func:`_loss`, the
  robust data term plus the priors that the light and pixel stages minimise;
* the model's prediction (:func:`_shade`, :func:`_predict`), the ambient's share of the light
  (:func:`ambient_share`), ``lights.json`` entries (:func:`lights_to_entries`), threads and the progress bar.
"""
from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from matcap.errors import MatcapError
from matcap.normals import unit_normals
from matcap.refine.settings import RefineSettings
from scenes.materialmaps import MaterialMaps


LUMA = (0.2126, 0.7152, 0.0722)


def check_inputs(images, mask: np.ndarray) -> np.ndarray:
    """(K, H, W, 3) float32 stack of ``images``; one-line MatcapError for <2 images, NaN/Inf, all-dark photos."""
    if len(images) < 2:
        raise MatcapError(f"refinement needs at least 2 photos, got {len(images)}")
    stack = np.stack([np.asarray(im, dtype=np.float32) for im in images])
    if stack.ndim != 4 or stack.shape[3] != 3:
        raise MatcapError(f"expected (H, W, 3) RGB photos, got {stack.shape[1:]}")
    if mask.shape != stack.shape[1:3]:
        raise MatcapError(f"mask is {mask.shape}, photos are {stack.shape[1:3]}")
    bad = ~np.isfinite(stack)
    if bad.any():
        k = int(np.argmax(bad.reshape(len(stack), -1).any(axis=1)))
        raise MatcapError(f"photo {k} holds NaN or Inf values; refinement needs finite pixels")
    if not mask.any():
        raise MatcapError("the mask is empty: nothing to refine")
    means = stack[:, mask].mean(axis=(1, 2))
    if not (means > 1e-6).any():
        raise MatcapError("every photo is black on the object: nothing to fit (check the exposure)")
    return np.clip(stack, 0.0, None)


def clipping_level(photo: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(3,) float32: where photo (H, W, 3) clips, per channel: 0.999 of its maximum over ``mask`` (H, W) bool; inf for
    a channel that is black there. An observation at or above it is clipped: a lower bound only."""
    level = (np.asarray(photo)[mask].max(axis=0) * 0.999).astype(np.float32)
    return np.where(level > 0, level, np.inf).astype(np.float32)


def light_variation(stack: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-pixel light variation (H, W): std / mean over the photos of the pixel's luminance (NaN off-mask).

    Near 0 where the lighting barely changes between photos (a weak moving light under a strong fixed one, a
    region outside a spot light): there the photos cannot tell the normal or the BRDF apart.
    """
    lum = np.tensordot(stack, np.float32(LUMA), axes=([3], [0]))  # (K, H, W)
    mean = lum.mean(axis=0)
    std = lum.std(axis=0)
    v = np.where(mean > 1e-6, std / np.maximum(mean, 1e-6), 0.0).astype(np.float32)
    return np.where(mask, v, np.nan).astype(np.float32)


def variation_warning(variation: np.ndarray, mask: np.ndarray, threshold: float) -> tuple[float, str | None]:
    """(fraction of mask pixels below ``threshold``, one-line warning or None when under 5 %)."""
    frac = float((variation[mask] < threshold).mean())
    if frac < 0.05:
        return frac, None
    return frac, (f"light variation: {frac:.0%} of the object's pixels barely change between photos (std/mean "
                  f"< {threshold:g}); their maps are guesses and weigh less in the fit: move the light further "
                  f"off-axis between photos (and dim any fixed light)")


def _resize(arr: np.ndarray, hw: tuple[int, int], interp: str = "area") -> np.ndarray:
    import cv2

    flag = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}[interp]
    out = cv2.resize(np.ascontiguousarray(arr, dtype=np.float32), (hw[1], hw[0]), interpolation=flag)
    if arr.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out


def _maps_arrays(maps: MaterialMaps) -> dict[str, np.ndarray]:
    m = maps.with_defaults()
    n = np.asarray(m.normal, np.float32).copy()
    n[~m.mask] = (0.0, 0.0, 1.0)
    return {"normal": unit_normals(n), "base": np.clip(np.nan_to_num(m.base_color), 0, 1).astype(np.float32),
            "rough": np.clip(np.nan_to_num(m.roughness, nan=0.5), 0, 1).astype(np.float32),
            "metal": np.clip(np.nan_to_num(m.metallic), 0, 1).astype(np.float32)}


def _downsample(stack: np.ndarray, mask: np.ndarray, arrays: dict[str, np.ndarray], hw: tuple[int, int]):
    small = np.stack([_resize(im, hw) for im in stack])
    cover = _resize(mask.astype(np.float32), hw)
    m = cover > 0.99
    if m.sum() < 16:
        m = cover > 0.5
    out = {}
    for k, v in arrays.items():
        out[k] = _resize(v, hw)
    for k in ("normal", "start"):
        if k in out:
            out[k] = unit_normals(out[k])
    return small, m, out


@dataclass
class _Photos:
    """The photos ready for the fit (:func:`_prepare`).

    mask (H, W); obs (K, H, W, 3) photos in fit units (their mean over the mask is 0.5); scale: fit units per
    photo unit; sat_level (K, 3) each photo's clipping level per channel in fit units (inf for a black channel);
    arrays: the networks' maps as "normal", "base", "rough", "metal"; variation (H, W) light variation (NaN
    off-mask); weak_fraction and warning: its diagnostic (:func:`variation_warning`); weight (H, W) per-pixel
    data weight (weakly lit pixels weigh less, down to 0.1)."""

    mask: np.ndarray
    obs: np.ndarray
    scale: float
    sat_level: np.ndarray
    arrays: dict[str, np.ndarray]
    variation: np.ndarray
    weak_fraction: float
    warning: str | None
    weight: np.ndarray

    def light_copy(self, side: int):
        """((h, w), (obs, mask, arrays, weight)) of the copy the light fit runs on: longer side at most ``side``
        pixels (these arrays themselves where they are no larger)."""
        h, w = self.mask.shape
        f = min(1.0, side / max(h, w))
        hw = (max(8, round(h * f)), max(8, round(w * f)))
        if hw == (h, w):
            return hw, (self.obs, self.mask, self.arrays, self.weight)
        return hw, (*_downsample(self.obs, self.mask, self.arrays, hw), _resize(self.weight, hw))


def _prepare(images, maps: MaterialMaps, s: RefineSettings) -> _Photos:
    """The first stage of the fit: the photos checked (:func:`check_inputs`, the maps' size), scaled to fit units,
    their clipping levels and light variation measured."""
    mask = np.asarray(maps.mask, bool)
    stack = check_inputs(images, mask)
    if stack.shape[1:3] != maps.shape:
        raise MatcapError(f"photos are {stack.shape[2]}x{stack.shape[1]} but the maps {maps.shape[1]}x{maps.shape[0]}")
    scale = 0.5 / float(stack[:, mask].mean())
    obs = stack * scale
    sat_level = np.stack([clipping_level(o, mask) for o in obs])
    variation = light_variation(stack, mask)
    frac_weak, warning = variation_warning(variation, mask, s.loss.variation_threshold)
    weight = np.clip(np.nan_to_num(variation) / s.loss.variation_threshold, 0.1, 1.0).astype(np.float32)
    return _Photos(mask, obs, scale, sat_level, _maps_arrays(maps), variation, frac_weak, warning, weight)


#: Fit units (the photos' mean over the mask is 0.5): how far below the prediction a cast-shadowed observation is
#: at least.
SHADOW_GAP = 0.05


class _Problem:
    """Observations of N pixels: obs (K, N, 3), weight (N,), positions, priors (torch); shadow: the share of the
    lamp's light below which an observation counts as cast shadow (0: none; ``loss.shadow``); ambient_sh
    (K|1, 9, 3) or None: the SH ambient of the lights the fit holds (fit units), which a cast shadow leaves.
    upper (K, N, 3): the residual (prediction - observation) above which an observation adds none: 0 exactly where
    it is clipped (at its photo's ``sat_level``: a lower bound only), the cast-shadow level where ``shadow`` is set
    (an observation whose excess over the ambient's part of the model is below ``shadow`` times the lamp's part, and
    at least :data:`SHADOW_GAP` below the prediction: an upper bound only), else infinite. The ambient's part is
    taken at the start maps (normals ``start``, the priors' base colour, roughness and metallic)."""

    def __init__(self, torch, stack, mask, arrays, weight, sat_level, device, idx=None, start=None,
                 shadow: float = 0.0, ambient_sh=None):
        rows, cols = np.nonzero(mask)
        if idx is not None:
            rows, cols = rows[idx], cols[idx]
        self.rows, self.cols = rows, cols
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(device)  # noqa: E731
        self.obs = t(stack[:, rows, cols])
        self.weight = t(weight[rows, cols])
        self.n0 = t(arrays["normal"][rows, cols])
        self.b0 = t(arrays["base"][rows, cols])
        self.r0 = t(arrays["rough"][rows, cols])
        self.m0 = t(arrays["metal"][rows, cols])
        self.ns = self.n0 if start is None else t(start[rows, cols])  # start normals (the prior is n0)
        if shadow > 0:
            # with A the ambient's part and P the prediction: obs - A < shadow (P - A) and P - obs > gap  <=>
            # P - obs > max((obs - A) (1 / shadow - 1), gap)
            above = self.obs if ambient_sh is None else self.obs - self._ambient_part(torch, ambient_sh)
            level = (above * (1.0 / shadow - 1.0)).clamp(min=SHADOW_GAP)
        else:
            level = torch.full_like(self.obs, float("inf"))
        self.upper = torch.where(self.obs >= t(sat_level)[:, None, :], torch.zeros_like(level), level)
        from matcap.refine.model import plane_positions

        h, w = mask.shape
        self.pos = plane_positions(torch.from_numpy(rows), torch.from_numpy(cols), h, w).to(device)
        self.backdrop = None  # (K, N, 3): what lies behind each pixel, where it mixes the object with it

    def _ambient_part(self, torch, ambient_sh):
        """(K|1, N, 3): the model's response to the SH ambient ``ambient_sh`` (K|1, 9, 3) alone, at the start maps:
        the diffuse albedo (1 - metallic) base / pi times the SH irradiance."""
        from matcap.refine.model import sh_irradiance

        return sh_irradiance(self.ns, ambient_sh) * ((1.0 - self.m0)[:, None] * self.b0 / math.pi)[None]

    def __len__(self) -> int:
        return len(self.rows)

    def part(self, sl) -> "_Problem":
        """The pixels ``sl`` (a slice or an index array) of this problem."""
        tsl = sl if isinstance(sl, slice) else __import__("torch").from_numpy(np.asarray(sl)).to(self.obs.device)
        new = self.take(tsl)
        new.rows, new.cols = self.rows[sl], self.cols[sl]
        return new

    def take(self, tsl) -> "_Problem":
        """The torch tensors alone at pixels ``tsl`` (a slice or an index tensor on the device), without the pixel
        coordinates: usable inside ``torch.func`` transforms, where an index cannot become numpy."""
        new = object.__new__(_Problem)
        new.obs, new.upper = self.obs[:, tsl], self.upper[:, tsl]
        for k in ("weight", "n0", "ns", "b0", "r0", "m0", "pos"):
            setattr(new, k, getattr(self, k)[tsl])
        new.backdrop = None if self.backdrop is None else self.backdrop[:, tsl]
        return new


def _loss(torch, prob: _Problem, px, lights, s: RefineSettings, c: float, brdf: bool = True):
    """Per-pixel loss (N,) (data + prior) and the data part alone."""
    n = px.normal()
    b = px.base()
    r = px.rough() if brdf else prob.r0
    m = px.metal() if brdf else prob.m0
    pred = _shade(lights, prob.pos, n, b, r, m)
    res = pred - prob.obs
    res = torch.where(res > prob.upper, torch.zeros_like(res), res)  # clipped: a lower bound; cast shadow: an upper
    rho = torch.log1p((res / c) ** 2)
    data = rho.mean(-1).sum(0) * prob.weight
    prior = s.priors.normal * ((n - prob.n0) ** 2).sum(-1)
    prior = prior + s.priors.base * ((torch.log(b + 0.02) - torch.log(prob.b0 + 0.02)) ** 2).mean(-1)
    if brdf:
        prior = prior + s.priors.rough * (r - prob.r0) ** 2 + s.priors.metal * (m - prob.m0) ** 2
    return data + prior, data


def _shade(lights, pos, n, b, r, m):
    from matcap.refine.model import shade_fast

    wo, irr = lights.incident(pos)
    return shade_fast(n, b, r, m, wo, irr, lights.sh)


def _luminance(obs, rows, cols) -> np.ndarray:
    """(K, P) luminance of the photos ``obs`` (K, H, W, 3) at pixels ``rows``, ``cols``."""
    return np.tensordot(obs[:, rows, cols], np.asarray(LUMA, np.float32), axes=([2], [0]))


def _centre(torch, mask: np.ndarray):
    """(3,) plane position of the mask's centroid: where near lights' directions and irradiances refer to."""
    from matcap.refine.model import plane_positions

    rows, cols = np.nonzero(mask)
    return plane_positions(torch.from_numpy(rows), torch.from_numpy(cols), *mask.shape).mean(0)


def _plane_normals(mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32: every pixel of ``mask``'s frame facing the camera (+z), a flat sample's own normal."""
    plane = np.zeros(mask.shape + (3,), np.float32)
    plane[..., 2] = 1.0
    return plane


def _median_distance(lights) -> float:
    """Median distance of near lights from the object's centre, in half-widths of the framing plane (inf: at
    None: at least half of them are distant, farther than 10^6)."""
    u = float(lights.inv_distance.clamp(min=0.0).median())
    return round(1.0 / u, 3) if u > 1e-6 else None


def ambient_share(torch, lights, pos, normal) -> float:
    """Share of the object's irradiance (luminance, mean over pixels and photos) that the fixed SH ambient gives
    against the photos' own lights: near 0 for one lamp per photo in a dark room, large for environment light.

    lights: :class:`matcap.refine.model.LightParams`; pos (N, 3) plane positions; normal (N, 3) unit normals."""
    a, d = _irradiance_parts(torch, lights, pos, normal)
    return a / max(a + d, 1e-12)


def _irradiance_parts(torch, lights, pos, normal) -> tuple[float, float]:
    """(ambient, direct): the luminance irradiance of the SH ambient and of the photos' own lights at the pixels
    ``pos`` (N, 3) with ``normal`` (N, 3), each summed over the pixels and averaged over the photos."""
    from matcap.refine.model import sh_irradiance

    luma = torch.tensor(LUMA, dtype=normal.dtype, device=normal.device)
    amb = (sh_irradiance(normal, lights.sh) * luma).sum(-1).clamp(min=0.0)  # (K|1, N)
    wo, irr = lights.incident(pos)
    direct = (normal[None] * wo).sum(-1).clamp(min=0.0) * (irr * luma).sum(-1)  # (K, N)
    return float(amb.mean(0).sum()), float(direct.mean(0).sum())


class _Stopped(Exception):
    """A chunk of the per-pixel solve abandoned because another one failed or the fit was interrupted."""


@contextlib.contextmanager
def _one_thread(torch):
    """torch's operations on one thread inside the block (its own setting restored after): the fit's operations are
    many and small, and a team of OpenMP threads meets at a barrier after each; where another job holds a core, the
    team waits for the thread it lost at every operation (and spins while it waits)."""
    was = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield was
    finally:
        torch.set_num_threads(was)


def _workers(threads: int) -> int:
    """Threads for the per-pixel solve's chunks: torch's thread count, at most the CPUs this process may use."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return max(1, min(threads, cpus))


def _free(sub: _Problem, res):
    """(K, P, 3) True where an observation adds a residual: not a clipped one the model exceeds (a clipped photo
    only bounds the model from below) and not a cast-shadowed one the model exceeds enough (``sub.upper``)."""
    return res <= sub.upper


def _predict(torch, prob: _Problem, px, lights, s) -> np.ndarray:
    outs = []
    with torch.no_grad():
        for i in range(0, len(prob), s.pixels.chunk):
            sl = slice(i, i + s.pixels.chunk)
            part = prob.part(sl)
            r = px.rough()[sl] if s.model.fit_brdf else part.r0
            m = px.metal()[sl] if s.model.fit_brdf else part.m0
            outs.append(_shade(lights, part.pos, px.normal()[sl], px.base()[sl], r, m).cpu().numpy())
    return np.concatenate(outs, axis=1)


def lights_to_entries(lights, scale: float) -> list[dict[str, Any]]:
    """lights.json ``images`` entries (without index/file) in photo units from fitted :class:`LightParams`."""
    out = []
    inten = (lights.log_intensity.exp() / scale).detach().cpu().numpy()
    sh = (lights.sh / scale).detach().cpu().numpy()
    kinds = [lights.kind] * len(inten)
    vec = (lights.directions() if lights.kind in ("directional", "near") else lights.vec).detach().cpu().numpy()
    if lights.kind == "near":  # a point light at centre + direction / u (intensity: irradiance there * distance^2)
        u = lights.inv_distance.detach().cpu().numpy().clip(0.0, None)[:, None]
        near = u > 1e-6  # 0: the fit left the lamp infinitely far, a distant light
        ud = np.maximum(u, 1e-6)
        vec = np.where(near, lights.centre.detach().cpu().numpy()[None] + vec / ud, vec)
        inten = np.where(near, inten / ud ** 2, inten)
        kinds = ["point" if v else "directional" for v in near[:, 0]]
    for k in range(len(inten)):
        e = {"kind": kinds[k]}
        e["direction" if kinds[k] == "directional" else "position"] = [float(v) for v in vec[k]]
        e["intensity"] = [float(v) for v in inten[k]]
        e["sh"] = [[float(v) for v in row] for row in sh[min(k, len(sh) - 1)]]
        out.append(e)
    return out


class _Bar:
    """The fit's progress (``networks.progress``: a bar on a terminal, one line per stage in logs, with the stage's
    last loss), or a callback ``progress(label, done, total, loss)``. A stage is a run of steps with one label
    ("lights", "point lights", "maps 1/2", "maps")."""

    def __init__(self, progress, s: RefineSettings, near: bool = False, total: int | None = None):
        self.cb = progress if callable(progress) else None
        self.show = progress is True
        self.done = 0
        self.total = s.lights.iters * (2 if near else 1) if total is None else total
        self.stage = None
        self.bar = None
        self.loss = float("nan")

    def add_total(self, n: int) -> None:
        self.total += n

    def step(self, label: str, loss: float) -> None:
        self.done += 1
        if self.show:
            if label != self.stage:
                self._close_stage()
                from networks.progress import progress

                self.stage = label
                self.bar = progress(total=None, desc=f"fit {label}", unit="it")
            self.loss = loss
            self.bar.update(1)
        if self.cb is not None:
            self.cb(label, self.done, self.total, loss)

    def _close_stage(self) -> None:
        if self.bar is not None:
            if math.isfinite(self.loss):
                self.bar.set_postfix(loss=f"{self.loss:.4g}")
            self.bar.close()
            self.bar = None

    def close(self) -> None:
        self._close_stage()
        self.stage = None

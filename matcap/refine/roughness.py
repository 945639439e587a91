"""The roughness stage of a fit with known lights: each pixel's roughness chosen among the values its photos
allow, by what the pixels of the same material that saw a highlight say.

A pixel whose photos show no highlight is explained about equally well by a narrow lobe (the highlight fell
between the lamps) and by a broad, faint one (its shape taken up by the base colour); between the two lies a
range that explains them worse. The per-pixel solve, started from the networks' roughness, stays in whichever of
the two it starts nearer. This stage looks at a pixel's whole range instead: it tries each value of a grid
(the base colour solved in closed form, the normal and metallic as fitted), keeps the values within a tolerance of
the best, and where those span a narrow range the pixel decides its own roughness. Pixels that do not are given
an allowed value near the typical decided roughness of their material (pixels grouped by fitted base colour).

Two rules, by what the pixels share:

- a flat sample (:func:`choose_roughness`): every pixel faces the camera under the same lamps and started from
  the networks' guess on the same side of the barrier, so decided pixels move to their own best value and a
  material without decided pixels takes the sample's typical one. A narrow or a very broad lobe is decided on
  far fewer pixels than one in between, so each decided pixel counts in its material's target by how rarely its
  roughness would be decided (:func:`decision_rates`); an undecided pixel takes the bottom of the valley of its
  costs that its material's decided pixels lie nearest;
- an object (:func:`object_targets`, :func:`follow_targets`): its pixels face every way, so a pixel that saw a
  highlight already had it in the per-pixel solve, with the full model (cast shadows, the outline's mixing), and
  keeps that fit; the others follow their material's target, and the targets come from a sample of the pixels. A
  material without decided pixels of its own follows the object's typical decided roughness, but only where a
  pixel's photos allow that value: a pixel whose photos rule it out may be of another finish that the colour groups
  did not separate, and keeps its fit.

The same stage sets each material's metallic to 0 or 1 where its pixels' photos vote for it (:func:`metal_costs`,
:func:`group_metallic`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from matcap.refine.settings import RoughnessSettings


@dataclass
class RoughnessChoice:
    """What the stage chose: ``rough`` (N,) float32, each pixel's roughness (0-1); ``decided`` (S,) bool, of the
    pixels scored for the targets (all N on a flat sample, a sample on an object, none where the roughness is
    held), those whose own photos allow only a narrow range; ``groups`` (N,) int, each pixel's material group
    (:func:`material_groups`); ``targets`` (G,) float, each group's typical decided roughness (NaN: the group had
    too few decided pixels of its own); ``typical``, that of every decided pixel, the target of a group without one
    (NaN: too few decided pixels in all); ``rule``:
    ``"plane"``, ``"object"`` or ``"held"`` (:attr:`matcap.refine.settings.RoughnessSettings.choose` off: every
    pixel kept its fitted roughness); ``metallic`` (G,) each group's metallic (:func:`group_metallic`: 0, 1 or
    NaN), or None."""

    rough: np.ndarray
    decided: np.ndarray
    groups: np.ndarray
    targets: np.ndarray
    rule: str = "plane"
    metallic: np.ndarray | None = None
    typical: float = float("nan")

    def record(self) -> dict[str, Any]:
        """The choice as fit.json's ``roughness`` entry (``group_metallic``: each material group's metallic, or
        None where the stage left metallic as fitted)."""
        return {
            "rule": self.rule,
            "decided_share": round(float(self.decided.mean()), 4) if len(self.decided) else 0.0,
            "group_targets": [None if not np.isfinite(t) else round(float(t), 4) for t in self.targets],
            "typical_target": round(float(self.typical), 4) if np.isfinite(self.typical) else None,
            "group_metallic": None if self.metallic is None else [
                None if np.isnan(v) else int(v) for v in self.metallic],
        }


def grid_costs(torch, obs, upper, pos, normal, metal, lights, grid, noise: float) -> np.ndarray:
    """The data cost of every pixel at every roughness of ``grid``, its base colour solved in closed form.

    obs (K, N, 3) photos in fit units; upper (K, N, 3) the residual above which an observation adds none (0 where
    clipped, -inf where left out, +inf elsewhere); pos (N, 3) positions; normal (N, 3), metal (N,) torch, held
    (and, where a pixel's is above 0.1, also none: the lower cost counts); lights:
    :class:`matcap.refine.model.LightParams`. The model is linear in the base colour at a fixed normal, roughness
    and metallic, so each channel's base colour is one least-squares division (over the observations not
    clipped), clipped to 0-1. The caller decides cast shadows once, before (``upper`` -inf: the observation
    adds nothing): a roughness that over-predicts an observation must not pass it off as shadow. Cost: sum over
    photos and channels of log(1 + (residual / (noise x the pixel's mean observation))^2). Returns (len(grid), N)
    float32.
    """
    out = np.empty((len(grid), obs.shape[1]), np.float32)
    with torch.no_grad():
        wo, irr, used, scale = _score_terms(obs, upper, pos, lights, noise)
        q = torch.nonzero(metal > 0.1).flatten()  # the pixels with some metallic: tried without it too
        for g, r in enumerate(grid):
            rv = torch.full_like(metal, float(r))
            cost = _cost(normal, rv, metal, wo, irr, lights.sh, obs, upper, used, scale)
            if len(q):
                wo_q, irr_q = (wo, irr) if wo.shape[1] == 1 else (wo[:, q], irr[:, q])  # distant: shared
                none = _cost(normal[q], rv[q], torch.zeros_like(metal[q]), wo_q, irr_q, lights.sh, obs[:, q],
                             upper[:, q], used[:, q], scale[:, q])
                cost[q] = torch.minimum(cost[q], none)
            out[g] = cost.cpu().numpy()
    return out


def value_scores(torch, obs, upper, pos, normal, values, lights, noise: float) -> np.ndarray:
    """(V, 4, N) float32: for N pixels at each of V (roughness, metallic) pairs ``values``, a sequence of ((N,),
    (N,)) torch, the data cost of :func:`grid_costs` (row 0) and the least-squares base colour it is scored with,
    before clipping (rows 1-3); the other arguments as there."""
    out = np.empty((len(values), 4, obs.shape[1]), np.float32)
    with torch.no_grad():
        wo, irr, used, scale = _score_terms(obs, upper, pos, lights, noise)
        for i, (r, m) in enumerate(values):
            cost, base = _fit(normal, r, m, wo, irr, lights.sh, obs, upper, used, scale)
            out[i, 0], out[i, 1:] = cost.cpu().numpy(), base.T.cpu().numpy()
    return out


def _score_terms(obs, upper, pos, lights, noise: float):
    """What every score of N pixels shares: the lights' (wo, irradiance) at ``pos``, the observations (K, N, 3)
    that set the base colour (``upper`` above 0: not clipped, not left out) and each pixel's residual scale
    (``noise`` times its mean observation)."""
    wo, irr = lights.incident(pos)
    used = (upper > 0).to(obs.dtype)  # a clipped observation bounds the model only from below
    scale = (noise * obs.mean(dim=(0, 2))).clamp(min=1e-4)[None, :, None]
    return wo, irr, used, scale


def _least_squares_base(p0, a, obs, used):
    """(N, 3) each channel's least-squares base colour b of ``obs`` ~ ``p0 + b a`` (K, N, 3) where ``used``."""
    return (used * a * (obs - p0)).sum(0) / (used * a * a).sum(0).clamp(min=1e-12)


def _fit(nrm, rv, m, wo, irr, sh, o, up, used, scale):
    """(cost (N,), base (N, 3) before clipping): :func:`_cost` and the least-squares base colour it used."""
    from matcap.refine.model import shade_base_linear

    p0, a = shade_base_linear(nrm, rv, m, wo, irr, sh)
    base = _least_squares_base(p0, a, o, used)
    res = _zero_above(p0 + base.clamp(0.0, 1.0)[None] * a - o, up)
    return (res / scale).square().log1p().sum(dim=(0, 2)), base


def _cost(nrm, rv, m, wo, irr, sh, o, up, used, scale):
    """(N,) the cost of :func:`grid_costs` at roughness ``rv`` and metallic ``m`` (N,), the base colour solved."""
    return _fit(nrm, rv, m, wo, irr, sh, o, up, used, scale)[0]


def _zero_above(res, up):
    """``res`` with the entries above ``up`` zeroed (a clipped observation the model exceeds, see ``upper``)."""
    return res * (res <= up).to(res.dtype)


def metal_costs(torch, obs, upper, pos, normal, rough, lights, grid, noise: float) -> np.ndarray:
    """(4, N) float32: the data cost of every pixel as a dielectric (metallic 0) and as a metal (metallic 1) at its
    roughness ``rough`` (N,) torch (rows 0, 1), and each at its best roughness of ``grid`` (rows 2, 3), the base
    colour solved in closed form; the other arguments and the cost as in :func:`grid_costs`."""
    out = np.full((4, obs.shape[1]), np.inf, np.float32)
    with torch.no_grad():
        wo, irr, used, scale = _score_terms(obs, upper, pos, lights, noise)
        ones = torch.ones(obs.shape[1], dtype=obs.dtype, device=obs.device)
        for i, m in enumerate((0.0, 1.0)):
            out[i] = _cost(normal, rough, ones * m, wo, irr, lights.sh, obs, upper, used, scale).cpu().numpy()
            for r in grid:
                c = _cost(normal, ones * float(r), ones * m, wo, irr, lights.sh, obs, upper, used, scale)
                out[2 + i] = np.minimum(out[2 + i], c.cpu().numpy())
    return out


def group_metallic(costs: np.ndarray, groups: np.ndarray, count: int, fitted: np.ndarray,
                   s: RoughnessSettings) -> np.ndarray:
    """(G,) float32, each material group's metallic: 0 or 1 where its pixels' photos vote for it, NaN where they do
    not (the fit then holds the networks' metallic for the group's pixels).

    costs: (4, N) :func:`metal_costs` of N pixels; groups: (N,) int in [0, count); fitted: (N,) their fitted
    metallic. A pixel votes metal where its cost as a metal is lower than as a dielectric by more than
    ``s.tolerance``, dielectric the other way round; a group with at least ``s.min_decided`` votes is what most of
    them say, one with fewer the median of its fitted metallic, rounded. The vote is taken twice, with each pixel's
    roughness held (rows 0, 1) and free (rows 2, 3), and a group is set only where both agree: held, the vote
    leans toward the side the per-pixel solve settled on (a metal fitted as a dielectric keeps a lobe too narrow
    for a metal); free, a broad metal lobe passes for a dielectric's diffuse colour.

    A real material is a metal or a dielectric (the metallic-roughness convention of glTF and the game engines);
    in-between values belong to the boundary between two materials, which one pixel of a photo rarely resolves.
    Per pixel, a dielectric's cast shadows and interreflections read as a touch of metal, and the fitted value is
    also pulled toward the networks' guess; the photos' vote over a material outvotes both."""
    costs = np.asarray(costs, np.float64)
    fitted = np.asarray(fitted, np.float64)
    out = np.full(count, np.nan, np.float32)
    for g in range(count):
        sel = groups == g
        if not sel.any():
            continue
        said = []
        for rows in ((0, 1), (2, 3)):
            d = costs[rows[1], sel] - costs[rows[0], sel]
            m, e = int((d < -s.tolerance).sum()), int((d > s.tolerance).sum())
            said.append(float(m > e) if m + e >= s.min_decided else float(np.median(fitted[sel]) > 0.5))
        if said[0] == said[1]:
            out[g] = said[0]
    return out


def held_metallic(group_metal: np.ndarray, groups: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """(N,) float32, the metallic the last solve holds each pixel to: its material group's (``group_metal`` (G,),
    :func:`group_metallic`: 0, 1 or NaN; ``groups`` (N,) int) where the group's photos voted, else the networks'
    (``prior`` (N,), the fit's prior). Where the photos do not decide, a pixel's own fit is the worse guess: it
    drifts toward metal wherever the model misses a stronger specular, a cast shadow or an interreflection."""
    voted = np.asarray(group_metal, np.float32)[np.asarray(groups)]
    return np.where(np.isnan(voted), np.asarray(prior, np.float32), voted).astype(np.float32)


#: Pixels per block where a step holds a (grid, pixels) array of its own.
CHUNK = 65536


def material_groups(base: np.ndarray, count: int, seed: int, sample: int = 20000, iters: int = 20) -> np.ndarray:
    """(N,) int: each pixel's group, k-means of log(base colour + 0.02) (base (N, 3), 0-1) into at most ``count``
    groups, its centres found on a random subsample of ``sample`` pixels (``seed``)."""
    x = np.log(np.asarray(base, np.float64) + 0.02)
    n = len(x)
    if n == 0:
        return np.zeros(0, np.int64)
    rng = np.random.default_rng(seed)
    fit = x[rng.choice(n, size=min(n, sample), replace=False)]
    centres = fit[rng.choice(len(fit), size=min(count, len(fit)), replace=False)]

    def assign(pts: np.ndarray) -> np.ndarray:
        return ((pts[:, None, :] - centres[None]) ** 2).sum(-1).argmin(1)

    for _ in range(iters):
        lab = assign(fit)
        centres = np.array([fit[lab == j].mean(0) if (lab == j).any() else centres[j] for j in range(len(centres))])
    return np.concatenate([assign(x[i:i + CHUNK]) for i in range(0, n, CHUNK)]) if n else np.zeros(0, np.int64)


def _vertex(costs: np.ndarray, lg: np.ndarray) -> np.ndarray:
    """(N,) log roughness at the vertex of the parabola through each pixel's lowest grid cost and its neighbours
    (costs (G, N), lg (G,) the grid's log roughness); at the grid's ends, the end value."""
    best = costs.argmin(axis=0)
    i = np.clip(best, 1, len(lg) - 2)
    cols = np.arange(costs.shape[1])
    x0, x1, x2 = lg[i - 1], lg[i], lg[i + 1]
    y0, y1, y2 = costs[i - 1, cols], costs[i, cols], costs[i + 1, cols]
    num = (x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)
    den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
    safe = np.abs(den) > 1e-12
    vertex = x1 - 0.5 * num / np.where(safe, den, 1.0)
    vertex = np.where(safe, np.clip(vertex, x0, x2), x1)
    return np.where((best == 0) | (best == len(lg) - 1), lg[best], vertex)


def explained(cost: np.ndarray, observations: int, s: RoughnessSettings) -> np.ndarray:
    """(N,) bool: where the model explains a pixel, its cost (N,) (:func:`grid_costs`, :func:`value_scores`; a sum
    over ``observations``, photos x 3 channels) at most ``s.explained`` per observation."""
    return cost <= s.explained * observations


def _span(costs: np.ndarray, s: RoughnessSettings):
    """(allowed (G, N) bool, lo (N,), hi (N,), decided (N,) bool) of grid costs (G, N): the grid values within
    ``s.tolerance`` of each pixel's lowest cost, their least and greatest log roughness, and whether those span at
    most a factor ``s.width``."""
    lg = np.log(np.asarray(s.grid, np.float64))[:, None]
    allowed = costs <= costs.min(axis=0, keepdims=True) + s.tolerance
    lo = np.where(allowed, lg, np.inf).min(axis=0)
    hi = np.where(allowed, lg, -np.inf).max(axis=0)
    return allowed, lo, hi, (hi - lo) <= np.log(s.width) + 1e-9


def _medians(middle: np.ndarray, decided: np.ndarray, groups: np.ndarray, n_groups: int, least: int) -> np.ndarray:
    """(n_groups,) each group's median roughness (exp of ``middle``, log roughness (N,)) over its ``decided``
    pixels; NaN where it has fewer than ``least``."""
    targets = np.full(n_groups, np.nan)
    for j in range(n_groups):
        own = (groups == j) & decided
        if own.sum() >= least:
            targets[j] = float(np.exp(np.median(middle[own])))
    return targets


def _typical(middle: np.ndarray, decided: np.ndarray, least: int) -> float:
    """The median roughness (exp of ``middle``, log roughness (N,)) of every ``decided`` pixel; NaN where there are
    fewer than ``least``."""
    return float(np.exp(np.median(middle[decided]))) if decided.sum() >= max(least, 1) else float("nan")


def object_targets(costs: np.ndarray, groups: np.ndarray, n_groups: int, s: RoughnessSettings
                   ) -> tuple[np.ndarray, float, np.ndarray]:
    """An object's material targets from the grid costs (G, M) of a sample of its pixels and their groups (M,)
    int: (targets (n_groups,), each group's median decided roughness, NaN where the sample holds fewer than
    ``s.min_decided`` decided pixels of it; the typical roughness, the median over every decided pixel, NaN where
    there are fewer than ``s.min_decided`` of those; decided (M,) bool)."""
    _, _, _, decided = _span(costs, s)
    middle = _vertex(costs, np.log(np.asarray(s.grid, np.float64)))
    return (_medians(middle, decided, groups, n_groups, s.min_decided), _typical(middle, decided, s.min_decided),
            decided)


def follow_targets(costs: np.ndarray, fitted: np.ndarray, target: np.ndarray, own: np.ndarray,
                   s: RoughnessSettings) -> tuple[np.ndarray, np.ndarray]:
    """An object's pixels (grid costs (G, M), fitted roughness (M,), their target (M,), whether that is their own
    material's (M,) bool, else the object's typical roughness): a decided pixel keeps its fitted roughness; the
    others take the allowed value nearest (in log roughness) the target, except that a pixel following the
    typical roughness keeps its fit where the grid value nearest the target is not allowed.
    Returns (roughness (M,) float32, decided (M,) bool)."""
    grid = np.asarray(s.grid, np.float64)
    allowed, _, _, decided = _span(costs, s)
    dist = np.abs(np.log(grid)[:, None] - np.log(target)[None])
    nearest = np.where(allowed, dist, np.inf).argmin(axis=0)
    there = np.take_along_axis(allowed, dist.argmin(axis=0)[None], axis=0)[0]
    keep = decided | ~(own | there)
    return np.where(keep, fitted, grid[nearest]).astype(np.float32), decided


def held_roughness(base: np.ndarray, fitted: np.ndarray, s: RoughnessSettings, seed: int) -> RoughnessChoice:
    """The choice where the roughness is held (``s.choose`` off, a constant roughness): every pixel keeps its
    fitted roughness (N,), nothing is decided, and the pixels fall into their material groups (by their fitted
    base colour (N, 3), :func:`material_groups`) for the metallic vote alone; rule ``"held"``."""
    groups = material_groups(base, s.groups, seed)
    count = int(groups.max()) + 1 if len(groups) else 0
    return RoughnessChoice(np.asarray(fitted, np.float32), np.zeros(0, bool), groups, np.full(count, np.nan), "held")


def decision_rates(torch, pos, normal, base, metal, lights, s: RoughnessSettings) -> np.ndarray:
    """(G,) float64: for each roughness v of ``s.grid``, the share of the pixels given (pos (S, 3), normal (S, 3),
    base (S, 3) 0-1, metal (S,) torch; a sample of the capture's) whose photos would decide their roughness
    (:func:`_span`) were it v: the model's own photos of them at v (no noise, nothing clipped), scored by
    :func:`grid_costs` under ``lights`` (:class:`matcap.refine.model.LightParams`).

    A pixel decides its roughness only where some lamp's reflection falls near enough to its normal for the
    lobe's shape to show: a narrow lobe needs a lamp almost at the mirror direction, and a very broad one is hard
    to tell from the diffuse colour, so the decided pixels of a material over-represent the roughnesses in between.
    :func:`choose_roughness` weighs each decided pixel by one over its value's rate to undo that."""
    from matcap.refine.model import shade_base_linear

    grid = np.asarray(s.grid, np.float64)
    n = len(pos)
    if n == 0:
        return np.zeros(len(grid))
    with torch.no_grad():
        tile = (len(grid), 1)
        pos_t, nrm_t, base_t = pos.repeat(*tile), normal.repeat(*tile), base.repeat(*tile)
        metal_t = metal.repeat(len(grid))
        rough_t = torch.from_numpy(np.repeat(grid, n)).to(pos.dtype).to(pos.device)
        wo, irr = lights.incident(pos_t)
        p0, a = shade_base_linear(nrm_t, rough_t, metal_t, wo, irr, lights.sh)
        obs = p0 + base_t[None] * a
        upper = torch.full_like(obs, float("inf"))
        costs = grid_costs(torch, obs, upper, pos_t, nrm_t, metal_t, lights, grid, s.noise)
    return _span(costs, s)[3].reshape(len(grid), n).mean(axis=1)


def _descend(costs: np.ndarray, allowed: np.ndarray, start: np.ndarray) -> np.ndarray:
    """(N,) grid index: from ``start`` (N,) each pixel steps to the cheaper of its allowed grid neighbours while
    that lowers its cost (costs, allowed (G, N)): the bottom of the valley of its costs that holds ``start``."""
    cols = np.arange(costs.shape[1])
    top = costs.shape[0] - 1
    at = np.asarray(start).copy()
    for _ in range(costs.shape[0]):
        up, down = np.minimum(at + 1, top), np.maximum(at - 1, 0)
        c_up = np.where(allowed[up, cols], costs[up, cols], np.inf)
        c_down = np.where(allowed[down, cols], costs[down, cols], np.inf)
        here = costs[at, cols]
        step = np.where((c_up < here) & (c_up <= c_down), up, np.where(c_down < here, down, at))
        if np.array_equal(step, at):
            break
        at = step
    return at


def _mean_distance(x: np.ndarray, m: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(X,) the weighted mean of |x - m| over the values ``m`` (M,) of weights ``w`` (M,), at each of ``x`` (X,)."""
    order = np.argsort(m)
    m, w = m[order], w[order]
    cw, cwm = np.concatenate([[0.0], np.cumsum(w)]), np.concatenate([[0.0], np.cumsum(w * m)])
    k = np.searchsorted(m, x)  # m[:k] below x
    below = x * cw[k] - cwm[k]
    above = (cwm[-1] - cwm[k]) - x * (cw[-1] - cw[k])
    return (below + above) / max(cw[-1], 1e-300)


def _agreeing(allowed: np.ndarray, disagreement: np.ndarray, target: np.ndarray, lg: np.ndarray) -> np.ndarray:
    """(N,) grid index: each pixel's allowed value (allowed (G, N) bool) at which its material disagrees least
    with its decided pixels (``disagreement`` (G, N), their weighted mean distance in log roughness from each grid
    value); ties go to the value nearest (in log roughness) the pixel's ``target`` (N,). Where the allowed values
    are one run, that is the one nearest the material's weighted median; where they are two valleys (a narrow lobe,
    a broad one), the valley the material's decided pixels lie nearer."""
    score = np.where(allowed, disagreement + 1e-9 * np.abs(lg - target[None]), np.inf)
    return score.argmin(axis=0)


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """The value of ``x`` (M,) at which the cumulative weight ``w`` (M,) reaches half its total."""
    order = np.argsort(x)
    cum = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cum, cum[-1] / 2.0)])


def choose_roughness(costs: np.ndarray, base: np.ndarray, fitted: np.ndarray, s: RoughnessSettings,
                     seed: int, rates: np.ndarray | None = None, observations: int | None = None,
                     descend: bool = True) -> RoughnessChoice:
    """Each pixel's roughness from its grid costs (:func:`grid_costs`, (G, N)), its fitted base colour (N, 3) and
    fitted roughness (N,).

    A pixel's allowed values are the grid values within ``s.tolerance`` of its lowest cost; where they span at
    most a factor ``s.width`` the pixel is decided, at the vertex of the parabola through its lowest cost and its
    two neighbours (in log roughness, kept inside them). A group's target is the weighted median log roughness of
    its decided pixels where it has ``s.min_decided`` of them, else of every decided pixel; each decided pixel
    weighs one over ``rates`` (G,) (:func:`decision_rates`, no lower than ``s.rate_floor``) at its grid value
    nearest, so that a roughness rarely decided counts for the pixels of it that were not (None: equal weights).
    Only the decided pixels that the model explains count toward the targets: lowest cost at most
    ``s.explained`` per observation (``observations``, photos x 3 channels; None, or no decided pixel explained:
    every decided pixel counts).
    The others start from the allowed value at which their material's decided pixels (those that set its target, with
    the same weights) disagree least, their weighted mean distance in log roughness (:func:`_agreeing`): within one
    run of allowed values that is the one nearest the target; between a narrow lobe's valley and a broad one's, the
    valley nearer those pixels as a whole (a colour group holding two finishes has its median between them). They
    descend their own costs to the bottom of that valley (:func:`_descend`): the material picks the valley, the
    pixel's photos place it within. ``descend`` False: they stay at that allowed value (lamps found from the photos
    themselves, whose errors each pixel's costs carry and the material's shared target averages out). Where no pixel
    is decided the fitted roughness stays.
    """
    grid = np.asarray(s.grid, np.float64)
    lg = np.log(grid)[:, None]
    n = costs.shape[1]
    allowed, lo, hi, decided = _span(costs, s)
    groups = material_groups(base, s.groups, seed)
    n_groups = int(groups.max()) + 1 if n else 0
    if not decided.any():
        return RoughnessChoice(np.asarray(fitted, np.float32), decided, groups, np.full(n_groups, np.nan))
    middle = np.where(decided, _vertex(costs, np.log(grid)), (lo + hi) / 2.0)
    rate = np.ones(len(grid)) if rates is None else np.maximum(np.asarray(rates, np.float64), s.rate_floor)
    weight = 1.0 / rate[np.searchsorted((lg[1:, 0] + lg[:-1, 0]) / 2.0, middle)]  # the grid value nearest
    evidence = decided if observations is None else decided & explained(costs.min(axis=0), observations, s)
    if not evidence.any():
        evidence = decided
    targets = np.full(n_groups, np.nan)
    # each material's disagreement with its decided pixels at every grid value: a column per group with a target of
    # its own; the last, of every decided pixel (the typical's)
    disagreement = np.zeros((len(grid), n_groups + 1))
    for j in range(n_groups):
        own = (groups == j) & evidence
        if own.sum() >= s.min_decided:
            targets[j] = float(np.exp(_weighted_median(middle[own], weight[own])))
            disagreement[:, j] = _mean_distance(lg[:, 0], middle[own], weight[own])
    typical = float(np.exp(_weighted_median(middle[evidence], weight[evidence])))
    disagreement[:, n_groups] = _mean_distance(lg[:, 0], middle[evidence], weight[evidence])
    target = np.log(np.where(np.isfinite(targets), targets, typical))[groups]
    column = np.where(np.isfinite(targets), np.arange(n_groups), n_groups)[groups]
    start = np.concatenate([_agreeing(allowed[:, i:i + CHUNK], disagreement[:, column[i:i + CHUNK]],
                                      target[i:i + CHUNK], lg) for i in range(0, n, CHUNK)])
    chosen = _descend(costs, allowed, start) if descend else start
    rough = np.where(decided, np.exp(middle), grid[chosen]).astype(np.float32)
    return RoughnessChoice(rough, decided, groups, targets, typical=typical)

"""Settings of the fit (:func:`matcap.refine.refine`), one dataclass per stage, nested in :class:`RefineSettings`
(recorded in fit.json ``settings``; ``--set group.field=value`` on the benchmarks, ``RefineSettings.replace`` in
code). Each field says what the knob means; docs/refine.md and docs/lights.md give the measurements behind the
defaults."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from matcap.errors import MatcapError


@dataclass
class ModelSettings:
    """What the fit models: the lights' kind, the fixed ambient, which maps move."""

    light: str = "directional"
    """Estimated lights: "directional", distant lights (where they fail to explain the photos, other candidate light
    models are tried, see :class:`CandidateSettings`); "point", a lamp per photo whose distance the fit always finds.
    Known lights keep the kind their file gives."""
    ambient: str = "shared"
    """"shared": one order-2 SH ambient for every photo (a fixed room light); "per-image"; "none"."""
    fit_brdf: bool = True
    """False: roughness and metallic stay the networks' (normals and base colour are still fitted)."""


@dataclass
class LossSettings:
    """The data term, in the fit's units (the photos scaled so that their mean over the mask is 0.5)."""

    cauchy: float = 0.15
    """Scale of the Cauchy loss on the photo residuals: shadows, interreflections and highlights the model cannot
    explain weigh less."""
    shadow: float = 0.2
    """With lights known (given, or from a ball), an observation whose light above the ambient's part of the
    model's prediction is less than this share of the lamp's part counts as cast shadow (the object hides the lamp
    from the point, which the model does not know, and leaves it the room's light): it bounds the prediction from
    above only and adds no residual. 0: none. Lights the fit estimates (a flat sample's lamps
    found from their falloff too) go without it: an error of the lights would pass for shadow. So does a flat
    sample under given lights: a plane facing the camera hides no lamp from itself. While the lights' intensities
    and the ambient are fitted, the ambient's part is that of their Lambertian start where it found a room's light
    (:attr:`LightSettings.room_share`)."""
    shadow_light_fit: float = 0.3
    """The same rule while the lights' intensities and the ambient are fitted where their start found no room's
    light: there an observation below this share of the whole prediction (the ambient's part included) counts as
    cast shadow."""
    variation_threshold: float = 0.08
    """Per-pixel light variation (std / mean over photos) below which a pixel is weakly constrained (it weighs
    less, down to 0.1, and a warning names the share of such pixels)."""


@dataclass
class PriorSettings:
    """Weights of the prior that holds every pixel near its start, per pixel, against a data term summed over the
    photos (so more photos weigh more)."""

    normal: float = 0.5
    """Weight of |n - n_prior|^2 (n_prior: calibrated Lambertian normals from the photos where solved, else the
    networks')."""
    base: float = 0.5
    """Weight of mean_c (log(b + 0.02) - log(b_net + 0.02))^2."""
    rough: float = 0.5
    """Weight of (r - r_net)^2."""
    metal: float = 0.5
    """Weight of (m - m_net)^2."""
    lambertian_misfit: float = 0.3
    """Known lights on an object: a pixel's calibrated Lambertian normal is its start and n_prior only where the
    Lambertian model explains its photos to this relative misfit (RMS over the photos that light it / its mean
    brightness); elsewhere (a highlight, metal, a cast shadow: not Lambertian) the networks' normal is. A flat
    sample keeps its Lambertian normals."""
    cover: float = 0.1
    """Weight of (1 - coverage)^2 of a pixel of the mask's outline (see :attr:`PixelStageSettings.outline`)."""


@dataclass
class LightStageSettings:
    """The light stage: the lights fitted with the maps of a pixel subsample of a downsampled copy."""

    side: int = 256
    """The light fit runs on a copy whose longer side is at most this many pixels."""
    pixels: int = 4096
    """Pixels of that copy taking part in the light fit."""
    known_pixels: int = 2048
    """Pixels taking part where the directions are known (only the intensities and the ambient are fitted), drawn
    off the mask's outline (``pixels.outline``), whose mixed pixels the light fit does not model."""
    iters: int = 400
    """Adam steps of the light fit where the lights are estimated (and of a near-lamp fit's distances)."""
    known_iters: int = 30
    """Levenberg-Marquardt iterations at most of the light fit where the directions are known (the intensities,
    the ambient and the subsample's maps solved together); 0: the least-squares intensities are kept."""
    kept_iters: int = 200
    """Adam steps of the light fit where the maps are kept (the lights are fitted to the networks' maps)."""
    lr: float = 0.02
    """Adam step size of the light parameters (directions, log intensities, ambient, inverse distances)."""
    lr_pixel: float = 0.05
    """Adam step size of the subsample's map parameters during the light fit."""
    room_share: float = 0.1
    """Known directions: the least room's light (its constant part, as a share of the lamps' mean irradiance) that
    the Lambertian start keeps; a weaker one is taken as none (the start's normals and intensities then have no
    room term, and the light fit finds the ambient from zero)."""
    known_ambient_order: int = 1
    """The highest order of the SH ambient fitted there: 0 its constant term alone, 1 also the linear terms (a room's
    light seen by a glossy surface changes with the normal), 2 all (they bend to fit cast shadows and
    interreflections); the higher orders stay as given (a lights.json's ``sh``) or 0."""
    flat_level_free: bool = True
    """A flat sample whose lights' relative intensities are known (a light file's lamps or distant lights with
    intensities): the base colour's prior holds the networks' pattern only, not its level (one factor on it is solved
    with the lights), so that the photos set the lights' overall power."""
    found_lamps_rounds: int = 3
    """A flat sample whose lamps were found from their falloff: rounds of the per-pixel stage on the light-fit copy
    before the full-size stage, each followed by the lamps placed again with that stage's maps
    (``found_lamps_steps``) and each photo's intensity fitted again to them. The falloff leaves a lamp's height
    weakly held (a lower lamp and a steeper relief explain it about alike), and the first fit anchors its pixels'
    maps to the networks', whose roughness and relief a glossy sample's highlights do not follow; the intensities
    then trade with the specular (a photo's intensity off by a few percent moves the roughness of every pixel its
    highlight crosses). 0: the lamps and the first fit's intensities are kept."""
    found_lamps_steps: int = 300
    """Adam steps, in each of those rounds, of the lamps' positions and intensities (the ambient held) fitted with
    the maps of ``known_pixels`` pixels of the light-fit copy (started from and anchored to the round's maps, their
    tilts wider than ``pixels.found_lamps_detail`` taken out), the normals' smooth tilt held at zero
    (``found_lamps_tilt_degree``). 0: the lamps stay where the falloff put them."""
    found_lamps_tilt_degree: int = 2
    """While the lamps are placed again, the part of the normals' gradient field (x and y of ``n / n_z``) that a
    polynomial of this degree in the plane's position explains is held at zero: a misplaced lamp shows as such a
    smooth tilt across the sample, which a flat sample does not have. -1: none is held."""
    flat_mean_held: bool = True
    """A flat sample whose given lights come without intensities: the light fit's pixels keep a mean normal
    gradient (x and y of ``n / n_z``) of 0. The sample's mean normal is the camera axis; without it a photo's
    fitted intensity trades with a tilt of the whole sample toward or away from that photo's light. (Lamps found
    from their falloff have every tilt wider than ``pixels.found_lamps_detail`` taken out instead.)"""


@dataclass
class FactorizationSettings:
    """Estimated lights: the Lambertian factorization and its bas-relief choice (:mod:`matcap.refine.linear`)."""

    pixels: int = 20000
    """Pixels of the light-fit copy used by the factorization (every occluding-contour pixel too)."""
    contour_weight: float = 1.0
    """Weight of the occluding contour's normals against the networks' in fixing the bas-relief."""
    contour_nz: float = 0.1
    """n_z given to contour pixels' normals (a pixel centre lies just inside the contour)."""
    contour_gate: float = 0.6
    """Mask-edge pixels count as occluding contour where the networks' n_z is below this."""
    equal_lights: float = 150.0
    """Weight of "every photo got about the same irradiance" (one lamp moved at a similar distance) against the
    prior's misfit, relative to the prior's own, in choosing the bas-relief; 0 ignores it."""


@dataclass
class CheckSettings:
    """Estimated lights: the factorization's check, which decides whether the photos may move the maps."""

    residual: float = 0.05
    """The factorization must explain the photos to this relative RMS ..."""
    inliers: float = 0.85
    """... with this share of inlier observations (these two: distant lights on a matte-like surface; only the
    first candidate light model must pass them);"""
    solved: float = 0.6
    """... under the lights found, this share of the pixels must get a Lambertian normal facing the camera;"""
    spread: float = 0.02
    """... and the photos' third singular value must be at least this share of the first (a flat sample's
    photos are nearly rank 1: its one normal cannot tell the lights apart)."""
    twin: float = 0.25
    """Not a gate: where the prior's misfit of the surface chosen is at least this share of its twin's (every
    tilt mirrored, which explains the photos as well; :func:`matcap.refine.linear.twin_ratio`), a note says
    that the photos cannot tell its bumps from its dents."""


@dataclass
class CandidateSettings:
    """Estimated lights: the candidate light models tried after distant lights (or point lamps) where only the
    residual / inliers part of the check failed, and the limits that accept them (:func:`_judge`)."""

    near: bool = True
    """Near lamps: fit lamps whose distances the fit finds, accepted where the conditions below hold."""
    near_distance: float = 15.0
    """... the median lamp within this many object radii (the radius of the disc as large as the mask);"""
    near_ambient: float = 0.2
    """... the fixed ambient at most this share of the object's irradiance (with light model "point": only this);"""
    near_loss_ratio: float = 0.8
    """... and the distances cut the light fit's loss to at most this share of what distant lamps reach ..."""
    near_dark: float = 0.05
    """... unless the fixed ambient is at most this share (a dark room, where highlights dominate the loss)."""
    glossy: bool = True
    """Glossy distant lamps (light model "directional" only): distant lamps under the Principled model alone,
    accepted where the fixed ambient of that fit and of the near-lamp fit before it is small."""
    glossy_ambient: float = 0.05
    """... at most this share of the object's irradiance ..."""
    glossy_ambient_far: float = 0.1
    """... or at most this share where the near-lamp fit left the lamps ``far_distance`` object radii away or more."""
    far_distance: float = 30.0
    """Object radii beyond which a near-lamp fit's lamps count as far (a fixed room light lets them stay far)."""


@dataclass
class PixelStageSettings:
    """The per-pixel stage: Levenberg-Marquardt per pixel with the lights fixed (:mod:`matcap.refine.solve`)."""

    coarse_iters: int = 10
    """Iterations at half size (skipped when the maps are 128 px or smaller)."""
    fine_iters: int = 20
    """Iterations at full size."""
    tol: float = 1e-4
    """A pixel is done once two iterations in a row lowered its loss by less than this share of it (a rejected
    step counts where the Gauss-Newton model promises less: :func:`matcap.refine.solve.levenberg_marquardt`)."""
    lm_observations: int = 262144
    """Pixels x photos per chunk of the solve (its Jacobians' memory grows with both)."""
    chunk: int = 32768
    """Pixels per chunk of the re-render."""
    outline: int = 1
    """Width in pixels of the mask's outline (where the mask meets the photo, not the photo's border): a pixel
    there can cover the object only in part (the lens's blur, a mask drawn a pixel wide), so it is fitted as a
    mixture, coverage x the model + (1 - coverage) x what lies behind it (the mean of the photo's pixels just off
    the mask), its coverage a free parameter. 0: every pixel is the object's alone."""
    restart_deg: float = 5.0
    """Known lights: a pixel whose fitted normal lies farther than this (degrees) from the median of its eight
    neighbours' is solved again from that median (``restart_iters`` iterations; base colour, roughness and
    metallic from its own fit) and keeps whichever solution has the lower loss (data and priors). 0: none."""
    restart_iters: int = 20
    """Iterations of that second solve."""
    restart_rounds: int = 3
    """Rounds of those restarts (a pixel fixed in one round gives its neighbours a better median in the next)."""
    found_lamps_detail: float = 0.125
    """A flat sample whose lamps were found from their falloff: its fitted normals keep only the tilts finer than
    this share of the sample's width (those of a Gaussian of that sigma are taken out; the sample is a plane at
    larger scales, and a found lamp's error tilts the fit smoothly across it). 0: keep every tilt."""


@dataclass
class RoughnessSettings:
    """Known lights (given, from a ball, or a flat sample's found from their falloff): the roughness stage
    (:mod:`matcap.refine.roughness`), after the per-pixel solve, then a last solve with the chosen roughness held."""

    iters: int = 10
    """Levenberg-Marquardt iterations of the last solve; 0 skips the stage (roughness as the per-pixel solve left
    it)."""
    choose: bool = True
    """False: every pixel keeps the roughness the per-pixel solve gave it (``--constant roughness=V`` holds V through
    the fit); the stage still votes each material's metallic."""
    grid: tuple[float, ...] = (0.04, 0.06, 0.08, 0.1, 0.13, 0.16, 0.2, 0.25, 0.3, 0.36, 0.43, 0.5, 0.58, 0.66,
                               0.75, 0.85, 0.95)
    """Roughness values each pixel's photos are tried at."""
    noise: float = 0.08
    """Scale of a residual in the stage's cost, as a share of the pixel's mean brightness."""
    tolerance: float = 8.0
    """A roughness is allowed where its cost is within this of the pixel's lowest (cost: sum over photos and
    channels of log(1 + (residual / scale)^2))."""
    width: float = 1.5
    """A pixel decides its own roughness where its allowed values span at most this factor."""
    groups: int = 8
    """Material groups (k-means of the fitted base colour) whose decided pixels set the others' roughness."""
    min_decided: int = 20
    """A group with fewer decided pixels has no target of its own and takes the typical roughness of every decided
    pixel (on an object, only its pixels whose photos allow that value; the others keep their fit)."""
    rate_pixels: int = 1000
    """A flat sample: how often each roughness of ``grid`` would be decided (a decided pixel's weight in its group's
    target is one over that share) is measured on this many of its pixels (a random sample)."""
    rate_floor: float = 0.02
    """The least share a roughness is taken to be decided at, bounding a decided pixel's weight (1 / share)."""
    explained: float = 0.25
    """The model explains a pixel where its cost per observation (photo and channel) is at most this, log(1 + x^2)
    with x the residual over ``noise`` times the pixel's brightness (0.25: about half of that scale). A pixel the
    model does not explain (a boundary between materials, a wrong normal) can decide a wrong value: on a flat sample
    only an explained decided pixel counts toward its material's target, and with known lights an output map's
    pixel not explained at its fitted values takes its window's values (``pool``)."""
    sample: int = 20000
    """An object's targets come from the scores of this many of its pixels (a random sample); then only the
    pixels farther than ``moved`` from their group's target are scored."""
    hold: float = 5.0
    """Weight of (r - r_chosen)^2 in the last solve (in place of ``priors.rough``)."""
    moved: float = 1.25
    """The last solve takes the pixels whose chosen roughness differs from the fitted one by more than this
    factor; the others keep their fit."""
    moved_flat: float = 1.05
    """The same on a flat sample, where every pixel is scored and takes a value of its own (its best, or the bottom
    of the valley its material picks), so that the choice reaches nearly every pixel."""
    metallic_hold: float = 5.0
    """Weight of (m - m_group)^2 in the last solve, m_group each material group's metallic, 0 or 1, as the photos
    of a sample of its pixels vote (:func:`matcap.refine.roughness.group_metallic`; a group whose vote is not
    clear holds the networks' metallic, the prior's); 0 leaves metallic free as in the per-pixel solve."""
    metallic_moved: float = 0.1
    """The last solve also takes the pixels whose fitted metallic differs from the one held (their group's, or
    the networks') by more than this (such a pixel keeps the normal the per-pixel solve gave it)."""
    pool: int = 3
    """After the last solve, each pixel's roughness and metallic take the median of this many pixels' square window
    around it where its photos allow them, and in the fit's output maps also where the model does not explain them
    (``explained``) (the mask's pixels only; its base colour shifted to match, its normal kept); 1: each pixel keeps
    its own."""


@dataclass
class RefineSettings:
    """Settings of :func:`refine`, one group per stage (recorded nested in fit.json ``settings``)."""

    model: ModelSettings = field(default_factory=ModelSettings)
    loss: LossSettings = field(default_factory=LossSettings)
    priors: PriorSettings = field(default_factory=PriorSettings)
    lights: LightStageSettings = field(default_factory=LightStageSettings)
    factorization: FactorizationSettings = field(default_factory=FactorizationSettings)
    checks: CheckSettings = field(default_factory=CheckSettings)
    candidates: CandidateSettings = field(default_factory=CandidateSettings)
    pixels: PixelStageSettings = field(default_factory=PixelStageSettings)
    roughness: RoughnessSettings = field(default_factory=RoughnessSettings)
    seed: int = 0
    """Seed of every random choice (pixel subsamples); the fit is repeatable bit for bit for a seed and device."""
    device: str = "cpu"
    """torch device."""

    def replace(self, changes: dict[str, Any]) -> "RefineSettings":
        """A copy with ``changes`` made: keys "group.field" (``{"lights.iters": 0}``) or "seed" / "device"; a
        MatcapError names an unknown key, or a value of another kind than the setting's (:func:`_checked`)."""
        import dataclasses

        groups: dict[str, dict[str, Any]] = {}
        top: dict[str, Any] = {}
        names = {f.name: f for f in dataclasses.fields(self)}
        for key, value in changes.items():
            group, _, name = key.partition(".")
            if group not in names or bool(name) != dataclasses.is_dataclass(getattr(self, group)) or (
                    name and name not in {f.name for f in dataclasses.fields(getattr(self, group))}):
                raise MatcapError(f"no fit setting {key!r} (settings: {', '.join(_setting_keys(self))})")
            current = getattr(getattr(self, group), name) if name else getattr(self, group)
            value = _checked(key, current, value)
            if name:
                groups.setdefault(group, {})[name] = value
            else:
                top[group] = value
        nested = {g: dataclasses.replace(getattr(self, g), **v) for g, v in groups.items()}
        return dataclasses.replace(self, **nested, **top)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "RefineSettings":
        """The settings that :func:`dataclasses.asdict` (fit.json ``settings``) recorded as ``d``."""
        import dataclasses

        kinds = {f.name: f.default_factory for f in dataclasses.fields(cls)
                 if f.default_factory is not dataclasses.MISSING}
        return cls(**{k: kinds[k](**v) if k in kinds else v for k, v in d.items()})


def _checked(key: str, current: Any, value: Any) -> Any:
    """``value`` for the setting ``key`` whose value is now ``current``, of the same kind: a bool for a switch
    (or the words "true" / "false", as ``--set`` gives them; any other string would read as true), a whole
    number for a count, a number for a float (as a float), a string for a choice, a sequence of numbers for a grid
    (as a tuple). A MatcapError names the key otherwise."""
    import numbers

    if isinstance(current, bool) and isinstance(value, str) and value.lower() in ("true", "false"):
        return value.lower() == "true"
    kinds = ((bool, lambda v: isinstance(v, (bool, np.bool_)), bool, "true or false"),
             (int, lambda v: isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)), int,
              "a whole number"),
             (float, lambda v: isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)), float,
              "a number"),
             (str, lambda v: isinstance(v, str), str, "a string"),
             (tuple, lambda v: isinstance(v, (tuple, list)) and all(
                 isinstance(x, numbers.Real) and not isinstance(x, bool) for x in v), tuple, "a list of numbers"))
    for kind, accepts, convert, words in kinds:
        if isinstance(current, kind):
            if not accepts(value):
                raise MatcapError(f"fit setting {key!r} takes {words}, not {value!r}")
            return convert(value)
    return value


def _setting_keys(s: RefineSettings) -> list[str]:
    """Every settings key, "group.field" or top-level, in the dataclasses' order."""
    import dataclasses

    out = []
    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        out += [f"{f.name}.{g.name}" for g in dataclasses.fields(v)] if dataclasses.is_dataclass(v) else [f.name]
    return out

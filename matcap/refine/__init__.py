"""Photo-consistent refinement of a capture: fit per-photo lights and per-pixel SVBRDF to the photos, starting
from (and anchored to) the networks' maps. torch only (no Mitsuba). See docs/refine.md.

- :mod:`matcap.refine.bsdf`: the Principled BSDF in torch (as ``renderers.relight`` renders it);
- :mod:`matcap.refine.model`: forward model (directional / point light + order-2 SH ambient);
- :mod:`matcap.refine.fit`: :func:`refine` (coarse to fine, robust, prior-anchored), which runs the stages:
  :mod:`~matcap.refine.photos`, the lights' :mod:`~matcap.refine.known_lights` or
  :mod:`~matcap.refine.estimated_lights` (what both share: :mod:`~matcap.refine.light_fit`),
  :mod:`~matcap.refine.pixel_stage`, :mod:`~matcap.refine.brdf_stage`;
- :mod:`matcap.refine.settings`: :class:`RefineSettings`, one group of knobs per stage;
- :mod:`matcap.refine.lightfile`: lights.json reader/writer and conversion to ``scenes.lights`` (relight);
- :mod:`matcap.refine.outputs`: lights.json / fit.json / residual.png / light_variation.png.
"""
from matcap.refine.fit import RefineResult, RefineSettings, refine
from matcap.refine.photos import light_variation

__all__ = ["RefineResult", "RefineSettings", "light_variation", "refine"]

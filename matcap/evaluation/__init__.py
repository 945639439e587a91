"""Evaluation of normal estimation: dataset loaders, angular-error metrics, classical baselines, benchmark runner.

``matcap eval`` (``matcap/commands/eval.py``) is the command-line entry point; :func:`runner.evaluate` the library
one. See ``docs/eval.md`` for the protocol and the conventions.

Modules (import what you need; nothing heavy is imported here):

* :mod:`matcap.evaluation.datasets` -- DiLiGenT-layout, UW-capture and synthetic-split loaders -> :class:`PSObject`
* :mod:`matcap.evaluation.metrics` -- angular error maps, MAE / median / share under 10, 20, 30 degrees
* :mod:`matcap.evaluation.baselines` -- least-squares Lambertian photometric stereo and a robust variant
* :mod:`matcap.evaluation.runner` -- method registry, K-images x N-trials protocol, tables, error-map PNGs
"""

"""matcap: relighting and material capture.

Library entry points (each mirrors a CLI command) are imported lazily so that ``import matcap`` stays light.
"""
from scenes.materialmaps import MaterialMaps

__all__ = ["MaterialMaps"]
__version__ = "0.1.0"

_LAZY = ("relight", "gallery")  # callable modules: ``from matcap import relight; relight(...)``


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return importlib.import_module(f"matcap.{name}")
    raise AttributeError(f"module 'matcap' has no attribute {name!r}")

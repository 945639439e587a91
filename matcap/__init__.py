"""matcap: relighting and material capture.

Library entry points (each mirrors a CLI command) are imported lazily so that ``import matcap`` stays light.
"""
from scenes.materialmaps import MaterialMaps

__all__ = ["MaterialMaps"]
__version__ = "0.1.0"

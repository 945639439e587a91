"""Synthetic scene specifications (geometry, materials, lights) and the SVBRDF map type. numpy/trimesh only."""
from scenes.materialmaps import MaterialMaps

__all__ = ["MaterialMaps"]

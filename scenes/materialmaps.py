"""`MaterialMaps`: the one type that carries SVBRDF maps between stages (capture, relight, export, eval).

All arrays are linear float32 in image layout (row 0 = top of the image). Encodings (sRGB, 8/16-bit, OpenGL or
DirectX normals) are decided only when files are written (``matcap.export`` / ``matcap.results``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np


@dataclass
class MaterialMaps:
    """SVBRDF maps of one scene seen from a fixed orthographic-like camera.

    normal: (H, W, 3) unit vectors in camera space: x right, y up, z toward the camera; zeros outside ``mask``.
    mask: (H, W) bool, True where the surface is valid.
    base_color: (H, W, 3) linear RGB in [0, 1], or None.
    roughness: (H, W) in [0, 1] (Principled/glTF perceptual roughness), or None.
    metallic: (H, W) in [0, 1], or None.
    height: (H, W) height along +z in pixel units, or None.
    meta: free-form provenance (model name and licence, colour handling, source files).
    """

    normal: np.ndarray
    mask: np.ndarray
    base_color: np.ndarray | None = None
    roughness: np.ndarray | None = None
    metallic: np.ndarray | None = None
    height: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.normal = np.asarray(self.normal, dtype=np.float32)
        if self.normal.ndim != 3 or self.normal.shape[2] != 3:
            raise ValueError(f"normal must be (H, W, 3), got {self.normal.shape}")
        h, w = self.normal.shape[:2]
        self.mask = np.asarray(self.mask).astype(bool)
        if self.mask.shape != (h, w):
            raise ValueError(f"mask must be {(h, w)}, got {self.mask.shape}")
        for name, channels in (("base_color", 3), ("roughness", 0), ("metallic", 0), ("height", 0)):
            value = getattr(self, name)
            if value is None:
                continue
            value = np.asarray(value, dtype=np.float32)
            want = (h, w, channels) if channels else (h, w)
            if value.shape != want:
                raise ValueError(f"{name} must be {want}, got {value.shape}")
            setattr(self, name, value)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W)."""
        return self.normal.shape[:2]

    @property
    def has_brdf(self) -> bool:
        return self.base_color is not None and self.roughness is not None and self.metallic is not None

    def with_defaults(self, base_color=(0.8, 0.8, 0.8), roughness: float = 0.5, metallic: float = 0.0) -> "MaterialMaps":
        """A copy where missing BRDF maps are filled with constants (for relighting normal-only results)."""
        h, w = self.shape
        return replace(
            self,
            base_color=self.base_color if self.base_color is not None
            else np.broadcast_to(np.asarray(base_color, np.float32), (h, w, 3)).copy(),
            roughness=self.roughness if self.roughness is not None else np.full((h, w), roughness, np.float32),
            metallic=self.metallic if self.metallic is not None else np.full((h, w), metallic, np.float32),
        )

    def with_constant(self, name: str, value: float) -> "MaterialMaps":
        """A copy whose ``name`` map (``"roughness"`` or ``"metallic"``) is ``value`` on the mask and 0 off it, as
        estimated maps are. For a map the user knows better than the network (metallic 0 for a non-metal)."""
        value = check_constant(name, value)
        return replace(self, **{name: np.where(self.mask, np.float32(value), np.float32(0)).astype(np.float32)})

    def with_constants(self, values: dict[str, float]) -> "MaterialMaps":
        """:meth:`with_constant` for each ``name: value`` of ``values``, listed in ``meta["constant_maps"]`` (added
        to any listed there before)."""
        out = self
        for name, value in values.items():
            out = out.with_constant(name, value)
        listed = {**self.meta.get("constant_maps", {}), **{name: float(value) for name, value in values.items()}}
        return replace(out, meta={**self.meta, "constant_maps": listed})


def check_constant(name: str, value: float) -> float:
    """``value`` as a float if ``name`` is a map that may be set to a constant and ``value`` lies in [0, 1]."""
    if name not in ("roughness", "metallic"):
        raise ValueError(f"only roughness and metallic can be set to a constant, not {name!r}")
    value = float(value)
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must lie in [0, 1], got {value:g}")
    return value

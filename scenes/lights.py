"""Light descriptions shared by synthetic scenes and relighting. Plain, JSON-serialisable dataclasses.

World space = our camera space: x right, y up, z toward the camera; the orthographic camera looks down -z.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Union


@dataclass
class DirectionalLight:
    """A distant light. ``direction`` points from the scene toward the light (unit or not, normalised on use);
    ``irradiance``: linear RGB irradiance on a surface facing the light."""

    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    irradiance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    kind: str = field(default="directional", init=False)


@dataclass
class PointLight:
    """An isotropic point light at ``position`` with radiant ``intensity`` (W/sr, linear RGB)."""

    position: tuple[float, float, float] = (0.0, 0.0, 3.0)
    intensity: tuple[float, float, float] = (10.0, 10.0, 10.0)
    kind: str = field(default="point", init=False)


@dataclass
class EnvironmentLight:
    """An equirectangular environment map (latitude-longitude, +y up).

    ``source`` names the map (a file path, or ``"procedural:<seed>"`` for a generated sky); the pixels themselves
    are handed to the renderer separately so specs stay small. ``rotation_deg`` turns the map about +y;
    ``scale`` multiplies its radiance (exposure EV e gives scale 2**e).
    """

    source: str = ""
    rotation_deg: float = 0.0
    scale: float = 1.0
    kind: str = field(default="environment", init=False)


Light = Union[DirectionalLight, PointLight, EnvironmentLight]
_KINDS = {"directional": DirectionalLight, "point": PointLight, "environment": EnvironmentLight}


def light_to_dict(light: Light) -> dict[str, Any]:
    return asdict(light)


def light_from_dict(d: dict[str, Any]) -> Light:
    d = dict(d)
    kind = d.pop("kind")
    if kind not in _KINDS:
        raise ValueError(f"unknown light kind {kind!r}")
    for key in ("direction", "irradiance", "position", "intensity"):
        if key in d:
            d[key] = tuple(float(v) for v in d[key])
    return _KINDS[kind](**d)

"""Light descriptions shared by synthetic scenes and relighting. Plain, JSON-serialisable dataclasses.

World space = our camera space: x right, y up, z toward the camera; the orthographic camera looks down -z.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Union

import numpy as np


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


@dataclass
class SpotLight:
    """A spot light at ``position`` aimed at ``target``: radiant ``intensity`` (W/sr, linear RGB) on its axis,
    falling off smoothly from ``beam_deg`` to zero at ``cutoff_deg`` (half-angles), so regions stay unlit."""

    position: tuple[float, float, float] = (0.0, 0.0, 3.0)
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    intensity: tuple[float, float, float] = (10.0, 10.0, 10.0)
    cutoff_deg: float = 20.0
    beam_deg: float = 15.0
    kind: str = field(default="spot", init=False)


@dataclass
class AreaLight:
    """A one-sided square emitter of side ``size`` centred at ``position`` facing ``target`` with uniform
    ``radiance`` (linear RGB). Synthetic scenes keep it outside the orthographic view."""

    position: tuple[float, float, float] = (1.5, 0.0, 2.0)
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    size: float = 0.5
    radiance: tuple[float, float, float] = (10.0, 10.0, 10.0)
    kind: str = field(default="area", init=False)


Light = Union[DirectionalLight, PointLight, EnvironmentLight, SpotLight, AreaLight]
_KINDS = {"directional": DirectionalLight, "point": PointLight, "environment": EnvironmentLight, "spot": SpotLight,
          "area": AreaLight}


def light_to_dict(light: Light) -> dict[str, Any]:
    return asdict(light)


def light_from_dict(d: dict[str, Any]) -> Light:
    d = dict(d)
    kind = d.pop("kind")
    if kind not in _KINDS:
        raise ValueError(f"unknown light kind {kind!r}")
    for key in ("direction", "irradiance", "position", "intensity", "target", "radiance"):
        if key in d:
            d[key] = tuple(float(v) for v in d[key])
    return _KINDS[kind](**d)


def envmap_direction(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit directions (toward the light, before the map's rotation) of equirectangular texture coordinates, as
    Mitsuba's ``envmap`` maps them: v = theta / pi from +y, u = atan2(x, -z) / (2 pi)."""
    theta, phi = np.asarray(v) * np.pi, np.asarray(u) * 2 * np.pi
    return np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)


def light_vector(light: Light, envmap_pixels: np.ndarray | None = None) -> np.ndarray:
    """(3,) float32 vector irradiance at the scene origin (mean over RGB): the sum over incoming light of
    radiance x direction toward the light x solid angle. Its direction is where the light comes from, its length
    the irradiance on a surface facing it. Sums linearly over a combination of lights, so an image's light
    ground truth is ``sum_b w_b * light_vector(basis_b)`` (times its exposure). A spot counts as a point light of
    its on-axis intensity (its cone is ignored: the vector says where the light is, also when its cone misses the
    origin)."""
    def unit(x):
        x = np.asarray(x, np.float64)
        return x / max(float(np.linalg.norm(x)), 1e-12)

    if isinstance(light, DirectionalLight):
        return (np.mean(light.irradiance) * unit(light.direction)).astype(np.float32)
    if isinstance(light, (PointLight, SpotLight)):
        p = np.asarray(light.position, np.float64)
        vec = np.mean(light.intensity) / max(float(p @ p), 1e-12) * unit(p)
        return vec.astype(np.float32)
    if isinstance(light, AreaLight):
        p = np.asarray(light.position, np.float64)
        cos_e = max(0.0, float(unit(np.subtract(light.target, p)) @ unit(-p)))
        return (np.mean(light.radiance) * light.size**2 * cos_e / max(float(p @ p), 1e-12) * unit(p)).astype(np.float32)
    if isinstance(light, EnvironmentLight):
        if envmap_pixels is None:
            raise ValueError("an EnvironmentLight needs its pixels")
        arr = np.asarray(envmap_pixels, np.float64).mean(-1)
        h, w = arr.shape
        v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
        d = envmap_direction(u, v)
        solid = np.sin(v * np.pi) * (np.pi / h) * (2 * np.pi / w)
        vec = (arr * solid)[..., None] * d
        vec = vec.reshape(-1, 3).sum(0) * light.scale
        a = np.radians(light.rotation_deg)  # rotation about +y (Mitsuba's rotate([0, 1, 0], angle))
        rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        return (rot @ vec).astype(np.float32)
    raise TypeError(f"not a light: {light!r}")


def envmap_directions(height: int, width: int, rotation_deg: float = 0.0) -> np.ndarray:
    """World directions (H, W, 3) of the texel centres of an equirectangular map under Mitsuba's ``envmap``
    convention (u = atan2(x, -z) / 2pi, v = acos(y) / pi), turned by ``rotation_deg`` about +y."""
    u = (np.arange(width, dtype=np.float64) + 0.5) / width
    v = (np.arange(height, dtype=np.float64) + 0.5) / height
    phi, theta = np.meshgrid(2.0 * np.pi * u, np.pi * v)
    local = np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)], axis=-1)
    a = np.radians(rotation_deg)
    rot = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return local @ rot.T

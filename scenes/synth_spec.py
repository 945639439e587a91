"""Scene specifications for synthetic photometric-stereo training data (PS-Mix style), numpy only.

A :class:`SceneSpec` is a plain, JSON-serialisable dataclass drawn from an explicit ``numpy.random.Generator``
seeded by (global seed, split, scene index, attempt): the same arguments give the same scene on any machine and in
any shard. Assets are named relative to an assets folder laid out like ``shared/data`` (``meshes/x.ply``,
``envmaps/y.hdr``, ``textures/z``); the pixels and vertices are loaded elsewhere (``matcap.synth``).

Recipe (after SDM-UniPS's PS-Mix, extended):
* 1-4 objects overlapping near the image centre: procedural shapes (sphere, box, torus, superquadric, bumpy sphere,
  bumpy torus) and asset meshes, random rotation, scale and depth; a background surface (tilted, sometimes bumpy)
  in 70 % of the train scenes, none otherwise (so both masked and mask-free learning see their case).
* Materials in three categories: diffuse, specular (dielectric) and metallic; base colour / roughness / metallic
  are constants, procedural patterns (noise, stripes, checkers, cells) or PBR texture sets, independently.
* Lights: a BASIS of lights is rendered separately (train: 2 environment-map rotations, 3 directional lights,
  3 point lights); each of the 10 images is a non-negative combination of the basis renders in one of the five
  configurations a) env, b) directional, c) point, d) env + directional, e) env + point.
* Test split: fixed lighting groups like PS-Wild-Test (directional / environment / directional+environment) on
  held-out environment maps, meshes and texture sets (see ``HELD_OUT_*``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from scenes.lights import (
    AreaLight,
    DirectionalLight,
    EnvironmentLight,
    PointLight,
    SpotLight,
    light_from_dict,
    light_to_dict,
)
from scenes.procedural import PATTERNS, random_rotation

GENERATOR_VERSION = "synth-1"
GENERATOR_VERSIONS = {1: "synth-1", 2: "synth-2"}  # --data-version -> generator_version (v1 draws never change)
NUM_IMAGES = 10
SPLITS = {"train": 1, "test": 2}
CONFIGS = "abcde"  # a env, b directional, c point, d env+directional, e env+point
# data v2 adds: f spot, g area, h env+spot, i env+area, m a strong fixed light plus a weak moving one
CONFIGS_V2 = "abcdefghi"
CONFIG_KINDS = {"a": ("env",), "b": ("directional",), "c": ("point",), "d": ("env", "directional"),
                "e": ("env", "point"), "f": ("spot",), "g": ("area",), "h": ("env", "spot"), "i": ("env", "area")}
TEST_GROUPS = ("directional", "environment", "directional+environment")
PROCEDURAL_SHAPES = ("sphere", "box", "torus", "superquadric", "bumpy_sphere", "bumpy_torus")
CATEGORIES = ("diffuse", "specular", "metallic")

# Held-out assets: used by the test split only, never by train. Copies of one place (several resolutions or
# sources) are listed together so that they stay on the same side.
HELD_OUT_ENVMAPS = (
    "tri_env_color_room_75", "tri_env_color_room_150", "tri_env_color_room_1200",
    "drei_studio_small_03_1k", "pmndrs_studio",            # same panorama
    "drei_empty_warehouse_01_1k", "pmndrs_warehouse",      # same panorama
    "blender_sunrise", "pmndrs_sunrise",                   # same panorama
    "pmndrs_esplanade",
)
HELD_OUT_MESHES = ("armadillo", "rocker-arm", "fertility", "decimated-max", "camelhead", "lion")
HELD_OUT_TEXTURES = ("sofa_03", "rosewood_veneer1")
# Meshes that are not usable as solid objects (planar 2-D meshes, inconsistent winding).
UNUSABLE_MESHES = ("alligator", "woody", "truck")
# Texture sets whose normal maps data v2 does not use: bell_pepper is BSD-3-Clause (its notice would have to
# travel with derived data); every other set is CC0 (see shared/data/textures/SOURCES.md).
NO_NORMAL_MAP_TEXTURES = ("bell_pepper",)


def _stem(name: str) -> str:
    base = name.rsplit("/", 1)[-1]
    return base.split(".", 1)[0]


def is_held_out(kind: str, name: str) -> bool:
    stem = _stem(name)
    return stem in {"envmaps": HELD_OUT_ENVMAPS, "meshes": HELD_OUT_MESHES, "textures": HELD_OUT_TEXTURES}[kind]


@dataclass
class AssetCatalog:
    """Names of available assets, relative to the assets folder (``meshes/spot.ply`` ...)."""

    meshes: list[str] = field(default_factory=list)
    envmaps: list[str] = field(default_factory=list)
    textures: list[str] = field(default_factory=list)
    normal_maps: list[str] = field(default_factory=list)  # texture sets with a normal_gl map (data v2)

    def for_split(self, split: str) -> AssetCatalog:
        """Only the assets a split may use: held-out ones for test, the others for train."""
        test = split == "test"

        def keep(kind, names):
            out = [n for n in sorted(names) if is_held_out(kind, n) == test]
            if kind == "meshes":
                out = [n for n in out if _stem(n) not in UNUSABLE_MESHES]
            return out

        nmaps = [n for n in keep("textures", self.normal_maps) if _stem(n) not in NO_NORMAL_MAP_TEXTURES]
        return AssetCatalog(keep("meshes", self.meshes), keep("envmaps", self.envmaps), keep("textures", self.textures),
                            nmaps)


@dataclass
class TextureSpec:
    """A procedural pattern (``pattern`` in scenes.procedural.PATTERNS) or a PBR set (``pattern="pbr"``)."""

    pattern: str
    seed: int = 0
    freq: float = 4.0
    angle: float = 0.0
    pbr_set: str | None = None


@dataclass
class MaterialSpec:
    """Principled BSDF parameters. Each map is ``lo + (hi - lo) * texture`` (a constant when texture is None).

    base colour: ``color_a`` where the texture is 0, ``color_b`` where it is 1 (for PBR: texture colour x tint).
    """

    category: str
    color_a: tuple[float, float, float] = (0.5, 0.5, 0.5)
    color_b: tuple[float, float, float] = (0.5, 0.5, 0.5)
    color_tex: TextureSpec | None = None
    roughness: tuple[float, float] = (0.5, 0.5)
    roughness_tex: TextureSpec | None = None
    metallic: tuple[float, float] = (0.0, 0.0)
    metallic_tex: TextureSpec | None = None
    specular: float = 0.5
    uv_scale: float = 1.0
    normal_tex: TextureSpec | None = None  # data v2: a normal map (PBR set's normal_gl, or a pattern's relief)
    normal_strength: float = 1.0  # tangent x, y scaled by this before renormalising


@dataclass
class ObjectSpec:
    shape: str  # one of PROCEDURAL_SHAPES, "mesh" or "backdrop"
    params: dict[str, float] = field(default_factory=dict)
    mesh: str | None = None
    rotation: list[list[float]] = field(default_factory=lambda: np.eye(3).tolist())
    scale: float = 1.0
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    material: MaterialSpec = field(default_factory=lambda: MaterialSpec("diffuse"))


@dataclass
class ImageSpec:
    config: str  # a..e
    weights: list[float]  # one per basis light, >= 0


@dataclass
class SceneSpec:
    name: str
    index: int
    split: str
    seed: int
    attempt: int
    resolution: int
    objects: list[ObjectSpec]
    background: ObjectSpec | None
    basis: list[dict[str, Any]]  # scenes.lights dicts
    images: list[ImageSpec]
    render_seed: int
    lighting_group: str | None = None
    envmap_normalisation: str = "unit mean radiance over the sphere"
    generator_version: str = GENERATOR_VERSION
    lighting_mode: str | None = None  # data v2 train scenes: "mixed", "fixed+moving" or "spot"

    @property
    def data_version(self) -> int:
        return {v: k for k, v in GENERATOR_VERSIONS.items()}.get(self.generator_version, 1)

    @property
    def basis_kind(self) -> list[str]:  # "env", "directional", "point" (+ "spot", "area" in data v2)
        return [{"environment": "env"}.get(b["kind"], b["kind"]) for b in self.basis]

    def lights(self):
        return [light_from_dict(b) for b in self.basis]

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["basis_kind"] = self.basis_kind
        if d["lighting_mode"] is None:  # v1 specs are stored exactly as before
            del d["lighting_mode"]
        if self.data_version == 1:
            for o in d["objects"] + ([d["background"]] if d["background"] else []):
                o["material"].pop("normal_tex", None)
                o["material"].pop("normal_strength", None)
        return d


def _tex_from(d):
    return None if d is None else TextureSpec(**d)


def _mat_from(d) -> MaterialSpec:
    d = dict(d)
    for k in ("color_tex", "roughness_tex", "metallic_tex", "normal_tex"):
        d[k] = _tex_from(d.get(k))
    for k in ("color_a", "color_b"):
        d[k] = tuple(d[k])
    for k in ("roughness", "metallic"):
        d[k] = tuple(d[k])
    return MaterialSpec(**d)


def _obj_from(d) -> ObjectSpec:
    d = dict(d)
    d["material"] = _mat_from(d["material"])
    d["position"] = tuple(d["position"])
    return ObjectSpec(**d)


# keys a stored scene's spec.json holds besides the spec itself (derived, or written by the renderer)
DERIVED_KEYS = ("basis_kind", "ground_truth_stats", "light_vectors")


def scene_from_dict(d: dict[str, Any]) -> SceneSpec:
    """The spec of :meth:`SceneSpec.to_dict` or of a dataset's ``spec.json``."""
    d = {k: v for k, v in d.items() if k not in DERIVED_KEYS}
    d["objects"] = [_obj_from(o) for o in d["objects"]]
    d["background"] = None if d.get("background") is None else _obj_from(d["background"])
    d["images"] = [ImageSpec(**i) for i in d["images"]]
    return SceneSpec(**d)


# ----------------------------------------------------------------------------------------------- seeds


def scene_seed_sequence(global_seed: int, split: str, index: int, attempt: int = 0,
                        data_version: int = 1) -> np.random.SeedSequence:
    """The per-scene seed: a function of (global seed, split, scene index, attempt, data version) only, so shards
    agree; data version 1 keeps the entropy it always had."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
    extra = [] if data_version == 1 else [int(data_version)]
    return np.random.SeedSequence([int(global_seed) & 0xFFFFFFFF, SPLITS[split], int(index), int(attempt), 0x5EED]
                                  + extra)


def _sub_seed(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2**31 - 1))


# ----------------------------------------------------------------------------------------------- materials


def _random_color(rng: np.random.Generator, dark_ok: bool = True) -> tuple[float, float, float]:
    """A linear RGB albedo: random hue/saturation, value mostly in [0.05, 0.9]."""
    h = rng.random()
    s = rng.choice([rng.uniform(0, 0.15), rng.uniform(0.2, 0.9)], p=[0.3, 0.7])
    v = rng.uniform(0.05 if dark_ok else 0.3, 0.9)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6) % 6
    rgb = v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)
    return tuple(float(c) for c in np.clip(rgb ** 2.2, 0.003, 0.85))


def _random_pattern(rng: np.random.Generator, textures: list[str], pbr_prob: float) -> TextureSpec:
    if textures and rng.random() < pbr_prob:
        return TextureSpec("pbr", pbr_set=str(rng.choice(textures)))
    kind = str(rng.choice(PATTERNS))
    freq = float(rng.uniform(2, 12)) if kind in ("stripes", "checkers") else float(rng.uniform(2, 6))
    return TextureSpec(kind, seed=_sub_seed(rng), freq=freq, angle=float(rng.uniform(0, np.pi)))


def random_material(rng: np.random.Generator, textures: list[str], category: str | None = None) -> MaterialSpec:
    category = category or str(rng.choice(CATEGORIES, p=[0.4, 0.35, 0.25]))
    color_a = _random_color(rng)
    color_b = _random_color(rng) if rng.random() < 0.8 else color_a
    color_tex = None
    mode = rng.random()
    if mode < 0.6:
        color_tex = _random_pattern(rng, textures, pbr_prob=0.5)
        if color_tex.pattern == "pbr":  # PBR colour times a tint (colour_a = colour_b = tint)
            tint = np.clip(np.array(_random_color(rng, dark_ok=False)) ** 0.3 * 1.2, 0.2, 1.0) if rng.random() < 0.5 else np.ones(3)
            color_a = color_b = tuple(float(c) for c in tint)
    if category == "diffuse":
        rough = tuple(sorted(rng.uniform(0.5, 1.0, 2)))
        metal = (0.0, 0.0)
        specular = float(rng.uniform(0.0, 0.3))
    elif category == "specular":
        rough = tuple(sorted(rng.uniform(0.08, 0.6, 2)))
        metal = (0.0, 0.0)
        specular = float(rng.uniform(0.4, 1.0))
    else:
        rough = tuple(sorted(rng.uniform(0.1, 0.6, 2)))
        metal = (float(rng.uniform(0.0, 0.6)), 1.0) if rng.random() < 0.4 else (1.0, 1.0)
        specular = 0.5
        if color_tex is None or color_tex.pattern != "pbr":  # metals: brighter, less saturated colours
            color_a = tuple(float(c) for c in np.clip(np.array(color_a) ** 0.4, 0.2, 0.98))
            color_b = tuple(float(c) for c in np.clip(np.array(color_b) ** 0.4, 0.2, 0.98))
    rough_tex = _random_pattern(rng, textures, 0.3) if rng.random() < 0.6 else None
    if rough_tex is None:
        rough = (rough[1], rough[1])
    metal_tex = None
    if metal[0] != metal[1]:
        metal_tex = _random_pattern(rng, [], 0.0)
    return MaterialSpec(
        category=category, color_a=color_a, color_b=color_b, color_tex=color_tex,
        roughness=(float(rough[0]), float(rough[1])), roughness_tex=rough_tex,
        metallic=(float(metal[0]), float(metal[1])), metallic_tex=metal_tex, specular=specular,
        uv_scale=float(rng.choice([1.0, 1.0, 2.0, 3.0])),
    )


# ----------------------------------------------------------------------------------------------- objects


def _random_object(rng: np.random.Generator, catalog: AssetCatalog, slot: int, count: int) -> ObjectSpec:
    use_mesh = bool(catalog.meshes) and rng.random() < 0.5
    params: dict[str, float] = {}
    mesh = None
    if use_mesh:
        shape = "mesh"
        mesh = str(rng.choice(catalog.meshes))
    else:
        shape = str(rng.choice(PROCEDURAL_SHAPES))
        if shape == "box":
            params = {k: float(rng.uniform(0.4, 1.0)) for k in ("ex", "ey", "ez")}
        elif shape in ("torus", "bumpy_torus"):
            params["minor"] = float(rng.uniform(0.2, 0.45))
        elif shape == "superquadric":
            params = {"e1": float(rng.uniform(0.2, 1.6)), "e2": float(rng.uniform(0.2, 1.6))}
        if shape.startswith("bumpy"):
            params["amplitude"] = float(rng.uniform(0.03, 0.12))
            params["seed"] = float(_sub_seed(rng))
    # Scale: radius in world units (the image spans [-1, 1]^2); more objects -> smaller.
    scale = float(rng.uniform(0.3, 0.75) * (1.0 if count == 1 else rng.uniform(0.6, 1.0)))
    if use_mesh:  # meshes are normalised into the unit ball; most are elongated, so they look smaller
        scale = min(scale * 1.25, 0.79)
    spread = 0.0 if count == 1 else 0.55
    xy = rng.uniform(-spread, spread, 2) if count > 1 else rng.uniform(-0.15, 0.15, 2)
    z = 0.1 * slot + float(rng.uniform(-0.3, 0.3))
    return ObjectSpec(shape=shape, params=params, mesh=mesh, rotation=random_rotation(rng).tolist(), scale=scale,
                      position=(float(xy[0]), float(xy[1]), z), material=random_material(rng, catalog.textures))


def _background(rng: np.random.Generator, catalog: AssetCatalog, objects: list[ObjectSpec]) -> ObjectSpec:
    zmin = min(o.position[2] - o.scale for o in objects)
    tilt = np.deg2rad(rng.uniform(-25, 25, 2))
    rx = np.array([[1, 0, 0], [0, np.cos(tilt[0]), -np.sin(tilt[0])], [0, np.sin(tilt[0]), np.cos(tilt[0])]])
    ry = np.array([[np.cos(tilt[1]), 0, np.sin(tilt[1])], [0, 1, 0], [-np.sin(tilt[1]), 0, np.cos(tilt[1])]])
    bump = float(rng.uniform(0.01, 0.06)) if rng.random() < 0.35 else 0.0
    mat = random_material(rng, catalog.textures, category=str(rng.choice(CATEGORIES, p=[0.6, 0.3, 0.1])))
    # The plane may cut through objects a little (objects "rest in" it) or float behind them.
    z = zmin - float(rng.uniform(-0.1, 0.5))
    return ObjectSpec(shape="backdrop", params={"size": 4.0, "bump": bump, "seed": float(_sub_seed(rng))},
                      rotation=(ry @ rx).tolist(), scale=1.0, position=(0.0, 0.0, float(z)), material=mat)


# ----------------------------------------------------------------------------------------------- lights


def random_direction(rng: np.random.Generator, min_z: float = 0.3) -> tuple[float, float, float]:
    """A unit direction toward a light, uniform on the cap z >= min_z (the camera side of the scene)."""
    z = rng.uniform(min_z, 1.0)
    phi = rng.uniform(0, 2 * np.pi)
    r = np.sqrt(1 - z * z)
    return (float(r * np.cos(phi)), float(r * np.sin(phi)), float(z))


def _tint(rng: np.random.Generator, amount: float = 0.15) -> np.ndarray:
    t = 1.0 + rng.uniform(-amount, amount, 3)
    return t / t.mean()


def random_directional(rng: np.random.Generator) -> DirectionalLight:
    # Irradiance pi: a white Lambertian surface facing it has radiance 1 (like a unit-mean environment).
    return DirectionalLight(direction=random_direction(rng), irradiance=tuple(float(c) for c in np.pi * _tint(rng)))


def random_point(rng: np.random.Generator) -> PointLight:
    pos = np.array([rng.uniform(-1.3, 1.3), rng.uniform(-1.3, 1.3), rng.uniform(1.8, 3.5)])
    d2 = float(pos @ pos)
    # Intensity so that the irradiance at the origin is pi.
    return PointLight(position=tuple(float(c) for c in pos), intensity=tuple(float(c) for c in np.pi * d2 * _tint(rng)))


def _envmap_source(rng: np.random.Generator, catalog: AssetCatalog) -> str:
    if catalog.envmaps and rng.random() < 0.85:
        return str(rng.choice(catalog.envmaps))
    return f"procedural:{_sub_seed(rng)}"


def _env_rotations(rng: np.random.Generator, source: str, count: int) -> list[EnvironmentLight]:
    start = rng.uniform(0, 360)
    return [EnvironmentLight(source=source, rotation_deg=float((start + k * 360.0 / count) % 360), scale=1.0)
            for k in range(count)]


def _train_images(rng: np.random.Generator, kinds: list[str]) -> list[ImageSpec]:
    idx = {k: [i for i, kk in enumerate(kinds) if kk == k] for k in ("env", "directional", "point")}
    images = []
    for _ in range(NUM_IMAGES):
        config = str(rng.choice(list(CONFIGS)))
        w = np.zeros(len(kinds))
        if config in "ade":
            w[rng.choice(idx["env"])] = rng.uniform(0.5, 1.5) if config == "a" else rng.uniform(0.15, 0.8)
        if config in "bd":
            w[rng.choice(idx["directional"])] = rng.uniform(0.5, 2.0)
        if config in "ce":
            w[rng.choice(idx["point"])] = rng.uniform(0.5, 2.0)
        images.append(ImageSpec(config, [float(x) for x in w]))
    return images


# ----------------------------------------------------------------------------------------------- scene


TRAIN_BASIS = {"env": 2, "directional": 3, "point": 3}


def generate_scene(global_seed: int, split: str, index: int, resolution: int,
                   catalog: AssetCatalog | None = None, attempt: int = 0, data_version: int = 1) -> SceneSpec:
    """Draw one scene. ``catalog`` None (or empty) means everything procedural. ``data_version`` 2: see
    :func:`generate_scene_v2`; 1 draws exactly what it always drew."""
    if data_version not in GENERATOR_VERSIONS:
        raise ValueError(f"data version must be one of {sorted(GENERATOR_VERSIONS)}, got {data_version}")
    if data_version == 2:
        return generate_scene_v2(global_seed, split, index, resolution, catalog, attempt)
    catalog = (catalog or AssetCatalog()).for_split(split)
    rng = np.random.default_rng(scene_seed_sequence(global_seed, split, index, attempt))
    count = int(rng.choice([1, 2, 3, 4], p=[0.2, 0.3, 0.3, 0.2]))
    objects = [_random_object(rng, catalog, k, count) for k in range(count)]
    background = _background(rng, catalog, objects) if rng.random() < 0.7 else None
    source = _envmap_source(rng, catalog)
    group = None
    if split == "train":
        basis = (_env_rotations(rng, source, TRAIN_BASIS["env"])
                 + [random_directional(rng) for _ in range(TRAIN_BASIS["directional"])]
                 + [random_point(rng) for _ in range(TRAIN_BASIS["point"])])
        kinds = [k for k, n in TRAIN_BASIS.items() for _ in range(n)]
        images = _train_images(rng, kinds)
    else:
        group = TEST_GROUPS[index % len(TEST_GROUPS)]
        if group == "directional":
            basis = [random_directional(rng) for _ in range(NUM_IMAGES)]
            images = [ImageSpec("b", [1.0 if j == k else 0.0 for j in range(NUM_IMAGES)]) for k in range(NUM_IMAGES)]
        elif group == "environment":
            basis = _env_rotations(rng, source, NUM_IMAGES)
            images = [ImageSpec("a", [1.0 if j == k else 0.0 for j in range(NUM_IMAGES)]) for k in range(NUM_IMAGES)]
        else:  # one environment (fixed) plus a different directional light per image
            basis = _env_rotations(rng, source, 1) + [random_directional(rng) for _ in range(NUM_IMAGES)]
            w_env = float(rng.uniform(0.2, 0.6))
            images = [ImageSpec("d", [w_env] + [1.0 if j == k else 0.0 for j in range(NUM_IMAGES)])
                      for k in range(NUM_IMAGES)]
    return SceneSpec(
        name=f"scene_{index:06d}", index=int(index), split=split, seed=int(global_seed), attempt=int(attempt),
        resolution=int(resolution), objects=objects, background=background,
        basis=[light_to_dict(b) for b in basis], images=images, render_seed=_sub_seed(rng), lighting_group=group,
    )


# ----------------------------------------------------------------------------------------------- data v2

TRAIN_BASIS_V2 = {"env": 2, "directional": 3, "point": 2, "spot": 2, "area": 1}
MODES_V2 = {"mixed": 0.7, "fixed+moving": 0.15, "spot": 0.15}  # how a v2 train scene's 10 images are lit
DISPLACEABLE = ("sphere", "torus", "superquadric", "mesh")


def random_near_point(rng: np.random.Generator) -> PointLight:
    """A point light close to the scene (z 0.9-1.8): irradiance falls off visibly across the objects."""
    pos = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(0.9, 1.8)])
    return PointLight(position=tuple(float(c) for c in pos),
                      intensity=tuple(float(c) for c in np.pi * float(pos @ pos) * _tint(rng)))


def random_spot(rng: np.random.Generator, objects: list[ObjectSpec]) -> SpotLight:
    """A narrow spot aimed near one object: irradiance pi on its axis at the target, regions outside its cone
    unlit (the paper's failure case)."""
    aim = np.asarray(objects[int(rng.integers(len(objects)))].position, float) + np.append(rng.uniform(-0.3, 0.3, 2), 0)
    pos = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), rng.uniform(1.5, 3.0)])
    cutoff = float(rng.uniform(12, 30))
    d2 = float(((pos - aim) ** 2).sum())
    return SpotLight(position=tuple(float(c) for c in pos), target=tuple(float(c) for c in aim),
                     intensity=tuple(float(c) for c in np.pi * d2 * _tint(rng)), cutoff_deg=cutoff,
                     beam_deg=float(cutoff * rng.uniform(0.5, 0.9)))


def random_area(rng: np.random.Generator) -> AreaLight:
    """A square area light outside the orthographic view (|x| or |y| > 1.4), facing the origin, irradiance about
    pi there."""
    phi = rng.uniform(0, 2 * np.pi)
    r = rng.uniform(1.4, 2.2)
    pos = np.array([r * np.cos(phi), r * np.sin(phi), rng.uniform(0.8, 2.5)])
    size = float(rng.uniform(0.4, 1.0))
    d = float(np.linalg.norm(pos))
    cos_e = 1.0  # it faces the origin
    radiance = np.pi * d * d / (size * size * cos_e) * _tint(rng)
    return AreaLight(position=tuple(float(c) for c in pos), target=(0.0, 0.0, 0.0), size=size,
                     radiance=tuple(float(c) for c in radiance))


def _add_detail(rng: np.random.Generator, obj: ObjectSpec, catalog: AssetCatalog, background: bool = False) -> None:
    """Data v2 surface detail: a normal map (half the surfaces) and, for smooth shapes, displacement."""
    m = obj.material
    if rng.random() < 0.5:
        if catalog.normal_maps and rng.random() < 0.6:
            m.normal_tex = TextureSpec("pbr", pbr_set=str(rng.choice(catalog.normal_maps)))
        else:
            kind = str(rng.choice(["noise", "cells_edge", "stripes", "checkers"]))
            m.normal_tex = TextureSpec(kind, seed=_sub_seed(rng), freq=float(rng.uniform(2, 8)),
                                       angle=float(rng.uniform(0, np.pi)))
        m.normal_strength = float(rng.uniform(0.4, 1.0))
    if not background and obj.shape in DISPLACEABLE and rng.random() < 0.3:
        obj.params.update({"disp_amp": float(rng.uniform(0.01, 0.05)), "disp_seed": float(_sub_seed(rng)),
                           "disp_freq": float(rng.uniform(2, 6))})


def _occluder(rng: np.random.Generator, catalog: AssetCatalog, objects: list[ObjectSpec]) -> ObjectSpec:
    """A small object in front of another one (partial occlusion and cast shadows)."""
    behind = objects[int(rng.integers(len(objects)))]
    occ = _random_object(rng, catalog, len(objects), 3)
    xy = np.asarray(behind.position[:2]) + rng.uniform(-0.35, 0.35, 2) * behind.scale
    occ.scale = float(behind.scale * rng.uniform(0.3, 0.55))
    occ.position = (float(xy[0]), float(xy[1]), float(behind.position[2] + behind.scale + occ.scale * rng.uniform(0.3, 1.5)))
    return occ


def _v2_images(rng: np.random.Generator, kinds: list[str]) -> tuple[str, list[ImageSpec]]:
    idx = {k: [i for i, kk in enumerate(kinds) if kk == k] for k in TRAIN_BASIS_V2}
    mode = str(rng.choice(list(MODES_V2), p=list(MODES_V2.values())))
    images = []
    if mode == "fixed+moving":  # a strong light fixed for all images, a weak one moving (the paper's failure case)
        fixed_kind = str(rng.choice(["env", "directional", "area"]))
        fixed = int(rng.choice(idx[fixed_kind]))
        strong = rng.uniform(0.8, 1.5) if fixed_kind == "env" else rng.uniform(1.0, 2.0)
        movers = [i for k in ("directional", "point", "spot") for i in idx[k] if i != fixed]
        for _ in range(NUM_IMAGES):
            w = np.zeros(len(kinds))
            w[fixed] = strong
            w[int(rng.choice(movers))] += strong * rng.uniform(0.08, 0.3)
            images.append(ImageSpec("m", [float(x) for x in w]))
        return mode, images
    for _ in range(NUM_IMAGES):
        if mode == "spot":
            config = "f" if rng.random() < 0.7 else "h"
        else:
            config = str(rng.choice(list(CONFIGS_V2), p=[0.14, 0.14, 0.12, 0.14, 0.12, 0.08, 0.08, 0.1, 0.08]))
        w = np.zeros(len(kinds))
        parts = CONFIG_KINDS[config]
        for kind in parts:
            if kind == "env":
                if len(parts) == 1:
                    w[rng.choice(idx["env"])] = rng.uniform(0.5, 1.5)
                else:
                    w[rng.choice(idx["env"])] = rng.uniform(0.02, 0.1) if mode == "spot" else rng.uniform(0.15, 0.8)
            else:
                w[rng.choice(idx[kind])] = rng.uniform(0.5, 2.0)
        images.append(ImageSpec(config, [float(x) for x in w]))
    return mode, images


def generate_scene_v2(global_seed: int, split: str, index: int, resolution: int,
                      catalog: AssetCatalog | None = None, attempt: int = 0) -> SceneSpec:
    """Data v2: 1-6 objects plus, in 35 % of scenes, a small occluder in front of one of them; normal-mapped
    (PBR sets' normal_gl or procedural relief) and displaced surfaces; train lighting from a basis of 2
    environment rotations, 3 directional, 2 near point, 2 spot and 1 area light, each scene lit in one of three
    modes: ``mixed`` (every image one of the configurations a-i), ``fixed+moving`` (a strong fixed light plus a
    weak moving one, configuration m) or ``spot`` (narrow spots leaving regions unlit, f/h). The test split keeps
    v1's lighting groups on v2 geometry."""
    catalog = (catalog or AssetCatalog()).for_split(split)
    rng = np.random.default_rng(scene_seed_sequence(global_seed, split, index, attempt, data_version=2))
    count = int(rng.choice([1, 2, 3, 4, 5, 6], p=[0.1, 0.2, 0.25, 0.2, 0.15, 0.1]))
    objects = [_random_object(rng, catalog, k, count) for k in range(count)]
    if rng.random() < 0.35:
        objects.append(_occluder(rng, catalog, objects))
    for o in objects:
        _add_detail(rng, o, catalog)
    background = _background(rng, catalog, objects) if rng.random() < 0.7 else None
    if background is not None:
        _add_detail(rng, background, catalog, background=True)
    source = _envmap_source(rng, catalog)
    group = None
    if split == "train":
        basis = (_env_rotations(rng, source, TRAIN_BASIS_V2["env"])
                 + [random_directional(rng) for _ in range(TRAIN_BASIS_V2["directional"])]
                 + [random_near_point(rng) for _ in range(TRAIN_BASIS_V2["point"])]
                 + [random_spot(rng, objects) for _ in range(TRAIN_BASIS_V2["spot"])]
                 + [random_area(rng) for _ in range(TRAIN_BASIS_V2["area"])])
        kinds = [k for k, n in TRAIN_BASIS_V2.items() for _ in range(n)]
        group_mode, images = _v2_images(rng, kinds)
    else:
        group_mode = None
        group = TEST_GROUPS[index % len(TEST_GROUPS)]
        one_hot = [[1.0 if j == k else 0.0 for j in range(NUM_IMAGES)] for k in range(NUM_IMAGES)]
        if group == "directional":
            basis = [random_directional(rng) for _ in range(NUM_IMAGES)]
            images = [ImageSpec("b", w) for w in one_hot]
        elif group == "environment":
            basis = _env_rotations(rng, source, NUM_IMAGES)
            images = [ImageSpec("a", w) for w in one_hot]
        else:
            basis = _env_rotations(rng, source, 1) + [random_directional(rng) for _ in range(NUM_IMAGES)]
            w_env = float(rng.uniform(0.2, 0.6))
            images = [ImageSpec("d", [w_env] + w) for w in one_hot]
    return SceneSpec(
        name=f"scene_{index:06d}", index=int(index), split=split, seed=int(global_seed), attempt=int(attempt),
        resolution=int(resolution), objects=objects, background=background,
        basis=[light_to_dict(b) for b in basis], images=images, render_seed=_sub_seed(rng), lighting_group=group,
        generator_version=GENERATOR_VERSIONS[2], lighting_mode=group_mode,
    )

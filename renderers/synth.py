"""Render synthetic photometric-stereo scenes with Mitsuba 3 (imported lazily): one path-traced image per BASIS
light plus ground-truth passes from the ``aov`` integrator. Takes numpy arrays, returns numpy arrays.

Camera: orthographic, looking down -z from z = +10, seeing world x, y in [-1, 1] (world = our camera space:
x right, y up, z toward the camera), so world normals are camera normals. Rendering is deterministic for a
given ``seed`` (independent sampler with a fixed seed; ground-truth passes use one pixel-centre sample).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderers.emitters import emitter_dict
from renderers.variant import render_array
from scenes.lights import AreaLight, EnvironmentLight, Light, SpotLight
from scenes.synth_build import RenderObject, finalize_normals

DEFAULT_SPP = 16
MAX_DEPTH = 3  # direct light + one indirect bounce (throughput trade-off, see docs/synth.md)
DELTA_SPP_FACTOR = 0.5  # directional/point basis renders use half the spp (no environment noise)


@dataclass
class SynthRender:
    basis: np.ndarray  # (B, H, W, 3) float32 linear
    normal: np.ndarray  # (H, W, 3) float32, camera space, zeros outside mask
    mask: np.ndarray  # (H, W) bool: any surface (objects and background surface)
    object_mask: np.ndarray  # (H, W) bool: objects only
    base_color: np.ndarray  # (H, W, 3)
    roughness: np.ndarray  # (H, W)
    metallic: np.ndarray  # (H, W)
    stats: dict


def _mi():
    from renderers.variant import choose_variant

    choose_variant()
    import mitsuba as mi

    return mi


def _bitmap_texture(mi, arr: np.ndarray, uv_scale: float) -> dict:
    arr = np.ascontiguousarray(np.asarray(arr, np.float32))
    return {"type": "bitmap", "bitmap": mi.Bitmap(arr), "raw": True, "filter_type": "bilinear",
            "wrap_mode": "repeat", "to_uv": mi.ScalarTransform4f().scale([uv_scale, uv_scale, 1.0])}


def _make_mesh(mi, name: str, obj: RenderObject, bsdf) -> object:
    g = obj.geometry
    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh(name, len(g.vertices), len(g.faces), props=props, has_vertex_normals=g.normals is not None,
                   has_vertex_texcoords=True)
    params = mi.traverse(mesh)

    def put(key: str, arr: np.ndarray, dtype) -> None:
        # The buffer's own type: mi.Float / mi.UInt32 are JIT arrays in the llvm/cuda variants but plain Python
        # scalars in the scalar ones (where the mesh buffers are drjit.scalar.ArrayXf / ArrayXu).
        params[key] = type(params[key])(np.ascontiguousarray(arr, dtype).ravel())

    put("vertex_positions", g.vertices, np.float32)
    put("faces", g.faces, np.uint32)
    if g.normals is not None:
        put("vertex_normals", g.normals, np.float32)
    put("vertex_texcoords", g.uv, np.float32)
    params.update()
    return mesh


FLAT_NORMAL = np.float32([0.5, 0.5, 1.0])


def _principled(mi, obj: RenderObject, normal_mapped: bool | None = None):
    """twosided(principled), or twosided(normalmap(principled)) when the object has a normal map (or
    ``normal_mapped`` asks for the wrapper anyway: a flat map then, which shades like none)."""
    bsdf = {
        "type": "principled",
        "base_color": _bitmap_texture(mi, obj.base_color, obj.uv_scale),
        "roughness": _bitmap_texture(mi, obj.roughness[..., None], obj.uv_scale),
        "metallic": _bitmap_texture(mi, obj.metallic[..., None], obj.uv_scale),
        "specular": float(obj.specular),
    }
    if normal_mapped is None:
        normal_mapped = obj.normal_map is not None
    if normal_mapped:
        nmap = obj.normal_map if obj.normal_map is not None else np.broadcast_to(FLAT_NORMAL, (4, 4, 3))
        bsdf = {"type": "normalmap", "normalmap": _bitmap_texture(mi, nmap, obj.uv_scale), "bsdf": bsdf}
    return mi.load_dict({"type": "twosided", "bsdf": bsdf})


def bilinear_repeat(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Look a texture up as Mitsuba's ``bitmap`` does (bilinear, wrap ``repeat``, row 0 at v = 0).

    tex: (S, T, C); uv: (N, 2) -> (N, C) float32."""
    tex = np.asarray(tex, np.float32)
    h, w = tex.shape[:2]
    uv = np.asarray(uv, np.float64)
    x = (uv[:, 0] - np.floor(uv[:, 0])) * w - 0.5
    y = (uv[:, 1] - np.floor(uv[:, 1])) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64) % w, y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    out = (tex[y0, x0] * (1 - fx) * (1 - fy) + tex[y0, x1] * fx * (1 - fy)
           + tex[y1, x0] * (1 - fx) * fy + tex[y1, x1] * fx * fy)
    return out.astype(np.float32)


def apply_normal_maps(sh_normal: np.ndarray, dp_du: np.ndarray, uv: np.ndarray, index: np.ndarray,
                      hit: np.ndarray, maps: dict[int, np.ndarray]) -> np.ndarray:
    """The shading normals Mitsuba's ``normalmap`` BSDF uses, from AOVs (H, W, .): ``n = normalize(s x + t y + N z)``
    with the map's (x, y, z) at the pixel's uv, N the interpolated normal, s = dp/du made orthogonal to N,
    t = N x s. ``index``: (H, W) int shape slot per pixel; ``maps``: slot -> (S, S, 3) encoded map (uv already
    scaled)."""
    out = np.asarray(sh_normal, np.float32).copy()
    for idx, nmap in maps.items():
        sel = hit & (np.asarray(index) == idx)
        if nmap is None or not sel.any():
            continue
        m = bilinear_repeat(nmap, uv[sel]) * 2 - 1
        n = out[sel].astype(np.float64)
        d = dp_du[sel].astype(np.float64)
        s_ = d - n * (n * d).sum(-1, keepdims=True)
        s_ /= np.maximum(np.linalg.norm(s_, axis=-1, keepdims=True), 1e-12)
        t_ = np.cross(n, s_)
        v = s_ * m[:, 0:1] + t_ * m[:, 1:2] + n * m[:, 2:3]
        out[sel] = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    return out


def _params_tex(obj: RenderObject, slot: int) -> np.ndarray:
    """(S, S, 3): roughness, metallic, and a code of (is_background, slot): 0.5 * is_background + (slot + 1) / 256
    (exact in float32; below 0.5 for objects)."""
    code = (0.5 if obj.is_background else 0.0) + (slot + 1) / 256.0
    return np.stack([obj.roughness, obj.metallic, np.full_like(obj.roughness, code)], -1)


def _decode_slot(code: np.ndarray) -> np.ndarray:
    """Shape slot per pixel from the third channel of the parameter pass (-1 where nothing was hit)."""
    return np.rint((code - np.where(code >= 0.5, 0.5, 0.0)) * 256).astype(np.int64) - 1


def _params_as_albedo(mi, obj: RenderObject, slot: int = 0):
    """A diffuse BSDF whose reflectance is :func:`_params_tex`: read back with the albedo AOV."""
    tex = _params_tex(obj, slot)
    return mi.load_dict({"type": "twosided", "bsdf": {"type": "diffuse",
                                                      "reflectance": _bitmap_texture(mi, tex, obj.uv_scale)}})


def _sensor(mi, resolution: int, spp: int, seed: int, centre: bool = False):
    sampler = ({"type": "stratified", "sample_count": 1, "jitter": False, "seed": int(seed)} if centre
               else {"type": "independent", "sample_count": int(spp), "seed": int(seed)})
    return mi.load_dict({
        "type": "orthographic",
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 10], target=[0, 0, 0], up=[0, 1, 0]),
        "near_clip": 0.01, "far_clip": 100.0,
        "sampler": sampler,
        "film": {"type": "hdrfilm", "width": int(resolution), "height": int(resolution),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    })


def _look_at(mi, position, target):
    p, t = np.asarray(position, float), np.asarray(target, float)
    d = t - p
    up = [0, 1, 0] if abs(d[1]) < 0.99 * np.linalg.norm(d) else [1, 0, 0]
    return mi.ScalarTransform4f().look_at(origin=p.tolist(), target=t.tolist(), up=up)


def _emitter(light: Light, envmaps: dict[str, np.ndarray], weight: float = 1.0) -> dict:
    """The Mitsuba dict of one light (an area light is a ``rectangle`` shape with an ``area`` emitter)."""
    if isinstance(light, SpotLight):
        mi = _mi()
        return {"type": "spot", "to_world": _look_at(mi, light.position, light.target),
                "intensity": {"type": "rgb", "value": [float(v) * weight for v in light.intensity]},
                "cutoff_angle": float(light.cutoff_deg), "beam_width": float(light.beam_deg)}
    if isinstance(light, AreaLight):
        mi = _mi()
        # rectangle: [-1, 1]^2 in z = 0, emitting toward +z; look_at's z axis points at the target
        return {"type": "rectangle",
                "to_world": _look_at(mi, light.position, light.target) @ mi.ScalarTransform4f().scale(
                    [light.size / 2, light.size / 2, 1.0]),
                "emitter": {"type": "area", "radiance": {"type": "rgb",
                                                         "value": [float(v) * weight for v in light.radiance]}}}
    pixels = envmaps.get(light.source) if isinstance(light, EnvironmentLight) else None
    if isinstance(light, EnvironmentLight) and pixels is None:
        raise ValueError(f"environment map {light.source!r} not loaded")
    d = emitter_dict(light, pixels)
    if weight != 1.0:  # scale a copy (linearity test / direct renders of combined lights)
        if d["type"] == "envmap":
            d["scale"] = d["scale"] * weight
        else:
            key = "irradiance" if d["type"] == "directional" else "intensity"
            d[key] = {"type": "rgb", "value": [v * weight for v in d[key]["value"]]}
    return d


GT_AOVS = "nn:sh_normal,ng:geo_normal,alb:albedo,dd:depth"
GT_AOVS_NORMAL_MAPPED = GT_AOVS + ",uv:uv,dpdu:dp_du"  # channels 10-11, 12-14


def _normal_mapped(a: np.ndarray, b: np.ndarray, objects: list[RenderObject], uv_scaled: bool) -> np.ndarray:
    """``a`` (the 15-channel AOV pass) with its shading normals (channels 0-2) replaced by the normal-mapped ones;
    the shape slot of each pixel comes from the parameter pass ``b``."""
    slot = _decode_slot(b[..., 2])
    hit = (a[..., 9] > 0) & (b[..., 3] > 0)
    a = a.copy()
    for k, o in enumerate(objects):
        if o.normal_map is None:
            continue
        uv = a[..., 10:12] * np.float32(1.0 if uv_scaled else o.uv_scale)
        a[..., 0:3] = apply_normal_maps(a[..., 0:3], a[..., 12:15], uv, slot, hit, {k: o.normal_map})
    return a


def _ground_truth_from(a: np.ndarray, b: np.ndarray) -> dict:
    """Ground-truth maps from the AOV passes: ``a`` (H, W, 10) sh_normal, geo_normal, albedo, depth of the
    principled shapes; ``b`` (H, W, 4) albedo (roughness, metallic, is_background), depth of the parameter shapes."""
    hit = a[..., 9] > 0
    hit2 = b[..., 3] > 0
    normal, stats = finalize_normals(a[..., 0:3], a[..., 3:6], hit)
    stats["mask_agreement"] = float((hit == hit2).mean())
    zero3 = np.zeros(3, np.float32)
    return {
        "normal": normal, "mask": hit, "object_mask": hit & (b[..., 2] < 0.5),
        "base_color": np.where(hit[..., None], np.clip(a[..., 6:9], 0, 1), zero3),
        "roughness": np.where(hit, np.clip(b[..., 0], 0, 1), 0.0).astype(np.float32),
        "metallic": np.where(hit, np.clip(b[..., 1], 0, 1), 0.0).astype(np.float32),
        "stats": stats,
    }


class SceneRenderer:
    """Holds the Mitsuba shapes of one scene; renders any set of lights on them."""

    def __init__(self, objects: list[RenderObject], resolution: int, spp: int = DEFAULT_SPP, seed: int = 0,
                 max_depth: int = MAX_DEPTH):
        self.mi = mi = _mi()
        self.objects = objects
        self.resolution, self.spp, self.seed = int(resolution), int(spp), int(seed)
        self.shapes = {f"shape_{k:02d}": _make_mesh(mi, f"shape_{k:02d}", o, _principled(mi, o))
                       for k, o in enumerate(objects)}
        self.sensor = _sensor(mi, resolution, spp, seed)
        self.integrator = mi.load_dict({"type": "path", "max_depth": int(max_depth)})
        self._single: dict[tuple, tuple] = {}  # one-light scenes kept loaded, by kind of light (and env map)

    def render(self, lights: list[Light], envmaps: dict[str, np.ndarray], weights: list[float] | None = None,
               spp: int | None = None, reuse: bool = True) -> np.ndarray:
        """Linear (H, W, 3) float32 render with all ``lights`` on (each scaled by ``weights``).

        A single light reuses the loaded scene of the previous light of its kind (same env map for environment
        lights) and only updates the emitter's parameters: the shapes' acceleration structure is built once per
        kind instead of once per basis light. The image is the same as from a freshly loaded scene
        (``reuse=False`` loads one).
        """
        mi = self.mi
        weights = weights or [1.0] * len(lights)
        if len(lights) == 1 and reuse:
            scene = self._single_light_scene(lights[0], envmaps, weights[0])
        else:
            desc = {"type": "scene", "sensor": self.sensor, **self.shapes}
            for k, (light, w) in enumerate(zip(lights, weights)):
                desc[f"light_{k:02d}"] = _emitter(light, envmaps, w)
            scene = mi.load_dict(desc)
        return render_array(scene, self.integrator, spp=spp or self.spp, seed=self.seed)[..., :3]

    def _single_light_scene(self, light: Light, envmaps: dict[str, np.ndarray], weight: float):
        mi = self.mi
        desc = _emitter(light, envmaps, weight)
        key = (desc["type"], light.source if isinstance(light, EnvironmentLight) else None)
        if key not in self._single:
            scene = mi.load_dict({"type": "scene", "sensor": self.sensor, **self.shapes, "light_00": desc})
            self._single[key] = (scene, mi.traverse(scene))
            return scene
        scene, params = self._single[key]
        if key[1] is not None:  # the same env map: only its rotation and scale change (no new sampling tables)
            params["light_00.to_world"] = mi.Transform4f(desc["to_world"])
            params["light_00.scale"] = desc["scale"]
        else:
            fresh = mi.traverse(mi.load_dict(desc))
            for name in fresh.keys():
                if name != "sampling_weight":
                    params[f"light_00.{name}"] = fresh[name]
        params.update()
        return scene

    def ground_truth(self) -> dict:
        """Normals, masks and BRDF maps from two one-sample (pixel centre) AOV passes."""
        mi = self.mi
        sensor = _sensor(mi, self.resolution, 1, self.seed, centre=True)
        nmapped = any(o.normal_map is not None for o in self.objects)
        aov = mi.load_dict({"type": "aov", "aovs": GT_AOVS_NORMAL_MAPPED if nmapped else GT_AOVS})
        scene = mi.load_dict({"type": "scene", "sensor": sensor, **self.shapes})
        a = render_array(scene, aov, spp=1, seed=self.seed)
        param_shapes = {name: _make_mesh(mi, name, o, _params_as_albedo(mi, o, k))
                        for k, ((name, _), o) in enumerate(zip(self.shapes.items(), self.objects))}
        scene2 = mi.load_dict({"type": "scene", "sensor": sensor, **param_shapes})
        aov2 = mi.load_dict({"type": "aov", "aovs": "alb:albedo,dd:depth"})
        b = render_array(scene2, aov2, spp=1, seed=self.seed)
        if nmapped:
            a = _normal_mapped(a, b, self.objects, uv_scaled=False)
        return _ground_truth_from(a, b)


def render_object_index(objects: list[RenderObject], resolution: int) -> np.ndarray:
    """(H, W) int16: at each pixel centre, the index into ``objects`` of the visible shape, -1 where none is.

    One AOV pass with every shape given a constant diffuse reflectance that encodes its index (exact in float32),
    for analyses that need per-pixel material parameters the stored maps do not keep (e.g. ``specular``).
    """
    mi = _mi()
    if len(objects) > 1000:
        raise ValueError(f"at most 1000 objects can be indexed, got {len(objects)}")
    shapes = {}
    for k, o in enumerate(objects):
        bsdf = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [(k + 1) / 1024, 0, 0]}})
        shapes[f"shape_{k:02d}"] = _make_mesh(mi, f"shape_{k:02d}", o, bsdf)
    scene = mi.load_dict({"type": "scene", "sensor": _sensor(mi, resolution, 1, 0, centre=True), **shapes})
    a = render_array(scene, mi.load_dict({"type": "aov", "aovs": "alb:albedo,dd:depth"}), spp=1, seed=0)
    index = np.rint(a[..., 0] * 1024).astype(np.int16) - 1
    return np.where(a[..., 3] > 0, index, -1).astype(np.int16)


def render_scene(objects: list[RenderObject], basis: list[Light], envmaps: dict[str, np.ndarray], resolution: int,
                 spp: int = DEFAULT_SPP, seed: int = 0, renderer: "BasisRenderer | None" = None,
                 persistent: bool = True) -> SynthRender:
    """Render every basis light separately (environment maps and area lights at ``spp``, delta lights -
    directional, point, spot - at half of it) plus the ground truth.

    ``persistent`` (default; JIT variants only): through a :class:`BasisRenderer` (``renderer``, or a new one)
    whose Mitsuba scenes outlive the scene: pass the same ``renderer`` for every scene of a dataset and nothing is
    loaded or compiled again. ``persistent=False`` loads fresh Mitsuba scenes (:class:`SceneRenderer`);
    both give the same images up to Monte Carlo noise.
    """
    delta_spp = max(1, round(spp * DELTA_SPP_FACTOR))
    if persistent and _mi().variant().startswith("scalar"):
        persistent = False  # nothing to save there (no kernel compilation); see BasisRenderer
    if not persistent:
        r = SceneRenderer(objects, resolution, spp, seed)
        renders = np.stack([r.render([light], envmaps, spp=None if isinstance(light, (EnvironmentLight, AreaLight))
                                     else delta_spp) for light in basis])
        return SynthRender(basis=renders, **r.ground_truth())
    if renderer is None or renderer.resolution != int(resolution):
        renderer = BasisRenderer(resolution)
    renderer.set_objects(objects)
    renders = np.stack([renderer.render(light, envmaps, spp if isinstance(light, (EnvironmentLight, AreaLight))
                                        else delta_spp, seed) for light in basis])
    return SynthRender(basis=renders, **renderer.ground_truth(seed))


# ----------------------------------------------------------------------------------------------- persistent scenes

_PARKED = np.float32([[5.0, 5.0, -50.0], [5.0001, 5.0, -50.0], [5.0, 5.0001, -50.0]])  # an unused slot's triangle


class BasisRenderer:
    """Mitsuba scenes that outlive one synthetic scene: one per kind of light (the path tracer needs the light
    alone in its scene) plus one for the BRDF-parameter ground-truth pass, each with ``slots`` mesh shapes.

    A new synthetic scene only overwrites buffers through ``mi.traverse`` (vertex positions, faces, normals, uv,
    texture data, emitter parameters); unused slots hold one tiny triangle parked outside the view behind the
    scene. Nothing is loaded and, once each kind has been seen, no kernel is compiled again: Dr.Jit's kernel cache
    hits because the scene's structure never changes (kernel compilation used to take more time per scene than
    path tracing at 256^2). JIT variants only (llvm/cuda): the scalar variants compile nothing, and their
    ParameterSet cannot swap a buffer for one of another size; :func:`render_scene` loads fresh scenes there.
    """

    def __init__(self, resolution: int, slots: int = 5, max_depth: int = MAX_DEPTH, normal_maps: bool = False):
        self.mi = mi = _mi()
        if mi.variant().startswith("scalar"):
            raise ValueError(f"BasisRenderer needs a JIT variant (llvm_ad_rgb / cuda_ad_rgb), not {mi.variant()}")
        self.resolution, self.slots = int(resolution), int(slots)
        self.normal_maps = bool(normal_maps)  # every shape's BSDF wrapped in a normalmap (flat where it has none)
        self.integrator = mi.load_dict({"type": "path", "max_depth": int(max_depth)})
        self.aov = mi.load_dict({"type": "aov", "aovs": GT_AOVS_NORMAL_MAPPED if normal_maps else GT_AOVS})
        self.aov2 = mi.load_dict({"type": "aov", "aovs": "alb:albedo,dd:depth"})
        self._sensors: dict[tuple, object] = {}
        self._scenes: dict[str, tuple] = {}  # kind -> (scene, params)
        self._objects: list[RenderObject] = []
        self._buffers: list[dict] | None = None
        self._version = 0
        self._synced: dict[str, int] = {}

    # -- helpers
    def _sensor(self, spp: int, seed: int, centre: bool = False):
        key = (int(spp), int(seed), centre)
        if key not in self._sensors:
            if len(self._sensors) > 16:
                self._sensors.clear()
            self._sensors[key] = _sensor(self.mi, self.resolution, spp, seed, centre=centre)
        return self._sensors[key]

    def _placeholder(self) -> RenderObject:
        from scenes.procedural import Geometry

        g = Geometry(_PARKED.copy(), np.int32([[0, 1, 2]]), None, np.float32([[0, 0], [1, 0], [0, 1]]))
        z = np.zeros((4, 4), np.float32)
        return RenderObject(g, np.zeros((4, 4, 3), np.float32), z + 0.5, z, 0.5, 1.0)

    def _new_scene(self, kind: str, emitter: dict | None):
        mi = self.mi
        ph = self._placeholder()
        desc = {"type": "scene"}
        for k in range(self.slots):
            bsdf = _params_as_albedo(mi, ph) if kind == "params" else _principled(mi, ph, self.normal_maps)
            desc[f"shape_{k:02d}"] = _make_mesh(mi, f"shape_{k:02d}", ph, bsdf)
        if emitter is not None:
            desc["light_00"] = emitter
        scene = mi.load_dict(desc)
        return scene, mi.traverse(scene)

    def set_objects(self, objects: list[RenderObject]) -> None:
        """The shapes of the next synthetic scene (at most ``slots``; more rebuild the scenes with more slots)."""
        if len(objects) > self.slots or (any(o.normal_map is not None for o in objects) and not self.normal_maps):
            self.slots = max(self.slots, len(objects))
            self.normal_maps = self.normal_maps or any(o.normal_map is not None for o in objects)
            self.aov = self.mi.load_dict({"type": "aov", "aovs": GT_AOVS_NORMAL_MAPPED if self.normal_maps else GT_AOVS})
            self._scenes.clear()
        self._objects = list(objects)
        self._version += 1

    def _sync(self, kind: str) -> None:
        """Write the current objects into the shapes of one kind's scene (once per synthetic scene)."""
        if self._synced.get(kind) == self._version:
            return
        mi = self.mi
        scene, params = self._scenes[kind]
        objs = self._objects + [self._placeholder()] * (self.slots - len(self._objects))
        for k, o in enumerate(objs):
            name = f"shape_{k:02d}"
            g = o.geometry

            def put(key, arr, dtype):
                params[key] = type(params[key])(np.ascontiguousarray(arr, dtype).ravel())

            put(f"{name}.vertex_positions", g.vertices, np.float32)
            put(f"{name}.faces", g.faces, np.uint32)
            normals = g.normals if g.normals is not None else _flat_vertex_normals(g)
            put(f"{name}.vertex_normals", normals, np.float32)
            # the texture repeat goes into the uv (a texture's to_uv is a literal in the kernel: one kernel per value)
            put(f"{name}.vertex_texcoords", np.asarray(g.uv, np.float32) * np.float32(o.uv_scale), np.float32)
            if kind == "params":
                maps = {"bsdf.brdf_0.reflectance": _params_tex(o, k)}
            else:
                pre = "bsdf.brdf_0.nested_bsdf" if self.normal_maps else "bsdf.brdf_0"
                maps = {f"{pre}.base_color": o.base_color, f"{pre}.roughness": o.roughness[..., None],
                        f"{pre}.metallic": o.metallic[..., None]}
                if self.normal_maps:
                    maps["bsdf.brdf_0.normalmap"] = (o.normal_map if o.normal_map is not None
                                                     else np.broadcast_to(FLAT_NORMAL, (4, 4, 3)))
                params[f"{name}.{pre}.specular"] = type(params[f"{name}.{pre}.specular"])(float(o.specular))
            for key, arr in maps.items():
                params[f"{name}.{key}.data"] = mi.TensorXf(np.ascontiguousarray(arr, np.float32))
        params.update()
        self._synced[kind] = self._version

    def _scene_for(self, light: Light, envmaps: dict[str, np.ndarray], weight: float = 1.0):
        mi = self.mi
        desc = _emitter(light, envmaps, weight)
        kind = desc["type"]
        if kind not in self._scenes:
            self._scenes[kind] = self._new_scene(kind, desc)
            self._synced.pop(kind, None)
        else:
            _, params = self._scenes[kind]
            fresh = mi.traverse(mi.load_dict(desc))
            for name in fresh.keys():
                if name != "sampling_weight":
                    params[f"light_00.{name}"] = fresh[name]
            params.update()
        self._sync(kind)
        return self._scenes[kind][0]

    # -- rendering
    def render(self, light: Light, envmaps: dict[str, np.ndarray], spp: int, seed: int) -> np.ndarray:
        """Linear (H, W, 3) float32 render of the current objects under one light."""
        scene = self._scene_for(light, envmaps)
        return render_array(scene, self.integrator, spp=spp, seed=seed, sensor=self._sensor(spp, seed))[..., :3]

    def ground_truth(self, seed: int = 0) -> dict:
        """Normals, masks and BRDF maps from two one-sample (pixel centre) AOV passes (as SceneRenderer's)."""
        if not self._scenes:
            raise RuntimeError("render a light first")
        kinds = [k for k in self._scenes if k not in ("params", "rectangle")]  # not the area light's extra shape
        kind = kinds[0] if kinds else "directional"
        if kind not in self._scenes:
            from scenes.lights import DirectionalLight

            self._scene_for(DirectionalLight(), {})
        self._sync(kind)
        sensor = self._sensor(1, seed, centre=True)
        a = render_array(self._scenes[kind][0], self.aov, spp=1, seed=seed, sensor=sensor)
        if "params" not in self._scenes:
            self._scenes["params"] = self._new_scene("params", None)
        self._sync("params")
        b = render_array(self._scenes["params"][0], self.aov2, spp=1, seed=seed, sensor=sensor)
        if self.normal_maps:
            a = _normal_mapped(a, b, self._objects, uv_scaled=True)
        return _ground_truth_from(a, b)


def _flat_vertex_normals(g) -> np.ndarray:
    """Vertex normals of a mesh given without (the placeholder triangle): its face normal, per vertex."""
    v = np.asarray(g.vertices, np.float64)
    f = np.asarray(g.faces, np.int64)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], n)
    return (acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-20)).astype(np.float32)

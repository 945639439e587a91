"""A glossy object with a mirror ball beside it, photographed under known distant lights (Mitsuba 3, lazily).

For light-calibration tests, benchmarks and the bundled example. World = camera space (x right, y up, z toward the
camera); an orthographic camera on +z looking down -z sees x, y in [-1, 1], so a square image of ``size`` pixels
maps world (x, y) to pixel (column, row) = ((x + 1) size / 2 - 0.5, (1 - y) size / 2 - 0.5) and the ball of radius
R at (bx, by) is the circle (cx, cy, r) = ((bx + 1) size / 2 - 0.5, (1 - by) size / 2 - 0.5, R size / 2).

Scene: the object (a sphere, or a triangle mesh given as vertices and faces, scaled into a box of half-size
``object_radius``) with a glossy Principled BSDF; the ball, a rough conductor (chrome, GGX alpha ``ball_alpha``);
a diffuse grey backdrop plane behind both (z = ``backdrop_z``) that the lights also light, so the ball's outline
shows against it; a dim uniform "room" ambient that the ball reflects. Each photo has one ``directional`` emitter.
Rendered with the ``path`` integrator, linear RGB; ``max_depth`` 2 by default (direct light and the ambient: the
ball's sharp lobe turns deeper paths from the backdrop into fireflies), 3 to let the ball show the lit object.
Ground truth of the object (normals, mask) from the ``aov`` integrator at one pixel-centre sample.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderers.variant import render_array

DEFAULT_SIZE = 128
DEFAULT_SPP = 36  # a square: the multijitter sampler rounds up to one


@dataclass
class BallScene:
    """What to render (all lengths in world units; the image spans x, y in [-1, 1]).

    directions: (K, 3) unit vectors toward each photo's light; irradiance: (K, 3) linear RGB (default 3.0 each).
    mesh: None for a sphere, else (vertices (V, 3), faces (F, 3)) in any units (centred and scaled here);
    mesh_rotation_deg: turn of the mesh about +y, then about +x (degrees).
    focal_px: a perspective camera instead (pinhole at (0, 0, camera_distance), focal length in pixels, principal
    point at the image centre).
    """

    directions: np.ndarray
    irradiance: np.ndarray | None = None
    object_centre: tuple[float, float, float] = (-0.3, 0.05, 0.0)
    object_radius: float = 0.55
    mesh: tuple[np.ndarray, np.ndarray] | None = None
    mesh_rotation_deg: tuple[float, float] = (0.0, 0.0)
    base_color: tuple[float, float, float] = (0.65, 0.32, 0.18)
    roughness: float = 0.3
    ball_centre: tuple[float, float, float] = (0.58, -0.52, 0.0)
    ball_radius: float = 0.32
    ball_alpha: float = 0.02
    backdrop_z: float = -1.0
    backdrop_albedo: float = 0.45
    ambient: float = 0.03
    max_depth: int = 2
    focal_px: float | None = None  # None: orthographic camera; else a pinhole at (0, 0, camera_distance)
    camera_distance: float = 10.0

    def circle_px(self, size: int) -> tuple[float, float, float]:
        """The ball's true circle (cx, cy, r) in pixels of a ``size`` x ``size`` render (see the module); for the
        perspective camera, its centre's projection and ``focal_px tan(angular radius)`` (an approximation: the
        image of an off-axis sphere is a slight ellipse)."""
        bx, by, bz = self.ball_centre
        if self.focal_px is None:
            return ((bx + 1) * size / 2 - 0.5, (1 - by) * size / 2 - 0.5, self.ball_radius * size / 2)
        depth = self.camera_distance - bz
        c = (size - 1) / 2
        dist = float(np.sqrt(bx * bx + by * by + depth * depth))
        return (c + self.focal_px * bx / depth, c - self.focal_px * by / depth,
                self.focal_px * self.ball_radius / np.sqrt(dist * dist - self.ball_radius ** 2))


@dataclass
class BallRender:
    """images: (K, H, W, 3) float32 linear; normal: (H, W, 3) float32 camera-space normals of the object (zeros
    elsewhere); object_mask / ball_mask: (H, W) bool (pixel centres); circle: the ball's (cx, cy, r) in pixels."""

    images: np.ndarray
    normal: np.ndarray
    object_mask: np.ndarray
    ball_mask: np.ndarray
    circle: tuple[float, float, float]
    directions: np.ndarray
    irradiance: np.ndarray


def default_lights(count: int = 16, seed: int = 0, min_deg: float = 12.0, max_deg: float = 55.0) -> np.ndarray:
    """(count, 3) unit light directions spread over a cone about +z: polar angles in [min_deg, max_deg] (degrees
    from the view axis), azimuths on a golden-angle spiral with a seeded jitter."""
    rng = np.random.default_rng(seed)
    k = np.arange(count)
    u = (k + rng.uniform(0.2, 0.8, count)) / count
    cmin, cmax = np.cos(np.radians(min_deg)), np.cos(np.radians(max_deg))
    cos_t = cmin + (cmax - cmin) * u
    phi = k * np.pi * (3 - np.sqrt(5)) + rng.uniform(0, 2 * np.pi)
    sin_t = np.sqrt(1 - cos_t**2)
    d = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _rotation(deg_y: float, deg_x: float) -> np.ndarray:
    ay, ax = np.radians(deg_y), np.radians(deg_x)
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    return rx @ ry


def placed_mesh(scene: BallScene) -> tuple[np.ndarray, np.ndarray]:
    """The scene's mesh rotated, centred on its bounding box and scaled so its largest half-extent is
    ``object_radius``, at ``object_centre``: (vertices (V, 3) float32, faces (F, 3) uint32)."""
    v, f = scene.mesh
    v = np.asarray(v, dtype=np.float64) @ _rotation(*scene.mesh_rotation_deg).T
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = (v - (lo + hi) / 2) * (scene.object_radius / ((hi - lo).max() / 2)) + np.asarray(scene.object_centre)
    return v.astype(np.float32), np.asarray(f, dtype=np.uint32)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit vertex normals: the area-weighted mean of the faces' normals around each vertex."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = twice the area
    n = np.zeros_like(v)
    for j in range(3):
        np.add.at(n, f[:, j], fn)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def _mesh_shape(mi, vertices: np.ndarray, faces: np.ndarray, bsdf: dict):
    """A Mitsuba mesh with smooth (vertex) normals."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh("object", len(vertices), len(faces), props=props, has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(vertices.ravel(), dtype=np.float32))
    params["vertex_normals"] = mi.Float(np.ascontiguousarray(vertex_normals(vertices, faces).ravel()))
    params["faces"] = mi.UInt32(np.ascontiguousarray(faces.ravel(), dtype=np.uint32))
    params.update()
    return mesh


def scene_shapes(scene: BallScene) -> dict:
    """Mitsuba dict entries (no sensor, no lights): ``object``, ``ball``, ``backdrop`` and the ``ambient``."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    object_bsdf = {"type": "principled", "base_color": {"type": "rgb", "value": list(scene.base_color)},
                   "roughness": float(scene.roughness), "metallic": 0.0, "specular": 0.5}
    if scene.mesh is None:
        obj = {"type": "sphere", "center": list(scene.object_centre), "radius": float(scene.object_radius),
               "bsdf": object_bsdf}
    else:
        obj = _mesh_shape(mi, *placed_mesh(scene), object_bsdf)
    return {
        "object": obj,
        "ball": {"type": "sphere", "center": list(scene.ball_centre), "radius": float(scene.ball_radius),
                 "bsdf": {"type": "roughconductor", "material": "Cr", "distribution": "ggx",
                          "alpha": float(scene.ball_alpha)}},
        "backdrop": {"type": "rectangle", "to_world": T().translate([0, 0, scene.backdrop_z]).scale([3, 3, 1]),
                     "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [scene.backdrop_albedo] * 3}}},
        "ambient": {"type": "constant", "radiance": {"type": "rgb", "value": [scene.ambient] * 3}},
    }


def _sensor(mi, size: int, spp: int, seed: int, centre: bool = False, focal_px: float | None = None,
            distance: float = 10.0) -> dict:
    """Orthographic camera on +z (default), or with ``focal_px`` a pinhole at (0, 0, ``distance``) looking down -z
    with that focal length in pixels (horizontal field of view ``2 atan(size / 2 / focal_px)``, principal point at
    the image centre)."""
    sampler = ({"type": "stratified", "sample_count": 1, "jitter": False, "seed": int(seed)} if centre
               else {"type": "multijitter", "sample_count": int(spp), "seed": int(seed)})
    film = {"type": "hdrfilm", "width": int(size), "height": int(size), "rfilter": {"type": "box"},
            "pixel_format": "rgb"}
    if focal_px is None:
        return {"type": "orthographic",
                "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 10], target=[0, 0, 0], up=[0, 1, 0]),
                "near_clip": 0.01, "far_clip": 100.0, "sampler": sampler, "film": film}
    fov = float(np.degrees(2 * np.arctan(size / 2 / focal_px)))
    return {"type": "perspective", "fov": fov, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, distance], target=[0, 0, 0], up=[0, 1, 0]),
            "near_clip": 0.01, "far_clip": 100.0, "sampler": sampler, "film": film}


def scene_dict(scene: BallScene, k: int, size: int = DEFAULT_SIZE, spp: int = DEFAULT_SPP, seed: int = 0) -> dict:
    """The Mitsuba scene dict of photo ``k`` (its one directional light)."""
    from renderers.emitters import emitter_dict
    from renderers.variant import choose_variant
    from scenes.lights import DirectionalLight

    choose_variant()
    import mitsuba as mi

    irr = _irradiance(scene)
    light = DirectionalLight(tuple(float(v) for v in scene.directions[k]), tuple(float(v) for v in irr[k]))
    return {"type": "scene", "integrator": {"type": "path", "max_depth": int(scene.max_depth)},
            "sensor": _sensor(mi, size, spp, seed + k, focal_px=scene.focal_px, distance=scene.camera_distance),
            **scene_shapes(scene), "light": emitter_dict(light)}


def _irradiance(scene: BallScene) -> np.ndarray:
    k = len(scene.directions)
    if scene.irradiance is None:
        return np.full((k, 3), 3.0)
    return np.broadcast_to(np.asarray(scene.irradiance, dtype=np.float64), (k, 3))


def render(scene: BallScene, size: int = DEFAULT_SIZE, spp: int = DEFAULT_SPP, seed: int = 0) -> BallRender:
    """Render every photo of ``scene`` (one per direction) and the object's ground truth at ``size`` x ``size``."""
    from renderers.variant import choose_variant

    choose_variant()
    import mitsuba as mi

    dirs = np.asarray(scene.directions, dtype=np.float64)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    images = []
    for k in range(len(dirs)):
        mscene = mi.load_dict(scene_dict(scene, k, size, spp, seed))
        images.append(render_array(mscene, spp=spp, seed=seed + k)[..., :3])
    gt = ground_truth(scene, size)
    return BallRender(images=np.stack(images).astype(np.float32), normal=gt["normal"],
                      object_mask=gt["object_mask"], ball_mask=gt["ball_mask"], circle=scene.circle_px(size),
                      directions=dirs, irradiance=np.array(_irradiance(scene)))


def ground_truth(scene: BallScene, size: int = DEFAULT_SIZE) -> dict:
    """The object's camera-space normals (H, W, 3) (zeros elsewhere), ``object_mask`` and ``ball_mask`` (H, W)
    bool, from one pixel-centre sample of the ``aov`` integrator (shading normal, shape index, depth)."""
    from renderers.variant import choose_variant

    choose_variant()
    import mitsuba as mi

    shapes = scene_shapes(scene)
    shapes.pop("ambient")
    desc = {"type": "scene", "sensor": _sensor(mi, size, 1, 0, centre=True, focal_px=scene.focal_px,
                                                distance=scene.camera_distance), **shapes}
    mscene = mi.load_dict(desc)
    aov = mi.load_dict({"type": "aov", "aovs": "nn:sh_normal,si:shape_index,dd:depth"})
    a = render_array(mscene, aov, spp=1, seed=0)
    index = np.rint(a[..., 3]).astype(int)
    hit = a[..., 4] > 0
    # the shape index is not the order of scene.shapes(): name the indices by what they cover (the ball's centre
    # pixel, a corner of the backdrop, the object the rest)
    cx, cy, _ = scene.circle_px(size)
    ball_id = index[int(round(cy)), int(round(cx))]
    backdrop_id = index[0, 0]
    obj = hit & (index != ball_id) & (index != backdrop_id)
    ball = hit & (index == ball_id)
    n = a[..., 0:3].astype(np.float32)
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-8)
    normal = np.where(obj[..., None], n, 0.0).astype(np.float32)
    return {"normal": normal, "object_mask": obj, "ball_mask": ball}


def example_scene(mesh: tuple[np.ndarray, np.ndarray] | None, count: int = 16, seed: int = 0) -> BallScene:
    """The bundled example's scene (``examples/ball``): ``mesh`` (Spot, the cow) turned to a three-quarter view
    left of centre, the chrome ball at the lower right, ``count`` lights from :func:`default_lights` with white
    irradiance drawn uniformly in [2.55, 3.45] (seeded)."""
    rng = np.random.default_rng(seed + 1000)
    irr = np.repeat(rng.uniform(0.85, 1.15, count)[:, None] * 3.0, 3, axis=1)
    return BallScene(directions=default_lights(count, seed), irradiance=irr, mesh=mesh,
                     mesh_rotation_deg=(-40.0, 10.0), object_centre=(-0.25, 0.12, 0.0), object_radius=0.6,
                     ball_centre=(0.66, -0.62, 0.0), ball_radius=0.3)

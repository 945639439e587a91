"""Scene-spec generator: determinism, JSON round trip, ranges, held-out assets, procedural assets."""
import json

import numpy as np

from scenes import procedural as P
from scenes.lights import DirectionalLight, PointLight
from scenes.synth_build import build_render_objects, material_maps
from scenes.synth_spec import (
    CONFIGS,
    HELD_OUT_ENVMAPS,
    NUM_IMAGES,
    TEST_GROUPS,
    AssetCatalog,
    generate_scene,
    is_held_out,
    scene_from_dict,
)

CATALOG = AssetCatalog(
    meshes=["meshes/spot.ply", "meshes/armadillo.ply", "meshes/teapot.ply", "meshes/truck.ply", "meshes/lion.ply"],
    envmaps=["envmaps/blender_city.exr", "envmaps/tri_env_color_room_75.hdr", "envmaps/tri_env_color_room_1200.hdr",
             "envmaps/pmndrs_apartment.exr", "envmaps/pmndrs_studio.exr", "envmaps/drei_studio_small_03_1k.hdr"],
    textures=["textures/curtain", "textures/sofa_03", "textures/bell_pepper"],
)


def test_same_seed_same_spec_and_json_round_trip():
    a = generate_scene(7, "train", 3, 256, CATALOG)
    b = generate_scene(7, "train", 3, 256, CATALOG)
    assert json.dumps(a.to_dict(), sort_keys=True) == json.dumps(b.to_dict(), sort_keys=True)
    text = json.dumps(a.to_dict())
    back = scene_from_dict(json.loads(text))
    assert json.dumps(back.to_dict(), sort_keys=True) == json.dumps(a.to_dict(), sort_keys=True)
    # a different index, seed, split or attempt gives a different scene
    for other in (generate_scene(7, "train", 4, 256, CATALOG), generate_scene(8, "train", 3, 256, CATALOG),
                  generate_scene(7, "test", 3, 256, CATALOG), generate_scene(7, "train", 3, 256, CATALOG, attempt=1)):
        assert json.dumps(other.to_dict(), sort_keys=True) != text


def test_ranges_over_many_scenes():
    counts, configs, cats, bg = [], set(), set(), 0
    for k in range(60):
        s = generate_scene(0, "train", k, 128, CATALOG)
        counts.append(len(s.objects))
        bg += s.background is not None
        assert len(s.images) == NUM_IMAGES
        assert s.basis_kind == ["env"] * 2 + ["directional"] * 3 + ["point"] * 3
        for im in s.images:
            w = np.asarray(im.weights)
            assert w.shape == (8,) and (w >= 0).all() and w.sum() > 0
            configs.add(im.config)
            kinds = {s.basis_kind[j] for j in np.nonzero(w)[0]}
            assert kinds == {"a": {"env"}, "b": {"directional"}, "c": {"point"}, "d": {"env", "directional"},
                             "e": {"env", "point"}}[im.config]
        for light in s.lights():
            if isinstance(light, DirectionalLight):
                d = np.asarray(light.direction)
                assert abs(np.linalg.norm(d) - 1) < 1e-9 and d[2] >= 0.3  # camera-side hemisphere
            if isinstance(light, PointLight):
                assert light.position[2] > 1.5
        for o in s.objects:
            cats.add(o.material.category)
            assert 0.1 < o.scale < 0.8 and max(abs(c) for c in o.position[:2]) <= 0.55
            r = np.asarray(o.rotation)
            assert np.allclose(r @ r.T, np.eye(3), atol=1e-9) and np.linalg.det(r) > 0
            m = o.material
            assert 0 <= m.roughness[0] <= m.roughness[1] <= 1 and 0 <= m.metallic[0] <= m.metallic[1] <= 1
            assert all(0 <= c <= 1 for c in m.color_a + m.color_b)
            if o.shape == "mesh":
                assert not is_held_out("meshes", o.mesh) and "truck" not in o.mesh
    assert set(counts) == {1, 2, 3, 4}
    assert set(configs) == set(CONFIGS)
    assert cats == {"diffuse", "specular", "metallic"}
    assert 20 < bg < 60  # background surface often, but not always


def test_held_out_assets_split_cleanly():
    train = CATALOG.for_split("train")
    test = CATALOG.for_split("test")
    assert not set(train.envmaps) & set(test.envmaps)
    # copies of one place stay on one side
    assert {"envmaps/tri_env_color_room_75.hdr", "envmaps/tri_env_color_room_1200.hdr"} <= set(test.envmaps)
    assert {"envmaps/pmndrs_studio.exr", "envmaps/drei_studio_small_03_1k.hdr"} <= set(test.envmaps)
    assert "meshes/armadillo.ply" in test.meshes and "meshes/armadillo.ply" not in train.meshes
    assert "textures/sofa_03" in test.textures and "textures/sofa_03" not in train.textures
    for k in range(30):
        s = generate_scene(0, "train", k, 64, CATALOG)
        for b in s.basis:
            if b["kind"] == "environment" and not b["source"].startswith("procedural:"):
                assert b["source"].rsplit("/", 1)[-1].split(".")[0] not in HELD_OUT_ENVMAPS


def test_test_split_lighting_groups():
    for k in range(6):
        s = generate_scene(0, "test", k, 64, CATALOG)
        assert s.lighting_group == TEST_GROUPS[k % 3]
        kinds = set(s.basis_kind)
        want = {"directional": {"directional"}, "environment": {"env"},
                "directional+environment": {"env", "directional"}}[s.lighting_group]
        assert kinds == want and len(s.images) == NUM_IMAGES
        for o in s.objects:
            if o.shape == "mesh":
                assert is_held_out("meshes", o.mesh)


def test_procedural_only_scene_builds():
    s = generate_scene(3, "train", 0, 64, None)
    assert all(o.shape != "mesh" for o in s.objects)
    assert all(b["source"].startswith("procedural:") for b in s.basis if b["kind"] == "environment")
    objs = build_render_objects(s)
    for o in objs:
        g = o.geometry
        assert g.vertices.dtype == np.float32 and g.faces.max() < len(g.vertices)
        assert o.base_color.shape == (256, 256, 3) and 0 <= o.base_color.min() and o.base_color.max() <= 1
        assert 0.02 <= o.roughness.min() and o.roughness.max() <= 1


def test_procedural_pieces():
    for g in (P.make_sphere(16), P.make_torus(0.3, 16), P.make_superquadric(0.3, 0.5, 16),
              P.make_bumpy_sphere(0.1, 1, 16), P.make_bumpy_torus(0.3, 0.1, 2, 16)):
        assert P.signed_volume(g.vertices, g.faces) > 0  # outward winding
        assert np.linalg.norm(g.vertices, axis=1).max() <= 1.0 + 1e-5
        assert np.allclose(np.linalg.norm(g.normals, axis=1), 1, atol=1e-4)
    sky = P.procedural_sky(5, 32)
    assert sky.shape == (32, 64, 3) and np.isfinite(sky).all() and sky.min() >= 0
    assert sky[:16].mean() > sky[16:].mean()  # bright sky above the ground
    for kind in P.PATTERNS:
        t = P.pattern(kind, 1, 64, 4.0, 0.3)
        assert t.shape == (64, 64) and 0 <= t.min() and t.max() <= 1 and t.std() > 0.01
        assert np.array_equal(t, P.pattern(kind, 1, 64, 4.0, 0.3))


def test_material_maps_follow_ranges():
    s = generate_scene(11, "train", 5, 64, None)
    for o in s.objects:
        _base, _rough, metal = material_maps(o.material, size=64)
        lo, hi = o.material.metallic
        assert lo - 1e-6 <= metal.min() and metal.max() <= hi + 1e-6
        if o.material.category != "metallic":
            assert metal.max() == 0

"""Tangent-space normals of known shapes (tilted plane, sphere) and height from normals (Gaussian bumps, sphere,
depth discontinuity, PLY mesh)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from matcap import MaterialMaps
from matcap.export import export, read_texture_set
from matcap.normals import camera_to_tangent
from matcap.height import integrate_normals
from matcap.imageio import read_exr

Q16 = 0.5 / 65535 + 1e-7


def raw(path) -> np.ndarray:
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return arr[:, :, ::-1] if arr.ndim == 3 else arr


def grid(h: int, w: int):
    """x right, y up, in pixels, origin at the image centre."""
    r, c = np.mgrid[0:h, 0:w].astype(np.float64)
    return c - (w - 1) / 2, (h - 1) / 2 - r


def normals_from_gradients(hx, hy):
    n = np.stack([-hx, -hy, np.ones_like(hx)], axis=2)
    return n / np.linalg.norm(n, axis=2, keepdims=True)


def gaussian_bumps(h=96, w=128):
    x, y = grid(h, w)
    z, hx, hy = np.zeros((h, w)), np.zeros((h, w)), np.zeros((h, w))
    for cx, cy, amp, s in [(-30, 10, 9.0, 10.0), (25, -15, 6.0, 8.0), (10, 25, -5.0, 12.0)]:
        g = amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        z, hx, hy = z + g, hx - g * (x - cx) / s**2, hy - g * (y - cy) / s**2
    return z, normals_from_gradients(hx, hy)


def sphere(h=64, w=64, radius=26.0, inner=0.97):
    x, y = grid(h, w)
    rho2 = x * x + y * y
    mask = rho2 < (inner * radius) ** 2
    z = np.sqrt(np.clip(radius**2 - rho2, 0, None))
    n = np.where(mask[..., None], np.stack([x, y, z], axis=2) / radius, 0.0)
    return z, n, mask


def aligned_error(est, truth, mask=None):
    mask = np.ones(truth.shape, bool) if mask is None else mask
    d = (est - truth)[mask]
    return np.abs(d - d.mean()).max()


# ------------------------------------------------------------------------------------------------ tangent space
def test_tilted_plane_tangent_normals(tmp_path):
    a, phi = np.deg2rad(25.0), np.deg2rad(30.0)  # tilted 25° toward upper right
    n0 = np.array([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)])
    h, w = 16, 20
    maps = MaterialMaps(normal=np.broadcast_to(n0, (h, w, 3)), mask=np.ones((h, w), bool))
    paths = export(maps, tmp_path, name="p", normal="dx", glb=False)
    gl, dx = raw(paths["normal"]) / 65535.0, raw(paths["normal_dx"]) / 65535.0
    # camera frame: tangent space = camera space (T = +x, B = +y = image up, N = +z)
    assert np.abs(gl - (n0 + 1) / 2).max() <= Q16
    assert gl[..., 0].min() > 0.5 and gl[..., 1].min() > 0.5  # facing right and up: R > .5, G > .5 (OpenGL)
    assert dx[..., 1].max() < 0.5  # DirectX: green down
    # its height is the plane: slope -nx/nz per column to the right, +ny/nz per row downward
    hgt = read_exr(paths["height"])
    assert np.allclose(np.diff(hgt, axis=1), -n0[0] / n0[2], atol=1e-4)
    assert np.allclose(np.diff(hgt, axis=0), n0[1] / n0[2], atol=1e-4)
    # "fit" frame: the plane itself is the sample, so its tangent-space normal is flat
    flat = camera_to_tangent(maps.normal, maps.mask, "fit")
    assert np.abs(flat - [0, 0, 1]).max() < 1e-5
    back = read_texture_set(export(maps, tmp_path / "fit", name="p", frame="fit", glb=False)["json"])
    assert np.abs(back.normal - n0).max() < 1e-4  # the stored frame takes it back to camera space


def test_sphere_tangent_normals(tmp_path):
    _, n, mask = sphere()
    paths = export(MaterialMaps(normal=n, mask=mask), tmp_path, name="s", normal="dx", glb=False, height=False)
    gl, dx = raw(paths["normal"]) / 65535.0, raw(paths["normal_dx"]) / 65535.0
    assert np.abs(gl - (n + 1) / 2)[mask].max() <= Q16
    c = 32
    top, bottom, right, left = (c - 20, c), (c + 20, c), (c, c + 20), (c, c - 20)  # (row, col)
    assert gl[top][1] > 0.8 and gl[bottom][1] < 0.2  # OpenGL: image-up side is green
    assert dx[top][1] < 0.2 and dx[bottom][1] > 0.8  # DirectX: inverted
    assert gl[right][0] > 0.8 and gl[left][0] < 0.2
    assert np.abs(gl[~mask] - [0.5, 0.5, 1.0]).max() <= Q16  # off-mask: flat


def test_normals_facing_away_are_folded():
    n = np.zeros((1, 2, 3))
    n[0, 0] = (0.6, 0.0, -0.8)
    n[0, 1] = (0.0, 0.0, 0.0)
    t = camera_to_tangent(n, np.ones((1, 2), bool))
    assert t[0, 0, 2] > 0 and t[0, 0, 0] > 0.99 and np.allclose(t[0, 1], [0, 0, 1])


# ------------------------------------------------------------------------------------------------ integration
@pytest.mark.parametrize("method", ["frankot-chellappa", "poisson-masked"])
def test_gaussian_bumps_integrate_within_one_percent(method):
    z, n = gaussian_bumps()
    est = integrate_normals(n, None, method)
    assert aligned_error(est, z) <= 0.01 * np.abs(z).max()


def test_gaussian_bumps_through_the_exported_normal_png(tmp_path):
    z, n = gaussian_bumps()
    maps = MaterialMaps(normal=n, mask=np.ones(z.shape, bool))
    paths = export(maps, tmp_path, name="b", glb=False)
    assert aligned_error(read_exr(paths["height"]), z) <= 0.01 * np.abs(z).max()
    back = read_texture_set(paths["json"])  # normals through the 16-bit PNG
    assert aligned_error(integrate_normals(back.normal, back.mask), z) <= 0.01 * np.abs(z).max()


def test_masked_sphere_and_depth_discontinuity():
    z, n, mask = sphere()
    r = 26.0
    fc = aligned_error(integrate_normals(n, mask, "frankot-chellappa"), z, mask)
    pm = aligned_error(integrate_normals(n, mask, "poisson-masked"), z, mask)
    assert pm <= 0.01 * r and pm < fc
    # sphere in front of a tilted background plane, one mask: the rim is a depth discontinuity
    x, y = grid(*mask.shape)
    bg = normals_from_gradients(np.full(mask.shape, 0.2), np.zeros(mask.shape))
    both = np.where(mask[..., None], n, bg)
    est = integrate_normals(both, None, "poisson-masked")
    assert aligned_error(est, z, mask) <= 0.01 * r  # sphere shape intact
    assert aligned_error(est, 0.2 * x, ~mask) <= 0.01 * r  # background plane intact
    smeared = integrate_normals(both, None, "frankot-chellappa")
    assert aligned_error(smeared, z, mask) > 0.05 * r  # what the discontinuity does to Frankot-Chellappa


def test_height_mesh_ply(tmp_path):
    import trimesh

    z, n, mask = sphere(32, 32, 13.0)
    paths = export(MaterialMaps(normal=n, mask=mask, base_color=np.full((32, 32, 3), 0.5)), tmp_path, name="m",
                   mesh=True, glb=False, height_method="poisson-masked")
    mesh = trimesh.load(paths["mesh"], process=False)
    hgt = read_exr(paths["height"])
    assert len(mesh.vertices) == mask.sum()
    assert np.allclose(np.sort(mesh.vertices[:, 2]), np.sort(hgt[mask]), atol=1e-5)
    assert (mesh.face_normals[:, 2] > 0).all()  # faces toward the camera
    assert mesh.vertices[:, 2].argmax() == np.argmax(hgt[mask])


@pytest.mark.parametrize("depth", [4.0, 8.0])
def test_ambient_occlusion_of_a_trench_floor_matches_the_analytic_value(depth):
    """Floor of a long trench (walls 4 and 5 pixel centres away, i.e. width 9 between wall tops): the cosine-weighted
    sky fraction is 1 / sqrt(1 + (2 d / w)^2)."""
    from matcap.height import ambient_occlusion

    h = np.zeros((128, 128))
    h[:, 60:68] = -depth
    ao = ambient_occlusion(h, radius=60, directions=64, steps=60)
    expected = 1 / np.sqrt(1 + (2 * depth / 9.0) ** 2)
    assert abs(ao[64, 63] - expected) < 0.03
    assert ao[64, 10] == pytest.approx(1.0)  # open ground far from the trench


def test_ambient_occlusion_flat_tilted_masked_and_bad_input():
    from matcap.height import ambient_occlusion

    yy, xx = np.mgrid[0:64, 0:64].astype(float)
    assert ambient_occlusion(np.zeros((64, 64))).min() == 1.0
    assert ambient_occlusion(0.7 * xx - 0.3 * yy).min() > 0.98  # a tilted plane is not occluded by itself
    mask = np.zeros((64, 64), bool)
    mask[:, :32] = True
    wall = np.where(xx >= 32, 50.0, 0.0)  # a tall wall outside the mask casts no occlusion
    ao = ambient_occlusion(wall, mask)
    assert ao[mask].min() > 0.98 and (ao[~mask] == 1.0).all()
    with pytest.raises(ValueError, match="height must be"):
        ambient_occlusion(np.zeros((4, 4, 3)))
    with pytest.raises(ValueError, match="mask shape"):
        ambient_occlusion(np.zeros((4, 4)), np.ones((3, 4), bool))

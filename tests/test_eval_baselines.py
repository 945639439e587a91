"""Classical baselines on analytic Lambertian objects written in the DiLiGenT layout (16-bit PNG)."""
import numpy as np
import pytest

from matcap.evaluation import baselines, metrics, toy
from matcap.evaluation.datasets import load_diligent_object


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("diligent")
    lights = toy.cone_lights(16, 35.0, seed=3)
    intens = np.linspace(0.6, 1.0, 16)[:, None] * np.array([1.0, 0.9, 0.8])
    n, m = toy.sphere_normals(64, max_angle_deg=50.0)  # n . l > 0 everywhere: no shadows
    toy.write_diligent_object(root / "spherePNG", toy.render_lambertian(n, m, lights, intens), m, n, lights, intens)
    n2, m2 = toy.plane_normals(32)
    toy.write_diligent_object(root / "planePNG", toy.render_lambertian(n2, m2, lights, intens), m2, n2, lights,
                              intens, normal_format="txt")
    return root


@pytest.mark.parametrize("name", ["spherePNG", "planePNG"])
def test_least_squares_recovers_sphere_and_plane(written, name):
    obj = load_diligent_object(written / name)
    assert obj.bit_depth == "16bit" and len(obj.images) == 16
    res = baselines.least_squares_ps(obj.images, obj.light_dirs, obj.mask, obj.light_intensities)
    err = metrics.angular_error_map(res.normal, obj.normal_gt, obj.mask)
    assert np.nanmax(err) < 0.5
    assert np.nanmean(err) < 0.05
    # albedo comes back once the light colours are divided out
    np.testing.assert_allclose(res.albedo[obj.mask].mean(axis=0), [0.8, 0.6, 0.4], atol=2e-3)


def test_robust_variant_handles_attached_shadows_and_highlights():
    n, m = toy.sphere_normals(64, max_angle_deg=85.0)
    lights = toy.cone_lights(20, 60.0, seed=1)
    shadowed = (n.reshape(-1, 3) @ lights.T <= 0).sum(axis=1).reshape(m.shape)
    # 30% of 20 lights = 6 darkest dropped: exact wherever at most 6 lights are behind the surface
    few = m & (shadowed <= 6)
    assert few.sum() > 0.8 * m.sum()
    matte = toy.render_lambertian(n, m, lights)
    plain = metrics.angular_error_map(baselines.least_squares_ps(matte, lights, m).normal, n, m)
    robust = metrics.angular_error_map(baselines.robust_least_squares_ps(matte, lights, m).normal, n, m)
    assert np.nanmax(robust[few]) < 0.5
    assert np.nanmean(plain[few]) > 2.0  # attached shadows bias the plain fit
    assert np.nanmean(robust) < 0.5 * np.nanmean(plain)
    shiny = toy.render_lambertian(n, m, lights, specular=0.5, shininess=200.0)
    plain = metrics.angular_error_map(baselines.least_squares_ps(shiny, lights, m).normal, n, m)
    robust = metrics.angular_error_map(baselines.robust_least_squares_ps(shiny, lights, m).normal, n, m)
    assert np.nanmean(robust[few]) < 1.0
    assert np.nanmean(robust[few]) < 0.25 * np.nanmean(plain[few])


def test_robust_weights_drop_darkest_and_brightest():
    obs = np.array([[5.0, 0.0], [1.0, 1.0], [3.0, 2.0], [2.0, 3.0], [4.0, 4.0], [0.0, 5.0]])
    w = baselines.robust_keep_weights(obs, 0.2, 0.2)  # K=6: drop 1 darkest, 1 brightest
    np.testing.assert_array_equal(w[:, 0], [0, 1, 1, 1, 1, 0])
    np.testing.assert_array_equal(w[:, 1], [0, 1, 1, 1, 1, 0])
    w3 = baselines.robust_keep_weights(obs[:3], 0.5, 0.5)  # never fewer than 3 kept
    assert (w3.sum(axis=0) == 3).all()


def test_needs_three_images():
    n, m = toy.plane_normals(8)
    lights = toy.cone_lights(2, 30.0)
    with pytest.raises(ValueError, match="at least 3"):
        baselines.least_squares_ps(toy.render_lambertian(n, m, lights), lights, m)

"""Angular-error metrics against hand-computed values."""
import math

import numpy as np
import pytest

from matcap.evaluation import metrics


def _pred_gt():
    s3 = math.sqrt(3.0)
    gt = np.zeros((2, 2, 3))
    gt[..., 2] = 1.0
    pred = np.array([
        [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]],  # 0 deg, 45 deg (not unit length on purpose)
        [[0.0, 2.0, 0.0], [s3, 0.0, 1.0]],   # 90 deg, 60 deg
    ])
    return pred, gt


def test_error_map_exact_angles():
    pred, gt = _pred_gt()
    err = metrics.angular_error_map(pred, gt)
    np.testing.assert_allclose(err, [[0.0, 45.0], [90.0, 60.0]], atol=1e-12)


def test_summary_matches_hand_computed_values():
    pred, gt = _pred_gt()
    s = metrics.normal_metrics(pred, gt)
    assert s["mae"] == pytest.approx((0 + 45 + 90 + 60) / 4, abs=1e-12)
    assert s["median"] == pytest.approx((45 + 60) / 2, abs=1e-12)
    assert (s["under10"], s["under20"], s["under30"]) == (0.25, 0.25, 0.25)
    assert s["pixels"] == 4


def test_mask_zero_gt_and_zero_prediction():
    pred, gt = _pred_gt()
    mask = np.array([[True, True], [False, True]])  # drop the 90 deg pixel
    s = metrics.normal_metrics(pred, gt, mask)
    assert s["mae"] == pytest.approx(35.0, abs=1e-12)
    assert s["median"] == pytest.approx(45.0, abs=1e-12)
    assert s["under10"] == pytest.approx(1 / 3)
    assert s["pixels"] == 3
    gt2 = gt.copy()
    gt2[0, 1] = 0.0  # no ground truth there: not counted
    assert metrics.normal_metrics(pred, gt2, mask)["mae"] == pytest.approx(30.0, abs=1e-12)
    pred2 = pred.copy()
    pred2[0, 0] = 0.0  # a method that gave up on a pixel scores 90 deg there
    assert metrics.normal_metrics(pred2, gt, mask)["mae"] == pytest.approx((90 + 45 + 60) / 3, abs=1e-12)


def test_small_angles_are_accurate():
    a = np.radians(1e-4)
    pred = np.array([[[np.sin(a), 0.0, np.cos(a)]]])
    gt = np.array([[[0.0, 0.0, 1.0]]])
    assert metrics.angular_error_map(pred, gt)[0, 0] == pytest.approx(1e-4, rel=1e-6)


def test_thresholds_are_strict_and_empty_raises():
    assert metrics.summarize_errors(np.array([10.0, 20.0, 30.0, np.nan]))["under10"] == 0.0
    assert metrics.summarize_errors(np.array([9.99, 19.99, 29.99]))["under30"] == 1.0
    with pytest.raises(ValueError):
        metrics.summarize_errors(np.array([np.nan]))


def test_colour_map_ends_and_background():
    rgb = metrics.colorize_error(np.array([[0.0, 90.0, 200.0, np.nan]]))
    np.testing.assert_allclose(rgb[0, 0], [0.0, 0.0, 0.5])
    np.testing.assert_allclose(rgb[0, 1], [0.55, 0.0, 0.0])
    np.testing.assert_allclose(rgb[0, 2], rgb[0, 1])  # clipped at 90
    np.testing.assert_allclose(rgb[0, 3], 0.0)


def test_fine_energy_share_finds_a_two_pixel_grid():
    """A normal map tilted by a stripe pattern of period 2 px (the networks' tile grid at 256^2) has all its fine
    detail at periods <= 2.2 px; smooth relief of period 16 px has none there."""
    from matcap.evaluation.metrics import fine_energy_share

    size = 64
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    mask = (yy - 31.5) ** 2 + (xx - 31.5) ** 2 < 30 ** 2

    def tilted(gx):
        n = np.dstack([gx, np.zeros_like(gx), np.ones_like(gx)])
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    grid = tilted(0.1 * (-1.0) ** xx)
    smooth = tilted(0.3 * np.sin(2 * np.pi * xx / 16))
    assert fine_energy_share(grid, mask, 2.2) > 0.99
    assert fine_energy_share(smooth, mask, 2.2) < 0.01  # (the crop holds no whole number of its periods: leakage)
    both = tilted(0.1 * (-1.0) ** xx + 0.1 * np.sin(2 * np.pi * xx / 16))
    assert 0.2 < fine_energy_share(both, mask, 2.2) < 0.99
    with pytest.raises(ValueError, match="no square"):
        fine_energy_share(grid, np.eye(size, dtype=bool), 2.2)

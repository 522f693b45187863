"""Metrics against hand-computed values on tiny arrays, and SSIM against a slow reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigspace.sdk.render import Maps, empty_maps
from rigspace.train import metrics

EXACT = 1e-12  # float64 arithmetic on a handful of values
SSIM_REFERENCE_TOLERANCE = 1e-10  # the same sums, by cv2's separable blur vs a direct loop


def test_psnr_hand_computed():
    target = np.array([[0.0, 0.0], [0.0, 0.5]], np.float32)
    pred = np.zeros_like(target)
    # MSE = 0.5^2 / 4 = 1/16 -> 10 log10(16).
    assert metrics.psnr(pred, target) == pytest.approx(10 * math.log10(16), abs=EXACT)
    # Only the masked pixel: MSE = 1/4.
    mask = np.array([[0, 0], [0, 1]], np.float32)
    assert metrics.psnr(pred, target, mask) == pytest.approx(10 * math.log10(4), abs=EXACT)
    # peak 2 multiplies peak^2 / MSE by 4.
    assert metrics.psnr(pred, target, peak=2.0) == pytest.approx(10 * math.log10(64), abs=EXACT)
    assert metrics.psnr(target, target) == math.inf
    assert math.isnan(metrics.psnr(pred, target, np.zeros_like(mask)))


def test_psnr_mask_selects_whole_pixels_of_colour_images():
    target = np.zeros((1, 2, 3), np.float32)
    pred = target.copy()
    pred[0, 1] = (0.1, 0.2, 0.3)  # the masked pixel: MSE = (0.01 + 0.04 + 0.09) / 3
    pred[0, 0] = 1.0  # outside the mask: ignored
    expected = 10 * math.log10(3 / 0.14)
    assert metrics.psnr(pred, target, np.array([[0.0, 1.0]])) == pytest.approx(expected, abs=1e-6)


def test_ssim_of_uniform_images_is_the_luminance_term():
    # No variance, no covariance: SSIM = (2ab + C1) / (a^2 + b^2 + C1) * C2 / C2.
    c1 = (0.01 * 1) ** 2
    expected = (2 * 0.5 * 0.6 + c1) / (0.5**2 + 0.6**2 + c1)  # = 0.6001 / 0.6101
    for size in (4, 16):  # smaller than the window (all pixels) and larger (valid region)
        a = np.full((size, size), 0.5, np.float32)
        assert metrics.ssim(a, a + np.float32(0.1)) == pytest.approx(expected, abs=1e-6)
    assert expected == pytest.approx(0.9836092, abs=1e-7)


def test_ssim_identity_symmetry_and_channel_mean():
    rng = np.random.default_rng(0)
    x = rng.random((16, 16, 3)).astype(np.float32)
    y = np.clip(x + 0.1 * rng.standard_normal(x.shape), 0, 1).astype(np.float32)
    assert metrics.ssim(x, x) == 1.0
    assert metrics.ssim(x, y) == pytest.approx(metrics.ssim(y, x), abs=EXACT)
    assert 0.0 < metrics.ssim(x, y) < 1.0
    per_channel = [metrics.ssim(x[..., c], y[..., c]) for c in range(3)]
    assert metrics.ssim(x, y) == pytest.approx(np.mean(per_channel), abs=EXACT)


def slow_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """Wang et al. 2004 by the definition: a weighted window at every valid position."""
    r = metrics.SSIM_WINDOW // 2
    k = np.exp(-((np.arange(-r, r + 1) / metrics.SSIM_SIGMA) ** 2) / 2)
    w = np.outer(k, k) / np.outer(k, k).sum()
    c1, c2 = metrics.SSIM_K1**2, metrics.SSIM_K2**2
    values = []
    for i in range(r, x.shape[0] - r):
        for j in range(r, x.shape[1] - r):
            a = x[i - r : i + r + 1, j - r : j + r + 1].astype(np.float64)
            b = y[i - r : i + r + 1, j - r : j + r + 1].astype(np.float64)
            ma, mb = (w * a).sum(), (w * b).sum()
            va, vb = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum()
            cov = (w * (a - ma) * (b - mb)).sum()
            values.append(
                (2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
            )
    return float(np.mean(values))


def test_ssim_matches_the_definition():
    rng = np.random.default_rng(1)
    x = rng.random((14, 15)).astype(np.float32)
    y = (0.7 * x + 0.2 * rng.random(x.shape)).astype(np.float32)
    assert metrics.ssim(x, y) == pytest.approx(slow_ssim(x, y), abs=SSIM_REFERENCE_TOLERANCE)


def test_mask_iou_hand_computed():
    pred = np.array([[1.0, 0.5], [0.0, 0.2]])  # 0.5 counts as covered, 0.2 does not
    target = np.array([[1.0, 0.0], [1.0, 0.0]])
    assert metrics.mask_iou(pred, target) == pytest.approx(1 / 3)  # {00} / {00, 01, 10}
    assert metrics.mask_iou(pred, target, threshold=0.1) == pytest.approx(1 / 4)
    assert metrics.mask_iou(np.zeros((2, 2)), np.zeros((2, 2))) == 1.0


def test_depth_mae_hand_computed():
    inf = np.inf
    pred = np.array([[1.0, 2.0], [inf, 5.0]], np.float32)
    target = np.array([[1.5, 2.0], [3.0, inf]], np.float32)
    mask = np.array([[1.0, 1.0], [1.0, 0.0]], np.float32)
    # (0,0): 0.5, (0,1): 0; (1,0) the prediction is empty, (1,1) outside the mask.
    mae, pct = metrics.depth_mae(pred, target, mask, character_height=2.0)
    assert mae == pytest.approx(0.25, abs=EXACT)
    assert pct == pytest.approx(12.5, abs=EXACT)
    assert all(math.isnan(v) for v in metrics.depth_mae(pred, target, 0 * mask, 2.0))


def test_normal_angle_error_hand_computed():
    target = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (1, 6, 1))
    pred = np.array(
        [[[0, 0, 2], [1, 0, 1], [0, 1, 0], [0, 0, -1], [0, 0, 0], [1, 0, 0]]], np.float32
    )  # 0, 45, 90, 180 degrees; an empty normal; a pixel outside the mask
    mask = np.array([[1, 1, 1, 1, 1, 0]], np.float32)
    mean, median = metrics.normal_angle_error(pred, target, mask)
    assert mean == pytest.approx((0 + 45 + 90 + 180) / 4, abs=1e-9)
    assert median == pytest.approx((45 + 90) / 2, abs=1e-9)
    # Identical normals: exactly 0 (atan2 of a zero cross product), not arccos's float noise.
    same = metrics.normal_angle_error(pred[:, :4], pred[:, :4], mask[:, :4])
    assert same == (0.0, 0.0)


def small_maps() -> Maps:
    rng = np.random.default_rng(2)
    maps = empty_maps(12, 12)
    maps.mask[3:9, 4:8] = 1.0
    inside = maps.mask > 0
    maps.albedo[inside] = rng.random((int(inside.sum()), 3))
    maps.depth[inside] = 3.0 + rng.random(int(inside.sum()))
    n = rng.standard_normal((int(inside.sum()), 3))
    maps.normal[inside] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return maps


def test_map_metrics_of_a_perfect_prediction():
    maps = small_maps()
    result = metrics.map_metrics(maps, maps, character_height=1.8)
    assert list(result) == list(metrics.METRICS)
    assert result == {
        "albedo_psnr": math.inf,
        "albedo_ssim": 1.0,
        "mask_iou": 1.0,
        "depth_mae": 0.0,
        "depth_mae_pct": 0.0,
        "normal_mean_deg": 0.0,
        "normal_median_deg": 0.0,
    }


def test_map_metrics_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="albedo"):
        metrics.map_metrics(empty_maps(8, 8), empty_maps(4, 4), 1.0)

"""FLIP beside PSNR (rigspace.sdk.flip): what it reads, its region, and the squeezed ceiling."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.sdk.flip import flip_map, mean_flip, region_of, squeezed


def _stripes(size: int = 128, period: int = 32, shift: int = 0) -> np.ndarray:
    """Black and white vertical stripes, linear RGB, moved `shift` pixels to the left."""
    x = ((np.arange(size) + shift) // (period // 2)) % 2
    return np.repeat(np.tile(x.astype(np.float32), (size, 1))[..., None], 3, axis=-1)


def test_identical_images_score_zero_and_a_blur_scores_worse_than_a_shift():
    """The point of FLIP here: PSNR prefers a blur of sharp stripes to the same stripes a
    pixel out of place; a viewer, and FLIP, do not (measured: MSE 0.038 against 0.063, FLIP
    0.44 against 0.20)."""
    import cv2

    truth = _stripes()
    assert mean_flip(truth, truth) == 0.0
    blurred = cv2.GaussianBlur(truth, (0, 0), 3.0)
    shifted = _stripes(shift=1)
    mse = [float(np.mean((x - truth) ** 2)) for x in (blurred, shifted)]
    assert mse[0] < mse[1]  # PSNR ranks the blur first
    assert mean_flip(blurred, truth) > 1.5 * mean_flip(shifted, truth)


def test_the_mean_reads_only_the_mask_and_is_nan_without_pixels():
    truth = _stripes()
    test = truth.copy()
    test[:, :64] = 0.5  # the left half wrong
    error = flip_map(test, truth)
    assert error.shape == truth.shape[:2] and 0 <= error.min() and error.max() <= 1
    right = np.zeros(truth.shape[:2], bool)
    right[:, 80:] = True
    assert mean_flip(test, truth, right) < 0.2 * mean_flip(test, truth, ~right)
    assert np.isnan(mean_flip(test, truth, np.zeros_like(right)))
    with pytest.raises(ValueError, match="two \\(H, W, 3\\) images of one shape"):
        flip_map(test[:10], truth)


def test_squeezing_keeps_a_flat_image_and_loses_stripes_finer_than_the_factor():
    flat = np.full((64, 64, 3), 0.3, np.float32)
    np.testing.assert_allclose(squeezed(flat, 4.0), flat, atol=1e-6)
    stripes = _stripes(64, 8)
    assert mean_flip(squeezed(stripes, 8.0), stripes) > 0.3  # gone at an eighth of the size
    assert mean_flip(squeezed(stripes, 1.0), stripes) == 0.0  # no squeeze: itself


def test_the_region_is_the_box_of_either_mask_with_a_margin():
    a = np.zeros((20, 30), np.float32)
    b = np.zeros((20, 30), np.float32)
    a[5:8, 10:12] = 1.0
    b[9, 20] = 0.6
    rows, cols = region_of(a, b, margin=1)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (4, 11, 9, 22)
    assert region_of(np.zeros((4, 4))) is None

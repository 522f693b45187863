"""FLIP, a perceptual difference of two images (Andersson et al. 2020), beside PSNR and SSIM.

PSNR rewards a blur over a sharp detail a texel out of place; FLIP (NVIDIA's flip-evaluator
package) models what a viewer sees at a viewing distance: colour differences filtered by the
eye's contrast sensitivity, and edges and points that appear, vanish or move. 0 is identical,
1 the largest difference. Images here are linear RGB; FLIP's LDR mode reads sRGB, so they are
encoded first (rigspace.sdk.color). The viewing condition is FLIP's default, PPD pixels per
degree of visual angle (a 0.7 m distance from a 24-inch 4K display).

`squeezed` makes the ceiling a table measures against: the truth box-averaged down to the
network's resolution and bilinearly stretched back, the best any image of that size can do.
"""

from __future__ import annotations

import numpy as np

from rigspace.sdk.color import linear_to_srgb

PPD = 67.0
"""Pixels per degree of visual angle: FLIP's own default viewing condition."""


def flip_map(test: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(H, W) FLIP error in [0, 1] of two (H, W, 3) linear RGB images."""
    import flip_evaluator

    if test.shape != reference.shape or test.ndim != 3 or test.shape[-1] != 3:
        raise ValueError(
            f"FLIP compares two (H, W, 3) images of one shape, got {test.shape} and "
            f"{reference.shape}"
        )
    if min(test.shape[:2]) < 2:
        return np.zeros(test.shape[:2], np.float32)
    encoded = [
        np.ascontiguousarray(linear_to_srgb(np.nan_to_num(image)), np.float32)
        for image in (reference, test)
    ]
    error, _, _ = flip_evaluator.evaluate(
        *encoded, "LDR", applyMagma=False, computeMeanError=False, parameters={"ppd": PPD}
    )
    return np.asarray(error, np.float32).reshape(test.shape[:2])


def mean_flip(test: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean FLIP of two linear RGB images, over the pixels where `mask` (H, W) is true (all
    when None); nan when the mask is empty."""
    error = flip_map(test, reference)
    if mask is not None:
        error = error[np.asarray(mask, bool)]
    return float(error.mean()) if error.size else float("nan")


def squeezed(image: np.ndarray, factor: float) -> np.ndarray:
    """`image` (H, W, C) area-averaged down by `factor` (> 1) and stretched back bilinearly:
    what survives of it at 1/factor of its size (the ceiling of an image predictor there)."""
    import cv2

    h, w = image.shape[:2]
    if factor <= 1.0:
        return image.copy()
    small = cv2.resize(
        image, (max(1, round(w / factor)), max(1, round(h / factor))), interpolation=cv2.INTER_AREA
    )
    back = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    return back.reshape(image.shape).astype(image.dtype)


def region_of(*masks: np.ndarray, margin: int = 2) -> tuple[slice, slice] | None:
    """The bounding box (rows, columns) of the pixels any mask covers (coverage >= 0.5), grown
    by `margin`; None when none does. FLIP's mean over it is the character's, not the frame's."""
    h, w = np.shape(masks[0])[:2]
    covered = np.zeros((h, w), bool)
    for mask in masks:
        covered |= np.asarray(mask) >= 0.5
    where = np.argwhere(covered)
    if where.size == 0:
        return None
    rows, cols = where[:, 0], where[:, 1]
    return (
        slice(max(0, rows.min() - margin), min(h, rows.max() + 1 + margin)),
        slice(max(0, cols.min() - margin), min(w, cols.max() + 1 + margin)),
    )

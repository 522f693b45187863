"""runtime/reference.py: a character region's PSNR, FLIP and mask IoU against the reference,
on small synthetic frames (`rigspace render --reference` runs it on the previs shot)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rigspace.runtime.reference import NOTHING_TO_COMPARE, compare_regions

PSNR_FLOOR_DB = 120.0
"""PSNR of identical images: the mean squared error is floored at 1e-12 (peak 1)."""


def frame(beauty: np.ndarray, characters: list[dict]) -> SimpleNamespace:
    """What compare_regions reads of an Engine frame: beauty, albedo, the characters' report."""
    return SimpleNamespace(
        beauty=beauty,
        maps=SimpleNamespace(albedo=beauty.copy()),
        report=SimpleNamespace(characters=characters),
    )


def test_regions_compare_beauty_albedo_flip_and_coverage():
    rng = np.random.default_rng(0)
    truth = rng.random((32, 48, 3), dtype=np.float32)
    entry = {"path": "/World/Hero", "region": [8, 4, 16, 20], "size_px": 20.0, "level": 32}
    same = frame(truth.copy(), [entry])
    mask = np.zeros((32, 48), np.float32)
    mask[4:24, 8:24] = 1.0
    half = mask.copy()
    half[4:24, 16:24] = 0.0
    (row,) = compare_regions(same, frame(truth, [entry]), {"/World/Hero": (half, mask)})
    assert row["psnr"] == pytest.approx(PSNR_FLOOR_DB) and row["albedo_psnr"] == row["psnr"]
    assert row["flip"] == 0.0 and row["flip_ceiling"] == 0.0  # level 32 is above 20 px
    assert row["mask_iou"] == pytest.approx(0.5)

    darker = frame(truth * 0.5, [entry])
    (row,) = compare_regions(darker, frame(truth, [entry]))
    assert 0.0 < row["psnr"] < PSNR_FLOOR_DB and row["flip"] > 0.0 and "mask_iou" not in row


def test_a_region_under_a_pixel_or_none_has_nothing_to_compare():
    image = np.zeros((8, 8, 3), np.float32)
    tiny = {"path": "/World/Far", "region": [3, 3, 1, 1], "size_px": 0.4, "level": 8}
    skipped = {"path": "/World/Off", "reason": "outside the view"}
    far, off = compare_regions(frame(image, [tiny, skipped]), frame(image, []))
    assert far["psnr"] is None and far["reason"].startswith(NOTHING_TO_COMPARE)
    assert off == {"path": "/World/Off", "psnr": None, "reason": "outside the view"}

"""The runtime keeps the model's accuracy: the issue's check of the neural frame against the mesh."""

from __future__ import annotations

import pytest

from rigspace.bench.accuracy import FRAMINGS, measure


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    return tmp_path_factory.mktemp("accuracy")


@pytest.fixture(scope="module")
def result(images):
    return measure(samples=4, out_dir=images)


def test_at_the_ring_camera_the_runtime_loses_nothing(result):
    centred = result["framings"]["centred"]
    # s = 1, R = I: the placement, warp and composite must hand the network's maps through.
    assert abs(centred["delta"]["albedo_psnr"]) < 0.05
    assert abs(centred["delta"]["mask_iou"]) < 0.005
    assert abs(centred["delta"]["depth_mae_pct"]) < 0.05


def test_off_centre_the_runtime_stays_within_1_db_of_the_model(result):
    off = result["framings"]["off-centre"]
    assert result["framings"]["centred"]["model"]["albedo_psnr"] > 24  # a trained model
    assert off["delta"]["albedo_psnr"] <= 1.0
    assert off["runtime"]["mask_iou"] > 0.75


def test_every_framing_is_measured_and_drawn(result, images):
    assert list(result["framings"]) == list(FRAMINGS)
    assert sorted(p.name for p in images.iterdir()) == sorted(f"accuracy_{n}.png" for n in FRAMINGS)
    for row in result["framings"].values():
        assert len(row["per_sample_albedo_psnr"]) == 4
        # A sample whose billboard fell outside the frame would compare empty with empty.
        assert max(row["per_sample_albedo_psnr"]) < 45

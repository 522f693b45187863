"""The point-cached arm's network against its LBS re-rig (apps/rerig_report.py, issue 36): the
arm's bulge is what the re-rig cannot give, so the truth departs from it around the elbow;
the twin of a sample is found by time, view and camera, and a re-rig captured from another
ring is refused by name with nothing written."""

from __future__ import annotations

import json

import cv2
import pytest

from rigspace.apps import rerig_report
from rigspace.sdk.cli import main
from tests.point_caches import trained_arm, write_point_cache_character

pytest.importorskip("torch", reason="training needs the train extra (torch)")


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    return trained_arm(tmp_path_factory)


def _capture_rerig(tmp_path, views: int = 4):
    scene = write_point_cache_character(tmp_path / "rerig_scene", bulge=False)
    out = tmp_path / "rerig_ds"
    capture = ["capture", str(scene), "--out", str(out), "--views", str(views),
               "--resolution", "16", "--frames-per-item", "4", "--workers", "1"]  # fmt: skip
    assert main(capture) == 0
    return out


def test_the_bulge_departs_from_the_rerig_and_both_are_measured_there(arm, tmp_path):
    _, bundle = arm
    dataset = bundle.parent / "ds"
    rerig = _capture_rerig(tmp_path)
    out = tmp_path / "report"
    argv = [str(dataset), "--model", str(bundle), "--rerig", str(rerig), "--out", str(out),
            "--split", "train", "--sheet", "3"]  # fmt: skip
    assert rerig_report.main(argv) == 0
    report = json.loads((out / "rerig_report.json").read_text())
    assert report["samples"] > 0 and report["departing_pixels"] > 0
    lbs, network = report["predictors"]["LBS re-rig"], report["predictors"]["network"]
    # The re-rig covers too little where the bulge swells: it cannot reach IoU 1 there.
    assert 0.0 <= lbs["departing_mask_iou"] < 1.0
    assert 0.0 <= network["departing_mask_iou"] <= 1.0
    assert lbs["whole_mask_iou"] > 0.5  # elsewhere the re-rig is the arm itself
    assert report["network_ms_per_sample"] > 0.0
    sheet = cv2.imread(str(out / "rerig_sheet.png"))
    assert sheet.shape[1] == 6 * rerig_report.TILE
    assert sheet.shape[0] == 22 + 3 * (rerig_report.TILE + 22)
    assert "| LBS re-rig |" in (out / "rerig_report.md").read_text()


def test_a_dataset_against_itself_departs_nowhere(arm, tmp_path):
    _, bundle = arm
    dataset = bundle.parent / "ds"
    argv = [str(dataset), "--model", str(bundle), "--rerig", str(dataset),
            "--out", str(tmp_path / "same"), "--split", "train", "--limit", "8"]  # fmt: skip
    assert rerig_report.main(argv) == 0
    report = json.loads((tmp_path / "same" / "rerig_report.json").read_text())
    assert report["samples"] == 8 and report["departing_pixels"] == 0


def test_a_rerig_from_another_ring_is_named_and_nothing_is_written(arm, tmp_path, capsys):
    _, bundle = arm
    rerig = _capture_rerig(tmp_path, views=3)  # other azimuths: no twin for most views
    out = tmp_path / "never"
    argv = [str(bundle.parent / "ds"), "--model", str(bundle), "--rerig", str(rerig),
            "--out", str(out), "--split", "train"]  # fmt: skip
    assert rerig_report.main(argv) == 2
    err = capsys.readouterr().err
    assert "rerig_ds" in err and "same capture ring" in err
    assert not out.exists()

"""The previs scripts in samples/scripts run as a user runs them, and do what they say."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from rigspace.sdk import validation
from rigspace.sdk.stage import open_stage
from tests.conftest import REPO, free_port

SCRIPTS = REPO / "samples" / "scripts"


def run(script: str, *args: str) -> list[str]:
    done = subprocess.run(
        [sys.executable, str(SCRIPTS / script), *args],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()


@pytest.mark.slow
def test_live_hook_renders_what_the_stream_sends(tmp_path):
    port = free_port()
    lines = run(
        "live_hook.py", "--out", str(tmp_path), "--url", f"vmc://127.0.0.1:{port}",
        "--send", "samples/motion/cmu_131_01.bvh", "--frames", "4", "--size", "96x54",
    )  # fmt: skip
    assert len(lines) == 4 and all("connected" in line for line in lines), lines
    samples = [int(line.split(", ")[1].split()[0]) for line in lines]
    assert samples == sorted(samples) and samples[0] > 0  # the stream kept arriving
    frames = sorted(tmp_path.glob("hook_*.png"))
    assert len(frames) == 4
    first, last = (cv2.imread(str(p)).astype(int) for p in (frames[0], frames[-1]))
    assert np.abs(first - last).max() > 30  # the character moved with the stream


def test_author_shot_writes_a_valid_stage_and_renders_its_character(tmp_path):
    lines = run("author_shot.py", "--out", str(tmp_path), "--frames", "0:30:30",
                "--size", "96x54")  # fmt: skip
    assert len(lines) == 2 and all(": evaluated" in line for line in lines), lines
    stage = open_stage(tmp_path / "shot.usda")
    assert not [i for i in validation.validate(stage) if i.severity == "error"]
    assert stage.GetPrimAtPath("/World/Hero").GetTypeName() == "RigspaceNeuralCharacter"
    frame = cv2.imread(str(tmp_path / "shot_00030.png"))
    assert frame.shape == (54, 96, 3)


def test_cesium_jaw_opens_cesium_man_s_jaw_apart_from_the_walk(tmp_path):
    """samples/scripts/cesium_jaw.py: a jawOpen shape on the front of CesiumMan's lower head,
    full at the chin (6 cm), animated with its own period, and a face region that draws it."""
    from rigspace.capture.regions import find_region, region_settings
    from rigspace.capture.settings import resolve_settings

    (line,) = run("cesium_jaw.py", "--out", str(tmp_path))
    assert "jawOpen on" in line
    scene = tmp_path / "cesium_jaw.usda"
    stage = open_stage(scene)
    assert not [i for i in validation.validate(stage) if i.severity == "error"]
    body, rig = resolve_settings(scene, "/World/CesiumMan", warn=lambda _: None)
    assert rig.blend_shapes == ("jawOpen",)
    weights = [float(rig.blend_weights(t)[0]) for t in range(1, 49)]
    assert weights[0] == pytest.approx(0.0, abs=1e-6) and max(weights) > 0.99
    assert weights[0] != pytest.approx(weights[-1], abs=0.05)  # not the walk's 48-frame cycle
    shut, opened = (rig.posed_meshes(10.0, weights=np.array([w], np.float32)) for w in (0.0, 1.0))
    drop = np.linalg.norm(opened[0].points - shut[0].points, axis=1)
    moved = drop > 1e-6
    assert 300 < moved.sum() < 700  # the front of the lower head, not the whole head
    assert drop.max() == pytest.approx(0.06 * np.hypot(1.0, 0.2), rel=0.02)
    # Where it moves, it moves down (the world's -Y) at the chin, whatever the walk's pose.
    height = shut[0].points[moved, 1]
    assert (opened[0].points[moved, 1] <= height + 1e-6).all()
    region = region_settings(body, rig, find_region(rig.character, "face"), lambda _: None)
    assert region.input_shapes == ("jawOpen",) and region.resolution == 64

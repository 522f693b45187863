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

"""The previs shot: its camera keeps the character framed, the crate passes in front, the ball behind."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from rigspace.sdk.camera import Camera
from rigspace.sdk.posing import CharacterRig
from tests.conftest import REPO

SCENES = REPO / "samples" / "scenes"
WIDTH, HEIGHT = 640, 360  # the README's render
STEP = 10  # the README's --step
MARGIN = 0.05 * HEIGHT
"""Pixels between every joint and the frame's edge: the mesh reaches past the joints (the
head's top, the hands), so a joint on the edge would still be a cut character."""


def _script():
    spec = importlib.util.spec_from_file_location(
        "build_previs_shot", SCENES / "build_previs_shot.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def shot():
    """Per rendered frame: the camera, the character's joints, the crate's and ball's corners."""
    stage = Usd.Stage.Open(str(SCENES / "previs.usda"))
    rig = CharacterRig(stage.GetPrimAtPath("/World/Hero"))
    camera = stage.GetPrimAtPath("/World/ShotCam")
    frames = np.arange(stage.GetStartTimeCode(), stage.GetEndTimeCode() + 1, STEP)
    rows = []
    for t in frames:
        boxes = UsdGeom.BBoxCache(Usd.TimeCode(t), [UsdGeom.Tokens.default_])
        corners = {}
        for name in ("PassingCrate", "RollingBall"):
            box = boxes.ComputeWorldBound(stage.GetPrimAtPath(f"/World/Set/{name}"))
            lo, hi = (
                np.array(box.ComputeAlignedRange().GetMin()),
                np.array(box.ComputeAlignedRange().GetMax()),
            )
            corners[name] = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                      for z in (lo[2], hi[2])])  # fmt: skip
        rows.append(
            {
                "time": float(t),
                "camera": Camera.from_usd(camera, float(t), WIDTH, HEIGHT),
                "joints": rig.world_transforms(float(t))[:, :3, 3],
                **corners,
            }
        )
    return rows


def test_the_shot_is_what_its_script_builds():
    """The samples in previs.usda are the script's output (it is deterministic and current)."""
    script = _script()
    text = script.SCENE.read_text()
    assert script.build(text, Usd.Stage.Open(str(script.SCENE))) == text


def test_every_rendered_frame_holds_the_whole_character(shot):
    for row in shot:
        xy, depth = row["camera"].project(row["joints"])
        assert np.all(depth > 0), row["time"]
        assert xy[:, 0].min() > MARGIN and xy[:, 0].max() < WIDTH - MARGIN, row["time"]
        assert xy[:, 1].min() > MARGIN and xy[:, 1].max() < HEIGHT - MARGIN, row["time"]


def test_the_camera_looks_at_the_pelvis(shot):
    """The look-at rig aims at the smoothed pelvis: the pelvis stays near the frame's centre."""
    for row in shot:
        xy, _ = row["camera"].project(row["joints"][:1])  # joint 0 is the pelvis
        offset = np.abs(xy[0] - (WIDTH / 2, HEIGHT / 2))
        assert offset[0] < 0.1 * WIDTH and offset[1] < 0.1 * HEIGHT, (row["time"], offset)


def _overlaps(row, prop: str) -> tuple[bool, float, float]:
    """Whether the prop's projected box meets the character's inside the frame, and the
    prop's depth range minus the character's (nearest prop - farthest joint, and farthest
    prop - nearest joint)."""
    camera = row["camera"]
    joints, joint_depth = camera.project(row["joints"])
    corners, prop_depth = camera.project(row[prop])
    frame = np.array([[0, 0], [WIDTH, HEIGHT]])
    lo = np.maximum.reduce([joints.min(0), np.nanmin(corners, 0), frame[0]])
    hi = np.minimum.reduce([joints.max(0), np.nanmax(corners, 0), frame[1]])
    meets = bool(np.all(hi > lo)) and np.all(prop_depth > 0)
    return meets, prop_depth.min() - joint_depth.max(), prop_depth.max() - joint_depth.min()


def test_the_crate_passes_in_front_and_the_ball_behind(shot):
    script = _script()
    for prop, crossings, in_front in (
        ("PassingCrate", script.CRATE_CROSSINGS, True),
        ("RollingBall", script.BALL_CROSSINGS, False),
    ):
        met = []
        for row in shot:
            meets, nearest, farthest = _overlaps(row, prop)
            if meets:
                met.append(row["time"])
                # Over the character on screen: wholly nearer (the crate) or farther (the ball).
                assert (farthest < 0) if in_front else (nearest > 0), (prop, row["time"])
        for first, last, *_ in crossings:
            seen = [t for t in met if first <= t <= last]
            assert len(seen) >= 3, (prop, first, last, met)  # visible over several frames
            assert (first + last) / 2 in seen, (prop, first, last, met)  # centred on the hero


def test_the_props_never_run_through_the_character(shot):
    for row in shot:
        for prop in ("PassingCrate", "RollingBall"):
            lo, hi = row[prop].min(0), row[prop].max(0)
            inside = np.all((row["joints"] > lo) & (row["joints"] < hi), axis=1)
            assert not inside.any(), (prop, row["time"])

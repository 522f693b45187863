"""The training views of a network's look-at joint, and how far (and which way) a frame's
view is from them: real ring cameras (Camera.look_at) and the runtime's rig parameters."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.capture.ring import direction
from rigspace.sdk.camera import Camera
from rigspace.sdk.rotations import rig_inputs, rig_parameters
from rigspace.sdk.view_coverage import (
    NOVEL_VIEW_DEG,
    WAYS,
    ViewCoverageError,
    advice,
    build_views,
    read_views,
    views_bytes,
)

UP = np.array([0.0, 1.0, 0.0])


def yaw(degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    out = np.eye(4)
    out[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    return out


def roll_about_z(degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    out = np.eye(4)
    out[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    return out


def row(azimuth: float, elevation: float, joint_world: np.ndarray | None = None) -> np.ndarray:
    """The rig row of a two-joint character (its second joint the look-at one, turned by
    `joint_world`) seen by a ring camera at this azimuth and elevation."""
    camera = Camera.look_at(
        200.0 * direction(azimuth, elevation, "Y"), np.zeros(3), UP,
        width=64, height=64, focal_length=35.0, horizontal_aperture=20.955,
    )  # fmt: skip
    world = np.stack([np.eye(4), np.eye(4) if joint_world is None else joint_world])
    return rig_inputs(rig_parameters(world, camera.camera_to_world)[None])[0]


@pytest.fixture(scope="module")
def ring():
    """A ring of 12 views at elevations 0 and 20 over poses that turn the joint about the
    up axis (every 5 deg): what a capture of a character turning on the spot records."""
    train = np.array(
        [row(a, e, yaw(t)) for a in range(0, 360, 30) for e in (0, 20) for t in range(0, 30, 5)]
    )
    held = np.array([row(a + 15, e, yaw(7.0)) for a in range(0, 360, 90) for e in (0, 20)])
    coverage, every = build_views(train, held, 1, (0.0, 20.0))
    return coverage, every


def test_a_view_from_below_the_ring_is_outside_and_says_so(ring):
    coverage, every = ring
    assert every == 12 * 2 * 6 and len(coverage.rotations) == every
    assert coverage.held_out == {"median": 0.0, "p95": 0.0}  # between the ring's azimuths
    # Between two azimuths and between the two elevations: inside what it learned.
    assert coverage.outside(row(45.0, 0.0, yaw(7.0))[None]) == (0.0, "")
    assert coverage.outside(row(45.0, 10.0, yaw(12.0))[None])[0] < 1.0
    below, way = coverage.outside(row(45.0, -15.0, yaw(12.0))[None])
    assert below == pytest.approx(15.0, abs=1.0) and way == WAYS[0]
    above, way = coverage.outside(row(45.0, 40.0, yaw(12.0))[None])
    assert above == pytest.approx(20.0, abs=1.5) and way == WAYS[1]
    rolled, way = coverage.outside(row(45.0, 10.0, yaw(12.0) @ roll_about_z(30.0))[None])
    assert rolled > NOVEL_VIEW_DEG and way == WAYS[3]


def test_the_advice_names_the_elevation_that_covers_the_frames():
    text = advice(WAYS[0], 14.2, (0.0, 20.0), "rigspace:region:face:elevations")
    assert "rigspace:region:face:elevations = [-15, 0, 20]" in text
    assert "[0, 20, 40]" in advice(WAYS[1], 17.0, (0.0, 20.0), "rigspace:captureRing:elevations")
    assert "viewsPerRing" in advice(WAYS[2], 12.0, (0.0,), "x")


def test_the_views_file_round_trips_and_a_bad_one_is_named(ring, tmp_path):
    coverage, every = ring
    (tmp_path / "views.npy").write_bytes(views_bytes(coverage))
    section = coverage.to_json(len(coverage.rotations), every)
    back = read_views(tmp_path, section, 2)
    probe = row(100.0, -12.0, yaw(3.0))[None]
    assert back.outside(probe)[0] == pytest.approx(coverage.outside(probe)[0], abs=0.01)
    assert back.elevations == (0.0, 20.0) and back.held_out == coverage.held_out
    with pytest.raises(ViewCoverageError, match="one of its 1 joints"):
        read_views(tmp_path, section, 1)  # the joint is not the bundle's
    (tmp_path / "views.npy").write_bytes(b"not a numpy file")
    with pytest.raises(ViewCoverageError, match=r"views\.npy cannot be read") as error:
        read_views(tmp_path, section, 2)
    assert "rigspace.apps.views BUNDLE DATASET" in error.value.fix
    for bad in (np.full((3, 4), np.nan, np.float32), np.array([["w", "x", "y", "z"]])):
        np.save(tmp_path / "views.npy", bad)
        with pytest.raises(ViewCoverageError, match="finite quaternions"):
            read_views(tmp_path, section, 2)

"""Billboard placement: size, off-centre rotation, homography and depth against direct geometry."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.runtime.billboard import TrainingView, place, rotation_between
from rigspace.sdk.camera import Camera

VIEW = TrainingView(distance=450.0, focal_length=35.0, horizontal_aperture=20.955)
PIXEL_TOLERANCE = 1e-6


def camera(width=128, height=128, focal=35.0) -> Camera:
    return Camera(
        np.eye(4), width, height, focal_length=focal, horizontal_aperture=20.955, near=1.0
    )


def test_a_training_camera_sees_exactly_the_training_image():
    bb = place([0, 0, -450.0], camera(), VIEW)
    assert bb.visible and np.allclose(bb.rotation, np.eye(3))
    assert np.allclose(bb.corners, [[0, 0], [128, 0], [128, 128], [0, 128]], atol=PIXEL_TOLERANCE)
    assert bb.size_px == pytest.approx(128)


def test_size_follows_distance_and_focal_length():
    near = place([0, 0, -225.0], camera(), VIEW)
    assert near.size_px == pytest.approx(256)
    zoomed = place([0, 0, -450.0], camera(focal=70.0), VIEW)
    assert zoomed.size_px == pytest.approx(256)
    scaled = place([0, 0, -450.0], camera(), VIEW, scale=0.5)
    assert scaled.size_px == pytest.approx(64)


@pytest.mark.parametrize("joint", [[100.0, 0, -450.0], [0, -80.0, -300.0], [150.0, 120.0, -200.0]])
def test_off_centre_rotation_points_the_virtual_camera_at_the_joint(joint):
    bb = place(joint, camera(), VIEW)
    r = bb.rotation
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(r), 1)
    assert np.allclose(r @ [0, 0, -1], np.asarray(joint) / np.linalg.norm(joint))
    # The joint projects where the network's image centre lands.
    h = bb.homography(64)
    centre = h @ [32, 32, 1]
    x, y = centre[:2] / centre[2]
    cam = camera()
    expected = cam.cx + cam.fx * joint[0] / -joint[2], cam.cy - cam.fy * joint[1] / -joint[2]
    assert np.allclose([x, y], expected, atol=1e-3)


def test_depth_of_the_plane_and_the_offset():
    cam = camera()
    bb = place([0, 0, -450.0], cam, VIEW)
    flat = bb.plane_depth(cam, np.zeros((128, 128)))
    assert np.allclose(flat, 450.0)
    bumped = bb.plane_depth(cam, np.full((128, 128), -20.0))  # 20 units towards the camera
    assert np.allclose(bumped, 430.0)
    off = place([50.0, 0, -400.0], cam, VIEW)
    depth = off.plane_depth(cam, np.zeros((128, 128)))
    col = round(cam.cx + cam.fx * 50 / 400 - 0.5)
    assert depth[64, col] == pytest.approx(400.0, rel=2e-3)  # the joint's own pixel


def test_invisible_cases_say_why():
    behind = place([0, 0, 10.0], camera(), VIEW)
    assert not behind.visible and "behind" in behind.reason
    inside = place([0, 0, -5.0], camera(), VIEW)
    assert not inside.visible and "inside" in inside.reason
    away = place([5000.0, 0, -450.0], camera(), VIEW)
    assert not away.visible and "outside" in away.reason


def test_rotation_between_opposite_vectors():
    r = rotation_between(np.array([0, 0, -1.0]), np.array([0, 0, 1.0]))
    assert np.allclose(r @ [0, 0, -1], [0, 0, 1]) and np.isclose(np.linalg.det(r), 1)

"""Rotation encodings against independent references (USD's Gf) and their properties."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf

from rigspace.sdk import rotations as rot

ROUND_TRIP = 1e-9


def random_rotations(n: int, seed: int = 0) -> np.ndarray:
    """Uniformly random rotations (normalised Gaussian quaternions)."""
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return rot.matrix_from_quat(q)


def test_matrix_from_quat_agrees_with_gf():
    q = np.random.default_rng(1).normal(size=(50, 4))
    ours = rot.matrix_from_quat(q)
    for qi, ri in zip(q, ours, strict=True):
        qi = qi / np.linalg.norm(qi)
        gf = Gf.Matrix3d(Gf.Rotation(Gf.Quatd(qi[0], Gf.Vec3d(*qi[1:]))))
        # Gf is row-vector: its matrix is the transpose of ours.
        np.testing.assert_allclose(ri, np.array(gf).T, atol=1e-12)


def test_quaternion_round_trip_and_hemisphere():
    r = random_rotations(2000)
    q = rot.quat_from_matrix(r)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1, atol=ROUND_TRIP)
    np.testing.assert_allclose(rot.matrix_from_quat(q), r, atol=1e-9)
    np.testing.assert_allclose(rot.matrix_from_quat(-q), r, atol=1e-9)  # q and -q agree


@pytest.mark.parametrize("angle", [0.0, np.pi, np.pi - 1e-9, 1e-9])
def test_quaternion_near_identity_and_half_turns(angle):
    for axis in np.eye(3):
        q = np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]
        r = rot.matrix_from_quat(q)
        np.testing.assert_allclose(rot.matrix_from_quat(rot.quat_from_matrix(r)), r, atol=1e-9)


def test_rot6d_round_trip_is_exact_for_rotations():
    r = random_rotations(2000, seed=2)
    x = rot.rot6d_from_matrix(r)
    assert x.shape == (2000, 6)
    np.testing.assert_allclose(rot.matrix_from_rot6d(x), r, atol=ROUND_TRIP)


def test_rot6d_decoding_projects_any_input_onto_a_rotation():
    x = np.random.default_rng(3).normal(size=(500, 6)) * 5
    r = rot.matrix_from_rot6d(x)
    np.testing.assert_allclose(
        r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(r), 1, atol=1e-9)


def test_orthonormalize_strips_scale():
    r = random_rotations(100, seed=4)
    scaled = r * np.random.default_rng(5).uniform(0.01, 100, size=(100, 1, 3))
    np.testing.assert_allclose(rot.orthonormalize(scaled), r, atol=1e-9)


def test_rig_parameters_are_camera_relative_and_ignore_translation():
    joints = np.tile(np.eye(4), (5, 1, 1))
    joints[:, :3, :3] = random_rotations(5, seed=6)
    camera = np.eye(4)
    camera[:3, :3] = random_rotations(1, seed=7)[0]
    params = rot.rig_parameters(joints, camera)
    moved = joints.copy()
    moved[:, :3, 3] += [10.0, -3.0, 7.0]
    np.testing.assert_array_equal(params, rot.rig_parameters(moved, camera))
    # Rotating the joints and the camera together leaves the parameters unchanged.
    turn = random_rotations(1, seed=8)[0]
    spun_joints, spun_camera = joints.copy(), camera.copy()
    spun_joints[:, :3, :3] = turn @ joints[:, :3, :3]
    spun_camera[:3, :3] = turn @ camera[:3, :3]
    np.testing.assert_allclose(params, rot.rig_parameters(spun_joints, spun_camera), atol=1e-6)
    decoded = rot.decode(params, rot.ROT6D)
    np.testing.assert_allclose(camera[:3, :3] @ decoded, joints[:, :3, :3], atol=1e-6)


def test_unknown_encoding():
    with pytest.raises(ValueError, match="unknown rotation encoding 'euler'"):
        rot.encode(np.eye(3), "euler")

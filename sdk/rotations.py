"""Rotation encodings for rig parameters: 6D (Zhou et al. 2019) and quaternions, vectorised.

Rig parameters (DESIGN.md): per joint, the joint's world rotation expressed in the
camera's frame, q~ = c^-1 q, encoded as the first two columns of its rotation matrix.
All functions take arrays of any leading shape; matrices are column-vector (v' = R @ v).
"""

from __future__ import annotations

import numpy as np

ROT6D = "rot6d"
QUATERNION = "quaternion"
ENCODING_SIZE = {ROT6D: 6, QUATERNION: 4}
_EPS = 1e-12  # guards divisions by a norm that is zero only for invalid input


def orthonormalize(m: np.ndarray) -> np.ndarray:
    """The rotation nearest to each 3x3 matrix (polar decomposition), stripping scale and shear."""
    m = np.asarray(m, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        # LAPACK's SVD never returns on an Inf entry (OpenBLAS 0.3.31) and fails with "SVD did
        # not converge" on NaN: name the matrix instead.
        flat = m.reshape(-1, 9)
        bad = int(np.flatnonzero(~np.isfinite(flat).all(axis=1))[0])
        raise ValueError(
            f"orthonormalize: matrix {bad} of {len(flat)} holds NaN or Inf; check the joint and "
            "camera transforms before building rig parameters."
        )
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    flip = np.linalg.det(r) < 0  # a mirror: flip the least significant axis
    if np.any(flip):
        u = u.copy()
        u[flip, :, 2] *= -1
        r = u @ vt
    return r


def rot6d_from_matrix(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): the first two columns, (r00, r10, r20, r01, r11, r21)."""
    r = np.asarray(r)
    return np.concatenate([r[..., :, 0], r[..., :, 1]], axis=-1)


def matrix_from_rot6d(x: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt (Zhou et al. 2019, eq. in section 4)."""
    x = np.asarray(x, dtype=np.float64)
    a1, a2 = x[..., 0:3], x[..., 3:6]
    b1 = a1 / np.maximum(np.linalg.norm(a1, axis=-1, keepdims=True), _EPS)
    a2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = a2 / np.maximum(np.linalg.norm(a2, axis=-1, keepdims=True), _EPS)
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a b of (..., 4) quaternions (w, x, y, z): apply b, then a."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation -> (..., 4) unit quaternion (w, x, y, z) with w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    # Squared magnitudes of each component, each computed from the trace (always >= 0 up to
    # rounding); take the largest for stability, signs from the off-diagonals.
    q2 = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        axis=-1,
    )
    q2 = np.maximum(q2, 0.0) / 4.0
    k = np.argmax(q2, axis=-1)
    big = np.sqrt(np.take_along_axis(q2, k[..., None], axis=-1))[..., 0]
    d = 4.0 * np.maximum(big, _EPS)
    zy, yz = r[..., 2, 1], r[..., 1, 2]
    xz, zx = r[..., 0, 2], r[..., 2, 0]
    yx, xy = r[..., 1, 0], r[..., 0, 1]
    candidates = np.stack(
        [
            np.stack([big, (zy - yz) / d, (xz - zx) / d, (yx - xy) / d], -1),
            np.stack([(zy - yz) / d, big, (xy + yx) / d, (xz + zx) / d], -1),
            np.stack([(xz - zx) / d, (xy + yx) / d, big, (yz + zy) / d], -1),
            np.stack([(yx - xy) / d, (xz + zx) / d, (yz + zy) / d, big], -1),
        ],
        axis=-2,
    )
    q = np.take_along_axis(candidates, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternion (w, x, y, z), normalised first -> (..., 3, 3). q and -q agree."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _EPS)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def encode(r: np.ndarray, encoding: str = ROT6D) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., k) in the named encoding."""
    if encoding == ROT6D:
        return rot6d_from_matrix(r)
    if encoding == QUATERNION:
        return quat_from_matrix(r)
    raise ValueError(
        f"unknown rotation encoding {encoding!r}; expected one of {list(ENCODING_SIZE)}"
    )


def decode(x: np.ndarray, encoding: str = ROT6D) -> np.ndarray:
    """(..., k) in the named encoding -> (..., 3, 3) rotations."""
    if encoding == ROT6D:
        return matrix_from_rot6d(x)
    if encoding == QUATERNION:
        return matrix_from_quat(x)
    raise ValueError(
        f"unknown rotation encoding {encoding!r}; expected one of {list(ENCODING_SIZE)}"
    )


def rig_inputs(
    rig: np.ndarray, blend: np.ndarray | None = None, controls: np.ndarray | None = None
) -> np.ndarray:
    """The network's input rows: each sample's rig parameters (N, J, k) or (N, J*k), then its
    blend shape weights (N, B) when the character has any, then its named controls' values
    (N, C) when it has any -> (N, J*k + B + C) float32. The paper's rig parameters are joint
    rotations, blend shapes or cage positions; rigspace feeds rotations, blend shape weights
    (the manifest's `blend_shapes` order) and controls (its `controls` order)."""
    rig = np.asarray(rig, dtype=np.float32)
    rows = rig.reshape(len(rig), -1)
    parts = [rows] + [
        np.asarray(extra, dtype=np.float32).reshape(len(rows), -1)
        for extra in (blend, controls)
        if extra is not None and np.size(extra) > 0
    ]
    if len(parts) == 1:
        return np.ascontiguousarray(rows)
    return np.ascontiguousarray(np.concatenate(parts, axis=1))


def rig_parameters(
    joint_to_world: np.ndarray, camera_to_world: np.ndarray, encoding: str = ROT6D
) -> np.ndarray:
    """Per-joint world rotations in the camera's frame, encoded: (J, 4, 4), (4, 4) -> (J, k).

    q~ = c^-1 q (the paper's camera-relative rotation). Scale and shear are stripped from
    both first, and translation never enters.
    """
    joints = orthonormalize(np.asarray(joint_to_world)[..., :3, :3])
    camera = orthonormalize(np.asarray(camera_to_world)[:3, :3])
    return encode(camera.T @ joints, encoding).astype(np.float32)


UPRIGHT_LIMIT = 0.05
"""Below this sine of the angle between a line of sight and the direction a camera keeps
upright (within 3 degrees of looking straight along it) that direction cannot be upright in
the image: the ring and the billboard keep the stage's up axis instead."""


def joint_up(joint_to_world: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(3,) unit world direction of a joint's own up `axis` (its local frame) at
    `joint_to_world` (4, 4, column vectors; scale and shear stripped)."""
    up = orthonormalize(np.asarray(joint_to_world, np.float64)[:3, :3]) @ np.asarray(axis, float)
    return up / max(float(np.linalg.norm(up)), _EPS)


def rest_up_axis(rest_joint_to_world: np.ndarray, stage_up: np.ndarray) -> np.ndarray:
    """(3,) the joint's local direction that is the stage's up in its rest pose
    (`rest_joint_to_world`, 4x4): the up a region's cameras keep upright with the joint."""
    rotation = orthonormalize(np.asarray(rest_joint_to_world, np.float64)[:3, :3])
    axis = rotation.T @ np.asarray(stage_up, np.float64)
    return axis / max(float(np.linalg.norm(axis)), _EPS)


def upright_usable(line_of_sight: np.ndarray, up: np.ndarray) -> bool:
    """Whether a camera looking along `line_of_sight` can keep `up` upright (UPRIGHT_LIMIT)."""
    forward = np.asarray(line_of_sight, float) / max(float(np.linalg.norm(line_of_sight)), _EPS)
    side = np.cross(forward, np.asarray(up, float) / max(float(np.linalg.norm(up)), _EPS))
    return bool(np.linalg.norm(side) >= UPRIGHT_LIMIT)

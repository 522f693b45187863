"""Pose-guided conditioning: the rig's joints by forward kinematics, in the training camera's image.

One implementation for training data and the runtime (no torch). The rig parameters already
hold every joint's rotation in the (virtual) camera's frame; with the skeleton's bone
offsets, forward kinematics gives each joint's camera-space position relative to the
look-at joint, which a camera at the training distance looking at that joint projects to
normalised image coordinates:

    u = (2 f / aperture) X / (D - Z),   v = -(2 f / aperture) Y / (D - Z)

u runs left to right and v top to bottom across [-1, 1] (the image edges; pixel k of R has
its centre at (k + 0.5) / R * 2 - 1), matching the network's maps row for row. Because the
input is the rig itself, a dataset sample and the runtime at that sample's camera and pose
give the same coordinates; the character's on-screen scale is the billboard's business,
as for the maps (the offsets are the training skeleton's, in scene units).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigspace.sdk.rotations import matrix_from_rot6d, orthonormalize

KINDS = ("joints2d", "bones2d")
"""Conditioning maps a bundle may compute from its `joints2d` input: one Gaussian per joint,
or one per bone segment (joint to parent)."""


def joint_parents(joints: Sequence[str]) -> np.ndarray:
    """Index of each joint's nearest listed ancestor (-1 for none), from the joints' paths.

    Joint names are UsdSkel paths ("pelvis/spine_01"), so the topology is in the names.
    """
    index = {name: k for k, name in enumerate(joints)}
    parents = np.full(len(joints), -1, dtype=np.int64)
    for k, name in enumerate(joints):
        parts = name.split("/")
        for cut in range(len(parts) - 1, 0, -1):
            parent = index.get("/".join(parts[:cut]))
            if parent is not None:
                parents[k] = parent
                break
        if parents[k] >= k:
            raise ValueError(
                f"joint {name!r} comes before its parent; joints must be in skeleton order"
            )
    return parents


def bone_offsets(joint_to_world: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(J, 3) each joint's position relative to its parent, in the parent's rotation frame.

    p_j = p_parent + R_parent o_j with R the orthonormalised world rotation (the rig's), so
    o_j is constant while bones keep their length; roots get their world position's zero.
    """
    world = np.asarray(joint_to_world, dtype=np.float64)
    rot = orthonormalize(world[:, :3, :3])
    pos = world[:, :3, 3]
    offsets = np.zeros((len(parents), 3))
    child = np.flatnonzero(parents >= 0)
    p = parents[child]
    offsets[child] = np.einsum("kji,kj->ki", rot[p], pos[child] - pos[p])
    return offsets


@dataclass(frozen=True)
class Skeleton2D:
    """What joints2d needs besides the rig: topology, bone offsets, look-at joint, the view."""

    parents: np.ndarray
    offsets: np.ndarray
    look_at: int
    distance: float
    focal_length: float
    horizontal_aperture: float

    def to_json(self) -> dict[str, Any]:
        return {
            "parents": [int(p) for p in self.parents],
            "offsets": [[float(x) for x in row] for row in self.offsets],
            "look_at": int(self.look_at),
            "distance": float(self.distance),
            "focal_length": float(self.focal_length),
            "horizontal_aperture": float(self.horizontal_aperture),
        }

    @classmethod
    def of_conditioning(cls, conditioning: dict[str, Any] | None) -> Skeleton2D | None:
        """A bundle manifest's `conditioning.skeleton` (ModelManifest.conditioning); None for
        an unconditioned bundle."""
        return cls.from_json(conditioning["skeleton"]) if conditioning else None

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Skeleton2D:
        return cls(
            np.asarray(data["parents"], dtype=np.int64),
            np.asarray(data["offsets"], dtype=np.float64).reshape(-1, 3),
            int(data["look_at"]),
            float(data["distance"]),
            float(data["focal_length"]),
            float(data["horizontal_aperture"]),
        )


def joints2d(rig: np.ndarray, skeleton: Skeleton2D) -> np.ndarray:
    """Rig parameters (N, J*6) or (N, J, 6) -> (N, J*2) float32 normalised image coordinates
    (u, v per joint, manifest order) in a camera at the training distance from the look-at joint.
    Network input rows (N, J*6 + B) work too: blend shape weights do not move joints.
    """
    rig = np.asarray(rig, dtype=np.float64)
    count = len(skeleton.parents)
    rows = rig.reshape(len(rig), -1)[:, : count * 6]
    rot = matrix_from_rot6d(rows.reshape(len(rig), count, 6))  # (N, J, 3, 3), camera frame
    pos = np.zeros((len(rig), count, 3))
    # Forward kinematics down the skeleton (parents come first): a loop over joints, each
    # step vectorised over the samples.
    for j, parent in enumerate(skeleton.parents):
        if parent >= 0:
            pos[:, j] = pos[:, parent] + rot[:, parent] @ skeleton.offsets[j]
    rel = pos - pos[:, skeleton.look_at : skeleton.look_at + 1]
    depth = np.maximum(skeleton.distance - rel[..., 2], 1e-3 * skeleton.distance)
    scale = 2.0 * skeleton.focal_length / skeleton.horizontal_aperture
    uv = np.stack([scale * rel[..., 0] / depth, -scale * rel[..., 1] / depth], axis=-1)
    return uv.reshape(len(rig), 2 * count).astype(np.float32)

"""Pose-guided conditioning for training: the dataset's skeleton, and joints2d -> maps in torch.

The 2D joint coordinates come from rigspace.sdk.conditioning (the runtime's function too);
`ConditionMaps` turns them into per-joint or per-bone Gaussian maps at a level, with only
elementwise ops, Gather, Clip and Exp, so the maps are computed inside the exported ONNX
graphs and a frame passes J*2 numbers.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from rigspace.sdk.conditioning import KINDS, Skeleton2D, bone_offsets, joint_parents

if TYPE_CHECKING:
    from rigspace.capture.dataset import DatasetManifest

BONE_LENGTH_TOLERANCE = 1e-3
"""Largest change of a bone offset across the clips, as a share of the ring radius, that still
counts as a rigid skeleton (the conditioning assumes constant bone offsets)."""


MAP_FLOOR = 20.0
"""Conditioning maps stop at exp(-MAP_FLOOR) (2e-9), a normal float32 (see ConditionMaps)."""


def dataset_skeleton(folder: str | Path, manifest: DatasetManifest) -> Skeleton2D:
    """The bone offsets of a dataset's character, read once from its scene (manifest `scene`).

    Offsets are taken at each clip's first frame and must agree (a rig that stretches its
    bones cannot be conditioned this way); the view is the capture ring's.
    """
    from rigspace.capture.dataset import DatasetError  # here: the network imports no dataset code
    from rigspace.sdk.posing import CharacterRig
    from rigspace.sdk.stage import open_stage

    scene = Path(manifest.scene)
    if not scene.is_file():
        raise DatasetError(
            f"Pose conditioning reads the character's skeleton from the dataset's scene "
            f"{scene}, which does not exist (dataset {folder}).",
            "restore the scene at that path, or train with --conditioning none.",
        )
    stage = open_stage(scene)  # held while the rig is used: prims expire with their stage
    rig = CharacterRig(stage.GetPrimAtPath(manifest.character))
    joints = list(manifest.joints)  # every joint, or a region's own (a closed tree)
    if not set(joints) <= set(rig.joints):
        raise DatasetError(
            f"The skeleton of {manifest.character} in {scene} no longer has the dataset's "
            f"joints (dataset {folder}).",
            "re-capture the dataset, or train with --conditioning none.",
        )
    index = [rig.joints.index(j) for j in joints]
    parents = joint_parents(joints)
    offsets = [
        bone_offsets(rig.world_transforms(clip.first)[index], parents) for clip in manifest.clips
    ]
    ring = manifest.ring
    spread = float(np.max(np.ptp(np.stack(offsets), axis=0)))
    if spread > BONE_LENGTH_TOLERANCE * ring.radius:
        raise DatasetError(
            f"The bones of {manifest.character} change length between clips (by {spread:.3g} "
            "scene units); pose conditioning assumes a rigid skeleton.",
            "train with --conditioning none.",
        )
    return Skeleton2D(
        parents,
        offsets[0],
        joints.index(manifest.look_at_joint),
        float(ring.radius),
        float(ring.focal_length),
        float(ring.horizontal_aperture),
    )


def parents_of(joints: list[str]) -> tuple[int, ...]:
    """The joints' parent indices (-1: a root) as network.Shape takes them."""
    return tuple(int(p) for p in joint_parents(joints))


def channels(kind: str, joints: int) -> int:
    """Conditioning maps per level: one per joint, one per bone (non-root joint), or none."""
    if kind == "none":
        return 0
    if kind not in KINDS:
        raise ValueError(f"unknown conditioning {kind!r}; choose none, {', '.join(KINDS)}")
    return joints if kind == "joints2d" else joints - 1


class ConditionMaps(nn.Module):
    """joints2d (N, J*2) -> (N, K, R, R) Gaussian maps of the joints or bone segments.

    A map's width is max(sigma, one pixel of the level) in normalised image units (the
    image spans [-1, 1]), so small levels never alias a joint between pixels.
    """

    child: torch.Tensor
    parent: torch.Tensor
    """Each bone's two joints (buffers: indices into joints2d's joints)."""

    def __init__(self, kind: str, parents: np.ndarray, sigma: float) -> None:
        super().__init__()
        self.kind, self.sigma, self.joints = kind, float(sigma), len(parents)
        self.count = channels(kind, len(parents))
        bones = np.flatnonzero(np.asarray(parents) >= 0)
        self.register_buffer("child", torch.as_tensor(bones, dtype=torch.long), persistent=False)
        self.register_buffer(
            "parent",
            torch.as_tensor(np.asarray(parents)[bones], dtype=torch.long),
            persistent=False,
        )

    def forward(self, joints2d: torch.Tensor, resolution: int) -> torch.Tensor:
        xy = joints2d.reshape(-1, self.joints, 2)
        grid = (torch.arange(resolution, dtype=joints2d.dtype, device=joints2d.device) + 0.5) * (
            2.0 / resolution
        ) - 1.0
        gx, gy = grid.view(1, 1, 1, -1), grid.view(1, 1, -1, 1)
        sigma = max(self.sigma, 2.0 / resolution)
        if self.kind == "joints2d":
            ax, ay = xy[..., 0, None, None], xy[..., 1, None, None]
            d2 = (gx - ax).square() + (gy - ay).square()
        else:
            a, b = xy[:, self.child], xy[:, self.parent]
            ax, ay = a[..., 0, None, None], a[..., 1, None, None]
            bx, by = (b - a)[..., 0, None, None], (b - a)[..., 1, None, None]
            # The closest point of the segment a -> b to each pixel centre (a point when a = b).
            t = ((gx - ax) * bx + (gy - ay) * by) / (bx.square() + by.square() + 1e-12)
            t = t.clamp(0.0, 1.0)
            d2 = (gx - ax - t * bx).square() + (gy - ay - t * by).square()
        # Far from every joint exp(-x) falls into float32 denormals, which made the convolutions
        # reading the maps 10-20x slower (measured, onnxruntime and torch): floor at exp(-20).
        return torch.exp(-(d2 * (0.5 / sigma**2)).clamp(max=MAP_FLOOR))

"""One live binding at run time: its source, buffer and retargeter, from RigspaceLiveBindingAPI."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigspace.runtime.live.buffer import BindingCounters, BufferSettings, LiveBuffer, LivePose
from rigspace.runtime.live.retarget import (
    PRESETS,
    Y_180,
    Preset,
    Retargeter,
    source_basis,
    source_hierarchy,
    target_skeleton,
)
from rigspace.runtime.live.sources import open_source
from rigspace.runtime.live.transports import Source
from rigspace.sdk.rotations import quat_from_matrix

DEFAULT_PRESET = {"vmc": "unity", "replay": "cmu", "bvh+tcp": "cmu"}
"""The bone-name preset a scheme gets when the binding authors no sourceBones (and the source's
bones match the preset's)."""
NATIVE_BASIS = {"vmc": Y_180}
"""Sources whose decoder already converted to right-handed Y up, but whose performer faces
-Z: their basis replaces the binding's sourceUpAxis/sourceHandedness (no double conversion)."""


@dataclass
class LiveBindingRuntime:
    """A started-on-demand binding: `apply(stage_local)` merges its live pose every frame."""

    name: str
    source: Source
    buffer: LiveBuffer
    retargeter: Retargeter

    def start(self) -> None:
        self.source.start(self.buffer)

    def stop(self) -> None:
        self.source.stop()

    def pose(self, now: float | None = None) -> LivePose:
        return self.buffer.pose(now)

    def apply(
        self, stage_local: np.ndarray, now: float | None = None
    ) -> tuple[np.ndarray, LivePose]:
        """The stage's (J, 4, 4) local transforms with this binding's pose merged in, and the pose
        (its status and weight belong in the frame's report)."""
        pose = self.buffer.pose(time.monotonic() if now is None else now)
        return self.retargeter.apply(stage_local, pose), pose

    def counters(self, now: float | None = None) -> BindingCounters:
        return self.source.counters(now)

    def rest_pose_attributes(self) -> tuple[list[str], np.ndarray]:
        """(sourceBones, restPose) to author after calibration: the mapped bones and their rest
        rotations (w, x, y, z), parallel."""
        r = self.retargeter
        bones = [r.source_bones[i] for i in r.map_source]
        return bones, r.rest_pose[r.map_source]


def open_binding(
    binding: Any,
    skeleton_prim: Any,
    stage_meters_per_unit: float,
    preset: str | None = None,
    extra: dict[str, Callable[[], Any]] | None = None,
) -> LiveBindingRuntime:
    """Build (not start) the runtime of an sdk.schema.LiveBinding for a UsdSkel Skeleton.

    - Bone map: the binding's sourceBones -> targetJoints when authored; else `preset` (or the
      scheme's default preset when the source sends its bones); else source bones onto joints
      of the same name.
    - Basis: the source's native one (VMC) or the binding's up axis and handedness.
    - Rest: restPose when authored (parallel to the map's source bones); else the character's
      rest aligned onto the source's (`Retargeter.align_rest`): a BVH's own, or the preset's
      canonical T-pose (VMC).
    - Units: sourceMetersPerUnit, or the preset's when the preset supplies the map and the
      binding leaves the default 1.
    - A recorded take (replay:// of a .usd file) plays back onto its own skeleton exactly: same
      joints, identity basis, the skeleton's rest as its rest pose, the take's units.
    """
    source = open_source(binding.url, binding.name, extra)
    scheme = binding.url.split("://", 1)[0].lower()
    joints, rest = target_skeleton(skeleton_prim)
    chosen = PRESETS.get(preset or DEFAULT_PRESET.get(scheme, ""))
    meters_per_unit = binding.source_meters_per_unit
    native = bool(getattr(source, "native", False))  # a recorded take of this skeleton
    if native:
        meters_per_unit = getattr(source, "meters_per_unit", None) or meters_per_unit
    if binding.source_bones:
        bone_map = dict(zip(binding.source_bones, binding.target_joints, strict=True))
    elif native:
        leaves = {j.rsplit("/", 1)[-1] for j in joints}
        bone_map = {b: b for b in source.bones if b in leaves}
    elif chosen is not None and set(chosen.bone_map) & set(source.bones):
        bone_map = chosen.bone_map
        if meters_per_unit == 1.0:
            meters_per_unit = chosen.meters_per_unit
    else:
        leaves = {j.rsplit("/", 1)[-1] for j in joints}
        bone_map = {b: b for b in source.bones if b in leaves}
    basis = np.eye(3) if native else NATIVE_BASIS.get(scheme)
    if basis is None:
        basis = source_basis(binding.source_up_axis, binding.source_handedness)
    hierarchy = source_hierarchy(source, chosen or PRESETS["unity"])
    retargeter = Retargeter(
        source.bones,
        hierarchy,
        source.space,
        joints,
        rest,
        bone_map,
        basis,
        meters_per_unit / stage_meters_per_unit,
    )
    if native:
        # The take's rest is the skeleton's own: then each joint gets the take's rotation back.
        leaf = {j.rsplit("/", 1)[-1]: i for i, j in enumerate(joints)}
        rest_rotations = quat_from_matrix(np.swapaxes(rest[:, :3, :3], 1, 2))
        full = np.tile([1.0, 0.0, 0.0, 0.0], (len(source.bones), 1))
        for k, bone in enumerate(source.bones):
            if bone in leaf:
                full[k] = rest_rotations[leaf[bone]]
        retargeter.calibrate_rotations(full)
        root = retargeter.target_root
        retargeter.rest_root = rest[root, 3, :3] * stage_meters_per_unit / meters_per_unit
    elif not binding.rest_pose and (positions := _rest_positions(source, chosen)) is not None:
        # The source's rest (this CMU conversion: arms hanging; VMC: a T-pose) is not the
        # character's (an A-pose): turn the character's rest onto the source's.
        retargeter.align_rest(positions)
    elif binding.rest_pose:
        full = np.tile([1.0, 0.0, 0.0, 0.0], (len(source.bones), 1))
        index = {b: i for i, b in enumerate(source.bones)}
        for bone, q in zip(bone_map, binding.rest_pose, strict=False):
            if bone in index:
                full[index[bone]] = q
        retargeter.calibrate_rotations(full)
    return LiveBindingRuntime(
        binding.name,
        source,
        LiveBuffer(source.bones, BufferSettings.from_binding(binding)),
        retargeter,
    )


def _rest_positions(source: Source, preset: Preset | None) -> np.ndarray | None:
    """The source's rest joint positions: its own skeleton's (BVH stream and replay), else its
    preset's canonical rest (VMC: a VRM-style T-pose), else None."""
    skeleton = getattr(getattr(source, "decoder", None), "skeleton", None)
    if skeleton is not None:
        return skeleton.rest_positions()
    own = getattr(source, "rest_positions", None)
    if own is not None:
        return own
    return preset.rest_positions_for(source.bones) if preset is not None else None

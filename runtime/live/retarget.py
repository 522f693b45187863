"""Retargeting: source bones onto a UsdSkel skeleton by world-rotation deltas, with presets.

Convention (the "documented conversion"): for every mapped target joint j fed by source bone b,

    W'_j = A (W_b R_b^-1) A^-1 W'rest_j

W_b is b's world rotation in the source (its local rotations composed down the source hierarchy,
or the sensor orientation for world-space sources), R_b its world rotation in the calibration
rest pose (identity without calibration: BVH rest frames are world-aligned), A the source-to-stage
basis, W'rest_j the target's rest world rotation. So a mapped joint turns, in the stage's frame,
exactly as its source bone turned away from its rest pose, whatever the two skeletons' joint
frames. The target's local rotation follows from its parent's final world rotation, so target
joints without a source keep the stage animation's local values and mapped children still land
on their source's world rotation.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from rigspace.runtime.live.buffer import LivePose
from rigspace.runtime.live.decoders.vmc import HUMAN_BODY_BONES, ROOT
from rigspace.runtime.live.source_frame import quat_slerp
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.rotations import matrix_from_quat, quat_from_matrix, quat_multiply


class RetargetError(RigspaceError):
    """A bone map that does not fit the source or the skeleton."""


Y_180 = np.diag([-1.0, 1.0, -1.0])
MIRROR_Z = np.diag([1.0, 1.0, -1.0])
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # (x, z, -y)


def source_basis(up_axis: str = "Y", handedness: str = "right", facing_yaw_degrees: float = 0.0):
    """3x3 matrix taking source coordinates to the stage's right-handed Y-up frame: a Z mirror
    for left-handed data, (x, y, z) -> (x, z, -y) for Z up, then a turn about Y (degrees) so the
    performer's forward becomes the character's forward."""
    m = np.eye(3)
    if handedness == "left":
        m = MIRROR_Z @ m
    if up_axis == "Z":
        m = Z_UP_TO_Y_UP @ m
    yaw = np.radians(facing_yaw_degrees)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ m


def _sided(pairs: Mapping[str, str], left: str, right: str, tl: str, tr: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for source, target in pairs.items():
        out[source.format(side=left)] = target.format(side=tl)
        out[source.format(side=right)] = target.format(side=tr)
    return out


@dataclass(frozen=True)
class Preset:
    """A source skeleton family: its bone map to the sample character, hierarchy, basis, units."""

    name: str
    bone_map: dict[str, str]
    """Source bone -> target joint name (the sample character's; a leaf name or full path)."""
    parents: dict[str, str]
    """Source bone -> its parent source bone (absent: a root), to compose world rotations."""
    basis: np.ndarray = field(default_factory=lambda: np.eye(3))
    """Source (as decoded) to the sample character's frame (Y up, facing +Z, left +X)."""
    meters_per_unit: float = 1.0
    rest_positions: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    """Joint positions in the family's rest pose, in the source's frame and units, where the
    wire carries no rest geometry (VMC); empty: the source supplies its own (BVH)."""

    def rest_positions_for(self, bones: Sequence[str]) -> np.ndarray | None:
        """(B, 3) rest positions for a source's bones (zeros for bones the preset lacks)."""
        if not self.rest_positions:
            return None
        return np.array([self.rest_positions.get(b, (0.0, 0.0, 0.0)) for b in bones])


def _unity_t_pose() -> dict[str, tuple[float, float, float]]:
    """A VRM-style humanoid T-pose (all local rotations identity), metres, in VmcDecoder's frame:
    Y up, the avatar facing -Z with its left at -X (Unity's +Z forward, mirrored)."""
    pose = {ROOT: (0.0, 0.0, 0.0), "Hips": (0.0, 0.95, 0.0), "Spine": (0.0, 1.05, 0.0)}
    pose |= {"Chest": (0.0, 1.2, 0.0), "UpperChest": (0.0, 1.32, 0.0)}
    pose |= {"Neck": (0.0, 1.48, 0.0), "Head": (0.0, 1.58, 0.0)}
    for side, x in (("Left", -1.0), ("Right", 1.0)):
        pose |= {
            f"{side}Shoulder": (0.04 * x, 1.42, 0.0),
            f"{side}UpperArm": (0.17 * x, 1.42, 0.0),
            f"{side}LowerArm": (0.45 * x, 1.42, 0.0),
            f"{side}Hand": (0.70 * x, 1.42, 0.0),
            f"{side}UpperLeg": (0.09 * x, 0.92, 0.0),
            f"{side}LowerLeg": (0.09 * x, 0.50, 0.0),
            f"{side}Foot": (0.09 * x, 0.08, 0.0),
            f"{side}Toes": (0.09 * x, 0.02, -0.13),
        }
    return pose


def _unity_parents() -> dict[str, str]:
    parents = {"Hips": ROOT, "Spine": "Hips", "Chest": "Spine", "UpperChest": "Chest"}
    parents |= {"Neck": "UpperChest", "Head": "Neck", "LeftEye": "Head", "RightEye": "Head"}
    parents["Jaw"] = "Head"
    for side in ("Left", "Right"):
        parents |= {
            f"{side}UpperLeg": "Hips",
            f"{side}LowerLeg": f"{side}UpperLeg",
            f"{side}Foot": f"{side}LowerLeg",
            f"{side}Toes": f"{side}Foot",
            f"{side}Shoulder": "UpperChest",
            f"{side}UpperArm": f"{side}Shoulder",
            f"{side}LowerArm": f"{side}UpperArm",
            f"{side}Hand": f"{side}LowerArm",
        }
        for finger in ("Thumb", "Index", "Middle", "Ring", "Little"):
            chain = [f"{side}Hand"] + [
                f"{side}{finger}{p}" for p in ("Proximal", "Intermediate", "Distal")
            ]
            parents |= dict(zip(chain[1:], chain[:-1], strict=True))
    assert set(parents) == set(HUMAN_BODY_BONES)
    return parents


UNITY = Preset(
    "unity",
    {"Hips": "pelvis", "Spine": "spine_01", "Chest": "spine_02", "UpperChest": "spine_03"}
    | {"Neck": "neck_01", "Head": "head"}
    | _sided(
        {
            "{side}Shoulder": "clavicle_{side}",
            "{side}UpperArm": "upperarm_{side}",
            "{side}LowerArm": "lowerarm_{side}",
            "{side}Hand": "hand_{side}",
            "{side}UpperLeg": "thigh_{side}",
            "{side}LowerLeg": "calf_{side}",
            "{side}Foot": "foot_{side}",
            "{side}Toes": "ball_{side}",
        },
        "Left",
        "Right",
        "l",
        "r",
    ),
    _unity_parents(),
    # VmcDecoder already mirrored Unity's Z: the avatar faces -Z with its left at -X; turn it.
    Y_180,
    1.0,
    _unity_t_pose(),
)

CMU = Preset(
    "cmu",
    {"Hips": "pelvis", "lowerback": "spine_01", "Chest": "spine_02", "Chest2": "spine_03"}
    | {"Neck": "neck_01", "Head": "head"}
    | _sided(
        {
            "{side}Collar": "clavicle_{side}",
            "{side}Shoulder": "upperarm_{side}",
            "{side}Elbow": "lowerarm_{side}",
            "{side}Wrist": "hand_{side}",
            "{side}Hip": "thigh_{side}",
            "{side}Knee": "calf_{side}",
            "{side}Ankle": "foot_{side}",
            "{side}Toe": "ball_{side}",
        },
        "Left",
        "Right",
        "l",
        "r",
    ),
    {},  # BVH sources bring their own hierarchy (BvhSkeleton.parents)
    np.eye(3),
    0.0254 / 0.45,  # the CMU ASF length unit: 1/0.45 inch
)

_MIXAMO_PARENTS = {"Spine": "Hips", "Spine1": "Spine", "Spine2": "Spine1", "Neck": "Spine2"}
_MIXAMO_PARENTS["Head"] = "Neck"
for _side in ("Left", "Right"):
    _MIXAMO_PARENTS |= {
        f"{_side}Shoulder": "Spine2",
        f"{_side}Arm": f"{_side}Shoulder",
        f"{_side}ForeArm": f"{_side}Arm",
        f"{_side}Hand": f"{_side}ForeArm",
        f"{_side}UpLeg": "Hips",
        f"{_side}Leg": f"{_side}UpLeg",
        f"{_side}Foot": f"{_side}Leg",
        f"{_side}ToeBase": f"{_side}Foot",
    }

MIXAMO = Preset(
    "mixamo",
    {
        f"mixamorig:{s}": t
        for s, t in (
            {"Hips": "pelvis", "Spine": "spine_01", "Spine1": "spine_02", "Spine2": "spine_03"}
            | {"Neck": "neck_01", "Head": "head"}
            | _sided(
                {
                    "{side}Shoulder": "clavicle_{side}",
                    "{side}Arm": "upperarm_{side}",
                    "{side}ForeArm": "lowerarm_{side}",
                    "{side}Hand": "hand_{side}",
                    "{side}UpLeg": "thigh_{side}",
                    "{side}Leg": "calf_{side}",
                    "{side}Foot": "foot_{side}",
                    "{side}ToeBase": "ball_{side}",
                },
                "Left",
                "Right",
                "l",
                "r",
            )
        ).items()
    },
    {f"mixamorig:{c}": f"mixamorig:{p}" for c, p in _MIXAMO_PARENTS.items()},
    np.eye(3),
    0.01,  # Mixamo FBX/BVH exports are in centimetres
)

PRESETS = {p.name: p for p in (UNITY, CMU, MIXAMO)}


def hierarchy_levels(parents: np.ndarray) -> list[np.ndarray]:
    """Joint indices grouped by depth (roots first), so parents are done before children,
    whatever order the joints are listed in (HumanBodyBones lists UpperChest last)."""
    parents = np.asarray(parents, dtype=np.int64)
    depth = np.where(parents < 0, 0, -1)
    for _ in range(len(parents)):
        pending = depth < 0
        if not pending.any():
            break
        ready = pending & (depth[np.maximum(parents, 0)] >= 0)
        depth[ready] = depth[parents[ready]] + 1
    if (depth < 0).any():
        raise RetargetError(
            "The source hierarchy has a cycle.", "give every bone a parent chain to a root."
        )
    return [np.flatnonzero(depth == d) for d in range(int(depth.max(initial=-1)) + 1)]


def _parent_indices(names: Sequence[str], parents: Mapping[str, str]) -> np.ndarray:
    """Parent index per bone from a name map; a parent the source does not send makes a root."""
    index = {n: i for i, n in enumerate(names)}
    return np.array([index.get(parents.get(n, ""), -1) for n in names], dtype=np.int64)


def _bone_map_indices(
    source_bones: tuple[str, ...], target_joints: tuple[str, ...], bone_map: Mapping[str, str]
) -> tuple[np.ndarray, np.ndarray]:
    """The bone map as index pairs: the source bones it maps that the source sends, and their
    target joints (a full path or a unique last element); a RetargetError when a target is not
    a joint or no bone is mapped."""
    leaf = {j.rsplit("/", 1)[-1]: i for i, j in enumerate(target_joints)}
    full = {j: i for i, j in enumerate(target_joints)}
    src_index = {b: i for i, b in enumerate(source_bones)}
    pairs = []
    for source, target in bone_map.items():
        if source not in src_index:
            continue  # the preset names bones this source does not send
        j = full.get(target, leaf.get(target))
        if j is None:
            raise RetargetError(
                f"Bone map target {target!r} (for source bone {source!r}) is not a joint of "
                "the skeleton.",
                f"use one of {', '.join(sorted(leaf))}.",
            )
        pairs.append((src_index[source], j))
    if not pairs:
        raise RetargetError(
            "The bone map maps none of the source's bones.",
            "choose the preset of the source's skeleton, or author sourceBones/targetJoints.",
        )
    return np.array([s for s, _ in pairs]), np.array([t for _, t in pairs])


class Retargeter:
    """Maps one source's poses onto a skeleton's local transforms (see the module docstring)."""

    def __init__(
        self,
        source_bones: Sequence[str],
        source_parents: Mapping[str, str] | Sequence[int] | np.ndarray,
        space: str,
        target_joints: Sequence[str],
        target_rest_local: np.ndarray,
        bone_map: Mapping[str, str],
        basis: np.ndarray | None = None,
        scale: float = 1.0,
        rest_pose: np.ndarray | None = None,
        rest_root: np.ndarray | None = None,
        root_motion: bool = True,
    ) -> None:
        """`space` is "local", "world" or "additive" (offsets on the stage animation, in each
        joint's frame). `target_rest_local` is (J, 4, 4) in USD's row-vector layout (restTransforms);
        `scale` takes source units to stage units (root motion: the source root's position
        relative to `rest_root`, else to where it first was, moves the target's root joint); `rest_pose` is (B, 4), the calibration."""
        self.source_bones = tuple(source_bones)
        if isinstance(source_parents, Mapping):
            self.source_parents = _parent_indices(self.source_bones, source_parents)
        else:
            self.source_parents = np.asarray(source_parents, dtype=np.int64)
        self.source_levels = hierarchy_levels(self.source_parents)
        self.space = space
        self.target_joints = tuple(target_joints)
        full = {j: i for i, j in enumerate(self.target_joints)}
        self.target_parents = np.array(
            [full.get(j.rsplit("/", 1)[0], -1) if "/" in j else -1 for j in self.target_joints]
        )
        self.target_levels = hierarchy_levels(self.target_parents)
        self.map_source, self.map_target = _bone_map_indices(
            self.source_bones, self.target_joints, bone_map
        )
        basis = np.eye(3) if basis is None else np.asarray(basis, dtype=np.float64)
        # A R A^T = (-A) R (-A)^T: a mirroring basis conjugates like the rotation -A.
        self.basis = basis
        self._a = basis if np.linalg.det(basis) > 0 else -basis
        self.scale = scale
        rest_local = np.asarray(target_rest_local, dtype=np.float64)
        n = len(self.target_joints)
        # Roots take their parent from a padded identity slot, so each level is one matmul.
        self._parent_slot = np.where(self.target_parents < 0, n, self.target_parents)
        self._rest_local = rest_local
        self._rest_world = self._compose_target(_rotations(rest_local))
        self._rest_positions = _world_positions(rest_local, self.target_levels, self._parent_slot)
        self._rest_t = rest_local[:, 3, :3]
        self.target_root = int(np.flatnonzero(self.target_parents < 0)[0])
        """Root motion moves the skeleton's (first) root joint, in stage units."""
        self.root_motion = root_motion
        self.rest_root = None if rest_root is None else np.asarray(rest_root, dtype=np.float64)
        self._index_arrays()
        self.calibrate_rotations(rest_pose)

    def _index_arrays(self) -> None:
        """Per-binding constants for `apply`, computed once: the source bones a frame composes
        (the mapped ones and their ancestors, not the fingers VMC also sends) and their levels."""
        need = np.zeros(len(self.source_bones), dtype=bool)
        for bone in self.map_source.tolist():
            while bone >= 0 and not need[bone]:
                need[bone] = True
                bone = int(self.source_parents[bone])
        self._need = np.flatnonzero(need)
        position = np.full(len(self.source_bones), -1)
        position[self._need] = np.arange(len(self._need))
        parents = self.source_parents[self._need]
        self._need_parents = np.where(parents >= 0, position[np.maximum(parents, 0)], -1)
        self._need_levels = hierarchy_levels(self._need_parents)
        self._map_in_need = position[self.map_source]
        self._right: np.ndarray | None = None
        """(M, 3, 3) source rest^-1 A^T target rest world per mapped pair (None: recompute after
        a calibration or a rest alignment)."""
        self._structure: dict[bytes, tuple] = {}
        """Received-bones mask -> the index arrays of `apply` for it (usually one entry)."""

    def align_rest(
        self, source_rest_positions: np.ndarray, preset: Preset | None = None
    ) -> dict[int, np.ndarray]:
        """Make the source's rest pose the target's: turn each mapped joint's rest so its bone
        points where the source bone points in the source's rest pose (this CMU conversion rests
        with the arms hanging, the sample character is bound in an A-pose).

        `source_rest_positions` are (B, 3) joint positions in the source's rest pose. A joint
        with one mapped child turns by the smallest rotation taking its bone onto the source's;
        a joint with several (the pelvis: spine and thighs; the chest: neck and clavicles) by
        the rotation that best takes all their directions onto the source's (`_fit_turn`), which
        leaves no twist free. Joints without a mapped child turn with their parent.

        With a `preset` whose map drives the same joints as the humanoid's (cmu, mixamo), the
        rest is aligned *through* the canonical T-posed humanoid (`humanoid_turns`): the source
        onto the humanoid, the humanoid onto the target, as `live send` and a VMC receiver do
        it. A least-squares fit does not compose, so aligning directly gave the pelvis 2.7 deg
        and the clavicles 2.3 deg more than the route through the humanoid (issue 21); through
        the one canonical rest, every path gives every joint the same rotation. Returns the
        turns applied, target joint -> (3, 3)."""
        turns = None
        if preset is not None and preset.name != UNITY.name:
            turns = self.humanoid_turns(source_rest_positions)
        if turns is None:
            turns = self.rest_turns(source_rest_positions)
        order = list(turns)
        self._rest_world[order] = np.array([turns[j] for j in order]) @ self._rest_world[order]
        self._right = None
        return turns

    def rest_turns(self, source_rest_positions: np.ndarray) -> dict[int, np.ndarray]:
        """The turn per mapped target joint that takes its rest bones onto the source's (see
        `align_rest`), without applying it."""
        src = (self.basis @ np.asarray(source_rest_positions, dtype=np.float64).T).T
        target_of = dict(zip(self.map_target.tolist(), self.map_source.tolist(), strict=True))
        mapped = set(target_of)
        nearest: dict[int, int] = {}  # target joint -> its nearest mapped ancestor
        for j in range(len(self.target_joints)):
            p = int(self.target_parents[j])
            while p >= 0 and p not in mapped:
                p = int(self.target_parents[p])
            nearest[j] = p
        turns: dict[int, np.ndarray] = {}
        for level in self.target_levels:
            for j in (int(x) for x in level if int(x) in mapped):
                pairs = []
                for c in (c for c in mapped if nearest[c] == j):
                    u = self._rest_positions[c] - self._rest_positions[j]
                    v = src[target_of[c]] - src[target_of[j]]
                    if np.linalg.norm(u) > 1e-9 and np.linalg.norm(v) > 1e-9:
                        pairs.append((u / np.linalg.norm(u), v / np.linalg.norm(v)))
                # The root (the pelvis) by all its children; the others by their nearest bone.
                turn = _fit_turn(pairs if nearest[j] < 0 else _nearest_pair(pairs))
                turns[j] = turn if turn is not None else turns.get(nearest[j], np.eye(3))
        return turns

    def humanoid_turns(self, source_rest_positions: np.ndarray) -> dict[int, np.ndarray] | None:
        """The rest turns of the route source -> T-posed humanoid -> target, or None when this
        map does not drive exactly the joints the humanoid's (UNITY) map drives.

        With A1 the source-to-humanoid basis, A2 the humanoid's (VMC's) and t1, t2 the two fits,
        the humanoid bone's world rotation is A1 W R^-1 A1^T t1 and the joint's
        A2 (that) A2^T t2 R_rest; with A = A2 A1 this is A W R^-1 A^T (A2 t1 A2^T t2) R_rest,
        so the joint's turn is A2 t1 A2^T t2."""
        joint_of = {s: j for s, j in zip(self.map_source, self.map_target, strict=True)}
        leaf = [j.rsplit("/", 1)[-1] for j in self.target_joints]
        humanoid = humanoid_rig()
        bone_of = {joint: bone for bone, joint in UNITY.bone_map.items()}
        wanted = {leaf[j] for j in joint_of.values()}
        if wanted != set(UNITY.bone_map.values()) or len(wanted) != len(joint_of):
            return None
        to_humanoid = {
            self.source_bones[s]: bone_of[leaf[j]] for s, j in joint_of.items()
        }  # source bone -> humanoid bone
        first = Retargeter(
            self.source_bones, self.source_parents, "local", humanoid.paths, humanoid.rest,
            to_humanoid, UNITY.basis.T @ self.basis,
        )  # fmt: skip
        t1 = first.rest_turns(source_rest_positions)
        bones = list(UNITY.bone_map)
        second = Retargeter(
            bones, UNITY.parents, "local", self.target_joints, self._rest_local, UNITY.bone_map,
            UNITY.basis,
        )  # fmt: skip
        t2 = second.rest_turns(np.array([UNITY.rest_positions[b] for b in bones]))
        a2 = second._a
        index = {path.rsplit("/", 1)[-1]: k for k, path in enumerate(humanoid.paths)}
        turns = {}
        for j in joint_of.values():
            t_h = t1.get(index[bone_of[leaf[j]]], np.eye(3))
            turns[j] = a2 @ t_h @ a2.T @ t2.get(j, np.eye(3))
        return turns

    def _compose_target(self, local: np.ndarray) -> np.ndarray:
        world = np.empty((len(local) + 1, 3, 3))
        world[-1] = np.eye(3)
        for level in self.target_levels:
            world[level] = world[self._parent_slot[level]] @ local[level]
        return world[:-1]

    def calibrate_rotations(self, rest_pose: np.ndarray | None) -> None:
        """Set the source's rest pose: (B, 4) rotations as the source sends them (None: identity)."""
        b = len(self.source_bones)
        rest = np.tile([1.0, 0.0, 0.0, 0.0], (b, 1)) if rest_pose is None else rest_pose
        rest = np.asarray(rest, dtype=np.float64)
        self.rest_pose = rest / np.linalg.norm(rest, axis=1, keepdims=True)
        self._source_rest_world = self._source_world(self.rest_pose)
        self._right = None

    def calibrate(self, pose: LivePose) -> np.ndarray:
        """Take `pose` (the performer in the skeleton's rest pose) as the rest pose; returns the
        (B, 4) rest rotations to store (restPose holds the mapped bones' rows, sourceBones order)."""
        self.calibrate_rotations(np.where(pose.valid[:, None], pose.rotations, [1.0, 0, 0, 0]))
        if pose.root_position is not None:
            self.rest_root = np.array(pose.root_position, dtype=np.float64)
        return self.rest_pose

    def _source_world(self, rotations: np.ndarray) -> np.ndarray:
        """(B, 4) source rotations -> (B, 3, 3) world rotation matrices."""
        m = matrix_from_quat(rotations)
        if self.space == "world":
            return m
        for level in self.source_levels[1:]:
            m[level] = m[self.source_parents[level]] @ m[level]
        return m

    def _mapped_world(self, rotations: np.ndarray) -> np.ndarray:
        """(B, 4) source rotations -> (M, 3, 3) world rotations of the mapped bones, composing
        only the bones they hang from."""
        m = _unit_matrices(rotations[self._need])
        if self.space != "world":
            for level in self._need_levels[1:]:
                m[level] = m[self._need_parents[level]] @ m[level]
        return m[self._map_in_need]

    def _desired(self, rotations: np.ndarray) -> np.ndarray:
        """(M, 3, 3) each mapped joint's desired world rotation: A W R_src^-1 A^T R_target,
        with everything right of W fixed per calibration."""
        if self._right is None:
            rest_inverse = np.swapaxes(self._source_rest_world[self.map_source], 1, 2)
            self._right = rest_inverse @ self._a.T @ self._rest_world[self.map_target]
        return self._a @ self._mapped_world(rotations) @ self._right

    def _structure_for(self, received: np.ndarray) -> tuple:
        """(pair rows, mapped joints, their parent slots, free joints per level) for a mask of
        received mapped bones, cached: the mask rarely changes once every bone has arrived."""
        key = received.tobytes()
        found = self._structure.get(key)
        if found is None:
            n = len(self.target_joints)
            mapped = np.zeros(n, dtype=bool)
            mapped[self.map_target[received]] = True
            # The last pair for a joint wins (as a fancy-index assignment would).
            last = np.full(n, -1)
            last[self.map_target[received]] = np.flatnonzero(received)
            joints = np.flatnonzero(mapped)
            free = [level[~mapped[level]] for level in self.target_levels]
            found = (last[joints], joints, self._parent_slot[joints], [f for f in free if len(f)])
            if len(self._structure) > 64:  # bounded: masks of a source whose bones trickle in
                self._structure.clear()
            self._structure[key] = found
        return found

    def apply(self, stage_local: np.ndarray, pose: LivePose) -> np.ndarray:
        """Merge `pose` into the stage's (J, 4, 4) local transforms (row-vector, as
        UsdSkel gives them); returns new (J, 4, 4) transforms. Joints without a source, or whose
        source bone never arrived, keep the stage's values; pose.weight blends live and stage."""
        stage_local = np.asarray(stage_local, dtype=np.float64)
        out = stage_local.copy()
        if pose.weight <= 0:
            return out
        # Row-vector layout: the upper 3x3 is S R^T, its rows the scaled axes.
        row_scale = np.linalg.norm(stage_local[:, :3, :3], axis=2)
        stage_rot = np.swapaxes(stage_local[:, :3, :3] / row_scale[:, :, None], 1, 2)
        if self.space == "additive":
            return self._apply_additive(out, stage_rot, row_scale, pose)
        rows, joints, parent_slots, free_levels = self._structure_for(pose.valid[self.map_source])
        desired = self._desired(pose.rotations)[rows]
        # Final world rotations: mapped joints take the desired ones; the others chain the
        # stage's local rotation onto their parent's final world, level by level.
        world = np.empty((len(self.target_joints) + 1, 3, 3))  # per call: the take thread
        world[-1] = np.eye(3)  # merges poses too
        world[joints] = desired
        for free in free_levels:
            world[free] = world[self._parent_slot[free]] @ stage_rot[free]
        live = np.swapaxes(world[parent_slots], 1, 2) @ desired
        if pose.weight < 1:
            q = quat_slerp(quat_from_matrix(stage_rot[joints]), quat_from_matrix(live), pose.weight)
            live = matrix_from_quat(q)
        out[joints, :3, :3] = np.swapaxes(live, 1, 2) * row_scale[joints][:, :, None]
        if self.root_motion and pose.root_position is not None:
            if self.rest_root is None:
                self.rest_root = np.array(pose.root_position, dtype=np.float64)  # start = here
            root = self.target_root
            move = self.basis @ (pose.root_position - self.rest_root) * self.scale
            live_t = self._rest_t[root] + move
            out[root, 3, :3] = (1 - pose.weight) * stage_local[root, 3, :3] + pose.weight * live_t
        return out

    def _apply_additive(
        self, out: np.ndarray, stage_rot: np.ndarray, row_scale: np.ndarray, pose: LivePose
    ) -> np.ndarray:
        """Additive sources (game controllers): each mapped joint's stage rotation turned by the
        source's rotation in the joint's own frame, scaled by the weight."""
        received = pose.valid[self.map_source]
        targets = self.map_target[received]
        offsets = pose.rotations[self.map_source[received]]
        if pose.weight < 1:
            offsets = quat_slerp(np.array([1.0, 0.0, 0.0, 0.0]), offsets, pose.weight)
        live = stage_rot[targets] @ (self._a @ matrix_from_quat(offsets) @ self._a.T)
        out[targets, :3, :3] = np.swapaxes(live, 1, 2) * row_scale[targets][:, :, None]
        return out


def _unit_matrices(q: np.ndarray) -> np.ndarray:
    """(k, 4) quaternions (w, x, y, z) -> (k, 3, 3) rotation matrices: sdk.rotations'
    matrix_from_quat without its stacking (the per-frame hot path: three times faster)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    m = np.empty((len(q), 3, 3))
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    m[:, 0, 0] = 1 - 2 * (yy + zz)
    m[:, 0, 1] = 2 * (xy - wz)
    m[:, 0, 2] = 2 * (xz + wy)
    m[:, 1, 0] = 2 * (xy + wz)
    m[:, 1, 1] = 1 - 2 * (xx + zz)
    m[:, 1, 2] = 2 * (yz - wx)
    m[:, 2, 0] = 2 * (xz - wy)
    m[:, 2, 1] = 2 * (yz + wx)
    m[:, 2, 2] = 1 - 2 * (xx + yy)
    return m


def blend_transforms(a: np.ndarray, b: np.ndarray, weight: float) -> np.ndarray:
    """(J, 4, 4) row-vector local transforms a and b blended by `weight` in [0, 1]: rotations
    slerped, translations and scales interpolated linearly (as UsdSkel interpolates samples)."""
    if weight <= 0:
        return a
    return fade_transforms(a, b, weight)[0]  # from the start: the short arc


def fade_transforms(
    a: np.ndarray, b: np.ndarray, weight: float, arcs: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The blend of `blend_transforms` for a fade whose ends move from call to call: each
    joint turns from a towards b along the arc it took in the last call (`arcs`, (J, 4) its
    turns a^-1 b then; None: the short arc), so a b that turns through the rotation opposite
    a keeps the blend turning the way it went instead of flipping to the other short arc (a
    pop of up to 180 deg times the weight in one tick). Returns the blend and the arcs for
    the next call."""
    scale_a = np.linalg.norm(a[:, :3, :3], axis=2)
    scale_b = np.linalg.norm(b[:, :3, :3], axis=2)
    qa = quat_from_matrix(np.swapaxes(a[:, :3, :3] / scale_a[:, :, None], 1, 2))
    qb = quat_from_matrix(np.swapaxes(b[:, :3, :3] / scale_b[:, :, None], 1, 2))
    turn = quat_multiply(qa * [1.0, -1.0, -1.0, -1.0], qb)  # a^-1 b: unit, so conj = inverse
    side = turn[:, 0] if arcs is None else np.sum(turn * arcs, axis=1)
    turn = np.where(side[:, None] < 0, -turn, turn)  # w < 0: past half a turn, the long way
    sine = np.linalg.norm(turn[:, 1:], axis=1)
    half = np.arctan2(sine, turn[:, 0]) * weight  # the half angle, 0..pi, times the weight
    axis = turn[:, 1:] / np.maximum(sine, 1e-12)[:, None]
    part = np.concatenate([np.cos(half)[:, None], axis * np.sin(half)[:, None]], axis=1)
    rotation = np.swapaxes(matrix_from_quat(quat_multiply(qa, part)), 1, 2)
    scale = (1 - weight) * scale_a + weight * scale_b
    out = a.copy()
    out[:, :3, :3] = rotation * scale[:, :, None]
    out[:, 3, :3] = (1 - weight) * a[:, 3, :3] + weight * b[:, 3, :3]
    return out, turn


def _nearest_pair(
    pairs: list[tuple[np.ndarray, np.ndarray]],
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The one (u, v) of `pairs` whose smallest turn is the smallest (the neck, not a clavicle,
    for the chest)."""
    return sorted(pairs, key=lambda p: -float(np.dot(p[0], p[1])))[:1]


def _fit_turn(pairs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    """The rotation R that best takes unit directions u onto v (least squares over the pairs,
    Kabsch's SVD solution; reflection excluded); for one pair, or directions all parallel,
    the smallest turn (`_swing`); None without pairs."""
    if not pairs:
        return None
    u = np.array([p[0] for p in pairs])
    v = np.array([p[1] for p in pairs])
    if len(pairs) == 1 or np.linalg.matrix_rank(u, tol=1e-6) < 2:
        return _swing(u[0], v[0])
    left, _, right = np.linalg.svd(v.T @ u)
    d = np.sign(np.linalg.det(left @ right)) or 1.0
    return left @ np.diag([1.0, 1.0, d]) @ right


def _swing(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking direction u to direction v."""
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    axis = np.cross(u, v)
    s, c = np.linalg.norm(axis), float(np.dot(u, v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Opposite: a half turn about any axis perpendicular to u.
        perp = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        perp /= np.linalg.norm(perp)
        return 2.0 * np.outer(perp, perp) - np.eye(3)
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * (kx @ kx)


def _world_positions(
    rest_local: np.ndarray, levels: list[np.ndarray], parent_slot: np.ndarray
) -> np.ndarray:
    """(J, 3) rest positions from (J, 4, 4) row-vector parent-space transforms."""
    world = np.empty((len(rest_local) + 1, 4, 4))
    world[-1] = np.eye(4)
    for level in levels:
        world[level] = rest_local[level] @ world[parent_slot[level]]  # row vectors: local first
    return world[:-1, 3, :3]


def _rotations(transforms: np.ndarray) -> np.ndarray:
    """(J, 4, 4) row-vector transforms -> (J, 3, 3) column-vector rotations (scale removed)."""
    m = transforms[:, :3, :3]
    return np.swapaxes(m / np.linalg.norm(m, axis=2, keepdims=True), 1, 2)


def target_skeleton(skeleton_prim) -> tuple[tuple[str, ...], np.ndarray]:
    """A UsdSkel Skeleton's joint paths and (J, 4, 4) rest transforms (row-vector, parent space)."""
    from pxr import UsdSkel

    skeleton = UsdSkel.Skeleton(skeleton_prim)
    joints = tuple(str(j) for j in skeleton.GetJointsAttr().Get() or ())
    rest = skeleton.GetRestTransformsAttr().Get()
    if not joints or rest is None or len(rest) != len(joints):
        raise RetargetError(
            f"Skeleton {skeleton_prim.GetPath()} has no restTransforms for its {len(joints)} "
            "joints.",
            "author restTransforms (one parent-space matrix per joint).",
        )
    return joints, np.array(rest, dtype=np.float64)


def source_hierarchy(source, preset: Preset) -> np.ndarray:
    """Parent index per source bone: the BVH's own hierarchy where the source has one (BVH
    stream, replay), else the preset's (VMC's HumanBodyBones); -1 for roots."""
    decoder = getattr(source, "decoder", None)
    skeleton = getattr(decoder, "skeleton", None)
    parents = getattr(source, "parents", ()) or (skeleton.parents if skeleton else ())
    if parents:
        return np.asarray(parents, dtype=np.int64)
    return _parent_indices(source.bones, preset.parents)


@dataclass(frozen=True)
class HumanoidRig:
    """The canonical T-posed humanoid: the HumanBodyBones that the unity preset maps, rest
    locals identity (VRM's normalised rest, what VMC receivers assume), in VmcDecoder's frame."""

    paths: tuple[str, ...]
    """Joint paths ("Hips/Spine/..."), parents before children."""
    rest: np.ndarray
    """(H, 4, 4) row-vector rest locals: identity rotations, the T-pose's bone offsets."""


def humanoid_rig() -> HumanoidRig:
    """The humanoid `live send` streams and every preset's rest is aligned through."""
    mapped = set(UNITY.bone_map)
    humanoid = [b for b in HUMAN_BODY_BONES if b in mapped]
    paths = {}
    for bone in humanoid:  # parents are in the map too (the 22 mapped bones form one tree)
        chain, b = [bone], UNITY.parents.get(bone)
        while b is not None and b in UNITY.parents:
            if b in humanoid:
                chain.append(b)
            b = UNITY.parents.get(b)
        paths[bone] = "/".join(reversed(chain))
    order = sorted(humanoid, key=lambda b: paths[b].count("/"))
    tpose = UNITY.rest_positions
    rest = np.tile(np.eye(4), (len(order), 1, 1))
    for k, bone in enumerate(order):
        parent = paths[bone].rsplit("/", 2)[-2] if "/" in paths[bone] else None
        origin = np.array(tpose[parent]) if parent else np.zeros(3)
        rest[k, 3, :3] = np.array(tpose[bone]) - origin
    return HumanoidRig(tuple(paths[b] for b in order), rest)

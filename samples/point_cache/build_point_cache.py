"""Bake the sample character as a production rig delivers it: point caches and controls (issue 36).

From the committed sample character (`samples/character/sample_character.usda`) it bakes, at
every frame of its clips, the body posed with two deformations that linear blend skinning
cannot express, each a pure function of the pose and several centimetres large:

- **a biceps bulge with elbow flexion**: the front of each upper arm (the side the forearm
  folds towards, found from the clips) swells along its radial direction by up to BULGE_CM at
  full flexion, peaking mid-bone (a muscle: no skin weights give a bulge that grows with
  another joint's angle);
- **a twist that keeps the limb's volume**: a joint's twist about its bone (the upper arm's
  relative to the clavicle, which the wave clip turns by 90 degrees; the hand's relative to
  the forearm, which the clips never turn, so the forearm's stays LBS's) is spread along the
  limb, each cross-section turned rigidly by its share (0 at the parent's end, all of it at
  the child's), where LBS blends the two joints' matrices and shrinks the cross-section (the
  candy-wrapper).

How: the skeleton's twists are taken out (their joints and everything below turned back about
the bone), the body skinned by LBS in that untwisted pose (no candy-wrapper: nothing twists),
the bulge added, then each vertex turned back about the bone by its share of the twist, the
share a smooth function over the mesh (its skin weights on the limb times the smoothstep of its
position along the bone): without flexion and twist the bake is LBS exactly.

It writes `point_cache_character.usdc`, a layer over the sample character whose body is a
point cache (its `points` time-sampled, its skinning primvars blocked: nothing skins it) and
whose SkelAnimation keeps the baked frames only (the skeleton's joints are the rig's joints),
and the shot `point_cache.usda` (the previs set, camera, lights and capture ring, as
samples/film_character's shot) whose character declares the cache (RigspacePointCacheAPI)
and, as controls (RigspaceControlAPI), the deformations' drivers that the baked clips move:
`bicepsBulge_l`/`_r` (the bulge's share, 0-1) and `armTwist_l`/`_r` (the upper arm's twist,
degrees). The shot has no model yet: capture and train it (docs/point_caches.md). The output
folder defaults to `samples/point_cache/build` (ignored by git: the cache of all 1,620 frames
is about 220 MB).

    python samples/point_cache/build_point_cache.py [--out DIR] [--frames A:B] [--every N]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom, UsdSkel, Vt

HERE = Path(__file__).resolve().parent
SAMPLES = HERE.parent
BASE = SAMPLES / "character" / "sample_character.usda"
PREVIS = SAMPLES / "scenes" / "previs.usda"
USD_NAME = "point_cache_character.usdc"
SCENE_NAME = "point_cache.usda"
RERIG_NAME = "rerig.usda"
SIDES = ("l", "r")

BULGE_CM = 4.0
"""The bulge's height at full flexion, centimetres (the sample's upper arm is about 5 cm in
radius): several centimetres, far beyond what a re-rig's LBS error hides."""
FULL_FLEXION_DEG = 120.0
"""Elbow flexion at which the bulge is full (smoothstep from straight)."""
BULGE_CENTRE, BULGE_SPREAD = 0.55, 0.22
"""Where along the upper arm the bulge peaks (fraction of the bone) and its Gaussian width."""
CONTROL_STILL = 1e-3
"""A control that moves less than this over the baked frames is not authored."""
CONTROL_RANGES = {"bicepsBulge": (0, 1), "armTwist": (-180, 180), "forearmTwist": (-180, 180)}


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _turn(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about the unit `axis` by `angles` radians (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


class Segment:
    """A limb segment (an upper arm, a forearm): its joint, its bone's axis and length in the
    joint's bind frame, and every body vertex's share s of the way along it (0 at the joint, 1
    at its child; below 0 and above 1 off its ends) and unit radial direction there."""

    def __init__(self, joint: int, child: int, bind: np.ndarray, rest: np.ndarray) -> None:
        self.joint, self.child = joint, child
        to_local = np.linalg.inv(bind[joint])
        tip = to_local[:3, :3] @ bind[child][:3, 3] + to_local[:3, 3]
        self.length = float(np.linalg.norm(tip))
        self.axis = tip / self.length
        """The bone's direction in the joint's own frame (the sample's right arm runs along
        -X: its bind frame is the left's mirrored)."""
        local = rest @ to_local[:3, :3].T + to_local[:3, 3]
        along = local @ self.axis
        self.s = along / self.length
        radial = local - along[:, None] * self.axis
        self.radial = radial / np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)

    def direction(self, world: np.ndarray) -> np.ndarray:
        """The bone's world direction in the (column-vector) joint transforms `world`."""
        return world[self.joint][:3, :3] @ self.axis


def twist(
    world: np.ndarray, bind: np.ndarray, driver: int, reference: int, axis: np.ndarray
) -> float:
    """Radians `driver` turns about its own bone `axis` (its frame) relative to `reference`,
    against the bind pose: the twist part (swing-twist) of its rotation."""
    r = (bind[reference][:3, :3].T @ bind[driver][:3, :3]).T @ (
        world[reference][:3, :3].T @ world[driver][:3, :3]
    )
    w = np.sqrt(max(1.0 + np.trace(r), 1e-12)) / 2.0
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (4.0 * w)
    return float(2.0 * np.arctan2(v @ axis, w))


def turn_about(world: np.ndarray, joint: int, axis: np.ndarray, angle: float) -> np.ndarray:
    """(4, 4) the rigid turn by `angle` radians about a joint's bone (`axis` in its frame),
    through the joint, in the space of `world`."""
    direction = world[joint][:3, :3] @ axis
    pivot = world[joint][:3, 3]
    out = np.eye(4)
    out[:3, :3] = _turn(direction / np.linalg.norm(direction), np.array([angle]))[0]
    out[:3, 3] = pivot - out[:3, :3] @ pivot
    return out


class Arm:
    """One arm: its segments, its joints' subtrees and its skin weights (module doc)."""

    def __init__(self, side: str, joints: list[str], bind: np.ndarray, weights: np.ndarray,
                 rest: np.ndarray) -> None:  # fmt: skip
        def index(name: str) -> int:
            return next(k for k, j in enumerate(joints) if j.endswith(f"/{name}_{side}"))

        def below(joint: int) -> list[int]:
            return [
                k
                for k, j in enumerate(joints)
                if j == joints[joint] or j.startswith(joints[joint] + "/")
            ]

        self.side = side
        self.bind = bind
        self.clavicle, upper, lower, hand = (
            index(n) for n in ("clavicle", "upperarm", "lowerarm", "hand")
        )
        self.upper = Segment(upper, lower, bind, rest)
        self.lower = Segment(lower, hand, bind, rest)
        self.hand = hand
        self.upper_tree, self.hand_tree = below(upper), below(hand)
        self.upper_share = weights[:, self.upper_tree].sum(axis=1)
        """Each vertex's skin weight on the upper arm and below: the twist's reach."""
        self.forearm_share = weights[:, below(lower)].sum(axis=1)
        self.biceps = weights[:, upper] * np.exp(
            -(((self.upper.s - BULGE_CENTRE) / BULGE_SPREAD) ** 2)
        )
        """The bulge's profile: the upper arm's skin weight, peaking mid-bone."""
        self.front = np.array([0.0, 0.0, 1.0])
        """The biceps' side in the upper arm's bind frame (`find_front`)."""

    def flexion(self, world: np.ndarray) -> float:
        """Degrees between the upper arm's and the forearm's bones."""
        a, b = self.upper.direction(world), self.lower.direction(world)
        return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))

    def arm_twist(self, world: np.ndarray) -> float:
        """Degrees the upper arm turns about its bone relative to the clavicle."""
        return float(
            np.degrees(twist(world, self.bind, self.upper.joint, self.clavicle, self.upper.axis))
        )

    def wrist_twist(self, world: np.ndarray) -> float:
        """Degrees the hand turns about the forearm's bone relative to the forearm."""
        axis = (
            self.bind[self.hand][:3, :3].T @ self.bind[self.lower.joint][:3, :3] @ self.lower.axis
        )
        return float(np.degrees(twist(world, self.bind, self.hand, self.lower.joint, axis)))

    def find_front(self, worlds: list[np.ndarray]) -> None:
        """The biceps' side: where the forearm points in the upper arm's frame, over the frames
        where the elbow bends (the side it folds towards), less its part along the bone."""
        folds = []
        for world in worlds:
            if self.flexion(world) > 20.0:
                local = world[self.upper.joint][:3, :3].T @ self.lower.direction(world)
                folds.append(local - (local @ self.upper.axis) * self.upper.axis)
        direction = np.mean(folds, axis=0) if folds else np.zeros(3)
        norm = np.linalg.norm(direction)
        if norm > 1e-6:
            self.front = direction / norm

    def bulge_amount(self, world: np.ndarray) -> float:
        """The bulge's share (0-1) at this pose: smoothstep of the flexion."""
        return float(_smoothstep(np.array(self.flexion(world) / FULL_FLEXION_DEG)))

    def untwist(self, world: np.ndarray) -> tuple[np.ndarray, float, float]:
        """The joint transforms with the hand's and the upper arm's twists taken out (each
        turned back about its bone with everything below it), and the two twists (radians)."""
        hand, upper = np.radians(self.wrist_twist(world)), np.radians(self.arm_twist(world))
        world = world.copy()
        forearm_axis = self.lower.axis
        world[self.hand_tree] = (
            turn_about(world, self.lower.joint, forearm_axis, -hand) @ world[self.hand_tree]
        )
        world[self.upper_tree] = (
            turn_about(world, self.upper.joint, self.upper.axis, -upper) @ world[self.upper_tree]
        )
        return world, hand, upper

    def deform(self, points: np.ndarray, untwisted: np.ndarray, hand: float, upper: float) -> None:
        """`points` (the body skinned in the untwisted pose `untwisted`) bulged and turned back
        by each vertex's share of the twists, in place."""
        height = BULGE_CM * self.bulge_amount(untwisted) * self.biceps
        facing = np.clip(self.upper.radial @ self.front, 0.0, 1.0) ** 2
        outward = self.upper.radial @ untwisted[self.upper.joint][:3, :3].T
        points += outward * (height * facing)[:, None]
        for segment, share, angle in (
            (self.lower, self.forearm_share, hand),
            (self.upper, self.upper_share, upper),
        ):
            if abs(angle) < 1e-9:
                continue
            shares = share * _smoothstep(segment.s)
            turns = _turn(segment.direction(untwisted), angle * shares)
            pivot = untwisted[segment.joint][:3, 3]
            points[:] = np.einsum("nij,nj->ni", turns, points - pivot) + pivot
            # The forearm's turn moves the upper arm's frame's descendants only: later turns
            # act on the turned points, so the hand ends where the skeleton puts it.


def skin(rest: np.ndarray, weights: np.ndarray, world: np.ndarray, bind: np.ndarray) -> np.ndarray:
    """Linear blend skinning of `rest` (skeleton space, the bind pose) by dense `weights` (N, J)
    at column-vector joint transforms `world`: sum_j w_j world_j bind_j^-1 p (UsdSkel's)."""
    skinning = world @ np.linalg.inv(bind)
    used = np.flatnonzero(weights.any(axis=0))
    moved = np.einsum("jab,nb->nja", skinning[used][:, :3, :3], rest) + skinning[used][:, :3, 3]
    return np.einsum("nj,nja->na", weights[:, used], moved)


def _weights(binding: UsdSkel.BindingAPI, joints: int) -> np.ndarray:
    """(N, J) the body's skin weights, dense."""
    indices = binding.GetJointIndicesPrimvar()
    size = indices.GetElementSize()
    idx = np.array(indices.Get()).reshape(-1, size)
    wts = np.array(binding.GetJointWeightsPrimvar().Get(), dtype=np.float64).reshape(-1, size)
    dense = np.zeros((len(idx), joints))
    np.add.at(dense, (np.repeat(np.arange(len(idx)), size), idx.reshape(-1)), wts.reshape(-1))
    return dense / dense.sum(axis=1, keepdims=True)


def _usd_skinning(frames: np.ndarray) -> tuple:
    """The sample's stage and skinning cache (which the queries need alive), its skeleton
    query, the body's skinning query, joints, bind transforms
    (column-vector), rest points in skeleton space, skin weights, and the joints' skeleton-space
    transforms (column-vector) at each of `frames`."""
    base = Usd.Stage.Open(str(BASE))
    skeleton = UsdSkel.Skeleton(base.GetPrimAtPath("/Character/Skel"))
    body = base.GetPrimAtPath("/Character/Body")
    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(base.GetPrimAtPath("/Character")), Usd.TraverseInstanceProxies())
    skel_query = cache.GetSkelQuery(skeleton)
    skinning = cache.GetSkinningQuery(body)
    joints = [str(j) for j in skeleton.GetJointsAttr().Get()]
    bind = np.array(skeleton.GetBindTransformsAttr().Get()).transpose(0, 2, 1)
    rest = np.array(UsdGeom.Mesh(body).GetPointsAttr().Get(), dtype=np.float64)
    geom_bind = np.array(skinning.GetGeomBindTransform()).T
    rest = rest @ geom_bind[:3, :3].T + geom_bind[:3, 3]
    weights = _weights(UsdSkel.BindingAPI(body), len(joints))
    worlds = [
        np.array(skel_query.ComputeJointSkelTransforms(Usd.TimeCode(float(t)))).transpose(0, 2, 1)
        for t in frames
    ]
    return (base, cache), skel_query, skinning, joints, bind, rest, weights, worlds


def _usd_difference(skel_query, skinning, rest: np.ndarray, t: float, posed: np.ndarray) -> float:
    """The largest difference between this script's LBS and UsdSkel's at time t."""
    xforms = skel_query.ComputeSkinningTransforms(Usd.TimeCode(t))
    points = Vt.Vec3fArray.FromNumpy(rest.astype(np.float32))
    skinning.ComputeSkinnedPoints(xforms, points, Usd.TimeCode(t))
    return float(np.abs(np.array(points) - posed).max())


KINDS = {
    "bicepsBulge": Arm.bulge_amount,
    "armTwist": Arm.arm_twist,
    "forearmTwist": Arm.wrist_twist,
}
"""Each control kind and the Arm method that measures it in a pose."""


def _bake_pose(arms, rest, weights, world, bind, values: dict) -> np.ndarray:
    """One pose baked: its twists taken out, skinned, bulged and twisted back; the pose's
    control values appended to `values`."""
    untwisted = world
    twists = []
    for arm in arms:
        for kind, measure in KINDS.items():
            values[f"{kind}_{arm.side}"].append(measure(arm, world))
        untwisted, hand, upper = arm.untwist(untwisted)
        twists.append((hand, upper))
    points = skin(rest, weights, untwisted, bind)
    for arm, (hand, upper) in zip(arms, twists, strict=True):
        arm.deform(points, untwisted, hand, upper)
    return points


def bake(frames: np.ndarray) -> dict:
    """The body's LBS and baked points (F, N, 3) in skeleton space, the controls per frame and
    what a bake measures: the deformations' largest offset from LBS (cm), and the largest
    difference between this script's LBS and UsdSkel's (the check that its skinning is
    UsdSkel's)."""
    from tqdm import tqdm

    _alive, skel_query, skinning, joints, bind, rest, weights, worlds = _usd_skinning(frames)
    arms = [Arm(side, joints, bind, weights, rest) for side in SIDES]
    for arm in arms:
        arm.find_front(worlds)
    values: dict[str, list[float]] = {f"{kind}_{a.side}": [] for kind in KINDS for a in arms}
    lbs, baked = [], []
    for world in tqdm(worlds, unit="frame", desc="bake"):
        lbs.append(skin(rest, weights, world, bind))
        baked.append(_bake_pose(arms, rest, weights, world, bind, values))
    # This LBS is UsdSkel's: checked on the first frame.
    usd_difference = _usd_difference(skel_query, skinning, rest, float(frames[0]), lbs[0])
    offsets = np.linalg.norm(np.array(baked) - np.array(lbs), axis=2)
    # A control that never moves over the bake cannot be learned (validation's
    # ControlConstant): only the ones the clips move are authored.
    controls = {k: np.array(v) for k, v in values.items() if np.ptp(v) > CONTROL_STILL}
    return {
        "lbs": np.array(lbs),
        "baked": np.array(baked),
        "controls": controls,
        "still": [k for k in values if k not in controls],
        "largest_offset_cm": float(offsets.max()),
        "usd_difference": usd_difference,
        "frames": frames,
        "arms": arms,
        "rest": rest,
    }


def write_character(out: Path, baked: dict) -> Path:
    """The layer over the sample character: the body a point cache, the animation trimmed to
    the baked frames."""
    path = out / USD_NAME
    stage = Usd.Stage.CreateNew(str(path))
    base = Usd.Stage.Open(str(BASE))
    for key in ("metersPerUnit", "upAxis", "timeCodesPerSecond", "framesPerSecond"):
        stage.SetMetadata(key, base.GetMetadata(key))
    frames = baked["frames"]
    stage.SetStartTimeCode(float(frames[0]))
    stage.SetEndTimeCode(float(frames[-1]))
    character = stage.DefinePrim("/Character")
    character.GetReferences().AddReference(Path(os.path.relpath(BASE, out.resolve())).as_posix())
    stage.SetDefaultPrim(character)
    body = UsdGeom.Mesh(stage.OverridePrim("/Character/Body"))
    points = body.CreatePointsAttr()
    for t, p in zip(frames, baked["baked"], strict=True):
        points.Set(Vt.Vec3fArray.FromNumpy(p.astype(np.float32)), Usd.TimeCode(float(t)))
    binding = UsdSkel.BindingAPI(body.GetPrim())
    for primvar in (
        binding.CreateJointIndicesPrimvar(False, 4),
        binding.CreateJointWeightsPrimvar(False, 4),
    ):
        primvar.GetAttr().Block()  # nothing skins the cache
    anim = UsdSkel.Animation(stage.OverridePrim("/Character/Skel/Anim"))
    anim0 = UsdSkel.Animation(base.GetPrimAtPath("/Character/Skel/Anim"))
    for name in ("rotations", "translations"):
        source, target = (
            anim0.GetPrim().GetAttribute(name),
            anim.GetPrim().CreateAttribute(name, anim0.GetPrim().GetAttribute(name).GetTypeName()),
        )
        for t in frames:  # a stronger layer's samples replace the sample's: the baked frames only
            target.Set(source.Get(float(t)), Usd.TimeCode(float(t)))
    stage.GetRootLayer().Save()
    return path


HELD_OUT_CLIP = "walk"
"""The clip held out of training. Not the previs shot's wave: the wave clip turns the upper arms
by up to 90 degrees, the largest departure from LBS in the clips, so it is trained on (held
out, the training clips would depart from LBS by under a pixel a sample); the walk, whose arms
swing with little flexion or twist, is held out instead."""


def _shot_text(clips: list[tuple[str, float, float]]) -> str:
    """The previs shot's text with the capture ring's clips cut to the baked frames and
    HELD_OUT_CLIP held out (when baked), no model yet; its character's reference unchanged."""
    text = PREVIS.read_text()
    text = text.replace(
        "        # Trained on this scene's capture: `rigspace train /tmp/sample_ds --out samples/models/sample`\n"
        "        uniform asset rigspace:model = @../models/sample@\n",
        "        # No model yet: capture and train this shot (docs/point_caches.md)\n",
    )
    names = ", ".join(f'"{n}"' for n, _, _ in clips)
    ranges = ", ".join(f"({a:g}, {b:g})" for _, a, b in clips)
    text = text.replace(
        '        uniform token[] rigspace:captureRing:clipNames = ["walk", "wave", "stretch", "roll", "yoga"]\n'
        "        uniform float2[] rigspace:captureRing:clipRanges = [(0, 359), (360, 599), (600, 959), (960, 1259), (1260, 1619)]\n",
        f"        uniform token[] rigspace:captureRing:clipNames = [{names}]\n"
        f"        uniform float2[] rigspace:captureRing:clipRanges = [{ranges}]\n",
    )
    held_out = (
        f'        uniform token[] rigspace:captureRing:heldOutClips = ["{HELD_OUT_CLIP}"]\n'
        if HELD_OUT_CLIP in {n for n, _, _ in clips}
        else ""
    )
    return text.replace(
        '        uniform token[] rigspace:captureRing:heldOutClips = ["wave"]\n', held_out
    )


def write_scene(out: Path, baked: dict, clips: list[tuple[str, float, float]]) -> Path:
    """The previs shot around the baked character, with its point cache and controls and the
    capture ring's clips cut to the baked frames."""
    text = _shot_text(clips).replace("@../character/sample_character.usda@", f"@./{USD_NAME}@")
    controls = baked["controls"]
    applied = ", ".join(f'"RigspaceControlAPI:{name}"' for name in controls)
    text = text.replace(
        '        prepend apiSchemas = ["RigspaceCaptureRingAPI", "RigspaceLiveBindingAPI:suit"]\n',
        '        prepend apiSchemas = ["RigspaceCaptureRingAPI", "RigspaceLiveBindingAPI:suit", '
        f'"RigspacePointCacheAPI", {applied}]\n',
    )
    frames = baked["frames"]
    lines = [
        "\n        # The point cache (docs/point_caches.md): the body as the rig evaluated it\n",
        "        rel rigspace:pointCache:meshes = </World/Hero/Asset/Body>\n",
    ]
    for name, values in controls.items():
        low, high = CONTROL_RANGES[name.rsplit("_", 1)[0]]
        samples = ", ".join(f"{t:g}: {v:.4f}" for t, v in zip(frames, values, strict=True))
        lines.append(f"        uniform float2 rigspace:control:{name}:range = ({low}, {high})\n")
        lines.append(f"        float rigspace:control:{name}:value.timeSamples = {{ {samples} }}\n")
    anchor = "        uniform int rigspace:captureRing:heldOutViewsPerRing = 4\n"
    text = text.replace(anchor, anchor + "".join(lines))
    text = text.replace(
        "Previs: the sample character",
        "Point cache: the sample character baked as point caches with its controls",
        1,
    )
    path = out / SCENE_NAME
    path.write_text(text)
    return path


def write_rerig_scene(out: Path, clips: list[tuple[str, float, float]]) -> Path:
    """The re-rig's shot: the same shot, ring and clips around the sample character as UsdSkel
    skins it (LBS: what moving the rig to a game engine's deformers gives), whose capture is
    the twin of the cached character's, sample for sample (apps/rerig_report.py)."""
    base = os.path.relpath(BASE, out).replace(os.sep, "/")
    text = _shot_text(clips).replace("@../character/sample_character.usda@", f"@{base}@")
    text = text.replace(
        "Previs: the sample character",
        "Re-rig: the sample character skinned by LBS, the point cache shot's twin",
        1,
    )
    path = out / RERIG_NAME
    path.write_text(text)
    return path


def clip_ranges(frames: np.ndarray) -> list[tuple[str, float, float]]:
    """The sample's clips cut to the baked frames (a clip with none is left out)."""
    base = Usd.Stage.Open(str(BASE))
    clips = base.GetPrimAtPath("/Character/Skel/Anim").GetCustomDataByKey("rigspace:clips")
    out = []
    for name, (first, last) in sorted(clips.items(), key=lambda c: c[1][0]):
        inside = frames[(frames >= first) & (frames <= last)]
        if len(inside):
            out.append((name, float(inside[0]), float(inside[-1])))
    return out


def build(out: Path, first: int = 0, last: int = 1619, every: int = 1) -> dict:
    """Bake frames first..last (every `every`th) into `out`; returns what was built."""
    start = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    frames = np.arange(first, last + 1, every, dtype=np.float64)
    baked = bake(frames)
    usd = write_character(out, baked)
    clips = clip_ranges(frames)
    scene = write_scene(out, baked, clips)
    rerig = write_rerig_scene(out, clips)
    return {
        "usd": str(usd),
        "scene": str(scene),
        "rerig": str(rerig),
        "frames": len(frames),
        "largest_offset_cm": round(baked["largest_offset_cm"], 2),
        "controls": list(baked["controls"]),
        "seconds": round(time.monotonic() - start, 1),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(HERE / "build"), help="folder for the cache and shot")
    parser.add_argument("--frames", default="0:1619", help="time codes A:B to bake (inclusive)")
    parser.add_argument("--every", type=int, default=1, help="bake every Nth frame")
    args = parser.parse_args(argv)
    first, last = (int(v) for v in args.frames.split(":"))
    built = build(Path(args.out), first, last, args.every)
    print(
        f"baked {built['frames']} frames into {built['usd']} in {built['seconds']} s: the "
        f"deformations move the body up to {built['largest_offset_cm']} cm from LBS; controls "
        f"{', '.join(built['controls'])}; shot {built['scene']}, its LBS re-rig {built['rerig']}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A tiny character whose rig is not UsdSkel's, written on the fly with usd-core.

An 'arm' (a cylinder 2 units tall along Y) delivered as a point cache: its points are
time-sampled at time codes 0-12, computed here by a rig of our own (the lower half stays, the
upper half bends about the elbow by the elbow's angle, and a bulge `bulge` pushes the points
around the elbow outwards), never skinned. A Skeleton (root, root/elbow) whose SkelAnimation
gives the elbow's rotation at the same time codes is the rig's joints (it skins nothing),
and one named float control `bulge` (RigspaceControlAPI, range (0, 1)) is the bulge's
amount, which moves apart from the elbow's angle. A RigspaceNeuralCharacter with a capture
ring frames it.

`broken` makes one malformed case at a time, for the validation's rules:
- "frames": the cache has one frame more than the skeleton animation and the control;
- "points": one cached frame has a point fewer (another topology);
- "nan": one cached frame has a NaN point;
- "constant": the control is authored at every frame but never moves.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

import rigspace.sdk  # noqa: F401  (schemas registered before the stage is made)
from tests.blendshapes import cylinder, two_joint_asset
from tests.materials import CHARACTER as CHARACTER  # the character prim (re-exported)
from tests.materials import add_character, use_model

SEGMENTS, RINGS, HEIGHT, RADIUS = 12, 8, 2.0, 0.35
JOINTS = ["root", "root/elbow"]
FRAMES = 13
MESH = "/World/Asset/Arm"
CONTROL = "bulge"


def elbow_angle(t: float) -> float:
    """Degrees the elbow bends (about X) at time code t."""
    return 50.0 * np.sin(np.pi * t / (FRAMES - 1))


def bulge_at(t: float) -> float:
    """The control's value at time code t: a ramp that moves apart from the elbow's angle."""
    return float(t) / (FRAMES - 1)


def arm_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The arm's rest points and quads (a cylinder of this module's size)."""
    return cylinder(SEGMENTS, RINGS, HEIGHT, RADIUS)


def cached_points(rest: np.ndarray, t: float, bulge: bool = True) -> np.ndarray:
    """The rig's points at time code t: the upper half bent about the elbow (y = 1), and the
    ring around the elbow pushed out by the bulge (not something the joints' skinning
    gives: it follows the control). Without `bulge`, the bend alone: the re-rig's points."""
    points = rest.astype(np.float64).copy()
    radial = points * np.array([1.0, 0.0, 1.0]) / RADIUS
    near = np.exp(-(((points[:, 1] - 1.0) / 0.3) ** 2))[:, None]
    points += 0.25 * bulge_at(t) * bulge * near * radial
    angle = np.radians(elbow_angle(t))
    c, s = np.cos(angle), np.sin(angle)
    upper = points[:, 1] > 1.0
    y, z = points[upper, 1] - 1.0, points[upper, 2]
    points[upper, 1], points[upper, 2] = 1.0 + c * y - s * z, s * y + c * z
    return points.astype(np.float32)


def write_point_cache_character(folder: Path, broken: str = "", bulge: bool = True) -> Path:
    """The scene (see the module doc) in `folder`; returns its path. Without `bulge` the
    cache holds the bend alone (what re-rigging the arm for a game engine gives)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "arm.usda"
    stage, skeleton, animation = two_joint_asset(path, JOINTS)
    rotations = animation.CreateRotationsAttr()
    for t in range(FRAMES):
        bend = Gf.Quatf(Gf.Rotation(Gf.Vec3d(1, 0, 0), elbow_angle(t)).GetQuat())
        rotations.Set(Vt.QuatfArray([Gf.Quatf(1), bend]), Usd.TimeCode(t))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()]
    )

    rest_points, faces = arm_mesh()
    mesh = UsdGeom.Mesh.Define(stage, MESH)
    mesh.CreateFaceVertexCountsAttr([4] * len(faces))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(faces.reshape(-1).tolist()))
    mesh.CreateSubdivisionSchemeAttr("none")
    mesh.CreateDisplayColorAttr([Gf.Vec3f(0.7, 0.5, 0.4)])
    points = mesh.CreatePointsAttr()
    cached = FRAMES + 1 if broken == "frames" else FRAMES
    for t in range(cached):
        frame = cached_points(rest_points, t, bulge)
        if broken == "points" and t == 5:
            frame = frame[:-1]
        if broken == "nan" and t == 7:
            frame[3, 1] = np.nan
        points.Set(Vt.Vec3fArray.FromNumpy(frame), Usd.TimeCode(t))

    character = add_character(stage, skeleton, "root/elbow", "flex", camera_distance=6.0)
    character.ApplyAPI("RigspacePointCacheAPI")
    character.CreateRelationship("rigspace:pointCache:meshes").SetTargets([Sdf.Path(MESH)])
    character.ApplyAPI("RigspaceControlAPI", CONTROL)
    value = character.CreateAttribute(f"rigspace:control:{CONTROL}:value", Sdf.ValueTypeNames.Float)
    character.CreateAttribute(f"rigspace:control:{CONTROL}:range", Sdf.ValueTypeNames.Float2).Set(
        Gf.Vec2f(0.0, 1.0)
    )
    for t in range(FRAMES):
        value.Set(0.5 if broken == "constant" else bulge_at(t), Usd.TimeCode(t))
    stage.GetRootLayer().Save()
    return path


_trained: dict[str, Path] = {}


def trained_arm(tmp_path_factory) -> tuple[Path, Path]:
    """(scene, bundle): the arm captured by `rigspace capture` (4 views, 16x16, every frame,
    --workers 1) and trained by `rigspace train --preset tiny --steps 3 --no-int8` (at 16x16),
    once per test session; the scene's character uses the bundle. Three steps teach the
    network nothing: the tests check what flows, not what it learned."""
    if "arm" not in _trained:
        from rigspace.sdk.cli import main

        root = tmp_path_factory.mktemp("arm_model")
        arm = write_point_cache_character(root / "scene")
        capture = ["capture", str(arm), "--out", str(root / "ds"), "--views", "4",
                   "--resolution", "16", "--frames-per-item", "4", "--workers", "1"]  # fmt: skip
        assert main(capture) == 0
        train = ["train", str(root / "ds"), "--out", str(root / "bundle"), "--preset", "tiny",
                 "--steps", "3", "--no-int8", "--resolution", "16"]  # fmt: skip
        assert main(train) == 0
        use_model(arm, root / "bundle")
        _trained["arm"] = arm
    arm = _trained["arm"]
    return arm, arm.parent.parent / "bundle"

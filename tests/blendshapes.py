"""A small skinned character with UsdSkel blend shapes, written on the fly with usd-core.

A cylinder 'head' (2 units tall) skinned to a 2-joint neck chain, with three blend shapes on
it and one on a second mesh:

- `smile`: every point of the lower half pushed out, with an inbetween `half` at weight 0.5
  that bulges the other way (so an inbetween that were ignored would show);
- `blink`: a few points (sparse `pointIndices`) pulled in;
- `jawOpen`: the lowest ring dropped;
- `frown`: the mouth ring pulled down; the animation never names it (weight 0), so the
  capture ring draws it within its authored range (blendShapeNames/blendShapeRanges);
- `brow` on the second mesh (`Brow`, a small quad strip), which has its own blend shape list.

The SkelAnimation names its weights in another order than the meshes (`blendShapes` =
brow, jawOpen, smile, blink) and animates them over time codes 0-12, together with a neck bend;
`extra` names a weight no mesh has (harmless, as UsdSkel says). A RigspaceNeuralCharacter with
a capture ring frames it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdSkel, Vt

import rigspace.sdk  # noqa: F401  (schemas registered before the stage is made)
from tests.materials import CHARACTER as CHARACTER  # the character prim (re-exported)
from tests.materials import add_character, new_asset_stage, quad_mesh, use_model

SEGMENTS, RINGS, HEIGHT, RADIUS = 16, 8, 2.0, 0.5
JOINTS = ["neck", "neck/head"]
ANIMATED = ["brow", "jawOpen", "smile", "blink", "extra"]


def weights_at(t: float) -> list[float]:
    """The animation's weights (ANIMATED order) at time code t: each sweeps its own range."""
    s = t / 12.0
    return [s, 1.0 - s, 1.2 * s, 0.5 + 0.5 * np.sin(2 * t), 0.3]


def cylinder(
    segments: int = SEGMENTS, rings: int = RINGS, height: float = HEIGHT, radius: float = RADIUS
) -> tuple[np.ndarray, np.ndarray]:
    """(points, quads) of an open cylinder standing on y = 0 (the test characters' body)."""
    angle = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    levels = np.linspace(0, height, rings + 1)
    points = np.array(
        [(radius * np.sin(a), h, radius * np.cos(a)) for h in levels for a in angle], np.float32
    )
    faces = []
    for r in range(rings):
        for k in range(segments):
            a, b = r * segments + k, r * segments + (k + 1) % segments
            faces.append((a, b, b + segments, a + segments))
    return points, np.array(faces)


def _shape(stage, path, offsets, indices=None, inbetweens=()):
    shape = UsdSkel.BlendShape.Define(stage, path)
    shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(offsets, np.float32)))
    if indices is not None:
        shape.CreatePointIndicesAttr(Vt.IntArray([int(i) for i in indices]))
    for name, weight, values in inbetweens:
        inbetween = shape.CreateInbetween(name)
        inbetween.SetWeight(weight)
        inbetween.SetOffsets(Vt.Vec3fArray.FromNumpy(np.asarray(values, np.float32)))
    return shape


def _skin(stage, mesh, skeleton, points, split: float) -> None:
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    upper = np.clip((points[:, 1] - split + 0.4) / 0.8, 0, 1)
    weights = np.stack([1 - upper, upper], 1).astype(np.float32)
    binding.CreateJointIndicesPrimvar(False, 2).Set(Vt.IntArray([0, 1] * len(points)))
    binding.CreateJointWeightsPrimvar(False, 2).Set(Vt.FloatArray(weights.reshape(-1).tolist()))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))


def two_joint_asset(
    path: Path, joints: list[str]
) -> tuple[Usd.Stage, UsdSkel.Skeleton, UsdSkel.Animation]:
    """A new asset stage at `path` with a skeleton of two joints one unit apart up y and its
    animation's joints, translations and scales (the rotations are each character's)."""
    stage, skeleton = new_asset_stage(path)
    skeleton.CreateJointsAttr(joints)
    bind = [Gf.Matrix4d(1).SetTranslate(Gf.Vec3d(0, y, 0)) for y in (0.0, 1.0)]
    rest = [Gf.Matrix4d(1).SetTranslate(Gf.Vec3d(0, y, 0)) for y in (0.0, 1.0)]
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray(bind))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray(rest))
    animation = UsdSkel.Animation.Define(stage, "/World/Asset/Skel/Anim")
    animation.CreateJointsAttr(joints)
    animation.CreateTranslationsAttr(Vt.Vec3fArray([(0, 0, 0), (0, 1.0, 0)]))
    animation.CreateScalesAttr(Vt.Vec3hArray([(1, 1, 1)] * 2))
    return stage, skeleton, animation


def _add_brow(stage: Usd.Stage, skeleton: UsdSkel.Skeleton) -> None:
    """The second mesh, `Brow` (one quad above the eyes), skinned, with its own blend shape
    list: `brow`, which raises it."""
    brow_points = np.array(
        [(x, 1.8, 0.55) for x in (-0.3, 0.3)] + [(x, 1.9, 0.55) for x in (-0.3, 0.3)], np.float32
    )
    brow = quad_mesh(stage, "/World/Asset/Brow", brow_points, np.array([[0, 1, 3, 2]]))
    _skin(stage, brow, skeleton, brow_points, 1.0)
    _shape(stage, "/World/Asset/Brow/brow", np.tile([0.0, 0.15, 0.0], (4, 1)))
    binding = UsdSkel.BindingAPI(brow.GetPrim())
    binding.CreateBlendShapesAttr(["brow"])
    binding.CreateBlendShapeTargetsRel().SetTargets([Sdf.Path("/World/Asset/Brow/brow")])


def write_blendshape_character(folder: Path) -> Path:
    """The scene (see the module doc) in `folder`; returns its path."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "face.usda"
    stage, skeleton, animation = two_joint_asset(path, JOINTS)
    animation.CreateBlendShapesAttr(ANIMATED)
    rotations = animation.CreateRotationsAttr()
    weights = animation.CreateBlendShapeWeightsAttr()
    for t in range(13):
        bend = Gf.Quatf(Gf.Rotation(Gf.Vec3d(1, 0, 0), 3.0 * t).GetQuat())
        rotations.Set(Vt.QuatfArray([Gf.Quatf(1), bend]), Usd.TimeCode(t))
        weights.Set(Vt.FloatArray(weights_at(t)), Usd.TimeCode(t))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()]
    )

    points, faces = cylinder()
    mesh = quad_mesh(stage, "/World/Asset/Head", points, faces)
    mesh.CreateDisplayColorAttr([Gf.Vec3f(0.8, 0.6, 0.5)])
    _skin(stage, mesh, skeleton, points, 1.0)
    radial = points * np.array([1, 0, 1], np.float32) / RADIUS
    lower = (points[:, 1] < HEIGHT / 2).astype(np.float32)[:, None]
    eyes = np.flatnonzero((np.abs(points[:, 1] - 1.5) < 0.2) & (points[:, 2] > 0.2))
    jaw = np.arange(SEGMENTS)
    base = "/World/Asset/Head"
    _shape(
        stage, f"{base}/smile", 0.3 * radial * lower,
        inbetweens=[("half", 0.5, -0.2 * radial * lower)],
    )  # fmt: skip
    _shape(stage, f"{base}/blink", np.tile([0.0, -0.1, -0.15], (len(eyes), 1)), eyes)
    _shape(stage, f"{base}/jawOpen", np.tile([0.0, -0.4, 0.1], (len(jaw), 1)), jaw)
    mouth = np.arange(SEGMENTS, 2 * SEGMENTS)
    _shape(stage, f"{base}/frown", np.tile([0.0, -0.25, 0.0], (len(mouth), 1)), mouth)
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    on_head = ["smile", "blink", "jawOpen", "frown"]
    binding.CreateBlendShapesAttr(on_head)
    binding.CreateBlendShapeTargetsRel().SetTargets([Sdf.Path(f"{base}/{n}") for n in on_head])
    _add_brow(stage, skeleton)

    ranges = {
        "blendShapeNames": (Sdf.ValueTypeNames.TokenArray, ["frown", "smile"]),
        "blendShapeRanges": (Sdf.ValueTypeNames.Float2Array, [(0.2, 0.9), (0.0, 1.0)]),
    }
    add_character(stage, skeleton, "neck/head", "talk", ranges, camera_distance=5.0)
    stage.GetRootLayer().Save()
    return path


def add_face_binding(prim: Usd.Prim, port: int, timeout: float) -> None:
    """A VMC live binding `face` on the character prim, from 127.0.0.1:`port`: its neck and
    head by name (a face stream), lost after `timeout` seconds without data."""
    prim.ApplyAPI("RigspaceLiveBindingAPI", "face")
    for name, kind, value in (
        ("url", Sdf.ValueTypeNames.String, f"vmc://127.0.0.1:{port}"),
        ("sourceBones", Sdf.ValueTypeNames.TokenArray, ["Neck", "Head"]),
        ("targetJoints", Sdf.ValueTypeNames.TokenArray, ["neck", "head"]),
        ("timeoutSeconds", Sdf.ValueTypeNames.Float, timeout),
    ):
        prim.CreateAttribute(f"rigspace:live:face:{name}", kind).Set(value)


def send_face(port: int, weights: dict[str, float], t: float) -> None:
    """A VMC face frame as a sender written from the protocol sends it, with python-osc alone:
    the neck and head bones (Unity's frame: x, y, z then quaternion x, y, z, w), each blend
    shape's /VMC/Ext/Blend/Val, one /VMC/Ext/Blend/Apply, then /VMC/Ext/OK and /VMC/Ext/T."""
    from pythonosc.udp_client import SimpleUDPClient

    client = SimpleUDPClient("127.0.0.1", port)
    for bone in ("Neck", "Head"):
        client.send_message("/VMC/Ext/Bone/Pos", [bone, 0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 1.0])
    for name, value in weights.items():
        client.send_message("/VMC/Ext/Blend/Val", [name, float(value)])
    client.send_message("/VMC/Ext/Blend/Apply", [])
    client.send_message("/VMC/Ext/OK", [1])
    client.send_message("/VMC/Ext/T", [float(t)])


_trained: dict[str, Path] = {}


def trained_face(tmp_path_factory) -> tuple[Path, Path]:
    """(scene, bundle): the face captured small (4 views, 32x32) and trained with the tiny
    preset (about 20 s), once per test session; the scene's character uses the bundle."""
    if "face" not in _trained:
        from rigspace.capture.pipeline import capture
        from rigspace.capture.settings import CaptureOverrides
        from rigspace.train import loop
        from rigspace.train.config import preset
        from rigspace.train.export import export_bundle

        root = tmp_path_factory.mktemp("face_model")
        face = write_blendshape_character(root / "scene")
        small = CaptureOverrides(views=4, elevations=(0.0,), resolution=32, frames_per_item=4)
        capture(face, CHARACTER, root / "ds", small, workers=1, progress=False, warn=lambda _: None)
        result = loop.train(root / "ds", root / "run", preset("tiny"), progress=False)
        assert result.stopped == "done"
        export_bundle(root / "run", root / "bundle", int8=False)
        use_model(face, root / "bundle")
        _trained["face"] = face
    face = _trained["face"]
    return face, face.parent.parent / "bundle"

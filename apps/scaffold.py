"""`rigspace init ASSET --out SCENE.usda`: a shot scene around a raw rigged, animated character.

A character exported from a DCC (a .usdz, .usd, .usda or .usdc with a UsdSkel Skeleton, its
animation and skinned meshes) has no RigspaceNeuralCharacter prim, so capture has nothing to
capture. `init` writes a new scene that references the asset under a RigspaceNeuralCharacter
and derives every value from the asset, printing each with how it was found:

- the skeleton (the only one, or `--skeleton PATH` among several: the error lists them);
- the look-at joint: the joint nearest the centre of the skinned meshes over the animation
  (not the root, which many rigs put at the feet: a ring aimed there frames the feet);
- the capture ring: its radius so that the character, seen from any side at any sampled
  frame, fits the square image with a margin; its clipping range from the same extent;
- one clip over the animation's time samples, named after the animation prim;
- the stage's units, up axis and rates from the asset; a camera that frames the character
  from the front, a sun and a sky.

The scene then passes `rigspace inspect`, and the next commands are printed (capture, train,
and render with `--model`, which draws the trained bundle without editing the scene).
An existing --out is never overwritten, and nothing is written unless the whole scene is
valid: it is authored in memory, checked with inspect's capture rules (a derived value that
is not finite, from an animation or mesh that gives NaN, is a named error before that), and
then written in one step. Time codes within the tolerance of a whole number (sdk.timecodes:
an exporter's float drift, 1.0000000521) are written as that number.
"""

from __future__ import annotations

import argparse
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdSkel

from rigspace.sdk import schema, validation
from rigspace.sdk.cli import CommandSpec
from rigspace.sdk.errors import SceneError
from rigspace.sdk.stage import open_stage
from rigspace.sdk.timecodes import whole

FOCAL_LENGTH = 35.0
APERTURE = 20.955
"""The ring's lens (the samples' 35 mm on a 20.955 mm film back)."""
MARGIN = 1.15
"""The character's farthest point from the look-at joint fills 1/MARGIN of the half image."""
SAMPLES = 24
"""Animation frames the extent is measured at (evenly spaced over the clip)."""
VIEWS, ELEVATIONS, RESOLUTION, HELD_OUT = 12, (0.0, 20.0), 128, 4
"""The capture ring's defaults (the sample scene's)."""
TRAIN_MINUTES = 60
"""The time budget the printed train command suggests. Without one the small preset trains
4,000 steps a level, 16,000 to 128x128: about two hours on 2 CPU cores (the sample model's
steps took 0.2, 0.3, 0.5 and 0.9 s at 16 to 128), with no word of it at the start. With
--minutes the run times its steps first, plans them to reach 128x128 in the budget (an hour:
about 1,500 a level there) and says so, or says which level it reaches."""


@dataclass
class Derived:
    """What `init` found, for the printout (and the tests)."""

    character: str
    skeleton: str
    joints: int
    look_at_joint: str
    root_joint: str
    root_offset: float
    """Distance from the root joint to the look-at joint (scene units), mean over frames."""
    extent: float
    """The farthest skinned point from the look-at joint over the sampled frames."""
    radius: float
    clipping: tuple[float, float]
    clip: tuple[str, float, float]
    camera: str


def find_skeletons(stage: Usd.Stage) -> list[Usd.Prim]:
    return [
        p
        for p in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies())
        if p.IsA(UsdSkel.Skeleton)
    ]


def _asset_root(stage: Usd.Stage, asset: Path) -> Usd.Prim:
    root = stage.GetDefaultPrim()
    if root:
        return root
    roots = [p for p in stage.GetPseudoRoot().GetChildren() if p.IsDefined()]
    if not roots:
        raise SceneError(f"{asset} defines no prim.", "export the character with its prims.")
    return roots[0]


def _prim_name(text: str) -> str:
    name = "".join(c if c.isalnum() or c == "_" else "_" for c in text)
    return name if name and not name[0].isdigit() else f"Character_{name}"


def init_scene(
    asset: str | Path,
    out: str | Path,
    skeleton: str | None = None,
    name: str | None = None,
) -> Derived:
    """Write the shot scene `out` around `asset` (see the module doc); return what was found."""
    asset, out = Path(asset), Path(out)
    if out.exists():
        raise SceneError(
            f"--out {out} exists: init never overwrites a file.", "choose a new scene path."
        )
    if out.suffix not in (".usda", ".usd", ".usdc"):
        raise SceneError(f"--out {out} is not a USD layer path.", "end it in .usda.")
    source = open_stage(asset)  # a missing or unreadable file: its own error
    root = _asset_root(source, asset)
    skeletons = find_skeletons(source)
    if not skeletons:
        raise SceneError(
            f"{asset} has no UsdSkel Skeleton: rigspace draws skinned, animated characters.",
            "export the character with its skeleton (UsdSkel: SkelRoot, Skeleton, joints).",
        )
    if skeleton is not None:
        chosen = [s for s in skeletons if str(s.GetPath()) == skeleton]
        if not chosen:
            raise SceneError(
                f"--skeleton {skeleton} is not a Skeleton of {asset}.",
                f"choose one of: {', '.join(str(s.GetPath()) for s in skeletons)}.",
            )
    elif len(skeletons) > 1:
        raise SceneError(
            f"{asset} has {len(skeletons)} skeletons: "
            f"{', '.join(str(s.GetPath()) for s in skeletons)}.",
            "pick the character's with --skeleton PATH.",
        )
    else:
        chosen = skeletons
    skel_path = chosen[0].GetPath()
    if not skel_path.HasPrefix(root.GetPath()):
        raise SceneError(
            f"Skeleton {skel_path} is outside {asset}'s default prim {root.GetPath()}.",
            "export the asset with one root prim holding the character (its defaultPrim).",
        )
    character_name = _prim_name(name or asset.stem)
    character = Sdf.Path("/World").AppendChild(character_name)
    asset_prim = character.AppendChild("Asset")
    skeleton_in_scene = asset_prim.AppendPath(skel_path.MakeRelativePath(root.GetPath()))
    # Authored in memory under --out's path (so the asset's relative reference resolves and
    # the checks name --out), and written only once it is valid.
    layer = Sdf.Layer.New(Sdf.FileFormat.FindByExtension(out.suffix[1:]), str(out))
    stage = Usd.Stage.Open(layer)
    derived = _author(stage, source, asset, out, root, character, asset_prim, skeleton_in_scene)
    validation.require_valid(stage, "capture")  # what inspect and capture check
    _write_new(layer, out)
    return derived


def _write_new(layer: Sdf.Layer, out: Path) -> None:
    """Write `layer` to `out` in one step, never over a file: beside it first, then linked
    into place (a hard link fails where `out` appeared meanwhile)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.{os.getpid()}.tmp{out.suffix}")
    try:
        if not layer.Export(str(tmp)):
            raise SceneError(f"--out {out} cannot be written.", "choose a writable folder.")
        try:
            os.link(tmp, out)
        except FileExistsError:
            raise SceneError(
                f"--out {out} exists: init never overwrites a file.", "choose a new scene path."
            ) from None
        except OSError:  # a file system without hard links
            if out.exists():
                raise SceneError(
                    f"--out {out} exists: init never overwrites a file.", "choose a new scene path."
                ) from None
            os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)


def _author(
    stage: Usd.Stage,
    source: Usd.Stage,
    asset: Path,
    out: Path,
    root: Usd.Prim,
    character: Sdf.Path,
    asset_prim: Sdf.Path,
    skeleton: Sdf.Path,
) -> Derived:
    """Author the new scene on `stage` around the asset; return what was derived."""
    from rigspace.sdk.posing import CharacterRig

    up = _copy_stage_metadata(stage, source)
    prim, joints = _define_character(
        stage, source, asset, out, root, character, asset_prim, skeleton
    )
    leaf = [j.rsplit("/", 1)[-1] for j in joints]
    prim.CreateAttribute("rigspace:lookAtJoint", Sdf.ValueTypeNames.Token, custom=False).Set(
        leaf[0]
    )  # provisional: the rig reads it; set below
    rig = CharacterRig(prim)
    samples, look, jp, extent = _animated_extent(rig, asset, skeleton)
    span = (whole(samples[0]), whole(samples[1]))  # an exporter's float drift is not written
    half_fov = math.atan(APERTURE / 2 / FOCAL_LENGTH)
    radius = MARGIN * extent / math.sin(half_fov)  # the whole sphere of that radius in view
    near = max((radius - extent) * 0.5, radius * 1e-3)
    far = (radius + extent) * 4
    target = jp[:, look].mean(axis=0)
    # The shot is 16:9: its narrower vertical field sets the distance that frames it whole.
    distance = MARGIN * extent / math.sin(math.atan(APERTURE * 9 / 16 / 2 / FOCAL_LENGTH))
    _require_finite(
        asset,
        {"ring radius": radius, "clipping range": (near, far), "shot camera distance": distance},
    )
    prim.GetAttribute("rigspace:lookAtJoint").Set(leaf[look])
    clip_name = _prim_name(rig.animation.GetName())
    _author_capture_ring(prim, radius, near, far, clip_name, span)
    stage.SetStartTimeCode(span[0])
    stage.SetEndTimeCode(span[1])
    camera = _camera(stage, up, target, distance, max(near, 1e-3 * distance), far + distance)
    _lights(stage, up)
    root_offset = float(np.linalg.norm(jp[:, look] - jp[:, 0], axis=1).mean())
    return Derived(
        character=str(character),
        skeleton=str(skeleton),
        joints=len(joints),
        look_at_joint=leaf[look],
        root_joint=leaf[0],
        root_offset=root_offset,
        extent=extent,
        radius=radius,
        clipping=(near, far),
        clip=(clip_name, float(span[0]), float(span[1])),
        camera=camera,
    )


def _copy_stage_metadata(stage: Usd.Stage, source: Usd.Stage) -> str:
    """Give `stage` the asset's units, up axis and rates; return the up axis."""
    units = UsdGeom.GetStageMetersPerUnit(source)
    up = UsdGeom.GetStageUpAxis(source)
    UsdGeom.SetStageMetersPerUnit(stage, units)
    UsdGeom.SetStageUpAxis(stage, up)
    stage.SetTimeCodesPerSecond(source.GetTimeCodesPerSecond())
    stage.SetFramesPerSecond(source.GetFramesPerSecond())
    return up


def _define_character(
    stage: Usd.Stage,
    source: Usd.Stage,
    asset: Path,
    out: Path,
    root: Usd.Prim,
    character: Sdf.Path,
    asset_prim: Sdf.Path,
    skeleton: Sdf.Path,
) -> tuple[Usd.Prim, list[str]]:
    """Define /World and the character (the asset referenced, its skeleton bound); return the
    character prim and the skeleton's joints."""
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    prim = stage.DefinePrim(character, schema.NEURAL_CHARACTER)
    reference = os.path.relpath(asset.resolve(), out.resolve().parent)
    held = stage.DefinePrim(asset_prim)
    if source.GetDefaultPrim():
        held.GetReferences().AddReference(reference)
    else:
        held.GetReferences().AddReference(reference, root.GetPath())
    prim.CreateRelationship("rigspace:skeleton", custom=False).SetTargets([skeleton])
    joints = [
        str(j) for j in UsdSkel.Skeleton(stage.GetPrimAtPath(skeleton)).GetJointsAttr().Get() or []
    ]
    if not joints:
        raise SceneError(f"Skeleton {skeleton} lists no joints.", "export the skeleton's joints.")
    return prim, joints


def _animated_extent(
    rig, asset: Path, skeleton: Sdf.Path
) -> tuple[tuple[float, float], int, np.ndarray, float]:
    """(the animation's time span, the look-at joint, (T, J, 3) joint positions, the farthest
    skinned point from the look-at joint) over SAMPLES frames of the animation."""
    span = rig.time_range()
    if span is None or span[1] <= span[0]:
        raise SceneError(
            f"The skeleton {skeleton} of {asset} has no animation over time (its SkelAnimation "
            "holds one pose or none).",
            "export the character with its animation: capture renders it in many poses.",
        )
    from rigspace.sdk.posing import centre_joint

    times = np.linspace(span[0], span[1], SAMPLES)
    found = centre_joint(rig, times)
    if found is None:
        raise SceneError(
            f"No mesh of {asset} is skinned to {skeleton}.",
            "bind the character's meshes to its skeleton (UsdSkelBindingAPI).",
        )
    look, jp, points = found
    for k, t in enumerate(times):
        what = "joint" if not np.all(np.isfinite(jp[k])) else "skinned point"
        if what == "joint" or not np.all(np.isfinite(points[k])):
            raise SceneError(
                f"The animation of {skeleton} in {asset} gives a {what} position that is NaN or "
                f"infinite at time code {t:g}, so init cannot measure the character to frame it "
                "(its ring radius and clipping range would be NaN).",
                "fix the SkelAnimation's (or the meshes') values there and export again.",
            )
    extent = max(float(np.linalg.norm(p - jp[k, look], axis=1).max()) for k, p in enumerate(points))
    if not extent > 0:
        raise SceneError(
            f"The skinned meshes of {asset} have no extent around {skeleton}'s joints (every "
            "point at the look-at joint), so init cannot frame the character.",
            "export the character's meshes with their points and skin weights.",
        )
    return span, look, jp, extent


def _require_finite(asset: Path, values: dict[str, float | tuple[float, ...]]) -> None:
    """A SceneError naming the first derived value that is not a finite number > 0."""
    for name, value in values.items():
        numbers = value if isinstance(value, tuple) else (value,)
        if not all(math.isfinite(v) and v > 0 for v in numbers):
            shown = ", ".join(f"{v:g}" for v in numbers)
            raise SceneError(
                f"init derived a {name} of {shown} from {asset}; it must be finite and > 0.",
                "check the asset's units, skeleton and animation with `rigspace inspect` on it.",
            )


def _author_capture_ring(
    prim: Usd.Prim,
    radius: float,
    near: float,
    far: float,
    clip_name: str,
    span: tuple[float, float],
) -> None:
    """Apply the capture ring schema to the character with the derived values (uniform)."""
    schema_ring = {
        "viewsPerRing": (Sdf.ValueTypeNames.Int, VIEWS),
        "elevations": (Sdf.ValueTypeNames.FloatArray, list(ELEVATIONS)),
        "radius": (Sdf.ValueTypeNames.Float, radius),
        "focalLength": (Sdf.ValueTypeNames.Float, FOCAL_LENGTH),
        "horizontalAperture": (Sdf.ValueTypeNames.Float, APERTURE),
        "resolution": (Sdf.ValueTypeNames.Int, RESOLUTION),
        "clippingRange": (Sdf.ValueTypeNames.Float2, Gf.Vec2f(near, far)),
        "clipNames": (Sdf.ValueTypeNames.TokenArray, [clip_name]),
        "clipRanges": (Sdf.ValueTypeNames.Float2Array, [Gf.Vec2f(*span)]),
        "heldOutViewsPerRing": (Sdf.ValueTypeNames.Int, HELD_OUT),
    }
    prim.AddAppliedSchema(schema.CAPTURE_RING_API)
    for key, (kind, value) in schema_ring.items():
        attr = prim.CreateAttribute(f"rigspace:captureRing:{key}", kind, custom=False)
        attr.SetVariability(Sdf.VariabilityUniform)
        attr.Set(value)


def _axes(up: str) -> tuple[Gf.Vec3d, Gf.Vec3d]:
    """(up vector, the front: where the shot camera stands) for the stage's up axis."""
    if up == UsdGeom.Tokens.z:
        return Gf.Vec3d(0, 0, 1), Gf.Vec3d(0, -1, 0)
    return Gf.Vec3d(0, 1, 0), Gf.Vec3d(0, 0, 1)


def _camera(
    stage: Usd.Stage, up: str, target: np.ndarray, distance: float, near: float, far: float
) -> str:
    """A 16:9 camera on the front axis, `distance` from the look-at joint, aimed at it."""
    up_vector, front = _axes(up)
    centre = Gf.Vec3d(*map(float, target))
    eye = centre + front * distance + up_vector * (distance * 0.1)
    view = Gf.Matrix4d().SetLookAt(eye, centre, up_vector)
    camera = UsdGeom.Camera.Define(stage, "/World/ShotCam")
    camera.CreateFocalLengthAttr(FOCAL_LENGTH)
    camera.CreateHorizontalApertureAttr(APERTURE)
    camera.CreateVerticalApertureAttr(APERTURE * 9 / 16)
    camera.CreateClippingRangeAttr(Gf.Vec2f(near, far))
    camera.AddTransformOp().Set(view.GetInverse())
    return str(camera.GetPath())


def _lights(stage: Usd.Stage, up: str) -> None:
    """A sun from above and the front, and a sky (the sample scenes' values)."""
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateAngleAttr(1.0)
    sun.CreateIntensityAttr(3.0)
    sun.CreateColorAttr(Gf.Vec3f(1.0, 0.96, 0.9))
    rotation = (-50.0, 30.0, 0.0) if up != UsdGeom.Tokens.z else (40.0, 0.0, 30.0)
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(*rotation))
    sky = UsdLux.DomeLight.Define(stage, "/World/Sky")
    sky.CreateIntensityAttr(0.4)
    sky.CreateColorAttr(Gf.Vec3f(0.6, 0.7, 0.9))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("asset", help="the character: a .usdz/.usd/.usda/.usdc with a UsdSkel rig")
    parser.add_argument("--out", required=True, help="the new scene (.usda); never overwritten")
    parser.add_argument("--skeleton", help="the Skeleton's path in the asset, when it has several")
    parser.add_argument("--name", help="the character prim's name (default: the asset's file name)")


def run(args: argparse.Namespace) -> int:
    derived = init_scene(args.asset, args.out, args.skeleton, args.name)
    out = Path(args.out)
    stem = out.with_suffix("")
    name, first, last = derived.clip
    print(f"wrote {out}: {derived.character} references {args.asset}")
    print(f"  skeleton        {derived.skeleton} ({derived.joints} joints)")
    root = (
        "the root joint itself"
        if derived.root_joint == derived.look_at_joint
        else f"the root joint {derived.root_joint} is {derived.root_offset:.3g} units from it"
    )
    print(f"  look-at joint   {derived.look_at_joint}: nearest the skinned meshes' centre ({root})")
    print(
        f"  capture ring    radius {derived.radius:.4g} (the character reaches "
        f"{derived.extent:.3g} units from the look-at joint), clipping "
        f"{derived.clipping[0]:.3g}-{derived.clipping[1]:.4g}, {VIEWS} views x "
        f"{len(ELEVATIONS)} elevations, {RESOLUTION} px"
    )
    print(f"  clip            {name}: time codes {first:g}-{last:g}")
    print(f"  shot camera     {derived.camera}, a sun and a sky")
    print("next:")
    print(f"  rigspace inspect {out}")
    print(f"  rigspace capture {out} --out {stem}_data")
    print(
        f"  rigspace train {stem}_data --out {stem}_model --minutes {TRAIN_MINUTES}"
        "  # it says first which level the budget reaches"
    )
    print(f"  rigspace render {out} --model {stem}_model --out {stem}_frames")
    return 0


COMMAND = CommandSpec(
    name="init",
    help="write a shot scene around a raw rigged, animated character (a RigspaceNeuralCharacter "
    "with every value derived)",
    description=__doc__.split("\n\n")[0] if __doc__ else "",
    add_arguments=add_arguments,
    run=run,
)

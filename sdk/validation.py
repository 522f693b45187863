"""Scene validation: USD's own validators plus rigspace's, run through UsdValidation.

A rigspace validator is a `ValidatorSpec` (plugin kind "validator", entry-point group
`rigspace.validators`): a function from a prim to `Issue`s. Each is registered in USD's
`UsdValidation.ValidationRegistry` as `rigspace:<name>` and runs in the same
`ValidationContext` as USD's built-in validators, so every finding has the same shape:
severity, validator, prim and a message that names the fix. Rules report, never raise.

These rules are the one set of checks: `rigspace inspect` reports them all, and
`require_valid` makes capture and render refuse the errors of the rules that concern
them, in the same words (docs/conventions.md, "Validation").
"""

from __future__ import annotations

import functools
import hashlib
import math
import re
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSkel, UsdValidation

from rigspace.sdk import schema, timecodes
from rigspace.sdk.bindings import SkelBinding, ignored_animation_sources, skel_binding
from rigspace.sdk.bundle import BundleError, read_manifest
from rigspace.sdk.errors import RigspaceError, SceneError
from rigspace.sdk.geometry import albedo_texture
from rigspace.sdk.plugins import Kind, discover

ERROR = "error"
WARNING = "warning"
PREFIX = "rigspace:"
CAPTURE, RENDER = "capture", "render"
PURPOSES = (CAPTURE, RENDER)
"""The commands that refuse a scene with errors (`require_valid`'s purposes)."""

# Limits documented on the schema properties (usd_schemas/schema.usda).
MAX_VIEWS = 360
MAX_ELEVATION_DEG = 89.0
MIN_RESOLUTION, MAX_RESOLUTION = 16, 4096
MAX_BUFFER_SECONDS = 5.0
UNIT_QUAT_TOLERANCE = 1e-3
MAPS = ("albedo", "normal", "depth", "mask")
UP_AXES = ("Y", "Z")


@dataclass(frozen=True)
class Issue:
    """One finding of a rigspace rule; the prim defaults to the prim being checked."""

    severity: str
    code: str
    message: str
    """What is wrong, then " Fix: " and what to do about it."""
    purposes: tuple[str, ...] | None = None
    """The commands this error stops, or this warning is shown to; None: its rule's
    (ValidatorSpec.purposes)."""
    exception: type[RigspaceError] | None = None
    """The exception `require_valid` raises for it alone (None: the caller's)."""

    def as_error(self, default: type[RigspaceError] = SceneError) -> RigspaceError:
        what, _, fix = self.message.partition(" Fix: ")
        return (self.exception or default)(what, fix)


@dataclass(frozen=True)
class ValidatorSpec:
    """A scene rule: `check(prim)` yields the issues it finds on that prim."""

    name: str
    doc: str
    check: Callable[[Usd.Prim], Iterable[Issue]]
    purposes: tuple[str, ...] = PURPOSES
    """The commands its errors stop (inspect reports every rule)."""
    stage: bool = False
    """Checked once per stage (`check` gets the pseudo-root) instead of once per prim."""


VALIDATORS: Kind[ValidatorSpec] = Kind("validator", "rigspace.validators", ValidatorSpec)


@dataclass(frozen=True)
class Finding:
    """A validation result from any validator, USD's or ours."""

    severity: str
    validator: str
    code: str
    prim: str
    message: str
    blocks: tuple[str, ...] = ()
    """The commands that refuse the scene for it (an error of a rigspace rule); USD's own
    validators report compliance and stop none."""

    def as_dict(self) -> dict[str, object]:
        return {
            "severity": self.severity,
            "validator": self.validator,
            "code": self.code,
            "prim": self.prim,
            "message": self.message,
            "blocks": list(self.blocks),
        }


def error(code: str, message: str, **kwargs) -> Issue:
    return Issue(ERROR, code, message, **kwargs)


def warning(code: str, message: str, **kwargs) -> Issue:
    return Issue(WARNING, code, message, **kwargs)


# ---------------------------------------------------------------------------------------
# Shared look-ups


def character_skeleton(prim: Usd.Prim) -> Usd.Prim | None:
    """The Skeleton prim a neural character targets, or None when it has no valid one."""
    targets = schema.read_neural_character(prim).skeleton_targets
    if len(targets) != 1:
        return None
    target = prim.GetStage().GetPrimAtPath(targets[0])
    return target if target and target.IsA(UsdSkel.Skeleton) else None


def character_animation(prim: Usd.Prim) -> Usd.Prim | None:
    """The SkelAnimation driving a neural character: its own relationship, else the one UsdSkel
    binds to its skeleton (the skeleton's own skel:animationSource or an ancestor's)."""
    found, _ = resolve_character(prim)
    return found.animation if found else None


def animation_time_range(anim: Usd.Prim) -> tuple[float, float] | None:
    """First and last time sample over the animation's rotations and translations."""
    samples: list[float] = []
    skel_anim = UsdSkel.Animation(anim)
    for attr in (skel_anim.GetRotationsAttr(), skel_anim.GetTranslationsAttr()):
        samples += attr.GetTimeSamples()
    return (min(samples), max(samples)) if samples else None


@dataclass
class CharacterBinding:
    """A neural character's skeleton, animation and skinned meshes, resolved as UsdSkel does."""

    skeleton: Usd.Prim
    joints: list[str]
    animation: Usd.Prim
    skel: SkelBinding = field(repr=False)


def resolve_character(prim: Usd.Prim) -> tuple[CharacterBinding | None, Issue | None]:
    """What posing a neural character needs (`CharacterRig`), or the first error that stops it.

    In order: exactly one rigspace:skeleton target that is a Skeleton with joints; a
    SkelAnimation (rigspace:animationSource, else the one UsdSkel binds); a skinned Mesh.
    """
    path = prim.GetPath()
    character = schema.read_neural_character(prim)
    stage = prim.GetStage()
    targets = character.skeleton_targets
    if len(targets) != 1:
        listed = f"it has {len(targets)}: {', '.join(targets)}" if targets else "it has none"
        code = "SeveralSkeletons" if targets else "NoSkeleton"
        return None, error(
            code,
            f"Neural character {path} has no single rigspace:skeleton target ({listed}). Fix: "
            "point rigspace:skeleton at the one UsdSkel Skeleton that drives the character.",
        )
    target = stage.GetPrimAtPath(targets[0])
    if not target:
        return None, error(
            "SkeletonMissing",
            f"Neural character {path}: rigspace:skeleton targets {targets[0]}, which does not "
            "exist on the stage. Fix: correct the path, or load the layer that defines it.",
        )
    if not target.IsA(UsdSkel.Skeleton):
        return None, error(
            "NotASkeleton",
            f"Neural character {path}: rigspace:skeleton targets {targets[0]}, a "
            f"{target.GetTypeName() or 'untyped prim'}, not a Skeleton. Fix: target the "
            "Skeleton prim (UsdSkel) instead.",
        )
    joints = schema.skeleton_joints(target)
    if not joints:
        return None, error(
            "EmptySkeleton",
            f"Skeleton {targets[0]} (rigspace:skeleton of {path}) has no joints. Fix: author "
            "its joints, bindTransforms and restTransforms.",
        )
    binding = skel_binding(target)
    if character.animation_targets:
        anim = stage.GetPrimAtPath(character.animation_targets[0])
        if not anim or not anim.IsA(UsdSkel.Animation):
            kind = anim.GetTypeName() if anim else "nothing"
            return None, error(
                "NotAnAnimation",
                f"Neural character {path}: rigspace:animationSource targets "
                f"{character.animation_targets[0]} ({kind}), not a SkelAnimation. Fix: target a "
                "SkelAnimation prim, or clear the relationship to use the skeleton's own binding.",
            )
    else:
        anim = binding.animation
    if anim is None:
        ignored = ignored_animation_sources(target)
        hint = (
            f" ({', '.join(ignored)} authors skel:animationSource without SkelBindingAPI, so "
            "UsdSkel ignores it: apply the API there)"
            if ignored
            else ""
        )
        return None, error(
            "NoAnimation",
            f"Neural character {path}: skeleton {targets[0]} has no animation (neither "
            "rigspace:animationSource nor a skel:animationSource on the skeleton or an ancestor "
            f"names a SkelAnimation){hint}. Fix: bind a SkelAnimation to the skeleton or its "
            "SkelRoot, or set rigspace:animationSource.",
        )
    if not binding.skinning:
        return None, error(
            "NoSkinnedMesh",
            f"Neural character {path}: no skinned mesh is bound to skeleton {targets[0]} (a "
            "visible Mesh under its SkelRoot with primvars:skel:jointIndices and jointWeights). "
            "Fix: bind the character's meshes to the skeleton with UsdSkelBindingAPI skin weights.",
        )
    return CharacterBinding(target, joints, anim, binding), None


def _animation_values(anim: Usd.Prim, path: Sdf.Path) -> Iterator[Issue]:
    """Every authored value of the animation finite; time samples to capture."""
    skel_anim = UsdSkel.Animation(anim)
    for attr in (
        skel_anim.GetTranslationsAttr(),
        skel_anim.GetRotationsAttr(),
        skel_anim.GetScalesAttr(),
    ):
        for t in attr.GetTimeSamples() or [Usd.TimeCode.Default()]:
            value = attr.Get(t)
            if value is not None and not np.all(np.isfinite(np.asarray(value, dtype=float))):
                when = f"at time {t:g}" if isinstance(t, float) else "(its default value)"
                yield error(
                    "AnimationNotFinite",
                    f"Animation {anim.GetPath()} (driving {path}) has NaN or Inf in "
                    f"{attr.GetName()} {when}. Fix: fix or delete that time sample (capture "
                    "and render read every time code).",
                )
                break
    if animation_time_range(anim) is None:
        yield error(
            "AnimationNotTimeSampled",
            f"Animation {anim.GetPath()} (driving {path}) has no time samples to capture. Fix: "
            "author time-sampled rotations on the SkelAnimation.",
            purposes=(CAPTURE,),
        )


def _missing_joints(names: Iterable[str], joints: list[str]) -> list[str]:
    missing = []
    for name in names:
        try:
            schema.find_joint(name, joints)
        except schema.JointLookupError:
            missing.append(name)
    return missing


def _owner_is_character(prim: Usd.Prim, api: str) -> Iterator[Issue]:
    if not schema.is_neural_character(prim):
        yield error(
            "NotOnCharacter",
            f"{prim.GetPath()} ({prim.GetTypeName() or 'untyped'}) has {api} applied, which "
            "only means something on a RigspaceNeuralCharacter. Fix: remove the API, or apply "
            "it to the character prim.",
        )


# ---------------------------------------------------------------------------------------
# The rules


def check_stage(root: Usd.Prim) -> Iterator[Issue]:
    """Units and up axis, read from the root layer (USD reads them nowhere else)."""
    stage = root.GetStage()
    name = stage.GetRootLayer().identifier
    if not stage.HasAuthoredMetadata("metersPerUnit"):
        yield warning(
            "MetersPerUnitAssumed",
            f"Stage {name} does not author metersPerUnit; rigspace assumes USD's fallback "
            "0.01 (centimetres). Fix: author metersPerUnit in the root layer (1 for metres).",
        )
    else:
        value = stage.GetMetadata("metersPerUnit")
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            yield error(
                "BadMetersPerUnit",
                f"Stage {name} has metersPerUnit {value}; it must be a finite number > 0 (light "
                "normalisation, capture distances and depth are in these units). Fix: author "
                "metersPerUnit in the root layer (0.01 for centimetres, 1 for metres).",
            )
    if not stage.HasAuthoredMetadata("upAxis"):
        yield warning(
            "UpAxisAssumed",
            f"Stage {name} does not author upAxis; rigspace assumes Y (USD's fallback). Fix: "
            'author upAxis = "Y" (or "Z") in the root layer.',
        )
    elif str(stage.GetMetadata("upAxis")) not in UP_AXES:
        yield error(
            "BadUpAxis",
            f"Stage {name} has upAxis {stage.GetMetadata('upAxis')!r}; USD allows Y or Z. Fix: "
            'author upAxis = "Y" or "Z" in the root layer.',
        )


def check_textures(prim: Usd.Prim) -> Iterator[Issue]:
    """A gprim's UsdPreviewSurface texture can be found (reading it is left to the renderer)."""
    if not prim.IsA(UsdGeom.Gprim):
        return
    texture = albedo_texture(prim)
    problem = texture.problem() if texture else None
    if problem:
        yield error(
            "TextureMissing",
            f"Gprim {prim.GetPath()}: {problem[0].upper()}{problem[1:]}. Fix: correct the "
            "shader's inputs:file (a relative path is relative to the layer that authors it) "
            "or put the image there.",
        )


def check_character_skeleton(prim: Usd.Prim) -> Iterator[Issue]:
    if not schema.is_neural_character(prim):
        return
    path = prim.GetPath()
    character = schema.read_neural_character(prim)
    found, problem = resolve_character(prim)
    if found is None:
        if problem is not None:
            yield problem
        return
    yield from _animation_values(found.animation, path)
    joints = found.joints
    if character.look_at_joint:
        yield from _joint_issues(
            "LookAtJointMissing", [character.look_at_joint], joints, path, "rigspace:lookAtJoint"
        )
    yield from _joint_issues("JointsMissing", character.joints, joints, path, "rigspace:joints")
    unknown_maps = [m for m in character.maps if m not in MAPS]
    if unknown_maps:
        yield error(
            "UnknownMaps",
            f"Neural character {path}: rigspace:maps lists {', '.join(unknown_maps)}; the "
            f"maps a model can provide are {', '.join(MAPS)}. Fix: remove the others.",
        )


def _joint_issues(
    code: str, names: Iterable[str], joints: list[str], path, prop: str
) -> Iterator[Issue]:
    missing = _missing_joints(names, joints)
    if missing:
        yield error(
            code,
            f"Neural character {path}: {prop} names joints the skeleton lacks: "
            f"{', '.join(missing)}. Fix: use names from the Skeleton's joint list (full path or "
            "a unique last element).",
        )


def check_character_model(prim: Usd.Prim) -> Iterator[Issue]:
    if not schema.is_neural_character(prim):
        return
    path = prim.GetPath()
    character = schema.read_neural_character(prim)
    if not character.model:
        yield warning(
            "NoModel",
            f"Neural character {path} has no model bundle (rigspace:model is empty): it can be "
            "captured but the runtime cannot draw it. Fix: train one with `rigspace train` and "
            "set rigspace:model to the bundle folder.",
        )
        return
    manifest_file = schema.resolve_model_path(character)
    if manifest_file is None:
        yield error(
            "ModelNotFound",
            f"Neural character {path}: rigspace:model @{character.model}@ does not resolve to a "
            "bundle folder or manifest.json. Fix: correct the path (relative paths are relative "
            "to the layer that authors them) or export the bundle there.",
        )
        return
    try:
        manifest = read_manifest(manifest_file)
    except BundleError as exc:
        yield error("BadModel", f"Neural character {path}: {exc}", exception=BundleError)
        return
    if "trunk" in manifest.raw or "levels" in manifest.raw:  # a manifest alone: nothing to load
        problem = _graphs_problem(manifest.folder)
        if problem:
            yield error("BadModel", f"Neural character {path}: {problem}", exception=BundleError)
    skeleton = character_skeleton(prim)
    if skeleton is not None:
        missing = _missing_joints(manifest.joints, schema.skeleton_joints(skeleton))
        if missing:
            yield error(
                "ModelJointsMissing",
                f"Neural character {path}: the model {manifest.path} needs joints that skeleton "
                f"{skeleton.GetPath()} lacks: {', '.join(missing)}. Fix: bind the skeleton the "
                "model was trained on, or retrain the model on this skeleton.",
            )
    if character.joints and tuple(character.joints) != manifest.joints:
        yield error(
            "JointsDisagree",
            f"Neural character {path}: rigspace:joints differs from the joints the model "
            f"{manifest.path} reads. Fix: clear rigspace:joints (the manifest is the truth) or "
            "copy the manifest's list.",
        )
    if character.rotation_encoding != manifest.rotation_encoding:
        yield error(
            "EncodingDisagrees",
            f"Neural character {path}: rigspace:rotationEncoding is "
            f"{character.rotation_encoding!r} but the model reads {manifest.rotation_encoding!r}. "
            "Fix: set it to the manifest's encoding.",
        )
    distance = character.training_distance or manifest.training_distance
    focal = character.training_focal_length or manifest.training_focal_length
    if distance <= 0 or focal <= 0:
        yield error(
            "NoTrainingCamera",
            f"Neural character {path}: the training camera distance and focal length must be "
            f"> 0 (distance {distance}, focal length {focal}); the billboard scale depends on "
            "them. Fix: author rigspace:trainingCamera:* or re-export the bundle.",
        )


def _graphs_problem(folder: Path) -> str | None:
    """Why the bundle's graphs cannot run, or None (cached per folder content)."""
    stamp = tuple((p.name, p.stat().st_mtime_ns, p.stat().st_size) for p in folder.glob("*"))
    return _check_graphs(folder.resolve(), stamp)


@functools.lru_cache(maxsize=32)
def _check_graphs(folder: Path, _stamp: tuple) -> str | None:
    """Every graph the manifest lists is there with the size and sha256 it records; the trunk,
    and any graph without a record or that differs from it, loads in onnxruntime (the
    runtime's loader, so its words). Loading every graph would triple inspect's time."""
    from rigspace.sdk.model import BundleModel  # onnxruntime, only once a bundle resolves

    try:
        model = BundleModel(folder)
        raw = model.manifest.raw
        sets = [raw["trunk"], *raw["levels"]]
        graphs = sorted(
            {g for s in sets for key in ("graphs", "int8") for g in s.get(key, {}).values()}
        )
        records = raw.get("files", {})
        load = {raw["trunk"]["graphs"]["trunk"]}
        changed = []
        for name in graphs:
            path = folder / name
            if not path.is_file():
                return (
                    f"Model file {path} is missing from the bundle. Fix: re-export the bundle, "
                    "or restore the file."
                )
            record = records.get(name)
            if not record or _differs(path, record):
                load.add(name)
                changed += [name] if record else []
        for name in sorted(load):
            model._session(name)  # the runtime loader: its errors, word for word
    except BundleError as exc:
        return str(exc)
    except (KeyError, TypeError, AttributeError) as exc:  # a manifest that lacks what it lists
        return (
            f"Model bundle {folder}: manifest.json is incomplete ({type(exc).__name__}: {exc}). "
            "Fix: re-export the bundle with `rigspace train`."
        )
    if changed:
        return (
            f"Model bundle {folder}: {', '.join(changed)} differ from the size and sha256 "
            "manifest.json records (changed after export). Fix: re-export the bundle with "
            "`rigspace train`, or restore the files."
        )
    return None


def _differs(path: Path, record: dict) -> bool:
    if path.stat().st_size != record.get("bytes"):
        return True
    return hashlib.sha256(path.read_bytes()).hexdigest() != record.get("sha256")


def _range_issue(ok: bool, code: str, message: str) -> Iterator[Issue]:
    if not ok:
        yield error(code, message)


def check_capture_ring(prim: Usd.Prim) -> Iterator[Issue]:
    if not schema.has_capture_ring(prim):
        return
    yield from _owner_is_character(prim, "RigspaceCaptureRingAPI")
    path = prim.GetPath()
    ring = schema.read_capture_ring(prim)
    ns = "rigspace:captureRing:"

    def out_of_range(prop: str, value, allowed: str) -> str:
        return (
            f"Capture ring on {path}: {ns}{prop} is {value}; allowed: {allowed}. Fix: author a "
            "value that is allowed."
        )

    yield from _range_issue(
        1 <= ring.views_per_ring <= MAX_VIEWS,
        "ViewsOutOfRange",
        out_of_range("viewsPerRing", ring.views_per_ring, f"1 to {MAX_VIEWS}"),
    )
    bad_elevations = [e for e in ring.elevations if not abs(e) <= MAX_ELEVATION_DEG]
    yield from _range_issue(
        bool(ring.elevations) and not bad_elevations,
        "ElevationOutOfRange",
        out_of_range(
            "elevations",
            list(ring.elevations),
            f"[-{MAX_ELEVATION_DEG:g}, {MAX_ELEVATION_DEG:g}] degrees, at least one ring",
        ),
    )
    bad_held = [e for e in ring.held_out_elevations if not abs(e) <= MAX_ELEVATION_DEG]
    yield from _range_issue(
        not bad_held,
        "ElevationOutOfRange",
        out_of_range(
            "heldOutElevations", bad_held, f"[-{MAX_ELEVATION_DEG:g}, {MAX_ELEVATION_DEG:g}]"
        ),
    )
    yield from _range_issue(
        math.isfinite(ring.radius) and ring.radius >= 0,
        "RadiusOutOfRange",
        out_of_range("radius", ring.radius, "> 0 scene units, or 0 to derive it from the bounds"),
    )
    for prop, value in (
        ("focalLength", ring.focal_length),
        ("horizontalAperture", ring.horizontal_aperture),
    ):
        yield from _range_issue(
            math.isfinite(value) and value > 0,
            "LensOutOfRange",
            out_of_range(prop, value, "> 0 tenths of a scene unit"),
        )
    res = ring.resolution
    yield from _range_issue(
        MIN_RESOLUTION <= res <= MAX_RESOLUTION and res & (res - 1) == 0,
        "ResolutionNotPowerOfTwo",
        out_of_range(
            "resolution", res, f"a power of two from {MIN_RESOLUTION} to {MAX_RESOLUTION}"
        ),
    )
    near, far = ring.clipping_range
    yield from _range_issue(
        0 < near < far and math.isfinite(far),
        "ClippingOutOfRange",
        out_of_range("clippingRange", (near, far), "0 < near < far"),
    )
    if ring.radius > 0 and 0 < near < far:
        yield from _range_issue(
            near < ring.radius < far,
            "RadiusOutsideClipping",
            f"Capture ring on {path}: {ns}radius {ring.radius:g} puts the look-at joint outside "
            f"the clipping range ({near:g}, {far:g}), so the character would be clipped away. "
            "Fix: author a radius between near and far, or widen clippingRange.",
        )
    yield from _range_issue(
        0 <= ring.held_out_views_per_ring <= ring.views_per_ring,
        "HeldOutViewsOutOfRange",
        out_of_range(
            "heldOutViewsPerRing", ring.held_out_views_per_ring, f"0 to {ring.views_per_ring}"
        ),
    )
    yield from _check_clips(prim, ring)


def _check_clips(prim: Usd.Prim, ring: schema.CaptureRing) -> Iterator[Issue]:
    path = prim.GetPath()
    if len(ring.clip_names) != len(ring.clip_ranges):
        yield error(
            "ClipsDisagree",
            f"Capture ring on {path}: {len(ring.clip_names)} clipNames but "
            f"{len(ring.clip_ranges)} clipRanges. Fix: author one (first, last) range per name.",
        )
        return
    duplicates = sorted({n for n in ring.clip_names if ring.clip_names.count(n) > 1})
    if duplicates:
        yield error(
            "DuplicateClips",
            f"Capture ring on {path}: clip names repeat: {', '.join(duplicates)}. Fix: give each "
            "clip a unique name.",
        )
    unknown = [c for c in ring.held_out_clips if c not in ring.clip_names]
    if unknown and ring.clip_names:
        yield error(
            "UnknownHeldOutClips",
            f"Capture ring on {path}: heldOutClips names {', '.join(unknown)}, which are not in "
            f"clipNames ({', '.join(ring.clip_names)}). Fix: use clip names.",
        )
    backwards = [n for n, (a, b) in zip(ring.clip_names, ring.clip_ranges, strict=True) if a > b]
    if backwards:
        yield error(
            "ClipRangeBackwards",
            f"Capture ring on {path}: clips {', '.join(backwards)} end before they start. Fix: "
            "author (first, last) with first <= last.",
        )
    anim = character_animation(prim) if schema.is_neural_character(prim) else None
    span = animation_time_range(anim) if anim is not None else None
    if anim is not None and span is not None:
        # As capture fits them (sdk/timecodes.py): an end within the tolerance is the same
        # frame, a clip reaching past the range is clamped, one wholly outside is refused.
        outside, clamped = [], []
        for n, (a, b) in zip(ring.clip_names, ring.clip_ranges, strict=True):
            if not (math.isfinite(a) and math.isfinite(b)) or a > b:
                continue  # ClipRangeBackwards, or not a range at all: said above
            inside = timecodes.clamp_range(a, b, *span)
            if inside is None:
                outside.append(f"{n} ({a:g}-{b:g})")
            elif not (timecodes.same_time(inside[0], a) and timecodes.same_time(inside[1], b)):
                clamped.append(f"{n} ({a:g}-{b:g} -> {inside[0]:g}-{inside[1]:g})")
        if outside:
            yield error(
                "ClipOutsideAnimation",
                f"Capture ring on {path}: clips {', '.join(outside)} fall outside the animation "
                f"{anim.GetPath()} ({span[0]:g}-{span[1]:g}). Fix: clip to the animated range.",
            )
        if clamped:
            yield warning(
                "ClipClamped",
                f"Capture ring on {path}: clips {', '.join(clamped)} reach past the animation "
                f"{anim.GetPath()} ({span[0]:g}-{span[1]:g}); capture clamps them. Fix: author "
                "clipRanges inside the animated range.",
                purposes=(),  # inspect's: capture warns itself about the clips it captures
            )
    skeleton = character_skeleton(prim) if schema.is_neural_character(prim) else None
    if skeleton is not None and ring.look_at_joint:
        missing = _missing_joints([ring.look_at_joint], schema.skeleton_joints(skeleton))
        if missing:
            yield error(
                "LookAtJointMissing",
                f"Capture ring on {path}: lookAtJoint {ring.look_at_joint!r} is not a joint of "
                f"{skeleton.GetPath()}. Fix: name a joint from its joint list.",
            )


URL_SCHEME = re.compile(r"^[a-z][a-z0-9+.-]*$")
SMOOTHING = ("none", "exponential", "oneEuro")
BUFFERING = ("latest", "interpolate", "buffered")


def url_problem(url: str) -> str | None:
    """Why `url` is not a usable live-source URL, or None when it parses."""
    if not url:
        return "it is empty"
    if "://" not in url:
        return "it has no scheme:// (for example vmc://127.0.0.1:39539)"
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        return f"it does not parse ({exc})"
    if not URL_SCHEME.match(parts.scheme):
        return f"its scheme {parts.scheme!r} is not a valid URL scheme"
    if port is not None and port == 0:
        return "port 0 is not a port a source can use"
    if not parts.netloc and not parts.path:
        return "it names neither a host nor a path"
    return None


def check_live_binding(prim: Usd.Prim) -> Iterator[Issue]:
    bindings = schema.read_live_bindings(prim)
    if not bindings:
        return
    yield from _owner_is_character(prim, "RigspaceLiveBindingAPI")
    skeleton = character_skeleton(prim) if schema.is_neural_character(prim) else None
    for b in bindings:
        where = f"Live binding {b.name!r} on {prim.GetPath()}"
        ns = f"rigspace:live:{b.name}:"
        problem = url_problem(b.url)
        if problem:
            yield error(
                "BadUrl",
                f"{where}: {ns}url {b.url!r} is not a source URL: {problem}. Fix: author "
                "scheme://host:port/path?options, such as vmc://127.0.0.1:39539.",
            )
        if b.source_bones and len(b.source_bones) != len(b.target_joints):
            yield error(
                "BoneMapDisagrees",
                f"{where}: {len(b.source_bones)} sourceBones but {len(b.target_joints)} "
                "targetJoints. Fix: author one target joint per source bone.",
            )
        if skeleton is not None:
            missing = _missing_joints(b.target_joints, schema.skeleton_joints(skeleton))
            if missing:
                yield error(
                    "TargetJointsMissing",
                    f"{where}: targetJoints names joints skeleton {skeleton.GetPath()} lacks: "
                    f"{', '.join(missing)}. Fix: use names from its joint list.",
                )
        if b.rest_pose:
            bones = len(b.source_bones) or len(b.target_joints)
            if len(b.rest_pose) != bones:
                yield error(
                    "RestPoseDisagrees",
                    f"{where}: {len(b.rest_pose)} restPose rotations for {bones} bones. Fix: "
                    "author one rotation per source bone, or none.",
                )
            norms = [math.sqrt(sum(c * c for c in q)) for q in b.rest_pose]
            if any(not abs(n - 1.0) <= UNIT_QUAT_TOLERANCE for n in norms):
                yield error(
                    "RestPoseNotUnit",
                    f"{where}: restPose holds non-unit quaternions (norms "
                    f"{min(norms):.4g} to {max(norms):.4g}). Fix: normalise them.",
                )
        for ok, prop, value, allowed in (
            (0 <= b.smoothing_strength < 1, "smoothingStrength", b.smoothing_strength, "[0, 1)"),
            (
                0 <= b.buffer_seconds <= MAX_BUFFER_SECONDS,
                "bufferSeconds",
                b.buffer_seconds,
                f"[0, {MAX_BUFFER_SECONDS:g}]",
            ),
            (b.timeout_seconds > 0, "timeoutSeconds", b.timeout_seconds, "> 0"),
            (b.source_meters_per_unit > 0, "sourceMetersPerUnit", b.source_meters_per_unit, "> 0"),
        ):
            if not ok:
                yield error(
                    "ValueOutOfRange",
                    f"{where}: {ns}{prop} is {value}; allowed: {allowed}. Fix: author a value "
                    "that is allowed.",
                )


STAGE_METADATA = ValidatorSpec(
    "StageMetadata",
    "The stage's metersPerUnit is a finite number > 0 and its upAxis Y or Z (else assumed).",
    check_stage,
    stage=True,
)
CHARACTER_SKELETON = ValidatorSpec(
    "CharacterSkeleton",
    "A neural character's Skeleton, animation (own or inherited) and skinned meshes resolve; "
    "its joints exist and its animation is finite.",
    check_character_skeleton,
)
CHARACTER_MODEL = ValidatorSpec(
    "CharacterModel",
    "A neural character's model bundle resolves, its graphs load, and it fits its skeleton.",
    check_character_model,
    purposes=(RENDER,),
)
CAPTURE_RING = ValidatorSpec(
    "CaptureRing",
    "Capture ring values are in range and its clips lie inside the animation.",
    check_capture_ring,
    purposes=(CAPTURE,),
)
LIVE_BINDING = ValidatorSpec(
    "LiveBinding",
    "Live bindings have parseable URLs and bone maps that fit the skeleton.",
    check_live_binding,
    purposes=(RENDER,),
)
TEXTURES = ValidatorSpec(
    "Textures",
    "Every UsdPreviewSurface texture a gprim reads can be found.",
    check_textures,
)
BUILTIN = (
    STAGE_METADATA,
    CHARACTER_SKELETON,
    CHARACTER_MODEL,
    CAPTURE_RING,
    LIVE_BINDING,
    TEXTURES,
)
"""Always run; the entry-point group adds plugins' rules (the built-ins are declared there
too, for discovery's sake, and are not run twice)."""


def rules() -> tuple[list[ValidatorSpec], dict[str, str]]:
    """The built-in rules and the installed plugins' rules; plugin name -> why it failed."""
    plugins = discover(VALIDATORS)
    failed = dict(plugins.failed)
    names = {spec.name for spec in BUILTIN}
    extra = []
    for plugin_name, spec in plugins.specs.items():
        if spec in BUILTIN:
            continue
        if spec.name in names:
            failed[plugin_name] = f"its rule name {spec.name!r} is a built-in rule's"
            continue
        extra.append(spec)
    return [*BUILTIN, *extra], failed


# ---------------------------------------------------------------------------------------
# Registration with UsdValidation and running


_SEVERITY = {ERROR: UsdValidation.ValidationErrorType.Error}
_registered: dict[str, UsdValidation.Validator] = {}
_failures: list[BaseException] = []
_blocks: dict[tuple[str, str, str], tuple[str, ...]] = {}
"""(code, prim, message) -> the commands an error stops, noted while USD runs the rules."""


def _blocked(spec: ValidatorSpec, issue: Issue) -> tuple[str, ...]:
    """The commands that refuse the scene for `issue` (none for a warning)."""
    if issue.severity != ERROR:
        return ()
    return tuple(p for p in spec.purposes if issue.purposes is None or p in issue.purposes)


def _usd_task(spec: ValidatorSpec):
    def task(subject, *_time_range):
        try:
            stage = subject if spec.stage else subject.GetStage()
            prim = stage.GetPseudoRoot() if spec.stage else subject
            found = []
            for issue in spec.check(prim):
                _blocks[(issue.code, str(prim.GetPath()), issue.message)] = _blocked(spec, issue)
                found.append(
                    UsdValidation.ValidationError(
                        issue.code,
                        _SEVERITY.get(issue.severity, UsdValidation.ValidationErrorType.Warn),
                        [UsdValidation.ValidationErrorSite(stage, prim.GetPath())],
                        issue.message,
                    )
                )
            return found
        except Exception as exc:  # a bug in a rule: re-raised after validation (loudly)
            _failures.append(exc)
            return []

    return task


def register(specs: Iterable[ValidatorSpec]) -> list[UsdValidation.Validator]:
    """Register rules with USD's validation registry (once per name per process)."""
    registry = UsdValidation.ValidationRegistry()
    validators = []
    for spec in specs:
        name = PREFIX + spec.name
        if name not in _registered:
            if not registry.HasValidator(name):
                metadata = UsdValidation.ValidatorMetadata(
                    name=name, keywords=["rigspace"], doc=spec.doc, isSuite=False
                )
                if spec.stage:
                    registry.RegisterStageValidator(metadata, _usd_task(spec))
                else:
                    registry.RegisterPrimValidator(metadata, _usd_task(spec))
            _registered[name] = registry.GetOrLoadValidatorByName(name)
        validators.append(_registered[name])
    return validators


def _site_path(err: UsdValidation.ValidationError) -> str:
    """The prim or property a finding is about, else its layer ("" for the stage itself)."""
    for site in err.GetSites():
        if site.IsProperty() and site.GetProperty():
            return str(site.GetProperty().GetPath())
        if site.IsPrim() and site.GetPrim():
            path = site.GetPrim().GetPath()
            return "" if path == Sdf.Path.absoluteRootPath else str(path)
        if site.GetLayer():
            return site.GetLayer().identifier
    return ""


def validate(stage: Usd.Stage, include_usd: bool = True) -> list[Finding]:
    """Run USD's built-in validators (unless `include_usd` is false) and every rigspace rule.

    Findings are sorted by severity, prim and validator. A rigspace validator plugin that
    fails to load is reported as a warning; a rule that raises is our bug and re-raises.
    """
    specs, failed = rules()
    validators = register(specs)
    if include_usd:
        validators += [
            v
            for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
            if not v.GetMetadata().isSuite and not str(v.GetMetadata().name).startswith(PREFIX)
        ]
    _failures.clear()
    _blocks.clear()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    if _failures:
        raise _failures[0]
    findings = []
    for e in errors:
        if e.HasNoError():
            continue
        prim = _site_path(e)
        code, message = str(e.GetName()), e.GetMessage()
        findings.append(
            Finding(
                severity=ERROR
                if e.GetType() == UsdValidation.ValidationErrorType.Error
                else WARNING,
                validator=str(e.GetValidator().GetMetadata().name) if e.GetValidator() else "",
                code=code,
                prim=prim,
                message=message,
                blocks=_blocks.get((code, prim or "/", message), ()),
            )
        )
    findings += [
        Finding(WARNING, PREFIX + "plugins", "PluginFailed", "", f"validator plugin {n!r}: {why}")
        for n, why in failed.items()
    ]
    order = {ERROR: 0, WARNING: 1}
    return sorted(findings, key=lambda f: (order[f.severity], f.prim, f.validator, f.code))


# ---------------------------------------------------------------------------------------
# Refusing what a command cannot use


_warned: set[tuple[str, str]] = set()


def _read_prims(stage: Usd.Stage, prims: Sequence[Usd.Prim] | None) -> list[Usd.Prim]:
    """The prims a command reads: every prim, or the given characters and their skinned meshes."""
    if prims is None:
        return list(stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    read = []
    for prim in prims:
        read.append(prim)
        if schema.is_neural_character(prim):
            found, _ = resolve_character(prim)
            if found is not None:
                read += [query.GetPrim() for query in found.skel.skinning]
    return read


def require_valid(
    stage: Usd.Stage,
    purpose: str,
    prims: Sequence[Usd.Prim] | None = None,
    *,
    exception: type[RigspaceError] = SceneError,
    warn: Callable[[str], None] | None = None,
) -> None:
    """Refuse a scene that `purpose` ("capture" or "render") cannot use, in inspect's words.

    Runs the stage rules and, on `prims` (None: every prim of the stage; a neural character
    brings its skinned meshes), the rigspace rules whose errors stop `purpose`; raises one
    `exception` for them (a lone finding keeps its own type, e.g. BundleError).
    Warnings go to `warn` (default: stderr, once per stage and message).
    """
    if purpose not in PURPOSES:
        raise ValueError(f"purpose must be one of {PURPOSES}, got {purpose!r}")
    specs, _failed = rules()
    errors: list[Issue] = []
    targets = _read_prims(stage, prims)
    for spec in specs:
        if purpose not in spec.purposes:
            continue
        for prim in [stage.GetPseudoRoot()] if spec.stage else targets:
            for issue in spec.check(prim):
                if purpose not in (spec.purposes if issue.purposes is None else issue.purposes):
                    continue
                if issue.severity == ERROR:
                    errors.append(issue)
                elif warn is not None:
                    warn(issue.message)
                elif (stage.GetRootLayer().identifier, issue.message) not in _warned:
                    _warned.add((stage.GetRootLayer().identifier, issue.message))
                    print(f"rigspace {purpose}: warning: {issue.message}", file=sys.stderr)
    if len(errors) == 1:
        raise errors[0].as_error(exception)
    if errors:
        name = stage.GetRootLayer().identifier
        raise exception(
            f"Scene {name} has {len(errors)} problems that stop {purpose}:\n"
            + "\n".join(f"  - {issue.message}" for issue in errors)
            + "\n",
            f"fix each as it says (`rigspace inspect {name}` lists them all).",
        )

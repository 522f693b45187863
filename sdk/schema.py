"""Typed readers for the rigspace schemas (codeless, so USD generates no Python classes).

Each reader returns a frozen dataclass of plain Python values: the authored value where
there is one, else the schema's fallback. Nothing here raises on bad values; the
validators (`rigspace.sdk.validation`) judge them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

from pxr import Sdf, Usd, UsdSkel

from rigspace.sdk.controls import DEFAULT_RANGE, Control
from rigspace.usd_schemas import (
    CAPTURE_RING_API,
    CONTROL_API,
    CONTROL_NAMESPACE,
    LIVE_BINDING_API,
    LIVE_NAMESPACE,
    NEURAL_CHARACTER,
    POINT_CACHE_API,
    REGION_API,
    REGION_NAMESPACE,
)

CAPTURE_NS = "rigspace:captureRing:"


def _get(prim: Usd.Prim, name: str, default=None):
    attr = prim.GetAttribute(name)
    if not attr:
        return default
    value = attr.Get()
    return default if value is None else value


def _targets(prim: Usd.Prim, name: str) -> tuple[str, ...]:
    rel = prim.GetRelationship(name)
    return tuple(str(p) for p in rel.GetForwardedTargets()) if rel else ()


def is_neural_character(prim: Usd.Prim) -> bool:
    return prim.GetTypeName() == NEURAL_CHARACTER


def neural_characters(stage: Usd.Stage) -> list[Usd.Prim]:
    """Every active RigspaceNeuralCharacter prim on the stage, in traversal order."""
    return [p for p in stage.Traverse() if is_neural_character(p)]


@dataclass(frozen=True)
class CharacterAttributes:
    """The values a RigspaceNeuralCharacter prim authors (read_neural_character); the
    runtime's character, with its loaded model, is rigspace.runtime.character.NeuralCharacter."""

    path: str
    skeleton_targets: tuple[str, ...]
    animation_targets: tuple[str, ...]
    model: str
    """The authored asset path, as written (empty: no model)."""
    model_resolved: str
    """The asset path resolved by USD's asset resolver (empty when it does not resolve)."""
    maps: tuple[str, ...]
    look_at_joint: str
    training_distance: float
    training_focal_length: float
    training_aperture: float
    joints: tuple[str, ...]
    rotation_encoding: str
    applied_apis: tuple[str, ...] = ()

    @property
    def skeleton(self) -> str | None:
        return self.skeleton_targets[0] if len(self.skeleton_targets) == 1 else None


def read_neural_character(prim: Usd.Prim) -> CharacterAttributes:
    model = _get(prim, "rigspace:model")
    return CharacterAttributes(
        path=str(prim.GetPath()),
        skeleton_targets=_targets(prim, "rigspace:skeleton"),
        animation_targets=_targets(prim, "rigspace:animationSource"),
        model=model.path if model else "",
        model_resolved=model.resolvedPath if model else "",
        maps=tuple(_get(prim, "rigspace:maps", ())),
        look_at_joint=str(_get(prim, "rigspace:lookAtJoint", "")),
        training_distance=float(_get(prim, "rigspace:trainingCamera:distance", 0.0)),
        training_focal_length=float(_get(prim, "rigspace:trainingCamera:focalLength", 0.0)),
        training_aperture=float(_get(prim, "rigspace:trainingCamera:horizontalAperture", 0.0)),
        joints=tuple(_get(prim, "rigspace:joints", ())),
        rotation_encoding=str(_get(prim, "rigspace:rotationEncoding", "rot6d")),
        applied_apis=tuple(prim.GetAppliedSchemas()),
    )


@dataclass(frozen=True)
class CaptureRing:
    """The values of a RigspaceCaptureRingAPI."""

    views_per_ring: int
    elevations: tuple[float, ...]
    radius: float
    focal_length: float
    horizontal_aperture: float
    resolution: int
    clipping_range: tuple[float, float]
    look_at_joint: str
    clip_names: tuple[str, ...]
    clip_ranges: tuple[tuple[float, float], ...]
    held_out_clips: tuple[str, ...]
    held_out_views_per_ring: int
    held_out_elevations: tuple[float, ...]
    blend_shape_names: tuple[str, ...] = ()
    blend_shape_ranges: tuple[tuple[float, float], ...] = ()


def has_capture_ring(prim: Usd.Prim) -> bool:
    return CAPTURE_RING_API in prim.GetAppliedSchemas()


def read_capture_ring(prim: Usd.Prim) -> CaptureRing:
    def get(name, default=None):
        return _get(prim, CAPTURE_NS + name, default)

    clipping = get("clippingRange", (0.1, 1e4))
    return CaptureRing(
        views_per_ring=int(get("viewsPerRing", 12)),
        elevations=tuple(float(e) for e in get("elevations", (0.0,))),
        radius=float(get("radius", 0.0)),
        focal_length=float(get("focalLength", 50.0)),
        horizontal_aperture=float(get("horizontalAperture", 20.955)),
        resolution=int(get("resolution", 128)),
        clipping_range=(float(clipping[0]), float(clipping[1])),
        look_at_joint=str(get("lookAtJoint", "")),
        clip_names=tuple(str(n) for n in get("clipNames", ())),
        clip_ranges=tuple((float(r[0]), float(r[1])) for r in get("clipRanges", ())),
        held_out_clips=tuple(str(n) for n in get("heldOutClips", ())),
        held_out_views_per_ring=int(get("heldOutViewsPerRing", 0)),
        held_out_elevations=tuple(float(e) for e in get("heldOutElevations", ())),
        blend_shape_names=tuple(str(n) for n in get("blendShapeNames", ())),
        blend_shape_ranges=tuple((float(r[0]), float(r[1])) for r in get("blendShapeRanges", ())),
    )


@dataclass(frozen=True)
class LiveBinding:
    """One instance of the multiple-apply RigspaceLiveBindingAPI."""

    name: str
    url: str
    enabled: bool
    source_bones: tuple[str, ...]
    target_joints: tuple[str, ...]
    source_up_axis: str
    source_handedness: str
    source_meters_per_unit: float
    rest_pose: tuple[tuple[float, float, float, float], ...]
    """(w, x, y, z) per source bone."""
    smoothing: str
    smoothing_strength: float
    buffering: str
    """latest or delayed (a deprecated token authored is read as one of them)."""
    buffer_seconds: float
    """The delay of `delayed`, seconds; 0: one sample interval."""
    timeout_seconds: float
    lost_seconds: float = 0.0
    """Seconds without data before the binding is lost; 0: LOST_FACTOR x timeout_seconds."""
    bone_preset: str = "auto"
    gamepad_offsets: tuple[str, ...] = ()
    gamepad_clips: tuple[str, ...] = ()
    gamepad_shapes: tuple[str, ...] = ()
    buffering_authored: str = ""
    """The buffering token as authored when it was a deprecated one (validation warns)."""
    extra: dict = field(default_factory=dict)

    @property
    def lost_after(self) -> float:
        """Seconds without data before the binding is lost (lostSeconds, or its fallback)."""
        return self.lost_seconds if self.lost_seconds > 0 else LOST_FACTOR * self.timeout_seconds


LOST_FACTOR = 4.0
"""lostSeconds = 0 (the fallback) means this many timeoutSeconds."""
DEPRECATED_BUFFERING = {"interpolate": ("delayed", 0.0), "buffered": ("delayed", None)}
"""Buffering tokens of earlier schema versions -> (token, bufferSeconds; None: as authored)."""


class LiveBindingDeprecationWarning(FutureWarning):
    """A live binding authors a token this schema version only reads for old files
    (FutureWarning: shown by default, the user who authored the file can fix it)."""


def _wxyz(q) -> tuple[float, float, float, float]:
    x, y, z = q.GetImaginary()
    return (float(q.GetReal()), float(x), float(y), float(z))


def live_binding_names(prim: Usd.Prim) -> list[str]:
    prefix = LIVE_BINDING_API + ":"
    return [s[len(prefix) :] for s in prim.GetAppliedSchemas() if s.startswith(prefix)]


def read_live_bindings(prim: Usd.Prim) -> list[LiveBinding]:
    bindings = []
    for name in live_binding_names(prim):

        def get(prop, default=None, _name=name):
            return _get(prim, f"{LIVE_NAMESPACE}:{_name}:{prop}", default)

        rest = get("restPose", ())
        buffering = str(get("buffering", "latest"))
        buffer_seconds = float(get("bufferSeconds", 0.05))
        authored = ""
        if buffering in DEPRECATED_BUFFERING:
            authored = buffering
            buffering, seconds = DEPRECATED_BUFFERING[authored]
            buffer_seconds = buffer_seconds if seconds is None else seconds
            warnings.warn(
                f"{prim.GetPath()}: {LIVE_NAMESPACE}:{name}:buffering = {authored!r} is "
                f"deprecated; it is read as {buffering!r}"
                + (" with bufferSeconds = 0 (one sample interval)" if seconds == 0.0 else "")
                + '. Fix: author buffering = "delayed" (and bufferSeconds).',
                LiveBindingDeprecationWarning,
                stacklevel=2,
            )
        bindings.append(
            LiveBinding(
                name=name,
                url=str(get("url", "")),
                enabled=bool(get("enabled", True)),
                source_bones=tuple(get("sourceBones", ())),
                target_joints=tuple(get("targetJoints", ())),
                source_up_axis=str(get("sourceUpAxis", "Y")),
                source_handedness=str(get("sourceHandedness", "right")),
                source_meters_per_unit=float(get("sourceMetersPerUnit", 1.0)),
                rest_pose=tuple(_wxyz(q) for q in rest),
                smoothing=str(get("smoothing", "none")),
                smoothing_strength=float(get("smoothingStrength", 0.5)),
                buffering=buffering,
                buffer_seconds=buffer_seconds,
                timeout_seconds=float(get("timeoutSeconds", 0.5)),
                lost_seconds=float(get("lostSeconds", 0.0)),
                bone_preset=str(get("bonePreset", "auto")),
                gamepad_offsets=tuple(str(v) for v in get("gamepadOffsets", ())),
                gamepad_clips=tuple(str(v) for v in get("gamepadClips", ())),
                gamepad_shapes=tuple(str(v) for v in get("gamepadShapes", ())),
                buffering_authored=authored,
            )
        )
    return bindings


@dataclass(frozen=True)
class Region:
    """One instance of the multiple-apply RigspaceRegionAPI: a part of the character (the
    face, a hand) captured, trained and drawn at its own resolution around its own joint."""

    name: str
    joint: str
    """The joint its cameras look at and follow ("" when not authored: an error)."""
    joints: tuple[str, ...] = ()
    """Joints whose skinned surface is the region (empty: `joint` and those below it)."""
    blend_shapes: tuple[str, ...] = ()
    """Shapes drawn independently of the pose in its capture (empty: those that move it)."""
    blend_shape_range: tuple[float, float] = (0.0, 1.0)
    size: float = 0.0
    """Side in scene units of the square its cameras frame at the joint (0: derived)."""
    resolution: int = 64
    views_per_ring: int = 0
    """0: the capture ring's."""
    elevations: tuple[float, ...] = ()
    """Empty: the capture ring's."""
    upright: str = "stage"
    """What its cameras keep upright (UPRIGHT_TOKENS): "stage" (the stage's up axis, as the
    body's ring) or "joint" (the joint's own up: its images turn with the joint)."""


UPRIGHT_STAGE = "stage"
UPRIGHT_TOKENS = (UPRIGHT_STAGE, "joint")


def region_names(prim: Usd.Prim) -> list[str]:
    prefix = REGION_API + ":"
    return [s[len(prefix) :] for s in prim.GetAppliedSchemas() if s.startswith(prefix)]


def read_regions(prim: Usd.Prim) -> list[Region]:
    """The character's regions in their authored order (schema fallbacks where unauthored)."""
    regions = []
    for name in region_names(prim):

        def get(prop, default=None, _name=name):
            return _get(prim, f"{REGION_NAMESPACE}:{_name}:{prop}", default)

        low, high = get("blendShapeRange", (0.0, 1.0))
        regions.append(
            Region(
                name=name,
                joint=str(get("joint", "")),
                joints=tuple(str(j) for j in get("joints", ())),
                blend_shapes=tuple(str(b) for b in get("blendShapes", ())),
                blend_shape_range=(float(low), float(high)),
                size=float(get("size", 0.0)),
                resolution=int(get("resolution", 64)),
                views_per_ring=int(get("viewsPerRing", 0)),
                elevations=tuple(float(e) for e in get("elevations", ())),
                upright=str(get("upright", UPRIGHT_STAGE)),
            )
        )
    return regions


POINT_CACHE_MESHES = "rigspace:pointCache:meshes"


def has_point_cache(prim: Usd.Prim) -> bool:
    return POINT_CACHE_API in prim.GetAppliedSchemas()


def point_cache_targets(prim: Usd.Prim) -> tuple[str, ...]:
    """The targets of rigspace:pointCache:meshes (Meshes, or prims above them), as authored."""
    return _targets(prim, POINT_CACHE_MESHES)


def control_names(prim: Usd.Prim) -> list[str]:
    """The RigspaceControlAPI instances applied to `prim`, in their applied order (the rig
    vector's order)."""
    prefix = CONTROL_API + ":"
    return [s[len(prefix) :] for s in prim.GetAppliedSchemas() if s.startswith(prefix)]


def control_value_attribute(prim: Usd.Prim, name: str) -> Usd.Attribute:
    """The time-sampled value of control `name` (rigspace:control:NAME:value)."""
    return prim.GetAttribute(f"{CONTROL_NAMESPACE}:{name}:value")


def read_controls(prim: Usd.Prim) -> tuple[Control, ...]:
    """The character's controls (name and range; the schema's fallback range where
    unauthored) in their applied order. Their values are read per time code by posing."""
    controls = []
    for name in control_names(prim):
        value = _get(prim, f"{CONTROL_NAMESPACE}:{name}:range", DEFAULT_RANGE)
        controls.append(Control(name, tuple(float(v) for v in value)))
    return tuple(controls)


def skeleton_joints(skeleton_prim: Usd.Prim) -> list[str]:
    """The Skeleton's joint paths (UsdSkel order), e.g. 'pelvis/spine_01'."""
    return [str(j) for j in (UsdSkel.Skeleton(skeleton_prim).GetJointsAttr().Get() or [])]


class JointLookupError(KeyError):
    """A joint name that is missing from, or ambiguous in, a skeleton's joint list."""


def find_joint(name: str, joints: list[str]) -> int:
    """Index of `name` in a skeleton's joint paths: a full path or a unique last element."""
    if name in joints:
        return joints.index(name)
    matches = [i for i, j in enumerate(joints) if Sdf.Path(j).name == name]
    if len(matches) == 1:
        return matches[0]
    if matches:
        raise JointLookupError(
            f"joint name {name!r} is ambiguous: "
            + ", ".join(joints[i] for i in matches)
            + "; use the full joint path"
        )
    raise JointLookupError(f"joint {name!r} is not in the skeleton")


def resolve_model_path(character: CharacterAttributes) -> Path | None:
    """The manifest.json of the character's model bundle, or None when it does not resolve."""
    if not character.model_resolved:
        return None
    path = Path(character.model_resolved)
    if path.is_dir():
        path = path / "manifest.json"
    return path if path.is_file() else None

"""The rules for the capture ring and live binding APIs: values in range, clips, bone maps."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from urllib.parse import urlsplit

from pxr import Sdf, Usd

from rigspace.sdk import schema, timecodes
from rigspace.sdk.character_rules import (
    _missing_joints,
    _owner_is_character,
    animation_time_range,
    character_animation,
    character_blend_shapes,
    character_skeleton,
)
from rigspace.sdk.input_codes import CONTROL_CODES
from rigspace.sdk.issues import CAPTURE, RENDER, Issue, ValidatorSpec, error, warning

# Limits documented on the schema properties (usd_schemas/schema.usda).
MAX_VIEWS = 360
MAX_ELEVATION_DEG = 89.0
MIN_RESOLUTION, MAX_RESOLUTION = 16, 4096
MAX_BUFFER_SECONDS = 5.0
UNIT_QUAT_TOLERANCE = 1e-3


def _range_issue(ok: bool, code: str, message: str) -> Iterator[Issue]:
    if not ok:
        yield error(code, message)


_RING_NS = "rigspace:captureRing:"


def _out_of_range(path: Sdf.Path, prop: str, value: object, allowed: str) -> str:
    """The message for a capture ring property whose value is not allowed."""
    return (
        f"Capture ring on {path}: {_RING_NS}{prop} is {value}; allowed: {allowed}. Fix: author a "
        "value that is allowed."
    )


def _check_ring_views(path: Sdf.Path, ring: schema.CaptureRing) -> Iterator[Issue]:
    """viewsPerRing, elevations and heldOutElevations are in range."""
    yield from _range_issue(
        1 <= ring.views_per_ring <= MAX_VIEWS,
        "ViewsOutOfRange",
        _out_of_range(path, "viewsPerRing", ring.views_per_ring, f"1 to {MAX_VIEWS}"),
    )
    bad_elevations = [e for e in ring.elevations if not abs(e) <= MAX_ELEVATION_DEG]
    yield from _range_issue(
        bool(ring.elevations) and not bad_elevations,
        "ElevationOutOfRange",
        _out_of_range(
            path,
            "elevations",
            list(ring.elevations),
            f"[-{MAX_ELEVATION_DEG:g}, {MAX_ELEVATION_DEG:g}] degrees, at least one ring",
        ),
    )
    bad_held = [e for e in ring.held_out_elevations if not abs(e) <= MAX_ELEVATION_DEG]
    yield from _range_issue(
        not bad_held,
        "ElevationOutOfRange",
        _out_of_range(
            path,
            "heldOutElevations",
            bad_held,
            f"[-{MAX_ELEVATION_DEG:g}, {MAX_ELEVATION_DEG:g}]",
        ),
    )


def _check_ring_camera(path: Sdf.Path, ring: schema.CaptureRing) -> Iterator[Issue]:
    """radius, lens, resolution and clippingRange are in range; the radius inside the clipping."""
    yield from _range_issue(
        math.isfinite(ring.radius) and ring.radius >= 0,
        "RadiusOutOfRange",
        _out_of_range(
            path, "radius", ring.radius, "> 0 scene units, or 0 to derive it from the bounds"
        ),
    )
    for prop, value in (
        ("focalLength", ring.focal_length),
        ("horizontalAperture", ring.horizontal_aperture),
    ):
        yield from _range_issue(
            math.isfinite(value) and value > 0,
            "LensOutOfRange",
            _out_of_range(path, prop, value, "> 0 tenths of a scene unit"),
        )
    res = ring.resolution
    yield from _range_issue(
        MIN_RESOLUTION <= res <= MAX_RESOLUTION and res & (res - 1) == 0,
        "ResolutionNotPowerOfTwo",
        _out_of_range(
            path, "resolution", res, f"a power of two from {MIN_RESOLUTION} to {MAX_RESOLUTION}"
        ),
    )
    near, far = ring.clipping_range
    yield from _range_issue(
        0 < near < far and math.isfinite(far),
        "ClippingOutOfRange",
        _out_of_range(path, "clippingRange", (near, far), "0 < near < far"),
    )
    if ring.radius > 0 and 0 < near < far:
        yield from _range_issue(
            near < ring.radius < far,
            "RadiusOutsideClipping",
            f"Capture ring on {path}: {_RING_NS}radius {ring.radius:g} puts the look-at joint "
            f"outside the clipping range ({near:g}, {far:g}), so the character would be clipped "
            "away. Fix: author a radius between near and far, or widen clippingRange.",
        )


def check_capture_ring(prim: Usd.Prim) -> Iterator[Issue]:
    if not schema.has_capture_ring(prim):
        return
    yield from _owner_is_character(prim, "RigspaceCaptureRingAPI")
    path = prim.GetPath()
    ring = schema.read_capture_ring(prim)
    yield from _check_ring_views(path, ring)
    yield from _check_ring_camera(path, ring)
    yield from _range_issue(
        0 <= ring.held_out_views_per_ring <= ring.views_per_ring,
        "HeldOutViewsOutOfRange",
        _out_of_range(
            path,
            "heldOutViewsPerRing",
            ring.held_out_views_per_ring,
            f"0 to {ring.views_per_ring}",
        ),
    )
    yield from _check_clips(prim, ring)
    yield from _check_blend_ranges(prim, ring)


def _check_blend_ranges(prim: Usd.Prim, ring: schema.CaptureRing) -> Iterator[Issue]:
    """blendShapeNames/blendShapeRanges: parallel, finite low <= high, unique names that the
    character's skinned meshes list in skel:blendShapes."""
    path = prim.GetPath()
    names, ranges = ring.blend_shape_names, ring.blend_shape_ranges
    if len(names) != len(ranges):
        yield error(
            "BlendRangesDisagree",
            f"Capture ring on {path}: {len(names)} blendShapeNames but {len(ranges)} "
            "blendShapeRanges. Fix: author one (low, high) weight range per name.",
        )
        return
    bad = [
        f"{n} ({a:g}, {b:g})"
        for n, (a, b) in zip(names, ranges, strict=True)
        if not (math.isfinite(a) and math.isfinite(b) and a <= b)
    ]
    if bad:
        yield error(
            "BlendRangeInvalid",
            f"Capture ring on {path}: blendShapeRanges {', '.join(bad)} are not finite "
            "(low, high) pairs with low <= high. Fix: author finite ranges, low first.",
        )
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        yield error(
            "BlendShapeRepeated",
            f"Capture ring on {path}: blendShapeNames repeats {', '.join(repeated)}. Fix: name "
            "each shape once.",
        )
    if names and schema.is_neural_character(prim):
        known = character_blend_shapes(prim)
        unknown = [n for n in names if n not in known]
        if unknown:
            yield error(
                "BlendShapeUnknown",
                f"Capture ring on {path}: blendShapeNames {', '.join(unknown)} are not blend "
                f"shapes of the character's meshes ({', '.join(known) or 'it has none'}). Fix: "
                "name shapes from the meshes' skel:blendShapes.",
            )


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
    yield from _clips_in_animation(prim, ring)
    yield from _ring_look_at_joint(prim, ring)


def _clips_in_animation(prim: Usd.Prim, ring: schema.CaptureRing) -> Iterator[Issue]:
    """The clips lie inside the character's animation, as capture fits them (sdk/timecodes.py):
    an end within the tolerance is the same frame, a clip reaching past the range is clamped,
    one wholly outside is refused."""
    path = prim.GetPath()
    anim = character_animation(prim) if schema.is_neural_character(prim) else None
    span = animation_time_range(anim) if anim is not None else None
    if anim is None or span is None:
        return
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


def _ring_look_at_joint(prim: Usd.Prim, ring: schema.CaptureRing) -> Iterator[Issue]:
    """lookAtJoint names a joint of the character's skeleton."""
    skeleton = character_skeleton(prim) if schema.is_neural_character(prim) else None
    if skeleton is not None and ring.look_at_joint:
        missing = _missing_joints([ring.look_at_joint], schema.skeleton_joints(skeleton))
        if missing:
            yield error(
                "LookAtJointMissing",
                f"Capture ring on {prim.GetPath()}: lookAtJoint {ring.look_at_joint!r} is not a "
                f"joint of {skeleton.GetPath()}. Fix: name a joint from its joint list.",
            )


URL_SCHEME = re.compile(r"^[a-z][a-z0-9+.-]*$")
SMOOTHING = ("none", "exponential", "oneEuro")
BUFFERING = ("latest", "delayed")
BONE_PRESETS = ("auto", "none", "unityHumanoid", "cmu", "mixamo")
GAMEPAD_OFFSET = re.compile(
    r"^(ABS|BTN)_[A-Z0-9]+:[^:\s]+:[XYZ]:[-+]?[0-9.]+(e[-+]?[0-9]+)?(:-?[0-9]+:-?[0-9]+)?$"
)
GAMEPAD_CLIP = re.compile(r"^(ABS|BTN)_[A-Z0-9]+:[^:\s]+(:-?[0-9]+:-?[0-9]+)?$")


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
        yield from _check_binding(prim, b, skeleton)


def _check_binding(
    prim: Usd.Prim, b: schema.LiveBinding, skeleton: Usd.Prim | None
) -> Iterator[Issue]:
    """One live binding: its URL parses, its bone map fits the skeleton, its rest pose the
    bones, its tokens are current and known, and its values are in range."""
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
    yield from _rest_pose_issues(b, where)
    if b.buffering_authored:
        yield warning(
            "DeprecatedToken",
            f"{where}: {ns}buffering = {b.buffering_authored!r} is a token of an earlier "
            f'schema, read as {b.buffering!r}. Fix: author buffering = "delayed" (the '
            "delay is bufferSeconds; 0: one sample interval).",
        )
    yield from _preset_and_gamepad(prim, b, where, ns, skeleton)
    yield from _binding_values(b, where, ns)


def _rest_pose_issues(b: schema.LiveBinding, where: str) -> Iterator[Issue]:
    """restPose, when authored, holds one unit quaternion per bone."""
    if not b.rest_pose:
        return
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


def _binding_values(b: schema.LiveBinding, where: str, ns: str) -> Iterator[Issue]:
    """smoothingStrength, bufferSeconds, timeoutSeconds, lostSeconds and
    sourceMetersPerUnit are in range."""
    for ok, prop, value, allowed in (
        (0 <= b.smoothing_strength < 1, "smoothingStrength", b.smoothing_strength, "[0, 1)"),
        (
            0 <= b.buffer_seconds <= MAX_BUFFER_SECONDS,
            "bufferSeconds",
            b.buffer_seconds,
            f"[0, {MAX_BUFFER_SECONDS:g}]",
        ),
        (b.timeout_seconds > 0, "timeoutSeconds", b.timeout_seconds, "> 0"),
        (
            b.lost_seconds == 0 or b.lost_seconds > b.timeout_seconds,
            "lostSeconds",
            b.lost_seconds,
            f"0 or > timeoutSeconds ({b.timeout_seconds:g})",
        ),
        (b.source_meters_per_unit > 0, "sourceMetersPerUnit", b.source_meters_per_unit, "> 0"),
    ):
        if not ok:
            yield error(
                "ValueOutOfRange",
                f"{where}: {ns}{prop} is {value}; allowed: {allowed}. Fix: author a value "
                "that is allowed.",
            )


def _preset_and_gamepad(
    prim: Usd.Prim, b: schema.LiveBinding, where: str, ns: str, skeleton: Usd.Prim | None
) -> Iterator[Issue]:
    """bonePreset is a known token; gamepadOffsets/gamepadClips parse, name joints of the
    skeleton and clips of the character's capture ring, and sit on a gamepad:// binding."""
    if b.bone_preset not in BONE_PRESETS:
        yield error(
            "BadToken",
            f"{where}: {ns}bonePreset {b.bone_preset!r} is not a preset. Fix: author one of "
            f"{', '.join(BONE_PRESETS)}.",
        )
    if not (b.gamepad_offsets or b.gamepad_clips or b.gamepad_shapes):
        return
    if not b.url.lower().startswith("gamepad://"):
        yield warning(
            "GamepadMapUnused",
            f"{where}: gamepadOffsets/Clips/Shapes are authored but the url {b.url!r} is not a "
            "gamepad:// source, so they are ignored. Fix: remove them or bind a gamepad://.",
        )
    joints = schema.skeleton_joints(skeleton) if skeleton is not None else None
    for prop, items, pattern, form in (
        (
            "gamepadOffsets",
            b.gamepad_offsets,
            GAMEPAD_OFFSET,
            "CONTROL:JOINT:AXIS:DEGREES[:MIN:MAX]",
        ),
        ("gamepadClips", b.gamepad_clips, GAMEPAD_CLIP, "CONTROL:CLIP[:MIN:MAX]"),
        ("gamepadShapes", b.gamepad_shapes, GAMEPAD_CLIP, "CONTROL:SHAPE[:MIN:MAX]"),
    ):
        for item in items:
            code = item.split(":", 1)[0]
            if not pattern.match(item) or code not in CONTROL_CODES:
                yield _bad_gamepad_map(where, ns, prop, item, form)
                continue
            yield from _gamepad_target_issues(prim, where, ns, prop, item, skeleton, joints)


def _bad_gamepad_map(where: str, ns: str, prop: str, item: str, form: str) -> Issue:
    """The error for a gamepad entry that does not parse or names no known evdev control."""
    return error(
        "BadGamepadMap",
        f"{where}: {ns}{prop} entry {item!r} is not {form} with a known evdev "
        "control. Fix: write it like "
        + {
            "gamepadOffsets": "'ABS_RX:head:Y:-60'",
            "gamepadClips": "'ABS_RZ:wave'",
        }.get(prop, "'ABS_Z:jawOpen'")
        + " (controls: ABS_X, ABS_Y, ABS_Z, ABS_RX, ABS_RY, ABS_RZ, ABS_HAT0X, "
        "ABS_HAT0Y, ABS_GAS, ABS_BRAKE, BTN_SOUTH, BTN_EAST, ...).",
    )


def _gamepad_target_issues(
    prim: Usd.Prim,
    where: str,
    ns: str,
    prop: str,
    item: str,
    skeleton: Usd.Prim | None,
    joints: list[str] | None,
) -> Iterator[Issue]:
    """A parsed gamepad entry names what it drives: a joint of the skeleton (gamepadOffsets),
    a blend shape of the character's meshes (gamepadShapes), a clip of its capture ring
    (gamepadClips)."""
    name = item.split(":")[1]
    missing = joints is not None and _missing_joints((name,), joints)
    if prop == "gamepadOffsets" and skeleton is not None and missing:
        yield error(
            "TargetJointsMissing",
            f"{where}: {ns}gamepadOffsets entry {item!r} names joint {name!r}, which "
            f"skeleton {skeleton.GetPath()} lacks. Fix: use a name from its joint list.",
        )
    if prop == "gamepadShapes" and schema.is_neural_character(prim):
        shapes = character_blend_shapes(prim)
        if name not in shapes:
            yield error(
                "BlendShapeUnknown",
                f"{where}: {ns}gamepadShapes entry {item!r} names blend shape "
                f"{name!r}, which the character's meshes lack "
                f"({', '.join(shapes) or 'they have none'}). Fix: name one of them.",
            )
    if prop == "gamepadClips":
        clips = schema.read_capture_ring(prim).clip_names if schema.has_capture_ring(prim) else ()
        if name not in clips:
            yield error(
                "ClipMissing",
                f"{where}: {ns}gamepadClips entry {item!r} names clip {name!r}, which "
                f"{prim.GetPath()} does not name in rigspace:captureRing:clipNames "
                f"({', '.join(clips) or 'none'}). Fix: name one of them, or add the clip "
                "(clipNames and clipRanges).",
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

"""Scene validation: USD's own validators plus rigspace's, run through UsdValidation.

A rigspace validator is a `ValidatorSpec` (plugin kind "validator", entry-point group
`rigspace.validators`): a function from a prim to `Issue`s. Each is registered in USD's
`UsdValidation.ValidationRegistry` as `rigspace:<name>` and runs in the same
`ValidationContext` as USD's built-in validators, so every finding has the same shape:
severity, validator, prim and a message that names the fix. Rules report, never raise.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from urllib.parse import urlsplit

from pxr import Usd, UsdSkel, UsdValidation

from rigspace.sdk import schema
from rigspace.sdk.bundle import BundleError, read_manifest
from rigspace.sdk.plugins import Kind, discover

ERROR = "error"
WARNING = "warning"
PREFIX = "rigspace:"

# Limits documented on the schema properties (usd_schemas/schema.usda).
MAX_VIEWS = 360
MAX_ELEVATION_DEG = 89.0
MIN_RESOLUTION, MAX_RESOLUTION = 16, 4096
MAX_BUFFER_SECONDS = 5.0
UNIT_QUAT_TOLERANCE = 1e-3
MAPS = ("albedo", "normal", "depth", "mask")


@dataclass(frozen=True)
class Issue:
    """One finding of a rigspace rule; the prim defaults to the prim being checked."""

    severity: str
    code: str
    message: str


@dataclass(frozen=True)
class ValidatorSpec:
    """A scene rule: `check(prim)` yields the issues it finds on that prim."""

    name: str
    doc: str
    check: Callable[[Usd.Prim], Iterable[Issue]]


VALIDATORS: Kind[ValidatorSpec] = Kind("validator", "rigspace.validators", ValidatorSpec)


@dataclass(frozen=True)
class Finding:
    """A validation result from any validator, USD's or ours."""

    severity: str
    validator: str
    code: str
    prim: str
    message: str

    def as_dict(self) -> dict[str, str]:
        return {
            "severity": self.severity,
            "validator": self.validator,
            "code": self.code,
            "prim": self.prim,
            "message": self.message,
        }


def error(code: str, message: str) -> Issue:
    return Issue(ERROR, code, message)


def warning(code: str, message: str) -> Issue:
    return Issue(WARNING, code, message)


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
    """The SkelAnimation driving a neural character: its own relationship, else the skeleton's."""
    stage = prim.GetStage()
    targets = schema.read_neural_character(prim).animation_targets
    if targets:
        anim = stage.GetPrimAtPath(targets[0])
        return anim if anim and anim.IsA(UsdSkel.Animation) else None
    skel = character_skeleton(prim)
    if skel is None:
        return None
    source = UsdSkel.BindingAPI(skel).GetAnimationSource()
    return source if source and source.IsA(UsdSkel.Animation) else None


def animation_time_range(anim: Usd.Prim) -> tuple[float, float] | None:
    """First and last time sample over the animation's rotations and translations."""
    samples: list[float] = []
    skel_anim = UsdSkel.Animation(anim)
    for attr in (skel_anim.GetRotationsAttr(), skel_anim.GetTranslationsAttr()):
        samples += attr.GetTimeSamples()
    return (min(samples), max(samples)) if samples else None


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


def check_character_skeleton(prim: Usd.Prim) -> Iterator[Issue]:
    if not schema.is_neural_character(prim):
        return
    path = prim.GetPath()
    character = schema.read_neural_character(prim)
    stage = prim.GetStage()
    if not character.skeleton_targets:
        yield error(
            "NoSkeleton",
            f"Neural character {path} has no rigspace:skeleton target. Fix: point "
            "rigspace:skeleton at the UsdSkel Skeleton that drives the character.",
        )
        return
    if len(character.skeleton_targets) > 1:
        yield error(
            "SeveralSkeletons",
            f"Neural character {path} has {len(character.skeleton_targets)} rigspace:skeleton "
            f"targets ({', '.join(character.skeleton_targets)}). Fix: keep exactly one.",
        )
        return
    target_path = character.skeleton_targets[0]
    target = stage.GetPrimAtPath(target_path)
    if not target:
        yield error(
            "SkeletonMissing",
            f"Neural character {path}: rigspace:skeleton targets {target_path}, which does not "
            "exist on the stage. Fix: correct the path, or load the layer that defines it.",
        )
        return
    if not target.IsA(UsdSkel.Skeleton):
        yield error(
            "NotASkeleton",
            f"Neural character {path}: rigspace:skeleton targets {target_path}, a "
            f"{target.GetTypeName() or 'untyped prim'}, not a Skeleton. Fix: target the "
            "Skeleton prim (UsdSkel) instead.",
        )
        return
    joints = schema.skeleton_joints(target)
    if not joints:
        yield error(
            "EmptySkeleton",
            f"Skeleton {target_path} (rigspace:skeleton of {path}) has no joints. Fix: author "
            "its joints, bindTransforms and restTransforms.",
        )
        return
    for anim_path in character.animation_targets[:1]:
        anim = stage.GetPrimAtPath(anim_path)
        if not anim or not anim.IsA(UsdSkel.Animation):
            kind = anim.GetTypeName() if anim else "nothing"
            yield error(
                "NotAnAnimation",
                f"Neural character {path}: rigspace:animationSource targets {anim_path} "
                f"({kind}), not a SkelAnimation. Fix: target a SkelAnimation prim, or clear the "
                "relationship to use the skeleton's own binding.",
            )
    if not character.animation_targets and character_animation(prim) is None:
        yield warning(
            "NoAnimation",
            f"Neural character {path}: neither it nor its skeleton {target_path} has an "
            "animation source, so it holds the rest pose. Fix: set rigspace:animationSource "
            "or the skeleton's skel:animationSource to a SkelAnimation.",
        )
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
        yield error("BadModel", f"Neural character {path}: {exc}")
        return
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
        outside = [
            f"{n} ({a:g}-{b:g})"
            for n, (a, b) in zip(ring.clip_names, ring.clip_ranges, strict=True)
            if a < span[0] or b > span[1]
        ]
        if outside:
            yield error(
                "ClipOutsideAnimation",
                f"Capture ring on {path}: clips {', '.join(outside)} fall outside the animation "
                f"{anim.GetPath()} ({span[0]:g}-{span[1]:g}). Fix: clip to the animated range.",
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


CHARACTER_SKELETON = ValidatorSpec(
    "CharacterSkeleton",
    "A neural character targets exactly one Skeleton, its joints and animation exist.",
    check_character_skeleton,
)
CHARACTER_MODEL = ValidatorSpec(
    "CharacterModel",
    "A neural character's model bundle resolves, reads, and fits its skeleton.",
    check_character_model,
)
CAPTURE_RING = ValidatorSpec(
    "CaptureRing",
    "Capture ring values are in range and its clips lie inside the animation.",
    check_capture_ring,
)
LIVE_BINDING = ValidatorSpec(
    "LiveBinding",
    "Live bindings have parseable URLs and bone maps that fit the skeleton.",
    check_live_binding,
)


# ---------------------------------------------------------------------------------------
# Registration with UsdValidation and running


_SEVERITY = {ERROR: UsdValidation.ValidationErrorType.Error}
_registered: dict[str, UsdValidation.Validator] = {}
_failures: list[BaseException] = []


def _usd_task(spec: ValidatorSpec):
    def task(prim, *_time_range):
        try:
            return [
                UsdValidation.ValidationError(
                    issue.code,
                    _SEVERITY.get(issue.severity, UsdValidation.ValidationErrorType.Warn),
                    [UsdValidation.ValidationErrorSite(prim.GetStage(), prim.GetPath())],
                    issue.message,
                )
                for issue in spec.check(prim)
            ]
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
                registry.RegisterPrimValidator(metadata, _usd_task(spec))
            _registered[name] = registry.GetOrLoadValidatorByName(name)
        validators.append(_registered[name])
    return validators


def _site_path(err: UsdValidation.ValidationError) -> str:
    """The prim or property a finding is about, else its layer."""
    for site in err.GetSites():
        if site.IsProperty() and site.GetProperty():
            return str(site.GetProperty().GetPath())
        if site.IsPrim() and site.GetPrim():
            return str(site.GetPrim().GetPath())
        if site.GetLayer():
            return site.GetLayer().identifier
    return ""


def validate(stage: Usd.Stage, include_usd: bool = True) -> list[Finding]:
    """Run USD's built-in validators (unless `include_usd` is false) and every rigspace rule.

    Findings are sorted by severity, prim and validator. A rigspace validator plugin that
    fails to load is reported as a warning; a rule that raises is our bug and re-raises.
    """
    plugins = discover(VALIDATORS)
    validators = register(plugins)
    if include_usd:
        validators += [
            v
            for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
            if not v.GetMetadata().isSuite and not str(v.GetMetadata().name).startswith(PREFIX)
        ]
    _failures.clear()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    if _failures:
        raise _failures[0]
    findings = [
        Finding(
            severity=ERROR if e.GetType() == UsdValidation.ValidationErrorType.Error else WARNING,
            validator=str(e.GetValidator().GetMetadata().name) if e.GetValidator() else "",
            code=str(e.GetName()),
            prim=_site_path(e),
            message=e.GetMessage(),
        )
        for e in errors
        if not e.HasNoError()
    ]
    findings += [
        Finding(WARNING, PREFIX + "plugins", "PluginFailed", "", f"validator plugin {n!r}: {why}")
        for n, why in plugins.failed.items()
    ]
    order = {ERROR: 0, WARNING: 1}
    return sorted(findings, key=lambda f: (order[f.severity], f.prim, f.validator, f.code))

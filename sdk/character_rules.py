"""The rules for the stage and its neural characters: units, bindings, animation, model, textures.

`resolve_character` is also what posing (`CharacterRig`) runs, so inspect reports exactly
what capture and the runtime refuse to pose, in the same words.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSkel

from rigspace.sdk import schema
from rigspace.sdk.bindings import SkelBinding, ignored_animation_sources, skel_binding
from rigspace.sdk.bundle import BundleError, ModelManifest, read_manifest
from rigspace.sdk.geometry import albedo_texture
from rigspace.sdk.issues import CAPTURE, RENDER, Issue, ValidatorSpec, error, warning
from rigspace.sdk.stage import unreadable_layers

MAPS = ("albedo", "normal", "depth", "mask")
UP_AXES = ("Y", "Z")


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


def blend_shape_names(skinning: Iterable[UsdSkel.SkinningQuery]) -> tuple[str, ...]:
    """A character's blend shapes: every name its skinned meshes' skel:blendShapes list, in
    the order first met (meshes in skinning order). The order of its weight vector."""
    names: list[str] = []
    for query in skinning:
        if query.HasBlendShapes():
            names += [str(n) for n in query.GetBlendShapeOrder() if str(n) not in names]
    return tuple(names)


def character_blend_shapes(prim: Usd.Prim) -> tuple[str, ...]:
    """The blend shapes of a neural character's skinned meshes (() when it does not resolve)."""
    found, _ = resolve_character(prim)
    return blend_shape_names(found.skel.skinning) if found else ()


def animation_time_range(anim: Usd.Prim) -> tuple[float, float] | None:
    """First and last time sample over the animation's rotations and translations."""
    samples: list[float] = []
    skel_anim = UsdSkel.Animation(anim)
    for attr in (skel_anim.GetRotationsAttr(), skel_anim.GetTranslationsAttr()):
        samples += attr.GetTimeSamples()
    return (min(samples), max(samples)) if samples else None


@dataclass
class CharacterBinding:
    """A neural character's skeleton, animation and skinned meshes, resolved as UsdSkel does,
    and its point-cached meshes (RigspacePointCacheAPI), which are drawn as the stage
    evaluates them and never skinned."""

    skeleton: Usd.Prim
    joints: list[str]
    animation: Usd.Prim
    skel: SkelBinding = field(repr=False)
    cached: list[Usd.Prim] = field(default_factory=list)
    """The point-cached Meshes, in the order rigspace:pointCache:meshes reaches them."""


def point_cached_meshes(prim: Usd.Prim) -> tuple[list[Usd.Prim], Issue | None]:
    """The visible Meshes rigspace:pointCache:meshes reaches (a Mesh target, or every Mesh
    below another target), in order, each once; or the first target that cannot be used."""
    if not schema.has_point_cache(prim):
        return [], None
    stage, path = prim.GetStage(), prim.GetPath()
    meshes: list[Usd.Prim] = []
    targets = schema.point_cache_targets(prim)
    if not targets:
        return [], error(
            "PointCacheEmpty",
            f"Neural character {path} has RigspacePointCacheAPI applied but "
            f"{schema.POINT_CACHE_MESHES} targets nothing. Fix: target the point-cached Meshes "
            "(or a prim above them), or remove the API.",
        )
    for target in targets:
        found = stage.GetPrimAtPath(target)
        if not found:
            return [], error(
                "PointCacheTargetMissing",
                f"Neural character {path}: {schema.POINT_CACHE_MESHES} targets {target}, which "
                "does not exist on the stage. Fix: correct the path, or load the layer that "
                "defines it.",
            )
        below = [
            p
            for p in Usd.PrimRange(found, Usd.TraverseInstanceProxies())
            if p.IsA(UsdGeom.Mesh)
            and UsdGeom.Imageable(p).ComputeVisibility() != UsdGeom.Tokens.invisible
        ]
        if not below:
            return [], error(
                "PointCacheNoMesh",
                f"Neural character {path}: {schema.POINT_CACHE_MESHES} targets {target} "
                f"({found.GetTypeName() or 'untyped prim'}), which is not a visible Mesh and has "
                "none below it. Fix: target the point-cached Mesh prims.",
            )
        meshes += [m for m in below if m not in meshes]
    return meshes, None


def resolve_character(prim: Usd.Prim) -> tuple[CharacterBinding | None, Issue | None]:
    """What posing a neural character needs (`CharacterRig`), or the first error that stops it.

    In order: exactly one rigspace:skeleton target that is a Skeleton with joints; a
    SkelAnimation (rigspace:animationSource, else the one UsdSkel binds); the point-cached
    meshes when it declares them (RigspacePointCacheAPI); a skinned or point-cached Mesh.
    A point-cached mesh is left out of the skinned ones (it is drawn from its cache).
    """
    path = prim.GetPath()
    character = schema.read_neural_character(prim)
    targets = character.skeleton_targets
    target, problem = _skeleton_target(prim, targets)
    if target is None:
        return None, problem
    joints = schema.skeleton_joints(target)
    if not joints:
        return None, error(
            "EmptySkeleton",
            f"Skeleton {targets[0]} (rigspace:skeleton of {path}) has no joints. Fix: author "
            "its joints, bindTransforms and restTransforms.",
        )
    binding = skel_binding(target)
    anim, problem = _animation_source(prim, character, target, binding)
    if anim is None:
        return None, problem
    cached, problem = point_cached_meshes(prim)
    if problem is not None:
        return None, problem
    binding.skinning = [q for q in binding.skinning if q.GetPrim() not in cached]
    if not binding.skinning and not cached:
        return None, error(
            "NoSkinnedMesh",
            f"Neural character {path}: no skinned mesh is bound to skeleton {targets[0]} (a "
            "visible Mesh under its SkelRoot with primvars:skel:jointIndices and jointWeights), "
            "and it declares no point-cached mesh. Fix: bind the character's meshes to the "
            "skeleton with UsdSkelBindingAPI skin weights, or apply RigspacePointCacheAPI and "
            f"target its point-cached meshes with {schema.POINT_CACHE_MESHES}.",
        )
    return CharacterBinding(target, joints, anim, binding, cached), None


def _skeleton_target(
    prim: Usd.Prim, targets: tuple[str, ...]
) -> tuple[Usd.Prim | None, Issue | None]:
    """The one Skeleton rigspace:skeleton targets, or why there is none."""
    path = prim.GetPath()
    if len(targets) != 1:
        listed = f"it has {len(targets)}: {', '.join(targets)}" if targets else "it has none"
        code = "SeveralSkeletons" if targets else "NoSkeleton"
        return None, error(
            code,
            f"Neural character {path} has no single rigspace:skeleton target ({listed}). Fix: "
            "point rigspace:skeleton at the one UsdSkel Skeleton that drives the character.",
        )
    target = prim.GetStage().GetPrimAtPath(targets[0])
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
    return target, None


def _animation_source(
    prim: Usd.Prim,
    character: schema.CharacterAttributes,
    skeleton: Usd.Prim,
    binding: SkelBinding,
) -> tuple[Usd.Prim | None, Issue | None]:
    """The SkelAnimation rigspace:animationSource targets, else the one UsdSkel binds to the
    skeleton; or why there is none."""
    path = prim.GetPath()
    targets = character.animation_targets
    if targets:
        anim = prim.GetStage().GetPrimAtPath(targets[0])
        if not anim or not anim.IsA(UsdSkel.Animation):
            kind = anim.GetTypeName() if anim else "nothing"
            return None, error(
                "NotAnAnimation",
                f"Neural character {path}: rigspace:animationSource targets {targets[0]} "
                f"({kind}), not a SkelAnimation. Fix: target a SkelAnimation prim, or clear the "
                "relationship to use the skeleton's own binding.",
            )
        return anim, None
    if binding.animation is not None:
        return binding.animation, None
    ignored = ignored_animation_sources(skeleton)
    hint = (
        f" ({', '.join(ignored)} authors skel:animationSource without SkelBindingAPI, so "
        "UsdSkel ignores it: apply the API there)"
        if ignored
        else ""
    )
    return None, error(
        "NoAnimation",
        f"Neural character {path}: skeleton {character.skeleton_targets[0]} has no animation "
        "(neither rigspace:animationSource nor a skel:animationSource on the skeleton or an "
        f"ancestor names a SkelAnimation){hint}. Fix: bind a SkelAnimation to the skeleton or its "
        "SkelRoot, or set rigspace:animationSource.",
    )


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


def unreadable_layer_issues(stage: Usd.Stage) -> Iterator[Issue]:
    """An UnreadableLayer error per layer of the stage USD cannot read (sdk.stage.
    unreadable_layers): the stage rule's findings, and what capture and render refuse before
    they look for a character or a camera such a layer may hold (validation.require_readable)."""
    name = stage.GetRootLayer().identifier
    for asset, why in unreadable_layers(stage):
        yield error(
            "UnreadableLayer",
            f"Stage {name} uses the layer @{asset}@, which USD cannot read: {why} Whatever it "
            "holds (a character, its skeleton, its meshes, a camera) is missing from the scene. "
            "Fix: restore or re-export that file, or remove the reference to it.",
        )


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
    yield from unreadable_layer_issues(stage)
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
    manifest, problem = _character_manifest(character, path)
    if manifest is None:
        if problem is not None:
            yield problem
        return
    yield from _graph_issues(manifest, path)
    yield from _model_blend_shape_issues(prim, manifest, path)
    yield from _model_control_issues(prim, manifest, path)
    yield from _model_joint_issues(prim, manifest, path)
    yield from _character_disagreements(character, manifest, path)


def _character_manifest(
    character: schema.CharacterAttributes, path: Sdf.Path
) -> tuple[ModelManifest | None, Issue | None]:
    """The manifest of the bundle rigspace:model names, or why there is none (a warning when
    it names none)."""
    if not character.model:
        return None, warning(
            "NoModel",
            f"Neural character {path} has no model bundle (rigspace:model is empty): it can be "
            "captured but the runtime cannot draw it. Fix: train one with `rigspace train` and "
            "set rigspace:model to the bundle folder, or draw it with `rigspace render --model "
            "BUNDLE`.",
        )
    manifest_file = schema.resolve_model_path(character)
    if manifest_file is None:
        return None, error(
            "ModelNotFound",
            f"Neural character {path}: rigspace:model @{character.model}@ does not resolve to a "
            "bundle folder or manifest.json. Fix: correct the path (relative paths are relative "
            "to the layer that authors them) or export the bundle there.",
        )
    try:
        return read_manifest(manifest_file), None
    except BundleError as exc:
        return None, error("BadModel", f"Neural character {path}: {exc}", exception=BundleError)


def _graph_issues(manifest: ModelManifest, path: Sdf.Path) -> Iterator[Issue]:
    """The bundle's graphs load (a manifest alone has none to load)."""
    if manifest.trunk is not None or manifest.levels:
        from rigspace.sdk.model import graphs_problem  # onnxruntime, only once a bundle resolves

        problem = graphs_problem(manifest.folder)
        if problem:
            yield error("BadModel", f"Neural character {path}: {problem}", exception=BundleError)


def _model_blend_shape_issues(
    prim: Usd.Prim, manifest: ModelManifest, path: Sdf.Path
) -> Iterator[Issue]:
    """The character's meshes have every blend shape the model reads."""
    wanted = manifest.blend_shapes
    if not wanted:
        return
    have = character_blend_shapes(prim)
    lacking = [name for name in wanted if name not in have]
    if lacking:
        yield error(
            "ModelBlendShapesMissing",
            f"Neural character {path}: the model {manifest.path} reads blend shapes its "
            f"meshes lack: {', '.join(lacking)} (they have "
            f"{', '.join(have) or 'none'}). Fix: bind the meshes the model was trained on "
            "(their skel:blendShapes), or retrain on this character.",
        )


def _model_control_issues(
    prim: Usd.Prim, manifest: ModelManifest, path: Sdf.Path
) -> Iterator[Issue]:
    """The character declares every control the model reads."""
    if not manifest.controls:
        return
    have_controls = schema.control_names(prim)
    lacking = [c.name for c in manifest.controls if c.name not in have_controls]
    if lacking:
        yield error(
            "ModelControlsMissing",
            f"Neural character {path}: the model {manifest.path} reads controls the "
            f"character does not declare: {', '.join(lacking)} (it declares "
            f"{', '.join(have_controls) or 'none'}). Fix: apply RigspaceControlAPI:NAME for "
            "each (with the values the model was trained on), or retrain on this character.",
        )


def _model_joint_issues(prim: Usd.Prim, manifest: ModelManifest, path: Sdf.Path) -> Iterator[Issue]:
    """The character's skeleton has every joint the model reads."""
    skeleton = character_skeleton(prim)
    if skeleton is None:
        return
    missing = _missing_joints(manifest.joints, schema.skeleton_joints(skeleton))
    if missing:
        yield error(
            "ModelJointsMissing",
            f"Neural character {path}: the model {manifest.path} needs joints that skeleton "
            f"{skeleton.GetPath()} lacks: {', '.join(missing)}. Fix: bind the skeleton the "
            "model was trained on, or retrain the model on this skeleton.",
        )


def _character_disagreements(
    character: schema.CharacterAttributes, manifest: ModelManifest, path: Sdf.Path
) -> Iterator[Issue]:
    """What the character authors agrees with the manifest: joints, rotation encoding, and a
    training camera (the character's, else the manifest's) to scale the billboard by."""
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

TEXTURES = ValidatorSpec(
    "Textures",
    "Every UsdPreviewSurface texture a gprim reads can be found.",
    check_textures,
)

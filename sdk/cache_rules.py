"""The rules for a rig that is not UsdSkel's: point-cached meshes and named float controls.

A character delivered as point caches (RigspacePointCacheAPI) is captured as the stage
evaluates it, so its pose space is its cached frames: every time-sampled channel (each
cached mesh's points, the SkelAnimation's rotations, each control's value) must have the same
samples, every sample of a mesh the mesh's point count and finite points. A control that
never moves over the frames cannot be learned (a warning). The rules report, with the
offending prim and the fix; `require_valid` makes capture refuse the errors before anything
is written. Reading a cache means reading every frame of it, so those checks run for
capture and inspect only (POINT_CACHE), the controls' own checks for render too (CONTROLS).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import numpy as np
from pxr import Usd, UsdGeom, UsdSkel

from rigspace.sdk import schema, timecodes
from rigspace.sdk.character_rules import (
    _owner_is_character,
    character_blend_shapes,
    resolve_character,
)
from rigspace.sdk.controls import STILL_VALUE
from rigspace.sdk.issues import CAPTURE, RENDER, Issue, ValidatorSpec, error, warning
from rigspace.usd_schemas import CONTROL_API, POINT_CACHE_API

RE_EXPORT = (
    "re-export the cache so that every frame has the mesh's topology (the point count its "
    "faceVertexIndices index) and finite points"
)


def _applies(prim: Usd.Prim) -> bool:
    """Whether `prim` has a point cache or a control applied."""
    return any(
        s == POINT_CACHE_API or s.startswith(CONTROL_API + ":") for s in prim.GetAppliedSchemas()
    )


def _frames_text(times: Sequence[float]) -> str:
    if not len(times):
        return "no time samples"
    return f"{len(times)} frames ({times[0]:g}-{times[-1]:g})"


def _frames(count: int) -> str:
    return f"{count} frame{'' if count == 1 else 's'}"


def _same_frames(a: Sequence[float], b: Sequence[float]) -> bool:
    return len(a) == len(b) and bool(np.all(timecodes.same_time(np.asarray(a), np.asarray(b))))


def cache_frames(prim: Usd.Prim) -> list[float]:
    """The character's cached frames: its first time-sampled point cache's samples (else the
    SkelAnimation's rotation samples: a rig with controls and no cache), [] when unresolved."""
    found, _ = resolve_character(prim)
    if found is None:
        return []
    for mesh in found.cached:
        samples = UsdGeom.Mesh(mesh).GetPointsAttr().GetTimeSamples()
        if len(samples) > 1:
            return list(samples)
    return list(UsdSkel.Animation(found.animation).GetRotationsAttr().GetTimeSamples())


def control_spans(prim: Usd.Prim, frames: Sequence[float]) -> dict[str, float]:
    """Per control, how far its value moves (peak to peak) over `frames` (its value at the
    default time when there are none)."""
    spans = {}
    for control in schema.read_controls(prim):
        attr = schema.control_value_attribute(prim, control.name)
        times = [Usd.TimeCode(t) for t in frames] or [Usd.TimeCode.Default()]
        read = [attr.Get(t) if attr else None for t in times]
        values = np.array([0.0 if v is None else v for v in read], dtype=np.float64)
        spans[control.name] = float(np.ptp(values)) if np.all(np.isfinite(values)) else math.inf
    return spans


def _check_controls(prim: Usd.Prim) -> Iterator[Issue]:
    """Each control's range, name and values."""
    path = prim.GetPath()
    shapes = character_blend_shapes(prim)
    for control in schema.read_controls(prim):
        where = f"Control {control.name!r} of {path}"
        problem = control.problem()
        if problem:
            yield error(
                "ControlRange",
                f"{where}: {problem} (rigspace:control:{control.name}:range). Fix: author "
                "(low, high) with finite low < high: the values the animators use.",
            )
        if control.name in shapes:
            yield error(
                "ControlNameTaken",
                f"{where} has the name of one of the character's blend shapes. Fix: rename the "
                "control (RigspaceControlAPI:NAME): a live weight or a slider of that name "
                "would drive both.",
            )
        attr = schema.control_value_attribute(prim, control.name)
        times = attr.GetTimeSamples() if attr else []
        for t in times or [Usd.TimeCode.Default()]:
            value = attr.Get(t) if attr else None
            if value is not None and not math.isfinite(float(value)):
                when = f"at time {t:g}" if isinstance(t, float) else "(its default value)"
                yield error(
                    "ControlNotFinite",
                    f"{where} is NaN or Inf {when}. Fix: fix or delete that time sample "
                    "(capture records it as a rig parameter).",
                )
                break
        values = np.array([attr.Get(t) for t in times] if times else [], dtype=np.float64)
        if not problem and len(values) and np.all(np.isfinite(values)):
            outside = (values < control.low) | (values > control.high)
            if outside.any():
                first = times[int(np.argmax(outside))]
                yield warning(
                    "ControlOutOfRange",
                    f"{where} leaves its range ({control.low:g}, {control.high:g}) at "
                    f"{int(outside.sum())} time samples, first at {first:g} "
                    f"({values[int(np.argmax(outside))]:g}). Fix: widen the range, or the live "
                    "sources and `rigspace view`'s sliders cannot reach the captured values.",
                )


def check_controls(prim: Usd.Prim) -> Iterator[Issue]:
    """A control's range, name and values (render reads them too)."""
    if not _applies(prim):
        return
    if not schema.is_neural_character(prim):
        yield from _owner_is_character(prim, "RigspacePointCacheAPI or RigspaceControlAPI")
        return
    yield from _check_controls(prim)


def _mesh_issues(mesh: Usd.Prim, path) -> tuple[list[float], list[Issue]]:
    """A cached mesh's samples, and its point count and finiteness over all of them."""
    geom = UsdGeom.Mesh(mesh)
    attr = geom.GetPointsAttr()
    samples = list(attr.GetTimeSamples())
    issues: list[Issue] = []
    if len(samples) < 2:
        issues.append(
            warning(
                "CacheNotTimeSampled",
                f"Point cache {mesh.GetPath()} (of {path}) has "
                f"{'one time sample' if samples else 'no time samples'}: it is drawn the same in "
                "every frame. Fix: export its points per frame, or leave it out of "
                f"{schema.POINT_CACHE_MESHES} (a static mesh belongs to the scene).",
            )
        )
        return samples, issues
    indices = geom.GetFaceVertexIndicesAttr().Get()
    needed = int(np.max(np.asarray(indices))) + 1 if indices else 0
    count = len(attr.Get(samples[0]) or ())
    expected = max(count, needed)
    wrong: list[tuple[float, int]] = []
    nan: list[float] = []
    for t in samples:
        points = np.asarray(attr.Get(t) or (), dtype=np.float32)
        if len(points) != expected:
            wrong.append((t, len(points)))
        elif not np.all(np.isfinite(points)):
            nan.append(t)
    if wrong:
        t, n = wrong[0]
        issues.append(
            error(
                "CachePointCount",
                f"Point cache {mesh.GetPath()} (of {path}) does not match its topology: "
                f"another point count in {len(wrong)} of its {len(samples)} frames, the first at "
                f"time {t:g} with {n} points where its faces need {expected}. Fix: {RE_EXPORT}.",
                purposes=(CAPTURE,),
            )
        )
    if nan:
        issues.append(
            error(
                "CachePointsNotFinite",
                f"Point cache {mesh.GetPath()} (of {path}) has NaN or Inf points in "
                f"{_frames(len(nan))}, the first at time {nan[0]:g}. Fix: {RE_EXPORT}.",
                purposes=(CAPTURE,),
            )
        )
    return samples, issues


def check_point_cache(prim: Usd.Prim) -> Iterator[Issue]:
    """The point caches' frames, topology and values; the controls' frames and movement."""
    if not schema.is_neural_character(prim) or not _applies(prim):
        return
    found, _ = resolve_character(prim)
    if found is None:
        return  # CharacterSkeleton reports it
    path = prim.GetPath()
    frames: list[float] = []
    source = ""
    for mesh in found.cached:
        samples, issues = _mesh_issues(mesh, path)
        yield from issues
        if len(samples) < 2:
            continue
        if not frames:
            frames, source = samples, f"point cache {mesh.GetPath()}"
        elif not _same_frames(samples, frames):
            yield _disagree(path, f"point cache {mesh.GetPath()}", samples, source, frames)
    rotations = UsdSkel.Animation(found.animation).GetRotationsAttr().GetTimeSamples()
    if not frames:
        frames, source = list(rotations), f"animation {found.animation.GetPath()}"
    elif len(rotations) > 1 and not _same_frames(rotations, frames):
        anim = f"the skeleton animation {found.animation.GetPath()} (its rotations)"
        yield _disagree(path, anim, rotations, source, frames)
    for control in schema.read_controls(prim):
        attr = schema.control_value_attribute(prim, control.name)
        samples = attr.GetTimeSamples() if attr else []
        if len(samples) > 1 and not _same_frames(samples, frames):
            yield _disagree(path, f"control {control.name!r}", samples, source, frames)
    for name, span in control_spans(prim, frames).items():
        if span <= STILL_VALUE:
            yield warning(
                "ControlConstant",
                f"Control {name!r} of {path} never moves over the {_frames_text(frames)} of "
                f"{source}: the network cannot learn what it does (it reads one value). Fix: "
                "export frames in which the animators move it, or remove the control.",
            )


def _disagree(path, what: str, samples, source: str, frames) -> Issue:
    return error(
        "CacheFramesDisagree",
        f"Neural character {path}: {what} has {_frames_text(samples)}, but {source} has "
        f"{_frames_text(frames)}; the cached frames are the pose space, so every time-sampled "
        "channel needs the same frames. Fix: export the point caches, the skeleton animation "
        "and the controls over the same frames (one sample per frame each).",
        purposes=(CAPTURE,),
    )


POINT_CACHE = ValidatorSpec(
    "PointCache",
    "A neural character's point caches have the same frames as its skeleton animation and "
    "controls, the mesh's topology and finite points at every frame; its controls move.",
    check_point_cache,
    purposes=(CAPTURE,),
)

CONTROLS = ValidatorSpec(
    "Controls",
    "A neural character's named controls have finite ranges (low < high), finite values and "
    "names of their own.",
    check_controls,
    purposes=(CAPTURE, RENDER),
)

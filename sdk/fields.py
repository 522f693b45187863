"""Typed checks of the JSON files rigspace writes and reads back, one spec per file.

A manifest edited by hand, written by another version or damaged can hold a string where a
number belongs; read on trust, that is a traceback deep inside whatever uses the field (the
billboard's maths, a level's loop). Each reader checks its file against its spec here first,
so a wrong type is one named error from every command, and inspect checks with the same code.

A spec maps dotted paths to kinds: "levels[].resolution" is the `resolution` of every item of
the list `levels`. A path whose parent is absent is not checked (optional sections); `required`
paths must be there.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rigspace.sdk.errors import RigspaceError

KINDS: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "number": ("a finite number", lambda v: _number(v)),
    "positive": ("a finite number > 0", lambda v: _number(v) and v > 0),
    "count": ("a whole number >= 0", lambda v: _int(v) and v >= 0),
    "size": ("a whole number > 0", lambda v: _int(v) and v > 0),
    "text": ("a string", lambda v: isinstance(v, str)),
    "names": (
        "a list of strings",
        lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
    ),
    "object": ("an object", lambda v: isinstance(v, dict)),
    "list": ("a list", lambda v: isinstance(v, list)),
    "numbers": ("a list of numbers", lambda v: isinstance(v, list) and all(_number(x) for x in v)),
    "flag": ("true or false", lambda v: isinstance(v, bool)),
}


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


@dataclass(frozen=True)
class Field:
    path: str
    kind: str
    required: bool = False


def problems(data: Any, spec: tuple[Field, ...]) -> list[str]:
    """A sentence per field of `data` that `spec` says is wrong (missing or of a wrong kind)."""
    found: list[str] = []
    for field in spec:
        what, ok = KINDS[field.kind]
        for where, value, present in _values(data, field.path.split(".")):
            if not present:
                if field.required:
                    found.append(f"'{where}' is missing (it must be {what})")
            elif not ok(value):
                shown = repr(value) if len(repr(value)) <= 40 else f"{type(value).__name__}"
                found.append(f"'{where}' is {shown}, not {what}")
    return found


def read_checked(path: Path, spec: tuple[Field, ...], error: type[RigspaceError], fix: str) -> dict:
    """A JSON file read and checked against `spec`: unreadable JSON, something other than an
    object, or a field of a wrong kind is an `error` naming the file (and the field), with
    `fix`."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise error(f"{path} is not readable JSON ({exc}).", fix) from exc
    wrong = problems(data, spec) if isinstance(data, dict) else ["it is not an object"]
    if wrong:
        raise error(f"{path}: {'; '.join(wrong)}.", fix)
    return data


def _values(data: Any, parts: list[str], where: str = ""):
    """(path with indices, value, present) for every value the dotted parts reach; a missing
    parent stops the walk silently (an optional section)."""
    if not parts:
        yield where, data, True
        return
    part, rest = parts[0], parts[1:]
    key = part.removesuffix("[]")
    here = f"{where}.{key}" if where else key
    if not isinstance(data, dict):
        return
    if key not in data:
        if not rest:
            yield here, None, False
        return
    value = data[key]
    if part.endswith("[]"):
        if not isinstance(value, list):
            return  # reported by the list's own field ("levels": a list)
        for k, item in enumerate(value):
            yield from _values(item, rest, f"{here}[{k}]")
        return
    yield from _values(value, rest, here)


BUNDLE_MANIFEST = (
    Field("joints", "names", required=True),
    Field("blend_shapes", "names"),
    Field("maps", "names"),
    Field("look_at_joint", "text"),
    Field("training_camera", "object"),
    Field("training_camera.distance", "positive"),
    Field("training_camera.focal_length", "positive"),
    Field("training_camera.horizontal_aperture", "positive"),
    Field("training_camera.resolution", "size"),
    Field("meters_per_unit", "positive"),
    Field("trunk", "object"),
    Field("trunk.graphs", "object"),
    Field("trunk.graphs.trunk", "text"),
    Field("levels", "list"),
    Field("levels[]", "object"),
    Field("levels[].resolution", "size", required=True),
    Field("levels[].graphs", "object", required=True),
    Field("levels[].graphs.albedo", "text"),
    Field("levels[].graphs.geometry", "text"),
    Field("levels[].graphs.texture", "text"),
    Field("levels[].int8", "object"),
    Field("depth", "object"),
    Field("depth.scale", "positive", required=True),
    Field("training", "object"),
    Field("training.steps", "count"),
    Field("training.trained_levels", "numbers"),
    Field("training.planned_levels", "numbers"),
    Field("texture", "object"),
    Field("texture.charts", "count", required=True),
    Field("texture.file", "text"),
    Field("conditioning", "object"),
    Field("conditioning.skeleton", "object", required=True),
    Field("int8_check", "object"),
    Field("torch", "object"),
    Field("torch.file", "text"),
    Field("torch.joints", "size", required=True),
    Field("torch.charts", "count"),
    Field("torch.blend_shapes", "count"),
    Field("torch.config", "object", required=True),
    Field("files", "object"),
    Field("capsules", "text"),
)
"""The fields of a model bundle's manifest.json that rigspace reads (sdk.bundle.read_manifest)."""

DATASET_MANIFEST = (
    Field("resolution", "size", required=True),
    Field("joints", "names", required=True),
    Field("blend_shapes", "names"),
    Field("look_at_joint", "text"),
    Field("scene", "text"),
    Field("scene_fingerprint", "text"),
    Field("character", "text"),
    Field("skeleton", "text"),
    Field("rotation_encoding", "text"),
    Field("up_axis", "text"),
    Field("checksum", "text"),
    Field("meters_per_unit", "positive"),
    Field("counts", "object"),
    Field("counts.samples", "count"),
    Field("counts.items", "count"),
    Field("counts.train", "count"),
    Field("counts.heldout-views", "count"),
    Field("counts.heldout-clips", "count"),
    Field("ring", "object", required=True),
    Field("ring.radius", "positive", required=True),
    Field("ring.focal_length", "positive", required=True),
    Field("ring.horizontal_aperture", "positive", required=True),
    Field("ring.views_per_ring", "count"),
    Field("ring.elevations", "numbers"),
    Field("ring.held_out_views_per_ring", "count"),
    Field("ring.held_out_elevations", "numbers"),
    Field("ring.clipping_range", "numbers"),
    Field("ring.views", "list"),
    Field("ring.views[]", "object"),
    Field("ring.views[].index", "count", required=True),
    Field("ring.views[].azimuth", "number", required=True),
    Field("ring.views[].elevation", "number", required=True),
    Field("ring.views[].held_out", "flag", required=True),
    Field("clips", "list"),
    Field("clips[]", "object"),
    Field("clips[].name", "text", required=True),
    Field("clips[].first", "number", required=True),
    Field("clips[].last", "number", required=True),
    Field("clips[].held_out", "flag"),
    Field("renderer", "object"),
    Field("renderer.name", "text", required=True),
    Field("renderer.samples_per_axis", "size", required=True),
    Field("channels", "object"),
    Field("charts", "object"),
    Field("charts.file", "text", required=True),
    Field("charts.count", "count", required=True),
    Field("params", "object"),
    Field("coverage", "object"),
    Field("coverage.empty_below_pixels", "number", required=True),
    Field("coverage.empty_samples", "count", required=True),
    Field("coverage.empty_by_view", "object", required=True),
    Field("splits", "names"),
    Field("bytes", "count"),
    Field("settings", "object"),
)
"""The fields of a dataset's manifest.json that rigspace reads (capture.dataset.read_manifest)."""

TRAINING_RUN = (
    Field("config", "object", required=True),
    Field("dataset", "text", required=True),
    Field("dataset_checksum", "text"),
    Field("joints", "names", required=True),
    Field("blend_shapes", "names"),
    Field("charts", "count"),
    Field("plan", "object"),
    Field("plan.steps_per_level", "size", required=True),
    Field("plan.seconds_per_step", "object"),
)
"""The fields of a training run's run.json (train.loop.read_run)."""

CAPTURE_SETTINGS = (
    Field("scene", "text", required=True),
    Field("character", "text", required=True),
    Field("joints", "names", required=True),
    Field("blend_shapes", "names"),
    Field("blend_draws", "list"),
    Field("clips", "list", required=True),
    Field("clips[].name", "text", required=True),
    Field("clips[].first", "number", required=True),
    Field("clips[].last", "number", required=True),
    Field("views_per_ring", "size", required=True),
    Field("elevations", "numbers", required=True),
    Field("radius", "positive", required=True),
    Field("focal_length", "positive", required=True),
    Field("horizontal_aperture", "positive", required=True),
    Field("resolution", "size", required=True),
    Field("clipping_range", "numbers", required=True),
    Field("renderer", "text", required=True),
    Field("samples_per_axis", "size", required=True),
    Field("frames_per_item", "size", required=True),
    Field("every", "size"),
)
"""The fields of a dataset's capture.json (capture.pipeline.prepare_folder reads it to
resume; capture.dataset.resume_command to say how)."""

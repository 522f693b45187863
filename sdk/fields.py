"""Typed checks of the JSON files rigspace writes and reads back, one spec per file.

A manifest edited by hand, written by another version or damaged can hold a string where a
number belongs; read on trust, that is a traceback deep inside whatever uses the field (the
billboard's maths, a level's loop). Each reader checks its file against its spec first (the
checks are here, with the specs written out; derived specs live beside their dataclasses), so
a wrong type is one named error from every command, and inspect checks with the same code.

A spec maps dotted paths to kinds: "levels[].resolution" is the `resolution` of every item of
the list `levels`. A path whose parent is absent is not checked (optional sections); `required`
paths must be there.

A format whose dataclass names the document's keys has its spec derived from it (spec_of):
each field's type gives the kind (`Size` and `Positive` mark what the type alone does not
say), a field without a default is required, and a dataclass-typed field is a section whose
own fields follow. The dataset manifest's spec (capture.dataset.DATASET_MANIFEST) and
run.json's (train.loop.TRAINING_RUN) are derived so, beside their dataclasses; only the keys
of their open tables (counts.samples, plan.steps_per_level) are written out there. The bundle
manifest's spec (BUNDLE_MANIFEST) stays written out: see its note.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

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


Size = Annotated[int, "size"]
"""A whole number > 0 (a resolution, samples per axis): spec_of gives it the kind "size"."""
Positive = Annotated[float, "positive"]
"""A finite number > 0 (a distance, a focal length): spec_of gives it the kind "positive"."""


_PLAIN = {str: "text", bool: "flag", int: "count", float: "number"}
"""The kinds of plain types (a bool is not a count: JSON's true is not 1)."""
_NUMBERS = ("number", "count", "positive", "size")


def spec_of(cls: type, skip: Collection[str] = (), prefix: str = "") -> tuple[Field, ...]:
    """The spec of a format from the dataclass that types its document: a Field per field
    (its name is the document's key), of the kind its type gives (kind_of), required when it
    has no default. A dataclass-typed field is a section and a tuple of dataclasses a list of
    them: their own fields follow ("ring.radius", "clips[].name"). `skip` names the fields,
    dotted as their paths, that are not keys of the document or are checked before the spec
    (the manifest's own path, its format)."""
    found: list[Field] = []
    hints = typing.get_type_hints(cls, include_extras=True)
    for item in dataclasses.fields(cls):
        path = f"{prefix}{item.name}"
        if path in skip:
            continue
        required = item.default is dataclasses.MISSING and (
            item.default_factory is dataclasses.MISSING
        )
        kind, section = kind_of(hints[item.name])
        found.append(Field(path, kind, required))
        if section is not None and kind == "list":
            found.append(Field(f"{path}[]", "object"))
            found.extend(spec_of(section, skip, f"{path}[]."))
        elif section is not None:
            found.extend(spec_of(section, skip, f"{path}."))
    return tuple(found)


def kind_of(hint: Any) -> tuple[str, type | None]:
    """The spec kind of a dataclass field's type, and the dataclass of a section (or of a
    list's items) whose fields the spec goes on into: str text, bool flag, int count, float
    number, `Size` size, `Positive` positive, a tuple of strings names, of numbers numbers,
    a dict object, `X | None` as X. Any other type is a TypeError (a format's dataclass
    must say what its fields hold)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    optional = [a for a in args if a is not type(None)]
    if origin is Annotated:
        return str(hint.__metadata__[0]), None
    if origin in (typing.Union, types.UnionType) and len(optional) == 1:
        return kind_of(optional[0])
    if hint in _PLAIN:
        return _PLAIN[hint], None
    if hint is dict or origin is dict:
        return "object", None
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return "object", hint
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        item, section = kind_of(args[0])
        if item == "text":
            return "names", None
        if item in _NUMBERS:
            return "numbers", None
        return "list", section
    raise TypeError(f"no spec kind for the type {hint!r}: annotate the field (sdk.fields)")


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


# The bundle manifest's spec is written out rather than derived (spec_of): ModelManifest is a
# typed view of the document, not its keys (training_distance is training_camera.distance,
# depth_scale depth.scale, int8_failed a judgement over int8_check, a level's GraphFiles its
# "graphs" and "int8"), and what the spec checks inside the open sections (training.steps,
# torch.config, conditioning.skeleton) has no field there. Where ModelManifest's fields do
# name the document's keys (joints, levels[].resolution, texture.charts, ...), the kinds and
# requirements agree with spec_of's: tests/sdk/test_fields.py holds them to it.
BUNDLE_MANIFEST = (
    Field("joints", "names", required=True),
    Field("blend_shapes", "names"),
    Field("controls", "list"),
    Field("controls[]", "object"),
    Field("controls[].name", "text", required=True),
    Field("controls[].range", "numbers", required=True),
    Field("maps", "names"),
    Field("look_at_joint", "text"),
    Field("training_camera", "object"),
    Field("training_camera.distance", "positive"),
    Field("training_camera.focal_length", "positive"),
    Field("training_camera.horizontal_aperture", "positive"),
    Field("training_camera.resolution", "size"),
    Field("training_camera.upright_axis", "numbers"),
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
    Field("texture.branch", "text"),
    Field("conditioning", "object"),
    Field("conditioning.skeleton", "object", required=True),
    Field("int8_check", "object"),
    Field("torch", "object"),
    Field("torch.file", "text"),
    Field("torch.joints", "size", required=True),
    Field("torch.charts", "count"),
    Field("torch.blend_shapes", "count"),
    Field("torch.controls", "count"),
    Field("torch.config", "object", required=True),
    Field("files", "object"),
    Field("capsules", "text"),
    Field("regions", "list"),
    Field("regions[]", "object"),
    Field("regions[].name", "text", required=True),
    Field("regions[].joint", "text", required=True),
    Field("regions[].bundle", "text", required=True),
    Field("views", "object"),
    Field("views.file", "text", required=True),
    Field("views.joint", "count", required=True),
    Field("views.elevations", "numbers"),
)
"""The fields of a model bundle's manifest.json that rigspace reads (sdk.bundle.read_manifest)."""

CAPTURE_SETTINGS = (
    Field("scene", "text", required=True),
    Field("character", "text", required=True),
    Field("joints", "names", required=True),
    Field("blend_shapes", "names"),
    Field("controls", "list"),
    Field("controls[].name", "text", required=True),
    Field("controls[].range", "numbers", required=True),
    Field("blend_draws", "list"),
    Field("shape_draws", "text"),
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

"""The model bundle's manifest: the one versioned artefact that crosses from train to runtime.

A bundle is a folder with `manifest.json` and the ONNX graphs it names. This module
reads and checks the manifest; `rigspace.train` writes it and `rigspace.runtime` loads
the graphs. Reading never executes anything from the bundle.

One contract for reading and writing it:

    read_manifest(folder) -> ModelManifest          what every reader uses: checked, typed
    read_manifest_document(folder) -> dict          the same checks, the document itself
    write_manifest_document(folder, document)       checked as a reader checks, then atomic

Every writer (the export, int8 re-quantisation, eval's and --display's recorded metrics,
the graph rewrite, capsules) reads the document, changes its sections and writes it back
through write_manifest_document, so no writer can leave a manifest that a reader refuses:
a document that fails the checks is a BundleError and nothing is written.

Why a checked document and not ModelManifest writing itself: ModelManifest is a typed view
of the fields the runtime reads (training_distance from training_camera.distance, the
int8 judgement from int8_check), while much of the document is open-ended and only
recorded (metrics, training, torch, int8_check, inputs, outputs, dataset). A full typed
model of every section, and a to_json that writes each bundle back byte for byte (the
committed bundles' sections are not even in the same order: the export's order changed
between them), would be a second description of those sections to keep in step. Writers
instead change only the sections they own and the rest passes through untouched.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rigspace.sdk.controls import Control, controls_from_json
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.fields import BUNDLE_MANIFEST, Size, problems
from rigspace.sdk.files import write_atomic

FORMAT = "rigspace.bundle"
MANIFEST_FILE = "manifest.json"
FORMAT_VERSION = 2
"""Written by this rigspace for the paper's rotations-only input. Version 2 added the albedo
graphs' `alpha` (coverage) output."""
CONDITIONED_VERSION = 3
"""Written for a pose-conditioned model (manifest `conditioning`): its graphs also read
`joints2d`, so a rigspace that reads only versions 1-2 refuses it by name instead of failing
inside onnxruntime on a missing input."""
TEXTURE_BRANCH_VERSION = 4
"""Written for a model whose texture head is a branch of its own (manifest texture.branch
"texture": texture_<R>.onnx graphs beside albedo and geometry), so a rigspace that reads
only versions 1-3 refuses it by name instead of drawing it untextured."""
READABLE_VERSIONS = (1, 2, 3, 4)
ENCODINGS = ("rot6d", "quaternion")


class BundleError(RigspaceError):
    """A model bundle that cannot be used: missing, unreadable, or of another format."""


@dataclass(frozen=True)
class GraphFiles:
    """One set of graphs (the trunk, or a level's branches): file names by graph, fp32 and
    int8 (an int8 name is None, or absent, where the export wrote none)."""

    fp32: dict[str, str]
    int8: dict[str, str | None]

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> GraphFiles:
        return cls(dict(data.get("graphs", {})), dict(data.get("int8") or {}))


@dataclass(frozen=True)
class Level:
    """A level of detail: the output resolution and its branches' graphs."""

    resolution: Size
    files: GraphFiles


@dataclass(frozen=True)
class TextureHead:
    """The texture head (manifest `texture`): K charts, their table, the branch giving them."""

    charts: int
    file: str = "charts.json"
    branch: str = "albedo"


@dataclass(frozen=True)
class RegionBundle:
    """A region of the character with a network of its own (manifest `regions`, issue 33):
    the face or a hand, drawn at its own resolution around its own joint and composited over
    the body's maps. Its bundle is a complete bundle in a folder inside this one (its own
    manifest: its look-at joint, its training camera, its levels)."""

    name: str
    joint: str
    """The joint its cameras looked at (its bundle's look_at_joint)."""
    folder: Path
    """Its bundle's folder (inside the body's bundle)."""


@dataclass(frozen=True)
class ModelManifest:
    """What a model bundle's manifest.json declares (format versions 1 to 4), read and checked
    once (read_manifest): every reader takes its sections from here, typed."""

    path: Path
    """The manifest file."""
    joints: tuple[str, ...]
    """Skeleton joint names the model reads, in input order."""
    rotation_encoding: str
    maps: tuple[str, ...] = ()
    look_at_joint: str = ""
    training_distance: float = 0.0
    training_focal_length: float = 0.0
    training_aperture: float = 0.0
    training_resolution: int | None = None
    """The capture's resolution (training_camera.resolution); None in older manifests."""
    training_upright: tuple[float, ...] = ()
    """training_camera.upright_axis: the look-at joint's local up that its cameras kept
    upright (a region's `upright = "joint"`); (): the stage's up axis."""
    format_version: int = FORMAT_VERSION
    blend_shapes: tuple[str, ...] = ()
    """Blend shapes whose weights follow the rotations in the rig input (manifest order)."""
    controls: tuple[Control, ...] = ()
    """Named float controls (RigspaceControlAPI) whose values follow the blend shape weights
    in the rig input, with their ranges (manifest order; none in a bundle of a UsdSkel-only
    rig, whose manifest has no `controls`)."""
    trunk: GraphFiles | None = None
    levels: tuple[Level, ...] = ()
    depth_scale: float = 1.0
    depth_units: str = "bundle units"
    texture: TextureHead | None = None
    capsules: str | None = None
    """The bundle's capsules.json (shadow capsules), None without any."""
    int8_offered_levels: tuple[int, ...] | None = None
    """Levels where int8 met the accuracy aim and was faster at export (int8_check); None for
    a check older than that judgement."""
    int8_failed: frozenset[str] = frozenset()
    """int8 graphs the export's check failed (int8_check.graphs[name].ok is false)."""
    files: dict[str, dict[str, Any]] = field(default_factory=dict, repr=False)
    """Per file its recorded bytes and sha256."""
    training: dict[str, Any] = field(default_factory=dict, repr=False)
    """The training record (train.export): config, steps, planned and trained levels, plan."""
    conditioning: dict[str, Any] | None = field(default=None, repr=False)
    """The pose conditioning (train.conditioning; rigspace.sdk.conditioning reads its skeleton)."""
    torch: dict[str, Any] | None = field(default=None, repr=False)
    """The torch predictor's section (train.torch_predictor): weights file, shape, config."""
    regions: tuple[RegionBundle, ...] = ()
    """The character's regions with networks of their own (docs/regions.md), in training order."""
    views: dict[str, Any] | None = field(default=None, repr=False)
    """The training views of its look-at joint (sdk.view_coverage: file, joint, elevations);
    None in a bundle exported before them."""

    @property
    def folder(self) -> Path:
        return self.path.parent

    @classmethod
    def from_json(cls, data: dict[str, Any], path: Path) -> ModelManifest:
        """Check a manifest document (BundleError naming `path` and the field) and type it."""
        return _typed(data, path)


def manifest_path(path: str | Path) -> Path:
    path = Path(path)
    return path / MANIFEST_FILE if path.is_dir() else path


def read_manifest(path: str | Path) -> ModelManifest:
    """Read and check a bundle's manifest (a bundle folder or its manifest.json)."""
    file = manifest_path(path)
    return _typed(_load(path, file), file)


def read_manifest_document(path: str | Path) -> dict[str, Any]:
    """A bundle's manifest document (a bundle folder or its manifest.json), checked as
    read_manifest checks it (the same BundleError): what a writer changes and hands to
    write_manifest_document."""
    file = manifest_path(path)
    data = _load(path, file)
    _typed(data, file)
    return data


def write_manifest_document(folder: str | Path, document: dict[str, Any]) -> ModelManifest:
    """Write `document` as the manifest.json of the bundle in `folder`, atomically, and return
    it as read_manifest will read it. It is first checked as every reader checks it (the
    format, version, joints and encoding, then the field spec): a document a reader would
    refuse is a BundleError, and nothing is written.

    The text is `json.dumps(document, indent=2)` and a newline, as every bundle so far was
    written: a document read and written back unchanged gives the same bytes."""
    file = Path(folder) / MANIFEST_FILE
    text = json.dumps(document, indent=2) + "\n"
    try:
        manifest = _typed(json.loads(text), file)  # the document as a reader will see it
    except BundleError as exc:
        raise BundleError(
            f"Refused to write {file}, which no reader would accept: {exc.what}",
            "nothing was written and the bundle is as it was; this is a rigspace bug in the "
            "command that wrote it: please report it with that command.",
        ) from exc
    write_atomic(file, text)
    return manifest


def _load(path: str | Path, file: Path) -> Any:
    """The JSON in a bundle's manifest file (BundleError when there is none, or unreadable)."""
    if not file.is_file():
        raise BundleError(
            f"Model bundle {path}: there is no manifest.json at {file}.",
            "point rigspace:model at a folder written by `rigspace train` (or its manifest.json).",
        )
    try:
        return json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BundleError(
            f"Model bundle manifest {file} is not readable JSON ({exc}).",
            "re-export the bundle with `rigspace train`; the file is damaged.",
        ) from exc


def _typed(data: Any, file: Path) -> ModelManifest:
    """A manifest document checked (format, version, joints, encoding, the field spec) and
    typed."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise BundleError(
            f"{file} is not a rigspace model bundle manifest (format is "
            f"{data.get('format') if isinstance(data, dict) else type(data).__name__!r}, "
            f"expected {FORMAT!r}).",
            "point rigspace:model at a folder written by `rigspace train`.",
        )
    version = data.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool):
        # "3", 3.0 and true compare equal to a readable version, or look like one: name the type.
        got = "missing" if version is None else f"{json.dumps(version)} ({_json_type(version)})"
        raise BundleError(
            f"{file}: format_version must be an integer (one of "
            f"{', '.join(map(str, READABLE_VERSIONS))}); it is {got}.",
            "re-export the bundle with `rigspace train`, or write the version as a bare "
            f'number ("format_version": {FORMAT_VERSION}, not "{FORMAT_VERSION}").',
        )
    if version not in READABLE_VERSIONS:
        raise BundleError(
            f"{file} has bundle format version {version!r}; this rigspace reads versions "
            f"{', '.join(map(str, READABLE_VERSIONS))}.",
            "re-export the bundle with this version of rigspace, or install the rigspace "
            "version that wrote it.",
        )
    joints = data.get("joints")
    if not isinstance(joints, list) or not joints or not all(isinstance(j, str) for j in joints):
        raise BundleError(
            f"{file}: 'joints' must be a non-empty list of joint names.",
            "re-export the bundle; the manifest is incomplete.",
        )
    encoding = data.get("rotation_encoding")
    if encoding not in ENCODINGS:
        raise BundleError(
            f"{file}: rotation_encoding is {encoding!r}, expected one of {ENCODINGS}.",
            "re-export the bundle; the manifest is incomplete.",
        )
    wrong = problems(data, BUNDLE_MANIFEST)
    if wrong:
        raise BundleError(
            f"Model bundle manifest {file}: {'; '.join(wrong)}.",
            "re-export the bundle with `rigspace train` (or restore the file).",
        )
    return _sections(data, file, tuple(joints), encoding, int(version))


def _sections(
    data: dict[str, Any], file: Path, joints: tuple[str, ...], encoding: str, version: int
) -> ModelManifest:
    """The checked document's sections, typed."""
    camera = data.get("training_camera", {})
    upright = camera.get("upright_axis") or []
    if upright and not (
        len(upright) == 3 and all(math.isfinite(v) for v in upright) and any(upright)
    ):
        raise BundleError(
            f"{file}: training_camera.upright_axis is {upright!r}: the look-at joint's up must be "
            "three finite numbers, not all 0.",
            "re-export the bundle with `rigspace train` from its dataset.",
        )
    check = data.get("int8_check") or {}
    offered = check.get("offered_levels")
    texture = data.get("texture")
    trunk = data.get("trunk")
    return ModelManifest(
        path=file,
        joints=joints,
        rotation_encoding=encoding,
        maps=tuple(data.get("maps", ())),
        look_at_joint=str(data.get("look_at_joint", "")),
        training_distance=float(camera.get("distance", 0.0)),
        training_focal_length=float(camera.get("focal_length", 0.0)),
        training_aperture=float(camera.get("horizontal_aperture", 0.0)),
        training_resolution=int(camera["resolution"]) if "resolution" in camera else None,
        training_upright=tuple(float(v) for v in upright),
        format_version=version,
        blend_shapes=tuple(data.get("blend_shapes") or ()),
        controls=_controls(data.get("controls") or [], file),
        trunk=GraphFiles.from_json(trunk) if isinstance(trunk, dict) else None,
        levels=tuple(
            Level(int(level["resolution"]), GraphFiles.from_json(level))
            for level in data.get("levels", ())
        ),
        depth_scale=float(data.get("depth", {}).get("scale", 1.0)),
        depth_units=str(data.get("depth", {}).get("units", "bundle units")),
        texture=(
            TextureHead(
                int(texture["charts"]),
                str(texture.get("file", "charts.json")),
                str(texture.get("branch", "albedo")),
            )
            if texture
            else None
        ),
        int8_offered_levels=None if offered is None else tuple(sorted(int(r) for r in offered)),
        int8_failed=frozenset(
            name
            for name, result in (check.get("graphs") or {}).items()
            if isinstance(result, dict) and not result.get("ok", True)
        ),
        capsules=str(data["capsules"]) if data.get("capsules") else None,
        files=dict(data.get("files") or {}),
        training=dict(data.get("training") or {}),
        conditioning=data.get("conditioning") or None,
        torch=data.get("torch") if isinstance(data.get("torch"), dict) else None,
        regions=_regions(data.get("regions") or [], file),
        views=data.get("views") if isinstance(data.get("views"), dict) else None,
    )


def _regions(entries: list[dict[str, Any]], file: Path) -> tuple[RegionBundle, ...]:
    """The manifest's regions (their fields already checked): each bundle a folder inside the
    body's, each name once."""
    regions: list[RegionBundle] = []
    for entry in entries:
        relative = Path(entry["bundle"])
        if relative.is_absolute() or ".." in relative.parts or not relative.parts:
            raise BundleError(
                f"Model bundle manifest {file}: region {entry['name']!r} names its bundle "
                f"{entry['bundle']!r}, which is not a folder inside the bundle.",
                "re-export the bundle with `rigspace train` (a region's bundle is regions/NAME).",
            )
        if any(r.name == entry["name"] for r in regions):
            raise BundleError(
                f"Model bundle manifest {file}: region {entry['name']!r} is listed twice.",
                "re-export the bundle with `rigspace train`.",
            )
        regions.append(RegionBundle(entry["name"], entry["joint"], file.parent / relative))
    return tuple(regions)


def _controls(entries: list[dict[str, Any]], file: Path) -> tuple[Control, ...]:
    """The manifest's controls (their fields already checked): each range two finite numbers
    with low < high, each name once and none a blend shape's."""
    controls = controls_from_json(entries)
    names = [c.name for c in controls]
    for control in controls:
        problem = control.problem()
        repeated = names.count(control.name) > 1
        if problem or repeated:
            raise BundleError(
                f"Model bundle manifest {file}: control {control.name!r} "
                + (problem if problem else "is listed twice")
                + ".",
                "re-export the bundle with `rigspace train`; the manifest is damaged.",
            )
    return controls


def _json_type(value: Any) -> str:
    """The JSON name of a decoded value's type ("a string", "a boolean", ...)."""
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, float):
        return "a decimal number"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__

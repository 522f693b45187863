"""The dataset on disk: work items, their atomic records, and the final manifest.

Layout of a dataset folder:
    capture.json            resolved CaptureSettings (written first; resume checks it)
    samples/<clip>/t<time>_v<view>.exr   one EXR per sample (sdk/exr.py)
    items/<item>.npz        one record per finished work item (written last, atomically)
    params.npz              the parameters table, every sample in dataset order (finalize)
    manifest.json           counts, splits, checksums, settings (finalize)
    contact_sheet.png       a grid of maps from a few samples (finalize)
    charts.json             the character's texture charts (rigspace.sdk.charts), which the
                            samples' chart AOV numbers: only for a character with textures

A work item is one clip's chunk of frames seen from one group of ring views (a ring, or
its held-out views). Items are independent; `--shard i/n` takes items i, i+n, ... An
item is done exactly when its record exists; a killed run leaves at most temporary files
and an item without a record, which the next run redoes from scratch. A resumed run first
checks every finished item against its record (`verify_items`: each sample file present,
its sha256 the recorded one) and redoes the damaged ones. Finalizing is deterministic and
idempotent, so one run, a resumed run, a repaired run and merged shards give the same
manifest.
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import shlex
import zipfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.capture.ring import HELDOUT_CLIPS, HELDOUT_VIEWS, SPLITS, TRAIN, RingView
from rigspace.capture.settings import CaptureSettings, Clip
from rigspace.sdk.charts import ChartTable, parse_charts
from rigspace.sdk.controls import Control, controls_from_json, controls_json
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.exr import read_exr
from rigspace.sdk.fields import Field, Positive, Size, problems, spec_of
from rigspace.sdk.files import write_atomic
from rigspace.sdk.render import Maps
from rigspace.sdk.view_coverage import ViewCoverage, build_views

FORMAT = "rigspace.dataset"
FORMAT_VERSION = 1
SETTINGS_FILE = "capture.json"
MANIFEST_FILE = "manifest.json"
PARAMS_FILE = "params.npz"
CONTACT_SHEET = "contact_sheet.png"
CHARTS_FILE = "charts.json"
ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)
"""The earliest time a zip entry can carry: every archive entry gets it."""
EMPTY_PIXELS = 4.0
"""A sample whose mask covers fewer pixels than this (a 2 x 2 patch) shows nothing to learn
from: the character is out of frame, clipped away, or too small for the ring."""


class DatasetError(RigspaceError):
    """A dataset folder that cannot be read as asked."""


def _number(x: float) -> str:
    short = f"{x:g}"
    return short if float(short) == x else repr(x)


def saved_flags(folder: str | Path) -> dict[str, Any] | None:
    """The flag values that give exactly the settings of the capture in `folder`, from its
    capture.json, by CaptureOverrides field (and `character`, `scene`): what `--resume`
    takes for each flag it is not given, and resume_command writes. None when there is no
    readable capture.json."""
    try:
        settings = json.loads((Path(folder) / SETTINGS_FILE).read_text())
        clips = settings["clips"]
        flags: dict[str, Any] = {
            "scene": str(settings["scene"]),
            "character": str(settings["character"]),
            "views": int(settings["views_per_ring"]),
            "elevations": tuple(float(e) for e in settings["elevations"]),
            "resolution": int(settings["resolution"]),
            "radius": float(settings["radius"]),
        }
        if [c["name"] for c in clips] == ["frames"]:
            flags["frames"] = (float(clips[0]["first"]), float(clips[0]["last"]))
        else:
            flags["clips"] = tuple(str(c["name"]) for c in clips)
            flags["held_out_clips"] = tuple(str(c["name"]) for c in clips if c.get("held_out"))
        flags["renderer"] = str(settings["renderer"])
        flags["samples_per_axis"] = int(settings["samples_per_axis"])
        flags["frames_per_item"] = int(settings["frames_per_item"])
        flags["every"] = int(settings.get("every", 1))
    except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError):
        return None
    return flags


def resume_command(folder: str | Path) -> str:
    """The command line that resumes (and repairs) the capture in `folder`, from its
    capture.json: the flags that give exactly its settings (saved_flags); "rigspace capture
    ... --resume" when there is no readable capture.json."""
    folder = Path(folder)
    flags = saved_flags(folder)
    if flags is None:
        return "rigspace capture ... --resume"
    args = ["rigspace", "capture", flags["scene"], "--character", flags["character"]]
    args += ["--out", str(folder), "--views", str(flags["views"])]
    args += ["--elevations", *(_number(e) for e in flags["elevations"])]
    args += ["--resolution", str(flags["resolution"])]
    args += ["--radius", _number(flags["radius"])]
    if "frames" in flags:
        args += ["--frames", f"{_number(flags['frames'][0])}:{_number(flags['frames'][1])}"]
    else:
        args += ["--clips", *flags["clips"], "--held-out-clips", *flags["held_out_clips"]]
    args += ["--renderer", flags["renderer"], "--samples", str(flags["samples_per_axis"])]
    args += ["--frames-per-item", str(flags["frames_per_item"])]
    if flags["every"] != 1:
        args += ["--every", str(flags["every"])]
    args += ["--resume"]
    return shlex.join(args)


@dataclass(frozen=True)
class ManifestView:
    """One camera of the capture ring as the manifest records it (capture.ring.RingView without
    its vectors, which the ring's settings give again)."""

    index: int
    """Position in the ring's view list (training views first, then held-out ones)."""
    azimuth: float
    """Degrees, 0 = the stage's front, counter-clockwise seen from above."""
    elevation: float
    """Degrees above the horizontal plane through the look-at joint."""
    held_out: bool

    def to_json(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "azimuth": self.azimuth,
            "elevation": self.elevation,
            "held_out": self.held_out,
        }


@dataclass(frozen=True)
class ManifestRing:
    """The capture ring (manifest `ring`): its camera and its views. A hand-written manifest
    may give only the camera (radius, focal_length, horizontal_aperture): the rest reads empty."""

    radius: Positive
    """Distance from the look-at joint to every camera, scene units."""
    focal_length: Positive
    """Millimetres, as UsdGeom.Camera's focalLength."""
    horizontal_aperture: Positive
    """Millimetres, as UsdGeom.Camera's horizontalAperture."""
    views_per_ring: int = 0
    elevations: tuple[float, ...] = ()
    """Degrees, one ring of training views per elevation."""
    held_out_views_per_ring: int = 0
    held_out_elevations: tuple[float, ...] = ()
    clipping_range: tuple[float, ...] = ()
    """(near, far) in scene units; empty when not recorded."""
    views: tuple[ManifestView, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "views_per_ring": self.views_per_ring,
            "elevations": list(self.elevations),
            "held_out_views_per_ring": self.held_out_views_per_ring,
            "held_out_elevations": list(self.held_out_elevations),
            "radius": self.radius,
            "focal_length": self.focal_length,
            "horizontal_aperture": self.horizontal_aperture,
            "clipping_range": list(self.clipping_range),
            "views": [view.to_json() for view in self.views],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ManifestRing:
        return cls(
            radius=data["radius"],
            focal_length=data["focal_length"],
            horizontal_aperture=data["horizontal_aperture"],
            views_per_ring=data.get("views_per_ring", 0),
            elevations=tuple(data.get("elevations", ())),
            held_out_views_per_ring=data.get("held_out_views_per_ring", 0),
            held_out_elevations=tuple(data.get("held_out_elevations", ())),
            clipping_range=tuple(data.get("clipping_range", ())),
            views=tuple(
                ManifestView(v["index"], v["azimuth"], v["elevation"], v["held_out"])
                for v in data.get("views", ())
            ),
        )


@dataclass(frozen=True)
class Renderer:
    """The renderer that made the samples (manifest `renderer`)."""

    name: str
    """The renderer's name ("gl" or "embree", the capture's --renderer)."""
    samples_per_axis: Size
    """Supersamples per pixel along each axis."""


@dataclass(frozen=True)
class ChartsFile:
    """The dataset's texture charts (manifest `charts`): the file and how many charts it holds,
    which the samples' chart AOV numbers 1..count."""

    file: str
    count: int


@dataclass(frozen=True)
class Coverage:
    """How many samples show nothing (manifest `coverage`: mask below `empty_below_pixels`)."""

    empty_below_pixels: float
    empty_samples: int
    empty_by_view: dict[int, int]
    """Per ring view index with any, its empty samples (ascending views)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "empty_below_pixels": self.empty_below_pixels,
            "empty_samples": self.empty_samples,
            "empty_by_view": {str(view): n for view, n in self.empty_by_view.items()},
        }


@dataclass(frozen=True)
class DatasetManifest:
    """What a dataset's manifest.json declares (format version 1), read and checked once
    (read_manifest, or from_json for a copy such as a pack's index): every reader takes its
    fields from here, typed. `to_json` gives the document back exactly as finalize writes it.

    A field an older or hand-written manifest lacks reads as its default: empty text, lists
    and tables, or None where nothing can stand in (a section, meters_per_unit); to_json leaves
    a None field out, as finalize leaves out `charts` and an empty `blend_shapes`."""

    path: Path
    """The manifest file (not part of the document)."""
    joints: tuple[str, ...]
    """Skeleton joint names, in the order of params.npz's `rig` rows."""
    ring: ManifestRing
    resolution: Size
    """Width and height of every sample, pixels."""
    format: str = FORMAT
    format_version: int = FORMAT_VERSION
    scene: str = ""
    """The scene as the capture was given it (a path), "" when not recorded."""
    scene_fingerprint: str = ""
    """sha256 over the bytes of every layer of the scene (capture.settings.scene_fingerprint)."""
    character: str = ""
    """The RigspaceNeuralCharacter prim's path."""
    skeleton: str = ""
    """The Skeleton prim's path."""
    blend_shapes: tuple[str, ...] = ()
    """Blend shapes whose weights params.npz's `blend` holds, in its order (none: no column)."""
    controls: tuple[Control, ...] = ()
    """Named controls whose values params.npz's `controls` holds, in its order, with their
    ranges (none: no column; docs/point_caches.md)."""
    look_at_joint: str = ""
    rotation_encoding: str = "rot6d"
    up_axis: str = "Y"
    meters_per_unit: Positive | None = None
    clips: tuple[Clip, ...] = ()
    renderer: Renderer | None = None
    channels: dict[str, str] = field(default_factory=dict, repr=False)
    """Per channel group of a sample EXR, what it holds."""
    charts: ChartsFile | None = None
    """None: the character has no texture (and the samples no uv/chart AOVs)."""
    params: dict[str, Any] = field(default_factory=dict, repr=False)
    """params.npz described: its file, what some columns hold, and every column's name."""
    counts: dict[str, int] = field(default_factory=dict)
    """Samples in all ("samples"), work items ("items") and samples per split (SPLITS)."""
    coverage: Coverage | None = None
    splits: tuple[str, ...] = SPLITS
    """The split names, in the order params.npz's `split` numbers them."""
    bytes: int = 0
    """Bytes of every sample EXR together."""
    checksum: str = ""
    """sha256 over every sample's path and sha256, params.npz and charts.json (finalize)."""
    settings: dict[str, Any] = field(default_factory=dict, repr=False)
    """The capture's settings as capture.json holds them (CaptureSettings.from_json reads it)."""

    @property
    def folder(self) -> Path:
        return self.path.parent

    @classmethod
    def from_json(cls, data: Any, path: Path) -> DatasetManifest:
        """Check a manifest document (DatasetError naming `path`, the field and the fix) and
        type it."""
        path = Path(path)
        if not isinstance(data, dict) or (data.get("format"), data.get("format_version")) != (
            FORMAT,
            FORMAT_VERSION,
        ):
            found = data if not isinstance(data, dict) else data.get("format")
            raise DatasetError(
                f"{path} is not a {FORMAT} manifest of version {FORMAT_VERSION} (found {found!r}).",
                "re-capture the dataset with this version of rigspace.",
            )
        wrong = problems(data, DATASET_MANIFEST) + _view_keys(data.get("coverage"))
        if wrong:
            raise DatasetError(
                f"{path}: {'; '.join(wrong)}.",
                f"restore the file, or re-capture the dataset (`{resume_command(path.parent)}` "
                "rewrites it from the samples).",
            )
        return _typed_manifest(data, path)

    def to_json(self) -> dict[str, Any]:
        """The manifest's document: what finalize writes to manifest.json."""
        document = {
            "format": self.format,
            "format_version": self.format_version,
            "scene": self.scene,
            "scene_fingerprint": self.scene_fingerprint,
            "character": self.character,
            "skeleton": self.skeleton,
            "joints": list(self.joints),
            "blend_shapes": list(self.blend_shapes) or None,
            "controls": controls_json(self.controls),
            "look_at_joint": self.look_at_joint,
            "rotation_encoding": self.rotation_encoding,
            "up_axis": self.up_axis,
            "meters_per_unit": self.meters_per_unit,
            "clips": [
                {"name": c.name, "first": c.first, "last": c.last, "held_out": c.held_out}
                for c in self.clips
            ],
            "ring": self.ring.to_json(),
            "resolution": self.resolution,
            "renderer": None if self.renderer is None else asdict(self.renderer),
            "channels": dict(self.channels),
            "charts": None if self.charts is None else asdict(self.charts),
            "params": copy.deepcopy(self.params),
            "counts": dict(self.counts),
            "coverage": None if self.coverage is None else self.coverage.to_json(),
            "splits": list(self.splits),
            "bytes": self.bytes,
            "checksum": self.checksum,
            "settings": copy.deepcopy(self.settings),
        }
        return {key: value for key, value in document.items() if value is not None}


DATASET_MANIFEST = (
    *spec_of(DatasetManifest, skip=("path", "format", "format_version")),
    # counts is an open table (a count per split name): the keys rigspace writes.
    Field("counts.samples", "count"),
    Field("counts.items", "count"),
    Field("counts.train", "count"),
    Field("counts.heldout-views", "count"),
    Field("counts.heldout-clips", "count"),
)
"""The fields of a dataset's manifest.json that rigspace reads (read_manifest), from
DatasetManifest and its sections' dataclasses (sdk.fields.spec_of); the manifest's path is no
key of it, and its format and version are checked before the spec."""


def _view_keys(coverage: Any) -> list[str]:
    """A sentence per key of coverage.empty_by_view that is not a view index (problems() checks
    the values' kinds only by path)."""
    if not isinstance(coverage, dict) or not isinstance(coverage.get("empty_by_view"), dict):
        return []
    return [
        f"'coverage.empty_by_view.{key}' is {value!r}, not a view's count of empty samples"
        for key, value in coverage["empty_by_view"].items()
        if not key.isdigit() or not isinstance(value, int) or isinstance(value, bool)
    ]


def _typed_manifest(data: dict[str, Any], path: Path) -> DatasetManifest:
    """A checked manifest document's fields, typed (values as written: to_json gives them back
    unchanged)."""
    renderer, charts, coverage = data.get("renderer"), data.get("charts"), data.get("coverage")
    return DatasetManifest(
        path=path,
        joints=tuple(data["joints"]),
        ring=ManifestRing.from_json(data["ring"]),
        resolution=data["resolution"],
        format=data["format"],
        format_version=data["format_version"],
        scene=data.get("scene", ""),
        scene_fingerprint=data.get("scene_fingerprint", ""),
        character=data.get("character", ""),
        skeleton=data.get("skeleton", ""),
        blend_shapes=tuple(data.get("blend_shapes") or ()),
        controls=controls_from_json(data.get("controls")),
        look_at_joint=data.get("look_at_joint", ""),
        rotation_encoding=data.get("rotation_encoding", "rot6d"),
        up_axis=data.get("up_axis", "Y"),
        meters_per_unit=data.get("meters_per_unit"),
        clips=tuple(
            Clip(c["name"], c["first"], c["last"], c.get("held_out", False))
            for c in data.get("clips", ())
        ),
        renderer=Renderer(renderer["name"], renderer["samples_per_axis"]) if renderer else None,
        channels=dict(data.get("channels", {})),
        charts=ChartsFile(charts["file"], charts["count"]) if charts else None,
        params=copy.deepcopy(data.get("params", {})),
        counts=dict(data.get("counts", {})),
        coverage=(
            Coverage(
                coverage["empty_below_pixels"],
                coverage["empty_samples"],
                {int(view): n for view, n in coverage["empty_by_view"].items()},
            )
            if coverage is not None
            else None
        ),
        splits=tuple(data.get("splits", SPLITS)),
        bytes=data.get("bytes", 0),
        checksum=data.get("checksum", ""),
        settings=copy.deepcopy(data.get("settings", {})),
    )


def read_manifest(folder: str | Path) -> DatasetManifest:
    """A finished dataset's manifest, checked and typed: the one reader that training and eval
    share."""
    folder = Path(folder)
    fix = "point at a dataset folder written by `rigspace capture SCENE --out DIR`."
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"Dataset {folder} is a file, not a dataset folder.", fix)
    if not folder.is_dir():
        raise DatasetError(f"Dataset folder {folder} does not exist.", fix)
    for name in (MANIFEST_FILE, PARAMS_FILE):
        if not (folder / name).is_file():
            raise DatasetError(
                f"{folder} has no {name}, so it is not a finished dataset.",
                f"{fix} An interrupted or damaged capture finishes with "
                f"`{resume_command(folder)}`.",
            )
    try:
        data = json.loads((folder / MANIFEST_FILE).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(
            f"{folder / MANIFEST_FILE} is not readable JSON ({exc}).",
            f"run `{resume_command(folder)}` to rewrite it.",
        ) from exc
    return DatasetManifest.from_json(data, folder / MANIFEST_FILE)


@dataclass(frozen=True)
class WorkItem:
    index: int
    clip_index: int
    clip: Clip
    times: tuple[float, ...]
    views: tuple[RingView, ...]

    @property
    def name(self) -> str:
        first = self.views[0].index
        return f"{self.clip_index:02d}_{self.clip.name}_t{self.times[0]:08.1f}_v{first:03d}"

    @property
    def samples(self) -> int:
        return len(self.times) * len(self.views)


def view_groups(views: list[RingView], settings: CaptureSettings) -> list[tuple[RingView, ...]]:
    """Views grouped by ring: each elevation's training views, then its held-out views."""
    groups: dict[tuple[float, bool], list[RingView]] = {}
    for view in views:
        groups.setdefault((view.elevation, view.held_out), []).append(view)
    return [tuple(g) for g in groups.values()]


def work_items(
    settings: CaptureSettings, samples: Sequence[float] | np.ndarray = ()
) -> list[WorkItem]:
    """Every work item of the capture, in dataset order; times snap to the animation's
    authored `samples` (settings.animation_time_samples) within the time-code tolerance."""
    groups = view_groups(settings.views(), settings)
    items: list[WorkItem] = []
    for clip_index, clip in enumerate(settings.clips):
        times = settings.clip_times(clip, samples)
        for start in range(0, len(times), settings.frames_per_item):
            chunk = tuple(float(t) for t in times[start : start + settings.frames_per_item])
            for group in groups:
                if clip.held_out and group[0].held_out:
                    continue  # held-out clips are seen from the training views only
                items.append(WorkItem(len(items), clip_index, clip, chunk, group))
    return items


def frame_batches(items: Sequence[WorkItem]) -> list[list[WorkItem]]:
    """Items grouped by (clip, frames), in order: one worker renders a batch, posing each frame
    once for all its view groups (ItemWorker.run_batch)."""
    batches: dict[tuple[int, tuple[float, ...]], list[WorkItem]] = {}
    for item in items:
        batches.setdefault((item.clip_index, item.times), []).append(item)
    return list(batches.values())


def shard_items(items: list[WorkItem], shard: tuple[int, int]) -> list[WorkItem]:
    index, count = shard
    return [item for item in items if item.index % count == index]


def split_of(clip: Clip, view: RingView) -> str:
    if clip.held_out:
        return HELDOUT_CLIPS
    return HELDOUT_VIEWS if view.held_out else TRAIN


def sample_path(clip: Clip, time: float, view: RingView) -> str:
    """A sample's EXR, relative to the dataset folder."""
    return f"samples/{clip.name}/t{time:08.1f}_v{view.index:03d}.exr"


def sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An .npz (np.load reads it) with fixed zip timestamps, so equal arrays give equal bytes.

    np.savez stamps each entry with the current time, which would make two captures of
    the same data differ byte for byte.
    """
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
        for name in sorted(arrays):
            entry = zipfile.ZipInfo(f"{name}.npy", date_time=ZIP_EPOCH)
            with archive.open(entry, "w", force_zip64=True) as stream:
                np.lib.format.write_array(stream, np.asarray(arrays[name]), allow_pickle=False)
    return buffer.getvalue()


def save_record(folder: Path, item: WorkItem, columns: dict[str, np.ndarray]) -> None:
    """Write an item's record (the commit point of the item)."""
    write_atomic(folder / "items" / f"{item.name}.npz", npz_bytes(columns))


def record_path(folder: Path, item: WorkItem) -> Path:
    return folder / "items" / f"{item.name}.npz"


def load_record(folder: Path, item: WorkItem) -> dict[str, np.ndarray]:
    with np.load(record_path(folder, item), allow_pickle=False) as data:
        record = {k: data[k] for k in data.files}
    if "coverage" not in record:  # written before coverage was recorded: read it off the EXRs
        record["coverage"] = np.array(
            [mask_coverage(read_exr(folder / str(p)).mask) for p in record["path"]],
            dtype=np.float32,
        )
    return record


def mask_coverage(mask: np.ndarray) -> float:
    """Pixels a sample's mask covers, as stored (half precision, like the EXR's A channel), so
    a re-rendered sample and its EXR give the same number."""
    return float(np.asarray(mask, dtype=np.float16).astype(np.float64).sum())


def empty_by_view(coverage: np.ndarray, views: np.ndarray) -> dict[int, int]:
    """How many samples of each view show nothing (coverage below EMPTY_PIXELS)."""
    found, counts = np.unique(
        np.asarray(views)[np.asarray(coverage) < EMPTY_PIXELS], return_counts=True
    )
    return {int(v): int(n) for v, n in zip(found, counts, strict=True)}


@dataclass(frozen=True)
class Damage:
    """A finished work item whose files no longer match its record."""

    item: WorkItem
    problems: tuple[str, ...]
    """One line per damaged file, e.g. "samples/walk/t000002.0_v001.exr: missing"."""


def verify_items(folder: Path, items: list[WorkItem]) -> list[Damage]:
    """Every finished item among `items` whose record or sample files are missing or damaged.

    Reads and hashes every sample file of every finished item (about 1 GB/s here); items
    without a record are not finished and not reported.
    """
    damaged = []
    for item in items:
        path = record_path(folder, item)
        if not path.is_file():
            continue
        try:
            with np.load(path, allow_pickle=False) as data:
                paths, checksums = data["path"], data["sha256"]
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            name = path.relative_to(folder)
            damaged.append(Damage(item, (f"{name}: unreadable ({type(exc).__name__})",)))
            continue
        expected = [sample_path(item.clip, t, v) for t in item.times for v in item.views]
        if sorted(str(p) for p in paths) != sorted(expected) or len(checksums) != len(paths):
            name = path.relative_to(folder)
            damaged.append(Damage(item, (f"{name}: lists other samples than the item's",)))
            continue
        problems = []
        for relative, checksum in zip(paths, checksums, strict=True):
            sample = folder / str(relative)
            if not sample.is_file():
                problems.append(f"{relative}: missing")
            elif sha256_file(sample) != checksum:
                problems.append(f"{relative}: checksum differs (damaged or truncated)")
        if problems:
            damaged.append(Damage(item, tuple(problems)))
    return damaged


def clean_temporaries(folder: Path) -> int:
    """Remove what killed runs left half-written (never a finished file)."""
    removed = 0
    for tmp in list(folder.rglob(".*.tmp*")):
        tmp.unlink(missing_ok=True)
        removed += 1
    return removed


def write_charts(folder: Path, charts: ChartTable) -> None:
    """The character's texture charts as charts.json (nothing for a character without textures:
    then its samples have no texture AOVs either)."""
    path = folder / CHARTS_FILE
    if len(charts):
        write_atomic(path, json.dumps(charts.to_json(), indent=2) + "\n")
    else:
        path.unlink(missing_ok=True)


def read_charts(folder: str | Path) -> dict[str, Any] | None:
    """A dataset's charts.json (None when it has none: no textured mesh, or an older capture)."""
    path = Path(folder) / CHARTS_FILE
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(
            f"{path} is not readable JSON ({exc}).",
            f"run `{resume_command(folder)}` to rewrite it.",
        ) from exc
    try:
        parse_charts(data)
    except ValueError as exc:
        raise DatasetError(
            f"{path} cannot be used: {exc}.",
            f"capture the dataset again (`{resume_command(folder)}` rewrites it when the "
            "dataset is otherwise whole).",
        ) from exc
    return data


def _dataset_checksum(
    folder: Path, table: dict[str, np.ndarray], params_bytes: bytes, charted: bool
) -> str:
    """sha256 over every sample's path and checksum, params.npz and charts.json if any."""
    digest = hashlib.sha256()
    for path, checksum in zip(table["path"], table["sha256"], strict=True):
        digest.update(f"{path} {checksum}\n".encode())
    digest.update(hashlib.sha256(params_bytes).digest())
    if charted:  # the chart numbering is part of what the samples mean
        digest.update(hashlib.sha256((folder / CHARTS_FILE).read_bytes()).digest())
    return digest.hexdigest()


def _ring(settings: CaptureSettings) -> ManifestRing:
    """The manifest's description of the capture ring and its views."""
    return ManifestRing(
        views_per_ring=settings.views_per_ring,
        elevations=tuple(settings.elevations),
        held_out_views_per_ring=settings.held_out_views_per_ring,
        held_out_elevations=tuple(settings.held_out_elevations),
        radius=settings.radius,
        focal_length=settings.focal_length,
        horizontal_aperture=settings.horizontal_aperture,
        clipping_range=tuple(settings.clipping_range),
        views=tuple(
            ManifestView(v.index, v.azimuth, v.elevation, v.held_out) for v in settings.views()
        ),
    )


def _channels_json(charts: ChartsFile | None) -> dict[str, str]:
    """The manifest's description of a sample EXR's channels (texture AOVs when charted)."""
    return {
        "R,G,B": "albedo, linear, premultiplied by A",
        "A": "coverage mask in [0, 1]",
        "Z": "camera-space depth along -Z, scene units, +inf where empty",
        "N.X,N.Y,N.Z": "camera-space unit normal, 0 where empty",
        **(
            {
                "uv.U,uv.V": "USD st of the visible surface on its chart's texture (the "
                "nearest sample's chart, mean over its samples on that chart), 0 where "
                "chart is 0",
                "chart": f"texture chart of the visible surface, 1..{charts.count} "
                f"({CHARTS_FILE}), 0: background or no texture",
            }
            if charts
            else {}
        ),
    }


def _params_json(settings: CaptureSettings, table: dict[str, np.ndarray]) -> dict[str, Any]:
    """The manifest's description of params.npz and its columns."""
    return {
        "file": PARAMS_FILE,
        "rig": "per joint (skeleton order) the world rotation in the camera frame, 6D "
        "(first two matrix columns)",
        "coverage": f"pixels the mask covers (sum of A); below {EMPTY_PIXELS:g} the sample "
        "shows nothing",
        **(
            {"blend": "per blend shape (blend_shapes order) the frame's weight"}
            if settings.dataset_shapes
            else {}
        ),
        **(
            {"controls": "per named control (controls order) the frame's value"}
            if settings.controls
            else {}
        ),
        "columns": sorted(table),
    }


def finalize(folder: Path, settings: CaptureSettings, items: list[WorkItem]) -> DatasetManifest:
    """Assemble params.npz and manifest.json from every item's record (all must exist)."""
    records = [load_record(folder, item) for item in items]
    table_of_charts = read_charts(folder)
    charts = ChartsFile(CHARTS_FILE, len(table_of_charts["charts"])) if table_of_charts else None
    table = {key: np.concatenate([r[key] for r in records]) for key in records[0]}
    params_bytes = npz_bytes(table)
    write_atomic(folder / PARAMS_FILE, params_bytes)
    split_counts = {s: int(np.sum(table["split"] == i)) for i, s in enumerate(SPLITS)}
    empty = empty_by_view(table["coverage"], table["view"])
    manifest = DatasetManifest(
        path=folder / MANIFEST_FILE,
        scene=settings.scene,
        scene_fingerprint=settings.scene_fingerprint,
        character=settings.character,
        skeleton=settings.skeleton,
        joints=tuple(settings.dataset_joints),
        blend_shapes=tuple(settings.dataset_shapes),
        controls=tuple(settings.controls),
        look_at_joint=settings.look_at_joint,
        rotation_encoding="rot6d",
        up_axis=settings.up_axis,
        meters_per_unit=settings.meters_per_unit,
        clips=tuple(settings.clips),
        ring=_ring(settings),
        resolution=settings.resolution,
        renderer=Renderer(settings.renderer, settings.samples_per_axis),
        channels=_channels_json(charts),
        charts=charts,
        params=_params_json(settings, table),
        counts={"samples": len(table["path"]), "items": len(items), **split_counts},
        coverage=Coverage(EMPTY_PIXELS, sum(empty.values()), empty),
        splits=SPLITS,
        bytes=int(sum((folder / str(p)).stat().st_size for p in table["path"])),
        checksum=_dataset_checksum(folder, table, params_bytes, charted=charts is not None),
        settings=json.loads(json.dumps(settings.to_json())),  # as read back: lists, not tuples
    )
    write_atomic(folder / MANIFEST_FILE, json.dumps(manifest.to_json(), indent=2) + "\n")
    return manifest


def read_sample(folder: Path, manifest: DatasetManifest, relative: str) -> Maps:
    """A dataset sample's maps; a missing or damaged EXR is a DatasetError naming the file
    and the capture command that re-renders it (training and evaluation read through here)."""
    path = folder / relative
    try:
        return read_exr(path)
    except OSError as exc:  # sdk.exr.ExrError is an OSError, as is a file that went away
        state = "missing" if not path.is_file() else "damaged"
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        scene = manifest.scene or "SCENE"
        raise DatasetError(
            f"Sample {path} of the dataset is {state} ({reason}).",
            f"re-render it: repeat the capture with --resume (`rigspace capture {scene} --out "
            f"{folder} --resume`: the settings come from its capture.json), which re-renders "
            "missing and damaged samples.",
        ) from exc


def training_views(folder: str | Path, joints: Sequence[str]) -> tuple[ViewCoverage, int] | None:
    """The training views of a dataset's look-at joint (sdk.view_coverage) for a network
    reading `joints` (its manifest's, in input order), with how many training rows there were;
    None without training rows or a look-at joint. Reads params.npz alone (no torch)."""
    from rigspace.sdk import schema

    folder = Path(folder)
    manifest = read_manifest(folder)
    if not manifest.look_at_joint:
        return None
    joint = schema.find_joint(manifest.look_at_joint, list(joints))
    with np.load(folder / "params.npz", allow_pickle=False) as table:
        rig, split = table["rig"], table["split"]
    if rig.ndim != 3 or rig.shape[1] != len(joints):
        raise DatasetError(
            f"Dataset {folder} records {rig.shape[1] if rig.ndim == 3 else '?'} joints a "
            f"sample, the network reads {len(joints)}.",
            "pass the dataset the network was trained on.",
        )
    rows = rig.reshape(len(rig), -1)
    train = rows[split == SPLITS.index(TRAIN)]
    if not len(train):
        return None
    held = rows[split == SPLITS.index(HELDOUT_VIEWS)]
    return build_views(train, held if len(held) else None, joint, manifest.ring.elevations)

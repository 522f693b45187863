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

import hashlib
import io
import json
import os
import shlex
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.capture.ring import HELDOUT_CLIPS, HELDOUT_VIEWS, SPLITS, TRAIN, RingView
from rigspace.capture.settings import CaptureSettings, Clip
from rigspace.sdk.charts import ChartTable, parse_charts
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.exr import read_exr
from rigspace.sdk.fields import DATASET_MANIFEST, problems
from rigspace.sdk.render import Maps

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


def resume_command(folder: str | Path) -> str:
    """The command line that resumes (and repairs) the capture in `folder`, from its
    capture.json: the flags that give exactly its settings; "rigspace capture ... --resume"
    when there is no readable capture.json."""
    folder = Path(folder)
    try:
        settings = json.loads((folder / SETTINGS_FILE).read_text())
        clips = settings["clips"]
        args = ["rigspace", "capture", settings["scene"], "--character", settings["character"]]
        args += ["--out", str(folder), "--views", str(settings["views_per_ring"])]
        args += ["--elevations", *(_number(e) for e in settings["elevations"])]
        args += ["--resolution", str(settings["resolution"])]
        args += ["--radius", _number(settings["radius"])]
        if [c["name"] for c in clips] == ["frames"]:
            args += ["--frames", f"{_number(clips[0]['first'])}:{_number(clips[0]['last'])}"]
        else:
            args += ["--clips", *(c["name"] for c in clips)]
        args += ["--renderer", settings["renderer"], "--samples", str(settings["samples_per_axis"])]
        args += ["--frames-per-item", str(settings["frames_per_item"])]
        if settings.get("every", 1) != 1:
            args += ["--every", str(settings["every"])]
        args += ["--resume"]
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return "rigspace capture ... --resume"
    return shlex.join(args)


def read_manifest(folder: str | Path) -> dict[str, Any]:
    """A finished dataset's manifest, checked: the one reader that training and eval share."""
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
        manifest = json.loads((folder / MANIFEST_FILE).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(
            f"{folder / MANIFEST_FILE} is not readable JSON ({exc}).",
            f"run `{resume_command(folder)}` to rewrite it.",
        ) from exc
    if not isinstance(manifest, dict) or (
        manifest.get("format"),
        manifest.get("format_version"),
    ) != (FORMAT, FORMAT_VERSION):
        found = manifest if not isinstance(manifest, dict) else manifest.get("format")
        raise DatasetError(
            f"{folder / MANIFEST_FILE} is not a {FORMAT} manifest of version {FORMAT_VERSION} "
            f"(found {found!r}).",
            "re-capture the dataset with this version of rigspace.",
        )
    wrong = problems(manifest, DATASET_MANIFEST)
    if wrong:
        raise DatasetError(
            f"{folder / MANIFEST_FILE}: {'; '.join(wrong)}.",
            f"restore the file, or re-capture the dataset (`{resume_command(folder)}` rewrites "
            "it from the samples).",
        )
    return manifest


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


def write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


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
        write_atomic(path, (json.dumps(charts.to_json(), indent=2) + "\n").encode())
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


def _ring_json(settings: CaptureSettings) -> dict[str, Any]:
    """The manifest's description of the capture ring and its views."""
    return {
        "views_per_ring": settings.views_per_ring,
        "elevations": list(settings.elevations),
        "held_out_views_per_ring": settings.held_out_views_per_ring,
        "held_out_elevations": list(settings.held_out_elevations),
        "radius": settings.radius,
        "focal_length": settings.focal_length,
        "horizontal_aperture": settings.horizontal_aperture,
        "clipping_range": list(settings.clipping_range),
        "views": [
            {
                "index": v.index,
                "azimuth": v.azimuth,
                "elevation": v.elevation,
                "held_out": v.held_out,
            }
            for v in settings.views()
        ],
    }


def _channels_json(charts: dict[str, Any] | None) -> dict[str, str]:
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
                "chart": f"texture chart of the visible surface, 1..{charts['count']} "
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
            if settings.blend_shapes
            else {}
        ),
        "columns": sorted(table),
    }


def finalize(folder: Path, settings: CaptureSettings, items: list[WorkItem]) -> dict[str, Any]:
    """Assemble params.npz and manifest.json from every item's record (all must exist)."""
    records = [load_record(folder, item) for item in items]
    table_of_charts = read_charts(folder)
    charts = (
        {"file": CHARTS_FILE, "count": len(table_of_charts["charts"])} if table_of_charts else None
    )
    table = {key: np.concatenate([r[key] for r in records]) for key in records[0]}
    params_bytes = npz_bytes(table)
    write_atomic(folder / PARAMS_FILE, params_bytes)
    split_counts = {s: int(np.sum(table["split"] == i)) for i, s in enumerate(SPLITS)}
    empty = empty_by_view(table["coverage"], table["view"])
    checksum = _dataset_checksum(folder, table, params_bytes, charted=bool(charts))
    total_bytes = int(sum((folder / str(p)).stat().st_size for p in table["path"]))
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "scene": settings.scene,
        "scene_fingerprint": settings.scene_fingerprint,
        "character": settings.character,
        "skeleton": settings.skeleton,
        "joints": list(settings.joints),
        **({"blend_shapes": list(settings.blend_shapes)} if settings.blend_shapes else {}),
        "look_at_joint": settings.look_at_joint,
        "rotation_encoding": "rot6d",
        "up_axis": settings.up_axis,
        "meters_per_unit": settings.meters_per_unit,
        "clips": [
            {"name": c.name, "first": c.first, "last": c.last, "held_out": c.held_out}
            for c in settings.clips
        ],
        "ring": _ring_json(settings),
        "resolution": settings.resolution,
        "renderer": {"name": settings.renderer, "samples_per_axis": settings.samples_per_axis},
        "channels": _channels_json(charts),
        **({"charts": charts} if charts else {}),
        "params": _params_json(settings, table),
        "counts": {"samples": len(table["path"]), "items": len(items), **split_counts},
        "coverage": {
            "empty_below_pixels": EMPTY_PIXELS,
            "empty_samples": sum(empty.values()),
            "empty_by_view": {str(v): n for v, n in empty.items()},
        },
        "splits": list(SPLITS),
        "bytes": total_bytes,
        "checksum": checksum,
        "settings": settings.to_json(),
    }
    write_atomic(folder / MANIFEST_FILE, (json.dumps(manifest, indent=2) + "\n").encode())
    return manifest


def read_sample(folder: Path, manifest: dict[str, Any], relative: str) -> Maps:
    """A dataset sample's maps; a missing or damaged EXR is a DatasetError naming the file
    and the capture command that re-renders it (training and evaluation read through here)."""
    path = folder / relative
    try:
        return read_exr(path)
    except OSError as exc:  # sdk.exr.ExrError is an OSError, as is a file that went away
        state = "missing" if not path.is_file() else "damaged"
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        scene = manifest.get("scene", "SCENE")
        raise DatasetError(
            f"Sample {path} of the dataset is {state} ({reason}).",
            f"re-render it: repeat the capture with --resume (`rigspace capture {scene} --out "
            f"{folder} --resume`, with the original capture's other flags), which re-renders "
            "missing and damaged samples.",
        ) from exc

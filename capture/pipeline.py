"""Run a capture: check the output folder, render the work items on every core, finalize.

Each worker process opens the stage, poses the character with UsdSkel and renders with
its own renderer (a GL context cannot cross a fork, so workers are spawned). The main
process hands out items, shows progress and watches coverage: when the first items show
nothing of the character (a ring that misses it) it stops with the fix, and at the end it
warns about views that stayed empty. See capture/dataset.py for the layout and the
resume, repair and shard guarantees.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import multiprocessing
import os
import shutil
import signal
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from rigspace.capture import dataset as ds
from rigspace.capture.contact import write_contact_sheet
from rigspace.capture.ring import RingView
from rigspace.capture.settings import (
    CaptureError,
    CaptureOverrides,
    CaptureSettings,
    Warn,
    animation_time_samples,
    character_reach,
    fit_radius,
    print_warning,
    resolve_settings,
)
from rigspace.sdk.camera import Camera
from rigspace.sdk.capsules import FILE_NAME as CAPSULES_FILE
from rigspace.sdk.capsules import fit_capsules, write_capsules
from rigspace.sdk.cli import sigterm_as_interrupt
from rigspace.sdk.exr import write_exr
from rigspace.sdk.fields import CAPTURE_SETTINGS, read_checked
from rigspace.sdk.files import write_atomic
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.render import DrawMesh, Maps, RenderSettings, choose_renderer
from rigspace.sdk.rotations import rig_parameters
from rigspace.sdk.stage import open_stage

STAGES = ("pose", "render", "write")
EARLY_SAMPLES = 24
"""Samples (whole items, as they finish) that must show something before the run goes on:
enough to see every view of a ring's first frames, a few seconds of work."""


@dataclass
class CaptureResult:
    folder: Path
    settings: CaptureSettings
    samples_total: int
    samples_done: int
    """Samples this run rendered (not counting items finished by earlier runs or other shards)."""
    seconds: float
    complete: bool
    manifest: ds.DatasetManifest | None
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds spent per stage (pose, render, write) summed over workers."""
    repaired: list[ds.Damage] = field(default_factory=list)
    """Finished items found damaged on disk and rendered again by this run."""
    warnings: list[str] = field(default_factory=list)

    def summary(self) -> str:
        rate = self.samples_done / self.seconds if self.seconds > 0 else 0.0
        text = (
            f"captured {self.samples_done} samples in {self.seconds:.1f} s "
            f"({rate:.1f} samples/s) into {self.folder}"
        )
        if self.timings and self.samples_done:
            per = {k: 1e3 * v / self.samples_done for k, v in self.timings.items()}
            text += " | per sample, one core: " + ", ".join(
                f"{k} {v:.1f} ms" for k, v in per.items()
            )
        if self.manifest:
            counts = self.manifest.counts
            text += (
                f"\ndataset complete: {counts['samples']} samples (train {counts['train']}, "
                f"held-out views {counts['heldout-views']}, held-out clips "
                f"{counts['heldout-clips']}), {self.manifest.bytes / 2**20:.1f} MiB, "
                f"checksum {self.manifest.checksum[:16]}"
            )
        else:
            text += f"\n{self.samples_total - self.samples_done} samples remain for other shards"
        if self.repaired:
            problems = [p for d in self.repaired for p in d.problems]
            shown = "; ".join(problems[:5]) + ("; ..." if len(problems) > 5 else "")
            text += (
                f"\nrepaired {len(self.repaired)} damaged work item(s) "
                f"({sum(d.item.samples for d in self.repaired)} samples rendered again): {shown}"
            )
        text += "".join(f"\nwarning: {w}" for w in self.warnings)
        return text


@dataclass(frozen=True)
class ItemDone:
    """What a worker reports for a finished item."""

    samples: int
    timings: dict[str, float]
    coverage: np.ndarray
    """Pixels the mask covers, per sample of the item."""
    views: np.ndarray
    """View index per sample of the item."""


@dataclass(frozen=True)
class PosedFrame:
    """One captured frame, posed once for all the views that render it."""

    time: float
    meshes: list[DrawMesh]
    world: np.ndarray
    """(J,4,4) joint world transforms."""
    joint_position: np.ndarray
    """The look-at joint's world position: the ring cameras aim at it."""
    weights: np.ndarray
    """The blend shape weights posed, then the controls' values (empty for a rig without
    either: CaptureSettings.frame_weights)."""
    region: list[DrawMesh] | None = None
    """A region's capture: its triangles of `meshes` (capture/regions.py), else None."""


ROW_FIELDS = (
    "path", "sha256", "rig", "joint_camera", "camera_to_world", "intrinsics",
    "clip", "time", "view", "elevation", "azimuth", "split", "coverage", "blend",
)  # fmt: skip
"""What a work item's record holds per sample (dataset.py; `blend` only for a rig with shapes,
split into `blend` and `controls` columns for a rig with named controls)."""


class ItemWorker:
    """Per-process state: the posed character and a renderer, reused for every item."""

    def __init__(self, settings: CaptureSettings, folder: Path) -> None:
        self.settings = settings
        self.folder = folder
        stage = open_stage(settings.scene)
        self.rig = CharacterRig(stage.GetPrimAtPath(settings.character))
        self.joint = self.rig.joints.index(settings.look_at_joint)
        spec = choose_renderer(settings.renderer)
        self.renderer = spec.create(RenderSettings(settings.samples_per_axis))
        self.lens = settings.lens
        self.region = None
        """A region's capture (capture/regions.py): its triangles, cut once."""
        self.inputs = dataset_inputs(settings, self.rig)
        """(joint indices, scalar indices) of the skeleton's joints and the frame's weights
        and controls that the dataset records (CaptureSettings.input_joints)."""
        if settings.region:
            from rigspace.capture.regions import RegionMeshes

            joints = tuple(self.rig.joints.index(j) for j in settings.region_joints)
            self.region = RegionMeshes(self.rig, joints)

    def run(self, item: ds.WorkItem) -> ItemDone:
        return self.run_batch([item])[0]

    def run_batch(self, items: Sequence[ds.WorkItem]) -> list[ItemDone]:
        """Items of one clip and frames (a frame's view groups, ds.frame_batches), frame by
        frame: each frame is posed once and its posed meshes are rendered from every view of
        every item, so a renderer keeps what it builds from them (embree's acceleration
        structure: about a second for a film character's 1.5M triangles) for all the views."""
        first = items[0]
        if any(i.clip_index != first.clip_index or i.times != first.times for i in items):
            raise ValueError("run_batch takes items of one clip and the same frames")
        timings = dict.fromkeys(STAGES, 0.0)
        rows: list[dict[str, list[Any]]] = [{k: [] for k in ROW_FIELDS} for _ in items]
        for t in first.times:
            start = time.perf_counter()
            frame = self.pose(first.clip.name, t)
            timings["pose"] += time.perf_counter() - start
            for item, item_rows in zip(items, rows, strict=True):
                for view in item.views:
                    self._sample(item, frame, view, item_rows, timings)
        done = []
        for item, item_rows in zip(items, rows, strict=True):
            columns = self._columns(item_rows)
            ds.save_record(self.folder, item, columns)
            # The first item carries the batch's timings: the pose was shared by them all.
            shared = timings if item is first else dict.fromkeys(timings, 0.0)
            done.append(ItemDone(item.samples, shared, columns["coverage"], columns["view"]))
        return done

    def pose(self, clip: str, t: float, overrides: dict[str, float] | None = None) -> PosedFrame:
        """The character at `t` of `clip` as captured, the shapes in `overrides` (name ->
        weight) set apart from the frame's own weights (train/shapes.py's shape response)."""
        world = self.rig.world_transforms(t)
        weights = self.settings.frame_weights(self.rig, clip, t)
        for name, value in (overrides or {}).items():
            weights[self.rig.blend_shapes.index(name)] = value
        # Blend shapes, then skinning; texture AOVs (sdk/charts.py).
        meshes = self.rig.posed_meshes(t, charts=True, weights=weights)
        region = None if self.region is None else self.region.of(meshes)
        return PosedFrame(t, meshes, world, world[self.joint][:3, 3], weights, region)

    def render(self, frame: PosedFrame, camera: Camera) -> Maps:
        """The frame's maps from `camera`; for a region's capture, the region's surface alone
        (CaptureSettings.region_surface "whole"), or where it is the nearest ("visible")."""
        if frame.region is None:
            return self.renderer.render(frame.meshes, camera)
        region = self.renderer.render(frame.region, camera)
        if self.settings.region_surface == "whole":
            return region
        from rigspace.capture.regions import visible_region

        return visible_region(self.renderer.render(frame.meshes, camera), region)

    def _sample(
        self,
        item: ds.WorkItem,
        frame: PosedFrame,
        view: RingView,
        rows: dict[str, list[Any]],
        timings: dict[str, float],
    ) -> None:
        """Render, write and describe one sample (a posed frame from one view)."""
        t, world, joint_position = frame.time, frame.world, frame.joint_position
        start = time.perf_counter()
        camera = view.camera(joint_position, self.lens, self.settings.camera_up(world[self.joint]))
        maps = self.render(frame, camera)
        timings["render"] += time.perf_counter() - start
        for phase, seconds in getattr(self.renderer, "last_timings", {}).items():
            timings[f"render.{phase}"] = timings.get(f"render.{phase}", 0.0) + seconds
        start = time.perf_counter()
        relative = ds.sample_path(item.clip, t, view)
        path = self.folder / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        write_exr(path, maps)
        timings["write"] += time.perf_counter() - start
        rows["path"].append(relative)
        rows["sha256"].append(ds.sha256_file(path))
        rows["rig"].append(rig_parameters(world[self.inputs[0]], camera.camera_to_world))
        rows["joint_camera"].append(camera.to_camera(joint_position[None])[0])
        rows["camera_to_world"].append(camera.camera_to_world)
        rows["intrinsics"].append([camera.fx, camera.fy, camera.cx, camera.cy])
        rows["clip"].append(item.clip_index)
        rows["time"].append(t)
        rows["view"].append(view.index)
        rows["elevation"].append(view.elevation)
        rows["azimuth"].append(view.azimuth)
        rows["split"].append(ds.SPLITS.index(ds.split_of(item.clip, view)))
        rows["coverage"].append(ds.mask_coverage(maps.mask))
        rows["blend"].append(frame.weights[self.inputs[1]])

    def _columns(self, rows: dict[str, list[Any]]) -> dict[str, np.ndarray]:
        """An item's record columns from its samples' rows."""
        columns = {
            "path": np.array(rows["path"]),
            "sha256": np.array(rows["sha256"]),
            "rig": np.stack(rows["rig"]).astype(np.float32),
            "joint_camera": np.array(rows["joint_camera"], dtype=np.float32),
            "camera_to_world": np.array(rows["camera_to_world"], dtype=np.float64),
            "intrinsics": np.array(rows["intrinsics"], dtype=np.float64),
            "clip": np.array(rows["clip"], dtype=np.int16),
            "time": np.array(rows["time"], dtype=np.float64),
            "view": np.array(rows["view"], dtype=np.int16),
            "elevation": np.array(rows["elevation"], dtype=np.float32),
            "azimuth": np.array(rows["azimuth"], dtype=np.float32),
            "split": np.array(rows["split"], dtype=np.int8),
            "coverage": np.array(rows["coverage"], dtype=np.float32),
        }
        # A rig without blend shapes or controls writes the columns it always did.
        scalars = np.array(rows["blend"], dtype=np.float32).reshape(len(rows["path"]), -1)
        shapes = len(self.settings.dataset_shapes)
        if shapes:
            columns["blend"] = scalars[:, :shapes]
        if self.rig.controls:
            columns["controls"] = scalars[:, shapes:]
        return columns

    def close(self) -> None:
        self.renderer.close()


def dataset_inputs(settings: CaptureSettings, rig: CharacterRig) -> tuple[np.ndarray, np.ndarray]:
    """(joint indices into the skeleton, indices into the frame's weights and controls) of
    what the dataset records: every joint, shape and control, or a region's own joints and
    shapes (CaptureSettings.input_joints) and every control."""
    joints = np.array([rig.joints.index(j) for j in settings.dataset_joints], np.int64)
    shapes = [rig.blend_shapes.index(s) for s in settings.dataset_shapes]
    controls = range(len(rig.blend_shapes), len(rig.blend_shapes) + len(rig.controls))
    return joints, np.array([*shapes, *controls], np.int64)


_worker: ItemWorker | None = None


def _init_worker(settings_json: dict[str, Any], folder: str) -> None:
    global _worker
    # Ctrl-C reaches the whole process group: the main process alone handles it (its pool
    # then terminates the workers, quietly), so no worker prints a traceback of its own.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _worker = ItemWorker(CaptureSettings.from_json(settings_json), Path(folder))


def _run_batch(items: list[ds.WorkItem]) -> list[ItemDone]:
    assert _worker is not None, "worker not initialised"
    return _worker.run_batch(items)


def parse_shard(text: str) -> tuple[int, int]:
    try:
        index, count = (int(x) for x in text.split("/"))
    except ValueError:
        raise CaptureError(
            f"--shard {text!r} is not i/n.", "write e.g. --shard 0/4 (shards 0 to 3 of 4)."
        ) from None
    if not 0 <= index < count:
        raise CaptureError(
            f"--shard {text}: i must be in 0 to n-1.", f"use 0/{count} to {count - 1}/{count}."
        )
    return index, count


def prepare_folder(folder: Path, settings: CaptureSettings, resume: bool, sharded: bool) -> bool:
    """Check the output folder before any work; create it when it is new (then True)."""
    if folder.exists() and not folder.is_dir():
        raise CaptureError(f"--out {folder} is a file.", "choose a folder.")
    settings_file = folder / ds.SETTINGS_FILE
    if folder.is_dir() and any(folder.iterdir()):
        if not settings_file.is_file():
            raise CaptureError(
                f"--out {folder} is not empty and is not a rigspace dataset.",
                "choose a new or empty folder.",
            )
        existing = read_checked(
            settings_file,
            CAPTURE_SETTINGS,
            CaptureError,
            "restore it, or capture into a new folder.",
        )
        wanted = json.loads(json.dumps(settings.to_json()))  # tuples become lists, as on disk
        differs = sorted(k for k in set(existing) | set(wanted) if existing.get(k) != wanted.get(k))
        if differs:
            raise CaptureError(
                f"--out {folder} holds a dataset captured with different settings "
                f"({', '.join(differs)}).",
                "capture into a new folder, or resume it with --resume and none of the flags "
                "that differ (it takes the settings its capture.json saved).",
            )
        if not (resume or sharded):
            raise CaptureError(
                f"--out {folder} already holds this capture.",
                "pass --resume to finish it, or choose a new folder.",
            )
        return False
    parent = next(p for p in [folder, *folder.parents] if p.exists())
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CaptureError(
            f"--out {folder} cannot be created: {parent} is not writable.",
            "choose a writable location.",
        )
    try:
        (folder / "items").mkdir(parents=True, exist_ok=True)
        write_atomic(settings_file, json.dumps(settings.to_json(), indent=2) + "\n")
    except OSError as exc:
        raise CaptureError(
            f"--out {folder} cannot be written: {exc}.", "choose a writable location."
        ) from exc
    return True


def repair(folder: Path, items: list[ds.WorkItem]) -> list[ds.Damage]:
    """Find the damaged finished items among `items` and mark them unfinished (drop their
    records), so this run renders them again; the manifest goes too until the dataset is
    whole again, so an interrupted repair leaves an unfinished dataset, never a wrong one."""
    damaged = ds.verify_items(folder, items)
    if damaged:
        (folder / ds.MANIFEST_FILE).unlink(missing_ok=True)
        for damage in damaged:
            ds.record_path(folder, damage.item).unlink(missing_ok=True)
    return damaged


def nothing_in_view(
    settings: CaptureSettings, rig: CharacterRig, samples: int, best: float
) -> CaptureError:
    """The error for a capture whose first samples show nothing, with framing that works."""
    joint = settings.joints.index(settings.look_at_joint)
    reach = character_reach(rig, joint, settings.clips)
    near, far = settings.clipping_range
    size = settings.resolution
    what = (
        f"Capture of {settings.character} shows nothing: its first {samples} samples cover at "
        f"most {best:.2g} pixels of {size}x{size} (fewer than {ds.EMPTY_PIXELS:g}). The ring: "
        f"radius {settings.radius:g}, focal length {settings.focal_length:g}, horizontal "
        f"aperture {settings.horizontal_aperture:g}, clipping range ({near:g}, {far:g}), "
        f"elevations {list(settings.elevations)}, looking at joint {settings.look_at_joint!r}; "
        f"the character reaches {reach:.3g} scene units from that joint."
    )
    if reach <= 0:
        return CaptureError(what, "check the character's meshes and skin weights.")
    fit = fit_radius(reach, settings.focal_length, settings.horizontal_aperture)
    focal = settings.focal_length * settings.radius / fit
    fix = (
        f"pass --radius {fit:.3g}, which frames the character (or set "
        "rigspace:captureRing:radius to 0 to fit it), or set rigspace:captureRing:focalLength "
        f"to {focal:.3g} to keep radius {settings.radius:g}"
    )
    if fit <= near:
        fix += f", and lower the near clipping distance below {fit:.3g}"
    return CaptureError(what, fix + ".")


def _empty_views_warning(settings: CaptureSettings, empty: dict[int, int], total: int) -> str:
    count = sum(empty.values())
    by_view = ", ".join(f"view {v}: {n}" for v, n in sorted(empty.items()))
    if settings.region:
        hidden = (
            "the rest of the character hides it there (a hand behind the body), or "
            if settings.region_surface == "visible"
            else ""
        )
        return (
            f"{count} of {total} samples show less than {ds.EMPTY_PIXELS:g} pixels of region "
            f"{settings.region} of {settings.character} ({by_view}): {hidden}its ring misses "
            f"it (radius {settings.radius:g}; rigspace:region:{settings.region}:size widens it)."
        )
    return (
        f"{count} of {total} samples show less than {ds.EMPTY_PIXELS:g} pixels of "
        f"{settings.character} ({by_view}); they teach the network nothing. Check those views' "
        f"cameras (radius {settings.radius:g}, clipping range "
        f"({settings.clipping_range[0]:g}, {settings.clipping_range[1]:g}), "
        "elevations, look-at joint) and capture again into a new folder."
    )


Runner = Callable[
    [CaptureSettings, Path, list[ds.WorkItem], int | None, contextlib.ExitStack],
    Iterator[ItemDone],
]
"""Renders `mine` (the unfinished items) and yields each item's ItemDone as it commits. Called
inside capture's ExitStack: it starts what it needs (processes, a cluster) before returning
and registers their clean-up on the stack."""


def local_items(
    settings: CaptureSettings,
    folder: Path,
    mine: list[ds.WorkItem],
    workers: int | None,
    stack: contextlib.ExitStack,
) -> Iterator[ItemDone]:
    """The items rendered here: in this process, or a pool of `workers` spawned processes."""
    batches = ds.frame_batches(mine)
    workers = max(1, min(workers or os.cpu_count() or 1, len(batches) or 1))
    if workers == 1:
        worker = ItemWorker(settings, folder)
        stack.callback(worker.close)
        return itertools.chain.from_iterable(map(worker.run_batch, batches))
    pool = stack.enter_context(
        multiprocessing.get_context("spawn").Pool(
            workers,
            initializer=_init_worker,
            initargs=(settings.to_json(), str(folder)),
        )
    )
    return itertools.chain.from_iterable(pool.imap_unordered(_run_batch, batches))


def _plan_items(
    folder: Path,
    settings: CaptureSettings,
    rig: CharacterRig,
    shard: tuple[int, int],
    created: bool,
) -> tuple[list[ds.WorkItem], list[ds.Damage], list[ds.WorkItem]]:
    """Tidy the folder; every work item, the shard's repaired ones, and its unfinished ones."""
    (folder / "items").mkdir(exist_ok=True)
    ds.clean_temporaries(folder)
    items = ds.work_items(settings, animation_time_samples(rig))
    ours = ds.shard_items(items, shard)
    repaired = [] if created else repair(folder, ours)
    mine = [i for i in ours if not ds.record_path(folder, i).is_file()]
    return items, repaired, mine


@dataclass
class _Tally:
    """What the items this run rendered add up to, as they commit."""

    done: int = 0
    timings: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    coverage: list[np.ndarray] = field(default_factory=list)
    views: list[np.ndarray] = field(default_factory=list)


def _tally_items(
    results: Iterator[ItemDone],
    settings: CaptureSettings,
    rig: CharacterRig,
    total: int,
    bar: tqdm,
    tally: _Tally,
) -> None:
    """Count each item as it commits; stop when the first samples show nothing."""
    seen_something = False
    for finished in results:
        tally.done += finished.samples
        bar.update(finished.samples)
        for k, v in finished.timings.items():
            tally.timings[k] = tally.timings.get(k, 0.0) + v
        tally.coverage.append(finished.coverage)
        tally.views.append(finished.views)
        # A ring that misses the character: stop after a few seconds, not hours.
        seen_something = seen_something or bool(np.any(tally.coverage[-1] >= ds.EMPTY_PIXELS))
        if not seen_something and tally.done >= min(EARLY_SAMPLES, total):
            best = float(np.concatenate(tally.coverage).max())
            raise nothing_in_view(settings, rig, tally.done, best)


def _render_items(
    settings: CaptureSettings,
    rig: CharacterRig,
    folder: Path,
    mine: list[ds.WorkItem],
    total: int,
    *,
    scene: str | Path,
    remove_on_error: bool,
    workers: int | None,
    progress: bool,
    runner: Runner,
) -> tuple[_Tally, float]:
    """Render the unfinished items with `runner`, with progress; their tally and seconds."""
    tally = _Tally()
    bar = tqdm(
        total=total, unit="sample", disable=not progress, file=sys.stderr, dynamic_ncols=True
    )
    start = time.perf_counter()
    restore = sigterm_as_interrupt()
    try:
        with contextlib.ExitStack() as stack:
            stack.callback(bar.close)
            results = runner(settings, folder, mine, workers, stack)
            start = time.perf_counter()  # after the runner's start-up (a pool, a cluster)
            _tally_items(results, settings, rig, total, bar, tally)
    except KeyboardInterrupt:
        # Ctrl-C or SIGTERM: the pool is gone, every committed item is kept; say how to go on.
        kept = len(list((folder / "items").glob("*.npz")))
        print(
            f"rigspace capture: interrupted: {kept} work items are kept in {folder}; finish "
            f"them with `rigspace capture {scene} --out {folder} --resume` (the settings "
            "come from its capture.json)",
            file=sys.stderr,
        )
        raise
    except CaptureError as exc:
        # The pool is gone (the with block ended); a folder this run created holds nothing
        # worth keeping, and leaving it would make the fixed command fail as "different
        # settings". An existing dataset, or one shared with other shards, is kept as it is.
        if remove_on_error:
            shutil.rmtree(folder, ignore_errors=True)
            exc.what += f" Nothing was kept: {folder} was removed."
        else:
            exc.what += f" {folder} is kept as it was."
        exc.args = (f"{exc.what} Fix: {exc.fix}",)
        raise
    finally:
        restore()
    return tally, time.perf_counter() - start


def _complete_dataset(
    folder: Path, settings: CaptureSettings, rig: CharacterRig, items: list[ds.WorkItem]
) -> ds.DatasetManifest:
    """Write a finished dataset's charts, manifest, contact sheet and capsules."""
    # The texture charts the samples' chart AOV numbers (before the manifest names them).
    ds.write_charts(folder, rig.texture_charts())
    manifest = ds.finalize(folder, settings, items)
    write_contact_sheet(folder)
    # The character's shadow capsules, fitted at bind pose; export copies them into the bundle.
    write_capsules(fit_capsules(rig), folder / CAPSULES_FILE)
    return manifest


def _empty_views(manifest: ds.DatasetManifest | None, tally: _Tally) -> tuple[dict[int, int], int]:
    """The empty samples per view, and how many samples they are counted among."""
    if manifest is not None and manifest.coverage is not None:
        return dict(manifest.coverage.empty_by_view), manifest.counts["samples"]
    empty = ds.empty_by_view(
        np.concatenate(tally.coverage or [np.zeros(0)]),
        np.concatenate(tally.views or [np.zeros(0)]),
    )
    return empty, tally.done


def _capture_settings(
    scene: str | Path,
    character: str,
    overrides: CaptureOverrides | None,
    region: str | None,
    warn: Warn,
) -> tuple[CaptureSettings, CharacterRig]:
    """The capture's settings (with `region`, that region's), its renderer chosen by name."""
    settings, rig = resolve_settings(scene, character, overrides, warn=warn)
    if region is not None:
        from rigspace.capture.regions import find_region, region_settings

        settings = region_settings(settings, rig, find_region(rig.character, region), warn)
    # A concrete name, so the dataset records it (and every worker renders with it).
    renderer = choose_renderer(settings.renderer, rig.triangle_count)
    return replace(settings, renderer=renderer.name), rig


def capture(
    scene: str | Path,
    character: str,
    out: str | Path,
    overrides: CaptureOverrides | None = None,
    *,
    shard: tuple[int, int] = (0, 1),
    resume: bool = False,
    workers: int | None = None,
    progress: bool = True,
    warn: Warn = print_warning,
    runner: Runner | None = None,
    region: str | None = None,
) -> CaptureResult:
    """Capture a neural character's dataset (see the module and capture/dataset.py docs), or
    with `region` the dataset of one of its regions (capture/regions.py).

    `runner` renders the unfinished items and yields each one's ItemDone as it commits:
    local_items (this machine's processes) by default, capture/ray_capture.py's on Ray.
    """
    warnings: list[str] = []

    def note(text: str) -> None:
        warnings.append(text)
        warn(text)

    settings, rig = _capture_settings(scene, character, overrides, region, note)
    folder = Path(out)
    created = prepare_folder(folder, settings, resume, sharded=shard[1] > 1)
    items, repaired, mine = _plan_items(folder, settings, rig, shard, created)
    total = sum(i.samples for i in mine)
    tally, seconds = _render_items(
        settings,
        rig,
        folder,
        mine,
        total,
        scene=scene,
        remove_on_error=created and shard[1] == 1,
        workers=workers,
        progress=progress,
        runner=runner or local_items,
    )
    complete = all(ds.record_path(folder, i).is_file() for i in items)
    manifest = _complete_dataset(folder, settings, rig, items) if complete else None
    empty, total_samples = _empty_views(manifest, tally)
    if empty:
        note(_empty_views_warning(settings, empty, total_samples))
    return CaptureResult(
        folder,
        settings,
        total,
        tally.done,
        seconds,
        complete,
        manifest,
        tally.timings,
        repaired,
        warnings,
    )

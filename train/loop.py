"""The training loop: progressive levels with fade-in, checkpoints, evaluation, previews.

    run = train(dataset, out, config, steps=None, minutes=None, resume=False)

The run folder holds run.json (the config and the dataset it trained on), checkpoints
(loadable with torch.load(weights_only=True): tensors, numbers and strings only),
log.jsonl (a line per step: the loss and its terms albedo, mask, alpha, depth, normal;
the level's resolution, its block's fade-in weight `fade` and the training seconds; older
logs hold the fade weight under `alpha` in place of that term), and previews/level_<R>.png
(prediction | ground truth | error). Every step's batch is a pure function of (seed, step)
and the RNG state is checkpointed, so a resumed run continues exactly where it stopped.
Ctrl-C (or SIGTERM) saves a checkpoint and returns; a non-finite loss stops with the step and the last good checkpoint named; a damaged sample
stops with a checkpoint and the capture command that re-renders it. With `minutes`, a new
run first measures its step time at every level and sizes its steps per level so that the
final level is reached within the budget (train.budget; the plan is saved in run.json).
"""

from __future__ import annotations

import copy
import functools
import io
import json
import math
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, ParamSpec, TypeVar

import cv2
import numpy as np
import torch

from rigspace.capture.dataset import DatasetError, DatasetManifest, read_manifest
from rigspace.sdk.cli import sigterm_as_interrupt
from rigspace.sdk.controls import Control, controls_from_json, controls_json
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.fields import Field, problems, read_checked, spec_of
from rigspace.sdk.files import replacing, write_atomic
from rigspace.train import distributed
from rigspace.train.budget import Pace, apply_plan, plan_schedule
from rigspace.train.callbacks import (
    Anneal,
    Callback,
    Checkpoints,
    LoopState,
    Pacer,
    Previews,
    ProgressBar,
    StepLog,
    run_steps,
)
from rigspace.train.conditioning import dataset_skeleton, parents_of
from rigspace.train.config import TrainConfig, check_anneal
from rigspace.train.data import SampleSet, chart_boxes, ensure_cache, texels_per_coordinate
from rigspace.train.loss import targets_for
from rigspace.train.network import Rig2Image, Shape, albedo_maps, geometry_maps, texture_maps
from rigspace.train.resident import ResidentBatches, resident_or_not
from rigspace.train.step import (
    forward_loss,
    make_optimizer,
    optimise,
    schedule,
    set_lr,
    to_torch,
)
from rigspace.train.stream import is_shards, open_split, prefetcher

if TYPE_CHECKING:
    from rigspace.train.regions import ShapeMobility

CHECKPOINT = "checkpoint.pt"
RUN_FILE = "run.json"
PROBE_STEPS = 3
"""Timed steps per level when a time budget is planned (after one warm-up step)."""


class TrainingError(RigspaceError):
    """Training cannot start or cannot go on."""


RUN_FIX = "restore it, or start the run over in a new --out."


@dataclass(frozen=True)
class RunRecord:
    """What a training run's run.json records: the options and the dataset it trains on (a
    resumed run must match them, `differences`), the network's input, and a time budget's plan.
    Read and checked once (read_run); `to_json` is the file's document (run_record's)."""

    config: dict[str, Any]
    """The training options as written (`train_config` reads them, with the defaults of
    options added since)."""
    dataset: str
    """The dataset (or shards) folder trained on, resolved."""
    joints: tuple[str, ...]
    """The dataset's joints: the rig input's order."""
    dataset_checksum: str = ""
    """The dataset manifest's checksum ("" when not recorded)."""
    blend_shapes: tuple[str, ...] = ()
    """Blend shapes whose weights follow the rotations in the rig input (none: not written)."""
    controls: tuple[Control, ...] = ()
    """Named controls whose values follow the blend shape weights (none: not written)."""
    charts: int | None = None
    """The texture head's charts; None for a run without one."""
    plan: dict[str, Any] | None = None
    """A time budget's plan (train.budget.Plan.to_json); None without a budget."""

    def train_config(self) -> TrainConfig:
        return TrainConfig.from_json(self.config)

    @property
    def planned_steps_per_level(self) -> int | None:
        """The steps per level the budget planned; None without a plan."""
        return None if not self.plan else int(self.plan["steps_per_level"])

    @classmethod
    def from_json(cls, data: Any, path: Path) -> RunRecord:
        """Check a run.json document (a TrainingError naming `path` and the field) and type it."""
        wrong = problems(data, TRAINING_RUN) if isinstance(data, dict) else ["it is not an object"]
        if wrong:
            raise TrainingError(f"{path}: {'; '.join(wrong)}.", RUN_FIX)
        return cls(
            config=copy.deepcopy(data["config"]),
            dataset=data["dataset"],
            joints=tuple(data["joints"]),
            dataset_checksum=data.get("dataset_checksum", ""),
            blend_shapes=tuple(data.get("blend_shapes") or ()),
            controls=controls_from_json(data.get("controls")),
            charts=data.get("charts"),
            plan=copy.deepcopy(data["plan"]) if data.get("plan") else None,
        )

    def to_json(self) -> dict[str, Any]:
        document = {
            "config": copy.deepcopy(self.config),
            "dataset": self.dataset,
            "dataset_checksum": self.dataset_checksum,
            "joints": list(self.joints),
            "blend_shapes": list(self.blend_shapes) or None,
            "controls": controls_json(self.controls),
            "charts": self.charts,
            "plan": copy.deepcopy(self.plan),
        }
        return {key: value for key, value in document.items() if value is not None}

    def differences(self, other: RunRecord) -> list[str]:
        """The fields this record has (a plan aside) that `other` records otherwise, by name;
        options compared as TrainConfig reads them, so an option added since is its default."""
        ours = replace(self, plan=None).to_json()
        theirs = replace(other, config=other.train_config().to_json()).to_json()
        ours, theirs = json.loads(json.dumps(ours)), json.loads(json.dumps(theirs))
        return sorted(key for key in ours if theirs.get(key) != ours[key])


TRAINING_RUN = (
    *spec_of(RunRecord),
    # plan is an open table (train.budget.Plan.to_json): the keys rigspace reads.
    Field("plan.steps_per_level", "size", required=True),
    Field("plan.seconds_per_step", "object"),
)
"""The fields of a training run's run.json (read_run), from RunRecord (sdk.fields.spec_of)."""


@dataclass
class TrainResult:
    folder: Path
    step: int
    seconds: float
    stopped: str
    """'done', 'time budget', 'step budget' or 'interrupted'."""
    last_loss: float
    images_per_second: float


def save_checkpoint(folder: Path, model, optimizer, step: int, level: int) -> Path:
    path = folder / CHECKPOINT
    with replacing(path) as tmp:
        torch.save(
            {
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "step": step,
                "level": level,
                "torch_rng": torch.get_rng_state(),
            },
            tmp,
        )
    return path


def load_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint, read without unpickling arbitrary objects (weights_only=True)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt, truncated, or not ours: say which file and why
        raise TrainingError(
            f"Checkpoint {path} cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0]}).",
            "delete it to start over, or restore it from a backup.",
        ) from exc


def _preview(
    model, samples: SampleSet, resolution: int, path: Path, texel_scale: np.ndarray | None = None
) -> dict[str, float]:
    """Prediction | ground truth | error for a few held-out samples; returns quick metrics
    (with a texture head: the share of covered pixels whose chart is right, and where it is,
    the coordinates' error in texels, median and 90th percentile, given `texel_scale`)."""
    ks = np.linspace(0, len(samples) - 1, min(4, len(samples))).astype(int)
    batch = samples.batch(ks)
    with torch.no_grad():
        joints2d = torch.from_numpy(batch["joints2d"]) if "joints2d" in batch else None
        heads = model(torch.from_numpy(batch["rig"]), resolution, joints2d=joints2d)
        albedo = albedo_maps(heads["albedo"][-1]).numpy()
        mask = geometry_maps(heads["geometry"][-1])[2].numpy()
        target = targets_for(
            {k: torch.from_numpy(v) for k, v in batch.items()}, resolution, model.charts
        )
    target_albedo, target_mask = target["albedo"].numpy(), target["mask"].numpy()
    quick: dict[str, float] = {}
    if model.charts and "chart" in target:  # how often the texture head names the right chart
        branch = model.texture_branch
        logits, coords = texture_maps(heads[branch][-1], model.charts, branch)
        covered = target_mask[:, 0] > 0.5
        chart = target["chart"][:, 0].numpy()
        right = logits.argmax(dim=1).numpy() == chart
        quick["chart_accuracy"] = float(right[covered].mean()) if covered.any() else math.nan
        if texel_scale is not None:
            quick |= texel_error(coords.numpy(), target["uv"].numpy(), chart, right & covered,
                                 texel_scale)  # fmt: skip
    mse = float(np.mean((albedo - target_albedo) ** 2))
    inter = np.logical_and(mask > 0.5, target_mask > 0.5).sum()
    union = np.logical_or(mask > 0.5, target_mask > 0.5).sum()
    rows = []
    for p, t in zip(albedo, target_albedo, strict=True):
        err = np.abs(p - t).mean(axis=0, keepdims=True).repeat(3, axis=0) * 4
        tiles = [np.clip(x, 0, 1) ** (1 / 2.2) for x in (p, t, err)]
        rows.append(np.concatenate([np.moveaxis(x, 0, -1) for x in tiles], axis=1))
    pixels = (np.concatenate(rows, axis=0) * 255 + 0.5).astype(np.uint8)[..., ::-1]
    scale = max(1, 128 // resolution)
    image: np.ndarray = cv2.resize(
        pixels, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), image)
    return {
        "albedo_psnr": 10 * math.log10(1.0 / max(mse, 1e-12)),
        "mask_iou": float(inter / max(union, 1)),
        **quick,
    }


def prepare_run(
    dataset: Path, out: Path, config: TrainConfig, resume: bool
) -> tuple[DatasetManifest, TrainConfig, RunRecord | None]:
    """Check the dataset and the run folder before any work.

    Returns the dataset manifest, the config to train with, and the run.json of the run
    being resumed (None for a new run). A run planned for a time budget keeps its planned
    steps per level when resumed with the same options.
    """
    manifest = read_manifest(dataset)
    if config.texture and manifest.charts is None and not resume:
        print(
            f"rigspace train: {dataset} has no texture charts (its character has no texture, "
            "or it was captured before texture AOVs): no texture head; the albedo head alone "
            "gives colour",
            file=sys.stderr,
        )
    if config.resolution > manifest.resolution:
        raise TrainingError(
            f"--resolution {config.resolution} is above the dataset's {manifest.resolution}.",
            f"train at {manifest.resolution} or below, or capture at a higher resolution.",
        )
    if out.exists() and not out.is_dir():
        raise TrainingError(f"{out} is a file, not a folder.", "choose a folder for --out.")
    run_file = out / RUN_FILE
    if not run_file.exists():
        return manifest, config, None
    existing = read_run(out)
    if not resume:
        raise TrainingError(
            f"{out} already holds a training run.",
            "pass --resume to continue it, or choose a new --out.",
        )
    if existing.planned_steps_per_level is not None:
        config = replace(config, steps_per_level=existing.planned_steps_per_level)
    differs = run_record(dataset, manifest, config).differences(existing)
    if differs:
        raise TrainingError(
            f"{out} holds a run with other settings or another dataset ({', '.join(differs)}).",
            "resume with the original options, or choose a new --out.",
        )
    return manifest, config, existing


def read_run(folder: Path) -> RunRecord:
    """A run folder's run.json, checked against its spec (TRAINING_RUN) and typed: a
    damaged or hand-edited file is a TrainingError naming the field, never a traceback."""
    path = folder / RUN_FILE
    return RunRecord.from_json(read_checked(path, TRAINING_RUN, TrainingError, RUN_FIX), path)


def run_record(dataset: Path, manifest: DatasetManifest, config: TrainConfig) -> RunRecord:
    """What run.json records of a run (a resumed run must match it); no plan yet."""
    boxes = chart_boxes(dataset) if config.texture else None
    return RunRecord(
        config=json.loads(json.dumps(config.to_json())),  # as read back: lists, not tuples
        dataset=str(Path(dataset).resolve()),
        dataset_checksum=manifest.checksum,
        joints=manifest.joints,
        blend_shapes=manifest.blend_shapes,  # the input's weights (none: not written)
        controls=manifest.controls,  # then the controls' values (none: not written)
        charts=None if boxes is None else len(boxes[0]) - 1,  # the texture head's size
    )


def measure_step_seconds(
    model: Rig2Image,
    samples: SampleSet,
    previews: SampleSet,
    config: TrainConfig,
    steps: int = PROBE_STEPS,
    device: torch.device | None = None,
) -> dict[int, float]:
    """Seconds per training step at every level, previews and checkpoints included.

    Real steps (batches read through the Prefetcher) on a copy of the model on `device` (the
    CPU by default), so the run itself is unchanged: the fastest of `steps` timed steps after
    one warm-up step (on a GPU, waited for), plus a preview's time over eval_every and a
    checkpoint's over checkpoint_every.
    """
    device = device or torch.device("cpu")
    probe = copy.deepcopy(model).to(device)

    def done() -> None:  # a GPU step is queued, not finished, when Python returns
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    optimizer = make_optimizer(probe, config)
    rng = torch.get_rng_state()
    prefetch = prefetcher(samples, config.batch, config.seed, oversample=config.oversample)
    seconds: dict[int, float] = {}
    step = 0
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for resolution in config.levels():
                times = []
                for _ in range(steps + 1):
                    begin = time.perf_counter()
                    batch = to_torch(prefetch.get(step), config.channels_last)
                    batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
                    loss, _ = forward_loss(probe, batch, resolution, 1.0, config)
                    optimise(probe, optimizer, loss, config)
                    done()
                    times.append(time.perf_counter() - begin)
                    step += 1
                begin = time.perf_counter()
                _preview(
                    probe if device.type == "cpu" else copy.deepcopy(probe).cpu(),
                    previews,
                    resolution,
                    Path(tmp) / "preview.png",
                )
                preview = time.perf_counter() - begin
                begin = time.perf_counter()
                torch.save({"m": probe.state_dict(), "o": optimizer.state_dict()}, io.BytesIO())
                save = time.perf_counter() - begin
                seconds[resolution] = (
                    min(times[1:]) + preview / config.eval_every + save / config.checkpoint_every
                )
    finally:
        prefetch.close()
        torch.set_rng_state(rng)
    return seconds


def logged_seconds(log: Path, step: int) -> float:
    """The training seconds a run's log records at `step` (0 for logs from before the field,
    or without that step): where a resumed run's clock continues."""
    seconds = 0.0
    if log.is_file():
        with log.open() as lines:
            for line in lines:
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:  # a line cut by a kill: the rest still counts
                    continue
                if record.get("step") == step and "seconds" in record:
                    seconds = float(record["seconds"])
    return seconds


P = ParamSpec("P")
R = TypeVar("R")


def _denormals_flushed(function: Callable[P, R]) -> Callable[P, R]:
    """Run `function` with denormal floats flushed to zero, the caller's setting restored."""

    @functools.wraps(function)
    def flushed(*args: P.args, **kwargs: P.kwargs) -> R:
        flushing = flush_denormal(True)
        try:
            return function(*args, **kwargs)
        finally:
            flush_denormal(flushing)

    return flushed


# Denormal floats flushed to zero (x86 FTZ/DAZ) while training, the caller's setting
# restored after: the sigmoid's saturated background logits and a fading-in block's
# small gradients produce denormals, and an Intel core takes microcode assists on each.
# Unflushed, the sample model's 128x128 steps slowed from 0.28 s to 1.7 s within 350
# steps of its fade-in (Xeon, 2 cores); flushed, they held at 0.28 s. The same step
# measured beside it: 0.61 s flushed, 0.75-1.13 s not.
@_denormals_flushed
def train(
    dataset: str | Path,
    out: str | Path,
    config: TrainConfig,
    *,
    steps: int | None = None,
    minutes: float | None = None,
    resume: bool = False,
    progress: bool = True,
    device: str | None = None,
    cache: bool = True,
    resident: str = "auto",
    anneal: float = 0.0,
) -> TrainResult:
    """Train Rig2Image on a capture dataset (see the module doc). `device`: a --device value
    (train.distributed.resolve_device; None: the CPU, or the context already made). `cache`:
    decode a dataset folder's samples once into its cache first (train.data.ensure_cache).
    `resident`: keep the training items in the device's memory (train.resident). `anneal`:
    the share of this call's run (its `minutes`, else its steps) at whose end the learning
    rate falls, at the level the run ends at (train.callbacks.Anneal; 0: constant)."""
    check_anneal(anneal)
    dataset, out = Path(dataset), Path(out)
    began = time.monotonic()  # the budget counts from here: the step-rate probe is part of it
    ctx = distributed.context(device)  # one process unless under torchrun (train.distributed)
    run = _set_up(dataset, out, config, resume, progress, cache, ctx)
    config, planned = _plan(run, ctx, minutes, began)
    model = run.model.to(ctx.device)
    state = LoopState(model, make_optimizer(model, config), config, out, start=0, total=0)
    checkpoint_path = out / CHECKPOINT
    if resume and checkpoint_path.exists():
        saved = load_checkpoint(checkpoint_path)
        model.load_state_dict(saved["model"])
        state.optimizer.load_state_dict(saved["optimizer"])
        torch.set_rng_state(saved["torch_rng"])
        state.start = state.step = int(saved["step"])
    state.total = config.total_steps() if steps is None else min(steps, config.total_steps())
    state.last_good = checkpoint_path if checkpoint_path.exists() else None
    state.seconds_before = logged_seconds(out / "log.jsonl", state.start) if state.start else 0.0
    pacer, pace, budget = None, None, None
    if minutes:
        # A time budget is the user's "train the best model in M minutes": when the planned
        # steps finish early (the probe ran on a busier machine), the final level trains on
        # until the budget ends instead of leaving it unused (also after --resume of a
        # finished run).
        deadline = began + 60 * minutes
        rates = {int(r): float(v) for r, v in planned.get("seconds_per_step", {}).items()}
        pace = Pace(config, rates, deadline) if planned else None
        pacer = Pacer(config, deadline, pace, ctx.agree)
        pacer.extends = steps is None
        budget = (began, deadline)
    if anneal > 0:
        state.anneal = Anneal(config, anneal, ctx.agree, budget, pace)
    done = "done" if steps is None else "step budget"
    stopped = _run(run, state, ctx, pacer, progress, done, resident)
    if stopped != "interrupted":
        ctx.barrier()  # the other ranks return once rank 0's checkpoint is written
    return TrainResult(
        out, state.step, state.elapsed, stopped, state.last_loss, state.images_per_second
    )


@dataclass
class _Run:
    """A run's data and network, set up and checked before the first step."""

    dataset: Path
    out: Path
    manifest: DatasetManifest
    config: TrainConfig
    existing: RunRecord | None
    """The run.json of the run being resumed; None for a new run."""
    samples: Any
    held_out: Any
    model: Rig2Image
    texel_scale: np.ndarray | None = None
    """(K+1, 2) texels per unit of the texture head's coordinates, chart by chart
    (data.texels_per_coordinate): the preview's coordinate error in texels; None without."""

    @property
    def previews(self) -> Any:
        """The samples previews show: held-out views, or training ones if there are none."""
        return self.held_out if len(self.held_out) else self.samples


def _set_up(
    dataset: Path,
    out: Path,
    config: TrainConfig,
    resume: bool,
    progress: bool,
    cache: bool,
    ctx: Any,
) -> _Run:
    """Check the run, decode the cache, open the splits and build the network."""
    manifest, config, existing = ctx.share(lambda: prepare_run(dataset, out, config, resume))
    if config.threads:
        torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    if cache and not is_shards(dataset):
        said = ctx.share(lambda: ensure_cache(dataset, manifest, progress))  # rank 0 decodes
        if ctx.is_main and progress:
            print(f"rigspace train: {said}", file=sys.stderr)
    samples = open_split(dataset, "train", config.resolution)  # a dataset or shards folder
    held_out = open_split(dataset, "heldout-views", config.resolution)
    if len(samples) == 0:
        raise TrainingError(
            f"{dataset} has no training samples.", "capture with some non-held-out views."
        )
    boxes = chart_boxes(dataset) if config.texture else None
    shape = Shape(
        len(samples.joints),
        parents=parents_of(samples.joints),
        charts=0 if boxes is None else len(boxes[0]) - 1,
        blend_shapes=len(manifest.blend_shapes),
        controls=len(manifest.controls),
    )
    model = Rig2Image(shape, config)
    if model.conditioned:  # every item gets joints2d (train.conditioning)
        samples.skeleton = held_out.skeleton = dataset_skeleton(dataset, manifest)
    texel_scale = None
    if model.charts:  # every item gets its texture head's targets (chart, uv)
        samples.charts = held_out.charts = boxes
        texel_scale = texels_per_coordinate(dataset, manifest) if ctx.is_main else None
    if config.shape_weight > 0:  # every item gets its mobility (where the shapes move)
        samples.mobility = held_out.mobility = dataset_mobility(dataset, manifest)
    if config.channels_last:
        model = model.to(memory_format=torch.channels_last)
    return _Run(dataset, out, manifest, config, existing, samples, held_out, model, texel_scale)


def dataset_mobility(dataset: Path, manifest: Any) -> ShapeMobility:
    """Where the blend shapes of the dataset's character move its surface (train.regions.
    shape_mobility over the dataset's texture charts), for --shape-weight; a TrainingError
    naming what is missing (the scene, blend shapes, texture charts)."""
    from rigspace.sdk.posing import CharacterRig
    from rigspace.sdk.stage import open_stage
    from rigspace.train.regions import shape_mobility

    off = "or train without --shape-weight."
    boxes = chart_boxes(dataset)
    if boxes is None:
        raise TrainingError(
            f"--shape-weight finds where the blend shapes move through the texture charts, "
            f"and {dataset} has none (its character has no texture).",
            f"give the character a texture and capture again, {off}",
        )
    if not manifest.blend_shapes:
        raise TrainingError(
            f"--shape-weight weighs where the blend shapes move, and {dataset} records none.",
            f"capture a character with blend shapes (skel:blendShapes), {off}",
        )
    scene = Path(manifest.scene)
    if not scene.is_file():
        raise TrainingError(
            f"--shape-weight reads the blend shapes from the captured scene {scene}, which is "
            "not here.",
            f"restore the scene (the dataset's manifest names it), {off}",
        )
    stage = open_stage(scene)  # held while the rig is read
    rig = CharacterRig(stage.GetPrimAtPath(manifest.character))
    mobility = shape_mobility(rig, *boxes)
    if mobility is None:
        raise TrainingError(
            f"No blend shape of {manifest.character} moves a textured triangle.",
            f"check the shapes' offsets and the meshes' uvs, {off}",
        )
    return mobility


def _plan(
    run: _Run, ctx: Any, minutes: float | None, began: float
) -> tuple[TrainConfig, dict[str, Any]]:
    """A new run's time-budget plan (measured on rank 0) and its run.json; the config to
    train with and the plan (a resumed run's from its run.json; {} without a budget)."""
    config, plan = run.config, None
    if run.existing is None and ctx.is_main:
        if minutes:
            probe = replace(config, batch=config.batch // ctx.world)  # one rank's share
            rates = measure_step_seconds(
                run.model, run.samples, run.previews, probe, device=ctx.device
            )
            plan = plan_schedule(config, rates, 60 * minutes - (time.monotonic() - began))
            config = apply_plan(config, plan)
            print(f"rigspace train: {plan.summary()}", file=sys.stderr)
        record = run_record(run.dataset, run.manifest, config)
        if plan is not None:
            record = replace(record, plan=plan.to_json())
        run.out.mkdir(parents=True, exist_ok=True)
        write_atomic(run.out / RUN_FILE, json.dumps(record.to_json(), indent=2) + "\n")
    config, plan = ctx.share(lambda: (config, plan))  # rank 0 planned and wrote run.json
    if plan is not None:
        return config, plan.to_json()
    return config, (run.existing.plan if run.existing else None) or {}


def _run(
    run: _Run,
    state: LoopState,
    ctx: Any,
    pacer: Pacer | None,
    progress: bool,
    done: str,
    resident: str = "auto",
) -> str:
    """The steps from state.step, with the main run's callbacks; why they stopped."""
    prefetch = _batches(run.samples, state.config, ctx, resident, progress)
    net = ctx.wrap(state.model)  # DDP under torchrun: gradients averaged over the ranks
    callbacks: list[Callback] = [
        ProgressBar(state, progress and ctx.is_main, _postfix),
        # Previews add to the step's record before StepLog writes it.
        *([Previews(functools.partial(_preview_step, run=run, ctx=ctx))] if ctx.is_main else []),
        StepLog(run.out / "log.jsonl", ctx.is_main),
        *([Checkpoints(functools.partial(_save, ctx=ctx))] if ctx.is_main else []),
    ]
    step = functools.partial(_train_step, net=net, prefetch=prefetch, ctx=ctx)
    state.started = time.monotonic()
    terminate = sigterm_as_interrupt()
    try:
        return run_steps(state, step, callbacks, pacer, done)
    except DatasetError as exc:  # a damaged sample: keep the progress, then say how to go on
        if state.step > state.start and ctx.is_main:
            _save(state, ctx=ctx)
        raise TrainingError(
            f"{exc.what} Training stopped at step {state.step}"
            + (f"; checkpoint saved in {run.out}." if state.step > state.start else "."),
            f"{exc.fix} Then continue training with --resume.",
        ) from exc
    finally:
        terminate()
        prefetch.close()


def _batches(samples: Any, config: TrainConfig, ctx: Any, resident: str, progress: bool) -> Any:
    """Where the steps' batches come from: a prefetcher reading them from the dataset, or
    the items kept in the device's memory (train.resident)."""
    plain = prefetcher(
        samples, config.batch, config.seed, ctx.rank, ctx.world, config.oversample
    )  # checks the batch against the world size
    keep, why = resident_or_not(samples, ctx.device, resident)
    if why is not None and ctx.is_main:
        print(f"rigspace train: {why}.", file=sys.stderr)
    if not keep:
        return plain
    plain.close()
    kept = ResidentBatches(
        samples, config.batch, config.seed, ctx.rank, ctx.world, config.oversample,
        device=ctx.device, channels_last=config.channels_last, progress=progress and ctx.is_main,
    )  # fmt: skip
    if ctx.is_main:
        print(
            f"rigspace train: {len(samples)} training items kept in {ctx.device} memory "
            f"({kept.bytes / 2**30:.2f} GiB): a batch is a gather there",
            file=sys.stderr,
        )
    return kept


def _train_step(state: LoopState, *, net: Any, prefetch: Any, ctx: Any) -> dict[str, Any]:
    """One optimizer step of the main run; its log record."""
    config, step = state.config, state.step
    where = schedule(config, step)
    if where.first_step_of_level and step > state.start:
        # A new block joins: fresh optimizer state (the paper resets per level).
        state.optimizer = make_optimizer(state.model, config)
    lr = config.lr * (state.anneal.factor(state) if state.anneal is not None else 1.0)
    set_lr(state.optimizer, lr)
    batch = prefetch.get(step)
    if not isinstance(prefetch, ResidentBatches):  # numpy from the dataset
        batch = ctx.to_device(to_torch(batch, config.channels_last))
    loss, terms = forward_loss(net, batch, where.resolution, where.alpha, config)
    shown, terms = ctx.mean(loss, terms)  # every rank sees the same value
    if not math.isfinite(shown):
        raise TrainingError(
            f"The loss became {shown} at step {step} (level {where.resolution}x"
            f"{where.resolution}, alpha {where.alpha:.2f}); training stopped. Last good "
            f"checkpoint: {state.last_good or 'none yet'}.",
            "lower --lr, or resume from the last good checkpoint with --resume.",
        )
    optimise(net, state.optimizer, loss, config)
    state.last_loss = shown
    return {
        "step": step + 1,
        "loss": shown,
        **terms,
        "fade": where.alpha,  # the newest block's fade-in weight; "alpha" is its loss term
        "lr": lr,
        "resolution": where.resolution,
        "seconds": round(state.seconds_before + state.elapsed, 2),
    }


def _postfix(record: dict[str, Any]) -> dict[str, Any]:
    return {"loss": f"{record['loss']:.4f}", "res": record["resolution"]}


def _preview_step(state: LoopState, resolution: int, *, run: _Run, ctx: Any) -> dict[str, float]:
    path = run.out / "previews" / f"level_{resolution}.png"
    return _preview(ctx.on_cpu(state.model), run.previews, resolution, path, run.texel_scale)


def texel_error(
    coords: np.ndarray, target: np.ndarray, chart: np.ndarray, where: np.ndarray, scale: np.ndarray
) -> dict[str, float]:
    """The coordinates' error in texels (median, 90th percentile) where `where` holds and the
    chart has a texture: `coords` (N, 2K, R, R) the head's, `target` (N, 2, R, R) the target
    chart's pair, `chart` (N, R, R), `scale` (K+1, 2) texels per coordinate unit."""
    pair = np.maximum(chart - 1, 0)[:, None]
    predicted = np.concatenate(
        [np.take_along_axis(coords[:, c::2], pair, 1) for c in (0, 1)], axis=1
    )
    texels = np.moveaxis((predicted - target), 1, -1) * scale[chart]
    keep = where & np.isfinite(texels).all(axis=-1)
    if not keep.any():
        return {}
    distance = np.linalg.norm(texels[keep], axis=-1)
    return {
        "uv_texels_median": float(np.median(distance)),
        "uv_texels_p90": float(np.percentile(distance, 90)),
    }


def _save(state: LoopState, *, ctx: Any) -> Path:
    """The checkpoint at state.step (the level of the step last trained)."""
    level = schedule(state.config, max(state.step - 1, 0)).level
    return save_checkpoint(state.out, state.model, state.optimizer, state.step, level)


def flush_denormal(on: bool) -> bool:
    """Set whether this process flushes denormal floats to zero (torch.set_flush_denormal);
    return whether it did before."""
    before = bool((torch.tensor([1e-39], dtype=torch.float32) * 1.0).item() == 0.0)
    torch.set_flush_denormal(on)
    return before


def build_model(
    run_folder: Path, checkpoint: Path | None = None
) -> tuple[Rig2Image, RunRecord, int]:
    """The trained model of a run folder (or of another `checkpoint` of the run, one kept
    while it trained), its run.json, and the step it reached."""
    run = read_run(run_folder)
    config = run.train_config()
    shape = Shape(
        len(run.joints),
        parents=parents_of(list(run.joints)),
        charts=run.charts or 0,
        blend_shapes=len(run.blend_shapes),
        controls=len(run.controls),
    )
    model = Rig2Image(shape, replace(config, channels_last=False))
    state = load_checkpoint(checkpoint or run_folder / CHECKPOINT)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        if "size mismatch for albedo.heads." in str(exc):
            raise TrainingError(
                f"The run in {run_folder} was trained before the albedo branch predicted "
                "coverage (bundle format 2).",
                "add it with `rigspace train DATASET --out MODEL --upgrade` (minutes; every "
                "other output stays identical).",
            ) from exc
        raise
    model.eval()
    return model, run, int(state["step"])

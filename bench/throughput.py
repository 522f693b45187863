"""Capture samples/s per renderer and resolution; training images/s per preset, with stability.

    capture_throughput(("gl", "embree"), (64, 128, 256), frames=(0.0, 31.0))
    training_throughput(("tiny", "small", "paper"), steps=5, dataset=None)

Capture rows come from capture/rates.py's `run` (real captures of the previs sample's
/World/Hero into a temporary folder). Training rows time real steps of the training loop's
own parts (Rig2Image, Prefetcher, total_loss, the Adam optimizer, each preset's batch,
widths, bf16 and channels_last) at the preset's final level with the fade-in complete,
after warm-up steps, on a dataset captured on the fly at the preset's resolution unless
one is given. Every function returns a list of plain JSON-able dicts, one per row.
"""

from __future__ import annotations

import contextlib
import io
import math
import statistics
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rigspace.capture import rates as capture_rates
from rigspace.capture.dataset import read_manifest
from rigspace.capture.pipeline import capture
from rigspace.capture.settings import CaptureOverrides
from rigspace.sdk.render import renderer_plugins

if TYPE_CHECKING:
    import torch

    from rigspace.train.config import TrainConfig
    from rigspace.train.data import SampleSet
    from rigspace.train.network import Rig2Image

SCENE = capture_rates.DEFAULT_SCENE
CHARACTER = capture_rates.DEFAULT_CHARACTER
DATASET_FRAMES = (0.0, 3.0)
"""Time codes of the on-the-fly training dataset (the walk clip's first four frames)."""
DATASET_VIEWS = 4
"""Training views at elevation 0 (the scene adds its held-out views, unused here)."""


def capture_throughput(
    renderers: tuple[str, ...] = ("gl", "embree"),
    resolutions: tuple[int, ...] = (64, 128, 256),
    frames: tuple[float, float] = (0.0, 31.0),
    views: int = 12,
) -> list[dict[str, Any]]:
    """samples/s per renderer and resolution; an unusable renderer gets a row saying why.

    Work items split by 16-frame chunks and by view group (training, held-out views), so
    even a small capture runs in worker processes whose start-up (about 2 s on 2 cores) is
    in `seconds`: a quick run (e.g. frames=(0, 1), views=2) gives a lower bound of samples/s,
    while its per-sample split (ms_per_sample_one_core) is unaffected.
    """
    plugins = renderer_plugins()
    rows: list[dict[str, Any]] = []
    for renderer in renderers:
        if renderer not in plugins:
            why = plugins.failed.get(renderer, "no such renderer plugin")
            rows.append({"renderer": renderer, "skipped": why})
            continue
        reason = plugins.specs[renderer].unavailable()
        if reason:
            rows.append({"renderer": renderer, "skipped": reason})
            continue
        with contextlib.redirect_stdout(io.StringIO()):  # run() prints a markdown row each
            measured = capture_rates.run(SCENE, CHARACTER, frames, views, resolutions, [renderer])
        for row in measured:
            rows.append(
                {
                    **row,
                    "scene": SCENE.name,
                    "character": CHARACTER,
                    "frames": list(frames),
                    "views": views,
                }
            )
    return rows


def capture_dataset(out: Path, resolution: int, frames=DATASET_FRAMES, views=DATASET_VIEWS) -> Path:
    """A small previs dataset for timing training (not for training a usable model)."""
    overrides = CaptureOverrides(
        views=views, elevations=(0.0,), resolution=resolution, frames=frames
    )
    capture(SCENE, CHARACTER, out, overrides, progress=False)
    return out


def _preset_row(name: str, config: TrainConfig, folder: Path, have: int) -> dict[str, Any]:
    """The row's start: preset `name`'s size and precision, and the dataset (at `have`
    pixels a side) it trains on."""
    return {
        "preset": name,
        "resolution": config.resolution,
        "batch": config.batch,
        "latent": config.latent,
        "base_width": config.base_width,
        "min_width": config.min_width,
        "bf16": config.bf16,
        "channels_last": config.channels_last,
        "dataset": str(folder),
        "dataset_resolution": have,
    }


def _timed_steps(
    model: Rig2Image,
    samples: SampleSet,
    config: TrainConfig,
    where: torch.device,
    total: int,
    warmup: int,
) -> tuple[list[float], list[float]]:
    """Train `total` steps: every step's loss, and the seconds of each after the first
    `warmup`."""
    import torch

    from rigspace.train.data import Prefetcher
    from rigspace.train.step import forward_loss, make_optimizer, optimise, to_torch

    optimizer = make_optimizer(model, config)
    prefetch = Prefetcher(samples, config.batch, config.seed)
    losses: list[float] = []
    seconds: list[float] = []
    try:
        for step in range(total):
            start = time.perf_counter()
            # One step of train.loop.train at the final level, fade-in done (alpha 1).
            batch = to_torch(prefetch.get(step), config.channels_last)
            batch = {k: v.to(where, non_blocking=True) for k, v in batch.items()}
            loss, _terms = forward_loss(model, batch, config.resolution, 1.0, config)
            optimise(model, optimizer, loss, config)
            losses.append(float(loss.detach()))
            if where.type == "cuda":
                torch.cuda.synchronize(where)
            if step >= warmup:
                seconds.append(time.perf_counter() - start)
    finally:
        prefetch.close()
    return losses, seconds


def _step_rate(
    name: str, folder: Path, steps: int, warmup: int, device: str | None = None
) -> dict[str, Any]:
    """Time `warmup + steps` training steps of preset `name` on the dataset in `folder`, on
    `device` (a --device value; None: the CPU)."""
    import torch  # here, not at the top: capture rows need no torch

    from rigspace.train.config import preset
    from rigspace.train.data import SampleSet
    from rigspace.train.distributed import resolve_device
    from rigspace.train.network import Rig2Image, Shape

    config = preset(name)
    have = read_manifest(folder).resolution
    row = _preset_row(name, config, folder, have)
    if config.resolution > have:
        row["skipped"] = (
            f"preset {name} trains at {config.resolution}x{config.resolution}; the dataset "
            f"holds {have}x{have} (capture at {config.resolution} or more)"
        )
        return row
    samples = SampleSet(folder, "train", config.resolution)
    if len(samples) == 0:
        row["skipped"] = "the dataset has no training samples"
        return row
    if config.threads:
        torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    where = resolve_device(device)
    row["device"] = str(where)
    model = Rig2Image(Shape(len(samples.joints)), config).to(where)
    if config.channels_last:
        model = model.to(memory_format=torch.channels_last)
    losses, seconds = _timed_steps(model, samples, config, where, warmup + steps, warmup)
    bad = [k for k, v in enumerate(losses) if not math.isfinite(v)]
    return {
        **row,
        "samples": len(samples),
        "parameters": sum(p.numel() for p in model.parameters()),
        "warmup_steps": warmup,
        "steps": steps,
        "images_per_s": config.batch * steps / sum(seconds),
        "median_step_ms": 1e3 * statistics.median(seconds),
        "losses": losses,
        "finite": not bad,
        "first_nonfinite_step": bad[0] if bad else None,
    }


def training_throughput(
    presets: tuple[str, ...] = ("tiny", "small", "paper"),
    steps: int = 5,
    dataset: str | Path | None = None,
    warmup: int = 2,
    device: str | None = None,
) -> list[dict[str, Any]]:
    """Training images/s per preset and whether every step's loss was finite.

    Without `dataset`, each preset's resolution is captured once (DATASET_FRAMES x
    DATASET_VIEWS at elevation 0) into a temporary folder. With one, a preset that trains
    above the dataset's resolution gets a row saying so instead of a measurement.
    """
    if steps < 1 or warmup < 0:
        raise ValueError(f"steps must be >= 1 and warmup >= 0, got {steps} and {warmup}")
    from rigspace.train.config import preset

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        captured: dict[int, Path] = {}
        for name in presets:
            if dataset is not None:
                folder = Path(dataset)
            else:
                resolution = preset(name).resolution
                if resolution not in captured:
                    captured[resolution] = capture_dataset(
                        Path(tmp) / f"ds_{resolution}", resolution
                    )
                folder = captured[resolution]
            row = _step_rate(name, folder, steps, warmup, device)
            if dataset is None:
                row["dataset"] = (
                    f"previs {CHARACTER}, frames {DATASET_FRAMES}, {DATASET_VIEWS} views"
                )
            rows.append(row)
    return rows

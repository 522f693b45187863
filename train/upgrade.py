"""Bring a run trained by an earlier rigspace up to the current network, training only what is new.

    rigspace train DATASET --out MODEL --upgrade [--steps N]

Bundle format 2 added a coverage output (alpha) to the albedo branch's 1x1 heads, so that
unlit frames can skip the geometry branch. A run trained before has 3-channel albedo
heads; this adds the fourth channel (zero-initialised), freezes every other weight, and
trains that channel alone against the mask at every level of detail. Adam's step for a
parameter whose gradient is always zero is exactly zero, so every existing output is
bit-identical afterwards (tested); only `alpha` is new. On a run that has the channel
already, the same trains it further. The optimiser state in the new
checkpoint starts fresh (its shapes changed), so a later --resume restarts its moments.
"""

from __future__ import annotations

import functools
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from rigspace.train.callbacks import LoopState, ProgressBar, StepLog, run_steps
from rigspace.train.data import Prefetcher, SampleSet
from rigspace.train.loop import (
    CHECKPOINT,
    RUN_FILE,
    TrainingError,
    TrainResult,
    load_checkpoint,
    read_run,
    save_checkpoint,
)
from rigspace.train.loss import downsample, mixed
from rigspace.train.network import ALBEDO_CHANNELS, Rig2Image, Shape, albedo_alpha
from rigspace.train.step import make_optimizer

UPGRADE_LOG_EVERY = 100
"""Upgrade steps per log.jsonl line."""


def upgrade_state(state: dict[str, torch.Tensor]) -> list[str]:
    """Widen 3-channel albedo heads to ALBEDO_CHANNELS in place; the names widened."""
    widened = []
    for name, value in list(state.items()):
        if name.startswith("albedo.heads.") and value.shape[0] == ALBEDO_CHANNELS - 1:
            extra = torch.zeros((1, *value.shape[1:]), dtype=value.dtype)
            state[name] = torch.cat([value, extra])
            widened.append(name)
    return widened


def upgrade(
    dataset: str | Path, run_folder: str | Path, *, steps: int = 1500, progress: bool = True
) -> TrainResult:
    """Add and train the albedo branch's alpha heads of the run in `run_folder`."""
    dataset, run_folder = Path(dataset), Path(run_folder)
    run_file = run_folder / RUN_FILE
    if not run_file.is_file():
        raise TrainingError(
            f"{run_folder} holds no training run (no {RUN_FILE}).",
            "pass --out the model bundle folder that `rigspace train` wrote.",
        )
    run = read_run(run_folder)
    config = replace(run.train_config(), channels_last=False, bf16=False)
    checkpoint = load_checkpoint(run_folder / CHECKPOINT)
    # A run that has the alpha channel already trains it further (more --steps).
    upgrade_state(checkpoint["model"])
    samples = SampleSet(dataset, "train", config.resolution)
    if samples.joints != list(run.joints):
        raise TrainingError(
            f"{dataset} is not the dataset the run in {run_folder} trained on (other joints).",
            f"pass the dataset it names: {run.dataset}.",
        )
    torch.manual_seed(config.seed)
    model = Rig2Image(
        Shape(len(run.joints), blend_shapes=len(run.blend_shapes), controls=len(run.controls)),
        config,
    )
    model.load_state_dict(checkpoint["model"])
    heads = list(model.albedo.heads)
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    for head in heads:
        for parameter in head.parameters():
            parameter.requires_grad_(True)
            # Only the new alpha channel learns: the colour channels' gradients are zeroed.
            parameter.register_hook(_alpha_only)
    optimizer = torch.optim.Adam(
        [p for head in heads for p in head.parameters()],
        lr=config.lr,
        betas=(config.adam_beta1, config.adam_beta2),
    )
    prefetch = Prefetcher(samples, config.batch, config.seed + 1)
    state = LoopState(model, optimizer, config, run_folder, start=0, total=steps)
    callbacks = [
        ProgressBar(state, progress, lambda r: {"alpha_loss": f"{r['alpha']:.4f}"}),
        StepLog(run_folder / "log.jsonl", True, every=UPGRADE_LOG_EVERY),
    ]
    try:
        stopped = run_steps(state, functools.partial(_alpha_step, prefetch=prefetch), callbacks)
    finally:
        prefetch.close()
    if stopped == "interrupted":
        raise KeyboardInterrupt  # the checkpoint is left as it was
    step = int(checkpoint["step"])
    save_checkpoint(
        run_folder, model, make_optimizer(model, config), step, int(checkpoint["level"])
    )
    return TrainResult(
        run_folder, step, state.elapsed, "upgraded", state.last_loss, state.images_per_second
    )


def _alpha_step(state: LoopState, *, prefetch: Prefetcher) -> dict[str, Any]:
    """One step of the alpha heads alone against the mask, at every level of detail."""
    model, config = state.model, state.config
    batch = {k: torch.from_numpy(v) for k, v in prefetch.get(state.step).items()}
    with torch.no_grad():
        features = model.features(batch["rig"])
    outs = model.albedo(features, config.resolution)
    loss = torch.zeros(())
    for k, head in enumerate(outs):
        weight = 1.0 if k == len(outs) - 1 else config.lower_level_weight
        target = downsample(batch["mask"], head.shape[-1])
        loss = loss + weight * mixed(albedo_alpha(head), target, config.l1_weight)
    if not torch.isfinite(loss):
        raise TrainingError(
            f"The alpha heads' loss became {float(loss)} at upgrade step {state.step}.",
            "lower --lr and run the upgrade again (the checkpoint is unchanged).",
        )
    state.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    state.optimizer.step()
    state.last_loss = float(loss.detach())
    return {"upgrade_step": state.step + 1, "alpha": state.last_loss}


def _alpha_only(grad: torch.Tensor) -> torch.Tensor:
    keep = torch.zeros_like(grad)
    keep[ALBEDO_CHANNELS - 1 :] = grad[ALBEDO_CHANNELS - 1 :]
    return keep

"""One training step, free of datasets and files: the schedule, the optimiser, forward and loss,
the update. `rigspace.train.loop` runs these over a dataset; the GPU check
(rigspace.apps.gpu_check) times them on a machine without usd-core or OpenImageIO.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from rigspace.train.config import TrainConfig
from rigspace.train.loss import total_loss
from rigspace.train.network import Rig2Image


@dataclass
class Schedule:
    """Where a global step falls in the progressive schedule."""

    level: int
    """Index into config.levels()."""
    resolution: int
    alpha: float
    """Fade-in weight of the newest block, 0 -> 1 linearly over the fade steps."""
    first_step_of_level: bool


def schedule(config: TrainConfig, step: int) -> Schedule:
    levels = config.levels()
    level = min(step // config.steps_per_level, len(levels) - 1)
    local = step - level * config.steps_per_level
    fade_steps = max(1, int(config.fade_fraction * config.steps_per_level))
    alpha = 1.0 if level == 0 else min(1.0, local / fade_steps)
    return Schedule(level, levels[level], alpha, local == 0)


ANNEAL_FLOOR = 0.02
"""The share of --lr an annealed run ends at (`rigspace train --anneal`)."""


def annealed(t: float) -> float:
    """The learning rate's factor at `t` (0..1) through the annealing window: a half cosine
    from 1 at its start to ANNEAL_FLOOR at its end (SGDR's, Loshchilov and Hutter 2017)."""
    t = min(max(t, 0.0), 1.0)
    return ANNEAL_FLOOR + (1.0 - ANNEAL_FLOOR) * 0.5 * (1.0 + math.cos(math.pi * t))


def set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Every parameter group's learning rate (Adam's moments are kept)."""
    for group in optimizer.param_groups:
        group["lr"] = lr


def make_optimizer(model: torch.nn.Module, config: TrainConfig) -> torch.optim.Optimizer:
    return torch.optim.Adam(
        model.parameters(), lr=config.lr, betas=(config.adam_beta1, config.adam_beta2)
    )


def to_torch(batch: dict[str, np.ndarray], channels_last: bool) -> dict[str, torch.Tensor]:
    out = {k: torch.from_numpy(v) for k, v in batch.items()}
    if channels_last:
        for k, v in out.items():
            if v.ndim == 4:
                out[k] = v.contiguous(memory_format=torch.channels_last)
    return out


def forward_loss(
    model: Rig2Image,
    batch: dict[str, torch.Tensor],
    resolution: int,
    alpha: float,
    config: TrainConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """One step's forward pass and loss at `resolution` with fade-in weight `alpha`."""
    # bf16 autocast where the batch is (cpu or cuda); torch refuses other device types
    # (meta) even disabled, so those get a disabled cpu one.
    kind = batch["rig"].device.type
    casts = kind in ("cpu", "cuda")
    with torch.autocast(
        kind if casts else "cpu", dtype=torch.bfloat16, enabled=config.bf16 and casts
    ):
        heads = model(batch["rig"], resolution, joints2d=batch.get("joints2d"))
        return total_loss(heads, batch, alpha, config)


def optimise(model: Rig2Image, optimizer, loss: torch.Tensor, config: TrainConfig) -> None:
    """One step's backward pass, gradient clipping and optimiser update."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if config.grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
    optimizer.step()

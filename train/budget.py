"""Fit the progressive schedule into a `--minutes` budget, and say which levels a run trained.

A run with a time budget measures its seconds per step at every level first (a few real
steps on a copy of the model, train.loop.measure_step_seconds), then sizes the steps per
level so that every level fits:

    steps_per_level = floor(PLAN_SHARE * remaining seconds / sum over levels of seconds per step)

capped at the preset's value. Below MIN_STEPS_PER_LEVEL the plan keeps that many and says,
before training starts, which level the budget reaches. A level counts as trained once its
block has fully faded in (the exported graph of a level still fading in is not what was
trained: the fade blends in the level below); the heads below the first level train with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

from rigspace.train.config import TrainConfig

PLAN_SHARE = 0.8
"""Share of the remaining budget planned for training steps: the rest covers the previews,
checkpoints and the step rate's noise on a shared machine (rates measured here varied by
about 10 % between runs)."""
MIN_STEPS_PER_LEVEL = 40
"""Fewer steps than this leave a block a fade-in of a dozen steps: not worth exporting, so
the plan does not go below it and reports the level the budget reaches instead."""


@dataclass(frozen=True)
class Plan:
    """A schedule sized to a time budget."""

    steps_per_level: int
    requested_steps_per_level: int
    seconds_per_step: dict[int, float]
    """Measured, per level resolution."""
    budget_seconds: float
    reaches: int
    """The last level resolution the planned steps finish within the budget."""
    final: int

    @property
    def reaches_final(self) -> bool:
        return self.reaches == self.final

    def summary(self) -> str:
        rates = ", ".join(f"{r}: {s * 1000:.0f} ms" for r, s in self.seconds_per_step.items())
        if self.steps_per_level < self.requested_steps_per_level:
            steps = f"{self.steps_per_level} steps per level (of {self.requested_steps_per_level})"
        else:
            steps = f"the full {self.steps_per_level} steps per level"
        text = (
            f"time budget {self.budget_seconds / 60:.1f} min, measured per step {rates}: "
            f"planned {steps}"
        )
        if self.reaches_final:
            return f"{text}; the run reaches {self.final}x{self.final}."
        if not self.reaches:
            return f"{text}; at this rate the budget is too short to train any level."
        return (
            f"{text}; at this rate the budget reaches only {self.reaches}x{self.reaches}, so "
            f"the bundle will hold levels up to {self.reaches} and not {self.final} (about "
            f"{math.ceil(self.minutes_for_final)} minutes reach it)."
        )

    @property
    def minutes_for_final(self) -> float:
        return self.steps_per_level * sum(self.seconds_per_step.values()) / PLAN_SHARE / 60

    def to_json(self) -> dict[str, Any]:
        return {
            "steps_per_level": self.steps_per_level,
            "requested_steps_per_level": self.requested_steps_per_level,
            "seconds_per_step": {str(r): s for r, s in self.seconds_per_step.items()},
            "budget_seconds": self.budget_seconds,
            "reaches": self.reaches,
        }


def plan_schedule(
    config: TrainConfig, seconds_per_step: dict[int, float], budget_seconds: float
) -> Plan:
    """The steps per level that fit every level of `config` into `budget_seconds`."""
    levels = config.levels()
    per_round = sum(seconds_per_step[r] for r in levels)
    fit = math.floor(PLAN_SHARE * max(budget_seconds, 0.0) / max(per_round, 1e-9))
    steps = min(config.steps_per_level, max(MIN_STEPS_PER_LEVEL, fit))
    # A level is trained once its fade-in is done; the fade is the level's first steps.
    elapsed, reaches = 0.0, 0
    for i, r in enumerate(levels):
        fade = 0 if i == 0 else max(1, int(config.fade_fraction * steps))
        if elapsed + (fade + 1) * seconds_per_step[r] > PLAN_SHARE * budget_seconds:
            break
        reaches = r
        elapsed += steps * seconds_per_step[r]
    return Plan(
        steps_per_level=steps,
        requested_steps_per_level=config.steps_per_level,
        seconds_per_step={r: seconds_per_step[r] for r in levels},
        budget_seconds=budget_seconds,
        reaches=reaches,
        final=levels[-1],
    )


def apply_plan(config: TrainConfig, plan: Plan) -> TrainConfig:
    return replace(config, steps_per_level=plan.steps_per_level)


def fade_steps(config: TrainConfig) -> int:
    """Steps a new block takes to fade in (train.loop.schedule's alpha reaches 1)."""
    return max(1, int(config.fade_fraction * config.steps_per_level))


def trained_levels(config: TrainConfig, step: int) -> list[int]:
    """The levels of config.levels() a run that stopped after `step` steps has trained.

    The first level counts once a step ran; a later one once a step ran with its block fully
    faded in (alpha 1), which schedule() gives at the level's step fade_steps.
    """
    out = []
    for i, r in enumerate(config.levels()):
        begin = i * config.steps_per_level
        if step > begin + (0 if i == 0 else fade_steps(config)):
            out.append(r)
    return out

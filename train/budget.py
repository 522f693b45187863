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
from collections import deque
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
    budget_seconds = max(0.0, budget_seconds)
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
    """Steps a new block takes to fade in (train.step.schedule's alpha reaches 1)."""
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


PACE_WARMUP = 5
"""First steps of each level the pace does not time: a run's first steps are slow (thread
pools and caches warming up: 5 s for the first 7 steps of a `small` run here, against 0.2 s
a step after), and so is a level's first step at its new size."""
PACE_WINDOW = 20
"""Steps over which the pace measures the current rate (the last ones)."""
PACE_SHARE = 0.95
"""Share of the time left the pace lets the later levels fill: the plan kept 1 - PLAN_SHARE
spare for noise, which the pace spends (the probe's step is the fastest of three, the run's
is an average); the rest covers the final checkpoint."""


MAX_FADE_STRIDE = 4
"""A fade-in the pace strides through still trains at least this share of its steps (1/4):
fewer, and alpha jumps to 1 in a few steps, a block barely trained; the level is then left
to the budget, not exported, as one the run does not reach (the plan's MIN_STEPS_PER_LEVEL
judges a fade-in of a dozen steps not worth exporting alike)."""


class Pace:
    """Keeps a run with a time budget on course for its final level while it trains.

    The plan's step times come from a few probe steps; a shared machine can run several
    times slower later (measured here: 1.7 s a step against the probe's 0.16 s while other
    work ran). The rate of a level's last PACE_WINDOW steps, scaled by the probe's ratios
    between levels, projects the later levels' times (before a level has its own window,
    the last level's measured scale stands in). Two decisions follow from it:

    - A block's fade-in always ends within the budget. A level counts as trained only once
      its block has fully faded in (trained_levels), so a budget that ends a fade-in loses
      the level whole: a `--minutes 3` run whose plan said "the run reaches 32x32" trained
      about 186 steps at 32x32, all inside the block's fade-in, and exported levels 8 and 16.
      When the steps that fit into PACE_SHARE of the time left cannot hold the rest of the
      fade-in, it strides: every `fade_stride`th step of it is trained, so alpha still rises
      step by step and reaches 1 in the steps that fit, as long as the fade-in keeps at least
      1/MAX_FADE_STRIDE of its steps (else the level is beyond reach, and left to the budget).
    - Past a level's fade-in, the target is the highest later level whose block can still
      fade in (the levels between given just their fade and a measured rate); none: this
      level trains on until the budget ends, the best the run can reach (`out_of_reach`
      says so). Else, once the levels up to the target need what is left of the budget for
      their planned steps (PACE_SHARE of it), this level ends: the step jumps to the next
      level's first step. So a level is shortened only as much as the later ones need,
      only when the run is behind, and never for a level it cannot reach. The final level
      is never ended early (the budget stops it).

    Batches are a pure function of the step, so skipping steps changes nothing else.
    """

    def __init__(
        self, config: TrainConfig, seconds_per_step: dict[int, float], deadline: float
    ) -> None:
        self.config, self.deadline = config, deadline
        self.probe = [float(seconds_per_step[r]) for r in config.levels()]
        self.out_of_reach = False
        """Whether the last look found no later level reachable at the current rate."""
        self.fade_stride = 1
        """The stride of the current fade-in (1: every step; more: the budget needs it)."""
        self._level, self._seen, self._scale, self._faded = -1, 0, 1.0, 0
        self._jumped_to: int | None = None
        self._recent: deque[tuple[int, float]] = deque(maxlen=PACE_WINDOW + 1)
        self._held = False

    def hold(self) -> None:
        """Keep the current level to the end of the budget, whatever the rate does later: the
        learning rate's fall began on it (train.callbacks.Anneal), and a level left for the
        next would take the fallen rate with it."""
        self._held = self.out_of_reach = True

    def next_step(self, step: int, now: float) -> int:
        """The step to train next: `step`, or a later one when behind (the next level's first
        step, or a later step of a fade-in)."""
        if self._held:
            return step
        if step == self._jumped_to:  # the step this pace jumped to: judged already, trained now
            self._jumped_to = None
            return step
        ahead = self._judge(step, now)
        self._jumped_to = ahead if ahead != step else None
        return ahead

    def _judge(self, step: int, now: float) -> int:
        per_level = self.config.steps_per_level
        level = min(step // per_level, len(self.probe) - 1)  # past the plan: the final level
        if level != self._level:
            self._level, self._seen, self._faded = level, 0, 0
            self._recent.clear()
        self.fade_stride = 1
        self._seen += 1
        if self._seen > PACE_WARMUP:
            self._recent.append((self._seen, now))  # steps trained, not step numbers: strides
        if len(self._recent) > PACE_WINDOW:
            (first, began), (last, latest) = self._recent[0], self._recent[-1]
            self._scale = (latest - began) / (last - first) / self.probe[level]
        local = step - level * per_level
        fade = fade_steps(self.config)
        left = PACE_SHARE * (self.deadline - now)
        if level > 0 and local < fade:
            return self._through_fade(step, level, fade, fade - local, left)
        measured = len(self._recent) > PACE_WINDOW
        if level == len(self.probe) - 1 or not measured or local <= (0 if level == 0 else fade):
            return step
        # Fewest steps that pass a level: its fade-in, and the pace's own measuring.
        passing = max(fade + 1, PACE_WARMUP + PACE_WINDOW + 1)
        scale, reach, target = self._scale, 0.0, level
        for j in range(level + 1, len(self.probe)):
            if reach + scale * (fade + 1) * self.probe[j] > left:
                break
            target, reach = j, reach + scale * passing * self.probe[j]
        self.out_of_reach = target == level
        later = scale * per_level * sum(self.probe[level + 1 : target + 1])
        if self.out_of_reach or later < left:
            return step
        return (level + 1) * per_level

    def _through_fade(self, step: int, level: int, fade: int, to_go: int, left: float) -> int:
        """`step`, or a later step of the fade-in when the `to_go` steps to its end (the first
        step at alpha 1 included) do not fit into `left` seconds at the current rate; `step`
        too when so few fit that the fade-in would train under 1/MAX_FADE_STRIDE of its steps
        (the budget then ends it: the level is beyond reach)."""
        self._faded += 1  # this call's step trains, whichever it is
        need = to_go + 1
        fits = max(1, math.floor(left / max(self._scale * self.probe[level], 1e-9)))
        stride = math.ceil(need / fits)
        if stride == 1 or self._faded - 1 + fits < (fade + 1) / MAX_FADE_STRIDE:
            self.fade_stride = 1
            return step
        self.fade_stride = stride
        return min(step + stride - 1, step + to_go)

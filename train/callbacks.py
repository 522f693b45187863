"""The training loop's parts: one step function, run by `run_steps` with callbacks around it.

    stopped = run_steps(state, step_fn, [ProgressBar(...), StepLog(...), ...], pacer)

`run_steps` owns only the loop: ask the pacer (a time budget) whether to stop or skip ahead,
call the step function (one optimizer step; it returns the step's log record), and hand the
record to each callback in order. What happens around a step lives in a callback, each one
screen long: the progress bar, the held-out previews, the log line, the checkpoints. The main
run (train.loop.train) and the upgrade of an older run (train.upgrade) share the loop and the
callbacks and differ in their step function. The pattern is PyTorch Lightning's `Callback`
hooks with its separate `ModelCheckpoint`, `Timer` and `ThroughputMonitor`.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from rigspace.train.budget import Pace
from rigspace.train.config import TrainConfig
from rigspace.train.step import annealed, schedule


@dataclass
class LoopState:
    """What the loop, its step function and its callbacks share while a run trains."""

    model: Any
    optimizer: Any
    config: TrainConfig
    out: Path
    start: int
    """The step this call began at (a resumed run's checkpoint step)."""
    total: int
    """The planned last step (a budget may train on past it: Pacer.extends)."""
    step: int = 0
    trained: int = 0
    """Optimizer steps in this call (a slow run's pace skips some steps)."""
    last_loss: float = math.nan
    last_good: Path | None = None
    """The newest checkpoint written, named when a step fails."""
    seconds_before: float = 0.0
    """Training seconds of earlier calls of this run (log.jsonl): the x axis of the curves."""
    started: float = field(default_factory=time.monotonic)
    anneal: Anneal | None = None
    """The learning rate's fall at the end of the run (--anneal); None: constant."""

    @property
    def elapsed(self) -> float:
        return time.monotonic() - self.started

    @property
    def images_per_second(self) -> float:
        return self.trained * self.config.batch / max(self.elapsed, 1e-9)


class Callback:
    """Hooks around the steps; each does nothing unless a subclass says otherwise."""

    def on_step(self, state: LoopState, record: dict[str, Any]) -> None:
        """After each optimizer step; `record` is the step's log line (callbacks may add)."""

    def on_skip(self, state: LoopState, to_step: int) -> None:
        """Before the pacer moves the step from state.step to `to_step`."""

    def on_end(self, state: LoopState, stopped: str) -> None:
        """After the last step: 'done', 'time budget', 'step budget' or 'interrupted'."""

    def close(self) -> None:
        """Release what the callback holds (files, the bar), whatever happened."""


def say(text: str) -> None:
    """A line above the progress bar."""
    tqdm.write(f"rigspace train: {text}", file=sys.stderr)


class Pacer:
    """A time budget: stop at the deadline, keep the final level on course (train.budget.Pace)
    and, when the planned steps finish early, train the final level on until the deadline."""

    def __init__(self, config: TrainConfig, deadline: float, pace: Pace | None, agree) -> None:
        self.config, self.deadline, self.pace = config, deadline, pace
        self.agree = agree  # rank 0's view decides for every rank (train.distributed)
        self.extends = True
        self._said_extended = self._said_reach = False
        self._said_stride: set[int] = set()

    def before(self, state: LoopState) -> int | None:
        """None to stop now, else the step to train next (state.step, or later when behind)."""
        now = time.monotonic()
        if self.agree(now > self.deadline):
            return None
        if state.step >= state.total and not self._said_extended:
            self._said_extended = True
            say(
                f"the planned {state.total} steps are done with "
                f"{(self.deadline - now) / 60:.1f} min of the budget left: the final level "
                f"({self.config.resolution}x{self.config.resolution}) trains on until it ends"
            )
        ahead = self.agree(self.pace.next_step(state.step, now) if self.pace else state.step)
        if self.pace is not None and self.pace.out_of_reach and not self._said_reach:
            self._said_reach = True
            say(
                "slower than planned: at this rate the budget reaches no level after "
                f"{schedule(self.config, state.step).resolution}, which trains on until it ends"
            )
        where = schedule(self.config, state.step)
        if self.pace is not None and self.pace.fade_stride > 1:
            if where.level not in self._said_stride:
                self._said_stride.add(where.level)
                say(
                    f"slower than planned: the {where.resolution}x{where.resolution} block "
                    f"fades in with a stride of {self.pace.fade_stride} steps from step "
                    f"{state.step} so that it is fully in (the level trained) within the budget"
                )
        elif ahead != state.step:
            say(
                f"slower than planned: level {where.resolution} ends at step {state.step} (of "
                f"{ahead}) so that the run reaches the final level within the budget"
            )
        return int(ahead)


class Anneal:
    """`--anneal SHARE`: over the last SHARE of this call's run the learning rate falls along a
    half cosine to ANNEAL_FLOOR of --lr (train.step.annealed), at the level the run ends at.

    The run is this call's: its time budget (`budget`), else its steps (state.start
    to state.total), so a resumed run anneals within its own --minutes. The level it ends at
    is the last of its steps' (a step budget), else the final level, or the level the pace
    (train.budget.Pace) finds the budget cannot leave (`out_of_reach`: it trains on until the
    budget ends); once the fall begins on such a level the pace holds it, so the fallen rate
    never carries into a level that would need the full one. A level first trained inside the
    window anneals from that step on, from the full rate. The constant rate leaves the weights
    wandering around a minimum (the film body's loss swung 0.53-0.78 over its last steps); the
    fall lets them settle in it. The factor and the pace's verdict are rank 0's (`agree`), so
    every rank steps alike."""

    def __init__(
        self,
        config: TrainConfig,
        share: float,
        agree: Callable[[int], int],
        budget: tuple[float, float] | None = None,
        pace: Pace | None = None,
    ) -> None:
        self.config, self.share, self.agree = config, share, agree
        self.budget, self.pace = budget, pace
        """`budget`: this call's (began, deadline) on the monotonic clock; None: its steps."""
        self.final = len(config.levels()) - 1
        self._level: int | None = None
        """The level the window is on in this call; None: not yet."""
        self._start = 1.0
        """Where (0..1 through the run) the window began on that level."""

    def progress(self, state: LoopState) -> float:
        """How far (0..1) this call's run is: by the clock with a budget, else by steps."""
        if self.budget is not None:
            began, deadline = self.budget
            return (time.monotonic() - began) / max(deadline - began, 1e-9)
        return (state.step - state.start) / max(state.total - state.start, 1)

    def ends_at(self, level: int, state: LoopState) -> bool:
        """Whether the run ends at `level` (see the class doc)."""
        if self.budget is None:
            return level == schedule(self.config, max(state.total - 1, state.start)).level
        if level == self.final:
            return True
        return self.pace is not None and bool(self.agree(int(self.pace.out_of_reach)))

    def factor(self, state: LoopState) -> float:
        """The learning rate's factor for the step about to train (1 before the window)."""
        level = schedule(self.config, state.step).level
        if not self.ends_at(level, state):
            return 1.0
        now = self.progress(state)
        if level != self._level:  # only before the fall: once it began, the level is held
            self._level, self._start = level, max(1.0 - self.share, now)
        t = max(now - self._start, 0.0) / max(1.0 - self._start, 1e-9)
        t = self.agree(round(t * 1e6)) / 1e6
        if t > 0 and level < self.final and self.pace is not None:
            self.pace.hold()
        return annealed(t)


def run_steps(
    state: LoopState,
    step_fn: Callable[[LoopState], dict[str, Any]],
    callbacks: Sequence[Callback],
    pacer: Pacer | None = None,
    done: str = "done",
) -> str:
    """Train from state.step: to state.total, or with a pacer until its deadline. Returns
    why it stopped (`done` when the steps ran out: 'step budget' for a run told its steps;
    'time budget' or 'interrupted'), said to every callback's on_end; other errors
    propagate after every callback is closed."""
    stopped = done
    try:
        try:
            while state.step < state.total or (pacer is not None and pacer.extends):
                if pacer is not None:
                    ahead = pacer.before(state)
                    if ahead is None:
                        stopped = "time budget"
                        break
                    if ahead != state.step:
                        for callback in callbacks:
                            callback.on_skip(state, ahead)
                        state.step = ahead
                        continue
                record = step_fn(state)  # the step's log line, "step" counting it done
                state.step += 1
                state.trained += 1
                for callback in callbacks:
                    callback.on_step(state, record)
        except KeyboardInterrupt:
            stopped = "interrupted"
        for callback in callbacks:
            callback.on_end(state, stopped)
    finally:
        for callback in callbacks:
            callback.close()
    return stopped


class ProgressBar(Callback):
    """A tqdm bar: steps, loss, level, images a second; a count and a rate past the plan."""

    def __init__(self, state: LoopState, enabled: bool, postfix: Callable[[dict], dict]) -> None:
        self.bar = tqdm(
            initial=state.start,
            total=state.total,
            unit="step",
            disable=not enabled,
            file=sys.stderr,
            dynamic_ncols=True,
        )
        self.postfix = postfix

    def on_step(self, state: LoopState, record: dict[str, Any]) -> None:
        if state.step > state.total and self.bar.total is not None:
            self.bar.total = None  # steps past the plan: no ETA
        self.bar.set_postfix(**self.postfix(record), img_s=f"{state.images_per_second:.1f}")
        self.bar.update(1)

    def on_skip(self, state: LoopState, to_step: int) -> None:
        self.bar.update(to_step - state.step)

    def close(self) -> None:
        self.bar.close()


class StepLog(Callback):
    """log.jsonl: a line per step (and per skip), appended; /dev/null off rank 0."""

    def __init__(self, path: Path, enabled: bool, every: int = 1) -> None:
        self.file = path.open("a") if enabled else open(os.devnull, "w")
        self.every = every

    def on_step(self, state: LoopState, record: dict[str, Any]) -> None:
        if state.trained % self.every == 0 or state.step == state.total:
            self.file.write(json.dumps(record) + "\n")

    def on_skip(self, state: LoopState, to_step: int) -> None:
        self.file.write(json.dumps({"step": state.step, "skipped_to": to_step}) + "\n")

    def close(self) -> None:
        self.file.close()


class Previews(Callback):
    """Every eval_every steps and at the last planned one: the held-out preview image and its
    quick metrics, added to the step's record (before StepLog writes it)."""

    def __init__(self, preview: Callable[[LoopState, int], dict[str, float]]) -> None:
        self.preview = preview

    def on_step(self, state: LoopState, record: dict[str, Any]) -> None:
        if state.step % state.config.eval_every == 0 or state.step == state.total:
            record["heldout"] = self.preview(state, record["resolution"])


class Checkpoints(Callback):
    """Every checkpoint_every steps, at the last planned one, and when a run stops early
    (a budget, Ctrl-C) with a finite loss: the checkpoint --resume continues from."""

    def __init__(self, save: Callable[[LoopState], Path]) -> None:
        self.save = save

    def on_step(self, state: LoopState, record: dict[str, Any]) -> None:
        if state.step % state.config.checkpoint_every == 0 or state.step == state.total:
            state.last_good = self.save(state)

    def on_end(self, state: LoopState, stopped: str) -> None:
        if stopped != "done" and state.step > state.start and math.isfinite(state.last_loss):
            state.last_good = self.save(state)  # at the last planned step: saved again, same

"""Shared fixtures for the train tests: one tiny CesiumMan dataset per session."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from rigspace.capture.pipeline import capture
from rigspace.capture.settings import CaptureOverrides
from tests.conftest import REPO

SCENE = REPO / "samples" / "scenes" / "cesium_man.usda"
CHARACTER = "/World/CesiumMan"
VIEWS = 8
FRAMES = (1.0, 4.0)
TINY = CaptureOverrides(views=VIEWS, elevations=(0.0,), resolution=32, frames=FRAMES)

_captured: dict[str, Path] = {}


def captured_dataset(tmp_path_factory) -> Path:
    """The tiny dataset, captured once per session (test_baselines uses it too).

    8 training views at elevation 0 and their 8 held-out midpoints, 4 frames, 32^2: 64
    samples; one clip and no held-out clip, so "heldout-clips" is empty.
    """
    if "tiny" not in _captured:
        out = tmp_path_factory.mktemp("eval") / "ds"
        capture(SCENE, CHARACTER, out, TINY, workers=1, progress=False)
        _captured["tiny"] = out
    return _captured["tiny"]


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory, tiny_dataset) -> Path:
    """A finished training run of the tiny preset on the tiny dataset (read-only: copy it)."""
    pytest.importorskip("torch", reason="training needs the train extra (torch)")
    from rigspace.train import loop
    from rigspace.train.config import preset

    run = tmp_path_factory.mktemp("train") / "run"
    result = loop.train(tiny_dataset, run, preset("tiny"), progress=False)
    assert result.stopped == "done" and result.step == preset("tiny").total_steps()
    return run


class _Clock:
    """The training loop's monotonic clock (train.loop, train.callbacks), moved on only by
    training steps, `seconds[resolution]` each: a run with a time budget takes the same steps
    on any machine, however loaded."""

    def __init__(self, seconds: dict[int, float]) -> None:
        self.now, self.seconds = 1000.0, seconds

    def monotonic(self) -> float:
        return self.now


@pytest.fixture
def step_clock(monkeypatch):
    """install(seconds per step by resolution, probe=the plan's measured rates): the budget's
    clock ticks per training step, and the probe measures `probe` (default: the same)."""

    def install(seconds: dict[int, float], probe: dict[int, float] | None = None) -> _Clock:
        from rigspace.train import callbacks, loop

        clock = _Clock(seconds)
        fake = SimpleNamespace(monotonic=clock.monotonic, perf_counter=time.perf_counter)
        monkeypatch.setattr(loop, "time", fake)
        monkeypatch.setattr(callbacks, "time", fake)
        measured = dict(probe or seconds)
        monkeypatch.setattr(loop, "measure_step_seconds", lambda *args, **kwargs: measured)
        real = loop._train_step

        def step(state, **kwargs):
            record = real(state, **kwargs)
            clock.now += seconds[record["resolution"]]
            return record

        monkeypatch.setattr(loop, "_train_step", step)
        return clock

    return install

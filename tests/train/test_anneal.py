"""--anneal: the learning rate falls at the end of a run, at the level it ends at, within the
call's own budget (a resumed run's too), and a bad share is refused before anything is written."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import replace
from pathlib import Path

import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from rigspace.sdk.cli import main  # noqa: E402
from rigspace.train import loop  # noqa: E402
from rigspace.train.budget import Pace  # noqa: E402
from rigspace.train.config import ConfigError, check_anneal, preset  # noqa: E402
from rigspace.train.step import ANNEAL_FLOOR, annealed  # noqa: E402

TINY = preset("tiny")  # 20 steps at 16x16, then 20 at 32x32 (the final level)


def _rates(run: Path) -> dict[int, tuple[int, float]]:
    """Each logged step's (resolution, learning rate), by step."""
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    return {r["step"]: (r["resolution"], r["lr"]) for r in records if "lr" in r}


def test_the_rate_falls_along_a_half_cosine_to_the_floor():
    assert annealed(0.0) == 1.0
    assert annealed(1.0) == pytest.approx(ANNEAL_FLOOR)
    assert annealed(0.5) == pytest.approx((1 + ANNEAL_FLOOR) / 2)
    ts = [i / 20 for i in range(21)]
    assert all(annealed(a) > annealed(b) for a, b in itertools.pairwise(ts))
    assert annealed(-1.0) == 1.0 and annealed(2.0) == pytest.approx(ANNEAL_FLOOR)


@pytest.mark.slow
def test_a_step_budget_anneals_its_final_level_only(tmp_path, tiny_dataset):
    run = tmp_path / "run"
    loop.train(tiny_dataset, run, TINY, steps=40, anneal=0.5, progress=False)
    rates = _rates(run)
    assert sorted(rates) == list(range(1, 41))
    # The window is the last half: steps 20-39, which are the final level's.
    assert all(rates[s] == (16, TINY.lr) for s in range(1, 21))
    final = [rates[s][1] for s in range(21, 41)]
    assert all(rates[s][0] == 32 for s in range(21, 41))
    assert final[0] == pytest.approx(TINY.lr)
    assert all(a > b for a, b in itertools.pairwise(final))
    assert final[-1] == pytest.approx(TINY.lr * annealed(19 / 20))
    assert final[-1] < 0.05 * TINY.lr
    # A window reaching back into the lower level starts where the final level does.
    whole = tmp_path / "whole"
    loop.train(tiny_dataset, whole, TINY, steps=40, anneal=1.0, progress=False)
    assert _rates(whole) == rates
    # Without --anneal the rate stays --lr.
    plain = tmp_path / "plain"
    loop.train(tiny_dataset, plain, TINY, steps=40, progress=False)
    assert {lr for _, lr in _rates(plain).values()} == {TINY.lr}


@pytest.mark.slow
def test_a_resumed_time_budget_anneals_within_its_own_minutes(tmp_path, tiny_dataset, step_clock):
    """A finished run resumed for 3 more seconds of the step clock (0.1 s a 32x32 step: 30
    steps) with --anneal 1: the whole resumed call falls from --lr to about the floor, the
    first call's steps stay at --lr."""
    step_clock({16: 0.05, 32: 0.1})
    run = tmp_path / "run"
    first = loop.train(tiny_dataset, run, TINY, steps=40, progress=False)
    again = loop.train(
        tiny_dataset, run, TINY, minutes=0.05, resume=True, anneal=1.0, progress=False
    )
    assert again.stopped == "time budget" and again.step == pytest.approx(first.step + 30, abs=1)
    rates = _rates(run)
    assert {rates[s][1] for s in range(1, first.step + 1)} == {TINY.lr}
    resumed = [rates[s][1] for s in range(first.step + 1, again.step + 1)]
    assert resumed[0] == pytest.approx(TINY.lr, rel=0.01)
    assert all(a > b for a, b in itertools.pairwise(resumed))
    assert resumed[-1] < 0.05 * TINY.lr
    # Resumed again without it, the run trains at the full rate: the fall was that call's.
    more = loop.train(tiny_dataset, run, TINY, minutes=0.01, resume=True, progress=False)
    assert more.step > again.step
    assert {_rates(run)[s][1] for s in range(again.step + 1, more.step + 1)} == {TINY.lr}


@pytest.mark.slow
def test_a_step_budget_short_of_the_final_level_anneals_the_level_it_ends_at(
    tmp_path, tiny_dataset
):
    run = tmp_path / "run"
    loop.train(tiny_dataset, run, TINY, steps=20, anneal=0.5, progress=False)
    rates = _rates(run)
    assert sorted(rates) == list(range(1, 21)) and {r for r, _ in rates.values()} == {16}
    assert all(rates[s][1] == TINY.lr for s in range(1, 11))
    fall = [rates[s][1] for s in range(11, 21)]
    assert fall[0] == pytest.approx(TINY.lr)
    assert all(a > b for a, b in itertools.pairwise(fall)) and fall[-1] < 0.05 * TINY.lr


@pytest.mark.slow
def test_a_budget_that_cannot_leave_its_level_anneals_that_level(
    tmp_path, tiny_dataset, step_clock
):
    """The probe said 0.01 s a 16x16 step; they take 0.5 s, so 30 s hold 60 of the level's 100
    and its 32x32 block can never fade in (the pace: out of reach). That level is what the
    run ends with: its last half falls, and no step reaches 32x32 at the fallen rate."""
    step_clock({16: 0.5, 32: 0.02}, probe={16: 0.01, 32: 0.02})
    config = replace(TINY, steps_per_level=100)
    run = tmp_path / "run"
    result = loop.train(tiny_dataset, run, config, minutes=0.5, anneal=0.5, progress=False)
    assert result.stopped == "time budget" and result.step == pytest.approx(60, abs=1)
    rates = _rates(run)
    assert {r for r, _ in rates.values()} == {16}
    steps = sorted(rates)
    assert all(rates[s][1] == TINY.lr for s in steps if s <= 30)
    fall = [rates[s][1] for s in steps if s > 30]
    assert fall[0] > 0.95 * TINY.lr and fall[-1] < 0.05 * TINY.lr
    assert all(a > b for a, b in itertools.pairwise(fall))


def test_a_held_pace_keeps_its_level_when_the_rate_recovers():
    config = replace(TINY, resolution=64, steps_per_level=100)  # levels 16, 32, 64; fade 50
    probe = {16: 0.01, 32: 0.02, 64: 0.04}
    for held in (False, True):
        pace = Pace(config, probe, deadline=100.0)
        assert all(pace.next_step(s, 1.0 * s) == s for s in range(30))  # a second a step
        assert pace.out_of_reach
        if held:
            pace.hold()
        # Then the probe's rate: 32 and 64 come back in reach, and 16 ends unless held.
        jumped = any(pace.next_step(s, 30.0 + 0.01 * (s - 29)) != s for s in range(30, 99))
        assert jumped != held and pace.out_of_reach == held


@pytest.mark.parametrize("share", [-0.1, 1.5, math.nan, math.inf])
def test_a_share_outside_0_to_1_is_refused_before_anything_is_written(tmp_path, share, capsys):
    with pytest.raises(ConfigError, match="--anneal"):
        check_anneal(share)
    out = tmp_path / "model"
    argv = ["train", str(tmp_path / "no_dataset"), "--out", str(out), "--preset", "tiny"]
    assert main([*argv, "--anneal", str(share)]) != 0
    err = capsys.readouterr().err
    assert "--anneal" in err and "from 0 (off) to 1" in err
    assert not out.exists()

"""--anneal: the learning rate falls at the end of a run, at its final level only, within the
call's own budget (a resumed run's too), and a bad share is refused before anything is written."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from rigspace.sdk.cli import main  # noqa: E402
from rigspace.train import loop  # noqa: E402
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

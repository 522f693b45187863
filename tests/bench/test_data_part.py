"""The bench's data part: a step's batch decoded against gathered from kept items."""

from __future__ import annotations

import pytest

pytest.importorskip("torch", reason="the kept items need the train extra (torch)")

from rigspace.bench import data
from rigspace.train.data import SampleSet


def test_the_batch_comparison_measures_both_ways_and_reports_them(tiny_dataset):
    result = data.batches(SampleSet(tiny_dataset, "train"), kept=16, batch=8, repeats=2)["batches"]
    assert result["kept"] == 16 and result["batch"] == 8
    assert result["decoded_ms"] > 0 and result["gathered_ms"] > 0 and result["kept_seconds"] > 0
    assert result["mib_per_item"] > 0
    (line,) = data._batch_lines(result)
    assert "A step's batch of 8: decoded by the prefetcher" in line and "16 items" in line

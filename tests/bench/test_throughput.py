"""bench/throughput.py: capture samples/s and training images/s at tiny sizes."""

from __future__ import annotations

import math

import pytest

from rigspace.bench.throughput import capture_dataset, capture_throughput, training_throughput


@pytest.fixture(scope="module")
def dataset_32(tmp_path_factory):
    return capture_dataset(tmp_path_factory.mktemp("bench") / "ds", 32, frames=(0.0, 1.0))


def test_capture_rows_are_positive_or_say_why_not():
    rows = capture_throughput(("gl", "embree", "no-such-renderer"), (32,), (0.0, 0.0), views=2)
    assert [r["renderer"] for r in rows] == ["gl", "embree", "no-such-renderer"]
    assert "skipped" in rows[-1]
    measured = [r for r in rows if "skipped" not in r]
    assert measured, rows  # embree needs no GPU or display
    for row in measured:
        assert row["resolution"] == 32 and row["samples"] > 0 and row["samples_per_s"] > 0


def test_training_rows_on_a_given_dataset(dataset_32):
    tiny, small = training_throughput(("tiny", "small"), steps=2, warmup=1, dataset=dataset_32)
    assert tiny["images_per_s"] > 0 and tiny["median_step_ms"] > 0
    assert tiny["finite"] and len(tiny["losses"]) == 3
    assert all(math.isfinite(v) for v in tiny["losses"])
    assert "images_per_s" not in small and "128" in small["skipped"]


def test_training_captures_its_own_dataset():
    (row,) = training_throughput(("tiny",), steps=1, warmup=1)
    assert row["dataset_resolution"] == row["resolution"] == 32
    assert row["images_per_s"] > 0 and row["finite"]

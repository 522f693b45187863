"""A training run's run.json, typed (train.loop.RunRecord): read_run gives back what the run
wrote, and a resumed run is compared with it field by field."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

pytest.importorskip("torch", reason="training needs the train extra (torch)")

from rigspace.train import loop

MINIMAL = {"config": {}, "dataset": "/d", "joints": ["a", "a/b"]}
"""What read_run needs (train.loop.TRAINING_RUN's required fields)."""


def test_read_run_gives_back_the_file_the_run_wrote(tiny_run):
    record = loop.read_run(tiny_run)
    written = (tiny_run / loop.RUN_FILE).read_text()
    assert json.dumps(record.to_json(), indent=2) + "\n" == written
    assert record.train_config().to_json() == record.config and len(record.joints) == 19
    assert record.plan is None and record.planned_steps_per_level is None


def test_a_minimal_run_json_reads_with_defaults_and_round_trips(tmp_path):
    record = loop.RunRecord.from_json(MINIMAL, tmp_path / loop.RUN_FILE)
    assert record.joints == ("a", "a/b") and record.charts is None and record.blend_shapes == ()
    assert loop.RunRecord.from_json(record.to_json(), tmp_path / loop.RUN_FILE) == record
    planned = replace(record, plan={"steps_per_level": 40, "seconds_per_step": {"8": 0.1}})
    assert planned.planned_steps_per_level == 40


def test_differences_name_the_fields_a_resumed_run_changes(tiny_run):
    record = loop.read_run(tiny_run)
    assert record.differences(record) == []
    assert record.differences(replace(record, plan={"steps_per_level": 5})) == []
    other = replace(record, dataset="/elsewhere", joints=record.joints[:-1])
    assert record.differences(other) == ["dataset", "joints"]
    older = replace(record, config={k: v for k, v in record.config.items() if k != "seed"})
    assert record.differences(older) == []  # an option added since reads as its default


def test_a_run_json_that_is_not_an_object_is_a_named_error(tmp_path):
    with pytest.raises(loop.TrainingError, match=r"run\.json: it is not an object.*Fix:"):
        loop.RunRecord.from_json([], tmp_path / loop.RUN_FILE)

"""Training under torchrun: two gloo ranks against one process, resume across world sizes, shards."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from rigspace.apps import train as cli  # noqa: E402
from rigspace.apps.train import torchrun_argv  # noqa: E402
from rigspace.capture.pack import pack  # noqa: E402
from rigspace.train import loop  # noqa: E402
from rigspace.train.config import preset  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402

TINY = preset("tiny")
LOSS_TOLERANCE = 0.01
"""Relative difference allowed between a two-rank step's loss and one process's at the same
global batch and samples. Not float noise alone: DDP averages per-rank gradients, and the
depth and normal terms are means over each rank's own covered pixels, so the two halves of
a batch weigh its pixels slightly differently than one process does (measured: at most 0.3%
over these steps)."""


def losses(run: Path) -> list[float]:
    return [json.loads(line)["loss"] for line in (run / "log.jsonl").read_text().splitlines()]


@pytest.mark.slow
def test_two_gloo_ranks_match_one_process_and_resume_on_one(tiny_dataset, tmp_path):
    one = tmp_path / "one"
    loop.train(tiny_dataset, one, TINY, steps=8, progress=False)
    # Two ranks through `rigspace train --nproc 2` (torchrun spawned, gloo), stopped at step 4.
    bundle = tmp_path / "two"
    done = subprocess.run(
        [sys.executable, "-m", "rigspace.apps.train", str(tiny_dataset), "--out",
         str(bundle), "--preset", "tiny", "--steps", "4", "--no-int8", "--nproc", "2"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert "trained 4 steps" in done.stdout and (bundle / "manifest.json").is_file()
    run = bundle / cli.TRAINING
    assert len(losses(run)) == 4  # rank 0 alone logs
    # Resume on one process (world size 2 -> 1): the same global batches, so the curve goes on.
    result = loop.train(tiny_dataset, run, TINY, steps=8, resume=True, progress=False)
    assert result.step == 8
    ours, theirs = np.array(losses(run)), np.array(losses(one))
    assert len(ours) == 8
    assert np.all(np.abs(ours - theirs) <= LOSS_TOLERANCE * theirs), (ours, theirs)
    assert not np.array_equal(ours, theirs)  # really two processes: not bit-identical


def test_training_reads_shards_and_exports_from_them(tiny_dataset, tmp_path):
    shards = tmp_path / "shards"
    pack(tiny_dataset, shards, samples_per_shard=8)
    run = tmp_path / "run"
    result = loop.train(shards, run, TINY, steps=3, progress=False)
    assert result.step == 3 and np.isfinite(result.last_loss)
    assert json.loads((run / loop.RUN_FILE).read_text())["dataset"] == str(shards.resolve())
    manifest = export_bundle(run, tmp_path / "bundle", int8=False)
    assert "trunk.onnx" in manifest["files"]


def test_rigspace_train_rebuilds_its_command_for_torchrun():
    parser = argparse.ArgumentParser()
    cli.add_train_arguments(parser)
    argv = ["DS", "--out", "M", "--preset", "tiny", "--steps", "5", "--resume", "--no-int8",
            "--batch", "8", "--lr", "0.002", "--no-channels-last", "--nproc", "2"]  # fmt: skip
    args = parser.parse_args(argv)
    command = torchrun_argv(args, 2)
    assert command[:6] == [sys.executable, "-m", "torch.distributed.run", "--standalone",
                           "--nproc-per-node=2", "-m"]  # fmt: skip
    assert command[6] == "rigspace.apps.train"
    again = parser.parse_args(command[7:])
    assert again.nproc == 1  # the ranks themselves run one process each
    assert {k: v for k, v in vars(again).items() if k != "nproc"} == {
        k: v for k, v in vars(args).items() if k != "nproc"
    }


def test_a_global_batch_that_does_not_split_over_the_ranks_is_refused(tiny_dataset):
    from rigspace.capture.dataset import DatasetError
    from rigspace.train.data import SampleSet
    from rigspace.train.stream import prefetcher

    with pytest.raises(DatasetError, match="--batch 4 does not split evenly over 3 ranks"):
        prefetcher(SampleSet(tiny_dataset, "train"), 4, seed=0, rank=0, world=3)

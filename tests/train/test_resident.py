"""Training items kept in the device's memory (train/resident.py): the same batches as the
prefetcher's, decoded alike by one process or a forked pool, device-clean, and a run that
trains identically with them."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from rigspace.train import loop  # noqa: E402
from rigspace.train.config import preset  # noqa: E402
from rigspace.train.data import Prefetcher, SampleSet  # noqa: E402
from rigspace.train.resident import ResidentBatches, decode_all, resident_or_not  # noqa: E402

TINY = preset("tiny")


@pytest.fixture(scope="module")
def samples(tiny_dataset):
    return SampleSet(tiny_dataset, "train")


@pytest.mark.parametrize("oversample, rank, world", [(0.0, 0, 1), (1.0, 0, 1), (0.0, 1, 2)])
def test_the_batches_are_the_prefetcher_s(samples, oversample, rank, world):
    plain = Prefetcher(samples, 8, seed=3, rank=rank, world=world, oversample=oversample)
    kept = ResidentBatches(samples, 8, seed=3, rank=rank, world=world, oversample=oversample,
                           device=torch.device("cpu"), workers=1, progress=False)  # fmt: skip
    try:
        for step in (0, 1, 7, 20):  # 20 * 8 > 48 samples: past the first epoch
            expected, got = plain.get(step), kept.get(step)
            assert sorted(got) == sorted(expected)
            for key, value in expected.items():
                assert got[key].dtype == torch.from_numpy(value).dtype
                assert np.array_equal(got[key].numpy(), value), (step, key)
    finally:
        plain.close()
        kept.close()


def test_a_forked_pool_decodes_the_same_items(samples):
    one = decode_all(samples, torch.device("cpu"), workers=1, progress=False)
    pool = decode_all(samples, torch.device("cpu"), workers=2, progress=False)
    assert len(one["rig"]) == len(samples) and set(one) == set(pool)
    for key in one:
        assert torch.equal(one[key], pool[key]), key


def test_the_items_live_on_the_device_and_batches_stay_there(samples):
    """On the meta device, as on CUDA: a tensor made on the CPU by mistake fails here."""
    kept = ResidentBatches(samples, 4, seed=0, device=torch.device("meta"), channels_last=True,
                           workers=1, progress=False)  # fmt: skip
    batch = kept.get(5)
    assert all(v.device.type == "meta" for v in kept.items.values())
    assert all(v.device.type == "meta" and len(v) == 4 for v in batch.values())
    assert batch["albedo"].is_contiguous(memory_format=torch.channels_last)
    assert kept.bytes == len(samples) * sum(v[0].numel() * 4 for v in kept.items.values())
    kept.close()


def test_auto_keeps_them_only_on_a_gpu(samples):
    assert resident_or_not(samples, torch.device("cpu"), "auto") == (False, None)
    assert resident_or_not(samples, torch.device("cpu"), "on") == (True, None)
    assert resident_or_not(samples, torch.device("cpu"), "off") == (False, None)
    with pytest.raises(ValueError, match="resident 'sometimes'"):
        resident_or_not(samples, torch.device("cpu"), "sometimes")


def test_a_run_trains_identically_with_the_items_kept(tiny_dataset, tmp_path, capfd):
    config = replace(TINY, steps_per_level=4, checkpoint_every=1000)
    losses = {}
    for mode in ("off", "on"):
        loop.train(tiny_dataset, tmp_path / mode, config, steps=6, progress=False,
                   resident=mode)  # fmt: skip
        log = (tmp_path / mode / "log.jsonl").read_text().splitlines()
        losses[mode] = [json.loads(line)["loss"] for line in log]
    assert len(losses["on"]) == 6 and losses["on"] == losses["off"]
    assert "training items kept in cpu memory" in capfd.readouterr().err

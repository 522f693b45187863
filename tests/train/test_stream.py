"""Tar shards (rigspace dataset pack) and the training stream: items, order, ranks, memory."""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import tarfile
from itertools import islice
from pathlib import Path

import numpy as np
import pytest

from rigspace.apps import dataset as dataset_cli
from rigspace.capture import dataset as ds
from rigspace.capture.pack import INDEX_FILE, pack
from rigspace.sdk.exr import write_exr
from rigspace.sdk.render import Maps
from rigspace.train.data import SampleSet
from rigspace.train.evaluate import DatasetTable
from rigspace.train.stream import ShardSet, ShardStream, open_split, prefetcher

MEMORY_CAP = 16 * 2**20
"""Peak RSS growth allowed while streaming a dataset several times larger (below)."""


@pytest.fixture(scope="module")
def shards(tiny_dataset, tmp_path_factory) -> Path:
    """The tiny dataset (32 train + 32 held-out samples) in shards of 6 samples."""
    out = tmp_path_factory.mktemp("shards") / "sh"
    pack(tiny_dataset, out, samples_per_shard=6)
    return out


def test_pack_writes_indexed_deterministic_single_split_shards(tiny_dataset, shards, tmp_path):
    index = json.loads((shards / INDEX_FILE).read_text())
    assert index["counts"] == {"train": 32, "heldout-views": 32, "heldout-clips": 0}
    assert [s["count"] for s in index["shards"] if s["split"] == "train"] == [6] * 5 + [2]
    with np.load(tiny_dataset / ds.PARAMS_FILE) as table:
        splits, paths = table["split"], table["path"]
    for shard in index["shards"]:
        data = (shards / shard["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == shard["sha256"] and len(data) == shard["bytes"]
        ids = [i for first, stop in shard["samples"] for i in range(first, stop)]
        assert {int(splits[i]) for i in ids} == {ds.SPLITS.index(shard["split"])}
        with tarfile.open(shards / shard["file"]) as tar:
            names = tar.getnames()
            assert names == [f"{i:09d}.{ext}" for i in ids for ext in ("exr", "npz")]
            # Each sample's EXR is the captured file, byte for byte.
            first = tar.extractfile(names[0])
            assert first is not None and first.read() == (tiny_dataset / paths[ids[0]]).read_bytes()
            assert {m.mtime for m in tar.getmembers()} == {0}
    # The same dataset packs to the same bytes; packing into the finished folder is a no-op.
    again = pack(tiny_dataset, tmp_path / "again", samples_per_shard=6)
    assert [s["sha256"] for s in again["shards"]] == [s["sha256"] for s in index["shards"]]
    assert pack(tiny_dataset, shards, samples_per_shard=6) == index
    with pytest.raises(ds.DatasetError, match="another dataset or shard size"):
        pack(tiny_dataset, shards, samples_per_shard=7)


def test_pack_refuses_a_damaged_sample_and_names_it(tiny_dataset, tmp_path):
    copy = tmp_path / "ds"
    shutil.copytree(tiny_dataset, copy)
    with np.load(copy / ds.PARAMS_FILE) as table:
        victim = copy / str(table["path"][3])
    victim.write_bytes(victim.read_bytes()[:-10])
    with pytest.raises(ds.DatasetError, match=r"differs from its recorded checksum") as info:
        pack(copy, tmp_path / "sh")
    assert str(victim) in str(info.value) and "--resume" in info.value.fix
    assert not (tmp_path / "sh" / INDEX_FILE).exists()  # an unfinished pack, never a wrong one


def test_dataset_pack_command(tiny_dataset, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    dataset_cli.add_arguments(parser)
    args = parser.parse_args(["pack", str(tiny_dataset), "--out", str(tmp_path / "sh")])
    assert dataset_cli.run(args) == 0
    assert "packed 64 samples (train 32, heldout-views 32, heldout-clips 0) into 2 shards" in (
        capsys.readouterr().out
    )


def test_shard_items_equal_the_dataset_folders(tiny_dataset, shards):
    for split in ("train", "heldout-views"):
        folder, stream = SampleSet(tiny_dataset, split, 16), open_split(shards, split, 16)
        assert isinstance(stream, ShardSet) and len(stream) == len(folder)
        for k in range(len(folder)):
            a, b = folder.item(k), stream.item(k)
            assert a.keys() == b.keys()
            assert all(np.array_equal(a[key], b[key]) for key in a), (split, k)


def test_eval_reads_a_shards_folder_as_it_reads_the_dataset(tiny_dataset, shards):
    """`rigspace eval MODEL SHARDS` sees the same captured maps, row for row (they were read
    from the EXR paths in the shards folder, which holds none, before)."""
    folder, packed = DatasetTable(tiny_dataset), DatasetTable(shards)
    rows = np.concatenate([folder.indices("heldout-views")[::5], folder.indices("train")[::7]])
    for row in rows:
        a, b = folder.captured_maps(int(row)), packed.captured_maps(int(row))
        for name in ("albedo", "mask", "normal", "depth"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), (row, name)


def keys(stream: ShardStream, epoch: int) -> list[str]:
    return [m.key for m in stream.epoch(epoch)]


def test_stream_order_is_seeded_per_rank_and_equal_in_length(shards):
    samples = ShardSet(shards, "train")
    one = ShardStream(samples, seed=3, buffer=8)
    # One rank: every sample once an epoch, shuffled beyond shard order, a new order each epoch.
    assert sorted(keys(one, 0)) == sorted(keys(one, 1)) and len(set(keys(one, 0))) == 32
    assert keys(one, 0) != keys(one, 1) and keys(one, 0) != sorted(keys(one, 0))
    assert keys(one, 0) == keys(ShardStream(samples, seed=3, buffer=8), 0)
    assert keys(one, 0) != keys(ShardStream(samples, seed=4, buffer=8), 0)
    for world in (2, 3, 4):
        ranks = [ShardStream(samples, 3, rank, world, buffer=8) for rank in range(world)]
        orders = [keys(r, 0) for r in ranks]
        # Same length on every rank (DDP never waits on a rank that ran out), 32 // world.
        assert {len(o) for o in orders} == {32 // world}
        # Each rank reads its own shards: shard sets are disjoint across ranks.
        dealt = [set(r.shards_of(0)) for r in ranks]
        assert sum(len(d) for d in dealt) == len(set().union(*dealt)) == 6
        assert orders == [
            keys(ShardStream(samples, 3, r, world, buffer=8), 0) for r in range(world)
        ]
    # Resume: the stream from a position is the uninterrupted stream's tail.
    full = [m.key for m in islice(one.members_from(0), 70)]
    assert [m.key for m in islice(one.members_from(45), 25)] == full[45:]


def test_stream_prefetcher_resumes_at_any_step_and_splits_the_global_batch(shards):
    samples = ShardSet(shards, "train", 16)
    a = prefetcher(samples, 4, seed=1, rank=1, world=2)
    b = prefetcher(samples, 4, seed=1, rank=1, world=2)
    try:
        steps = [a.get(s) for s in range(5)]
        assert steps[0]["rig"].shape == (2, 19 * 6) and steps[0]["albedo"].shape == (2, 3, 16, 16)
        resumed = b.get(3)
        assert all(np.array_equal(resumed[k], steps[3][k]) for k in resumed)
    finally:
        a.close()
        b.close()
    with pytest.raises(ds.DatasetError, match="does not split evenly over 3 ranks"):
        prefetcher(samples, 4, seed=1, rank=0, world=3)


def test_a_truncated_shard_is_named_with_the_fix(shards, tmp_path):
    copy = tmp_path / "sh"
    shutil.copytree(shards, copy)
    index = json.loads((copy / INDEX_FILE).read_text())
    victim = copy / index["shards"][0]["file"]
    victim.write_bytes(victim.read_bytes()[:4096])
    stream = ShardStream(ShardSet(copy, "train"), seed=0)
    with pytest.raises(ds.DatasetError, match=r"not the size index\.json records") as info:
        list(stream.epoch(0))
    assert str(victim) in str(info.value) and "rigspace dataset pack" in info.value.fix


READER = """
import sys
from rigspace.train.stream import ShardSet, prefetcher

def kib(key):
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith(key))

samples = ShardSet(sys.argv[1], "train", 64)
batches = prefetcher(samples, 16, seed=0)
batches.get(0)  # imports, threads and the first batches: the reader's fixed cost
base = kib("VmRSS:")
open("/proc/self/clear_refs", "w").write("5")  # restart the peak (VmHWM) from here
steps = len(samples) // 16
for step in range(1, steps):
    batches.get(step)
batches.close()
print(steps * 16, (kib("VmHWM:") - base) * 1024)
"""


@pytest.mark.slow
def test_streaming_memory_stays_under_the_cap_on_a_dataset_five_times_larger(tmp_path):
    """Real format (EXRs, params.npz, manifest) of noise images, so nothing compresses away;
    1200 samples reuse 16 image files, packed into 64-sample shards (each sample whole)."""
    rng = np.random.default_rng(0)
    folder, size, rows, files = tmp_path / "ds", 64, 1200, 16
    (folder / "samples").mkdir(parents=True)
    paths, sums = [], []
    for u in range(files):
        maps = Maps(
            albedo=rng.random((size, size, 3), dtype=np.float32),
            normal=rng.random((size, size, 3), dtype=np.float32),
            depth=rng.random((size, size), dtype=np.float32),
            mask=rng.random((size, size), dtype=np.float32),
        )
        paths.append(f"samples/s{u:02d}.exr")
        write_exr(folder / paths[-1], maps)
        sums.append(ds.sha256_file(folder / paths[-1]))
    pick = np.arange(rows) % files
    table = {
        "path": np.array(paths)[pick],
        "sha256": np.array(sums)[pick],
        "rig": rng.random((rows, 19, 6), dtype=np.float32),
        "joint_camera": rng.random((rows, 3), dtype=np.float32),
        "split": np.zeros(rows, dtype=np.int8),
    }
    (folder / ds.PARAMS_FILE).write_bytes(ds.npz_bytes(table))
    manifest = {
        "format": ds.FORMAT,
        "format_version": ds.FORMAT_VERSION,
        "resolution": size,
        "joints": [f"j{i}" for i in range(19)],
        "ring": {"radius": 3.0, "horizontal_aperture": 20.955, "focal_length": 50.0},
        "checksum": "synthetic",
    }
    (folder / ds.MANIFEST_FILE).write_text(json.dumps(manifest))
    index = pack(folder, tmp_path / "sh", samples_per_shard=64)
    assert index["bytes"] > 5 * MEMORY_CAP
    out = subprocess.run(
        [sys.executable, "-c", READER, str(tmp_path / "sh")],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    streamed, growth = int(out[0]), int(out[1])
    assert streamed == rows
    assert growth < MEMORY_CAP, f"peak RSS grew {growth / 2**20:.1f} MiB while streaming"

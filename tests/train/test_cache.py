"""The decoded cache (capture.cache): bit-identical to the EXRs, rebuilt when stale, never
read when damaged, built by `rigspace train` and `rigspace dataset cache`."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from rigspace.capture.cache import (
    FOLDER,
    CacheError,
    DecodedCache,
    build_cache,
    open_cache,
    stale_reason,
)
from rigspace.capture.dataset import DatasetError, read_manifest
from rigspace.sdk.cli import main
from rigspace.sdk.exr import read_exr
from rigspace.train.data import SampleSet


@pytest.fixture
def dataset(tmp_path, tiny_dataset):
    """A private copy of the tiny dataset, without a cache."""
    out = tmp_path / "ds"
    shutil.copytree(tiny_dataset, out, ignore=shutil.ignore_patterns(FOLDER))
    return out


def paths_of(folder):
    with np.load(folder / "params.npz", allow_pickle=False) as table:
        return [str(p) for p in table["path"]]


def assert_same_maps(a, b):
    for name in ("albedo", "normal", "depth", "mask", "uv", "chart"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and x.shape == y.shape, name
            np.testing.assert_array_equal(x, y, err_msg=name)  # inf where empty included


def test_every_sample_reads_back_bit_identical_to_its_exr(dataset):
    manifest = read_manifest(dataset)
    paths = paths_of(dataset)
    cache = build_cache(dataset, manifest, paths, workers=2, progress=False)
    assert len(cache) == len(paths) and cache.textured
    assert stale_reason(dataset, manifest) is None
    for row in range(0, len(paths), 7):
        assert_same_maps(cache.maps(row), read_exr(dataset / paths[row]))
    stored = cache.info["stored_pixels"] / (len(cache) * cache.size**2)
    assert 0 < stored < 1  # only the character's box is kept


def test_training_items_are_the_same_from_the_cache_and_the_exrs(dataset):
    plain = SampleSet(dataset, "train", 16)
    assert plain.cache is None
    build_cache(dataset, read_manifest(dataset), paths_of(dataset), progress=False)
    cached = SampleSet(dataset, "train", 16)
    assert cached.cache is not None
    ks = np.arange(0, len(plain), 5)
    a, b = plain.batch(ks), cached.batch(ks)
    assert sorted(a) == sorted(b)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_new_samples_or_params_make_it_stale_and_it_is_not_read(dataset):
    manifest = read_manifest(dataset)
    build_cache(dataset, manifest, paths_of(dataset), progress=False)
    changed = replace(manifest, checksum="0" * 64)
    assert "samples changed" in stale_reason(dataset, changed)
    assert open_cache(dataset, changed) is None
    params = dataset / "params.npz"
    params.write_bytes(params.read_bytes() + b"\0")  # any change to the file's bytes
    assert "params.npz changed" in stale_reason(dataset, manifest)


def test_a_truncated_cache_is_never_read(dataset):
    manifest = read_manifest(dataset)
    build_cache(dataset, manifest, paths_of(dataset), progress=False)
    half = dataset / FOLDER / "half.u16"
    half.write_bytes(half.read_bytes()[:100])
    assert open_cache(dataset, manifest) is None  # training reads the EXRs instead
    with pytest.raises(CacheError) as info:
        DecodedCache(dataset)
    assert "half.u16" in str(info.value) and f"delete {dataset / FOLDER}" in str(info.value)
    assert SampleSet(dataset, "train").cache is None


def test_a_damaged_exr_stops_the_build_naming_it_and_leaves_no_cache(dataset):
    manifest = read_manifest(dataset)
    paths = paths_of(dataset)
    bad = dataset / paths[5]
    bad.write_bytes(bad.read_bytes()[:200])
    with pytest.raises(DatasetError) as info:
        build_cache(dataset, manifest, paths, workers=2, progress=False)
    assert str(bad) in str(info.value) and "--resume" in str(info.value)
    assert not (dataset / FOLDER).exists()
    assert not list(dataset.glob(f".{FOLDER}.*"))


def test_the_dataset_cache_command_builds_once(dataset, capsys):
    assert main(["dataset", "cache", str(dataset), "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert "decoded" in out and "samples/s" in out
    info = json.loads((dataset / FOLDER / "index.json").read_text())
    assert info["samples"] == len(paths_of(dataset))
    assert main(["dataset", "cache", str(dataset)]) == 0
    assert "up to date" in capsys.readouterr().out


def test_train_decodes_the_dataset_once_unless_told_not_to(dataset, tmp_path):
    from rigspace.train import loop
    from rigspace.train.config import preset

    loop.train(dataset, tmp_path / "a", preset("tiny"), steps=1, progress=False, cache=False)
    assert not (dataset / FOLDER).exists()
    loop.train(dataset, tmp_path / "b", preset("tiny"), steps=1, progress=False)
    assert stale_reason(dataset, read_manifest(dataset)) is None


def test_a_sample_with_nothing_in_view_reads_back(dataset):
    """A region's sample where the rest of the character hides the region entirely holds
    only the fill: an empty box in the cache, read back as the EXR has it."""
    from rigspace.sdk.exr import write_exr

    manifest = read_manifest(dataset)
    paths = paths_of(dataset)
    full = read_exr(dataset / paths[3])
    empty = replace(
        full,
        albedo=np.zeros_like(full.albedo),
        normal=np.zeros_like(full.normal),
        depth=np.full_like(full.depth, np.inf),
        mask=np.zeros_like(full.mask),
        uv=None if full.uv is None else np.zeros_like(full.uv),
        chart=None if full.chart is None else np.zeros_like(full.chart),
    )
    write_exr(dataset / paths[3], empty)
    cache = build_cache(dataset, manifest, paths, workers=1, progress=False)
    assert tuple(int(v) for v in cache.boxes[3]) == (0, 0, 0, 0)
    assert_same_maps(cache.maps(3), read_exr(dataset / paths[3]))

"""--oversample: pose rarity, weighted batches, their determinism, and the flag's errors."""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rigspace.apps import train as cli
from rigspace.capture import dataset as ds
from rigspace.capture.pack import pack
from rigspace.sdk.rotations import rot6d_from_matrix
from rigspace.train.config import ConfigError, TrainConfig, preset
from rigspace.train.data import (
    Prefetcher,
    SampleSet,
    batch_indices,
    epoch_order,
    pose_features,
    pose_rarity,
)
from rigspace.train.stream import ShardSet, prefetcher
from tests.conftest import axis_rotations

JOINTS = ["root", "root/arm", "root/arm/hand"]
FPS = 30.0
WALK_FRAMES, WHEEL_FRAMES = 300, 30
VIEWS = [(azimuth, elevation) for elevation in (0.0, 20.0) for azimuth in (0.0, 120.0, 240.0)]
HELD_OUT_VIEW = 5
"""Of VIEWS, the one whose rows go to heldout-views (rarity reads the train split only)."""
INVARIANCE = 1e-6
"""Feature differences between views of one frame: float32 rig rows, rotated back."""


def motion() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(clip, time, world rotations (frames, J, 3, 3)) of two clips on a Y-up stage.

    walk: 300 frames, the arm swinging +-30 degrees at 0.9 Hz (9 cycles, phases interleaved)
    while the heading turns 360 degrees; cartwheel: 30 frames, the root turning once about
    the forward axis with the arm raised. The cartwheel's poses are the rare ones.
    """
    t = np.arange(WALK_FRAMES) / FPS
    heading = axis_rotations("y", 360.0 * t / t[-1])
    swing = axis_rotations("x", 30.0 * np.sin(2 * np.pi * 0.9 * t))
    walk = np.stack([heading, heading @ swing, heading @ swing], axis=1)
    turn = axis_rotations("z", 360.0 * np.arange(WHEEL_FRAMES) / WHEEL_FRAMES)
    raised = turn @ axis_rotations("z", np.full(WHEEL_FRAMES, 90.0))
    wheel = np.stack([turn, raised, raised], axis=1)
    clip = np.repeat([0, 1], [WALK_FRAMES, WHEEL_FRAMES])
    time = np.concatenate([np.arange(WALK_FRAMES), 1000.0 + np.arange(WHEEL_FRAMES)])
    return clip, time, np.concatenate([walk, wheel])


def write_dataset(folder: Path, drop: tuple[str, ...] = ()) -> Path:
    """A dataset folder's manifest and params.npz of motion() seen from VIEWS (no images:
    rarity and batch order need none); `drop` leaves columns out."""
    clip, time, world = motion()
    cameras = [axis_rotations("y", [a])[0] @ axis_rotations("x", [-e])[0] for a, e in VIEWS]
    rows: dict[str, list] = {c: [] for c in ("rig", "clip", "time", "camera_to_world", "split")}
    for f in range(len(clip)):
        for v, camera in enumerate(cameras):
            rows["rig"].append(rot6d_from_matrix(camera.T @ world[f]))
            rows["clip"].append(clip[f])
            rows["time"].append(time[f])
            to_world = np.eye(4)
            to_world[:3, :3] = camera
            rows["camera_to_world"].append(to_world)
            rows["split"].append(1 if v == HELD_OUT_VIEW else 0)
    n = len(rows["rig"])
    table = {
        "path": np.array([f"samples/{i}.exr" for i in range(n)]),
        "sha256": np.array(["0" * 64] * n),
        "rig": np.array(rows["rig"], dtype=np.float32),
        "joint_camera": np.zeros((n, 3), dtype=np.float32),
        "clip": np.array(rows["clip"], dtype=np.int16),
        "time": np.array(rows["time"], dtype=np.float64),
        "camera_to_world": np.array(rows["camera_to_world"]),
        "split": np.array(rows["split"], dtype=np.int8),
    }
    folder.mkdir(parents=True)
    (folder / ds.PARAMS_FILE).write_bytes(
        ds.npz_bytes({k: v for k, v in table.items() if k not in drop})
    )
    manifest = {
        "format": ds.FORMAT,
        "format_version": ds.FORMAT_VERSION,
        "scene": "synthetic.usda",
        "up_axis": "Y",
        "resolution": 32,
        "joints": JOINTS,
        "ring": {"radius": 3.0, "horizontal_aperture": 20.955, "focal_length": 50.0},
        "checksum": "synthetic",
    }
    (folder / ds.MANIFEST_FILE).write_text(json.dumps(manifest))
    return folder


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("oversample") / "ds")


def indices_only(samples: SampleSet) -> SampleSet:
    """The split with `batch` returning the drawn indices instead of reading images."""
    samples.batch = lambda ks: {"k": np.asarray(ks)}  # type: ignore[method-assign]
    return samples


def clips_of(samples: SampleSet) -> np.ndarray:
    with np.load(samples.folder / ds.PARAMS_FILE) as table:
        return table["clip"][samples.rows]


def old_batch_indices(n: int, batch: int, step: int, seed: int) -> np.ndarray:
    """batch_indices as it was before --oversample (the runs it must resume identically)."""
    start, out, filled = step * batch, np.empty(batch, dtype=np.int64), 0
    while filled < batch:
        epoch, offset = divmod(start + filled, n)
        perm = np.random.default_rng([seed, epoch]).permutation(n)
        take = min(batch - filled, n - offset)
        out[filled : filled + take] = perm[offset : offset + take]
        filled += take
    return out


def test_pose_features_ignore_the_camera_and_the_heading():
    clip, _, world = motion()
    cameras = [axis_rotations("y", [a])[0] @ axis_rotations("x", [-e])[0] for a, e in VIEWS]
    per_view = []
    for camera in cameras:
        rig = rot6d_from_matrix(camera.T @ world).reshape(len(world), -1).astype(np.float32)
        to_world = np.tile(np.eye(4), (len(world), 1, 1))
        to_world[:, :3, :3] = camera
        per_view.append(pose_features(rig, to_world, np.array([0.0, 1.0, 0.0])))
    assert all(np.abs(f - per_view[0]).max() < INVARIANCE for f in per_view)
    walk = per_view[0][clip == 0]
    # Frames 0 and 100 (0.9 Hz: three whole cycles) share the arm's swing, not the heading.
    assert np.abs(walk[100] - walk[0]).max() < INVARIANCE
    # The cartwheel upside down (frame 15 of 30) differs from upright in its tilt.
    wheel = per_view[0][clip == 1]
    assert np.allclose(wheel[0, -3:], [0, 1, 0], atol=INVARIANCE)
    assert np.allclose(wheel[15, -3:], [0, -1, 0], atol=INVARIANCE)


def test_rarity_and_weights_favour_the_cartwheel(synthetic):
    samples = SampleSet(synthetic, "train")
    clip = clips_of(samples)
    rarity = samples.rarity()
    assert rarity.shape == (len(samples),) and np.median(rarity) == pytest.approx(1.0, abs=0.01)
    assert rarity.min() >= 0.1 and rarity.max() <= 10.0
    # Every cartwheel frame is rarer than the walk's 90th percentile.
    assert rarity[clip == 1].min() > np.percentile(rarity[clip == 0], 90)
    # One frame's views share one rarity.
    views = len(VIEWS) - 1
    assert np.all(rarity.reshape(-1, views) == rarity.reshape(-1, views)[:, :1])
    share = {g: samples.sampling_weights(g)[clip == 1].sum() for g in (0.0, 0.5, 1.0)}
    assert share[0.0] == pytest.approx(WHEEL_FRAMES / (WALK_FRAMES + WHEEL_FRAMES))
    assert share[0.0] < share[0.5] < share[1.0] and share[1.0] > 3 * share[0.0]


def test_pose_rarity_is_exact_on_a_line_and_subsamples_above_the_reference():
    line = np.arange(20.0)[:, None] ** 2  # gaps grow along the line: the far end is rarer
    rarity = pose_rarity(line, neighbours=1)
    assert np.all(np.diff(rarity[1:]) >= 0) and rarity[-1] > rarity[1]
    assert np.array_equal(pose_rarity(np.zeros((5, 3))), np.ones(5))  # one pose: all alike
    points = np.random.default_rng(1).normal(size=(300, 4))
    coarse = pose_rarity(points, neighbours=4, reference=100)
    exact = pose_rarity(points, neighbours=4)
    assert np.corrcoef(coarse, exact)[0, 1] > 0.8  # the same ranking, at a coarser scale
    assert np.array_equal(coarse, pose_rarity(points, neighbours=4, reference=100))


def test_oversample_zero_keeps_the_old_batch_order(synthetic):
    for n, batch, seed in ((10, 4, 3), (1650, 16, 0)):
        for step in (0, 1, 2, 200, 207):
            assert np.array_equal(
                batch_indices(n, batch, step, seed), old_batch_indices(n, batch, step, seed)
            )
    samples = indices_only(SampleSet(synthetic, "train"))
    uniform = Prefetcher(samples, 16, seed=2)
    try:
        assert uniform.weights is None
        for step in (0, 5, 103):
            expected = old_batch_indices(len(samples), 16, step, 2)
            assert np.array_equal(uniform.get(step)["k"], expected)
    finally:
        uniform.close()


def test_weighted_epochs_draw_each_sample_its_expected_count_deterministically():
    weights = np.random.default_rng(0).random(50) ** 3
    weights /= weights.sum()
    order = epoch_order(50, 7, 4, weights)
    assert len(order) == 50 and np.array_equal(order, epoch_order(50, 7, 4, weights))
    counts = np.bincount(order, minlength=50)
    expected = 50 * weights
    assert np.all(counts >= np.floor(expected)) and np.all(counts <= np.ceil(expected))
    assert not np.array_equal(order, epoch_order(50, 8, 4, weights))  # a new epoch
    # Steps are a pure function of the step across epoch boundaries.
    steps = [batch_indices(50, 16, s, 4, weights) for s in range(8)]
    assert np.array_equal(
        np.concatenate(steps)[:100],
        np.concatenate([epoch_order(50, 0, 4, weights), epoch_order(50, 1, 4, weights)]),
    )


def test_oversampled_batches_resume_and_split_over_ranks(synthetic, capsys):
    samples = indices_only(SampleSet(synthetic, "train"))
    one = Prefetcher(samples, 8, seed=5, oversample=1.0)
    again = Prefetcher(samples, 8, seed=5, oversample=1.0)
    ranks = [Prefetcher(samples, 8, seed=5, rank=r, world=2, oversample=1.0) for r in (0, 1)]
    try:
        straight = [one.get(s)["k"] for s in range(6)]
        assert np.array_equal(again.get(4)["k"], straight[4])  # a resume at step 4
        for step in (0, 4):
            halves = [r.get(step)["k"] for r in ranks]
            assert np.array_equal(np.concatenate(halves), straight[step])
        # The weights reach the batches: cartwheel rows come up far more than their share.
        clip = clips_of(samples)
        drawn = np.concatenate([one.get(s)["k"] for s in range(200)])
        assert np.mean(clip[drawn] == 1) > 2 * WHEEL_FRAMES / (WALK_FRAMES + WHEEL_FRAMES)
    finally:
        for p in (one, again, *ranks):
            p.close()
    # The weights are announced once per split (the first prefetcher), by rank 0 only.
    lines = [line for line in capsys.readouterr().err.splitlines() if "rarest tenth" in line]
    assert len(lines) == 1 and lines[0].startswith("rigspace train: --oversample 1:")


@pytest.mark.parametrize("value", [-0.5, math.nan, math.inf])
def test_invalid_values_name_the_flag(value, synthetic):
    with pytest.raises(ConfigError, match="--oversample") as info:
        preset("tiny", oversample=value)
    assert "finite number >= 0" in info.value.fix
    with pytest.raises(ConfigError, match="--oversample"):
        TrainConfig.from_json({**preset("tiny").to_json(), "oversample": value})
    with pytest.raises(ConfigError, match="--oversample"):
        Prefetcher(indices_only(SampleSet(synthetic, "train")), 4, 0, oversample=value)


def test_the_flag_is_on_rigspace_train_and_checked_before_any_work(tmp_path):
    parser = argparse.ArgumentParser()
    cli.add_train_arguments(parser)
    args = parser.parse_args(["ds", "--out", str(tmp_path / "m"), "--oversample", "1.5"])
    assert args.oversample == 1.5
    assert preset("small").oversample == 0.0 and "oversample" in preset("small").to_json()
    args = parser.parse_args(["ds", "--out", str(tmp_path / "m"), "--oversample", "nan"])
    with pytest.raises(ConfigError, match="--oversample is nan"):
        cli.run_train(args)
    assert not (tmp_path / "m").exists()


def test_datasets_without_the_pose_columns_and_shards_are_refused(tmp_path, tiny_dataset):
    old = write_dataset(tmp_path / "old", drop=("camera_to_world",))
    samples = SampleSet(old, "train")
    with pytest.raises(ds.DatasetError, match="no camera_to_world column") as info:
        prefetcher(samples, 4, seed=0, oversample=1.0)
    assert "--oversample 0" in info.value.fix
    prefetcher(samples, 4, seed=0).close()  # uniform sampling needs no pose columns
    pack(tiny_dataset, tmp_path / "sh", samples_per_shard=16)
    shards = ShardSet(tmp_path / "sh", "train")
    try:
        with pytest.raises(ds.DatasetError, match="--oversample 1 needs a dataset folder") as info:
            prefetcher(shards, 4, seed=0, oversample=1.0)
        assert "--oversample 0" in info.value.fix
    finally:
        shards.close()


def test_a_tiny_oversampled_run_trains_and_exports(tmp_path, tiny_dataset, capfd):
    pytest.importorskip("torch", reason="training needs the train extra (torch)")
    from rigspace.sdk.model import BundleModel
    from rigspace.train import loop
    from rigspace.train.export import export_bundle

    config = replace(preset("tiny"), oversample=1.0, steps_per_level=8, eval_every=8)
    result = loop.train(tiny_dataset, tmp_path / "run", config, progress=False)
    assert result.stopped == "done" and math.isfinite(result.last_loss)
    assert "--oversample 1: the rarest tenth" in capfd.readouterr().err
    run = json.loads((tmp_path / "run" / loop.RUN_FILE).read_text())
    assert run["config"]["oversample"] == 1.0
    export_bundle(tmp_path / "run", tmp_path / "bundle", int8=False)
    model = BundleModel(tmp_path / "bundle", "fp32")
    rig = SampleSet(tiny_dataset, "train").rig[:1]
    maps = model.predict(rig, 32)
    assert maps and all(np.isfinite(m).all() for m in maps.values())

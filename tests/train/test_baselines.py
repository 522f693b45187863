"""Baselines: nearest captured view and two-view interpolation, on synthetic cameras and CesiumMan."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from rigspace.capture.dataset import PARAMS_FILE, npz_bytes
from rigspace.capture.ring import SPLITS
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import Maps, empty_maps
from rigspace.train import baselines as bl
from rigspace.train.evaluate import DatasetError, DatasetTable, evaluate
from tests.train.conftest import VIEWS, captured_dataset

ROTATION_TOLERANCE = 1e-6  # float32 normals through a float64 rotation
STEP = 360.0 / VIEWS
ANGLE_TOLERANCE = 1e-6  # degrees, float64 camera matrices


@pytest.fixture(scope="session")
def table(tmp_path_factory) -> DatasetTable:
    return DatasetTable(captured_dataset(tmp_path_factory))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def pose(rotation: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = (1.0, 2.0, 3.0)  # translation plays no part in a normal's rotation
    return m


def test_rotate_normals_expresses_world_normals_in_the_target_camera():
    rng = np.random.default_rng(0)
    r_source, r_target = random_rotation(rng), random_rotation(rng)
    world = rng.standard_normal((4, 5, 3))
    world /= np.linalg.norm(world, axis=-1, keepdims=True)
    world[0, 0] = 0.0  # an empty pixel
    in_source = (world @ r_source).astype(np.float32)  # R^T n as row vectors: n^T R
    rotated = bl.rotate_normals(in_source, pose(r_source), pose(r_target))
    assert rotated.dtype == np.float32
    np.testing.assert_allclose(rotated, world @ r_target, atol=ROTATION_TOLERANCE)
    assert np.all(rotated[0, 0] == 0.0)
    same = bl.rotate_normals(in_source, pose(r_source), pose(r_source))
    np.testing.assert_allclose(same, in_source, atol=ROTATION_TOLERANCE)


def test_rotate_normals_between_ring_cameras():
    # Two cameras looking at the origin from azimuth 0 (+Z) and 90 (+X): the surface
    # facing +Z is seen head-on by the first, and edge-on from the left by the second.
    lens = {"width": 8, "height": 8, "focal_length": 35.0, "horizontal_aperture": 20.955}
    front = Camera.look_at((0, 0, 3), (0, 0, 0), **lens).camera_to_world
    side = Camera.look_at((3, 0, 0), (0, 0, 0), **lens).camera_to_world
    facing = np.array([[[0.0, 0.0, 1.0]]], np.float32)  # camera space of the front camera
    np.testing.assert_allclose(
        bl.rotate_normals(facing, front, side)[0, 0], (-1, 0, 0), atol=ROTATION_TOLERANCE
    )
    directions = bl.view_directions(np.stack([front, side]))
    assert np.degrees(bl.angles_between(directions[0], directions)) == pytest.approx([0, 90])


def test_blend_rules_for_depth_and_normals():
    a, b = empty_maps(1, 3), empty_maps(1, 3)
    a.depth[0] = (1.0, 2.0, np.inf)
    b.depth[0] = (3.0, np.inf, np.inf)
    a.mask[0], b.mask[0] = (1, 1, 0), (1, 0, 0)
    a.albedo[0] = 0.4
    a.normal[0, :2] = (1, 0, 0)
    b.normal[0, 0] = (0, 1, 0)
    out = bl.blend([a, b], np.array([0.75, 0.25]))
    np.testing.assert_allclose(out.depth, [[0.75 * 1 + 0.25 * 3, 2.0, np.inf]])
    np.testing.assert_allclose(out.mask, [[1.0, 0.75, 0.0]])
    np.testing.assert_allclose(out.albedo[0, :, 0], [0.3, 0.3, 0.3])
    n = np.array([0.75, 0.25, 0]) / np.hypot(0.75, 0.25)
    np.testing.assert_allclose(out.normal[0], [n, (1, 0, 0), (0, 0, 0)], atol=1e-6)


def azimuth_gap(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_nearest_view_is_a_training_view_of_the_same_frame(table):
    nearest = bl.BaselinePredictor(table, "nearest")
    clip, time, split = table.column("clip"), table.column("time"), table.column("split")
    azimuth = table.column("azimuth")
    for index in table.indices("heldout-views"):
        rows, angles, weights = nearest.neighbours(int(index))
        (row,) = rows
        assert SPLITS[split[row]] == "train"
        assert (clip[row], time[row]) == (clip[index], time[index])
        assert azimuth_gap(azimuth[row], azimuth[index]) == pytest.approx(STEP / 2)
        assert angles[0] == pytest.approx(STEP / 2, abs=ANGLE_TOLERANCE)
        assert weights.tolist() == [1.0]
    index = int(table.indices("heldout-views")[3])
    (predicted,) = nearest.predict(np.array([index]))
    expected = table.maps(int(nearest.neighbours(index)[0][0]))
    for name in ("albedo", "normal", "depth", "mask"):  # used as is
        np.testing.assert_array_equal(getattr(predicted, name), getattr(expected, name))


def test_a_training_view_is_not_its_own_neighbour(table):
    """On the train split the nearest view of a sample's frame was the sample itself: the
    baseline scored inf dB and measured nothing (issue 22). It takes the nearest other view."""
    nearest = bl.BaselinePredictor(table, "nearest")
    for index in table.indices("train")[:6]:
        rows, angles, _ = nearest.neighbours(int(index))
        assert int(rows[0]) != int(index) and angles[0] > 0
    report = evaluate(nearest, table, "train", limit=3)
    assert np.isfinite(report["metrics"]["albedo_psnr"]["mean"])


def test_linear_blends_the_two_neighbours_half_and_half_at_midpoints(table):
    linear = bl.BaselinePredictor(table, "linear")
    azimuth = table.column("azimuth")
    for index in table.indices("heldout-views"):
        rows, angles, weights = linear.neighbours(int(index))
        assert len(rows) == 2 and rows[0] < rows[1]  # an exact tie breaks on the row index
        np.testing.assert_allclose(weights, [0.5, 0.5])
        np.testing.assert_allclose(angles, [STEP / 2] * 2, atol=ANGLE_TOLERANCE)
        gaps = sorted((azimuth[rows] - azimuth[index] + 180.0) % 360.0 - 180.0)
        assert gaps == pytest.approx([-STEP / 2, STEP / 2])  # one on each side


def test_linear_is_at_least_as_good_as_nearest(table):
    reports = {
        kind: evaluate(bl.BaselinePredictor(table, kind), table, "heldout-views")
        for kind in bl.KINDS
    }
    means = {k: {m: v["mean"] for m, v in r["metrics"].items()} for k, r in reports.items()}
    # Measured on this dataset: IoU 0.69 vs 0.76, PSNR 16.2 vs 18.6 dB.
    assert means["linear"]["mask_iou"] >= means["nearest"]["mask_iou"]
    assert means["linear"]["albedo_psnr"] >= means["nearest"]["albedo_psnr"]
    assert 0.3 < means["nearest"]["mask_iou"] < 1.0  # a real error, not a copy of the truth


def test_footprint_is_every_training_sample_at_stored_precision(table):
    footprint = bl.BaselinePredictor(table, "linear").footprint()
    # R,G,B,A and N.X,N.Y,N.Z in half (2 bytes), Z in float (4 bytes): 18 bytes a pixel.
    assert bl.bytes_per_pixel() == 7 * 2 + 4
    assert footprint["samples"] == VIEWS * 4
    assert footprint["bytes"] == VIEWS * 4 * 32 * 32 * 18
    assert 0 < footprint["disk_bytes"] < footprint["bytes"]  # zip compressed
    assert bl.BaselinePredictor(table, "nearest").footprint_bytes == footprint["bytes"]


def test_bad_baseline_inputs(table, tmp_path):
    with pytest.raises(DatasetError, match=r"Unknown baseline 'cubic'.*nearest, linear"):
        bl.BaselinePredictor(table, "cubic")
    # The last frame of the capture relabelled as a held-out clip: no training view of it.
    folder = tmp_path / "ds"
    shutil.copytree(table.folder, folder)
    with np.load(folder / PARAMS_FILE) as data:
        columns = {k: data[k] for k in data.files}
    last = columns["time"] == columns["time"].max()
    columns["clip"][last] = 1
    columns["split"][last] = SPLITS.index("heldout-clips")
    (folder / PARAMS_FILE).write_bytes(npz_bytes(columns))
    relabelled = DatasetTable(folder)
    with pytest.raises(DatasetError, match=r"no training view of its frame.*heldout-views"):
        evaluate(bl.BaselinePredictor(relabelled, "linear"), relabelled, "heldout-clips")


def test_baseline_predictions_are_maps(table):
    index = int(table.indices("heldout-views")[0])
    (maps,) = bl.BaselinePredictor(table.folder, "linear").predict(np.array([index]))
    assert isinstance(maps, Maps) and maps.albedo.dtype == np.float32
    length = np.linalg.norm(maps.normal, axis=-1)
    assert np.allclose(length[length > 0], 1.0, atol=ROTATION_TOLERANCE)
    assert np.all(np.isinf(maps.depth[maps.mask == 0]))

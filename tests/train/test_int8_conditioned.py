"""int8 for pose-conditioned bundles: export, the export's check, the runtime, re-quantising.

A conditioned bundle's graphs read joints2d besides rig (the trunk) or features (the
branches above 8x8); every int8 step feeds it from the rows' own rig by
rigspace.sdk.conditioning, as training and the runtime do.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import warnings

import numpy as np
import pytest

pytest.importorskip("torch", reason="training and exporting need the train extra (torch)")

from rigspace.sdk.model import BundleModel
from rigspace.train.config import preset
from rigspace.train.export import check_rows, export_bundle
from rigspace.train.int8check import check_int8, drift, session, verdict
from rigspace.train.loop import train
from rigspace.train.quantize import pose_nodes, recheck_bundle, requantize_bundle

PREDICT_TOLERANCE = {
    "albedo": 0.015,
    "alpha": 0.015,
    "mask": 0.015,
    "depth": 0.06,
    "normal": 0.06,
}
"""Mean |int8 - fp32| per output of BundleModel.predict (int8 trunk and branches, joints2d
fed by the runtime) on the fixed check rows; depth and normals weighted by the fp32
coverage (undefined outside it). Measured on the tiny bones2d "add" model: albedo, alpha,
mask <= 0.006; depth <= 0.017, normals <= 0.009."""
RECORDED = 1e-5
"""The export's recorded drift against the same drift recomputed through the runtime's
feeds (one-thread onnxruntime on the same rows: equal up to float printing)."""


@pytest.fixture(scope="module")
def run(tmp_path_factory, tiny_dataset):
    """A tiny bones2d run whose maps are 1x1-projected and added, computed up to 16x16."""
    folder = tmp_path_factory.mktemp("int8-conditioned") / "training"
    config = preset("tiny", conditioning="bones2d", conditioning_mode="add", conditioning_top=16)
    assert train(tiny_dataset, folder, config, progress=False).stopped == "done"
    return folder


@pytest.fixture(scope="module")
def bundle(run):
    out = run.parent / "bundle"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        export_bundle(run, out)
    assert not [w for w in caught if "int8" in str(w.message)], [str(w.message) for w in caught]
    return out


def _manifest(bundle):
    return json.loads((bundle / "manifest.json").read_text())


def _inputs(folder, name):
    return [i.name for i in session(folder / name).get_inputs()]


def test_the_export_writes_int8_graphs_for_the_trunk_and_every_branch(bundle):
    manifest = _manifest(bundle)
    assert manifest["conditioning"]["mode"] == "add"
    trunk = manifest["trunk"]
    assert trunk["int8"]["trunk"] == "trunk.int8.onnx"
    assert _inputs(bundle, "trunk.int8.onnx") == ["rig", "joints2d"]
    assert [level["resolution"] for level in manifest["levels"]] == [8, 16, 32]
    for level in manifest["levels"]:
        assert sorted(level["int8"]) == ["albedo", "geometry"]
        for branch, name in level["int8"].items():
            # The int8 graph reads what its fp32 graph reads: no joints2d at 8x8.
            expected = ["features"] + (["joints2d"] if level["resolution"] > 8 else [])
            assert _inputs(bundle, level["graphs"][branch]) == expected
            assert _inputs(bundle, name) == expected
            assert name in manifest["files"]


def test_the_int8_check_records_drift_per_map_within_the_tolerances(bundle, tiny_dataset):
    """Each graph's recorded drift passes TOLERANCES, and equals the drift recomputed with the
    runtime's own joints2d on the same fixed check rows (so the check fed the real poses)."""
    check = _manifest(bundle)["int8_check"]
    rows, split = check_rows(tiny_dataset)
    assert (check["split"], check["samples"]) == (split, len(rows))
    assert len(check["graphs"]) == 7
    for name, result in check["graphs"].items():
        assert result["ok"] and verdict(result["metrics"], True) == [], (name, result)
    fp32, int8 = BundleModel(bundle, threads=1), BundleModel(bundle, "int8", threads=1)
    assert int8.int8_fallbacks == {}
    joints2d = fp32.joints2d(rows)
    features = fp32.features(rows, joints2d)
    judged = 0
    for resolution in fp32.resolutions:
        for branch in ("albedo", "geometry"):
            reference = fp32.branch(features, branch, resolution, joints2d)
            quantised = int8.branch(features, branch, resolution, joints2d)
            recorded = check["graphs"][int8.levels[resolution][branch]]["metrics"]
            for key, value in drift(reference, quantised).items():
                if value is None:  # too few covered pixels to judge (int8check)
                    assert recorded[key] is None, (resolution, branch, key)
                    continue
                judged += 1
                assert recorded[key] == pytest.approx(value, rel=RECORDED, abs=RECORDED)
    assert judged >= 6  # albedo PSNR and alpha IoU at 16 and 32 at least


def test_the_runtime_runs_the_int8_graphs_close_to_fp32(bundle, tiny_dataset):
    rows, _ = check_rows(tiny_dataset)
    fp32, int8 = BundleModel(bundle, threads=1), BundleModel(bundle, "int8", threads=1)
    assert int8._trunk_file == "trunk.int8.onnx"
    for resolution in fp32.resolutions:
        reference, quantised = fp32.predict(rows, resolution), int8.predict(rows, resolution)
        weight = reference["mask"]
        for name, value in reference.items():
            assert np.isfinite(quantised[name]).all(), (resolution, name)
            w = weight if name in ("depth", "normal") else np.ones_like(weight)
            full = w * np.ones_like(value)
            error = float(np.sum(np.abs(quantised[name] - value) * w) / np.sum(full))
            assert error <= PREDICT_TOLERANCE[name], (resolution, name, error)


def test_the_pose_maps_stay_float_in_the_int8_graphs(bundle):
    """The maps' computation from joints2d is not quantised (train.quantize.pose_nodes)."""
    import onnx

    kept = pose_nodes(bundle / "albedo_32.onnx")
    graph = onnx.load(str(bundle / "albedo_32.int8.onnx")).graph
    producer = {o: n.op_type for n in graph.node for o in n.output}
    exp = [n for n in graph.node if n.op_type == "Exp"]
    assert exp and all(n.name in kept for n in exp)
    assert all(producer.get(i) != "DequantizeLinear" for n in exp for i in n.input)
    assert pose_nodes(bundle / "albedo_8.onnx") == []  # no joints2d input


def test_the_check_names_a_missing_joints2d(bundle, tiny_dataset):
    manifest = _manifest(bundle)
    rows, _ = check_rows(tiny_dataset)
    trunk = {"fp32": "trunk.onnx", "int8": "trunk.int8.onnx"}
    with pytest.raises(ValueError, match="joints2d"):
        check_int8(bundle, trunk, manifest["levels"], rows, timing=False)


@pytest.mark.slow
def test_requantize_gives_an_fp32_only_conditioned_bundle_its_int8_graphs(
    run, tiny_dataset, tmp_path
):
    """`python -m rigspace.apps.quantize` on a conditioned bundle exported without int8
    (as before int8 was offered for one): the skeleton comes from the manifest."""
    out = tmp_path / "bundle"
    export_bundle(run, out, int8=False)
    fp32_bytes = {p.name: p.read_bytes() for p in out.glob("*.onnx")}
    check = requantize_bundle(out, tiny_dataset, rows=32)
    manifest = _manifest(out)
    assert manifest["trunk"]["int8"]["trunk"] == "trunk.int8.onnx"
    assert all(sorted(level["int8"]) == ["albedo", "geometry"] for level in manifest["levels"])
    assert len(check["graphs"]) == 7 and all(g["ok"] for g in check["graphs"].values())
    assert sorted(int(r) for r in check["levels"]) == [8, 16, 32]
    assert manifest["int8_check"]["offered_levels"] == check["offered_levels"]
    for name, record in manifest["files"].items():
        data = (out / name).read_bytes()
        assert record == {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}, name
    assert all((out / name).read_bytes() == data for name, data in fp32_bytes.items())
    rows, _ = check_rows(tiny_dataset)
    assert np.isfinite(BundleModel(out, "int8").predict(rows[:2], 32)["albedo"]).all()


def test_recheck_of_a_conditioned_bundle(bundle, tiny_dataset, tmp_path):
    copy = tmp_path / "bundle"
    shutil.copytree(bundle, copy)
    int8_bytes = {p.name: p.read_bytes() for p in copy.glob("*.int8.onnx")}
    check = recheck_bundle(copy, tiny_dataset, limit=6)
    assert all(g["ok"] for g in check["graphs"].values())
    for resolution, entry in check["levels"].items():
        assert entry["samples"] == 6, resolution
        assert entry["int8"]["alpha_iou"] == pytest.approx(entry["fp32"]["alpha_iou"], abs=0.05)
    assert BundleModel(copy, "int8").int8_offered == sorted(check["offered_levels"])
    assert all((copy / name).read_bytes() == data for name, data in int8_bytes.items())

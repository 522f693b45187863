"""The torch predictor against the exported graphs; the weights the export writes; refusals;
and its modules on the meta device (a tensor made without `device=` fails there as on CUDA)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rigspace.sdk.bundle import BundleError, read_manifest  # noqa: E402
from rigspace.sdk.model import BundleModel  # noqa: E402
from rigspace.sdk.predictors import GraphSet, PredictorUnavailable  # noqa: E402
from rigspace.sdk.weights import WeightsError  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402
from rigspace.train.torch_predictor import CHECK_TOLERANCE, WEIGHTS, TorchRunner  # noqa: E402
from tests.conftest import REPO  # noqa: E402

SAMPLE = REPO / "samples" / "models" / "sample"
AGREE = 1e-4
"""|torch - onnxruntime| on the CPU in fp32: float reassociation only (measured 3e-5)."""


def rigs(model: BundleModel, n: int = 3) -> np.ndarray:
    rng = np.random.default_rng(1)
    rest = np.tile(np.array([1, 0, 0, 0, 1, 0], np.float32), (n, len(model.joints)))
    return rest + rng.normal(0, 0.1, rest.shape).astype(np.float32)


def copy_sample(tmp_path: Path) -> Path:
    out = tmp_path / "bundle"
    shutil.copytree(SAMPLE, out, ignore=shutil.ignore_patterns("training"))
    return out


def edit_manifest(bundle: Path, edit) -> None:
    path = bundle / "manifest.json"
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest))


def test_the_torch_predictor_matches_every_graph_of_the_sample_model():
    onnx = BundleModel(SAMPLE, predictor="onnxruntime")
    ours = BundleModel(SAMPLE, predictor="torch", device="cpu")
    assert ours.runner.description == "torch cpu fp32"
    rig = rigs(onnx)
    for level in onnx.resolutions:
        a, b = onnx.predict(rig, level), ours.predict(rig, level)
        assert sorted(a) == sorted(b)  # chart and uv (texture head), alpha, depth, ...
        for name in a:
            assert b[name].dtype == np.float32 and b[name].shape == a[name].shape
            assert np.abs(a[name] - b[name]).max() < AGREE, (level, name)


def test_the_sample_bundle_records_its_weights_check():
    check = read_manifest(SAMPLE).torch["check"]
    assert check["ok"] and check["max_abs"] <= CHECK_TOLERANCE
    assert set(check["graphs"]) == {
        f for level in read_manifest(SAMPLE).levels for f in level.files.fp32.values()
    } | {"trunk.onnx"}


def test_the_export_writes_weights_that_pass_its_check(tiny_run, tmp_path):
    out = tmp_path / "bundle"
    manifest = export_bundle(tiny_run, out, int8=False)
    assert (out / WEIGHTS).is_file() and WEIGHTS in manifest["files"]
    check = manifest["torch"]["check"]
    assert check["ok"] and check["max_abs"] < AGREE, check
    onnx, ours = BundleModel(out, predictor="onnxruntime"), BundleModel(out, predictor="torch")
    rig = rigs(onnx)
    level = max(onnx.resolutions)
    a, b = onnx.predict(rig, level), ours.predict(rig, level)
    assert max(float(np.abs(a[k] - b[k]).max()) for k in a) < AGREE


def test_int8_is_onnxruntime_s(tmp_path):
    with pytest.raises(PredictorUnavailable, match="int8"):
        BundleModel(SAMPLE, "int8", predictor="torch")
    assert BundleModel(SAMPLE, "int8").runner.description.startswith("onnxruntime")


def test_a_bundle_without_weights_is_refused_by_torch_and_auto_passes_over_it(tmp_path):
    bundle = copy_sample(tmp_path)
    edit_manifest(bundle, lambda m: m.pop("torch"))
    (bundle / WEIGHTS).unlink(missing_ok=True)  # the sample reads its weights from its graphs
    with pytest.raises(PredictorUnavailable) as info:
        BundleModel(bundle, predictor="torch")
    assert "no network weights" in str(info.value) and "--resume" in str(info.value)
    assert BundleModel(bundle).runner.description == "onnxruntime CPU (fp32)"


def test_weights_that_failed_the_export_check_are_refused(tmp_path):
    bundle = copy_sample(tmp_path)
    edit_manifest(bundle, lambda m: m["torch"]["check"].update(ok=False, max_abs=0.5))
    with pytest.raises(PredictorUnavailable, match="differ from its graphs"):
        BundleModel(bundle, predictor="torch")


def test_damaged_or_mismatched_weights_name_the_file(tmp_path, tiny_run):
    bundle = tmp_path / "bundle"
    export_bundle(tiny_run, bundle, int8=False)  # an export writes its weights file
    data = (bundle / WEIGHTS).read_bytes()
    (bundle / WEIGHTS).write_bytes(data[: len(data) // 2])
    with pytest.raises(WeightsError, match=WEIGHTS):
        BundleModel(bundle, predictor="torch")
    (bundle / WEIGHTS).write_bytes(data)
    edit_manifest(bundle, lambda m: m["torch"].update(joints=m["torch"]["joints"] - 1))
    with pytest.raises(BundleError, match="do not fit the network"):
        BundleModel(bundle, predictor="torch")


@pytest.mark.parametrize("half", [False, True])
def test_every_graph_module_runs_on_the_meta_device(half):
    manifest = read_manifest(SAMPLE)
    graphs = {"trunk.onnx": ("trunk", 8)}
    for level in manifest.levels:
        graphs |= {f: (b, level.resolution) for b, f in level.files.fp32.items()}
    runner = TorchRunner(
        GraphSet(manifest, "fp32", 0, graphs), device="meta", half=half, cuda_graphs=False
    )
    dtype = torch.float16 if half else torch.float32
    joints = len(manifest.joints)
    features = runner.forward("trunk.onnx", {
        "rig": torch.zeros(2, joints * 6, device="meta", dtype=dtype),
        "joints2d": torch.zeros(2, joints * 2, device="meta", dtype=dtype),
    })[0]  # fmt: skip
    assert features.device.type == "meta" and features.dtype == dtype
    for graph in graphs:
        if graph == "trunk.onnx":
            continue
        given = {"features": features, "joints2d": torch.zeros(2, joints * 2, device="meta")}
        for out in runner.forward(graph, {k: given[k] for k in runner.inputs(graph)}):
            assert out.device.type == "meta", graph


def test_the_weights_read_back_from_the_graphs_are_the_exported_ones(tmp_path, tiny_run):
    """A bundle needs no second copy of its weights: the fp32 graphs hold every parameter (the
    heads as their per-output slices); the sample bundle ships none."""
    from rigspace.sdk.weights import read_safetensors
    from rigspace.train.torch_predictor import weights_from_graphs

    bundle = tmp_path / "bundle"
    export_bundle(tiny_run, bundle, int8=False)
    exported, _ = read_safetensors(bundle / WEIGHTS)
    derived = weights_from_graphs(bundle, read_manifest(bundle))
    assert sorted(derived) == sorted(exported)
    for name, value in exported.items():
        np.testing.assert_array_equal(derived[name], value, err_msg=name)
    assert not (SAMPLE / WEIGHTS).exists() and "file" not in read_manifest(SAMPLE).torch

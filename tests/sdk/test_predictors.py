"""Predictors as a plugin kind: discovery, `auto`, --device, refusals (no torch needed)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from rigspace.sdk.bundle import BundleError
from rigspace.sdk.errors import PluginError, RigspaceError
from rigspace.sdk.model import BundleModel
from rigspace.sdk.plugins import discover
from rigspace.sdk.predictors import (
    PREDICTORS,
    PredictorUnavailable,
    available,
    device_spec,
    nvidia_driver,
)
from tests.conftest import REPO

SAMPLE = REPO / "samples" / "models" / "sample"


def test_the_installed_predictors_are_found():
    found = discover(PREDICTORS)
    assert {"onnxruntime", "onnxruntime-cuda", "torch"} <= set(found.specs), found.failed
    assert available()[0] in found.specs
    assert "onnxruntime" in available()


def test_auto_on_a_machine_without_a_gpu_runs_onnxruntime_and_imports_no_torch():
    # A machine without a GPU, wherever the test runs: no NVIDIA driver, a CPU onnxruntime.
    code = (
        "import sys; import rigspace.sdk.predictors as p; "
        "import rigspace.train.torch_predictor as t; "
        "p.nvidia_driver = t.nvidia_driver = lambda: False; "
        "p._ort_providers = lambda: ['CPUExecutionProvider']; "
        "from rigspace.sdk.model import BundleModel; "
        f"m = BundleModel({str(SAMPLE)!r}); m.preload(); "
        "print(m.runner.description); print('torch' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split("\n")
    assert out[:2] == ["onnxruntime CPU (fp32)", "False"]


def test_an_unknown_predictor_names_the_installed_ones():
    with pytest.raises(PluginError) as info:
        BundleModel(SAMPLE, predictor="tensorflow")
    assert "onnxruntime" in str(info.value) and "tensorflow" in str(info.value)


def test_a_gpu_device_without_a_gpu_predictor_says_why_for_each():
    with pytest.raises(RigspaceError) as info:
        BundleModel(SAMPLE, device="cuda:99")  # a GPU no machine has
    text = str(info.value)
    assert "onnxruntime: onnxruntime (CPU) does not run on cuda:99" in text
    if "torch" in available() and not nvidia_driver():
        assert "torch: torch sees no GPU for cuda:99" in text


def test_onnxruntime_refuses_a_gpu_and_onnxruntime_cuda_the_cpu():
    with pytest.raises(PredictorUnavailable, match="does not run on cuda"):
        BundleModel(SAMPLE, predictor="onnxruntime", device="cuda")
    if "onnxruntime-cuda" not in available():
        with pytest.raises(PredictorUnavailable, match="cannot run on this machine"):
            BundleModel(SAMPLE, predictor="onnxruntime-cuda")


def test_device_values_are_checked_before_anything_runs():
    import argparse

    assert device_spec(" CUDA:1 ") == "cuda:1"
    for bad in ("gpu", "cuda:x", "cuda:"):
        with pytest.raises(argparse.ArgumentTypeError):
            device_spec(bad)


def test_a_missing_graph_is_reported_when_the_bundle_loads(tmp_path):
    import shutil

    bundle = tmp_path / "bundle"
    shutil.copytree(SAMPLE, bundle, ignore=shutil.ignore_patterns("training"))
    (bundle / "albedo_32.onnx").unlink()
    model = BundleModel(bundle, predictor="onnxruntime")
    with pytest.raises(BundleError, match=r"albedo_32\.onnx is missing"):
        model.preload()
    rig = np.zeros((1, len(model.joints) * 6), np.float32)
    rig[:, 0] = rig[:, 4] = 1
    assert model.predict(rig, 16)["albedo"].shape == (1, 3, 16, 16)  # other levels still run

"""`--device`: where training runs (train.distributed.resolve_device), refused by name when the
GPU is not there, and the CPU run it picks on a machine without one."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from rigspace.sdk.cli import main  # noqa: E402
from rigspace.sdk.errors import RigspaceError  # noqa: E402
from rigspace.train import distributed, loop  # noqa: E402
from rigspace.train.config import preset  # noqa: E402

NO_GPU = not torch.cuda.is_available()


def test_device_names_resolve():
    assert distributed.resolve_device(None) == torch.device("cpu")
    assert distributed.resolve_device(" CPU ") == torch.device("cpu")
    expected = torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
    assert distributed.resolve_device("auto") == expected
    for bad in ("gpu", "cuda:x", "cuda:-1", "mps"):
        with pytest.raises(RigspaceError, match="Unknown device") as raised:
            distributed.resolve_device(bad)
        assert "--device auto, cpu, cuda or cuda:N" in raised.value.fix


MISSING = "cuda:99"
"""A GPU no machine running these tests has: the refusal is tested with or without GPUs."""


def test_a_gpu_that_is_not_there_is_refused_before_anything_is_written(
    tiny_dataset, tmp_path, capsys
):
    with pytest.raises(RigspaceError, match="not available") as raised:
        distributed.resolve_device(MISSING)
    assert "--device cpu" in raised.value.fix
    out = tmp_path / "model"
    code = main(["train", str(tiny_dataset), "--out", str(out), "--preset", "tiny",
                 "--steps", "2", "--device", MISSING])  # fmt: skip
    assert code != 0 and f"Device '{MISSING}' is not available" in capsys.readouterr().err
    assert not out.exists()


def test_auto_trains_on_the_cpu_without_a_gpu_and_bf16_autocasts_there(tiny_dataset, tmp_path):
    config = preset("tiny", steps_per_level=2, bf16=True)
    result = loop.train(tiny_dataset, tmp_path / "run", config, progress=False, device="auto")
    assert result.step == config.total_steps() and np.isfinite(result.last_loss)
    if NO_GPU:
        assert distributed.context().device == torch.device("cpu")
    run = json.loads((tmp_path / "run" / loop.RUN_FILE).read_text())
    assert run["config"]["bf16"] is True
    distributed.context("cpu")  # later tests in this process: the CPU, as by default


def test_the_ablation_passes_its_device_to_every_variant(tiny_dataset, tmp_path, capsys):
    from rigspace.apps import ablation

    out = tmp_path / "abl"
    code = ablation.main([str(tiny_dataset), "--out", str(out), "--variants", "paper",
                          "--steps-per-level", "1", "--device", MISSING])  # fmt: skip
    assert code != 0 and f"Device '{MISSING}' is not available" in capsys.readouterr().err
    assert not (out / "paper" / "run").exists()
    distributed.context("cpu")


def test_eval_and_the_curve_take_a_device_and_refuse_one_that_is_not_there(
    tiny_dataset, tmp_path, capsys
):
    from rigspace.apps import curve
    from rigspace.train.export import export_bundle

    run = tmp_path / "run"
    loop.train(tiny_dataset, run, preset("tiny"), progress=False)
    keep = tmp_path / "keep"
    keep.mkdir()
    (keep / "last.pt").write_bytes((run / loop.CHECKPOINT).read_bytes())
    args = [str(run), str(tiny_dataset), "--checkpoints", str(keep), "--limit", "2"]
    args += ["--out", str(tmp_path / "curve.png")]
    with pytest.raises(SystemExit, match=f"Device '{MISSING}' is not available"):
        curve.main([*args, "--device", MISSING])
    assert curve.main([*args, "--device", "cpu"]) == 0
    bundle = tmp_path / "bundle"
    export_bundle(run, bundle, int8=False)
    evaluate = ["eval", str(bundle), str(tiny_dataset), "--limit", "2", "--no-baselines"]
    assert main([*evaluate, "--device", "cpu"]) == 0
    assert "the model runs on onnxruntime CPU (fp32)" in capsys.readouterr().err
    assert main([*evaluate, "--device", MISSING]) != 0
    assert f"does not run on {MISSING}" in capsys.readouterr().err

"""Rig2Image, its progressive schedule, the training loop, export parity, and bundle errors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from rigspace.sdk.bundle import BundleError  # noqa: E402
from rigspace.sdk.model import BundleModel  # noqa: E402
from rigspace.train import loop  # noqa: E402
from rigspace.train.config import PRESETS, TrainConfig, preset  # noqa: E402
from rigspace.train.data import DatasetError, SampleSet, batch_indices  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402
from rigspace.train.network import Rig2Image, Shape, albedo_maps, geometry_maps  # noqa: E402

FP32_PARITY = 1e-5
"""onnxruntime fp32 against torch: float32 reassociation differences only."""
TINY = preset("tiny")


def test_shapes_at_every_level():
    model = Rig2Image(Shape(19), TINY)
    with torch.no_grad():
        heads = model(torch.randn(3, 19 * 6), 32)
    assert [h.shape[-1] for h in heads["albedo"]] == [8, 16, 32]
    assert [tuple(h.shape[:2]) for h in heads["geometry"]] == [(3, 5)] * 3
    _depth, normal, mask = geometry_maps(heads["geometry"][-1])
    assert torch.allclose(normal.norm(dim=1), torch.ones(3, 32, 32), atol=1e-5)
    assert 0 <= float(mask.min()) and float(mask.max()) <= 1
    albedo = albedo_maps(heads["albedo"][-1])
    assert 0 <= float(albedo.min()) and float(albedo.max()) <= 1
    # Asking for a lower resolution stops early: the runtime's level of detail.
    assert len(model(torch.randn(1, 19 * 6), 16)["albedo"]) == 2


def test_fade_in_schedule():
    config = replace(TINY, steps_per_level=20, fade_fraction=0.5, resolution=64)
    assert config.levels() == [16, 32, 64]
    at = {s: loop.schedule(config, s) for s in range(60)}
    assert [at[s].resolution for s in (0, 19, 20, 39, 40, 59)] == [16, 16, 32, 32, 64, 64]
    assert all(at[s].alpha == 1.0 for s in range(20))  # the first level has nothing to fade
    assert [at[s].alpha for s in (20, 25, 30, 35)] == [0.0, 0.5, 1.0, 1.0]
    alphas = [at[s].alpha for s in range(20, 31)]
    assert np.allclose(np.diff(alphas), 0.1)  # linear
    assert [s for s in range(60) if at[s].first_step_of_level] == [0, 20, 40]


def test_batches_are_a_pure_function_of_the_step():
    a = [batch_indices(10, 4, s, seed=3) for s in range(6)]
    b = [batch_indices(10, 4, s, seed=3) for s in range(6)]
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    epoch = np.concatenate(a)[:10]
    assert sorted(epoch.tolist()) == list(range(10))  # every sample once per epoch


def log(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]


def test_tiny_run_reduces_the_loss(tiny_run):
    losses = [r["loss"] for r in log(tiny_run) if r["resolution"] == 16]
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5])
    assert (tiny_run / "previews" / "level_32.png").is_file()
    run = json.loads((tiny_run / loop.RUN_FILE).read_text())
    assert run["config"] == TINY.to_json() and len(run["joints"]) == 19


def test_checkpoints_load_without_unpickling(tiny_run):
    state = torch.load(tiny_run / loop.CHECKPOINT, weights_only=True)
    assert state["step"] == TINY.total_steps() and "model" in state


def test_resume_continues_exactly(tmp_path, tiny_dataset):
    straight = loop.train(tiny_dataset, tmp_path / "a", TINY, progress=False)
    loop.train(tiny_dataset, tmp_path / "b", TINY, steps=25, progress=False)  # mid-fade
    resumed = loop.train(tiny_dataset, tmp_path / "b", TINY, resume=True, progress=False)
    assert resumed.step == straight.step
    a = torch.load(tmp_path / "a" / loop.CHECKPOINT, weights_only=True)["model"]
    b = torch.load(tmp_path / "b" / loop.CHECKPOINT, weights_only=True)["model"]
    for key in a:
        assert torch.allclose(a[key], b[key], atol=1e-6), key
    # The log's training clock continues across the resume (quality against training time).
    records = [
        json.loads(line) for line in (tmp_path / "b" / "log.jsonl").read_text().split("\n")[:-1]
    ]
    seconds = [r["seconds"] for r in records if "loss" in r]
    assert len(seconds) == straight.step and seconds[25] >= seconds[24] > 0
    assert seconds == sorted(seconds)


def _flushed() -> bool:
    return (torch.tensor([1e-39], dtype=torch.float32) * 1.0).item() == 0.0


def test_training_flushes_denormals_and_gives_the_setting_back(tmp_path, tiny_dataset, monkeypatch):
    seen = []
    forward = loop.forward_loss

    def recording(*args, **kwargs):
        seen.append(_flushed())
        return forward(*args, **kwargs)

    monkeypatch.setattr(loop, "forward_loss", recording)
    assert loop.flush_denormal(False) in (True, False) and not _flushed()
    loop.train(tiny_dataset, tmp_path / "run", TINY, steps=3, progress=False)
    assert seen == [True, True, True] and not _flushed()
    with pytest.raises(loop.TrainingError):  # an early refusal gives it back too
        loop.train(tiny_dataset, tmp_path / "run", TINY, steps=3, progress=False)
    assert not _flushed()


def test_a_nan_loss_stops_with_the_step_and_the_checkpoint(tmp_path, tiny_dataset, monkeypatch):
    from rigspace.train import step

    real = step.total_loss
    calls = {"n": 0}

    def poisoned(*args, **kwargs):
        loss, terms = real(*args, **kwargs)
        calls["n"] += 1
        return (loss * float("nan") if calls["n"] == 26 else loss), terms

    monkeypatch.setattr(step, "total_loss", poisoned)
    config = replace(TINY, checkpoint_every=10)
    with pytest.raises(
        loop.TrainingError, match=r"step 25 .*Last good checkpoint: .*checkpoint\.pt"
    ):
        loop.train(tiny_dataset, tmp_path / "run", config, progress=False)
    saved = torch.load(tmp_path / "run" / loop.CHECKPOINT, weights_only=True)
    assert saved["step"] == 20  # the last good one is intact
    assert all(torch.isfinite(v).all() for v in saved["model"].values())


def test_corrupt_checkpoint_is_a_clear_error(tmp_path, tiny_dataset):
    loop.train(tiny_dataset, tmp_path / "run", TINY, steps=5, progress=False)
    (tmp_path / "run" / loop.CHECKPOINT).write_bytes(b"not a checkpoint")
    with pytest.raises(loop.TrainingError, match=r"cannot be read.*delete it"):
        loop.train(tiny_dataset, tmp_path / "run", TINY, resume=True, progress=False)


def test_bad_datasets_and_runs(tmp_path, tiny_dataset):
    with pytest.raises(DatasetError, match=r"no manifest.json"):
        loop.train(tmp_path, tmp_path / "run", TINY, progress=False)
    broken = tmp_path / "broken"
    shutil.copytree(tiny_dataset, broken)
    (broken / "manifest.json").write_text("{oops")
    with pytest.raises(DatasetError, match="not readable JSON"):
        loop.train(broken, tmp_path / "run", TINY, progress=False)
    with pytest.raises(loop.TrainingError, match="above the dataset's 32"):
        loop.train(tiny_dataset, tmp_path / "run", replace(TINY, resolution=64), progress=False)
    loop.train(tiny_dataset, tmp_path / "ok", TINY, steps=2, progress=False)
    with pytest.raises(loop.TrainingError, match="--resume"):
        loop.train(tiny_dataset, tmp_path / "ok", TINY, progress=False)
    with pytest.raises(loop.TrainingError, match="other settings"):
        loop.train(
            tiny_dataset, tmp_path / "ok", replace(TINY, lr=0.5), resume=True, progress=False
        )
    with pytest.raises(DatasetError, match="Unknown split"):
        SampleSet(tiny_dataset, "validation")


@pytest.fixture(scope="module")
def bundle(tiny_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bundle")
    export_bundle(tiny_run, out)
    return out


def test_export_matches_torch(bundle, tiny_run, tiny_dataset):
    model, _, _ = loop.build_model(tiny_run)
    samples = SampleSet(tiny_dataset, "heldout-views")
    rig = samples.rig[samples.rows[:5]]
    with torch.no_grad():
        heads = model(torch.from_numpy(rig), 32)
    expected = {"albedo": albedo_maps(heads["albedo"][-1]).numpy()}
    expected.update(
        zip(
            ("depth", "normal", "mask"),
            (t.numpy() for t in geometry_maps(heads["geometry"][-1])),
            strict=True,
        )
    )
    fp32 = BundleModel(bundle).predict(rig, 32)
    for name, value in expected.items():
        assert np.abs(fp32[name] - value).max() < FP32_PARITY, name
    int8 = BundleModel(bundle, "int8").predict(rig, 32)
    drift = {name: float(np.abs(int8[name] - value).mean()) for name, value in expected.items()}
    print("int8 mean abs drift per map:", drift)  # reported, not asserted tightly
    assert all(np.isfinite(v) and v < 0.5 for v in drift.values())


def test_bundle_manifest_and_levels(bundle):
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert [level["resolution"] for level in manifest["levels"]] == [8, 16, 32]
    assert manifest["trunk"]["graphs"]["trunk"] == "trunk.onnx"
    assert manifest["depth"]["scale"] > 0 and manifest["training_camera"]["distance"] == 3.0
    model = BundleModel(bundle)
    assert model.level_for(20) == 32 and model.level_for(3) == 8 and model.level_for(999) == 32
    out = model.predict(np.zeros((2, 19 * 6), np.float32), 16, branches=("albedo",))
    assert set(out) == {"albedo", "alpha"} and out["albedo"].shape == (2, 3, 16, 16)
    assert out["alpha"].shape == (2, 1, 16, 16)


def test_bundle_errors(bundle, tmp_path):
    model = BundleModel(bundle)
    with pytest.raises(BundleError, match="NaN or Inf"):
        model.predict(np.full((1, 19 * 6), np.nan, np.float32), 16)
    with pytest.raises(BundleError, match=r"\(N, 114\)"):
        model.predict(np.zeros((1, 10), np.float32), 16)
    broken = tmp_path / "broken"
    shutil.copytree(bundle, broken)
    (broken / "albedo_16.onnx").write_bytes(b"\x00garbage")
    (broken / "geometry_16.onnx").unlink()
    damaged = BundleModel(broken)
    with pytest.raises(BundleError, match=r"albedo_16.onnx cannot be loaded.*damaged"):
        damaged.predict(np.zeros((1, 114), np.float32), 16, branches=("albedo",))
    with pytest.raises(BundleError, match=r"geometry_16.onnx is missing"):
        damaged.predict(np.zeros((1, 114), np.float32), 16, branches=("geometry",))


def test_eval_command(bundle, tiny_dataset, tmp_path, capsys):
    from rigspace.sdk.cli import main

    copy = tmp_path / "bundle"
    shutil.copytree(bundle, copy)
    args = ["eval", str(copy), str(tiny_dataset), "--errors", str(tmp_path / "err"), "--record"]
    assert main(args) == 0
    out = capsys.readouterr().out
    for name in ("| model |", "| nearest |", "| linear |"):
        assert name in out
    assert list((tmp_path / "err").glob("model_*worst0*.png"))
    recorded = json.loads((copy / "manifest.json").read_text())["metrics"]["heldout-views"]["fp32"]
    assert recorded["samples"] == 32 and recorded["rows"][0]["predictor"] == "model"


def test_model_runner_imports_no_torch(bundle):
    code = (
        "import sys, numpy as np\n"
        "from rigspace.sdk.model import BundleModel\n"
        f"m = BundleModel({str(bundle)!r})\n"
        "m.predict(np.zeros((1, 114), np.float32), 32)\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr


def test_presets_are_consistent():
    for name, config in PRESETS.items():
        assert config.preset == name
        assert (
            config.levels()[0] == config.start_resolution
            and config.levels()[-1] == config.resolution
        )
        assert TrainConfig.from_json(config.to_json()) == config


@pytest.mark.parametrize("signum", ["SIGINT", "SIGTERM"])
@pytest.mark.slow
def test_ctrl_c_or_sigterm_stops_with_a_usable_checkpoint(tmp_path, tiny_dataset, signum):
    import os
    import signal
    import time

    out = tmp_path / "model"
    cmd = [sys.executable, "-m", "rigspace.sdk", "train", str(tiny_dataset), "--out", str(out),
           "--preset", "tiny", "--steps-per-level", "100000"]  # fmt: skip
    # As from a terminal: a suite started in the background (`nohup ... &`) hands its children
    # SIGINT ignored, and Python then installs no KeyboardInterrupt for it.
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    log_file = out / "training" / "log.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if log_file.exists() and len(log_file.read_text().splitlines()) >= 30:
            break
        time.sleep(0.05)
    proc.send_signal(getattr(signal, signum))
    stdout, stderr = proc.communicate(timeout=120)  # a loaded machine: stop, save, exit
    assert proc.returncode == 130, stderr
    assert "stopped: interrupted" in stdout and "--resume" in stdout
    state = torch.load(out / "training" / loop.CHECKPOINT, weights_only=True)
    assert state["step"] >= 30
    assert not (out / "manifest.json").exists()
    assert os.path.getsize(log_file) > 0


def test_upgrade_adds_the_alpha_heads_and_changes_nothing_else(tmp_path, tiny_run, tiny_dataset):
    import torch

    from rigspace.train.upgrade import upgrade

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    state = loop.load_checkpoint(run / loop.CHECKPOINT)
    # A run from before bundle format 2: 3-channel albedo heads.
    for name in [k for k in state["model"] if k.startswith("albedo.heads.")]:
        state["model"][name] = state["model"][name][:3].clone()
    torch.save(state, run / loop.CHECKPOINT)
    with pytest.raises(loop.TrainingError, match="--upgrade"):
        export_bundle(run, tmp_path / "bundle")
    result = upgrade(tiny_dataset, run, steps=30, progress=False)
    assert result.stopped == "upgraded" and np.isfinite(result.last_loss)
    before, _, _ = loop.build_model(tiny_run)
    after, _, _ = loop.build_model(run)
    for name, value in after.state_dict().items():
        old = before.state_dict()[name]
        if name.startswith("albedo.heads."):
            # Colour rows bit-identical; only the alpha row (re-trained from zero) differs.
            assert torch.equal(value[:3], old[:3]) and not torch.equal(value[3:], old[3:])
        else:
            assert torch.equal(value, old), name
    # Again: the alpha trains further, the rest stays as it was.
    upgrade(tiny_dataset, run, steps=5, progress=False)
    again, _, _ = loop.build_model(run)
    for name, value in again.state_dict().items():
        if name.startswith("albedo.heads."):
            assert torch.equal(value[:3], before.state_dict()[name][:3])
            assert not torch.equal(value[3:], after.state_dict()[name][3:])
        else:
            assert torch.equal(value, before.state_dict()[name]), name

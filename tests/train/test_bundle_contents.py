"""What a bundle holds and what train/eval refuse: trained levels only, time budgets, --force,
int8 graphs checked against fp32, capsules, and clear errors for bad paths and samples."""

from __future__ import annotations

import json
import math
import shutil
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from rigspace.sdk.bundle import read_manifest  # noqa: E402
from rigspace.sdk.capsules import CapsuleError, read_capsules  # noqa: E402
from rigspace.sdk.cli import main  # noqa: E402
from rigspace.sdk.model import BundleModel  # noqa: E402
from rigspace.train import loop  # noqa: E402
from rigspace.train.budget import (  # noqa: E402
    MIN_STEPS_PER_LEVEL,
    PACE_WARMUP,
    PACE_WINDOW,
    PLAN_SHARE,
    Pace,
    plan_schedule,
    trained_levels,
)
from rigspace.train.config import preset  # noqa: E402
from rigspace.train.data import DatasetError, SampleSet  # noqa: E402
from rigspace.train.evaluate import DatasetTable  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402
from rigspace.train.int8check import failure_lines  # noqa: E402
from tests.conftest import REPO  # noqa: E402

TINY = preset("tiny")


def levels(manifest: dict) -> list[int]:
    return [level["resolution"] for level in manifest["levels"]]


def test_a_level_counts_as_trained_once_it_has_faded_in():
    # Tiny: 20 steps per level; level 32 fades in over its first 10 steps (20-29).
    assert trained_levels(TINY, 0) == []
    assert trained_levels(TINY, 1) == [16]
    assert trained_levels(TINY, 30) == [16]
    assert trained_levels(TINY, 31) == [16, 32]


def test_a_run_stopped_early_exports_only_the_levels_it_trained(tmp_path, tiny_dataset, capsys):
    model = tmp_path / "model"
    loop.train(tiny_dataset, model / "training", TINY, steps=25, progress=False)  # 32 fading
    manifest = export_bundle(model / "training", model, int8=False)
    assert levels(manifest) == [8, 16]
    assert manifest["training"]["trained_levels"] == [8, 16]
    assert manifest["training"]["planned_levels"] == [8, 16, 32]
    assert not list(model.glob("*_32*.onnx"))
    runtime = BundleModel(model)
    assert runtime.resolutions == [8, 16] and runtime.level_for(999) == 16
    # eval measures it at its top level (as the runtime draws it), and says the run stopped.
    assert main(["eval", str(model), str(tiny_dataset), "--no-baselines", "--json"]) == 0
    captured = capsys.readouterr()
    assert "before level 32 was trained: the model is measured at its top level 16" in captured.err
    assert "--resume" in captured.err and json.loads(captured.out)["resolution"] == 16


def test_the_plan_fits_every_level_into_the_budget():
    seconds = {16: 0.01, 32: 0.03}
    long = replace(TINY, steps_per_level=100_000)
    plan = plan_schedule(long, seconds, 60.0)
    assert plan.steps_per_level == math.floor(PLAN_SHARE * 60.0 / 0.04) and plan.reaches_final
    assert "reaches 32x32" in plan.summary()
    assert plan_schedule(TINY, seconds, 60.0).steps_per_level == TINY.steps_per_level
    short = plan_schedule(long, {16: 0.01, 32: 1.0}, 10.0)  # not even the floor fits
    assert short.steps_per_level == MIN_STEPS_PER_LEVEL and short.reaches == 16
    assert "reaches only 16x16" in short.summary()


def test_a_run_slower_than_planned_ends_a_level_early_to_reach_the_final_one():
    config = replace(TINY, resolution=64, steps_per_level=100)  # levels 16, 32, 64; fade 50
    probe = {16: 0.01, 32: 0.02, 64: 0.04}
    # On the probe's pace after a slow start (a second a step while warming up): no cut.
    on_pace = Pace(config, probe, deadline=20.0)
    times = [min(s, PACE_WARMUP) + 0.01 * max(0, s - PACE_WARMUP) for s in range(100)]
    assert all(on_pace.next_step(s, t) == s for s, t in enumerate(times))
    # Ten times slower: level 16 ends once the rate is measured (32 and 64 need 60 s).
    slow = Pace(config, probe, deadline=60.0)
    measured = PACE_WARMUP + PACE_WINDOW
    assert all(slow.next_step(s, 0.1 * s) == s for s in range(measured))
    assert slow.next_step(measured, 0.1 * measured) == 100
    # Level 32 is not cut before its block has faded in (steps 100-150); then 64's 40 s
    # are more than the 39.7 s left, though its fade-in (20 s) still fits.
    assert all(slow.next_step(s, 8.0 + 0.2 * (s - 100)) == s for s in range(100, 151))
    assert slow.next_step(151, 8.0 + 0.2 * 51) == 200 and not slow.out_of_reach
    # The final level is never ended early, nor past the plan: the budget stops it.
    assert all(slow.next_step(s, 20.0 + 0.05 * (s - 200)) == s for s in range(200, 400))
    # Twice slower: level 16 goes on until the time left is what 32 and 64 need (12 s).
    behind = Pace(config, probe, deadline=13.5)
    cut = next(s for s in range(100) if behind.next_step(s, 0.02 * s) != s)
    assert 40 <= cut <= 50 and behind.next_step(cut + 1, 0.02 * (cut + 1)) == 100
    # A hundred times slower: no later level can fade in, so 16 trains on, said once.
    stuck = Pace(config, probe, deadline=100.0)
    assert all(stuck.next_step(s, 1.0 * s) == s for s in range(60))
    assert stuck.out_of_reach


def _run_paced(pace: Pace, deadline: float, seconds: dict[int, float], steps_per_level: int):
    """Steps a run takes under `pace` until `deadline` when a step at each level takes
    `seconds[level]`: (the step it stopped at, the steps it trained)."""
    t, step, trained = 0.0, 0, []
    while t <= deadline:
        ahead = pace.next_step(step, t)
        if ahead != step:
            step = ahead
            continue
        trained.append(step)
        t += seconds[min(step // steps_per_level, len(seconds) - 1)]
        step += 1
    return step, trained


def test_a_fade_in_ends_within_the_budget_however_slow_the_level_runs():
    """A level counts only once its block has faded in: a final level that runs slower than
    the probe said (here 6x, and only there) strides through the rest of its fade-in so that
    alpha reaches 1 before the budget ends, instead of the budget ending the fade-in and the
    bundle losing the level its plan promised; not so far that the fade-in is a few steps."""
    config = replace(TINY, steps_per_level=100)  # levels 16, 32; fade 50 (steps 100-150)
    probe = {16: 0.01, 32: 0.02}
    assert plan_schedule(config, probe, 6.0).reaches_final
    step, trained = _run_paced(Pace(config, probe, deadline=6.0), 6.0, [0.01, 0.12], 100)
    assert trained_levels(config, step) == [16, 32]
    assert 150 in trained  # the first step at alpha 1 is one that trained
    fade = [s for s in trained if 100 <= s <= 150]
    assert fade[0] == 100 and len(fade) < 51 and max(np.diff(fade)) == 2  # every 2nd step
    # On the probe's pace nothing strides: every step of the fade-in trains.
    step, trained = _run_paced(Pace(config, probe, deadline=6.0), 6.0, [0.01, 0.02], 100)
    assert set(range(100, 151)) <= set(trained) and step > 200
    # Time for a few steps only, on the measured pace (20x the probe's): a fade-in of 7 of its
    # 51 steps is no fade-in; the budget ends it, and the level is not counted.
    step, trained = _run_paced(Pace(config, probe, deadline=23.0), 23.0, [0.2, 0.4], 100)
    assert trained_levels(config, step) == [16] and trained[-1] - trained[0] == len(trained) - 1
    # The middle level's fade-in too (the final one then may not be reached at all).
    three = replace(config, resolution=64)  # 16, 32, 64
    rates = {16: 0.01, 32: 0.02, 64: 0.04}
    step, trained = _run_paced(Pace(three, rates, deadline=5.0), 5.0, [0.01, 0.12, 0.5], 100)
    assert trained_levels(three, step)[:2] == [16, 32]


@pytest.mark.slow
def test_a_budget_that_promised_the_final_level_exports_it(
    tmp_path, tiny_dataset, capsys, step_clock
):
    """The issue's run: the plan says the run reaches 32x32, the final level then runs six
    times slower than the probe measured, and the budget ended its fade-in: it trained about
    186 steps at 32x32 and exported 8 and 16 only. Its fade-in now strides to alpha 1."""
    step_clock({16: 0.01, 32: 0.12}, probe={16: 0.01, 32: 0.02})
    config = replace(TINY, steps_per_level=100)
    model = tmp_path / "model"
    result = loop.train(tiny_dataset, model / "training", config, minutes=0.1, progress=False)
    assert result.stopped == "time budget"
    manifest = export_bundle(model / "training", model, int8=False)
    assert levels(manifest) == [8, 16, 32]
    assert manifest["training"]["trained_levels"] == [8, 16, 32]
    err = capsys.readouterr().err
    assert "the run reaches 32x32" in err
    assert "the 32x32 block fades in with a stride of 2 steps" in err
    records = [json.loads(line) for line in (model / "training" / "log.jsonl").open()]
    faded = [r for r in records if r.get("resolution") == 32 and r["fade"] == 1.0]
    assert faded and all(r["fade"] <= 1.0 for r in records if "fade" in r)


@pytest.mark.slow
def test_a_time_budget_plans_the_schedule_before_training(tmp_path, tiny_dataset, capsys):
    # Far more steps than 6 seconds hold. Whether the plan reaches 32x32 depends on the
    # machine's load (the plan's arithmetic is tested above); the run must plan, say so, and
    # export exactly what it trained.
    config = replace(TINY, steps_per_level=100_000)
    model = tmp_path / "model"
    result = loop.train(tiny_dataset, model / "training", config, minutes=0.1, progress=False)
    record = json.loads((model / "training" / loop.RUN_FILE).read_text())
    plan = record["plan"]
    planned = plan["steps_per_level"]
    assert MIN_STEPS_PER_LEVEL <= planned < 100_000
    assert record["config"]["steps_per_level"] == planned
    assert set(plan["seconds_per_step"]) == {"16", "32"}
    err = capsys.readouterr().err
    assert "time budget" in err
    if plan["reaches"] == 32 and planned > MIN_STEPS_PER_LEVEL:
        assert "the run reaches 32x32" in err
        assert (
            planned * sum(plan["seconds_per_step"].values()) <= PLAN_SHARE * plan["budget_seconds"]
        )
    # Past the plan only when it finished early: then the final level used the rest.
    assert result.step <= 2 * planned or "trains on until it ends" in err
    trained = trained_levels(replace(config, steps_per_level=planned), result.step)
    if not trained:  # a machine so loaded that the probe took the budget
        with pytest.raises(loop.TrainingError, match="trained no level"):
            export_bundle(model / "training", model, int8=False)
        return
    assert levels(export_bundle(model / "training", model, int8=False)) == [8, *trained]
    # Resumed with the same options, the run keeps its plan.
    again = loop.train(
        tiny_dataset, model / "training", config, steps=result.step, resume=True, progress=False
    )
    assert again.step == result.step


@pytest.mark.slow
def test_a_budget_left_over_trains_the_final_level_on(tmp_path, tiny_dataset, capsys, step_clock):
    """The tiny preset's 40 steps take 3 s of a 6-second budget (on the step clock: the same
    on any machine); the rest is not left unused: the final level trains on (fade 1) until
    it ends, and so does a resumed finished run."""
    clock = step_clock({16: 0.05, 32: 0.1})
    run = tmp_path / "model" / "training"
    began = clock.now
    result = loop.train(tiny_dataset, run, TINY, minutes=0.1, progress=False)
    assert result.stopped == "time budget" and result.step > TINY.total_steps()
    assert clock.now - began == pytest.approx(6.0, abs=0.1)  # 20 x 0.05 + 50 x 0.1
    assert result.step == pytest.approx(70, abs=1)
    assert "the final level (32x32) trains on until it ends" in capsys.readouterr().err
    assert trained_levels(TINY, result.step) == [16, 32]
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    extra = [r for r in records if r.get("step", 0) > TINY.total_steps() and "loss" in r]
    assert extra and all(r["resolution"] == 32 and r["fade"] == 1.0 for r in extra)
    assert torch.load(run / loop.CHECKPOINT, weights_only=True)["step"] == result.step
    again = loop.train(tiny_dataset, run, TINY, minutes=0.05, resume=True, progress=False)
    assert again.stopped == "time budget" and again.step == pytest.approx(result.step + 30, abs=1)
    # A step budget is exact: no extension.
    fixed = loop.train(tiny_dataset, tmp_path / "fixed", TINY, steps=40, progress=False)
    assert fixed.step == 40


def _train_args(dataset: Path, out: Path, *extra: str) -> list[str]:
    return ["train", str(dataset), "--out", str(out), "--preset", "tiny", "--no-int8", *extra]


def test_out_with_a_bundle_is_refused_or_replaced_with_force(
    tmp_path, tiny_run, tiny_dataset, capsys
):
    bundle = tmp_path / "bundle"
    export_bundle(tiny_run, bundle, int8=False)  # a bundle without its training run
    (bundle / "albedo_64.onnx").write_bytes(b"a graph of an older, larger bundle")
    (bundle / "notes.txt").write_text("mine")
    before = (bundle / "manifest.json").read_text()
    assert main(_train_args(tiny_dataset, bundle, "--steps", "2")) == 2
    err = capsys.readouterr().err
    assert "holds a model bundle" in err and "--force" in err
    assert main(_train_args(tiny_dataset, bundle, "--resume")) == 2
    assert "nothing to continue" in capsys.readouterr().err
    assert (bundle / "manifest.json").read_text() == before
    assert not (bundle / "training").exists()

    assert main(_train_args(tiny_dataset, bundle, "--steps", "2", "--force")) == 0
    out = capsys.readouterr()
    manifest = json.loads((bundle / "manifest.json").read_text())
    graphs = sorted(name for name in manifest["files"] if name.endswith(".onnx"))
    assert sorted(p.name for p in bundle.glob("*.onnx")) == graphs
    assert not (bundle / "albedo_64.onnx").exists() and levels(manifest) == [8, 16]
    assert (bundle / "notes.txt").read_text() == "mine"
    assert "levels 8, 16" in out.out and "before level 32 was trained" in out.err
    # Its own run continues with --resume as before; past 32's fade-in the export adds it.
    assert main(_train_args(tiny_dataset, bundle, "--resume", "--steps", "31")) == 0
    assert levels(json.loads((bundle / "manifest.json").read_text())) == [8, 16, 32]
    assert main(_train_args(tiny_dataset, bundle, "--resume", "--force")) == 2


@pytest.fixture(scope="module")
def fp32_bundle(tiny_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fp32") / "bundle"
    export_bundle(tiny_run, out, int8=False)
    return out


def test_output_paths_that_are_files_are_refused_before_any_work(
    tmp_path, fp32_bundle, tiny_dataset, capsys
):
    file = tmp_path / "file"
    file.write_text("x")
    assert main(_train_args(tiny_dataset, file, "--steps", "1")) == 2
    assert "--out" in capsys.readouterr().err and file.read_text() == "x"
    args = ["eval", str(fp32_bundle), str(tiny_dataset), "--errors", str(file), "--no-baselines"]
    assert main(args) == 2
    out = capsys.readouterr()
    assert f"--errors {file} is a file" in out.err and out.out == ""  # nothing was evaluated


def test_a_damaged_sample_names_the_file_and_the_capture_that_re_renders_it(
    tmp_path, fp32_bundle, tiny_dataset, capsys
):
    dataset = tmp_path / "ds"
    # Without the decoded cache an earlier run built: training decodes the EXRs (and so meets
    # the damaged one) as a fresh dataset would.
    shutil.copytree(tiny_dataset, dataset, ignore=shutil.ignore_patterns("cache"))
    table = DatasetTable(dataset)
    row = int(table.indices("train")[3])
    path = table.path(row)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # truncated
    scene = table.manifest.scene
    fix = f"`rigspace capture {scene} --out {dataset} --resume`"
    assert main(_train_args(dataset, tmp_path / "model", "--steps", "10")) == 2
    err = capsys.readouterr().err
    assert f"Sample {path} of the dataset is damaged" in err and fix in err
    args = ["eval", str(fp32_bundle), str(dataset), "--split", "train", "--limit", "0"]
    assert main([*args, "--no-baselines"]) == 2
    err = capsys.readouterr().err
    assert f"{path} of the dataset is damaged" in err and fix in err and "delete" not in err
    path.unlink()
    with pytest.raises(DatasetError, match="is missing"):
        SampleSet(dataset, "train").batch(np.arange(len(table.indices("train"))))


def test_healthy_int8_graphs_pass_the_export_check(tmp_path, tiny_run):
    manifest = export_bundle(tiny_run, tmp_path / "bundle")
    check = manifest["int8_check"]
    assert check["split"] == "heldout-views" and check["samples"] == 32
    assert len(check["graphs"]) == 7  # the trunk and two branches at 8, 16, 32
    assert all(result["ok"] for result in check["graphs"].values()), check["graphs"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert BundleModel(tmp_path / "bundle", "int8").int8_fallbacks == {}


def _edited_run(tmp_path: Path, tiny_run: Path, edit) -> Path:
    """A copy of the tiny run whose weights `edit` changed in place."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    state = loop.load_checkpoint(run / loop.CHECKPOINT)
    edit(state["model"])
    torch.save(state, run / loop.CHECKPOINT)
    return run


def _confident_mask(weights: dict) -> None:
    # Mask logits spanning hundreds, as a well-trained character's do (the 2-joint case).
    for name, value in weights.items():
        if name.startswith("geometry.heads."):
            value[4:5] *= 100.0
            if value.ndim == 1:
                value[4:5] += 100.0


def test_a_confident_mask_keeps_its_int8_normals(tmp_path, tiny_run, tiny_dataset):
    """One shared int8 scale for the geometry head's channels rounded every normal to zero."""
    bundle = tmp_path / "bundle"
    manifest = export_bundle(_edited_run(tmp_path, tiny_run, _confident_mask), bundle)
    check = manifest["int8_check"]["graphs"]["geometry_32.int8.onnx"]
    assert check["ok"] and check["metrics"]["normal_zero_fraction"] == 0.0
    samples = SampleSet(tiny_dataset, "heldout-views")
    rig = samples.rig[samples.rows[:8]]
    covered = BundleModel(bundle).predict(rig, 32)["mask"][:, 0] >= 0.5
    assert covered.sum() > 100
    normal = BundleModel(bundle, "int8").predict(rig, 32)["normal"]
    assert np.all(np.linalg.norm(np.moveaxis(normal, 1, -1)[covered], axis=-1) > 0.9)


def _outlier_channel(weights: dict, scale: float = 1000.0) -> None:
    # One trunk channel 1000x larger, its readers' weights 1000x smaller: the same fp32
    # model (leaky ReLU is positively homogeneous), but one int8 scale for every channel
    # of the features rounds the others to zero.
    weights["trunk.conv2.weight"][0] *= scale
    weights["trunk.conv2.bias"][0] *= scale
    for branch in ("albedo", "geometry"):
        weights[f"{branch}.blocks.0.conv1.weight"][:, 0] /= scale
        weights[f"{branch}.heads.0.weight"][:, 0] /= scale


def test_a_broken_int8_graph_is_flagged_and_the_runtime_runs_fp32_instead(
    tmp_path, tiny_run, tiny_dataset
):
    bundle = tmp_path / "bundle"
    manifest = export_bundle(_edited_run(tmp_path, tiny_run, _outlier_channel), bundle)
    graphs = manifest["int8_check"]["graphs"]
    failed = sorted(name for name, result in graphs.items() if not result["ok"])
    assert "trunk.int8.onnx" in failed
    assert any("albedo_psnr" in why for why in graphs["trunk.int8.onnx"]["failed"])
    lines = failure_lines(manifest["int8_check"])
    assert len(lines) == len(failed) and all(name in " ".join(lines) for name in failed)

    with pytest.warns(UserWarning, match=r"trunk\.int8\.onnx"):
        int8 = BundleModel(bundle, "int8")
    assert sorted(int8.int8_fallbacks) == failed
    for level in manifest["levels"]:
        for branch, name in level["int8"].items():
            used = int8.levels[level["resolution"]][branch]
            assert used == (level["graphs"][branch] if name in failed else name)
    samples = SampleSet(tiny_dataset, "heldout-views")
    rig = samples.rig[samples.rows[:8]]
    fp32 = BundleModel(bundle)
    assert np.array_equal(int8.features(rig), fp32.features(rig))  # the fp32 trunk ran
    # eval --int8 --record says which graphs ran in fp32.
    args = ["eval", str(bundle), str(tiny_dataset), "--int8", "--no-baselines", "--limit", "4"]
    with pytest.warns(UserWarning, match=r"trunk\.int8\.onnx"):
        assert main([*args, "--record"]) == 0
    recorded = json.loads((bundle / "manifest.json").read_text())["metrics"]["heldout-views"]
    assert recorded["int8"]["fp32_in_place_of"] == failed


def test_capsules_in_the_dataset_travel_with_the_bundle(tmp_path, tiny_run, tiny_dataset):
    dataset = tmp_path / "ds"
    shutil.copytree(tiny_dataset, dataset)
    capsules = dataset / "capsules.json"  # the capture fits them (rigspace.sdk.capsules)
    assert read_capsules(capsules).joints
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    record = json.loads((run / loop.RUN_FILE).read_text())
    (run / loop.RUN_FILE).write_text(json.dumps({**record, "dataset": str(dataset)}))
    bundle = tmp_path / "bundle"
    manifest = export_bundle(run, bundle, int8=False)
    assert manifest["capsules"] == "capsules.json" and "capsules.json" in manifest["files"]
    assert (bundle / "capsules.json").read_bytes() == capsules.read_bytes()
    assert read_manifest(bundle).capsules == "capsules.json"
    assert BundleModel(bundle).resolutions == [8, 16, 32]
    # A dataset without them (captured before capsules): the bundle's own stay named.
    capsules.unlink()
    manifest = export_bundle(run, bundle, int8=False)
    assert manifest["capsules"] == "capsules.json" and (bundle / "capsules.json").is_file()
    # Unusable capsules are refused, naming the file.
    capsules.write_text("{not json")
    with pytest.raises(CapsuleError, match=r"capsules\.json are not readable"):
        export_bundle(run, bundle, int8=False)


def test_the_bundle_keeps_its_training_views_and_a_render_from_below_says_so(
    tmp_path, tiny_run, tiny_dataset, capsys
):
    """The export keeps the look-at joint's training views (views.npy); a render whose camera
    looks up at the character from far below its ring (elevation 0 alone) reports each
    frame's distance from them and warns once, naming the elevation that would cover it."""
    bundle = tmp_path / "bundle"
    manifest = export_bundle(tiny_run, bundle, int8=False)
    views = manifest["views"]
    assert views["file"] == "views.npy" and "views.npy" in manifest["files"]
    assert views["rows"] == views["of"] == len(SampleSet(tiny_dataset, "train"))
    # The held-out views, 22.5 deg from the nearest training view (between two of the 8), lie
    # inside the training views: interpolated, not novel.
    assert views["elevations"] == [0.0] and views["held_out_deg"]["p95"] < 1.0
    assert read_manifest(bundle).views == views
    scene = tmp_path / "low.usda"
    scene.write_text(
        "#usda 1.0\n(\n    subLayers = [@"
        + str(REPO / "samples" / "scenes" / "cesium_man.usda")
        + '@]\n)\nover "World"\n{\n    over "ShotCam"\n    {\n'
        "        double3 xformOp:translate = (0, -1.2, 2.6)\n"
        "        float xformOp:rotateX = 38\n    }\n}\n"
    )
    out = tmp_path / "out"
    code = main(["render", str(scene), "--out", str(out), "--frames", "2:3",
                 "--resolution", "160x90", "--model", f"/World/CesiumMan={bundle}"])  # fmt: skip
    assert code == 0
    err = capsys.readouterr().err
    frames = json.loads((out / "report.json").read_text())["frames"]
    entries = [f["characters"][0] for f in frames]
    assert all(e["decision"] == "evaluated" for e in entries), entries
    assert all(e["novel_view_deg"] > 12.0 and e["novel_view"] == "from below" for e in entries)
    assert "/World/CesiumMan's body network: in 2 of 2 frames (2-3)" in err
    assert "mostly from below" in err and "rigspace:captureRing:elevations = [-" in err
    # A damaged views file: said once, the frames render without the check.
    (bundle / "views.npy").write_bytes(b"damaged")
    code = main(["render", str(scene), "--out", str(tmp_path / "again"), "--frames", "2:2",
                 "--resolution", "160x90", "--model", f"/World/CesiumMan={bundle}"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0 and "reports no views its network never learned" in err
    assert "views.npy cannot be read" in err and "rigspace.apps.views" in err


def test_views_added_to_an_older_bundle_from_its_dataset_are_the_exports(
    tmp_path, tiny_run, tiny_dataset, capsys
):
    """A bundle exported before training views (no views.npy, no `views`) gets the export's
    own from the dataset it was trained on; another dataset is refused, nothing written."""
    from rigspace.apps.views import main as views_main
    from rigspace.sdk.bundle import read_manifest_document, write_manifest_document

    bundle = tmp_path / "bundle"
    exported = export_bundle(tiny_run, bundle, int8=False)
    data = (bundle / "views.npy").read_bytes()
    (bundle / "views.npy").unlink()
    document = read_manifest_document(bundle)
    del document["views"], document["files"]["views.npy"]
    write_manifest_document(bundle, document)
    other = tmp_path / "other"
    shutil.copytree(tiny_dataset, other, ignore=shutil.ignore_patterns("cache"))
    manifest = json.loads((other / "manifest.json").read_text())
    (other / "manifest.json").write_text(json.dumps({**manifest, "checksum": "0" * 64}))
    assert views_main([str(bundle), str(other)]) == 1
    assert "pass the dataset the bundle was trained on" in capsys.readouterr().err
    assert not (bundle / "views.npy").exists()
    assert views_main([str(bundle), str(tiny_dataset)]) == 0
    assert "32 training views of Skeleton_torso_joint_1" in capsys.readouterr().out
    restored = read_manifest_document(bundle)
    assert restored["views"] == exported["views"]
    assert restored["files"]["views.npy"] == exported["files"]["views.npy"]
    assert (bundle / "views.npy").read_bytes() == data

"""Evaluation on a tiny CesiumMan capture: perfect predictor, sample choice, PNGs, tables, errors."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.render import Maps
from rigspace.sdk.stage import open_stage
from rigspace.train import evaluate as ev
from tests.train.conftest import CHARACTER, FRAMES, SCENE, VIEWS, captured_dataset

HEIGHT_TOLERANCE = 0.1
"""Relative: the mask estimate is off by up to a pixel at each end (0.06 units at 32^2)."""


@pytest.fixture(scope="session")
def table(tmp_path_factory) -> ev.DatasetTable:
    return ev.DatasetTable(captured_dataset(tmp_path_factory))


class Truth:
    """Predicts the dataset's own maps."""

    name = "truth"

    def __init__(self, table: ev.DatasetTable) -> None:
        self.table = table

    def predict(self, indices: np.ndarray) -> list[Maps]:
        return [self.table.maps(int(i)) for i in indices]


class Blank:
    """Predicts nothing at all, at a chosen size."""

    name = "blank"

    def __init__(self, size: int) -> None:
        self.size = size

    def predict(self, indices: np.ndarray) -> list[Maps]:
        from rigspace.sdk.render import empty_maps

        return [empty_maps(self.size, self.size) for _ in indices]


def test_table_reads_splits_and_maps(table):
    train, held = table.indices("train"), table.indices("heldout-views")
    assert len(train) == len(held) == VIEWS * 4 and len(table) == 64
    assert np.all(table.column("split")[held] == 1)
    maps = table.maps(int(held[0]))
    assert maps.albedo.shape == (32, 32, 3) and maps.mask.max() > 0


def test_character_height_matches_the_posed_mesh(table):
    stage = open_stage(SCENE)  # kept alive: the rig's prims expire with their stage
    rig = CharacterRig(stage.GetPrimAtPath(CHARACTER))
    extents = []
    for time in np.arange(FRAMES[0], FRAMES[1] + 1):
        points = np.concatenate([m.points for m in rig.posed_meshes(float(time))])
        extents.append(np.ptp(points[:, 1]))  # Y up; the ring at elevation 0 sees it upright
    assert table.character_height == pytest.approx(max(extents), rel=HEIGHT_TOLERANCE)


def test_perfect_predictor_scores_perfectly(table):
    report = ev.evaluate(Truth(table), table, "heldout-views", limit=6)
    assert report["samples"] == 6 and len(report["per_sample"]) == 6
    m = report["metrics"]
    assert m["albedo_psnr"]["mean"] == math.inf
    assert m["albedo_ssim"]["mean"] == 1.0 and m["mask_iou"]["mean"] == 1.0
    for key in ("depth_mae", "depth_mae_pct", "normal_mean_deg", "normal_median_deg"):
        assert m[key]["mean"] == 0.0 and m[key]["median"] == 0.0
    json.loads(ev.to_json(report))  # strict JSON: inf becomes null


def test_limit_takes_a_fixed_evenly_spaced_subset(table):
    held = table.indices("heldout-views")
    chosen = ev.evenly_spaced(held, 5)
    assert len(chosen) == 5 and chosen[0] == held[0] and chosen[-1] == held[-1]
    assert np.all(np.diff(chosen) > 0)
    again = ev.evaluate(Truth(table), table, "heldout-views", limit=5)
    assert again["indices"] == chosen.tolist()
    assert ev.evenly_spaced(held, None) is held and len(ev.evenly_spaced(held, 1000)) == len(held)


def test_error_map_images_are_written_for_the_worst_samples(table, tmp_path, monkeypatch):
    monkeypatch.setattr(ev, "PREDICT_BATCH", 3)  # the worst are kept across batches
    report = ev.evaluate(Blank(32), table, "heldout-views", limit=8, worst=2, out_dir=tmp_path)
    assert len(report["worst"]) == 2
    psnrs = sorted(s["albedo_psnr"] for s in report["per_sample"])
    assert [w["albedo_psnr"] for w in report["worst"]] == psnrs[:2]
    for entry in report["worst"]:
        image = cv2.imread(entry["image"])
        assert image is not None and image.shape[2] == 3
        tiles = 4 * 32 * (ev.TILE_MIN // 32)  # 32^2 maps upscaled x4 to TILE_MIN
        assert image.shape[1] == ev.ROW_LABEL_WIDTH + tiles
        assert image.std() > 0  # something is drawn
    saved = json.loads((tmp_path / "blank_heldout-views_report.json").read_text())
    assert saved["samples"] == 8 and saved["metrics"]["mask_iou"]["mean"] == 0.0


def test_compare_runs_every_predictor_on_the_same_samples(table):
    result = ev.compare([Truth(table), Blank(32)], table, "heldout-views", limit=4)
    assert [r["predictor"] for r in result["rows"]] == ["truth", "blank"]
    for report in result["reports"].values():
        assert report["indices"] == result["indices"]
    text = ev.format_table(result)
    lines = text.strip().splitlines()
    assert lines[2].startswith("| predictor | albedo PSNR (dB)")
    assert lines[4].startswith("| truth | inf | 1.0000 | 1.0000 | 0.0000")
    assert lines[5].startswith("| blank |") and "n/a" in lines[5]  # no depth to compare


def test_bad_inputs_name_the_thing_and_the_fix(table, tmp_path):
    with pytest.raises(ev.DatasetError, match="does not exist"):
        ev.DatasetTable(tmp_path / "nowhere")
    with pytest.raises(ev.DatasetError, match=r"has no manifest.json.*Fix: point at a dataset"):
        ev.DatasetTable(tmp_path)
    partial = tmp_path / "partial"
    partial.mkdir()
    shutil.copy(table.folder / "manifest.json", partial)
    with pytest.raises(ev.DatasetError, match=r"has no params.npz.*--resume"):
        ev.DatasetTable(partial)
    with pytest.raises(ev.DatasetError, match=r"Unknown split 'test'.*heldout-views"):
        table.indices("test")
    with pytest.raises(ev.DatasetError, match=r"'heldout-clips' .* is empty.*Fix: capture"):
        ev.evaluate(Truth(table), table, "heldout-clips")
    with pytest.raises(ev.DatasetError, match=r"returns 16x16 maps.*32x32"):
        ev.evaluate(Blank(16), table, "heldout-views", limit=1)
    assert issubclass(ev.DatasetError, RigspaceError)


def test_evaluation_imports_no_torch():
    code = (
        "import sys, rigspace.train.evaluate, rigspace.train.baselines, rigspace.train.metrics;"
        "sys.exit('torch' in sys.modules)"
    )
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def _reject(constant: str):
    raise ValueError(f"not strict JSON: {constant}")


def test_reports_are_strict_json_with_null_for_nan_and_inf(table):
    report = ev.evaluate(Truth(table), table, "heldout-views", limit=2)
    assert math.isinf(report["metrics"]["albedo_psnr"]["mean"])  # an exact match
    report["numpy"] = [np.float32("nan"), np.int64(3), np.array([1.5, np.inf])]
    parsed = json.loads(ev.to_json(report), parse_constant=_reject)
    assert parsed["metrics"]["albedo_psnr"]["mean"] is None
    assert parsed["numpy"] == [None, 3, [1.5, None]]
    assert parsed["metrics"]["mask_iou"]["mean"] == 1.0


def test_downsampled_targets_are_the_training_targets(table):
    """A table below the capture's resolution box-downsamples exactly as training does."""
    from rigspace.train.data import SampleSet

    half = ev.DatasetTable(table.folder, 16)
    assert (half.resolution, half.captured_resolution, half.factor) == (16, 32, 2)
    row = int(half.indices("train")[5])
    maps = half.maps(row)
    assert maps.mask.shape == (16, 16)
    samples = SampleSet(table.folder, "train", resolution=16)
    item = samples.item(int(np.flatnonzero(samples.rows == row)[0]))
    np.testing.assert_allclose(np.moveaxis(maps.albedo, -1, 0), item["albedo"], atol=1e-6)
    np.testing.assert_allclose(maps.mask, item["mask"][0], atol=1e-6)
    covered = maps.mask > 0
    assert np.all(np.isinf(maps.depth[~covered])) and np.all(np.isfinite(maps.depth[covered]))
    joint_depth = -table.column("joint_camera")[row][2]
    relative = (maps.depth[covered] - joint_depth) / samples.depth_scale
    np.testing.assert_allclose(relative, item["depth"][0][covered], atol=1e-4)
    assert half.character_height == table.character_height  # measured at the capture's size
    with pytest.raises(ev.DatasetError, match=r"captured at 32x32; 24x24 targets cannot"):
        ev.DatasetTable(table.folder, 24)


@pytest.fixture(scope="module")
def fp32_model(tiny_run, tmp_path_factory):
    from rigspace.train.export import export_bundle

    out = tmp_path_factory.mktemp("eval32") / "bundle"
    export_bundle(tiny_run, out, int8=False)
    return out


@pytest.fixture(scope="module")
def bundle_at_16(fp32_model, tmp_path_factory):
    """The tiny model as a network whose top level is 16 (its level 32 left out)."""
    out = tmp_path_factory.mktemp("eval16") / "bundle"
    shutil.copytree(fp32_model, out)
    path = out / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["levels"] = [lv for lv in manifest["levels"] if lv["resolution"] <= 16]
    manifest["training"]["planned_levels"] = manifest["training"]["trained_levels"] = [8, 16]
    path.write_text(json.dumps(manifest))
    return out


def test_eval_above_the_top_level_uses_downsampled_targets_and_strict_json(
    bundle_at_16, tiny_dataset, capsys
):
    from rigspace.sdk.cli import main
    from rigspace.train.predictor import BundlePredictor

    args = ["eval", str(bundle_at_16), str(tiny_dataset), "--limit", "6", "--json"]
    assert main(args) == 0
    out = capsys.readouterr()
    assert "box-downsampled 2x from the captured 32x32 to 16x16" in out.err
    result = json.loads(out.out, parse_constant=_reject)  # strict: no NaN/Infinity tokens
    assert result["resolution"] == 16 and "box-downsampled" in result["targets"]
    rows = {row["predictor"]: row for row in result["rows"]}
    assert set(rows) == {"model", "nearest", "linear"}  # baselines downsampled alike
    # The model's numbers are those of its level 16 against the downsampled targets.
    half = ev.DatasetTable(tiny_dataset, 16)
    direct = ev.evaluate(
        BundlePredictor(bundle_at_16, half), half, "heldout-views", indices=result["indices"]
    )
    assert rows["model"]["albedo_psnr"] == pytest.approx(direct["metrics"]["albedo_psnr"]["mean"])
    assert rows["model"]["mask_iou"] == pytest.approx(direct["metrics"]["mask_iou"]["mean"])
    assert main([*args[:-1]]) == 0  # the table says so as well
    assert "(targets box-downsampled 2x" in capsys.readouterr().out


def test_eval_json_writes_null_where_a_metric_is_not_finite(tiny_dataset):
    """A predictor that returns the targets themselves scores PSNR +inf: strict JSON null."""

    class Truth:
        name, footprint_bytes = "truth", 0

        def __init__(self, table):
            self.table = table

        def predict(self, indices):
            return [self.table.maps(int(i)) for i in indices]

    table = ev.DatasetTable(tiny_dataset)
    result = ev.compare([Truth(table)], table, "train", limit=2)
    parsed = json.loads(ev.to_json(result), parse_constant=_reject)
    (row,) = parsed["rows"]
    assert row["albedo_psnr"] is None and row["mask_iou"] == 1.0
    samples = parsed["reports"]["truth"]["per_sample"]
    assert all(sample["albedo_psnr"] is None for sample in samples)


def test_eval_warns_of_a_damaged_graph_at_a_level_it_does_not_use(
    bundle_at_16, tiny_dataset, tmp_path, capsys
):
    """eval loads the top level only; a truncated level-8 graph (which the runtime loads for a
    distant character) is named before the measurement, and the measurement still runs."""
    from rigspace.sdk.cli import main

    bundle = tmp_path / "bundle"
    shutil.copytree(bundle_at_16, bundle)
    manifest = json.loads((bundle / "manifest.json").read_text())
    (level8,) = [lv for lv in manifest["levels"] if lv["resolution"] == 8]
    graph = bundle / level8["graphs"]["albedo"]
    graph.write_bytes(graph.read_bytes()[:500])
    args = ["eval", str(bundle), str(tiny_dataset), "--limit", "2", "--no-baselines"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert f"warning: Model file {graph} cannot be loaded" in err
    assert "render` and inspect refuse the bundle" in err
    assert (
        main(["eval", str(bundle_at_16), str(tiny_dataset), "--limit", "2", "--no-baselines"]) == 0
    )
    # (The 40-step tiny model's level 16 draws nothing on these two samples: said, too.)
    assert "cannot be loaded" not in capsys.readouterr().err


@pytest.mark.parametrize("damage", ["format_version", "measured level"])
def test_eval_says_a_problem_with_what_it_measures_once_as_its_error(
    bundle_at_16, tiny_dataset, tmp_path, capsys, damage
):
    """A manifest eval cannot read, or a damaged graph of the level it measures, stops eval:
    its error, not also a warning with the same text before it."""
    from rigspace.sdk.cli import main

    bundle = tmp_path / "bundle"
    shutil.copytree(bundle_at_16, bundle)
    path = bundle / "manifest.json"
    manifest = json.loads(path.read_text())
    if damage == "format_version":
        manifest["format_version"] = str(manifest["format_version"])
        path.write_text(json.dumps(manifest))
        said = 'format_version must be an integer (one of 1, 2, 3, 4); it is "2" (a string)'
    else:
        (level16,) = [lv for lv in manifest["levels"] if lv["resolution"] == 16]
        graph = bundle / level16["graphs"]["albedo"]
        graph.write_bytes(graph.read_bytes()[:500])
        said = f"Model file {graph} cannot be loaded"
    args = ["eval", str(bundle), str(tiny_dataset), "--limit", "2", "--no-baselines"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count(said) == 1 and "error: " in err and "warning" not in err, err


def _coverage_bundle(tiny_run, folder, logit: float):
    """The tiny model with its mask and alpha logits set to `logit` everywhere: -100 draws
    nothing (as an untrained model, or one trained on another character, can), +100 covers
    its whole billboard."""
    import torch

    from rigspace.train import loop
    from rigspace.train.export import export_bundle

    run = folder / "run"
    shutil.copytree(tiny_run, run)
    state = loop.load_checkpoint(run / loop.CHECKPOINT)
    for name, value in state["model"].items():
        if name.startswith(("geometry.heads.", "albedo.heads.")):
            channel = 4 if name.startswith("geometry.") else 3  # the mask; albedo's alpha
            value[channel] = logit if value.ndim == 1 else 0.0
    torch.save(state, run / loop.CHECKPOINT)
    export_bundle(run, folder / "bundle", int8=False)
    return folder / "bundle"


@pytest.fixture(scope="module")
def blind_bundle(tiny_run, tmp_path_factory):
    return _coverage_bundle(tiny_run, tmp_path_factory.mktemp("blind"), -100.0)


@pytest.fixture(scope="module")
def covering_bundle(tiny_run, tmp_path_factory):
    return _coverage_bundle(tiny_run, tmp_path_factory.mktemp("covering"), 100.0)


def test_eval_says_when_the_model_draws_nothing(
    blind_bundle, covering_bundle, tiny_dataset, capsys
):
    """eval printed IoU 0.0000 and SSIM 0.0007 and no word of why."""
    from rigspace.sdk.cli import main

    args = [str(tiny_dataset), "--limit", "4", "--no-baselines"]
    assert main(["eval", str(blind_bundle), *args]) == 0
    err = capsys.readouterr().err
    assert "warning: the model draws nothing: its mask is empty on 4 of 4 samples" in err
    assert "(untrained, or the wrong bundle for this character?)" in err
    assert main(["eval", str(covering_bundle), *args]) == 0  # a model that draws: no word
    assert "draws nothing" not in capsys.readouterr().err


def test_render_says_when_the_model_draws_nothing(blind_bundle, covering_bundle, tmp_path, capsys):
    """render --reference showed the set alone, IoU 0.000, `warnings: []`, and no word."""
    from rigspace.sdk.cli import main

    out = tmp_path / "frames"
    render = ["render", str(SCENE), "--model", str(blind_bundle), "--out", str(out),
              "--frames", "1:3", "--resolution", "64x36", "--prim-samples", "1"]  # fmt: skip
    assert main([*render, "--reference"]) == 0
    err = capsys.readouterr().err
    said = f"{CHARACTER}: the model draws nothing: its mask is empty on 3 of 3 frames"
    assert said in err and "wrong bundle for this character?" in err
    report = json.loads((out / "report.json").read_text())
    assert any(said in w for w in report["warnings"])
    assert all(e["covered_px"] == 0 for f in report["frames"] for e in f["characters"])
    assert main([*render[:3], str(covering_bundle), *render[4:]]) == 0
    assert "draws nothing" not in capsys.readouterr().err


def test_region_metrics_measure_the_region_pixels_from_the_truths_uv_and_chart():
    """A region is found from the ground truth's texture coordinates: the error inside it
    counts, the error outside it does not; a region out of view is nan, not 0."""
    from rigspace.sdk.render import Maps
    from rigspace.train.evaluate import region_metrics
    from rigspace.train.regions import TEXELS, SurfaceRegion, WholeCharacter

    h = w = 8
    uv = np.zeros((h, w, 2), np.float32)
    uv[..., 0] = (np.arange(w) + 0.5) / w  # u runs across the image, on chart 1
    chart = np.ones((h, w), np.int32)
    truth = Maps(
        albedo=np.full((h, w, 3), 0.5, np.float32),
        normal=np.zeros((h, w, 3), np.float32),
        depth=np.ones((h, w), np.float32),
        mask=np.ones((h, w), np.float32),
        uv=uv,
        chart=chart,
    )
    left = np.zeros((TEXELS, TEXELS), bool)
    left[:, : TEXELS // 2] = True  # u < 0.5: the image's left half
    region = SurfaceRegion("face", "the left half", {1: (np.zeros(2), np.ones(2), left)})
    pred = Maps(truth.albedo.copy(), truth.normal, truth.depth, truth.mask)
    pred.albedo[:, w // 2 :] = 0.0  # wrong on the right half only
    got = region_metrics(pred, truth, [WholeCharacter(), region])
    assert got["pixels@face"] == h * w // 2 and got["pixels@character"] == h * w
    assert got["albedo_psnr@face"] == np.inf
    assert np.isclose(got["albedo_psnr@character"], 10 * np.log10(1 / (0.5 * 0.25)))
    elsewhere = Maps(truth.albedo, truth.normal, truth.depth, truth.mask, uv, chart * 2)
    assert np.isnan(region_metrics(pred, elsewhere, [region])["albedo_psnr@face"])


def test_a_region_no_sample_shows_is_named_not_n_a():
    """A region with no pixel in any sample evaluated gets a reason, not "n/a" (issue 33)."""
    region = {"description": "the surface its blend shapes move", "pixels_mean": 0.0}
    result = {
        "split": "heldout-views", "samples": 4, "dataset": "ds",
        "rows": [{"predictor": "model", "albedo_psnr@face": float("nan")}],
        "reports": {"model": {"regions": {"face": region}}},
    }  # fmt: skip
    text = ev.format_table(result)
    assert (
        "over the face (the surface its blend shapes move): not measured: no sample of the 4"
        in text
    )
    assert "n/a" not in text.split("over the face")[1]
    region["pixels_mean"] = 120.0
    result["rows"][0]["albedo_psnr@face"] = 27.5
    assert (
        "face (the surface its blend shapes move, 120 pixels a sample): model 27.50 dB"
        in ev.format_table(result)
    )

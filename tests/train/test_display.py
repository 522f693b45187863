"""`rigspace eval --display`: a model measured at the size it is seen, on a capture above its
resolution, against the truth there and the truth at its resolution upsampled."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="these tests train a tiny model (the train extra)")

from rigspace.sdk.cli import main  # noqa: E402
from rigspace.train.config import preset  # noqa: E402
from rigspace.train.display import (  # noqa: E402
    MODES,
    DisplayPredictor,
    UpsampledTruth,
    display_sizes,
    scene_textures,
)
from rigspace.train.evaluate import DatasetTable  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402
from rigspace.train.loop import train  # noqa: E402


@pytest.fixture(scope="module")
def small_model(tmp_path_factory, tiny_dataset):
    """A textured model of the tiny CesiumMan dataset that stops at 16x16 (the dataset: 32)."""
    folder = tmp_path_factory.mktemp("display")
    config = preset("tiny", texture=True, resolution=16, steps_per_level=60)
    train(tiny_dataset, folder / "training", config, progress=False)
    export_bundle(folder / "training", folder, int8=False)
    return folder


def test_sizes_are_the_powers_of_two_above_the_model():
    assert display_sizes(128, 512) == [256, 512]
    assert display_sizes(64, 128) == [128]
    assert display_sizes(128, 128) == []


def test_the_predictors_draw_at_the_tables_size(small_model, tiny_dataset):
    from rigspace.sdk.model import BundleModel

    model = BundleModel(small_model)
    table = DatasetTable(tiny_dataset)
    textures, why = scene_textures(model, table.manifest)
    assert textures is not None and why == ""
    rows = table.indices("heldout-views")[:3]
    for mode in MODES:
        maps = DisplayPredictor(model, table, mode, textures).predict(rows)
        assert len(maps) == 3 and maps[0].albedo.shape == (32, 32, 3)
        assert np.all(np.isfinite(maps[0].albedo)) and maps[0].mask.max() <= 1
    truth = UpsampledTruth(table, 16).predict(rows)
    # The truth at 16 upsampled keeps the captured colours' mean (box down, bilinear up).
    captured = table.maps(int(rows[0]))
    assert abs(truth[0].albedo.mean() - captured.albedo.mean()) < 0.01


def test_eval_display_prints_and_records_every_size(small_model, tiny_dataset, capsys):
    args = ["eval", str(small_model), str(tiny_dataset), "--display", "--limit", "6", "--record"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "at 32x32 (2x the model's 16x16):" in out
    for name in (*MODES, "truth at 16, upsampled"):
        assert f"| {name} |" in out
    assert "| textures at the true 16 coordinates |" in out
    recorded = json.loads((small_model / "manifest.json").read_text())["metrics"]["display"]
    rows = recorded["heldout-views"]["32"]["rows"]
    ceiling = "textures at the true 16 coordinates"
    assert [r["predictor"] for r in rows] == [*MODES, "truth at 16, upsampled", ceiling]
    assert all(r["albedo_psnr"] > 5 for r in rows)
    by_name = {r["predictor"]: r for r in rows}
    # Exact charts and coordinates beat a 60-step head's, through the same sampler.
    assert by_name[ceiling]["albedo_psnr"] > by_name["runtime"]["albedo_psnr"]


def test_eval_display_on_a_capture_not_above_the_model_says_what_to_capture(
    tiny_dataset, tmp_path, capsys
):
    from tests.train.test_texture_head import TINY

    folder = tmp_path / "m32"  # every level to 32x32 (a step or two each): the bundle's top is 32
    train(tiny_dataset, folder / "training", replace(TINY, steps_per_level=2), progress=False)
    export_bundle(folder / "training", folder, int8=False)
    assert main(["eval", str(folder), str(tiny_dataset), "--display"]) != 0
    err = capsys.readouterr().err
    assert "not above the model's 32x32" in err and "--resolution 128 --every 10" in err

"""Every sample scene validates: inspect finds no error, capture and render accept it as it is."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rigspace.sdk import schema, validation
from rigspace.sdk.cli import main
from rigspace.sdk.stage import open_stage

SCENES = sorted((Path(__file__).resolve().parents[2] / "samples" / "scenes").glob("*.usda"))


def test_there_are_sample_scenes():
    assert {"previs.usda", "cesium_man.usda"} <= {p.name for p in SCENES}


@pytest.mark.parametrize("scene", SCENES, ids=[p.stem for p in SCENES])
def test_every_sample_scene_inspects_clean(scene, capsys):
    code = main(["inspect", "--json", str(scene)])
    report = json.loads(capsys.readouterr().out)
    assert report["errors"] == [] and code == 0


@pytest.mark.parametrize("scene", SCENES, ids=[p.stem for p in SCENES])
def test_capture_and_render_accept_every_sample_scene(scene):
    stage = open_stage(scene)
    characters = schema.neural_characters(stage)
    warnings: list[str] = []
    validation.require_valid(stage, "capture", characters, warn=warnings.append)
    validation.require_valid(stage, "render", warn=warnings.append)
    # The only warning a sample may give: a character not trained yet (CesiumMan).
    without_model = [c for c in characters if not schema.read_neural_character(c).model]
    assert len(warnings) == len(without_model)
    assert all("has no model bundle" in text for text in warnings)

"""The runtime colouring a character from its own textures (a bundle with a texture head), and
falling back to the albedo branch where no texture drives the colour or the scene's character
is not the one the bundle was trained on."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="these tests train a tiny model (the train extra)")

from pxr import Sdf, Usd, UsdGeom, UsdShade  # noqa: E402

from rigspace.capture.pipeline import capture  # noqa: E402
from rigspace.runtime.engine import Engine, EngineSettings  # noqa: E402
from rigspace.train.config import preset  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402
from rigspace.train.loop import train  # noqa: E402
from tests.materials import CHARACTER, write_material_character  # noqa: E402

TINY = preset("tiny", texture=True, steps_per_level=150, chart_weight=1.0)
"""Enough for the tiny network to cover the cylinder (held-out mask IoU 0.82, chart accuracy
0.87 measured): below that its coverage stays under 0.5 and nothing is drawn. The chart
classifier's weight is raised from 0.25: at the default, 150 steps leave its most likely
chart under CHART_CONFIDENCE on most pixels (0.3-0.48 measured on an AMD EPYC; 12.6% of the
pixels textured on CI's Xeon), and the runtime rightly falls back to the albedo branch."""


def _capture_and_train(folder, textured: bool = True, steps: int = TINY.steps_per_level):
    scene = write_material_character(folder, textured)
    capture(scene, CHARACTER, folder / "ds", workers=1, progress=False, warn=lambda text: None)
    config = replace(TINY, steps_per_level=steps)
    train(folder / "ds", folder / "model" / "training", config, progress=False)
    export_bundle(folder / "model" / "training", folder / "model", int8=False)
    return scene


def _with_model(scene, edit=None):
    """The scene with rigspace:model authored on the character (and `edit` applied)."""
    stage = Usd.Stage.Open(str(scene))
    stage.GetPrimAtPath(CHARACTER).CreateAttribute("rigspace:model", Sdf.ValueTypeNames.Asset).Set(
        Sdf.AssetPath("./model")
    )
    if edit is not None:
        edit(stage)
    stage.GetRootLayer().Save()
    return scene


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    return _capture_and_train(tmp_path_factory.mktemp("textured"))


def _frame(scene, capsys):
    with Engine(scene, EngineSettings(camera="/World/Camera", width=160, height=120)) as engine:
        frame = engine.render(6.0)
    entry = next(c for c in frame.report.characters if c["path"] == CHARACTER)
    return frame, entry, capsys.readouterr().err


def test_a_textured_bundle_colours_from_the_scenes_textures(textured, capsys):
    manifest = json.loads((textured.parent / "model" / "manifest.json").read_text())
    assert manifest["texture"]["charts"] == 4  # trousers and shirt, by UDIM tile
    frame, entry, err = _frame(_with_model(textured), capsys)
    assert entry["decision"] == "evaluated"
    # The boots have no texture: the albedo branch colours them, the textures the rest.
    share = float(entry["colour"].split("% ")[0].split()[-1]) / 100
    assert "its textures" in entry["colour"] and 0.2 < share < 1.0
    assert "samples no texture" not in err
    assert frame.maps.mask.max() > 0.5


def test_a_texture_head_on_its_own_branch_colours_lit_and_unlit_frames(textured, tmp_path, capsys):
    """A bundle whose texture head is a branch of its own (format 4): the frame runs it beside
    the map branches and colours from the scene's textures, lit (both map branches) and unlit
    (the albedo branch alone), as the head on the albedo branch does."""
    folder = tmp_path / "own"
    shutil.copytree(textured.parent, folder, ignore=shutil.ignore_patterns("model"))
    config = replace(TINY, texture_branch="texture")
    train(folder / "ds", folder / "model" / "training", config, progress=False)
    manifest = export_bundle(folder / "model" / "training", folder / "model", int8=False)
    assert manifest["texture"]["branch"] == "texture"
    scene = _with_model(folder / textured.name)
    _, entry, err = _frame(scene, capsys)
    assert entry["branches"] == ["albedo", "geometry", "texture"]
    share = float(entry["colour"].split("% ")[0].split()[-1]) / 100
    assert "its textures" in entry["colour"] and 0.2 < share < 1.0
    assert "samples no texture" not in err

    def unlit(stage):  # no light and nothing beside it: the unlit mode
        for prim in list(stage.Traverse()):
            if prim.GetTypeName().endswith("Light"):
                stage.RemovePrim(prim.GetPath())

    _, entry, _ = _frame(_with_model(scene, unlit), capsys)
    if entry["mode"] == "unlit":
        assert entry["branches"] == ["albedo", "texture"]
    assert "its textures" in entry["colour"]


def test_a_character_with_other_uvs_falls_back_with_a_warning(textured, tmp_path, capsys):
    folder = tmp_path / "other"
    shutil.copytree(textured.parent, folder)

    def move_uvs(stage):
        primvar = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/World/Asset/Body")).GetPrimvar("st")
        primvar.Set(np.asarray(primvar.Get()) * np.float32(0.5))

    scene = _with_model(folder / textured.name, move_uvs)
    _, entry, err = _frame(scene, capsys)
    assert "samples no texture" in err and "other uvs" in err
    assert entry["colour"] == "the albedo branch"


def test_a_scene_without_textures_falls_back_with_a_warning(textured, tmp_path, capsys):
    folder = tmp_path / "plain"
    shutil.copytree(textured.parent, folder)

    def drop_textures(stage):
        for look in ("Denim", "Cotton"):
            surface = UsdShade.Shader(stage.GetPrimAtPath(f"/World/Looks/{look}/Surface"))
            surface.GetInput("diffuseColor").DisconnectSource()

    scene = _with_model(folder / textured.name, drop_textures)
    _, entry, err = _frame(scene, capsys)
    assert "none of its meshes has a texture" in err
    assert entry["colour"] == "the albedo branch"


def test_a_character_without_textures_trains_no_head(tmp_path, capsys):
    scene = _capture_and_train(tmp_path, textured=False, steps=10)
    assert "no texture charts" in capsys.readouterr().err
    assert not (tmp_path / "ds" / "charts.json").exists()
    manifest = json.loads((tmp_path / "model" / "manifest.json").read_text())
    assert "texture" not in manifest
    _, entry, err = _frame(_with_model(scene), capsys)
    assert entry.get("colour") in (None, "the albedo branch") and "samples no texture" not in err


def test_a_bundle_with_a_damaged_chart_table_draws_with_its_albedo_branch(
    textured, tmp_path, capsys
):
    folder = tmp_path / "damaged"
    shutil.copytree(textured.parent, folder)
    (folder / "model" / "charts.json").write_text("{not json")
    frame, entry, err = _frame(_with_model(folder / textured.name), capsys)
    assert "samples no texture" in err and "charts.json cannot be read" in err
    assert entry["colour"] == "the albedo branch" and frame.maps.mask.max() > 0.5

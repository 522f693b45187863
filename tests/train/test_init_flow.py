"""A raw character to a rendered shot: `rigspace init`, then `render --model` with a bundle
trained on it, the scene file untouched."""

from __future__ import annotations

import json

from rigspace.sdk.cli import main
from rigspace.train.export import export_bundle
from tests.conftest import CESIUM_MAN


def test_init_then_render_with_model_draws_the_character(tmp_path, tiny_run, capsys):
    bundle = tmp_path / "bundle"
    export_bundle(tiny_run, bundle, int8=False)  # trained on CesiumMan (the tiny dataset)
    scene = tmp_path / "shot.usda"
    assert main(["init", str(CESIUM_MAN), "--out", str(scene)]) == 0
    before = scene.read_bytes()
    frames = tmp_path / "frames"
    args = ["render", str(scene), "--out", str(frames), "--frames", "10:10"]
    args += ["--resolution", "96x54", "--max-level", "16"]
    assert main([*args, "--model", str(bundle)]) == 0
    (frame,) = json.loads((frames / "report.json").read_text())["frames"]
    (entry,) = frame["characters"]
    assert entry["decision"] == "evaluated", entry
    assert scene.read_bytes() == before  # the bundle went into the session layer only
    capsys.readouterr()
    assert main([*args, "--model", f"/World/Nobody={bundle}"]) == 2
    assert "/World/Nobody is not a neural character" in capsys.readouterr().err
    assert main([*args, "--model", str(tmp_path)]) == 2
    assert "is not a model bundle" in capsys.readouterr().err

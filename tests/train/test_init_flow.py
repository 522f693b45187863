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


def test_a_shot_that_clips_the_character_away_says_so(tmp_path, tiny_run, capsys):
    """USD's fallback near plane is 1: a small character nearer than that is culled. The
    report and the console say which plane and what to author, not a silent empty shot."""
    bundle = tmp_path / "bundle"
    export_bundle(tiny_run, bundle, int8=False)
    assert main(["init", str(CESIUM_MAN), "--out", str(tmp_path / "shot.usda")]) == 0
    clipped = tmp_path / "clipped.usda"
    clipped.write_text(
        "#usda 1.0\n(\n    subLayers = [@./shot.usda@]\n)\n"
        'over "World"\n{\n    over "ShotCam"\n    {\n'
        "        float2 clippingRange = (50, 1000)\n    }\n}\n"
    )
    frames = tmp_path / "frames"
    args = ["render", str(clipped), "--out", str(frames), "--frames", "10:12"]
    assert main([*args, "--resolution", "64x36", "--model", str(bundle)]) == 0
    err = capsys.readouterr().err
    assert "/World/CesiumMan is in none of the 3 frames: nearer than the camera's near" in err
    report = json.loads((frames / "report.json").read_text())
    (warning,) = report["warnings"]
    assert "author a smaller clippingRange on the camera" in warning

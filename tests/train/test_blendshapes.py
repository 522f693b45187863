"""Blend shapes as rig parameters, end to end (issue 23): a character with blend shapes is
captured, trained and exported with its weights in the network's input, and the runtime
feeds the animation's weights to it; a rig without blend shapes is unchanged."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from pxr import Usd

from rigspace.capture.settings import CaptureOverrides
from rigspace.sdk.bundle import BundleError
from rigspace.sdk.model import BundleModel
from tests.blendshapes import (
    CHARACTER,
    add_face_binding,
    send_face,
    trained_face,
    write_blendshape_character,
)

pytest.importorskip("torch", reason="training needs the train extra (torch)")

SMALL = CaptureOverrides(views=4, elevations=(0.0,), resolution=32, frames_per_item=4)
SHAPES = ["smile", "blink", "jawOpen", "frown", "brow"]


@pytest.fixture(scope="module")
def face(tmp_path_factory):
    return write_blendshape_character(tmp_path_factory.mktemp("face"))


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return trained_face(tmp_path_factory)[1]


def test_the_bundle_names_its_blend_shapes_and_its_graph_reads_them(bundle):
    import onnxruntime as ort

    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["blend_shapes"] == SHAPES
    assert manifest["torch"]["blend_shapes"] == len(SHAPES)
    run = json.loads((bundle.parent / "run" / "run.json").read_text())  # trained_face's
    assert run["blend_shapes"] == SHAPES
    trunk = ort.InferenceSession(str(bundle / manifest["trunk"]["graphs"]["trunk"]))
    (rig,) = trunk.get_inputs()
    assert rig.name == "rig" and rig.shape[1] == 2 * 6 + len(SHAPES)
    assert manifest["torch"]["check"]["ok"]  # the torch predictor agrees with the graphs


def test_the_weights_change_the_prediction_and_bad_ones_are_named(bundle):
    model = BundleModel(bundle, predictor="onnxruntime")
    rotations = np.tile(np.array([1, 0, 0, 0, 1, 0], np.float32), 2)
    rows = np.stack([np.concatenate([rotations, w]) for w in (np.zeros(5), np.ones(5))])
    out = model.predict(rows.astype(np.float32), 32)
    assert np.abs(out["albedo"][0] - out["albedo"][1]).max() > 1e-4
    with pytest.raises(BundleError, match=r"\(N, 17\) \(2 joints x 6 \+ 5 blend shape weights\)"):
        model.predict(rows[:, :12], 32)
    rows[1, 12 + SHAPES.index("jawOpen")] = np.nan
    with pytest.raises(BundleError, match=r"sample 1, blend shape jawOpen"):
        model.predict(rows, 32)


def _scene_with(face, bundle, tmp_path):
    stage = Usd.Stage.Open(str(face))
    stage.GetPrimAtPath(CHARACTER).GetAttribute("rigspace:model").Set(str(bundle))
    path = tmp_path / "shot.usda"
    stage.GetRootLayer().Export(str(path))
    return path


def test_the_runtime_feeds_the_animations_weights_and_re_evaluates_when_only_they_change(
    face, bundle, tmp_path
):
    """The face's joints hold still from time code 12 on (the neck stops bending) while its
    weights are those of 12: a copy whose weights keep changing must be evaluated each frame,
    not reused as 'the same pose'."""
    from rigspace.runtime.engine import Engine, EngineSettings

    stage = Usd.Stage.Open(str(face))
    anim = stage.GetPrimAtPath("/World/Asset/Skel/Anim")
    rotations = anim.GetAttribute("rotations")
    still = rotations.Get(6)
    for t in range(13):
        rotations.Set(still, t)  # the pose never changes; the weights do
    stage.GetPrimAtPath(CHARACTER).GetAttribute("rigspace:model").Set(str(bundle))
    scene = tmp_path / "still.usda"
    stage.GetRootLayer().Export(str(scene))
    engine = Engine(
        scene, EngineSettings(camera="/World/Camera", width=96, height=64, renderer="gl")
    )
    try:
        decisions = []
        frames = []
        for t in (3.0, 4.0, 4.0):
            frame = engine.render(t)
            (entry,) = frame.report.characters
            decisions.append(entry["decision"])
            frames.append(frame.beauty.copy())
    finally:
        engine.close()
    assert decisions == ["evaluated", "evaluated", "reused"]  # same weights: reused
    assert np.abs(frames[0] - frames[1]).max() > 0  # the weights reached the image


def test_a_model_whose_blend_shapes_the_character_lacks_is_named(face, bundle, tmp_path):
    from rigspace.sdk.validation import validate

    other = tmp_path / "bundle"
    shutil.copytree(bundle, other)
    path = other / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["blend_shapes"] = [*SHAPES[:-1], "sneer"]
    path.write_text(json.dumps(manifest))
    scene = _scene_with(face, other, tmp_path)
    found = [
        f
        for f in validate(Usd.Stage.Open(str(scene)), include_usd=False)
        if "ModelBlendShapesMissing" in f.code
    ]
    assert found and "sneer" in found[0].message and "render" in found[0].blocks


def _live_face(face, bundle, tmp_path, port):
    """The face with its model and a VMC binding (the neck and head by name: a face stream)."""
    stage = Usd.Stage.Open(str(face))
    prim = stage.GetPrimAtPath(CHARACTER)
    prim.GetAttribute("rigspace:model").Set(str(bundle))
    add_face_binding(prim, port, 30.0)
    path = tmp_path / "live_face.usda"
    stage.GetRootLayer().Export(str(path))
    return path


def test_a_live_vmc_face_stream_moves_the_rendered_face(face, bundle, tmp_path):
    """An independent sender's weights reach the network: by exact name (jawOpen), by a VRM
    preset ("Blink" drives the character's blink), loosely (Frown_ -> frown); the rendered
    face changes with them; a name the face lacks is ignored."""
    from rigspace.runtime.engine import Engine, EngineSettings
    from tests.conftest import free_port
    from tests.runtime.live.conftest import wait_for

    port = free_port()
    scene = _live_face(face, bundle, tmp_path, port)
    with Engine(
        scene, EngineSettings(camera="/World/Camera", width=96, height=64, renderer="gl")
    ) as engine:
        engine.render(6.0)  # opens the source
        runtime = engine.live.characters[CHARACTER].runtimes[0]
        frames = {}
        for k, jaw in enumerate((0.0, 1.0)):
            sent = {"jawOpen": jaw, "Blink": 1.0, "Frown_": 0.25, "tongueOut": 1.0}
            send_face(port, sent, 0.1 * (k + 1))
            assert wait_for(lambda j=jaw: runtime.buffer.pose().weights.get("jawOpen") == j)
            assert wait_for(lambda: engine.render(6.0) is not None and not runtime.fading)
            frame = engine.render(6.0)
            frames[jaw] = frame.beauty.copy()
            weights = engine.live.weights(engine.characters[0], 6.0)
            shapes = engine.characters[0].rig.blend_shapes
            got = dict(zip(shapes, weights.round(4).tolist(), strict=True))
            assert got["jawOpen"] == jaw and got["blink"] == 1.0 and got["frown"] == 0.25
            assert got["smile"] == pytest.approx(0.6)  # not sent: the animation's at 6
        assert runtime.counters().malformed == 0
    assert np.abs(frames[0.0] - frames[1.0]).max() > 1e-3


def test_eval_measures_the_whole_character_and_says_why_there_is_no_face_region(bundle, capsys):
    """rigspace eval on a character with blend shapes adds albedo PSNR over the character's
    pixels; the shapes' own region needs texture charts, which this untextured face lacks."""
    from rigspace.sdk.cli import main

    dataset = bundle.parent / "ds"  # trained_face's
    assert main(["eval", str(bundle), str(dataset), "--no-baselines", "--limit", "4"]) == 0
    out, err = capsys.readouterr()
    assert "albedo PSNR over the character (every pixel the character covers" in out
    assert re.search(r"over the character \(every pixel .*\): model \d+\.\d\d dB", out)
    assert "measured as a whole only" in err and "over the face" not in out
    assert (
        main(["eval", str(bundle), str(dataset), "--no-baselines", "--limit", "4", "--json"]) == 0
    )
    row = json.loads(capsys.readouterr().out)["rows"][0]
    assert np.isfinite(row["albedo_psnr@character"])
    assert row["albedo_psnr@character"] < row["albedo_psnr"]  # the black background is easy

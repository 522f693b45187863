"""A character delivered as point caches with its controls, end to end (issue 36): the arm
(tests/point_caches.py) is captured by `rigspace capture`, trained by `rigspace train --preset
tiny --steps 3` and drawn by the Engine through `rigspace render`; its control travels in the
rig vector after the (absent) blend shape weights, from the dataset to the bundle, the
runtime, the live sources and the takes."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from pxr import Sdf, Usd

from rigspace.sdk.bundle import BundleError, read_manifest
from rigspace.sdk.cli import main
from rigspace.sdk.model import BundleModel
from tests.point_caches import CHARACTER, CONTROL, FRAMES, bulge_at, trained_arm

pytest.importorskip("torch", reason="training needs the train extra (torch)")

RESOLUTION = 16
JOINTS = 2


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    return trained_arm(tmp_path_factory)


def test_the_dataset_records_the_control_after_the_rig_and_lists_its_range(arm):
    _, bundle = arm
    dataset = bundle.parent / "ds"
    manifest = json.loads((dataset / "manifest.json").read_text())
    assert manifest["controls"] == [{"name": CONTROL, "range": [0.0, 1.0]}]
    assert "blend_shapes" not in manifest and "controls" in manifest["params"]
    settings = json.loads((dataset / "capture.json").read_text())
    assert settings["controls"] == [{"name": CONTROL, "range": [0.0, 1.0]}]
    with np.load(dataset / "params.npz") as table:
        assert "blend" not in table.files and table["controls"].shape == (len(table["path"]), 1)
        expected = [bulge_at(t) for t in table["time"]]
        np.testing.assert_allclose(table["controls"][:, 0], expected, atol=1e-6)
        assert len(np.unique(table["time"])) == FRAMES  # every cached frame
    from rigspace.capture.dataset import read_manifest as read_dataset

    assert [c.name for c in read_dataset(dataset).controls] == [CONTROL]


def test_the_bundle_names_its_control_and_its_graph_reads_it(arm):
    import onnxruntime as ort

    _, bundle = arm
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["controls"] == [{"name": CONTROL, "range": [0.0, 1.0]}]
    assert manifest["torch"]["controls"] == 1 and "blend_shapes" not in manifest
    assert read_manifest(bundle).controls[0].range == (0.0, 1.0)
    trunk = ort.InferenceSession(str(bundle / manifest["trunk"]["graphs"]["trunk"]))
    (rig,) = trunk.get_inputs()
    assert rig.name == "rig" and rig.shape[1] == JOINTS * 6 + 1
    assert manifest["torch"]["check"]["ok"]  # the torch predictor agrees with the graphs


def test_the_control_changes_the_prediction_and_a_bad_one_is_named(arm):
    _, bundle = arm
    model = BundleModel(bundle, predictor="onnxruntime")
    rotations = np.tile(np.array([1, 0, 0, 0, 1, 0], np.float32), JOINTS)
    rows = np.stack([np.concatenate([rotations, [v]]) for v in (0.0, 1.0)]).astype(np.float32)
    out = model.predict(rows, RESOLUTION)
    assert np.abs(out["albedo"][0] - out["albedo"][1]).max() > 0  # the input reaches the maps
    with pytest.raises(BundleError, match=r"\(N, 13\) \(2 joints x 6 \+ 1 control values\)"):
        model.predict(rows[:, :12], RESOLUTION)
    rows[1, 12] = np.nan
    with pytest.raises(BundleError, match=r"sample 1, control bulge"):
        model.predict(rows, RESOLUTION)


def test_rigspace_render_draws_the_cached_character_with_the_engine(arm, tmp_path, capsys):
    scene, _ = arm
    out = tmp_path / "frames"
    code = main(["render", str(scene), "--out", str(out), "--frames", "0:4", "--step", "2",
                 "--resolution", "64x36"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert sorted(p.name for p in out.glob("*.png") if p.name.startswith("frame_")) == [
        "frame_000000.0.png", "frame_000002.0.png", "frame_000004.0.png",
    ]  # fmt: skip
    report = json.loads((out / "report.json").read_text())
    frames = report.get("frames", report)
    assert frames, report


def test_eval_measures_the_model_on_the_cached_frames(arm, capsys):
    _, bundle = arm
    dataset = bundle.parent / "ds"
    assert main(["eval", str(bundle), str(dataset), "--no-baselines", "--limit", "4"]) == 0
    assert "| model |" in capsys.readouterr().out


def test_the_runtime_feeds_the_stage_control_and_re_evaluates_when_only_it_changes(arm, tmp_path):
    """The arm's elbow holds still while its control keeps moving: each new value is a new
    evaluation (not 'the same pose'); a repeated one is reused."""
    from rigspace.runtime.engine import Engine
    from rigspace.runtime.settings import EngineSettings

    scene, _ = arm
    stage = Usd.Stage.Open(str(scene))
    rotations = stage.GetPrimAtPath("/World/Asset/Skel/Anim").GetAttribute("rotations")
    still = rotations.Get(6)
    for t in range(FRAMES):
        rotations.Set(still, t)
    path = tmp_path / "still.usda"
    stage.GetRootLayer().Export(str(path))
    with Engine(
        path, EngineSettings(camera="/World/Camera", width=64, height=48, renderer="gl")
    ) as engine:
        character = engine.characters[0]
        assert character.weights(3.0) == pytest.approx([bulge_at(3.0)])
        # A source of the blend shape weights alone (none here) takes the stage's controls.
        assert character.weights(3.0, np.zeros(0, np.float32)) == pytest.approx([bulge_at(3.0)])
        decisions = []
        for t in (3.0, 4.0, 4.0):
            (entry,) = engine.render(t).report.characters
            decisions.append(entry["decision"])
    assert decisions[1:] == ["evaluated", "reused"] and decisions[0] in ("evaluated", "skipped")


def test_a_model_whose_controls_the_character_lacks_is_named(arm, tmp_path):
    from rigspace.runtime.character import NeuralCharacter
    from rigspace.sdk.errors import SceneError
    from rigspace.sdk.validation import validate

    scene, bundle = arm
    other = tmp_path / "bundle"
    shutil.copytree(bundle, other)
    path = other / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["controls"] = [{"name": "twist", "range": [-1.0, 1.0]}]
    path.write_text(json.dumps(manifest))
    stage = Usd.Stage.Open(str(scene))
    stage.GetPrimAtPath(CHARACTER).GetAttribute("rigspace:model").Set(str(other))
    shot = tmp_path / "shot.usda"
    stage.GetRootLayer().Export(str(shot))
    found = [
        f
        for f in validate(Usd.Stage.Open(str(shot)), include_usd=False)
        if f.code == "ModelControlsMissing"
    ]
    assert found and "twist" in found[0].message and "render" in found[0].blocks
    opened = Usd.Stage.Open(str(shot))
    with pytest.raises(SceneError, match="reads controls the character does not declare: twist"):
        NeuralCharacter(
            opened.GetPrimAtPath(CHARACTER), BundleModel(other, predictor="onnxruntime")
        )


def _live_arm(scene, tmp_path, port):
    """The arm with a VMC binding (the elbow by name)."""
    stage = Usd.Stage.Open(str(scene))
    prim = stage.GetPrimAtPath(CHARACTER)
    prim.ApplyAPI("RigspaceLiveBindingAPI", "rig")
    for name, kind, value in (
        ("url", Sdf.ValueTypeNames.String, f"vmc://127.0.0.1:{port}"),
        ("sourceBones", Sdf.ValueTypeNames.TokenArray, ["RightLowerArm"]),
        ("targetJoints", Sdf.ValueTypeNames.TokenArray, ["elbow"]),
        ("timeoutSeconds", Sdf.ValueTypeNames.Float, 30.0),
    ):
        prim.CreateAttribute(f"rigspace:live:rig:{name}", kind).Set(value)
    path = tmp_path / "live_arm.usda"
    stage.GetRootLayer().Export(str(path))
    return path


def test_live_controls_arrive_by_vmc_and_plain_osc_clamped_into_their_range(arm, tmp_path):
    """A VMC sender's Blend/Val of the control's name sets it like a blend shape; a plain OSC
    /rigspace/control NAME VALUE (no VMC framing) sets it at once; a value past the range is
    its end; the take records what the frames used and replays it."""
    from pythonosc.udp_client import SimpleUDPClient

    from rigspace.runtime.engine import Engine
    from rigspace.runtime.live.record import TakeRecorder, read_take
    from rigspace.runtime.settings import EngineSettings
    from tests.conftest import free_port
    from tests.runtime.live.conftest import wait_for

    scene, _ = arm
    port = free_port()
    path = _live_arm(scene, tmp_path, port)
    with Engine(
        path, EngineSettings(camera="/World/Camera", width=64, height=48, renderer="gl")
    ) as engine:
        engine.render(6.0)  # opens the source
        character = engine.characters[0]
        runtime = engine.live.characters[CHARACTER].runtimes[0]
        client = SimpleUDPClient("127.0.0.1", port)
        client.send_message(
            "/VMC/Ext/Bone/Pos", ["RightLowerArm", 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
        )
        client.send_message("/VMC/Ext/Blend/Val", [CONTROL, 0.25])
        client.send_message("/VMC/Ext/Blend/Apply", [])
        client.send_message("/VMC/Ext/OK", [1])
        assert wait_for(lambda: runtime.buffer.pose().weights.get(CONTROL) == 0.25)
        assert wait_for(lambda: engine.render(6.0) is not None and not runtime.fading)
        assert engine.live.weights(character, 6.0) == pytest.approx([0.25])
        client.send_message("/rigspace/control", [CONTROL, 5.0])  # past the range: clamped
        assert wait_for(lambda: runtime.buffer.pose().weights.get(CONTROL) == 5.0)
        engine.render(7.0)
        weights = engine.live.weights(character, 7.0)
        assert weights == pytest.approx([1.0])
        assert character.weights(7.0, weights) == pytest.approx([1.0])  # what the network reads
        assert runtime.counters().malformed == 0
        recorder = TakeRecorder(character.rig.joints, character.rig.blend_shapes, [CONTROL])
        local = np.asarray(character.rig.local_transforms(7.0))
        recorder.add(7.0, local, weights)
        recorder.add(8.0, local, np.array([0.5]))
    take = read_take(recorder.write(tmp_path / "take.usda", 24.0))
    assert take.blend_shapes == (CONTROL,)
    np.testing.assert_allclose(take.blend_weights[:, 0], [1.0, 0.5])
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "take.usda"))
    assert layer.GetAttributeAtPath(f"/Take.rigspace:control:{CONTROL}:value") is not None


def test_an_override_of_a_control_reaches_the_network(arm):
    """`rigspace view`'s control sliders and Engine.set_weights: an override of the control
    replaces the stage's value in the frame's rig vector."""
    from rigspace.runtime.engine import Engine
    from rigspace.runtime.settings import EngineSettings

    scene, _ = arm
    with Engine(
        scene, EngineSettings(camera="/World/Camera", width=64, height=48, renderer="gl")
    ) as engine:
        engine.set_weights(CHARACTER, {CONTROL: 0.75})
        (entry,) = engine.render(3.0).report.characters
        character = engine.characters[0]
        assert character.weights(
            3.0, engine.character_stages.weights_of(character, 3.0)
        ) == pytest.approx([0.75])
        assert entry["decision"] in ("evaluated", "skipped")

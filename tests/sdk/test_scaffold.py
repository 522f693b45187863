"""`rigspace init`: a shot scene around a raw character, every value derived, inspect passing."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from rigspace.apps.scaffold import init_scene
from rigspace.sdk import schema, validation
from rigspace.sdk.cli import main
from rigspace.sdk.errors import SceneError
from tests.conftest import CESIUM_MAN

ROBOT = """#usda 1.0
(
    defaultPrim = "Robot"
    metersPerUnit = 1
    upAxis = "Y"
    timeCodesPerSecond = 24
)

def SkelRoot "Robot" (prepend apiSchemas = ["SkelBindingAPI"])
{{
    rel skel:animationSource = </Robot/Anim>
    rel skel:skeleton = </Robot/Skel>

    def Skeleton "Skel"
    {{
        uniform token[] joints = ["root", "root/hips", "root/hips/head"]
        uniform matrix4d[] bindTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1)), ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0.9,0,1)), ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,1.6,0,1))]
        uniform matrix4d[] restTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1)), ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0.9,0,1)), ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0.7,0,1))]
    }}

    def SkelAnimation "Anim"
    {{
        uniform token[] joints = ["root", "root/hips", "root/hips/head"]
        quatf[] rotations.timeSamples = {{ 1: [(1,0,0,0), (1,0,0,0), (1,0,0,0)], 24: [(1,0,0,0), (0.9659258,0,0.258819,0), (1,0,0,0)] }}
        float3[] translations = [(0, 0, 0), (0, 0.9, 0), (0, 0.7, 0)]
        half3[] scales = [(1, 1, 1), (1, 1, 1), (1, 1, 1)]
    }}

    def Mesh "Body" (prepend apiSchemas = ["SkelBindingAPI"])
    {{
        int[] faceVertexCounts = [4, 4]
        int[] faceVertexIndices = [0, 1, 2, 3, 4, 5, 6, 7]
        point3f[] points = [(-0.2, 0, 0), (0.2, 0, 0), (0.2, 1.8, 0), (-0.2, 1.8, 0), (0, 0, -0.2), (0, 0, 0.2), (0, 1.8, 0.2), (0, 1.8, -0.2)]
        int[] primvars:skel:jointIndices = [1, 1, 1, 1, 1, 1, 1, 1] (
            interpolation = "vertex"
            elementSize = 1
        )
        float[] primvars:skel:jointWeights = [1, 1, 1, 1, 1, 1, 1, 1] (
            interpolation = "vertex"
            elementSize = 1
        )
        matrix4d primvars:skel:geomBindTransform = ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1))
        rel skel:skeleton = </Robot/Skel>
    }}
{extra}
}}
"""


def robot(tmp_path, extra: str = "", name: str = "robot.usda"):
    path = tmp_path / name
    path.write_text(ROBOT.format(extra=extra))
    return path


def test_a_rig_rooted_at_its_feet_is_aimed_at_its_middle_and_framed_whole(tmp_path):
    scene = tmp_path / "shot.usda"
    derived = init_scene(robot(tmp_path), scene)
    assert derived.root_joint == "root" and derived.look_at_joint == "hips"  # not the feet
    assert derived.clip == ("Anim", 1.0, 24.0)
    stage = Usd.Stage.Open(str(scene))
    validation.require_valid(stage, "capture")  # inspect's capture rules: no error
    prim = stage.GetPrimAtPath(derived.character)
    ring = schema.read_capture_ring(prim)
    # The whole 1.8-unit figure within the square ring image around the hips, with a margin.
    half = np.tan(np.arctan(ring.horizontal_aperture / 2 / ring.focal_length))
    assert ring.radius * half > 0.95 > ring.radius * half / 2.5
    near, far = ring.clipping_range
    assert 0 < near < ring.radius - 1.0 and far > ring.radius + 1.0
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1 and stage.GetEndTimeCode() == 24
    camera = UsdGeom.Camera(stage.GetPrimAtPath(derived.camera))
    assert camera and stage.GetPrimAtPath("/World/Sun") and stage.GetPrimAtPath("/World/Sky")


def test_cesium_man_gets_the_values_the_hand_made_sample_has(tmp_path):
    derived = init_scene(CESIUM_MAN, tmp_path / "shot.usda")
    assert derived.look_at_joint == "Skeleton_torso_joint_1"  # samples/scenes/cesium_man.usda
    assert 2.5 < derived.radius < 4.0  # the sample's hand-chosen radius: 3
    assert derived.clip[1:] == (1.0, 48.0)


def test_init_never_overwrites_and_leaves_nothing_behind_on_failure(tmp_path):
    scene = tmp_path / "shot.usda"
    scene.write_text("mine")
    with pytest.raises(SceneError, match="never overwrites"):
        init_scene(robot(tmp_path), scene)
    assert scene.read_text() == "mine"
    still = robot(tmp_path, name="still.usda")
    still.write_text(
        still.read_text().replace(
            "rotations.timeSamples = { 1:",
            "rotations = [(1,0,0,0), (1,0,0,0), (1,0,0,0)]\n        quatf[] unused.timeSamples = { 1:",
        )
    )
    with pytest.raises(SceneError, match="no animation over time"):
        init_scene(still, tmp_path / "still_shot.usda")
    assert not (tmp_path / "still_shot.usda").exists()


def test_several_skeletons_are_listed_and_one_is_chosen(tmp_path):
    second = '    def Skeleton "Other"\n    {\n        uniform token[] joints = ["a"]\n    }\n'
    asset = robot(tmp_path, extra=second)
    with pytest.raises(SceneError) as info:
        init_scene(asset, tmp_path / "a.usda")
    assert "/Robot/Skel" in str(info.value) and "/Robot/Other" in str(info.value)
    assert "--skeleton" in str(info.value)
    derived = init_scene(asset, tmp_path / "b.usda", skeleton="/Robot/Skel")
    assert derived.skeleton == "/World/robot/Asset/Skel"


def test_an_asset_without_a_skeleton_says_what_is_missing(tmp_path):
    plain = tmp_path / "prop.usda"
    plain.write_text('#usda 1.0\n(defaultPrim = "Box")\ndef Cube "Box" {}\n')
    with pytest.raises(SceneError, match="no UsdSkel Skeleton"):
        init_scene(plain, tmp_path / "shot.usda")


def test_the_command_prints_what_it_found_and_the_next_commands(tmp_path, capsys):
    scene = tmp_path / "shot.usda"
    assert main(["init", str(robot(tmp_path)), "--out", str(scene)]) == 0
    out = capsys.readouterr().out
    assert "look-at joint   hips: nearest the skinned meshes' centre" in out
    assert f"rigspace render {scene} --model {tmp_path / 'shot_model'}" in out
    # A budget: the preset alone is 4,000 steps a level, hours on a CPU.
    train = next(line for line in out.splitlines() if "rigspace train" in line)
    assert f"rigspace train {tmp_path / 'shot_data'} --out {tmp_path / 'shot_model'}" in train
    assert "--minutes 60" in train
    assert main(["inspect", str(scene)]) == 0


def test_capture_warns_when_the_look_at_joint_is_far_from_the_characters_middle(tmp_path):
    """A ring aimed at the root of a rig rooted at its feet frames the feet: capture says so
    and names the joint in the middle (the one init picks)."""
    from rigspace.capture.settings import resolve_settings

    derived = init_scene(robot(tmp_path), tmp_path / "shot.usda")
    feet = tmp_path / "feet.usda"
    feet.write_text(
        '#usda 1.0\n(\n    subLayers = [@./shot.usda@]\n)\nover "World"\n{\n'
        '    over "robot"\n    {\n        uniform token rigspace:lookAtJoint = "root"\n    }\n}\n'
    )
    said: list[str] = []
    resolve_settings(feet, derived.character, warn=said.append)
    (warning,) = [w for w in said if "look-at joint" in w]
    assert "look-at joint root is" in warning and 'rigspace:lookAtJoint = "hips"' in warning
    said.clear()
    resolve_settings(tmp_path / "shot.usda", derived.character, warn=said.append)
    assert not [w for w in said if "look-at joint" in w]  # init's choice is the middle


def test_a_non_finite_derived_value_is_named_and_nothing_is_written(tmp_path, capsys):
    """A mesh point at NaN made the radius and clipping range NaN: init wrote the scene, then
    its own check refused it, and a rerun was refused because the file existed."""
    asset = robot(tmp_path, name="nan.usda")
    asset.write_text(
        asset.read_text().replace("(0.2, 0, 0), (0.2, 1.8, 0)", "(nan, 0, 0), (0.2, 1.8, 0)")
    )
    scene = tmp_path / "shot" / "nan_shot.usda"
    assert main(["init", str(asset), "--out", str(scene)]) == 2
    err = capsys.readouterr().err
    assert "skinned point position that is NaN or infinite at time code 1" in err, err
    assert not scene.exists() and not list(tmp_path.glob("shot/*"))  # no temporary left
    asset.write_text(ROBOT.format(extra=""))  # fixed: the same command goes through
    assert main(["init", str(asset), "--out", str(scene)]) == 0
    assert "radius" in capsys.readouterr().out and scene.is_file()
    assert [p.name for p in scene.parent.iterdir()] == [scene.name]


def test_a_scene_init_would_write_invalid_is_not_written(tmp_path, monkeypatch):
    """Whatever inspect's capture rules refuse is refused before the file exists."""
    from rigspace.apps import scaffold

    monkeypatch.setattr(scaffold, "RESOLUTION", 100)  # not a power of two: capture refuses it
    scene = tmp_path / "shot.usda"
    with pytest.raises(SceneError, match="resolution"):
        init_scene(robot(tmp_path), scene)
    assert not scene.exists() and [p.name for p in tmp_path.iterdir()] == ["robot.usda"]


def test_time_codes_drifted_by_the_exporter_are_written_whole(tmp_path):
    """An export with samples at 1.0000000521 and 24.0000012517 (float32 drift): the scene's
    range and clip are 1-24, not startTimeCode = 1.0000000521540642."""
    asset = robot(tmp_path, name="drift.usda")
    asset.write_text(
        asset.read_text()
        .replace("{ 1: [", "{ 1.0000000521540642: [")
        .replace("24: [(1,0,0,0), (0.96", "24.00000125169754: [(1,0,0,0), (0.96")
    )
    scene = tmp_path / "shot.usda"
    derived = init_scene(asset, scene)
    text = scene.read_text()
    assert "startTimeCode = 1\n" in text and "endTimeCode = 24\n" in text
    assert "clipRanges = [(1, 24)]" in text and derived.clip == ("Anim", 1.0, 24.0)
    stage = Usd.Stage.Open(str(scene))
    ring = schema.read_capture_ring(stage.GetPrimAtPath(derived.character))
    assert [tuple(r) for r in ring.clip_ranges] == [(1.0, 24.0)]

"""A rig that is not UsdSkel's (issue 36): point-cached meshes drawn as the stage evaluates
them, named float controls after the blend shape weights, and the rules that refuse a
malformed cache by name before anything is written."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Sdf, Usd

from rigspace.sdk import validation
from rigspace.sdk.cli import main
from rigspace.sdk.errors import SceneError
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.stage import open_stage
from tests.point_caches import (
    CHARACTER,
    CONTROL,
    FRAMES,
    MESH,
    arm_mesh,
    bulge_at,
    cached_points,
    write_point_cache_character,
)

POINTS_TOLERANCE = 1e-6
"""float32 points read back from the layer against the same float32 values written."""


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    return write_point_cache_character(tmp_path_factory.mktemp("arm"))


def _rig(path) -> CharacterRig:
    stage = open_stage(path)
    rig = CharacterRig(stage.GetPrimAtPath(CHARACTER))
    rig.stage_ref = stage  # keep the stage alive as long as the rig
    return rig


def test_the_meshes_are_the_cache_and_the_controls_follow_the_weights(arm):
    rig = _rig(arm)
    assert rig.joints == ["root", "root/elbow"] and rig.blend_shapes == ()
    assert rig.scalar_names == (CONTROL,) and rig.cached_meshes[0].GetPath() == MESH
    assert not rig.has_skinned_meshes and len(rig.time_samples()) == FRAMES
    rest = arm_mesh()[0]
    for t in (0.0, 5.0, 12.0):
        (mesh,) = rig.posed_meshes(t)
        assert np.abs(mesh.points - cached_points(rest, t)).max() < POINTS_TOLERANCE
        assert rig.scalars(t) == pytest.approx([bulge_at(t)])
    # A weight vector of the rig's scalars (controls included) poses the same meshes.
    (again,) = rig.posed_meshes(5.0, weights=rig.scalars(5.0))
    assert np.array_equal(again.points, rig.posed_meshes(5.0)[0].points)
    assert rig.dominant_joints()[0].tolist() == [-1] * len(rest)  # no joint skins it


def test_a_frame_the_cache_cannot_give_is_a_scene_error(tmp_path):
    rig = _rig(write_point_cache_character(tmp_path, broken="points"))
    with pytest.raises(
        SceneError, match=r"Point cache /World/Asset/Arm has 107 points for its 108"
    ):
        rig.posed_meshes(5.0)


@pytest.mark.parametrize(
    ("broken", "code", "said"),
    [
        ("frames", "CacheFramesDisagree", "has 13 frames (0-12), but point cache /World/Asset/Arm "
         "has 14 frames (0-13)"),
        ("points", "CachePointCount", "another point count in 1 of its 13 frames, the first at "
         "time 5 with 107 points where its faces need 108"),
        ("nan", "CachePointsNotFinite", "NaN or Inf points in 1 frame, the first at time 7"),
    ],
)  # fmt: skip
def test_a_malformed_cache_is_named_and_capture_writes_nothing(
    tmp_path, capsys, broken, code, said
):
    scene = write_point_cache_character(tmp_path / "scene", broken=broken)
    found = [f for f in validation.validate(open_stage(scene), include_usd=False) if f.code == code]
    assert found and said in found[0].message and "Fix:" in found[0].message
    assert all(f.severity == "error" and f.blocks == ("capture",) for f in found)
    out = tmp_path / "ds"
    assert main(["capture", str(scene), "--out", str(out), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert said in err and "Traceback" not in err and not out.exists()


def test_a_control_that_never_moves_is_a_warning(tmp_path, capsys):
    scene = write_point_cache_character(tmp_path, broken="constant")
    findings = validation.validate(open_stage(scene), include_usd=False)
    (found,) = [f for f in findings if f.code == "ControlConstant"]
    assert found.severity == "warning" and "cannot learn" in found.message
    warned: list[str] = []
    stage = open_stage(scene)
    validation.require_valid(stage, "capture", [stage.GetPrimAtPath(CHARACTER)], warn=warned.append)
    assert any("never moves" in w for w in warned)  # capture goes on, and says so


def _edited(scene, tmp_path, edit) -> Usd.Stage:
    stage = Usd.Stage.Open(str(scene))
    edit(stage.GetPrimAtPath(CHARACTER))
    path = tmp_path / "edited.usda"
    stage.GetRootLayer().Export(str(path))
    return open_stage(path)


@pytest.mark.parametrize(
    ("edit", "code", "said"),
    [
        (lambda p: p.GetAttribute(f"rigspace:control:{CONTROL}:range").Set((1.0, 0.0)),
         "ControlRange", "does not have low < high"),
        (lambda p: p.GetAttribute(f"rigspace:control:{CONTROL}:value").Set(float("nan"), 3.0),
         "ControlNotFinite", "is NaN or Inf at time 3"),
        (lambda p: p.GetRelationship("rigspace:pointCache:meshes").SetTargets(["/World/Nothing"]),
         "PointCacheTargetMissing", "targets /World/Nothing, which does not exist"),
        (lambda p: p.GetRelationship("rigspace:pointCache:meshes").SetTargets([]),
         "PointCacheEmpty", "targets nothing"),
    ],
)  # fmt: skip
def test_a_bad_control_or_cache_target_is_named(arm, tmp_path, edit, code, said):
    stage = _edited(arm, tmp_path, edit)
    found = [f for f in validation.validate(stage, include_usd=False) if f.code == code]
    assert found and said in found[0].message and "Fix:" in found[0].message


def test_a_control_may_not_take_a_blend_shapes_name(tmp_path):
    from tests.blendshapes import write_blendshape_character

    scene = write_blendshape_character(tmp_path / "face")

    def edit(prim):
        prim.ApplyAPI("RigspaceControlAPI", "smile")
        prim.CreateAttribute("rigspace:control:smile:value", Sdf.ValueTypeNames.Float).Set(0.5, 0)

    stage = _edited(scene, tmp_path, edit)
    (found,) = [
        f for f in validation.validate(stage, include_usd=False) if f.code == "ControlNameTaken"
    ]
    assert "has the name of one of the character's blend shapes" in found.message


def test_without_skinned_meshes_the_error_names_the_point_cache_too(arm, tmp_path):
    def edit(prim):
        prim.RemoveAPI("RigspacePointCacheAPI")

    stage = _edited(arm, tmp_path, edit)
    (found,) = [
        f for f in validation.validate(stage, include_usd=False) if f.code == "NoSkinnedMesh"
    ]
    assert "rigspace:pointCache:meshes" in found.message


def test_inspect_says_the_cached_frames_and_which_controls_vary(arm, tmp_path, capsys):
    assert main(["inspect", str(arm), "--no-usd-validators"]) == 0
    out = capsys.readouterr().out
    assert "point cache of 13 frames" in out
    assert "pose space: 13 cached frames (0-12), point caches /World/Asset/Arm" in out
    assert f"varying: {CONTROL}" in out and "never varying (cannot be learned): none" in out
    constant = write_point_cache_character(tmp_path, broken="constant")
    assert main(["inspect", str(constant), "--no-usd-validators", "--json"]) == 0
    import json

    report = json.loads(capsys.readouterr().out)
    (hero,) = [p for p in report["prims"] if p["path"] == CHARACTER]
    assert hero["rig"]["controlsConstant"] == [CONTROL] and hero["rig"]["cachedFrames"] == 13

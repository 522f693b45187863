"""skel:animationSource authored on the SkelRoot and inherited by the Skeleton, as exporters write it.

The fixture is the sample character with its binding moved from the Skeleton to the
SkelRoot (SkelBindingAPI applied there), referenced by a scene as a neural character.
inspect, validation, posing and capture must all find the animation, as UsdSkel does.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, UsdSkel

from rigspace.capture.pipeline import capture
from rigspace.capture.settings import CaptureOverrides
from rigspace.sdk import validation
from rigspace.sdk.bindings import bound_animation, ignored_animation_sources
from rigspace.sdk.cli import main
from rigspace.sdk.errors import SceneError
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.stage import open_stage
from tests.conftest import REPO

SAMPLE = REPO / "samples" / "character"
HERO = "/World/Hero"
ANIM = "/World/Hero/Asset/Skel/Anim"
SCENE = """#usda 1.0
(
    defaultPrim = "World"
    metersPerUnit = 0.01
    upAxis = "Y"
    startTimeCode = 0
    endTimeCode = 1619
    timeCodesPerSecond = 30
    framesPerSecond = 30
)

def Xform "World"
{
    def RigspaceNeuralCharacter "Hero" (prepend apiSchemas = ["RigspaceCaptureRingAPI"])
    {
        rel rigspace:skeleton = </World/Hero/Asset/Skel>
        uniform token rigspace:lookAtJoint = "pelvis"
        uniform float rigspace:captureRing:radius = 450
        uniform float rigspace:captureRing:focalLength = 35
        uniform float2 rigspace:captureRing:clippingRange = (10, 5000)

        def "Asset" (prepend references = @./character.usdc@)
        {
        }
    }
}
"""


def moved_binding_scene(folder: Path, apply_api: bool = True) -> Path:
    """The sample character with skel:animationSource on its SkelRoot, and a scene using it."""
    layer = Sdf.Layer.CreateNew(str(folder / "character.usdc"))
    layer.TransferContent(Sdf.Layer.FindOrOpen(str(SAMPLE / "sample_character.usda")))
    skeleton = layer.GetPrimAtPath("/Character/Skel")
    skeleton.RemoveProperty(skeleton.relationships["skel:animationSource"])
    root = layer.GetPrimAtPath("/Character")
    rel = Sdf.RelationshipSpec(root, "skel:animationSource", custom=False)
    rel.targetPathList.explicitItems = ["/Character/Skel/Anim"]
    if apply_api:
        root.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=["SkelBindingAPI"]))
    assert layer.Save()
    (folder / "textures").symlink_to(SAMPLE / "textures")
    scene = folder / "scene.usda"
    scene.write_text(SCENE)
    return scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return moved_binding_scene(tmp_path_factory.mktemp("moved"))


def test_the_fixture_binds_on_the_skelroot_only(scene):
    stage = open_stage(scene)
    skeleton = stage.GetPrimAtPath("/World/Hero/Asset/Skel")
    assert not UsdSkel.BindingAPI(skeleton).GetAnimationSourceRel().GetTargets()
    assert bound_animation(skeleton).GetPath() == ANIM  # as UsdSkel.Cache resolves it


def test_inspect_lists_the_inherited_animation_and_no_errors(scene, capsys):
    code = main(["inspect", "--json", str(scene)])
    report = json.loads(capsys.readouterr().out)
    (skeleton,) = [p for p in report["prims"] if p["kind"] == "skeleton"]
    assert skeleton["animationSource"] == ANIM
    assert report["errors"] == [] and code == 0


def test_posing_matches_the_skeletons_own_binding(scene):
    stages = open_stage(scene), open_stage(REPO / "samples" / "scenes" / "previs.usda")
    moved, direct = (CharacterRig(stage.GetPrimAtPath(HERO)) for stage in stages)
    assert str(moved.animation.GetPath()) == ANIM
    for time in (0.0, 400.0, 1300.0):
        # Same character and animation, both at the world origin: the same joint transforms.
        assert np.allclose(moved.world_transforms(time), direct.world_transforms(time), atol=1e-6)


def test_capture_runs_on_the_inherited_binding(scene, tmp_path):
    overrides = CaptureOverrides(views=2, elevations=(0.0,), resolution=16, frames=(10.0, 11.0))
    result = capture(scene, HERO, tmp_path / "ds", overrides, workers=1, progress=False)
    assert result.complete and result.settings.animation == ANIM
    assert result.manifest.counts["train"] == 4  # 2 frames x 2 views


def test_a_skelroot_binding_without_the_api_is_named_in_the_error(tmp_path):
    # UsdSkel ignores skel:animationSource where SkelBindingAPI is not applied: say so.
    stage = open_stage(moved_binding_scene(tmp_path, apply_api=False))
    skeleton = stage.GetPrimAtPath("/World/Hero/Asset/Skel")
    assert bound_animation(skeleton) is None
    assert ignored_animation_sources(skeleton) == ["/World/Hero/Asset"]
    (finding,) = [f for f in validation.validate(stage, include_usd=False) if f.severity == "error"]
    assert finding.code == "NoAnimation" and "/World/Hero/Asset authors" in finding.message
    with pytest.raises(SceneError) as refused:
        CharacterRig(stage.GetPrimAtPath(HERO))
    assert str(refused.value) == finding.message  # posing refuses in inspect's words

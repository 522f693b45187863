"""Blend shapes in posing: applied before skinning exactly as UsdSkel specifies (issue 23)."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdSkel

from rigspace.sdk.posing import CharacterRig
from tests.blendshapes import ANIMATED, CHARACTER, weights_at, write_blendshape_character


@pytest.fixture(scope="module")
def face(tmp_path_factory):
    return write_blendshape_character(tmp_path_factory.mktemp("face"))


@pytest.fixture(scope="module")
def stage(face):
    return Usd.Stage.Open(str(face))  # held: a rig's prims expire with their stage


@pytest.fixture(scope="module")
def rig(stage):
    return CharacterRig(stage.GetPrimAtPath(CHARACTER))


def test_the_character_lists_its_meshes_blend_shapes_and_reads_the_animations_weights(rig):
    assert rig.blend_shapes == ("smile", "blink", "jawOpen", "frown", "brow")  # meshes' order
    for t in (0, 5, 12):
        animated = dict(zip(ANIMATED, weights_at(t), strict=True)) | {"frown": 0.0}
        want = [animated[name] for name in rig.blend_shapes]  # "extra" drives no mesh
        np.testing.assert_allclose(rig.blend_weights(t), want, rtol=1e-6)


def test_posed_points_equal_usdskel_bake_skinning_inbetweens_and_sparse_shapes_included(
    face, rig, tmp_path
):
    """UsdSkel.BakeSkinning (UsdSkel's own blend shapes, then skinning) on a copy of the stage
    is the reference, at time codes where smile passes its 0.5 inbetween and goes past 1."""
    baked = tmp_path / "baked.usda"
    Usd.Stage.Open(str(face)).GetRootLayer().Export(str(baked))
    copy = Usd.Stage.Open(str(baked))
    assert UsdSkel.BakeSkinning(
        UsdSkel.Root(copy.GetPrimAtPath("/World/Asset")), Gf.Interval(0, 12)
    )
    moved = 0.0
    for t in (0, 2, 5, 7, 12):  # smile weight 0, 0.2, 0.5 (the inbetween), 0.7, 1.2
        ours = rig.posed_meshes(t)
        for mesh, name in zip(ours, ("Head", "Brow"), strict=True):
            want = np.array(
                copy.GetPrimAtPath(f"/World/Asset/{name}").GetAttribute("points").Get(t)
            )
            np.testing.assert_allclose(mesh.points, want, atol=2e-6)
        plain = rig.posed_meshes(t, weights=np.zeros(len(rig.blend_shapes)))
        moved = max(moved, float(np.abs(plain[0].points - ours[0].points).max()))
    assert moved > 0.2  # the shapes are large: a posing that ignored them would fail above


def test_weights_given_replace_the_animations(rig):
    """The live seam: weights passed in (character order) are what deform the mesh."""
    only_jaw = np.zeros(len(rig.blend_shapes), np.float32)
    only_jaw[rig.blend_shapes.index("jawOpen")] = 1.0
    rest = rig.posed_meshes(0, weights=np.zeros(len(rig.blend_shapes)))[0].points
    jaw = rig.posed_meshes(0, weights=only_jaw)[0].points
    changed = np.flatnonzero(np.abs(jaw - rest).max(axis=1) > 1e-6)
    np.testing.assert_array_equal(changed, np.arange(16))  # the lowest ring only
    np.testing.assert_allclose(jaw[:16] - rest[:16], np.tile([0, -0.4, 0.1], (16, 1)), atol=1e-6)


def test_inspect_lists_each_meshs_blend_shapes_and_the_animations_weights(face, capsys):
    from rigspace.sdk.cli import main

    assert main(["inspect", str(face)]) == 0
    out = capsys.readouterr().out
    assert "5 blend shape weights" in out  # the SkelAnimation's (one drives no mesh)
    assert "blend shapes smile, blink, jawOpen, frown" in out and "blend shapes brow" in out


def test_a_gamepad_binding_names_only_the_characters_shapes(face, tmp_path):
    from pxr import Sdf

    from rigspace.sdk.validation import validate

    stage = Usd.Stage.Open(str(face))
    prim = stage.GetPrimAtPath(CHARACTER)
    prim.ApplyAPI("RigspaceLiveBindingAPI", "pad")
    prim.CreateAttribute("rigspace:live:pad:url", Sdf.ValueTypeNames.String).Set("gamepad://")
    prim.CreateAttribute("rigspace:live:pad:gamepadShapes", Sdf.ValueTypeNames.StringArray).Set(
        ["ABS_Z:jawOpen", "ABS_RZ:pout", "jawOpen"]
    )
    found = {(f.code.rsplit(".", 1)[-1], f.message) for f in validate(stage, include_usd=False)}
    codes = [c for c, _ in found]
    assert "BlendShapeUnknown" in codes and "BadGamepadMap" in codes
    assert any("'pout'" in m for c, m in found if c == "BlendShapeUnknown")
    assert not any("jawOpen'" in m for c, m in found if c == "BlendShapeUnknown")

"""The film-weight character's builder (issue 23): fingers, a face of blend shapes with
correctives, several textured materials, posed exactly as UsdSkel poses it. Built here at its
lightest (no subdivision, small textures); the default build's numbers are in its README."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from pxr import Gf, Usd, UsdSkel

from tests.conftest import REPO

BUILDER = REPO / "samples" / "film_character" / "build_film_character.py"


def _builder():
    spec = importlib.util.spec_from_file_location("build_film_character", BUILDER)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    out = tmp_path_factory.mktemp("film")
    return _builder().build(out, subdivisions=1, texture_size=256), out


def test_the_character_has_fingers_a_face_and_several_materials(built):
    info, out = built
    assert info["joints"] >= 50
    stage = Usd.Stage.Open(info["usd"])
    joints = [
        str(j)
        for j in UsdSkel.Skeleton(stage.GetPrimAtPath("/Character/Skel")).GetJointsAttr().Get()
    ]
    assert len([j for j in joints if "/hand_l/" in j]) == 15  # five fingers, three joints each
    assert UsdSkel.Topology(joints).Validate()[0]
    assert len(info["blend_shapes"]) >= 10 and info["inbetweens"] >= 5
    body = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Character/Body"))
    assert list(body.GetBlendShapesAttr().Get()) == info["blend_shapes"]
    assert info["triangles"]["Body"] == 4 * 22_956  # one midpoint step
    materials = {
        str(m.GetPath())
        for m in (
            __import__("pxr")
            .UsdShade.MaterialBindingAPI(stage.GetPrimAtPath(f"/Character/{p}"))
            .ComputeBoundMaterial()[0]
            for p in ("Body", "Hands", "Eyes")
        )
    }
    assert len(materials) == 3
    for name in ("body", "gloves", "eyes"):
        assert (out / "textures" / f"{name}_albedo.png").is_file()


def test_the_shot_validates_and_the_ring_draws_the_still_shapes(built):
    from rigspace.sdk.validation import validate

    info, _ = built
    stage = Usd.Stage.Open(info["scene"])
    errors = [f for f in validate(stage, include_usd=False) if f.severity == "error"]
    assert errors == []
    prim = stage.GetPrimAtPath("/World/Hero")
    drawn = list(prim.GetAttribute("rigspace:captureRing:blendShapeNames").Get())
    assert "cheekPuffLeft" in drawn and "jawOpen" not in drawn


def test_posing_equals_usdskel_bake_skinning_with_fingers_and_face(built, tmp_path):
    """rigspace's posing (blend shapes with their inbetweens, then skinning) against
    UsdSkel.BakeSkinning, on frames where the jaw passes its corrective and a blink closes."""
    from rigspace.sdk.posing import CharacterRig

    info, _ = built
    stage = Usd.Stage.Open(info["scene"])
    rig = CharacterRig(stage.GetPrimAtPath("/World/Hero"))
    assert len(rig.blend_shapes) == len(info["blend_shapes"])
    copy = Usd.Stage.Open(info["usd"])
    copy.GetRootLayer().Export(str(tmp_path / "baked.usdc"))
    baked = Usd.Stage.Open(str(tmp_path / "baked.usdc"))
    assert UsdSkel.BakeSkinning(UsdSkel.Root(baked.GetPrimAtPath("/Character")), Gf.Interval(0, 12))
    world = rig.skeleton_to_world(0)
    for t in (2, 4, 12):  # a blink at 4
        ours = {m.name: m.points for m in rig.posed_meshes(t)}
        for name in ("Body", "Hands", "Eyes"):
            want = np.array(baked.GetPrimAtPath(f"/Character/{name}").GetAttribute("points").Get(t))
            want = want @ world[:3, :3].T + world[:3, 3]
            got = next(v for k, v in ours.items() if k.endswith(name))
            np.testing.assert_allclose(got, want, atol=2e-3)  # cm, float32

"""The compiled mesh path (sdk/skinning.py) against UsdSkel's own skinning (sdk/posing.py)."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdSkel

from rigspace.sdk import schema
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.render import vertex_normals
from rigspace.sdk.skinning import NORMAL_TOLERANCE, SKINNING_TOLERANCE, CompiledRig
from rigspace.sdk.skinning import vertex_normals as compiled_normals
from rigspace.sdk.stage import open_stage
from tests.blendshapes import CHARACTER, write_blendshape_character
from tests.conftest import REPO

SCENES = REPO / "samples" / "scenes"


def _both(prim: Usd.Prim) -> tuple[CharacterRig, CompiledRig]:
    return CharacterRig(prim), CompiledRig(prim)


def _assert_same(reference: CharacterRig, compiled: CompiledRig, times, **kwargs) -> float:
    """Every posed mesh's points within SKINNING_TOLERANCE of the posed extent; the largest
    distance the reference's points moved from their rest (so that a test sees a pose)."""
    moved = 0.0
    for t in times:
        ours = compiled.posed_meshes(t, **kwargs)
        usd = reference.posed_meshes(t, **kwargs)
        assert [m.name for m in ours] == [m.name for m in usd]
        for a, b in zip(ours, usd, strict=True):
            extent = float(np.ptp(b.points, axis=0).max())
            assert np.abs(a.points - b.points).max() <= SKINNING_TOLERANCE * extent
            assert a.points.dtype == np.float32 and a.normals.dtype == np.float32
            np.testing.assert_array_equal(a.triangles, b.triangles)
        rest = [p.rest_points for p in reference.mesh_sources()]
        moved = max(
            moved, max(float(np.abs(m.points - r).max()) for m, r in zip(usd, rest, strict=True))
        )
    return moved


def test_the_sample_character_skins_as_usdskel_does():
    stage = open_stage(SCENES / "previs.usda")
    (prim,) = schema.neural_characters(stage)
    reference, compiled = _both(prim)
    assert _assert_same(reference, compiled, (100.0, 500.0, 900.0, 1300.0)) > 0.1


def test_cesium_man_skins_as_usdskel_does():
    stage = open_stage(SCENES / "cesium_man.usda")
    reference, compiled = _both(stage.GetPrimAtPath("/World/CesiumMan"))
    assert _assert_same(reference, compiled, (1.0, 20.0, 48.0)) > 0.05


@pytest.fixture(scope="module")
def face(tmp_path_factory):
    return write_blendshape_character(tmp_path_factory.mktemp("face"))


def test_blend_shapes_inbetweens_and_given_weights_deform_as_usdskel_does(face):
    stage = Usd.Stage.Open(str(face))
    reference, compiled = _both(stage.GetPrimAtPath(CHARACTER))
    # smile passes its 0.5 inbetween and goes past 1 over these time codes (tests/blendshapes)
    _assert_same(reference, compiled, (0, 2, 5, 7, 12))
    weights = np.linspace(-0.5, 1.5, len(reference.blend_shapes)).astype(np.float32)
    _assert_same(reference, compiled, (3,), weights=weights)
    shaped = compiled.posed_meshes(3, weights=weights)[0].points
    plain = compiled.posed_meshes(3, weights=np.zeros_like(weights))[0].points
    assert np.abs(shaped - plain).max() > 0.2  # the shapes showed


def _edited_copy(face, tmp_path) -> Usd.Stage:
    copy = tmp_path / "copy.usda"
    assert Sdf.Layer.FindOrOpen(str(face)).Export(str(copy))
    return Usd.Stage.Open(str(copy))


def test_a_mesh_with_its_own_joint_order_and_geom_bind_skins_as_usdskel_does(face, tmp_path):
    """skel:joints of the mesh's own (UsdSkel's joint mapper: indices count that list) and a
    geomBindTransform that moves the rest points before skinning."""
    stage = _edited_copy(face, tmp_path)
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/World/Asset/Head"))
    joints = list(UsdSkel.Skeleton(binding.GetInheritedSkeleton()).GetJointsAttr().Get())
    binding.CreateJointsAttr().Set(joints[::-1])
    indices = binding.GetJointIndicesPrimvar()
    indices.Set([len(joints) - 1 - i for i in indices.Get()])
    bind = (
        Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(0, 0, 1), 20)).SetTranslateOnly((0.1, 0.2, 0))
    )
    binding.CreateGeomBindTransformAttr().Set(bind)
    reference, compiled = _both(stage.GetPrimAtPath(CHARACTER))
    assert reference._meshes[0].query.GetJointOrder()  # the mapper is in use
    _assert_same(reference, compiled, (0, 5, 12))


def test_a_dual_quaternion_mesh_is_left_to_usdskel(face, tmp_path):
    stage = _edited_copy(face, tmp_path)
    head = stage.GetPrimAtPath("/World/Asset/Head")
    UsdSkel.BindingAPI(head).CreateSkinningMethodAttr().Set(UsdSkel.Tokens.dualQuaternion)
    reference, compiled = _both(stage.GetPrimAtPath(CHARACTER))
    for t in (2, 7):
        a, b = compiled.posed_meshes(t)[0], reference.posed_meshes(t)[0]
        np.testing.assert_array_equal(a.points, b.points)  # UsdSkel's, not a compiled LBS


def test_compiled_normals_equal_numpys_on_the_same_points():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(500, 3)).astype(np.float32)
    triangles = rng.integers(0, 480, size=(2000, 3)).astype(np.int32)  # 20 points unused
    triangles[:5, 1] = triangles[:5, 0]  # degenerate faces add nothing
    out = np.empty_like(points)
    compiled_normals(points, triangles, np.empty(points.shape), out)
    want = vertex_normals(points, triangles)
    np.testing.assert_allclose(out, want, atol=NORMAL_TOLERANCE)
    assert not out[480:].any()  # unused points: zero, not NaN

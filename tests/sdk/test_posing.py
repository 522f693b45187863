"""Posing and USD geometry reading: checked against UsdSkel itself and an independent numpy LBS."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdSkel

from rigspace.sdk.camera import from_gf
from rigspace.sdk.errors import SceneError
from rigspace.sdk.geometry import read_albedo, read_mesh_source, triangulate
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.stage import open_stage
from tests.conftest import REPO, write_tiny_scene

CESIUM_SCENE = REPO / "samples" / "scenes" / "cesium_man.usda"
SKINNING_TOLERANCE = 1e-4  # scene units (metres here): float32 skinning vs float64 numpy


def test_triangulate_fans_polygons_and_skips_degenerate_faces():
    counts = [4, 2, 5]
    indices = [0, 1, 2, 3, 9, 9, 4, 5, 6, 7, 8]
    triangles, corners, faces = triangulate(counts, indices)
    assert triangles.tolist() == [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [4, 7, 8]]
    assert faces.tolist() == [0, 0, 2, 2, 2]
    assert corners[2].tolist() == [6, 7, 8]
    flipped, _, _ = triangulate(counts, indices, left_handed=True)
    assert flipped[0].tolist() == [0, 2, 1]


@pytest.fixture(scope="module")
def cesium_rig():
    stage = open_stage(CESIUM_SCENE)
    return CharacterRig(stage.GetPrimAtPath("/World/CesiumMan"))


def test_rig_matches_usdskel(cesium_rig):
    rig = cesium_rig
    assert len(rig.joints) == 19
    assert rig.time_range() == (1.0, 48.0)
    for time in (1.0, 17.5, 48.0):
        ours = rig.skel_transforms(rig.local_transforms(time))
        usd = rig._skel_query.ComputeJointSkelTransforms(Usd.TimeCode(time))
        # rigspace normalises each quaternion first (UsdSkel builds a non-unit one into a
        # sheared, scaled joint); CesiumMan's authored quaternions are unit to about 1e-5,
        # which is what separates the two here (7e-6 at most).
        np.testing.assert_allclose(from_gf(ours), from_gf(usd), atol=1e-5)
        world = rig._skel_query.ComputeJointWorldTransforms(UsdGeom.XformCache(Usd.TimeCode(time)))
        np.testing.assert_allclose(rig.world_transforms(time), from_gf(world), atol=1e-5)


def test_skinned_points_match_an_independent_lbs(cesium_rig):
    rig = cesium_rig
    time = 20.0
    (mesh,) = rig.posed_meshes(time)
    prim = rig._meshes[0].query.GetPrim()
    binding = UsdSkel.BindingAPI(prim)
    indices = np.asarray(binding.GetJointIndicesPrimvar().Get()).reshape(-1, 4)
    weights = np.asarray(binding.GetJointWeightsPrimvar().Get()).reshape(-1, 4)
    rest = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(), dtype=np.float64)
    joint_order = rig._meshes[0].query.GetJointOrder()
    skel_order = list(rig.skeleton.GetJointsAttr().Get())
    remap = np.array([skel_order.index(j) for j in joint_order]) if joint_order else None
    bind = from_gf(rig.skeleton.GetBindTransformsAttr().Get())
    skel = from_gf(rig.skel_transforms(rig.local_transforms(time)))
    skinning = skel @ np.linalg.inv(bind)  # column-vector: skel-space joint * inverse bind
    geom_bind = from_gf(binding.GetGeomBindTransformAttr().Get() or np.eye(4))
    rest_h = np.c_[rest, np.ones(len(rest))] @ geom_bind.T
    joint = remap[indices] if remap is not None else indices
    posed = np.einsum("nk,nkij,nj->ni", weights, skinning[joint], rest_h)[:, :3]
    to_world = rig.skeleton_to_world(time)
    expected = posed @ to_world[:3, :3].T + to_world[:3, 3]
    assert np.abs(mesh.points - expected).max() < SKINNING_TOLERANCE
    assert np.abs(mesh.points - rest).max() > 0.05  # it really deforms


def test_usdz_texture_and_faceVarying_or_vertex_uvs(cesium_rig):
    (mesh,) = cesium_rig.posed_meshes(1.0)
    assert mesh.texture is not None and mesh.texture.shape == (1024, 1024, 3)
    assert mesh.texture.dtype == np.float32 and 0 <= mesh.texture.min() and mesh.texture.max() <= 1
    assert mesh.corner_uv.shape == (len(mesh.triangles), 3, 2)


def _character_stage(tiny_scene, **kwargs):
    stage = open_stage(tiny_scene(**kwargs))
    return stage, stage.GetPrimAtPath("/World/Hero")


def test_rig_without_skinned_mesh_is_a_clear_error(tmp_path):
    stage = open_stage(write_tiny_scene(tmp_path))  # the shared tiny scene has no mesh
    with pytest.raises(SceneError, match="no skinned mesh is bound"):
        CharacterRig(stage.GetPrimAtPath("/World/Hero"))


def test_rig_without_animation_is_a_clear_error(tiny_scene):
    path = tiny_scene()
    path.write_text(
        path.read_text().replace("rel skel:animationSource = </World/Asset/Skel/Anim>", "")
    )
    stage = open_stage(path)
    with pytest.raises(SceneError, match="has no animation"):
        CharacterRig(stage.GetPrimAtPath("/World/Hero"))


def test_albedo_fallbacks():
    stage = Usd.Stage.CreateInMemory()
    plain = UsdGeom.Mesh.Define(stage, "/Plain")
    colored = UsdGeom.Mesh.Define(stage, "/Colored")
    colored.CreateDisplayColorPrimvar().Set([(1.0, 0.5, 0.25)])
    assert np.allclose(read_albedo(plain.GetPrim()).color, 0.18)
    assert np.allclose(read_albedo(colored.GetPrim()).color, (1.0, 0.5, 0.25))


def test_mesh_with_bad_indices_is_a_clear_error():
    stage = Usd.Stage.CreateInMemory()
    mesh = UsdGeom.Mesh.Define(stage, "/Bad")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 7])
    with pytest.raises(SceneError, match="indexes point 7"):
        read_mesh_source(mesh.GetPrim())

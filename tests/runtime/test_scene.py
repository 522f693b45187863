"""Scene prims as renderer meshes: tessellation, placement at a time, reuse, exclusions."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from rigspace.runtime.scene import SceneGeometry, tessellate
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import RenderSettings, choose_renderer
from tests.conftest import REPO

SURFACE_TOLERANCE = 1e-6


def shape_stage():
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, "Y")
    return stage


@pytest.mark.parametrize(
    ("make", "check"),
    [
        (
            lambda s: UsdGeom.Sphere.Define(s, "/P").CreateRadiusAttr(2.0),
            lambda p: np.allclose(np.linalg.norm(p, axis=1), 2.0),
        ),
        (
            lambda s: UsdGeom.Cube.Define(s, "/P").CreateSizeAttr(4.0),
            lambda p: np.allclose(np.abs(p).max(axis=1), 2.0),
        ),
        (
            lambda s: UsdGeom.Cylinder.Define(s, "/P").CreateAxisAttr("Y"),
            lambda p: (
                np.allclose(np.abs(p[:, 1]).max(), 1.0)
                and np.linalg.norm(p[:, [0, 2]], axis=1).max() <= 1 + 1e-9
            ),
        ),
        (
            lambda s: UsdGeom.Capsule.Define(s, "/P").CreateAxisAttr("Z"),
            lambda p: (
                np.isclose(p[:, 2].max(), 1.0)
                and np.isclose(np.linalg.norm(p[:, :2], axis=1).max(), 0.5)
            ),
        ),
        (
            lambda s: UsdGeom.Plane.Define(s, "/P").CreateAxisAttr("Y"),
            lambda p: np.allclose(p[:, 1], 0.0),
        ),
    ],
    ids=["sphere", "cube", "cylinder", "capsule", "plane"],
)
def test_tessellation_lies_on_the_shape(make, check):
    stage = shape_stage()
    make(stage)
    points, triangles = tessellate(stage.GetPrimAtPath("/P"), Usd.TimeCode.Default())
    assert check(points)
    assert triangles.min() >= 0 and triangles.max() < len(points)


def test_closed_shapes_face_outwards():
    stage = shape_stage()
    for name, kind in (
        ("S", UsdGeom.Sphere),
        ("C", UsdGeom.Cube),
        ("Y", UsdGeom.Cylinder),
        ("K", UsdGeom.Cone),
    ):
        kind.Define(stage, f"/{name}")
        points, triangles = tessellate(stage.GetPrimAtPath(f"/{name}"), Usd.TimeCode.Default())
        a, b, c = (points[triangles[:, k]] for k in range(3))
        # Signed volume of a closed, outward-facing surface is positive.
        volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
        assert volume > 0, name


def test_previs_prims_exclude_the_character_and_reuse_static_meshes():
    stage = Usd.Stage.Open(str(REPO / "samples" / "scenes" / "previs.usda"))
    scene = SceneGeometry(stage)
    paths = {str(p.GetPath()) for p in scene.prims}
    assert "/World/Set/Ground" in paths and "/World/Set/PassingCrate" in paths
    assert not any(p.startswith("/World/Hero") for p in paths)  # the network draws the hero
    first = {m.name: m for m in scene.meshes(0)}
    second = {m.name: m for m in scene.meshes(100)}
    assert second["/World/Set/Ground"] is first["/World/Set/Ground"]  # static: same object
    assert second["/World/Set/PassingCrate"] is not first["/World/Set/PassingCrate"]  # animated
    moved = second["/World/Set/PassingCrate"].points.mean(0) - first[
        "/World/Set/PassingCrate"
    ].points.mean(0)
    assert moved[0] > 100  # it travels along +X


def test_scene_prims_render_with_their_colours():
    stage = shape_stage()
    cube = UsdGeom.Cube.Define(stage, "/Box")
    cube.CreateDisplayColorPrimvar().Set([Gf.Vec3f(1.0, 0.0, 0.0)])
    hidden = UsdGeom.Sphere.Define(stage, "/Hidden")
    hidden.MakeInvisible()
    meshes = SceneGeometry(stage).meshes(0)
    assert [m.name for m in meshes] == ["/Box"]
    camera = Camera.look_at(
        (0, 0, 6), (0, 0, 0), width=32, height=32, focal_length=50, horizontal_aperture=20
    )
    renderer = choose_renderer("embree").create(RenderSettings())
    maps = renderer.render(meshes, camera)
    renderer.close()
    centre = maps.albedo[16, 16]
    assert maps.mask[16, 16] == 1 and centre[0] > 0.9 and centre[1] < SURFACE_TOLERANCE
    assert np.isclose(maps.depth[16, 16], 5.0, atol=1e-4)  # the face at z = 1, camera at 6

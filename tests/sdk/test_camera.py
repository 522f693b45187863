"""Camera: pose and lens conventions, projection, rays, and reading UsdGeom.Camera prims."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom

from rigspace.sdk.camera import CV_FROM_USD, Camera, from_gf, to_gf
from rigspace.sdk.errors import SceneError

EXACT = 1e-9
"""float64 round-off on values of order 1-1000 (pixels, scene units)."""
USD_FLOAT = 1e-5
"""Relative tolerance for values USD stores as float32 (focalLength, apertures, clipping)."""


def lens(**kw):
    values = {"width": 80, "height": 60, "focal_length": 35.0, "horizontal_aperture": 20.955}
    return values | kw


def random_points(cam: Camera, n: int, seed: int = 0) -> np.ndarray:
    """World points spread over the view frustum between near and far."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(cam.near * 2, 50.0, n)
    x = (rng.uniform(0, cam.width, n) - cam.cx) / cam.fx * depth
    y = (cam.cy - rng.uniform(0, cam.height, n)) / cam.fy * depth
    p_cam = np.stack([x, y, -depth, np.ones(n)], 1)
    return (p_cam @ cam.camera_to_world.T)[:, :3]


def test_look_at_points_minus_z_at_the_target():
    cam = Camera.look_at((3.0, 2.0, 5.0), (0.5, 0.5, 0.0), **lens())
    xy, depth = cam.project([(0.5, 0.5, 0.0)])
    np.testing.assert_allclose(xy[0], (cam.cx, cam.cy), atol=EXACT)
    np.testing.assert_allclose(depth[0], np.linalg.norm([2.5, 1.5, 5.0]), rtol=EXACT)
    np.testing.assert_allclose(cam.forward, -np.array([2.5, 1.5, 5.0]) / depth[0], atol=EXACT)
    # World up appears up (smaller image y); a right-handed frame.
    (above,), _ = cam.project([(0.5, 1.5, 0.0)])
    assert above[1] < cam.cy
    np.testing.assert_allclose(np.linalg.det(cam.camera_to_world[:3, :3]), 1.0, atol=EXACT)
    np.testing.assert_allclose(cam.world_to_camera @ cam.camera_to_world, np.eye(4), atol=EXACT)


def test_look_at_from_the_front_sees_plus_x_on_the_right():
    cam = Camera.look_at((0, 0, 5), (0, 0, 0), **lens())
    np.testing.assert_allclose(cam.camera_to_world[:3, :3], np.eye(3), atol=EXACT)
    (right, up), _ = cam.project([(1, 0, 0), (0, 1, 0)])
    assert right[0] > cam.cx and up[1] < cam.cy


def test_projection_formula_and_intrinsics():
    cam = Camera.look_at((1.0, -2.0, 6.0), (0, 0, 0), **lens())
    # Square pixels by default: the vertical aperture follows the image aspect.
    assert cam.fx == pytest.approx(35.0 / 20.955 * 80) and cam.fy == pytest.approx(cam.fx)
    assert cam.effective_vertical_aperture == pytest.approx(20.955 * 60 / 80)
    p = random_points(cam, 50)
    xy, depth = cam.project(p)
    pc = cam.to_camera(p)
    np.testing.assert_allclose(depth, -pc[:, 2], rtol=EXACT)
    np.testing.assert_allclose(xy[:, 0], 40 + cam.fx * pc[:, 0] / -pc[:, 2], atol=1e-6)
    np.testing.assert_allclose(xy[:, 1], 30 - cam.fy * pc[:, 1] / -pc[:, 2], atol=1e-6)
    h = (pc @ CV_FROM_USD.T) @ cam.intrinsics.T
    np.testing.assert_allclose(h[:, :2] / h[:, 2:], xy, atol=1e-6)
    # An explicit vertical aperture gives non-square pixels.
    tall = Camera(np.eye(4), **lens(vertical_aperture=10.0))
    assert tall.fy == pytest.approx(35.0 / 10.0 * 60)


def test_points_behind_the_camera_have_no_image_position():
    cam = Camera(np.eye(4), **lens())
    xy, depth = cam.project([(0, 0, 1.0), (0, 0, 0.0)])
    assert np.all(np.isnan(xy)) and list(depth) == [-1.0, 0.0]


def test_gl_projection_agrees_with_project():
    cam = Camera.look_at((2.0, 1.0, 4.0), (0, 0.3, 0), near=0.5, far=100.0, **lens())
    p = random_points(cam, 100)
    clip = np.c_[cam.to_camera(p), np.ones(len(p))] @ cam.gl_projection.T
    ndc = clip[:, :3] / clip[:, 3:]
    xy, depth = cam.project(p)
    np.testing.assert_allclose((ndc[:, 0] + 1) / 2 * cam.width, xy[:, 0], atol=1e-6)
    np.testing.assert_allclose((1 - ndc[:, 1]) / 2 * cam.height, xy[:, 1], atol=1e-6)
    np.testing.assert_allclose(clip[:, 3], depth, rtol=EXACT)
    # Depth range: the near plane maps to NDC z = -1 and the far plane to +1.
    ends = np.array([[0, 0, -0.5, 1], [0, 0, -100.0, 1]]) @ cam.gl_projection.T
    np.testing.assert_allclose(ends[:, 2] / ends[:, 3], (-1, 1), atol=EXACT)


def test_rays_pass_through_the_sub_sample_positions():
    cam = Camera.look_at((1.0, 2.0, 3.0), (0, 0, 0), **lens(width=5, height=3))
    s = 2
    origins, dirs = cam.rays(s)
    assert origins.shape == dirs.shape == (3 * s * 5 * s, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1, atol=EXACT)
    np.testing.assert_allclose(origins, np.broadcast_to(cam.position, origins.shape))
    xy, depth = cam.project(origins + dirs * 7.0)
    assert np.all(depth > 0)
    grid = xy.reshape(3, s, 5, s, 2)
    # Pixel (i=2, j=4), sub-sample (a=1, b=0) passes through (4 + 0.25, 2 + 0.75).
    np.testing.assert_allclose(grid[2, 1, 4, 0], (4.25, 2.75), atol=1e-9)
    off = cam.sample_offsets(s)
    expected_x = (np.arange(5)[:, None] + off).reshape(-1)
    np.testing.assert_allclose(xy.reshape(3 * s, 5 * s, 2)[0, :, 0], expected_x, atol=1e-9)


def test_invalid_cameras_name_the_value():
    with pytest.raises(ValueError, match="width"):
        Camera(np.eye(4), **lens(width=0))
    with pytest.raises(ValueError, match="height"):
        Camera(np.eye(4), **lens(height=2.5))
    with pytest.raises(ValueError, match="focal_length"):
        Camera(np.eye(4), **lens(focal_length=-1.0))
    with pytest.raises(ValueError, match="near"):
        Camera(np.eye(4), near=10.0, far=1.0, **lens())
    with pytest.raises(ValueError, match="non-finite"):
        Camera(np.full((4, 4), np.nan), **lens())
    with pytest.raises(ValueError, match="4x4"):
        Camera(np.eye(3), **lens())
    with pytest.raises(ValueError, match="no scale"):
        Camera(np.diag([2.0, 2.0, 2.0, 1.0]), **lens())
    with pytest.raises(ValueError, match="last row"):
        Camera(np.array(to_gf(np.eye(4) + np.eye(4, k=3))), **lens())  # a row-vector matrix
    with pytest.raises(ValueError, match="parallel"):
        Camera.look_at((0, 5, 0), (0, 0, 0), **lens())
    with pytest.raises(ValueError, match="samples_per_axis"):
        Camera(np.eye(4), **lens()).rays(0)


def test_pose_is_read_only():
    m = np.eye(4)
    cam = Camera(m, **lens())
    m[0, 3] = 5.0  # the camera keeps its own copy
    assert cam.position[0] == 0.0
    with pytest.raises(ValueError):
        cam.camera_to_world[0, 3] = 1.0


def test_gf_matrices_are_transposed():
    gf = Gf.Matrix4d().SetTranslate(Gf.Vec3d(1, 2, 3))
    m = from_gf(gf)
    np.testing.assert_allclose(m[:3, 3], (1, 2, 3))  # column-vector: translation in the last column
    np.testing.assert_allclose(m @ (1, 1, 1, 1), (2, 3, 4, 1))
    assert to_gf(m) == gf
    rot = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(0, 1, 0), 30))
    p = Gf.Vec3d(1, 0, 0)
    np.testing.assert_allclose(from_gf(rot)[:3, :3] @ (1, 0, 0), rot.Transform(p), atol=EXACT)


# --- from_usd -----------------------------------------------------------------------------------
def make_camera(stage: Usd.Stage, path: str = "/Cam") -> UsdGeom.Camera:
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(24.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.5, 200.0))
    return cam


def test_from_usd_reads_pose_lens_and_clipping():
    stage = Usd.Stage.CreateInMemory()
    cam = make_camera(stage)
    xf = UsdGeom.Xformable(cam)
    xf.AddTranslateOp().Set(Gf.Vec3d(0, 1, 5))
    xf.AddRotateYOp().Set(30.0)
    c = Camera.from_usd(cam, Usd.TimeCode.Default(), 120, 80)
    assert (c.width, c.height, c.focal_length, c.horizontal_aperture) == (120, 80, 50.0, 36.0)
    assert c.vertical_aperture is None  # square pixels: the horizontal aperture spans the width
    assert (c.near, c.far) == pytest.approx((0.5, 200.0), rel=USD_FLOAT)
    expected = Camera.look_at(
        (0, 1, 5), (0, 1, 5) - np.array([np.sin(np.radians(30)), 0, np.cos(np.radians(30))]),
        width=120, height=80, focal_length=50.0, horizontal_aperture=36.0,
    )  # fmt: skip
    np.testing.assert_allclose(c.camera_to_world, expected.camera_to_world, atol=1e-6)
    authored = Camera.from_usd(cam.GetPrim(), 0, 120, 100, square_pixels=False)
    assert authored.vertical_aperture == pytest.approx(24.0)


def test_from_usd_on_a_z_up_stage_and_over_time():
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    cam = make_camera(stage, "/Rig/Cam")
    # A Z-up camera rig: rotateX 90 turns the camera's -Z to world +Y and its +Y to world +Z.
    UsdGeom.Xformable(cam).AddRotateXOp().Set(90.0)
    translate = UsdGeom.Xformable(stage.DefinePrim("/Rig", "Xform")).AddTranslateOp()
    translate.Set(Gf.Vec3d(0, -10, 0), 0)
    translate.Set(Gf.Vec3d(0, -20, 0), 10)
    c0 = Camera.from_usd(cam, 0, 64, 64)
    c10 = Camera.from_usd(cam, 10, 64, 64)
    xy, depth = c0.project([(0, 0, 0), (0, 0, 1)])
    np.testing.assert_allclose(xy[0], (32, 32), atol=1e-6)
    assert depth[0] == pytest.approx(10.0) and xy[1, 1] < 32  # world +Z is up in the image
    assert c10.project([(0, 0, 0)])[1][0] == pytest.approx(20.0)


def test_from_usd_removes_scale_so_depth_is_in_scene_units():
    stage = Usd.Stage.CreateInMemory()
    parent = UsdGeom.Xform.Define(stage, "/Scaled")
    parent.AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    cam = make_camera(stage, "/Scaled/Cam")
    UsdGeom.Xformable(cam).AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    c = Camera.from_usd(cam, 0, 32, 32)
    np.testing.assert_allclose(c.position, (0, 0, 10))
    assert c.project([(0, 0, 0)])[1][0] == pytest.approx(10.0)


def test_from_usd_rejects_what_it_cannot_model():
    stage = Usd.Stage.CreateInMemory()
    cam = make_camera(stage)
    cam.CreateProjectionAttr(UsdGeom.Tokens.orthographic)
    with pytest.raises(SceneError, match="orthographic"):
        Camera.from_usd(cam, 0, 32, 32)
    cam.GetProjectionAttr().Set(UsdGeom.Tokens.perspective)
    cam.CreateHorizontalApertureOffsetAttr(1.0)
    with pytest.raises(SceneError, match="aperture offset"):
        Camera.from_usd(cam, 0, 32, 32)
    xform = stage.DefinePrim(Sdf.Path("/NotACamera"), "Xform")
    with pytest.raises(SceneError, match=r"not a UsdGeom\.Camera"):
        Camera.from_usd(xform, 0, 32, 32)

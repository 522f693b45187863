"""Regions (capture/regions.py): a part of the character captured around its own joint, at its
own resolution, its surface alone (whole, whatever passes before it), its blend shapes drawn
apart from the pose."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from pxr import Sdf, Usd

from rigspace.capture.pipeline import ItemWorker, capture
from rigspace.capture.regions import (
    find_region,
    region_joints,
    region_points,
    region_reach,
    region_settings,
    region_triangles,
    visible_region,
)
from rigspace.capture.settings import (
    CaptureError,
    CaptureOverrides,
    CaptureSettings,
    fit_radius,
    resolve_settings,
)
from rigspace.sdk import schema
from rigspace.sdk.render import DrawMesh, Maps
from rigspace.sdk.rotations import matrix_from_rot6d, rig_parameters
from tests.blendshapes import ANIMATED, CHARACTER, weights_at, write_blendshape_character

SMALL = CaptureOverrides(views=4, elevations=(0.0,), resolution=32, frames_per_item=4, every=3)


def _with_region(scene, name="face", **values):
    """The scene with RigspaceRegionAPI:`name` on the character, its attributes `values`."""
    stage = Usd.Stage.Open(str(scene))
    prim = stage.GetPrimAtPath(CHARACTER)
    prim.ApplyAPI("RigspaceRegionAPI", name)
    kinds = {
        "joint": Sdf.ValueTypeNames.Token,
        "joints": Sdf.ValueTypeNames.TokenArray,
        "blendShapes": Sdf.ValueTypeNames.TokenArray,
        "blendShapeRange": Sdf.ValueTypeNames.Float2,
        "size": Sdf.ValueTypeNames.Float,
        "resolution": Sdf.ValueTypeNames.Int,
        "upright": Sdf.ValueTypeNames.Token,
    }
    for key, value in values.items():
        prim.CreateAttribute(f"rigspace:region:{name}:{key}", kinds[key]).Set(value)
    stage.GetRootLayer().Save()
    return scene


@pytest.fixture(scope="module")
def face_scene(tmp_path_factory):
    scene = write_blendshape_character(tmp_path_factory.mktemp("face"))
    return _with_region(scene, joint="head", resolution=32)


def _settings(scene, warned=None):
    warn = warned.append if warned is not None else lambda _: None
    body, rig = resolve_settings(scene, CHARACTER, SMALL, warn=warn)
    return body, rig, region_settings(body, rig, find_region(rig.character, "face"), warn)


def test_a_region_rings_its_own_joint_at_its_own_resolution(face_scene):
    warned: list[str] = []
    body, rig, settings = _settings(face_scene, warned)
    assert schema.read_regions(rig.character)[0].joint == "head"
    assert settings.look_at_joint == "neck/head" and settings.region == "face"
    assert settings.region_joints == ("neck/head",)  # the joint and those below it: none
    assert settings.resolution == 32 and settings.views_per_ring == body.views_per_ring
    # Its ring frames how far the head's points reach from the head joint over the clip.
    head = region_joints(rig, schema.Region("face", "head"))
    reach = region_reach(rig, head[0], region_points(rig, head), body.clips)
    assert 0.5 < reach < 1.3  # the upper half of a 2-unit cylinder of radius 0.5, and the brow
    assert settings.radius == pytest.approx(
        fit_radius(reach, body.focal_length, body.horizontal_aperture)
    )
    near, far = settings.clipping_range
    assert 0 < near < settings.radius < far
    # The shapes that move the head's points (blink on it, brow on the second mesh) are drawn
    # in every clip apart from the animation; smile, jawOpen and frown move the neck's points.
    assert settings.blend_draws == (("*", "blink", 0.0, 1.0), ("*", "brow", 0.0, 1.0))
    assert any("region face: the weights of blink, brow are drawn" in w for w in warned)
    # The body capture says that the ring's range on smile is not used (the clip moves it).
    assert any("blend shape smile has a capture range" in w for w in warned)


def test_a_region_is_the_points_its_joints_weigh_most(face_scene):
    _, rig, _ = _settings(face_scene)
    head = region_joints(rig, schema.Region("face", "head"))
    points = region_points(rig, head)
    posed = rig.posed_meshes(0.0)
    for mesh, inside in zip(posed, points, strict=True):
        # The cylinder's upper half is skinned mostly to the head (tests/blendshapes.py).
        assert np.all(mesh.points[inside][:, 1] > 0.9)
        kept = region_triangles(mesh.triangles, inside)
        assert np.all(inside[mesh.triangles[kept]].sum(axis=1) >= 2)
    everything = region_points(rig, region_joints(rig, schema.Region("all", "neck")))
    assert all(p.all() for p in everything)  # the root and all below it: every point


def test_an_upright_joint_region_s_cameras_turn_with_the_joint(tmp_path):
    """`upright = "joint"`: every camera of the region's ring keeps the head's own up upright
    (its right axis square to it), the head bending 36 degrees about X over the clip, which the
    side views see as a roll; the stage's region keeps the stage's up. The recorded head row
    (its rotation in the camera) then never rolls: its up has no part along the camera's X."""
    scene = _with_region(
        write_blendshape_character(tmp_path / "face"), joint="head", upright="joint"
    )
    body, rig = resolve_settings(scene, CHARACTER, SMALL, warn=lambda _: None)
    settings = region_settings(body, rig, find_region(rig.character, "face"), lambda _: None)
    np.testing.assert_allclose(settings.upright_axis, (0.0, 1.0, 0.0), atol=1e-9)  # rest: upright
    stage_settings = _settings(
        _with_region(write_blendshape_character(tmp_path / "s"), joint="head")
    )[2]
    assert stage_settings.upright_axis == () and "upright_axis" not in stage_settings.to_json()
    assert CaptureSettings.from_json(settings.to_json()) == settings
    head = rig.joints.index("neck/head")
    rolled = 0.0
    for t in (0.0, 6.0, 12.0):
        world = rig.world_transforms(t)
        own = world[head][:3, :3] @ np.array([0.0, 1.0, 0.0])
        for view in settings.views():
            camera = view.camera(world[head][:3, 3], settings.lens, settings.camera_up(world[head]))
            assert abs(camera.camera_to_world[:3, 0] @ own) < 1e-9
            upright = view.camera(world[head][:3, 3], settings.lens)
            assert abs(upright.camera_to_world[:3, 0] @ np.array([0.0, 1.0, 0.0])) < 1e-9
            rolled = max(rolled, abs(float(upright.camera_to_world[:3, 0] @ own)))
            row = rig_parameters(world[head][None], camera.camera_to_world)[0]
            assert abs(matrix_from_rot6d(row)[0, 1]) < 1e-6  # the head's up: no X in the camera
    assert rolled > np.sin(np.radians(30))  # the stage-upright side views see the bend as a roll


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"joint": "tail"}, "Region 'face': .*tail"),
        ({"joint": "head", "resolution": 48}, "resolution is 48"),
        ({"joint": "head", "blendShapes": ["grin"]}, "names grin, which the character"),
        ({"joint": "head", "blendShapeRange": (1.0, 0.0)}, r"blendShapeRange is \(1, 0\)"),
        ({"resolution": 32}, "names no joint"),
        ({"joint": "head", "upright": "sideways"}, "upright is 'sideways'.*'stage' or 'joint'"),
    ],
)
def test_bad_region_values_are_named_before_any_work(tmp_path, values, message):
    scene = _with_region(write_blendshape_character(tmp_path / "face"), **values)
    body, rig = resolve_settings(scene, CHARACTER, SMALL, warn=lambda _: None)
    with pytest.raises(CaptureError, match=message):
        region_settings(body, rig, find_region(rig.character, "face"), lambda _: None)
    with pytest.raises(CaptureError, match=r"has no region 'hand' .*its regions: face"):
        find_region(rig.character, "hand")
    out = tmp_path / "ds"
    with pytest.raises(CaptureError, match=message):
        capture(scene, CHARACTER, out, SMALL, workers=1, progress=False,
                warn=lambda _: None, region="face")  # fmt: skip
    assert not out.exists()  # nothing written


def test_the_region_keeps_its_surface_where_it_is_the_nearest():
    """A surface in front of the region (a hand before the face) hides it; where the region is
    the nearest surface its own maps stay; elsewhere the pixel is empty."""
    h, w = 4, 6
    region = Maps(
        albedo=np.full((h, w, 3), 0.5, np.float32),
        normal=np.tile(np.array([0, 0, 1], np.float32), (h, w, 1)),
        depth=np.full((h, w), 10.0, np.float32),
        mask=np.ones((h, w), np.float32),
    )
    region.mask[:, 5] = 0.0  # no region surface in the last column
    region.depth[:, 5] = np.inf
    whole = Maps(
        albedo=np.ones((h, w, 3), np.float32),
        normal=region.normal.copy(),
        depth=np.full((h, w), 10.0, np.float32),
        mask=np.ones((h, w), np.float32),
    )
    whole.depth[:, :2] = 7.0  # something nearer over the first two columns
    out = visible_region(whole, region)
    assert np.all(out.mask[:, :2] == 0) and np.all(np.isinf(out.depth[:, :2]))
    assert np.all(out.mask[:, 2:5] == 1) and np.all(out.albedo[:, 2:5] == 0.5)
    assert np.all(out.mask[:, 5] == 0)


@pytest.fixture(scope="module")
def captured_face(face_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("face_ds") / "face"
    result = capture(face_scene, CHARACTER, out, SMALL, workers=1, progress=False,
                     warn=lambda _: None, region="face")  # fmt: skip
    assert result.complete
    return out


def _occluder(camera, joint) -> DrawMesh:
    """A two-sided quad halfway between `camera` and `joint`, over the left half of the view."""
    axes = camera.camera_to_world[:3, :3]
    right, up = axes[:, 0], axes[:, 1]
    middle = (camera.position + np.asarray(joint)) / 2.0
    big = 10.0 * float(np.linalg.norm(camera.position - joint))
    points = np.array([middle - big * right - big * up, middle - big * up,
                       middle + big * up, middle - big * right + big * up], np.float32)  # fmt: skip
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]], np.int32)
    return DrawMesh(points=points, triangles=faces)


def test_a_region_dataset_shows_its_whole_surface_alone(face_scene, captured_face):
    """Each sample is the region's surface alone, all of it the view sees: what passes before
    it (an arm raised beside the head) is not cut out of it, since its network does not read
    what moves that; a dataset captured before (region_surface "visible") cut it."""
    settings = json.loads((captured_face / "capture.json").read_text())
    assert settings["region"] == "face" and settings["look_at_joint"] == "neck/head"
    assert settings["region_surface"] == "whole"
    _, _, region = _settings(face_scene)
    worker = ItemWorker(region, captured_face)
    visible = ItemWorker(replace(region, region_surface="visible"), captured_face)
    try:
        frame = worker.pose("talk", 6.0)
        assert frame.region is not None
        assert sum(len(m.triangles) for m in frame.region) < sum(
            len(m.triangles) for m in frame.meshes
        )
        view = region.views()[0]
        camera = view.camera(frame.joint_position, worker.lens)
        alone = worker.renderer.render(frame.region, camera)
        whole = worker.renderer.render(frame.meshes, camera)
        before = replace(frame, meshes=[*frame.meshes, _occluder(camera, frame.joint_position)])
        kept, cut = worker.render(before, camera), visible.render(before, camera)
    finally:
        worker.close()
        visible.close()
    inside = alone.mask > 0
    assert 0 < inside.sum() < (whole.mask > 0).sum()  # the head, not the whole cylinder
    np.testing.assert_array_equal(kept.mask, alone.mask)  # the quad in front changes nothing
    np.testing.assert_array_equal(kept.albedo, alone.albedo)
    left = np.zeros_like(inside)
    left[:, : inside.shape[1] // 2 - 1] = True
    assert (inside & left).sum() > 10 and (inside & ~left).sum() > 10
    assert np.all(cut.mask[left] == 0) and np.all(np.isinf(cut.depth[left]))  # cut behind it
    # clear of the quad's edge, as without it: where it is the character's nearest surface
    right = np.s_[:, inside.shape[1] // 2 + 1 :]
    np.testing.assert_array_equal(cut.mask[right], visible_region(whole, alone).mask[right])
    # The captured sample of that frame and view is the surface alone too.
    from rigspace.sdk.exr import read_exr

    (sample,) = (captured_face / "samples" / "talk").glob("t000006.0_v000.exr")
    np.testing.assert_array_equal(read_exr(sample).mask > 0, inside)


def test_a_region_capture_json_without_region_surface_is_read_as_the_visible_one_it_was_made_with(
    face_scene,
):
    body, _, region = _settings(face_scene)
    assert "region_surface" not in body.to_json()  # the whole character's has none
    stored = {**json.loads(json.dumps(region.to_json())), "region_surface": "nearest"}
    with pytest.raises(CaptureError, match="region_surface is 'nearest'"):
        CaptureSettings.from_json(stored)
    assert region.to_json()["region_surface"] == "whole"
    before = {k: v for k, v in stored.items() if k != "region_surface"}
    assert CaptureSettings.from_json(before).region_surface == "visible"
    assert CaptureSettings.from_json(body.to_json()).region_surface == "whole"


def test_a_region_s_shapes_are_drawn_apart_from_the_animation(captured_face):
    manifest = json.loads((captured_face / "manifest.json").read_text())
    names = manifest["blend_shapes"]
    # The region records its own shapes alone: the animation's jawOpen, smile and frown move
    # the neck's points, not the head's, and its network does not read them.
    assert names == ["blink", "brow"]
    with np.load(captured_face / "params.npz") as table:
        blend, times = table["blend"], table["time"]
    frames = np.unique(times)
    drawn = {name: [] for name in ("blink", "brow")}
    for t in frames:
        row = blend[times == t][0]
        for name in drawn:
            drawn[name].append(row[names.index(name)])
    for name, values in drawn.items():
        values = np.array(values)
        assert values.min() >= 0 and values.max() <= 1
        at_work = values[values > 0]  # sparse draws: at rest (0) or a weight of its own
        assert 0 < len(at_work) < len(frames) and len(np.unique(at_work)) == len(at_work)
        animation = np.array([dict(zip(ANIMATED, weights_at(float(t)), strict=True))[name]
                              for t in frames])  # fmt: skip
        assert not np.allclose(values, animation, atol=1e-3)  # not the clip's weights


def test_capture_regions_captures_each_region_after_the_body(face_scene, tmp_path, capsys):
    from rigspace.sdk.cli import main

    out = tmp_path / "ds"
    args = ["capture", str(face_scene), "--out", str(out), "--views", "2", "--every", "6",
            "--workers", "1", "--regions"]  # fmt: skip
    assert main(args) == 0
    assert json.loads((out / "capture.json").read_text()).get("region") is None  # the body's
    region = json.loads((out / "regions" / "face" / "capture.json").read_text())
    assert region["region"] == "face" and region["resolution"] == 32
    assert (out / "regions" / "face" / "manifest.json").is_file()
    assert "region face ->" in capsys.readouterr().out
    assert main([*args[:-1], "--region", "face", "--ray"]) == 2
    assert "--ray captures the whole character only" in capsys.readouterr().err

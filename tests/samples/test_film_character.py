"""The film-weight character's builder (issue 23): fingers, a face of blend shapes with
correctives, several textured materials, posed exactly as UsdSkel poses it. Built here at its
lightest (no subdivision, small textures); the default build's numbers are in its README."""

from __future__ import annotations

import importlib.util
import json

import cv2
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


def test_the_right_hand_mirrors_the_left(built):
    """Both hands' fingers leave the wrist along the forearm and curl towards the palm: the
    right hand's finger joints are the left's mirrored in X, in the hands' own frames, open
    and in the roll clip's fist (the right ones once pointed up the forearm: FINGERS is laid
    out along +X, the right arm's bones run along -X)."""
    from rigspace.sdk.posing import CharacterRig

    info, _ = built
    stage = Usd.Stage.Open(info["scene"])
    rig = CharacterRig(stage.GetPrimAtPath("/World/Hero"))
    names = [j.rsplit("/", 1)[-1] for j in rig.joints]
    mirror = np.array([-1.0, 1.0, 1.0])
    for t in (0.0, 1100.0):  # open, a fist
        world = np.asarray(rig.world_transforms(t))
        reach = {}
        for side in "lr":
            hand = world[names.index(f"hand_{side}")]
            forearm = hand[:3, 3] - world[names.index(f"lowerarm_{side}")][:3, 3]
            tips = {}
            for finger in ("thumb", "index", "middle", "ring", "pinky"):
                tip = world[names.index(f"{finger}_03_{side}")]
                tips[finger] = (np.linalg.inv(hand) @ tip)[:3, 3]  # in the hand's frame
            middle = world[names.index(f"middle_03_{side}")][:3, 3] - hand[:3, 3]
            reach[side] = (tips, float(middle @ forearm / np.linalg.norm(forearm)))
        (left, left_reach), (right, right_reach) = reach["l"], reach["r"]
        for finger, tip in left.items():
            np.testing.assert_allclose(right[finger], tip * mirror, atol=1e-3)
        assert left_reach > 10 and right_reach == pytest.approx(left_reach, abs=1e-3)
        assert left["middle"][1] < -1  # curled towards the palm (-Y)


def _around_the_head(info: dict):
    """The shot's character (its rig) and its maps at time 0 from each view of its capture
    ring's first elevation, around the head (the gl renderer)."""
    from rigspace.capture.settings import resolve_settings
    from rigspace.sdk.render import RenderSettings, choose_renderer

    settings, rig = resolve_settings(info["scene"], "/World/Hero", None, warn=lambda _: None)
    meshes = rig.posed_meshes(0.0, charts=True)
    head = rig.world_transforms(0.0)[rig.joints.index(settings.look_at_joint)][:3, 3]
    views = [v for v in settings.views() if v.elevation == settings.views()[0].elevation]
    with choose_renderer("gl").create(RenderSettings(1)) as renderer:
        return rig, [renderer.render(meshes, v.camera(head, settings.lens)) for v in views]


def test_the_face_region_is_found_from_the_shapes_and_seen_only_from_the_front(built):
    """train/regions.py: the surface the blend shapes move, found in texture space and read
    back from a render's uv and chart maps: seen in the head's part of the image from the
    front, all but hidden from behind."""
    from rigspace.train.regions import WholeCharacter, blend_shape_region

    rig, ring = _around_the_head(built[0])
    face = blend_shape_region(rig)
    assert face is not None and face.name == "face"
    counts = []
    for maps in ring:
        pixels = face.pixels(maps)
        character = WholeCharacter().pixels(maps)
        assert pixels is not None and not np.any(pixels & ~character)
        if pixels.any():  # the face is the top of the character, never its legs
            rows = np.flatnonzero(character.any(axis=1))
            top, height = rows[0], rows[-1] - rows[0]
            assert np.flatnonzero(pixels.any(axis=1))[-1] < top + 0.25 * height
        counts.append(int(pixels.sum()))
    # Seen from the front; from behind, at most the jaw's edge by the neck.
    assert max(counts) > 20 and min(counts) <= 0.05 * max(counts)


def test_the_shapes_mobility_covers_the_moving_face_and_nothing_behind_the_head(built):
    """--shape-weight's map (train.regions.shape_mobility, train.data.mobility_target): in
    [0, 1], reaching 1 where a shape moves most, on the face's pixels from the front, none
    from behind beyond the jaw's edge, none off the character; downsampled by box means."""
    from rigspace.train.data import mobility_target
    from rigspace.train.regions import blend_shape_region, shape_mobility

    rig, ring = _around_the_head(built[0])
    mobility = shape_mobility(rig, *rig.texture_charts().boxes())
    face = blend_shape_region(rig)
    assert mobility is not None and face is not None
    seen = []
    for maps in ring:
        full = mobility_target(mobility, maps, 1)[0]
        assert full.min() >= 0.0 and full.max() <= 1.0
        assert np.all(full[cv2.dilate((maps.mask > 0).astype(np.uint8), np.ones((3, 3))) == 0] == 0)
        half = mobility_target(mobility, maps, 2)[0]
        np.testing.assert_allclose(
            half, full.reshape(half.shape[0], 2, -1, 2).mean((1, 3)), atol=1e-6
        )
        pixels = face.pixels(maps)
        moving = full * (maps.mask >= 0.5)
        seen.append((float(moving.sum()), float(moving.max()), int(pixels.sum())))
    front = max(seen)
    assert front[1] == pytest.approx(1.0) and front[0] > 0.2 * front[2]  # most of the face moves
    assert min(s[0] for s in seen) <= 0.05 * front[0]  # from behind, at most the jaw's edge


def test_the_committed_bundle_has_seen_the_wave_every_network_of_it(built, tmp_path, capsys):
    """The film bundle's training views (views.npy of the body and each region): since
    2026-11-29 evening each network was trained on every clip, the wave included, so at its
    frame 500 (the face tilted as only the wave tilts it, the right hand raised) the shot sees
    each of them as it learned them, and the render warns about none (docs/regions.md, "Views
    a network never learned"; the face of before, trained with the wave held out, read
    "rolled", 7-10 degrees outside its views, there)."""
    from rigspace.sdk.cli import main

    info, _ = built
    out = tmp_path / "out"
    code = main(["render", info["scene"], "--out", str(out), "--frames", "500:500",
                 "--resolution", "320x180"])  # fmt: skip
    assert code == 0
    err = capsys.readouterr().err
    entry = json.loads((out / "report.json").read_text())["frames"][0]["characters"][0]
    assert entry["novel_view_deg"] == 0.0 and "novel_view" not in entry
    regions = {r["name"]: r for r in entry["regions"]}
    assert set(regions) == {"face", "leftHand", "rightHand"}
    for name, region in regions.items():
        assert "novel_view" not in region and region["novel_view_deg"] < 6, (name, region)
    assert "network: in 1 of 1 frames" not in err

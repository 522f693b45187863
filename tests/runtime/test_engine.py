"""The engine and `rigspace render` on the previs scene with the committed sample model."""

from __future__ import annotations

import json

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest

from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.runtime.lights import light_prims
from rigspace.runtime.output import CHANNELS
from rigspace.sdk.cli import main
from rigspace.sdk.errors import SceneError
from tests.conftest import REPO

PREVIS = REPO / "samples" / "scenes" / "previs.usda"


@pytest.fixture(scope="module")
def engine():
    e = Engine(PREVIS, EngineSettings(width=160, height=90))
    yield e
    e.close()


def test_a_frame_composites_the_character_with_the_scene(engine):
    frame = engine.render(100.0)
    (hero,) = frame.report.characters
    assert hero["decision"] == "evaluated" and hero["level"] in (32, 64, 128)
    # Every UsdLux light of the scene: the sun, the lamp (and the sky's DomeLight).
    lights = len(light_prims(engine.stage))
    assert lights >= 2 and frame.report.lights == lights
    assert frame.report.scene_prims["meshes"] == 5
    assert frame.beauty.shape == (90, 160, 3) and np.all(np.isfinite(frame.beauty))
    covered = frame.maps.mask > 0.5
    assert np.all(np.isfinite(frame.maps.depth[covered]))
    assert set(frame.report.seconds) >= {
        "scene",
        "rig",
        "network",
        "shadows",
        "lighting",
        "composite",
        "total",
    }


def test_same_pose_and_camera_reuses_everything(engine):
    engine.render(200.0)
    again = engine.render(200.0)
    assert again.report.characters[0]["decision"] == "reused"
    assert again.report.scene_prims["reused"] is False or again.report.scene_prims["reused"]


def test_yoga_hold_reuses_the_character_while_the_camera_is_still(tmp_path):
    # Frames 1338-1554 hold the pose; a still camera there makes the network's work reusable.
    scene = tmp_path / "still.usda"
    text = PREVIS.read_text().replace("@../character/", f"@{REPO / 'samples' / 'character'}/")
    text = text.replace("@../models/sample@", f"@{REPO / 'samples' / 'models' / 'sample'}@")
    start = text.index("        float xformOp:rotateY.timeSamples = {")
    end = text.index("}", start) + 1
    scene.write_text(text[:start] + "        float xformOp:rotateY = 10" + text[end:])
    e = Engine(scene, EngineSettings(width=96, height=54))
    try:
        decisions = [e.render(t).report.characters[0]["decision"] for t in (1400.0, 1401.0, 1402.0)]
    finally:
        e.close()
    assert decisions == ["evaluated", "reused", "reused"]


def test_render_command_writes_exr_png_video_and_report(tmp_path):
    out = tmp_path / "frames"
    code = main(["render", str(PREVIS), "--out", str(out), "--frames", "0:60", "--step", "30",
                 "--resolution", "96x54", "--video", str(tmp_path / "v.mp4")])  # fmt: skip
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert len(report["frames"]) == 3
    image = oiio.ImageInput.open(str(out / "frame_000030.0.exr"))
    assert set(image.spec().channelnames) == set(CHANNELS)  # by name: OpenImageIO reorders
    image.close()
    assert cv2.imread(str(out / "frame_000030.0.png")).shape == (54, 96, 3)
    assert cv2.imread(str(out / "contact_sheet.png")) is not None
    capture = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert capture.isOpened() and int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 3


def test_bad_viewport_and_camera(tmp_path):
    with pytest.raises(SceneError, match="0x90"):
        Engine(PREVIS, EngineSettings(width=0, height=90))
    with pytest.raises(SceneError, match="not a Camera"):
        Engine(PREVIS, EngineSettings(camera="/World/Hero"))


def test_rendering_a_frame_loads_no_torch():
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from rigspace.runtime.engine import Engine, EngineSettings\n"
        f"e = Engine({str(PREVIS)!r}, EngineSettings(width=64, height=36))\n"
        "frame = e.render(10.0)\n"
        "assert frame.report.characters[0]['decision'] == 'evaluated'\n"
        "assert not any(m == 'torch' or m.startswith('torch.') for m in sys.modules), 'torch loaded'\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr


def test_reference_mode_compares_the_network_with_the_mesh(tmp_path):
    out = tmp_path / "ref"
    args = [
        "render",
        str(PREVIS),
        "--out",
        str(out),
        "--frames",
        "700:700",
        "--resolution",
        "160x90",
        "--reference",
    ]
    assert main(args) == 0
    (frame,) = json.loads((out / "report.json").read_text())["frames"]
    (hero,) = frame["reference"]
    assert hero["region"] == frame["characters"][0]["region"]
    # The mesh and the network agree far better than chance (floor; measured values are in
    # docs/runtime.md), and the comparison image is neural | reference | error.
    assert hero["psnr"] > 15
    # The character's own silhouette against its skinned mesh's, in its region (floor).
    assert 0.7 < hero["mask_iou"] <= 1.0
    # FLIP beside PSNR, and its ceiling: the mesh's region squeezed to the network's level.
    # At 160x90 the character is smaller than its level (no ceiling to speak of: 0).
    assert 0.0 < hero["flip"] < 0.5 and hero["flip_ceiling"] == 0.0
    image = cv2.imread(str(out / "compare_000700.0.png"))
    assert image.shape == (90, 3 * 160, 3)


def test_reference_engine_draws_the_mesh_not_the_network():
    e = Engine(PREVIS, EngineSettings(width=96, height=54, reference=True))
    try:
        frame = e.render(700.0)
    finally:
        e.close()
    assert frame.report.characters[0]["decision"] == "reference"
    assert frame.report.scene_prims["meshes"] == 5  # the prims; the mesh is the layer
    assert frame.maps.mask.max() == 1


def test_the_reference_differs_from_the_network_only_in_the_character():
    """The skinned mesh stands in for the network's maps and nothing else: it casts the same
    capsule shadow, so the set around the character is the same image in both modes."""
    frames, coverage = {}, {}
    for reference in (False, True):
        e = Engine(PREVIS, EngineSettings(width=320, height=180, reference=reference))
        try:
            frame = e.render(1000.0)
            frames[reference] = np.array(frame.beauty)
            coverage[reference] = e.coverage_of(e.characters[0].path, 1000.0)
            assert frame.report.shadows["casters"] == 1
        finally:
            e.close()
    outside = (coverage[False] == 0) & (coverage[True] == 0)
    gap = np.abs(frames[True] - frames[False]).max(axis=-1)[outside]
    assert outside.sum() > 0.9 * outside.size and gap.max() < 1e-4
    # What is compared holds the character's shadow on the ground (darker than the lit
    # ground around it), so a reference without it would fail above.
    assert (
        frames[True].sum(axis=-1)[outside] < 0.5 * np.median(frames[True].sum(axis=-1))
    ).sum() > 50


def test_nan_animation_skips_the_character_for_that_frame_only(monkeypatch, capsys):
    e = Engine(PREVIS, EngineSettings(width=64, height=36))
    try:
        (hero,) = e.characters
        real = hero.rig.world_transforms

        def broken(t, local=None):
            world = real(t, local)
            return world * np.nan if t == 11.0 else world

        monkeypatch.setattr(hero.rig, "world_transforms", broken)
        decisions = [e.render(t).report.characters[0] for t in (10.0, 11.0, 12.0)]
    finally:
        e.close()
    assert [d["decision"] for d in decisions] == ["evaluated", "skipped", "evaluated"]
    assert "NaN or Inf joint transforms at time 11" in decisions[1]["reason"]
    assert "warning" in capsys.readouterr().err


def test_a_damaged_bundle_fails_before_the_first_frame(tmp_path):
    import shutil

    from rigspace.sdk.bundle import BundleError

    bundle = tmp_path / "sample"
    shutil.copytree(
        REPO / "samples" / "models" / "sample", bundle, ignore=shutil.ignore_patterns("training")
    )
    (bundle / "geometry_64.onnx").write_bytes(b"damaged")
    scene = tmp_path / "scene.usda"
    text = PREVIS.read_text().replace("@../character/", f"@{REPO / 'samples' / 'character'}/")
    scene.write_text(text.replace("@../models/sample@", f"@{bundle}@"))
    with pytest.raises(BundleError, match=r"geometry_64\.onnx cannot be loaded"):
        Engine(scene, EngineSettings(width=64, height=36))


def test_a_repeated_frame_is_answered_from_the_frame_cache(engine):
    first = engine.render(300.0)
    again = engine.render(300.0)
    assert again.report.repeat_of_last_frame and again.report.counts["reused"] == 1
    assert np.array_equal(first.beauty, again.beauty)
    assert again.report.seconds["total"] < first.report.seconds["total"]


def test_an_edit_to_the_stage_invalidates_what_was_read_as_still(tmp_path):
    from pxr import UsdLux

    e = Engine(_overlay(tmp_path), EngineSettings(width=64, height=36))
    try:
        first = e.render(300.0)
        lamp = UsdLux.LightAPI(e.stage.GetPrimAtPath("/World/Lights/Lamp"))
        lamp.GetIntensityAttr().Set(0.0)
        e.stage.GetPrimAtPath("/World/Lights/Sun").SetActive(False)
        second = e.render(300.0)
    finally:
        e.close()
    assert not second.report.repeat_of_last_frame
    assert second.report.lights == first.report.lights - 1
    # Without the sun and the lamp the prims and the character darken (a sky still shows).
    covered = second.maps.mask > 0.5
    assert second.beauty[covered].sum() < 0.5 * first.beauty[covered].sum()


def test_characters_sharing_a_bundle_run_as_one_batch(tmp_path):
    from rigspace.bench.scenes import crowd_scene

    e = Engine(crowd_scene(tmp_path, 4), EngineSettings(width=128, height=72))
    try:
        assert len({id(c.model) for c in e.characters}) == 1  # one set of sessions
        frame = e.render(700.0)
    finally:
        e.close()
    evaluated = [c for c in frame.report.characters if c["decision"] == "evaluated"]
    assert len(frame.report.characters) == 4 and evaluated
    same_level = [c for c in evaluated if c["level"] == evaluated[0]["level"]]
    assert all(c["batch"] == len(same_level) for c in same_level)


def test_a_reused_character_is_relit_when_a_light_changes(tmp_path, monkeypatch):
    # The yoga hold with a still camera reuses the character's maps; the sun brightens over
    # those frames, so the character must be re-lit, not shown with the old light.
    scene = tmp_path / "still.usda"
    text = PREVIS.read_text().replace("@../character/", f"@{REPO / 'samples' / 'character'}/")
    text = text.replace("@../models/sample@", f"@{REPO / 'samples' / 'models' / 'sample'}@")
    start = text.index("        float xformOp:rotateY.timeSamples = {")
    end = text.index("}", start) + 1
    text = text[:start] + "        float xformOp:rotateY = 10" + text[end:]
    text = text.replace(
        "            float inputs:intensity = 2.5\n",
        "            float inputs:intensity.timeSamples = {1400: 1, 1402: 4}\n",
    )
    scene.write_text(text)
    e = Engine(scene, EngineSettings(width=96, height=54))
    try:
        first, second = e.render(1400.0), e.render(1402.0)
        layer = e.caches.layers["/World/Hero"].layer
        assert e.caches.prims is not None
        x, y, w, h = second.report.characters[0]["region"]
        # Only the character's own pixels: covered by it and in front of the prims.
        hero = (layer.mask > 0.5) & (layer.depth < e.caches.prims.depth[y : y + h, x : x + w])
    finally:
        e.close()
    assert second.report.characters[0]["decision"] == "reused" and hero.sum() > 20
    before = first.beauty[y : y + h, x : x + w][hero].mean()
    after = second.beauty[y : y + h, x : x + w][hero].mean()
    assert after > 1.5 * before


def _overlay(tmp_path, *inactive: str):
    """The previs scene with some prims deactivated, through an overlay layer."""
    from pxr import Usd

    from rigspace.sdk.stage import overlay_layer

    layer = overlay_layer(tmp_path / "overlay.usda", PREVIS)
    stage = Usd.Stage.Open(layer)
    for path in inactive:
        stage.OverridePrim(path).SetActive(False)
    layer.Save()
    return tmp_path / "overlay.usda"


def test_an_unlit_unoccluded_character_runs_its_albedo_branch_only(tmp_path):
    scene = _overlay(tmp_path, "/World/Lights", "/World/Set")
    unlit = Engine(scene, EngineSettings(width=160, height=90, aovs=("beauty", "mask")))
    full = Engine(scene, EngineSettings(width=160, height=90))
    try:
        a, b = unlit.render(700.0), full.render(700.0)
    finally:
        unlit.close()
        full.close()
    (hero,) = a.report.characters
    assert hero["mode"] == "unlit" and hero["branches"] == ["albedo"]
    assert a.report.counts["unlit"] == 1 and a.report.counts["evaluated"] == 1
    (other,) = b.report.characters
    assert other["branches"] == ["albedo", "geometry"]
    assert other["mode_reason"] == "the normal or depth AOV is asked for"
    # The albedo branch's alpha draws nearly the silhouette of the geometry branch's mask
    # (0.83 against 0.86 IoU with the truth on held-out views, docs/training.md).
    from rigspace.train.metrics import mask_iou, psnr

    assert mask_iou(a.maps.mask, b.maps.mask) > 0.75
    assert psnr(a.beauty, b.beauty) > 25


def test_lights_or_a_prim_behind_the_billboard_need_the_geometry_branch(tmp_path):
    for inactive, reason in (
        (("/World/Set",), "lights reach it: normals and depth are shaded"),
        (("/World/Lights",), "a scene prim overlaps its billboard: depth-tested"),
    ):
        e = Engine(
            _overlay(tmp_path, *inactive), EngineSettings(width=160, height=90, aovs=("beauty",))
        )
        try:
            (hero,) = e.render(700.0).report.characters
        finally:
            e.close()
        assert hero["branches"] == ["albedo", "geometry"] and hero["mode_reason"] == reason


def test_overlapping_characters_are_depth_tested(tmp_path):
    from pxr import Gf, Usd, UsdGeom

    scene = _overlay(tmp_path, "/World/Lights", "/World/Set")
    stage = Usd.Stage.Open(str(scene))
    twin = stage.DefinePrim("/World/Twin")
    twin.GetReferences().AddInternalReference("/World/Hero")
    UsdGeom.XformCommonAPI(twin).SetTranslate(Gf.Vec3d(30.0, 0, -60.0))
    stage.GetRootLayer().Save()
    e = Engine(scene, EngineSettings(width=160, height=90, aovs=("beauty",)))
    try:
        frame = e.render(700.0)
    finally:
        e.close()
    reasons = {c["mode_reason"] for c in frame.report.characters}
    assert reasons == {"another character overlaps its billboard: depth-tested"}


def test_aovs_choose_the_exr_channels_and_bad_names_are_refused(tmp_path):
    out = tmp_path / "aov"
    args = ["render", str(PREVIS), "--out", str(out), "--frames", "10:10"]
    assert main([*args, "--resolution", "64x36", "--aovs", "beauty,depth"]) == 0
    spec = oiio.ImageInput.open(str(out / "frame_000010.0.exr")).spec()
    assert list(spec.channelnames) == ["R", "G", "B", "A", "Z"]
    with pytest.raises(SceneError, match="Unknown AOV"):
        Engine(PREVIS, EngineSettings(width=8, height=8, aovs=("beauty", "specular")))
    with pytest.raises(SystemExit):
        main([*args, "--aovs", "beauty,specular"])


def test_a_light_with_a_nan_intensity_is_left_out_loudly(tmp_path, capsys):
    from pxr import Usd, UsdLux

    scene = _overlay(tmp_path)
    stage = Usd.Stage.Open(str(scene))
    UsdLux.LightAPI(stage.GetPrimAtPath("/World/Lights/Lamp")).GetIntensityAttr().Set(float("nan"))
    stage.GetRootLayer().Save()
    e = Engine(scene, EngineSettings(width=64, height=36))
    try:
        frame = e.render(700.0)
    finally:
        e.close()
    assert frame.report.lights == len(light_prims(e.stage)) - 1
    assert "/World/Lights/Lamp" in frame.report.lights_left_out[0]
    assert np.all(np.isfinite(frame.beauty))
    assert "left out" in capsys.readouterr().err


def test_max_level_caps_the_level_of_detail():
    e = Engine(PREVIS, EngineSettings(width=320, height=180, max_level=32))
    try:
        (hero,) = e.render(10.0).report.characters
    finally:
        e.close()
    assert hero["level"] == 32 and hero["level_reason"].startswith("capped by max_level 32")


def test_lighting_the_prims_while_the_network_runs_changes_no_pixel():
    images = {}
    for overlap in (True, False):
        e = Engine(PREVIS, EngineSettings(width=160, height=90))
        e.overlap = overlap
        try:
            frames = [e.render(t) for t in (300.0, 310.0, 900.0)]
            images[overlap] = [np.array(f.beauty) for f in frames]
            assert all(f.report.counts["evaluated"] == 1 for f in frames)
        finally:
            e.close()
    for a, b in zip(images[True], images[False], strict=True):
        assert np.array_equal(a, b)


def test_the_prims_are_drawn_once_a_frame_whichever_stage_asks_first(tmp_path):
    # Lit: after the networks are sent off (drawn while they run). Unlit: when the branch
    # decision reads the prims' coverage behind the character. Never twice in a frame.
    for scene, reason in (
        (PREVIS, "lights reach it: normals and depth are shaded"),
        (_overlay(tmp_path, "/World/Lights"), "a scene prim overlaps its billboard: depth-tested"),
    ):
        e = Engine(scene, EngineSettings(width=160, height=90, aovs=("beauty",)))
        draws: list = []

        def counted(meshes, camera, draws=draws, draw=e.renderer.render):
            draws.append(camera)
            return draw(meshes, camera)

        e.renderer.render = counted
        try:
            frames = [e.render(t) for t in (700.0, 701.0, 702.0)]
        finally:
            e.close()
        assert {f.report.characters[0]["mode_reason"] for f in frames} == {reason}
        drawn = [not f.report.scene_prims["reused"] for f in frames]
        assert drawn[0] and len(draws) == sum(drawn)

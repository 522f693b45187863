"""Capture end to end on CesiumMan: dataset contents, invariances, resume, shards, bad input."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from rigspace.capture import dataset as ds
from rigspace.capture.pipeline import capture
from rigspace.capture.settings import CaptureError, CaptureOverrides
from rigspace.sdk import rotations
from rigspace.sdk.cli import main
from rigspace.sdk.errors import RigspaceError, SceneError
from rigspace.sdk.exr import CHANNELS, TEXTURE_CHANNELS, read_exr
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.stage import open_stage
from tests.capture.conftest import (
    CHARACTER,
    IMAGE_TOLERANCE,
    ROTATION_TOLERANCE,
    SCENE,
    SMALL,
    capture_variant,
    checksum,
    small_capture,
    with_character_ops,
)
from tests.conftest import REPO


def test_dataset_layout_and_manifest(dataset):
    folder = dataset.folder
    manifest = json.loads((folder / ds.MANIFEST_FILE).read_text())
    views = 4 + 4  # training views and their held-out midpoints (the ring holds out 12 -> 4)
    assert manifest["counts"]["samples"] == 6 * views
    assert manifest["counts"]["train"] == 6 * 4 and manifest["counts"]["heldout-views"] == 6 * 4
    assert manifest["joints"][0] == "Skeleton_torso_joint_1" and len(manifest["joints"]) == 19
    assert manifest["renderer"]["name"] in ("gl", "embree")
    assert manifest["settings"]["resolution"] == 32
    with np.load(folder / ds.PARAMS_FILE) as table:
        assert table["rig"].shape == (48, 19, 6)
        assert set(table["split"].tolist()) == {0, 1}
        for path, checksum in zip(table["path"], table["sha256"], strict=True):
            assert ds.sha256_file(folder / str(path)) == checksum
        azimuths = table["azimuth"][table["split"] == 1]
        assert np.allclose(np.sort(np.unique(azimuths)), [45, 135, 225, 315])  # halfway
    assert not list(folder.rglob("*.tmp*"))


def test_exr_channels_and_conventions(dataset):
    import OpenImageIO as oiio

    with np.load(dataset.folder / ds.PARAMS_FILE) as table:
        first = dataset.folder / str(table["path"][0])
    image = oiio.ImageInput.open(str(first))
    # CesiumMan is textured: its samples hold the texture AOVs too.
    assert set(image.spec().channelnames) == set(CHANNELS + TEXTURE_CHANNELS)
    image.close()
    maps = read_exr(first)
    assert maps.mask.max() == 1 and 0 < maps.mask.mean() < 0.6
    empty = maps.mask == 0
    assert np.isinf(maps.depth[empty]).all() and np.isfinite(maps.depth[~empty]).all()
    assert np.all(maps.albedo <= maps.mask[..., None] + 1e-3)  # premultiplied
    norms = np.linalg.norm(maps.normal[maps.mask == 1], axis=-1)
    assert np.allclose(norms, 1, atol=2e-3)  # unit normals (half precision)
    # The look-at joint sits at the image centre, at the ring radius.
    with np.load(dataset.folder / ds.PARAMS_FILE) as table:
        joint = table["joint_camera"][0]
    assert np.allclose(joint, [0, 0, -3.0], atol=1e-4)


def test_texture_aovs_and_charts(dataset):
    """Where the mask is whole, the surface has a chart of charts.json and its uv lies inside
    that chart's uv box; background has chart 0 and uv 0; the manifest names both."""
    folder = dataset.folder
    manifest = json.loads((folder / ds.MANIFEST_FILE).read_text())
    charts = ds.read_charts(folder)
    assert charts is not None and manifest["charts"] == {
        "file": ds.CHARTS_FILE,
        "count": len(charts["charts"]),
    }
    assert "uv.U,uv.V" in manifest["channels"] and "chart" in manifest["channels"]
    boxes = {c["index"]: (np.array(c["uv_min"]), np.array(c["uv_max"])) for c in charts["charts"]}
    assert sorted(boxes) == list(range(1, len(boxes) + 1))
    seen: set[int] = set()
    with np.load(folder / ds.PARAMS_FILE) as table:
        paths = [str(p) for p in table["path"][:8]]
    for path in paths:
        maps = read_exr(folder / path)
        assert maps.uv is not None and maps.chart is not None
        assert np.all(maps.chart[maps.mask == 0] == 0) and np.all(maps.uv[maps.mask == 0] == 0)
        whole = maps.mask == 1
        assert np.all(maps.chart[whole] > 0)
        for k in np.unique(maps.chart[whole]):
            lo, hi = boxes[int(k)]
            uv = maps.uv[whole & (maps.chart == k)]
            assert np.all(uv >= lo - 1e-6) and np.all(uv <= hi + 1e-6)
        seen |= set(np.unique(maps.chart[whole]).tolist())
    assert len(seen) >= 4  # a body seen from around shows several charts


def test_contact_sheet_is_an_image(dataset):
    sheet = cv2.imread(str(dataset.folder / ds.CONTACT_SHEET))
    assert sheet is not None and sheet.shape[1] == 4 * 32 * 2 and sheet.mean() > 5


def test_rot6d_reconstructs_the_joint_rotations(dataset):
    stage = open_stage(SCENE)  # a prim does not keep its stage alive
    rig = CharacterRig(stage.GetPrimAtPath(CHARACTER))
    with np.load(dataset.folder / ds.PARAMS_FILE) as table:
        for k in (0, 17, 40):
            world = rig.world_transforms(float(table["time"][k]))
            camera = table["camera_to_world"][k][:3, :3]
            decoded = camera @ rotations.matrix_from_rot6d(table["rig"][k])
            expected = rotations.orthonormalize(world[:, :3, :3])
            assert np.abs(decoded - expected).max() < ROTATION_TOLERANCE


def test_parameters_invariant_when_character_and_ring_rotate_together(tmp_path, dataset):
    # Turn the character one view step (90 degrees) about the up axis: view k+1 of the turned
    # character must see exactly what view k saw before.
    text = with_character_ops(SCENE.read_text(), "float xformOp:rotateY = 90")
    turned = capture_variant(tmp_path, "turned", text)
    with (
        np.load(dataset.folder / ds.PARAMS_FILE) as a,
        np.load(turned.folder / ds.PARAMS_FILE) as b,
    ):
        for time_code in (1.0, 4.0):
            for view in range(4):
                i = np.flatnonzero((a["time"] == time_code) & (a["view"] == view))[0]
                j = np.flatnonzero((b["time"] == time_code) & (b["view"] == (view + 1) % 4))[0]
                assert np.abs(a["rig"][i] - b["rig"][j]).max() < ROTATION_TOLERANCE
                before = read_exr(dataset.folder / str(a["path"][i]))
                after = read_exr(turned.folder / str(b["path"][j]))
                assert np.abs(before.albedo - after.albedo).mean() < IMAGE_TOLERANCE


def test_shards_merge_to_the_same_dataset(tmp_path, dataset):
    out = tmp_path / "sharded"
    first = small_capture(out, shard=(0, 2))
    assert not first.complete and not (out / ds.MANIFEST_FILE).exists()
    second = small_capture(out, shard=(1, 2))
    assert second.complete
    assert checksum(out) == checksum(dataset.folder)


def test_multiprocess_capture_matches(tmp_path, dataset):
    result = small_capture(tmp_path / "two", workers=2)
    assert result.complete and checksum(result.folder) == checksum(dataset.folder)


def capture_command(out, workers: int, renderer: str) -> list[str]:
    """The CLI capture of the fixture's settings in one-frame items (12 items of 4 samples)."""
    return [
        sys.executable, "-m", "rigspace.sdk", "capture", str(SCENE), "--out", str(out),
        "--views", "4", "--elevations", "0", "--resolution", "32", "--frames", "1:6",
        "--frames-per-item", "1", "--workers", str(workers), "--renderer", renderer,
    ]  # fmt: skip


def test_kill_9_then_resume_gives_the_same_dataset(tmp_path, dataset):
    out = tmp_path / "killed"
    cmd = capture_command(out, 1, dataset.settings.renderer)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(list((out / "items").glob("*.npz"))) < 3:
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = len(list((out / "items").glob("*.npz")))
    assert 3 <= done < 12, "the kill should land mid-capture"
    assert not (out / ds.MANIFEST_FILE).exists()
    # Same settings as the fixture except the item size, so compare with a fresh run of it.
    overrides = CaptureOverrides(**{**SMALL.__dict__, "frames_per_item": 1})
    resumed = capture(SCENE, CHARACTER, out, overrides, resume=True, workers=1, progress=False)
    assert resumed.complete and resumed.samples_done == (12 - done) * 4
    reference = capture(SCENE, CHARACTER, tmp_path / "ref", overrides, workers=1, progress=False)
    assert checksum(out) == checksum(reference.folder)


# -- bad input: a clear error before anything is written ---------------------------------

NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (CaptureOverrides(resolution=100), "not a power of two"),
        (CaptureOverrides(frames=(60.0, 90.0)), r"--frames 60:90 lies outside the animation"),
        (
            CaptureOverrides(frames=(1e12, 1e12)),
            r"lies outside the animation's time samples \(1-48",
        ),
        (CaptureOverrides(frames=(NAN, NAN)), "--frames nan:nan is not a range of finite"),
        (CaptureOverrides(frames=(1.0, INF)), "is not a range of finite time codes"),
        (CaptureOverrides(frames=(9.0, 3.0)), "ends before it starts"),
        (CaptureOverrides(clips=("run",)), "does not define"),
        (CaptureOverrides(views=0), "outside 1 to 360"),
        (CaptureOverrides(elevations=(NAN,)), r"must be in \[-89, 89\]"),
        (CaptureOverrides(radius=NAN), "radius nan is not a finite distance"),
        (CaptureOverrides(radius=INF), "radius inf is not a finite distance"),
        (CaptureOverrides(radius=500.0), "beyond the far clipping plane 100"),
        (CaptureOverrides(samples_per_axis=1000), "--samples 1000 is outside 1 to 8"),
    ],
)
def test_bad_settings(tmp_path, overrides, message):
    with pytest.raises(CaptureError, match=message):
        capture(SCENE, CHARACTER, tmp_path / "out", overrides, workers=1, progress=False)
    assert not (tmp_path / "out").exists()


def test_not_a_character(tmp_path):
    with pytest.raises(CaptureError, match="not a RigspaceNeuralCharacter"):
        capture(SCENE, "/World/ShotCam", tmp_path / "out", SMALL, workers=1, progress=False)
    with pytest.raises(CaptureError, match="/World/CesiumMan"):
        capture(SCENE, "/World/Nobody", tmp_path / "out", SMALL, workers=1, progress=False)
    assert not (tmp_path / "out").exists()


UNWEIGHTED_MESH = """
        def Mesh "Body"
        {
            int[] faceVertexCounts = [3]
            int[] faceVertexIndices = [0, 1, 2]
            point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
        }
"""


def test_character_without_skeleton_animation_or_skin(tmp_path, tiny_scene):
    path = tiny_scene()
    text = path.read_text()
    # A mesh under the SkelRoot, bound to nothing: no jointIndices / jointWeights.
    path.write_text(
        text.replace(
            '    def SkelRoot "Asset"\n    {\n',
            '    def SkelRoot "Asset"\n    {\n' + UNWEIGHTED_MESH,
        )
    )
    assert 'def Mesh "Body"' in path.read_text()
    with pytest.raises(SceneError, match=r"no skinned mesh is bound .*jointWeights"):
        capture(path, "/World/Hero", tmp_path / "out", SMALL, workers=1, progress=False)
    path.write_text(text.replace("rel rigspace:skeleton = </World/Asset/Skel>", ""))
    with pytest.raises(SceneError, match="no single rigspace:skeleton"):
        capture(path, "/World/Hero", tmp_path / "out", SMALL, workers=1, progress=False)
    path.write_text(text.replace("rel skel:animationSource = </World/Asset/Skel/Anim>", ""))
    with pytest.raises(SceneError, match="has no animation"):
        capture(path, "/World/Hero", tmp_path / "out", SMALL, workers=1, progress=False)
    assert not (tmp_path / "out").exists()


def test_unwritable_output(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(CaptureError, match="cannot be"):
        small_capture(blocker / "out")
    with pytest.raises(CaptureError, match="is a file"):
        small_capture(blocker)


def test_existing_dataset_with_other_settings(tmp_path, dataset):
    out = tmp_path / "ds"
    small_capture(out)
    before = checksum(out)
    with pytest.raises(CaptureError, match=r"different settings .*resolution"):
        small_capture(out, overrides=CaptureOverrides(**{**SMALL.__dict__, "resolution": 64}))
    with pytest.raises(CaptureError, match="--resume"):
        small_capture(out)
    again = small_capture(out, resume=True)  # a complete dataset: nothing to do, same result
    assert again.samples_done == 0 and checksum(out) == before
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(CaptureError, match="not a rigspace dataset"):
        small_capture(tmp_path / "other")
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_cli_errors_are_one_line(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "rigspace.sdk", "capture", str(SCENE), "--out", str(tmp_path / "o"),
         "--resolution", "100"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert result.returncode == 2
    assert "not a power of two" in result.stderr and "Traceback" not in result.stderr


def test_rigspace_error_is_the_base():
    assert issubclass(CaptureError, RigspaceError)


def test_the_sample_character_captures(tmp_path):
    previs = REPO / "samples" / "scenes" / "previs.usda"
    overrides = CaptureOverrides(views=3, resolution=32, frames=(600.0, 605.0))
    result = capture(previs, "/World/Hero", tmp_path / "ds", overrides, progress=False)
    manifest = result.manifest
    assert result.complete and manifest is not None
    # 3 views x 2 elevations, and the ring's 4 held-out views per ring capped at 3.
    assert manifest.counts["train"] == 6 * 6
    assert manifest.counts["heldout-views"] == 6 * 6
    with np.load(result.folder / ds.PARAMS_FILE) as table:
        assert table["rig"].shape[1:] == (22, 6)
        first = read_exr(result.folder / str(table["path"][0]))
    assert 0.02 < first.mask.mean() < 0.5


def test_held_out_clips_are_seen_from_training_views_only(tmp_path):
    previs = REPO / "samples" / "scenes" / "previs.usda"
    overrides = CaptureOverrides(views=1, elevations=(0.0,), resolution=16, clips=("wave",))
    warned: list[str] = []
    result = capture(
        previs, "/World/Hero", tmp_path / "ds", overrides, progress=False, warn=warned.append
    )
    counts = result.manifest.counts
    assert (counts["heldout-clips"], counts["train"], counts["heldout-views"]) == (240, 0, 0)
    # Only held-out material: said before rendering, and again in the summary.
    assert len(warned) == 1 and "every clip of this capture (wave) is held out" in warned[0]
    assert "0 training samples" in warned[0] and "capture a training clip too" in warned[0]
    assert "warning: every clip" in result.summary()


def test_z_up_stage_gives_the_same_parameters(tmp_path, dataset):
    # Z up, the character turned +90 degrees about X (its Y becomes Z): the ring's up axis and
    # front (-Y) turn the same way, so every view sees exactly what it saw on the Y-up stage.
    text = SCENE.read_text().replace('upAxis = "Y"', 'upAxis = "Z"')
    z_up = capture_variant(tmp_path, "zup", with_character_ops(text, "float xformOp:rotateX = 90"))
    assert z_up.settings.up_axis == "Z"
    with np.load(dataset.folder / ds.PARAMS_FILE) as a, np.load(z_up.folder / ds.PARAMS_FILE) as b:
        assert np.abs(a["rig"] - b["rig"]).max() < ROTATION_TOLERANCE
        first_a, first_b = (
            read_exr(dataset.folder / str(a["path"][0])),
            read_exr(z_up.folder / str(b["path"][0])),
        )
    assert np.abs(first_a.mask - first_b.mask).mean() < IMAGE_TOLERANCE


def test_centimetre_stage_scales_depth_not_parameters(tmp_path, dataset):
    # The same character on a centimetre stage (scaled x100, ring radius x100): parameters
    # and masks are unchanged, depth is in the stage's units (x100).
    text = (
        SCENE.read_text()
        .replace("metersPerUnit = 1", "metersPerUnit = 0.01")
        .replace("rigspace:captureRing:radius = 3", "rigspace:captureRing:radius = 300")
        .replace("clippingRange = (0.05, 100)", "clippingRange = (5, 10000)")
    )
    scaled = with_character_ops(text, "float3 xformOp:scale = (100, 100, 100)")
    cm = capture_variant(tmp_path, "cm", scaled)
    assert cm.settings.meters_per_unit == pytest.approx(0.01)
    with np.load(dataset.folder / ds.PARAMS_FILE) as a, np.load(cm.folder / ds.PARAMS_FILE) as b:
        assert np.abs(a["rig"] - b["rig"]).max() < ROTATION_TOLERANCE
        metres, centimetres = (
            read_exr(dataset.folder / str(a["path"][3])),
            read_exr(cm.folder / str(b["path"][3])),
        )
    both = (metres.mask == 1) & (centimetres.mask == 1)
    assert np.array_equal(metres.mask > 0, centimetres.mask > 0)
    assert np.allclose(centimetres.depth[both], 100 * metres.depth[both], rtol=1e-3)


def test_nan_in_the_animation_is_refused_before_any_work(tmp_path):
    from pxr import Usd, UsdSkel

    from rigspace.sdk.stage import overlay_layer

    layer = overlay_layer(tmp_path / "nan.usda", SCENE)
    stage = Usd.Stage.Open(layer)
    rig = CharacterRig(stage.GetPrimAtPath(CHARACTER))
    rotations_attr = UsdSkel.Animation(rig.animation).GetRotationsAttr()
    time_code = rotations_attr.GetTimeSamples()[3]
    values = np.array(rotations_attr.Get(time_code))
    values[0, 0] = np.nan
    rotations_attr.Set(values, time_code)
    layer.Save()
    with pytest.raises(CaptureError, match=rf"NaN or Inf in rotations at time {time_code:g}"):
        capture(
            tmp_path / "nan.usda", CHARACTER, tmp_path / "out", SMALL, workers=1, progress=False
        )
    assert not (tmp_path / "out").exists()


def test_sigterm_stops_quietly_keeps_the_items_and_says_how_to_resume(tmp_path, dataset):
    """What a scheduler or `kill` sends: like Ctrl-C, no worker traceback, the committed
    items kept, the resume command printed; --resume then finishes the same dataset."""
    out = tmp_path / "termed"
    cmd = capture_command(out, 2, dataset.settings.renderer)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120  # a loaded machine spawns its workers slowly
    while time.monotonic() < deadline and len(list((out / "items").glob("*.npz"))) < 2:
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    done = len(list((out / "items").glob("*.npz")))
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "leaked" not in err, err
    assert f"--out {out} --resume" in err and f"{done} work items are kept" in err
    overrides = CaptureOverrides(**{**SMALL.__dict__, "frames_per_item": 1})
    resumed = capture(SCENE, CHARACTER, out, overrides, resume=True, workers=1, progress=False)
    assert resumed.complete


def test_held_out_clips_from_the_command_line(tmp_path):
    """--held-out-clips replaces the ring's heldOutClips (previs.usda holds out the wave): none
    held out, every clip trains; a name the ring does not define is refused before anything is
    written; the resume command carries the split."""
    previs = REPO / "samples" / "scenes" / "previs.usda"
    small = {"views": 1, "elevations": (0.0,), "resolution": 16, "every": 60}
    none = CaptureOverrides(**small, clips=("walk", "wave"), held_out_clips=())
    result = capture(previs, "/World/Hero", tmp_path / "none", none, progress=False)
    assert [(c.name, c.held_out) for c in result.settings.clips] == [
        ("walk", False),
        ("wave", False),
    ]
    assert result.manifest.counts["heldout-clips"] == 0
    command = ds.resume_command(tmp_path / "none")
    assert "--clips walk wave --held-out-clips --renderer" in command
    (tmp_path / "none" / ds.MANIFEST_FILE).unlink()  # unfinished: the command finishes it
    assert main(shlex.split(command)[1:]) == 0  # the same split, or "different settings"
    assert ds.read_manifest(tmp_path / "none").counts["heldout-clips"] == 0
    walk = CaptureOverrides(**small, clips=("walk", "wave"), held_out_clips=("walk",))
    result = capture(previs, "/World/Hero", tmp_path / "walk", walk, progress=False)
    assert [c.name for c in result.settings.clips if c.held_out] == ["walk"]
    assert ds.saved_flags(tmp_path / "walk")["held_out_clips"] == ("walk",)
    bad = CaptureOverrides(**small, held_out_clips=("dance",))
    with pytest.raises(CaptureError, match=r"--held-out-clips names dance.*use some of: roll"):
        capture(previs, "/World/Hero", tmp_path / "bad", bad, progress=False)
    assert not (tmp_path / "bad").exists()

"""`rigspace render` on bad input and at the edges: clear errors, no stray folders, warnings."""

from __future__ import annotations

import json

import av
import cv2
import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from rigspace.sdk.cli import main
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.stage import overlay_layer
from tests.conftest import REPO

PREVIS = REPO / "samples" / "scenes" / "previs.usda"
ANIMATION = "/World/Hero/Asset/Skel/Anim"
SMALL = ["--resolution", "48x27", "--prim-samples", "1"]


def _overlay(tmp_path, name: str, edit) -> str:
    """The previs scene with `edit(stage)` applied in an overlay layer."""
    layer = overlay_layer(tmp_path / name, PREVIS)
    edit(Usd.Stage.Open(layer))
    layer.Save()
    return str(tmp_path / name)


def test_frames_past_the_stage_end_warn_naming_the_range(tmp_path, capsys):
    out = tmp_path / "late"
    args = ["render", str(PREVIS), "--out", str(out), "--frames", "1610:1640", "--step", "15"]
    assert main([*args, *SMALL]) == 0
    err = capsys.readouterr().err
    assert "past the stage's time range 0-1619" in err and "frames 1619-1640" in err
    assert len(json.loads((out / "report.json").read_text())["frames"]) == 3  # still rendered


def test_frames_inside_the_stage_do_not_warn(tmp_path, capsys):
    out = tmp_path / "ok"
    args = ["render", str(PREVIS), "--out", str(out), "--frames", "0:1619", "--step", "1619"]
    assert main([*args, *SMALL]) == 0
    assert "warning" not in capsys.readouterr().err


def test_a_drifted_stage_range_holds_its_whole_frames(capsys):
    """An exporter wrote 1.0000000521-3023.0001577 (float32 drift); capture reads those as
    frames 1-3023 (sdk.timecodes), and render compares --frames with the same tolerance: no
    warning that 1:3023 reaches past the range. A frame past it by more still warns."""
    from rigspace.apps.render import frame_times

    stage = Usd.Stage.CreateInMemory()
    stage.SetStartTimeCode(1.0000000521540642)
    stage.SetEndTimeCode(3023.0001577)
    times = frame_times((1.0, 3023.0), 1.0, stage)
    assert len(times) == 3023 and "warning" not in capsys.readouterr().err
    frame_times((0.0, 3024.0), 1.0, stage)
    err = capsys.readouterr().err
    assert "frames 0-1 and 3023-3024 show the stage held at its first or last" in err
    with pytest.raises(RigspaceError, match="lies outside"):
        frame_times((3025.0, 3030.0), 1.0, stage)
    frame_times((3023.0, 3023.0), 1.0, stage)  # the last frame itself: inside, no warning
    assert "warning" not in capsys.readouterr().err


@pytest.mark.parametrize(
    ("frames", "step", "words"),
    [
        ("nan:nan", "1", "--frames nan:nan is not a range of time codes"),
        ("0:inf", "1", "--frames 0:inf is not a range of time codes"),
        ("1e12:1e12", "1", "lies outside the stage's time range 0-1619"),
        ("0:100", "nan", "--step nan is not a positive number"),
        ("0:1619", "1e-9", "frames"),
        ("20:10", "1", "is empty"),
    ],
)
def test_bad_frames_are_refused_clearly_and_leave_no_folder(tmp_path, capsys, frames, step, words):
    out = tmp_path / "never"
    args = ["render", str(PREVIS), "--out", str(out), "--frames", frames, "--step", step]
    assert main([*args, *SMALL]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err
    assert not out.exists()


def test_a_rejected_scene_leaves_no_folder_and_keeps_an_existing_one(tmp_path, capsys):
    bad = tmp_path / "notes.usda"
    bad.write_text("these are notes, not USD\n")
    new = tmp_path / "new" / "frames"
    assert main(["render", str(bad), "--out", str(new)]) == 2
    assert not (tmp_path / "new").exists()
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    assert main(["render", str(bad), "--out", str(existing)]) == 2
    assert (existing / "keep.txt").read_text() == "mine"
    assert "error" in capsys.readouterr().err


def test_an_out_that_is_a_file_is_refused_and_kept(tmp_path, capsys):
    out = tmp_path / "frames"
    out.write_text("not a folder")
    assert main(["render", str(PREVIS), "--out", str(out), "--frames", "0:0", *SMALL]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    assert out.read_text() == "not a folder"


def test_an_unwritable_video_removes_only_the_folder_it_created(tmp_path, capsys):
    out = tmp_path / "made" / "frames"
    video = tmp_path / "no such folder" / "v.mp4"
    args = ["render", str(PREVIS), "--out", str(out), "--frames", "0:0", "--video", str(video)]
    assert main([*args, *SMALL]) == 2
    assert "--video" in capsys.readouterr().err
    assert not (tmp_path / "made").exists() and tmp_path.exists()


def test_the_video_is_h264_with_every_frame_and_the_pngs_pixels(tmp_path):
    out = tmp_path / "frames"
    video = out / "shot.mp4"
    args = ["render", str(PREVIS), "--out", str(out), "--frames", "0:20", "--step", "10",
            "--resolution", "96x54", "--video", str(video)]  # fmt: skip
    assert main(args) == 0
    with av.open(str(video)) as container:
        assert container.streams.video[0].codec_context.name == "h264"
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 3
    png = cv2.imread(str(out / "frame_000010.0.png"))[..., ::-1]
    # The whole frame within compression error of its PNG (a swapped channel or a flipped
    # frame would be off by far more).
    assert np.abs(frames[1].astype(int) - png).mean() < 3


def _animation_values(name: str, frame: int, values):
    """An overlay edit: the animation's `name` samples on frames 0-20, with the first
    joints' values at `frame` replaced by `values` (samples in a stronger layer replace the
    weaker layer's)."""

    def edit(stage):
        attr = stage.GetPrimAtPath(ANIMATION).GetAttribute(name)
        for t in range(0, 21):
            value = list(attr.Get(t))
            if t == frame:
                value[: len(values)] = values
            attr.Set(value, t)

    return edit


def test_reference_with_nan_in_the_animation_names_the_animation(tmp_path, capsys):
    nan = _animation_values("rotations", 10, [Gf.Quatf(float("nan"), 0, 0, 0)])
    scene = _overlay(tmp_path, "nan.usda", nan)
    out = tmp_path / "ref"
    args = ["render", scene, "--out", str(out), "--frames", "0:20", "--step", "5", "--reference"]
    assert main([*args, *SMALL]) == 2
    err = capsys.readouterr().err
    assert ANIMATION in err and "NaN or Inf" in err and "at time 10" in err
    assert "Traceback" not in err and not out.exists()


def test_reference_with_points_past_float32_names_the_animation(tmp_path, capsys):
    # Finite samples (inspect passes them), but the pelvis and spine at 3e38 each put the
    # skinned points past float32's 3.4e38: the network draws, the mesh cannot.
    far = Gf.Vec3f(3e38, 0, 0)
    scene = _overlay(tmp_path, "far.usda", _animation_values("translations", 10, [far, far]))
    out = tmp_path / "ref"
    args = ["render", scene, "--out", str(out), "--frames", "0:20", "--step", "5", "--reference"]
    assert main([*args, *SMALL]) == 2
    err = capsys.readouterr().err
    assert f"the animation {ANIMATION} of /World/Hero gives NaN or Inf points" in err
    assert "at time 10" in err and "Traceback" not in err and not out.exists()


def _tiny_hero(stage):
    # 2 mm tall in a centimetre scene: its billboard is a tenth of a pixel. Lights off: the
    # test is about the comparison, not the shading.
    UsdGeom.XformCommonAPI(stage.OverridePrim("/World/Hero")).SetScale(Gf.Vec3f(0.002))
    stage.OverridePrim("/World/Lights").SetActive(False)


def test_reference_over_a_character_without_pixels_has_nothing_to_compare(tmp_path, capsys):
    scene = _overlay(tmp_path, "tiny.usda", _tiny_hero)
    out = tmp_path / "ref"
    args = ["render", scene, "--out", str(out), "--frames", "100:100", "--reference"]
    assert main([*args, "--resolution", "160x90"]) == 0
    (frame,) = json.loads((out / "report.json").read_text())["frames"]
    (hero,) = frame["reference"]
    assert hero["psnr"] is None and hero["albedo_psnr"] is None
    assert hero["reason"].startswith("nothing to compare")
    printed = capsys.readouterr().out
    assert "nothing to compare" in printed and "120.00" not in printed

"""Foreign assets and damaged datasets: drifted time codes, nothing in view, repair on resume."""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdSkel

from rigspace.capture import dataset as ds
from rigspace.capture.pipeline import capture
from rigspace.capture.settings import CaptureError, CaptureOverrides, resolve_settings
from rigspace.sdk.cli import main
from rigspace.sdk.exr import read_exr
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.stage import overlay_layer
from tests.capture.conftest import (
    CHARACTER,
    ROTATION_TOLERANCE,
    SCENE,
    SMALL,
    capture_variant,
    checksum,
    scene_variant,
    small_capture,
    with_character_ops,
)

DRIFT = 1 + 5.2e-8
"""What a real exporter wrote: frame k at k * (1 + 5.2e-8), 3023 at 3023.0001577."""


def drifted_scene(tmp_path: Path) -> Path:
    """CesiumMan with every animation sample moved from k to k * DRIFT (an overlay layer)."""
    layer = overlay_layer(tmp_path / "drifted.usda", SCENE)
    stage = Usd.Stage.Open(layer)
    anim = UsdSkel.Animation(CharacterRig(stage.GetPrimAtPath(CHARACTER)).animation)
    for attr in (anim.GetTranslationsAttr(), anim.GetRotationsAttr(), anim.GetScalesAttr()):
        values = {t: attr.Get(t) for t in attr.GetTimeSamples()}
        if values:
            attr.Clear()  # the overlay's own samples replace the asset's
            for t, value in values.items():
                attr.Set(value, t * DRIFT)
    layer.Save()
    return tmp_path / "drifted.usda"


def test_drifted_time_codes_capture_at_the_authored_samples(tmp_path, dataset):
    scene = drifted_scene(tmp_path)
    stage = Usd.Stage.Open(str(scene))  # a prim does not keep its stage alive
    rig = CharacterRig(stage.GetPrimAtPath(CHARACTER))
    assert rig.time_range() == (DRIFT, 48 * DRIFT)  # the drift is really there
    warned: list[str] = []
    result = capture(
        scene, CHARACTER, tmp_path / "ds", SMALL, workers=1, progress=False, warn=warned.append
    )
    assert result.complete and warned == []  # 1:6 rounds into the range: nothing to say
    with (
        np.load(result.folder / ds.PARAMS_FILE) as b,
        np.load(dataset.folder / ds.PARAMS_FILE) as a,
    ):
        # Posed at the authored samples exactly, not at 2.0 between 1.99... and 2.0000001.
        assert set(b["time"].tolist()) == {k * DRIFT for k in range(1, 7)}
        assert np.abs(a["rig"] - b["rig"]).max() < ROTATION_TOLERANCE
        assert np.array_equal(a["path"], b["path"])


def test_a_clip_past_the_animation_is_clamped_with_a_warning(tmp_path):
    scene = drifted_scene(tmp_path)
    warned: list[str] = []
    settings, _ = resolve_settings(
        scene, CHARACTER, CaptureOverrides(frames=(40.0, 90.0)), warn=warned.append
    )
    (clip,) = settings.clips
    assert (clip.first, clip.last) == (40 * DRIFT, 48 * DRIFT)  # snapped to the samples
    assert len(warned) == 1 and re.search(
        r"40:90 reaches past .*\(1-48\); capturing 40-48", warned[0]
    )
    # The whole range, asked for with rounded ends, is the whole range without a word.
    warned.clear()
    settings, _ = resolve_settings(
        scene, CHARACTER, CaptureOverrides(frames=(1.0, 48.0)), warn=warned.append
    )
    assert (settings.clips[0].first, settings.clips[0].last) == (DRIFT, 48 * DRIFT)
    assert warned == []


TINY_AND_FAR = {
    "rigspace:captureRing:radius = 3": "rigspace:captureRing:radius = 600",
    "clippingRange = (0.05, 100)": "clippingRange = (0.05, 10000)",
}


def tiny_far_scene_text() -> str:
    """CesiumMan scaled to 0.12 units tall, seen from 600 units: the issue's empty capture."""
    text = with_character_ops(SCENE.read_text(), "float3 xformOp:scale = (0.08, 0.08, 0.08)")
    for old, new in TINY_AND_FAR.items():
        assert old in text
        text = text.replace(old, new)
    return text


def test_nothing_in_view_stops_early_with_a_radius_that_works(tmp_path):
    with pytest.raises(CaptureError) as caught:
        capture_variant(tmp_path, "tiny", tiny_far_scene_text())
    message = str(caught.value)
    assert "Capture of /World/CesiumMan shows nothing: its first 24 samples" in message
    assert "radius 600" in message and "focal length 35" in message
    assert "Nothing was kept" in message and not (tmp_path / "tiny").exists()
    # The suggested radius frames the character.
    radius = float(re.search(r"pass --radius ([0-9.e+-]+),", caught.value.fix).group(1))
    assert 0.1 < radius < 1.0
    scene = scene_variant(tmp_path, "tiny", tiny_far_scene_text())
    overrides = CaptureOverrides(**{**SMALL.__dict__, "radius": radius, "frames": (1.0, 3.0)})
    fixed = capture(scene, CHARACTER, tmp_path / "fixed", overrides, workers=1, progress=False)
    assert fixed.complete and fixed.manifest.coverage.empty_samples == 0
    with np.load(fixed.folder / ds.PARAMS_FILE) as table:
        assert table["coverage"].min() > 0.05 * 32 * 32


def test_nothing_in_view_never_loses_an_existing_folder(tmp_path):
    text = tiny_far_scene_text()
    scene = scene_variant(tmp_path, "kept", text)
    out = tmp_path / "kept"
    with pytest.raises(CaptureError, match=f"{out} is kept as it was"):
        capture(scene, CHARACTER, out, SMALL, shard=(0, 2), workers=1, progress=False)
    records = sorted(p.name for p in (out / "items").glob("*.npz"))
    assert records and (out / ds.SETTINGS_FILE).is_file()
    with pytest.raises(CaptureError, match="shows nothing"):
        capture(scene, CHARACTER, out, SMALL, resume=True, workers=1, progress=False)
    assert set(records) <= {p.name for p in (out / "items").glob("*.npz")}


def test_empty_views_are_counted_in_a_warning(tmp_path):
    # A character flattened along the stage's front axis: the side views (1 and 3) see an
    # edge thinner than a pixel, the front and back views see it whole.
    flat = with_character_ops(SCENE.read_text(), "float3 xformOp:scale = (1, 1, 0.0005)")
    result = capture_variant(tmp_path, "flat", flat)
    assert result.complete
    assert result.manifest.coverage.empty_by_view == {1: 6, 3: 6}
    (warning,) = result.warnings
    assert warning.startswith("12 of 48 samples show less than 4 pixels of /World/CesiumMan")
    assert "(view 1: 6, view 3: 6)" in warning and "warning: 12 of 48" in result.summary()


def test_resume_repairs_damaged_and_missing_samples_byte_for_byte(tmp_path, dataset):
    out = tmp_path / "damaged"
    shutil.copytree(dataset.folder, out)
    with np.load(out / ds.PARAMS_FILE) as table:
        paths = [str(p) for p in table["path"]]
    truncated, deleted = out / paths[5], out / paths[30]
    truncated.write_bytes(truncated.read_bytes()[:500])
    deleted.unlink()
    record = sorted((out / "items").glob("*.npz"))[-1]
    record.write_bytes(record.read_bytes()[:100])
    (out / ds.MANIFEST_FILE).write_text("{")  # a half-written manifest goes as well

    result = small_capture(out, resume=True)
    assert result.complete and len(result.repaired) == 3
    problems = [p for d in result.repaired for p in d.problems]
    assert f"{paths[5]}: checksum differs (damaged or truncated)" in problems
    assert f"{paths[30]}: missing" in problems
    assert f"items/{record.name}: unreadable (BadZipFile)" in problems
    assert result.samples_done == sum(d.item.samples for d in result.repaired) == 36
    assert "repaired 3 damaged work item(s) (36 samples rendered again)" in result.summary()
    # Byte-identical to the undamaged capture, every file.
    assert checksum(out) == checksum(dataset.folder)
    for original in dataset.folder.rglob("*"):
        if original.is_file():
            copy = out / original.relative_to(dataset.folder)
            assert copy.read_bytes() == original.read_bytes(), copy
    # Nothing left to repair: a second resume renders nothing.
    again = small_capture(out, resume=True)
    assert again.repaired == [] and again.samples_done == 0


def test_records_written_before_coverage_existed_still_finalize(tmp_path, dataset):
    out = tmp_path / "old"
    shutil.copytree(dataset.folder, out)
    for record in (out / "items").glob("*.npz"):
        with np.load(record) as data:
            columns = {k: data[k] for k in data.files if k != "coverage"}
        record.write_bytes(ds.npz_bytes(columns))
    small_capture(out, resume=True)
    assert checksum(out) == checksum(dataset.folder)  # coverage read back off the EXRs


@pytest.mark.parametrize(
    ("frames", "message"),
    [("nan:nan", "--frames nan:nan is not a range of finite"), ("1e12:1e12", "lies outside")],
)
def test_cli_bad_frames_are_one_line(tmp_path, capsys, frames, message):
    code = main(["capture", str(SCENE), "--out", str(tmp_path / "o"), "--frames", frames])
    err = capsys.readouterr().err
    assert code == 2 and message in err and "Traceback" not in err
    assert err.startswith("rigspace capture: error:") and not (tmp_path / "o").exists()


def test_read_exr_of_a_repaired_sample(tmp_path, dataset):
    # The repaired folder's samples read back as maps (not only as equal bytes).
    out = tmp_path / "one"
    shutil.copytree(dataset.folder, out)
    with np.load(out / ds.PARAMS_FILE) as table:
        first = out / str(table["path"][0])
    first.write_bytes(b"")
    small_capture(out, resume=True)
    assert read_exr(first).mask.max() == 1


def test_the_resume_command_in_read_manifest_repairs_the_dataset(tmp_path, dataset, capsys):
    out = tmp_path / "unfinished"
    shutil.copytree(dataset.folder, out)
    (out / ds.MANIFEST_FILE).unlink()
    with np.load(out / ds.PARAMS_FILE) as table:
        (out / str(table["path"][7])).unlink()
    with pytest.raises(ds.DatasetError, match="finishes with `rigspace capture ") as caught:
        ds.read_manifest(out)
    command = re.search(r"`(rigspace capture [^`]+--resume)`", str(caught.value)).group(1)
    assert "--frames 1:6" in command and "--radius 3" in command
    assert main(shlex.split(command)[1:]) == 0  # the same settings: no "different settings"
    assert "repaired 1 damaged work item(s)" in capsys.readouterr().out
    assert checksum(out) == checksum(dataset.folder)


def test_resume_alone_takes_the_settings_from_capture_json(tmp_path, dataset, capsys):
    """`rigspace capture SCENE --out DS --resume` with none of the original flags (views,
    elevations, resolution, frames, frames per item): it refused the capture as one "captured
    with different settings"; it continues it with the settings capture.json saved. A flag
    given still has to match them."""
    out = tmp_path / "unfinished"
    shutil.copytree(dataset.folder, out)
    (out / ds.MANIFEST_FILE).unlink()
    with np.load(out / ds.PARAMS_FILE) as table:
        (out / str(table["path"][7])).unlink()
    assert main(["capture", str(SCENE), "--out", str(out), "--resume"]) == 0
    assert "repaired 1 damaged work item(s)" in capsys.readouterr().out
    assert checksum(out) == checksum(dataset.folder)
    assert main(["capture", str(SCENE), "--out", str(out), "--resume", "--views", "5"]) == 2
    err = capsys.readouterr().err
    assert "different settings (" in err and "views_per_ring)" in err and "--resume and none" in err

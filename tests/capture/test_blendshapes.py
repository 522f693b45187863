"""Capturing a character with blend shapes: each frame posed with its weights, which the
dataset records (params.npz `blend`, manifest `blend_shapes`); shapes the clips leave still
are drawn within the ring's authored ranges (issue 23)."""

from __future__ import annotations

import hashlib
import json
import re

import numpy as np
import pytest
from pxr import Sdf, Usd

from rigspace.capture.pipeline import capture
from rigspace.capture.settings import CaptureError, CaptureOverrides
from rigspace.sdk.validation import validate
from tests.blendshapes import ANIMATED, CHARACTER, weights_at, write_blendshape_character

SMALL = CaptureOverrides(views=3, elevations=(0.0,), resolution=32, frames_per_item=4)


@pytest.fixture(scope="module")
def face(tmp_path_factory):
    return write_blendshape_character(tmp_path_factory.mktemp("face"))


@pytest.fixture(scope="module")
def captured(face, tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "ds"
    capture(face, CHARACTER, out, SMALL, workers=1, progress=False, warn=lambda _: None)
    return out


def test_every_sample_records_the_weights_it_was_posed_with(captured):
    manifest = json.loads((captured / "manifest.json").read_text())
    names = manifest["blend_shapes"]
    assert names == ["smile", "blink", "jawOpen", "frown", "brow"]
    with np.load(captured / "params.npz") as table:
        blend, times = table["blend"], table["time"]
    assert blend.shape == (len(times), 5) and blend.dtype == np.float32
    for t in np.unique(times):
        rows = blend[times == t]
        np.testing.assert_array_equal(rows, rows[:1].repeat(len(rows), 0))  # views share it
        animated = dict(zip(ANIMATED, weights_at(float(t)), strict=True))
        for name in ("blink", "jawOpen", "brow"):  # animated: the clip's weights
            assert rows[0, names.index(name)] == pytest.approx(animated[name], abs=1e-6)
        # smile moves in the clip, so its authored range is not used
        assert rows[0, names.index("smile")] == pytest.approx(animated["smile"], abs=1e-6)
    frown = blend[:, names.index("frown")]  # still in the clip (never animated): drawn
    assert frown.min() >= 0.2 - 1e-6 and frown.max() <= 0.9 + 1e-6
    per_frame = np.array([frown[times == t][0] for t in np.unique(times)])
    # Sparse draws: at rest (its range's value nearest 0, 0.2 here) or drawn, a draw per frame.
    rest = np.isclose(per_frame, 0.2)
    assert 0 < rest.sum() < len(per_frame)
    assert len(np.unique(per_frame[~rest])) == (~rest).sum() and np.ptp(per_frame) > 0.2
    assert manifest["settings"]["blend_draws"] == [
        ["talk", "frown", pytest.approx(0.2), pytest.approx(0.9)]
    ]
    assert manifest["settings"]["shape_draws"] == "sparse"


def _settings(captured, shapes: int, draws: str):
    """The capture's settings drawing `shapes` shapes of a 0..1 range in every clip."""
    from dataclasses import replace

    from rigspace.capture.settings import CaptureSettings

    settings = CaptureSettings.from_json(json.loads((captured / "capture.json").read_text()))
    names = tuple(f"shape{k}" for k in range(shapes))
    draws_ = tuple(("*", name, 0.0, 1.0) for name in names)
    return replace(settings, blend_shapes=names, blend_draws=draws_, shape_draws=draws)


class _StillRig:
    """A rig whose animation leaves every weight at 0 (frame_weights reads `scalars` alone)."""

    def __init__(self, shapes: int) -> None:
        self.shapes = shapes

    def scalars(self, time: float) -> np.ndarray:
        return np.zeros(self.shapes)


def test_sparse_draws_put_a_uniform_number_of_shapes_at_work(captured):
    """15 shapes drawn over 3,200 frames: each count of shapes at work, none to all 15, in about
    1/16 of the frames (a face at rest among them), each shape at work in about half; the
    same frame draws the same weights again (every view, a resume, another worker)."""
    settings = _settings(captured, 15, "sparse")
    rig = _StillRig(15)
    weights = np.array([settings.frame_weights(rig, "talk", t / 3) for t in range(3200)])
    counts = np.bincount((weights > 0).sum(axis=1), minlength=16)
    assert counts.min() > 3200 / 16 * 0.6 and counts.max() < 3200 / 16 * 1.4, counts
    assert np.all(np.abs((weights > 0).mean(axis=0) - 0.5) < 0.06)
    assert weights.max() <= 1.0 and weights.min() >= 0.0
    np.testing.assert_array_equal(weights[7], settings.frame_weights(rig, "talk", 7 / 3))
    # "uniform" (captures before sparse draws) draws every shape, as those captures did.
    uniform = _settings(captured, 15, "uniform")
    drawn = np.array([uniform.frame_weights(rig, "talk", t / 3) for t in range(200)])
    assert (drawn > 0).all()
    key = f"talk|{7 / 3:.6f}|shape4".encode()
    old = int.from_bytes(hashlib.sha256(key).digest()[:8], "little") / 2.0**64
    assert drawn[7, 4] == pytest.approx(old)


def test_a_capture_json_without_shape_draws_is_read_as_the_uniform_draws_it_was_made_with(
    captured,
):
    from rigspace.capture.settings import CaptureSettings

    data = json.loads((captured / "capture.json").read_text())
    assert data["shape_draws"] == "sparse"
    del data["shape_draws"]
    assert CaptureSettings.from_json(data).shape_draws == "uniform"
    data["shape_draws"] = "gaussian"
    with pytest.raises(CaptureError, match="shape_draws is 'gaussian'"):
        CaptureSettings.from_json(data)


def test_the_weights_shape_the_images(face, captured, tmp_path):
    """The same capture with every shape forced still at 0 (the ring's ranges at (0, 0) and the
    animation's weights removed) gives other masks: the shapes reach the renderer."""
    from rigspace.capture.dataset import read_manifest, read_sample

    stage = Usd.Stage.Open(str(face))
    stage.GetPrimAtPath("/World/Asset/Skel/Anim").GetAttribute("blendShapeWeights").Clear()
    ring = stage.GetPrimAtPath(CHARACTER)
    ring.GetAttribute("rigspace:captureRing:blendShapeRanges").Set([(0.0, 0.0), (0.0, 0.0)])
    flat = tmp_path / "flat.usda"
    stage.GetRootLayer().Export(str(flat))
    out = tmp_path / "ds"
    capture(flat, CHARACTER, out, SMALL, workers=1, progress=False, warn=lambda _: None)
    with np.load(out / "params.npz") as table:
        assert not table["blend"].any()
    shaped, plain = read_manifest(captured), read_manifest(out)
    with np.load(captured / "params.npz") as table:
        paths = list(table["path"])
    differ = [
        np.abs(read_sample(captured, shaped, p).mask - read_sample(out, plain, p).mask).sum()
        for p in paths[::7]
    ]
    assert max(differ) > 5  # pixels of the mask moved with the shapes


def _ring(face, tmp_path, names, ranges):
    layer = Sdf.Layer.FindOrOpen(str(face))
    text = layer.ExportToString()
    stage = Usd.Stage.Open(Sdf.Layer.CreateAnonymous(".usda"))
    stage.GetRootLayer().ImportFromString(text)
    prim = stage.GetPrimAtPath(CHARACTER)
    prim.GetAttribute("rigspace:captureRing:blendShapeNames").Set(names)
    prim.GetAttribute("rigspace:captureRing:blendShapeRanges").Set(ranges)
    path = tmp_path / "ring.usda"
    stage.GetRootLayer().Export(str(path))
    return path


@pytest.mark.parametrize(
    ("names", "ranges", "code", "words"),
    [
        (["frown"], [], "BlendRangesDisagree", "1 blendShapeNames but 0 blendShapeRanges"),
        (["frown"], [(0.8, 0.2)], "BlendRangeInvalid", r"frown \(0.8, 0.2\)"),
        (["frown"], [(0.0, float("nan"))], "BlendRangeInvalid", "not finite"),
        (["frown", "frown"], [(0, 1), (0, 1)], "BlendShapeRepeated", "repeats frown"),
        (["pout"], [(0, 1)], "BlendShapeUnknown", "pout are not blend shapes"),
    ],
)
def test_bad_blend_ranges_are_named_by_inspect_and_refused_by_capture(
    face, tmp_path, names, ranges, code, words
):
    path = _ring(face, tmp_path, names, ranges)
    found = [f for f in validate(Usd.Stage.Open(str(path)), include_usd=False) if code in f.code]
    assert found and found[0].severity == "error" and "capture" in found[0].blocks
    assert re.search(words, found[0].message)
    with pytest.raises(CaptureError, match=words):
        capture(path, CHARACTER, tmp_path / "ds", SMALL, workers=1, progress=False)
    assert not (tmp_path / "ds").exists()

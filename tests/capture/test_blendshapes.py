"""Capturing a character with blend shapes: each frame posed with its weights, which the
dataset records (params.npz `blend`, manifest `blend_shapes`); shapes the clips leave still
are drawn within the ring's authored ranges (issue 23)."""

from __future__ import annotations

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
    assert len(np.unique(frown)) == len(np.unique(times))  # one draw per frame
    assert np.ptp(frown) > 0.2
    assert manifest["settings"]["blend_draws"] == [
        ["talk", "frown", pytest.approx(0.2), pytest.approx(0.9)]
    ]


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

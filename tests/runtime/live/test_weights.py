"""Live blend shape weights: absurd ones are malformed, the rest clamped into their shapes'
ranges, in every frame and every take."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from pxr import Usd

from tests.blendshapes import CHARACTER, add_face_binding, send_face, write_blendshape_character
from tests.conftest import free_port
from tests.runtime.live.conftest import FrameDriver

SENT = {"jawOpen": 1e30, "smile": 5.0, "frown": -3.0, "blink": 5.0, "brow": -3.0}
"""One absurd weight, and four out of range: smile and frown have declared ranges (the
face's capture ring: smile 0..1, frown 0.2..0.9), blink and brow the default, [-2, 2]."""


def test_the_ranges_are_the_capture_rings_where_it_declares_them(tmp_path):
    from rigspace.runtime.live.engine import weight_ranges

    face = write_blendshape_character(tmp_path)
    stage = Usd.Stage.Open(str(face))
    low, high = weight_ranges(stage.GetPrimAtPath(CHARACTER), ["smile", "blink", "frown"])
    np.testing.assert_allclose(low, [0.0, -2.0, 0.2], atol=1e-7)
    np.testing.assert_allclose(high, [1.0, 2.0, 0.9], atol=1e-7)


def _live_face(face, port: int, path) -> None:
    """The trained face with a VMC face binding (its neck and head by name)."""
    stage = Usd.Stage.Open(str(face))
    add_face_binding(stage.GetPrimAtPath(CHARACTER), port, 60.0)
    stage.GetRootLayer().Export(str(path))


@pytest.mark.slow
def test_absurd_and_out_of_range_weights_reach_no_frame_and_no_take(
    tmp_path_factory, tmp_path, monkeypatch
):
    pytest.importorskip("torch", reason="the face's model is trained here (the train extra)")
    from rigspace.runtime.live.record import read_take
    from rigspace.sdk.cli import main
    from tests.blendshapes import trained_face

    face, _ = trained_face(tmp_path_factory)
    port = free_port()
    scene = tmp_path / "live_face.usda"
    _live_face(face, port, scene)
    beauty: list[np.ndarray] = []
    applied: list[int] = []

    def on_frame(engine, frame) -> bool:
        beauty.append(frame.beauty.copy())
        live = engine.live.characters.get(CHARACTER)
        runtimes = live.runtimes if live is not None else []
        if runtimes and not applied:
            if "smile" in runtimes[0].buffer.pose().weights:
                applied.append(len(beauty))  # the first frame that may show them
            else:
                send_face(port, SENT, 0.01 * len(beauty))
        return bool(applied) and len(beauty) >= applied[0] + 3

    FrameDriver(monkeypatch, on_frame)
    take = tmp_path / "take.usda"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = main(
            ["live", str(scene), "--out", str(tmp_path / "out"), "--seconds", "120", "--camera",
             "/World/Camera", "--resolution", "64x64", "--record", str(take)]
        )  # fmt: skip
    assert code == 0 and applied
    assert all(np.isfinite(b).all() for b in beauty)  # a NaN weight drew a black silhouette
    assert not [w for w in caught if "invalid value" in str(w.message)]
    recorded = read_take(take)
    weights = dict(zip(recorded.blend_shapes, recorded.blend_weights.T, strict=True))
    assert np.abs(recorded.blend_weights).max() <= 2.0  # jawOpen's 1e30 was malformed
    # From the first tick the live weights reached on, each is clamped into its range: smile
    # 5 -> 1 and frown -3 -> 0.2 (the capture ring's), blink 5 -> 2 and brow -3 -> -2 (the
    # default); the ticks before hold the stage animation's, as its frames did.
    live = np.flatnonzero(weights["smile"] == 1.0)
    assert len(live) and np.all(np.diff(live) == 1) and live[-1] == len(recorded.times) - 1
    clamped = {"smile": 1.0, "frown": 0.2, "blink": 2.0, "brow": -2.0}
    for name, value in clamped.items():
        np.testing.assert_allclose(weights[name][live], value, atol=1e-6)

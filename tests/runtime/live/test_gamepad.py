"""Game controllers: recorded evdev events through the decoder, and a real fd through the source."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pxr import Usd, UsdSkel

from rigspace.runtime.live.binding import open_binding
from rigspace.runtime.live.buffer import LiveBuffer
from rigspace.runtime.live.decoders.evdev import (
    ABS_CODES,
    EV_ABS,
    EV_KEY,
    EV_SYN,
    EVENT,
    SYN_DROPPED,
    SYN_REPORT,
    EvdevDecoder,
)
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.runtime.live.sources import open_source
from rigspace.runtime.live.transports import LiveSourceError
from rigspace.sdk.rotations import matrix_from_quat, quat_from_matrix
from tests.runtime.live.conftest import SAMPLE_CHARACTER, live_binding, wait_for


def ev(kind: int, code: int, value: int, t: float = 5.0) -> bytes:
    return EVENT.pack(int(t), round((t % 1) * 1e6), kind, code, value)


def axis(name: str, value: int, t: float = 5.0) -> bytes:
    return ev(EV_ABS, ABS_CODES[name], value, t)


def about(axis_index: int, degrees: float) -> np.ndarray:
    q = np.zeros(4)
    q[0] = np.cos(np.radians(degrees) / 2)
    q[1 + axis_index] = np.sin(np.radians(degrees) / 2)
    return q


def test_axes_become_joint_rotations_on_syn_report():
    decoder = EvdevDecoder()
    assert decoder.bones == ("head", "spine_02")
    data = axis("ABS_RX", 32767) + axis("ABS_RY", -16384) + ev(EV_KEY, 304, 1)
    assert decoder.feed(data, 0.0) == []  # nothing until the report
    (frame,) = decoder.feed(ev(EV_SYN, SYN_REPORT, 0, 5.25), 0.0)
    assert frame.timestamp == pytest.approx(5.25)
    # Full right: -60 deg about Y; half down (past the 10 % dead zone): 40 * (0.5 - 0.1) / 0.9.
    pitch = 40.0 * ((-16384 + 0.5) / 32767.5 + 0.1) / 0.9  # range centre: -0.5
    expected = quat_from_matrix(matrix_from_quat(about(0, pitch)) @ matrix_from_quat(about(1, -60)))
    assert quat_angle(frame.rotations[0], expected) < 1e-7
    assert quat_angle(frame.rotations[1], [1.0, 0, 0, 0]) < 1e-12  # left stick centred
    assert decoder.counters.ignored == 1


def test_dead_zone_split_events_and_syn_dropped():
    decoder = EvdevDecoder()
    data = axis("ABS_X", 3000) + ev(EV_SYN, SYN_REPORT, 0)
    frames = decoder.feed(data[:10], 0.0) + decoder.feed(data[10:], 0.0)  # split mid-event
    assert len(frames) == 1 and quat_angle(frames[0].rotations[1], [1.0, 0, 0, 0]) < 1e-12
    # After SYN_DROPPED everything up to the next report is discarded.
    data = ev(EV_SYN, SYN_DROPPED, 0) + axis("ABS_X", 32767) + ev(EV_SYN, SYN_REPORT, 0)
    assert decoder.feed(data, 0.0) == []
    bad = EVENT.pack(1, 5_000_000, 99, 0, 0)  # no such event type, microseconds out of range
    decoder.feed(bad, 0.0)
    assert decoder.counters.malformed == 1 and decoder.buffered == 0


@settings(max_examples=150, deadline=None)
@given(chunks=st.lists(st.binary(max_size=100), max_size=20))
def test_fuzz(chunks):
    decoder = EvdevDecoder()
    for chunk in chunks:
        for f in decoder.feed(chunk, 0.0):
            np.testing.assert_allclose(np.linalg.norm(f.rotations, axis=1), 1.0, atol=1e-9)
        assert decoder.buffered < EVENT.size


def test_controller_fd_turns_the_head_on_top_of_the_stage_animation():
    stage = Usd.Stage.Open(str(SAMPLE_CHARACTER))
    skel = stage.GetPrimAtPath("/Character/Skel")
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    local = np.array(
        UsdSkel.MakeTransforms(*(a.Get(400) for a in (anim.GetTranslationsAttr(), anim.GetRotationsAttr(), anim.GetScalesAttr())))
    )  # fmt: skip
    read_end, write_end = os.pipe()  # a real file descriptor read through select/os.read
    binding = live_binding(f"gamepad:///proc/self/fd/{read_end}", name="pad")
    runtime = open_binding(binding, skel, 0.01)
    runtime.start()
    try:
        os.write(write_end, axis("ABS_RX", 32767) + ev(EV_SYN, SYN_REPORT, 0))
        assert wait_for(lambda: runtime.buffer.samples == 2)
        out, pose = runtime.apply(local)
    finally:
        runtime.stop()
        os.close(read_end)
        os.close(write_end)
    joints = [str(j).rsplit("/", 1)[-1] for j in UsdSkel.Skeleton(skel).GetJointsAttr().Get()]
    head = joints.index("head")
    stage_head = matrix_from_quat(quat_from_matrix(local[head, :3, :3].T))
    want = quat_from_matrix(stage_head @ matrix_from_quat(about(1, -60.0)))
    assert quat_angle(quat_from_matrix(out[head, :3, :3].T), want) < 1e-9
    untouched = [j for j in range(len(joints)) if joints[j] not in ("head", "spine_02")]
    np.testing.assert_array_equal(out[untouched], local[untouched])
    assert pose.status == "connected"


def test_gamepad_errors_name_the_fix(monkeypatch):
    with pytest.raises(LiveSourceError, match=r"'pad'.*event99 cannot be opened.*input group"):
        source = open_source("gamepad:///dev/input/event99", "pad")
        source.start(LiveBuffer(source.bones))
    import glob

    monkeypatch.setattr(glob, "glob", lambda pattern: [])  # a machine without controllers
    with pytest.raises(LiveSourceError, match="no game controller is connected"):
        open_source("gamepad://", "pad")
    with pytest.raises(LiveSourceError, match=r"axes=.*CONTROL:JOINT:AXIS:DEGREES"):
        open_source("gamepad:///dev/input/event0?axes=ABS_Q:head:Y:10", "pad")


def test_triggers_and_buttons_set_blend_shape_weights():
    """shapes=CONTROL:SHAPE[:MIN:MAX] (the binding's gamepadShapes): a trigger's position, a
    button while held; two controls of one shape: the stronger wins."""
    from rigspace.runtime.live.decoders.evdev import parse_clips

    shapes = parse_clips("ABS_Z:jawOpen,BTN_SOUTH:eyeBlinkLeft,ABS_RZ:jawOpen")
    decoder = EvdevDecoder(shapes=shapes)
    data = axis("ABS_Z", 256) + axis("ABS_RZ", 768) + ev(EV_KEY, 304, 1)
    (frame,) = decoder.feed(data + ev(EV_SYN, SYN_REPORT, 0, 5.5), 0.0)
    assert frame.weights == {"jawOpen": pytest.approx(768 / 1023), "eyeBlinkLeft": 1.0}
    (frame,) = decoder.feed(ev(EV_KEY, 304, 0) + ev(EV_SYN, SYN_REPORT, 0, 5.6), 0.0)
    assert frame.weights["eyeBlinkLeft"] == 0.0
    url = "gamepad:///dev/null?shapes=ABS_Z:jawOpen:0:255"
    source = open_source(url, "pad")
    assert source.decoder.shapes[0].maximum == 255  # type: ignore[attr-defined]
    with pytest.raises(LiveSourceError, match="shapes"):
        open_source("gamepad:///dev/null?shapes=ABS_Q:jawOpen", "pad")

"""The engine with a live binding: lazy sources, the live pose per frame, reuse when it holds still."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.runtime.live.decoders.vmc import encode_frame
from rigspace.runtime.live.retarget import PRESETS
from rigspace.runtime.live.transports import LiveSourceError
from tests.conftest import REPO, free_port
from tests.runtime.live.conftest import udp_port_bound, wait_for

LIVE_SCENE = REPO / "samples" / "scenes" / "live.usda"
PREVIS = REPO / "samples" / "scenes" / "previs.usda"
SMALL = {"width": 96, "height": 54, "max_level": 32, "prim_samples": 1}


def send_pose(port: int, bones, rotations, t: float) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for dgram in encode_frame(bones, rotations, np.array([0.0, 0.95, 0.0]), None, t):
            sock.sendto(dgram, ("127.0.0.1", port))


HELD = tuple(PRESETS["unity"].bone_map)
"""Every bone the binding maps: a joint whose bone never arrives plays the stage animation."""


def held_pose(angle: float) -> np.ndarray:
    """A T-pose with the arms lowered by `angle` radians about Z (w, x, y, z)."""
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(HELD), 1))
    q[HELD.index("LeftUpperArm")] = [np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)]
    q[HELD.index("RightUpperArm")] = [np.cos(angle / 2), 0.0, 0.0, -np.sin(angle / 2)]
    return q


def test_a_still_source_costs_a_reused_frame_and_every_frame_reports_the_binding():
    port = free_port()
    with Engine(
        LIVE_SCENE, EngineSettings(sources={"suit": f"vmc://127.0.0.1:{port}"}, **SMALL)
    ) as engine:
        assert not udp_port_bound(port)  # sources open lazily, at the first frame
        first = engine.render(10.0)
        assert udp_port_bound(port)
        (entry,) = first.report.characters
        assert entry["live"] == [{"binding": "suit", "status": "waiting", "weight": 0.0}]
        assert first.report.live[0]["samples"] == 0
        live = engine.live.characters["/World/Hero"]
        for k in range(3):  # a performer holding still: the same values, new timestamps
            send_pose(port, HELD, held_pose(0.6), 0.01 * k)
        runtime = live.runtimes[0]
        assert wait_for(lambda: runtime.counters().samples >= 3 * len(HELD))
        moved = engine.render(11.0)
        assert moved.report.characters[0]["live"][0]["status"] == "connected"
        assert moved.report.characters[0]["decision"] == "evaluated"
        # The connect fades in from the stage pose (issue 21: no pop); the held pose after it.
        # The performer holds still meanwhile (a gap would hold the fade where it was).
        assert runtime.fading
        sent = [3]

        def holding() -> bool:
            send_pose(port, HELD, held_pose(0.6), 0.01 * sent[0])
            sent[0] += 1
            samples = sent[0] * (len(HELD) + 1)  # and Root
            assert wait_for(lambda: runtime.counters().samples >= samples)
            engine.render(11.0)
            return not runtime.fading

        assert wait_for(holding)
        holding()  # one more sample of the held pose, after the fade
        # A later stage time, the same live pose: the character's layer is reused (no network
        # call), while the set's props go on moving with the stage.
        still = engine.render(12.0)
        assert still.report.characters[0]["decision"] == "reused"
        assert still.report.seconds["network"] < 1e-4  # no network evaluation
        assert still.report.live[0]["samples"] == sent[0] * (len(HELD) + 1)
        # The same time code with a new live pose is not the last frame repeated.
        send_pose(port, HELD, held_pose(-0.4), 0.01 * sent[0])
        assert wait_for(lambda: runtime.counters().samples >= (sent[0] + 1) * (len(HELD) + 1))
        changed = engine.render(12.0)
        assert not changed.report.repeat_of_last_frame
        assert changed.report.characters[0]["decision"] == "evaluated"
    assert not udp_port_bound(port)  # closed with the engine


def test_the_stage_animation_is_not_reused_without_a_live_binding():
    with Engine(LIVE_SCENE, EngineSettings(live=False, **SMALL)) as engine:
        assert not engine.live.active
        engine.render(11.0)
        frame = engine.render(12.0)
    assert frame.report.characters[0]["decision"] == "evaluated"  # the animation moves
    assert frame.report.live is None and "live" not in frame.report.characters[0]


def test_a_disabled_binding_leaves_the_stage_animation():
    with Engine(PREVIS, EngineSettings(**SMALL)) as engine:
        assert not engine.live.active  # previs authors its suit binding disabled


def test_a_binding_whose_source_cannot_open_is_one_error_naming_it():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        engine = Engine(
            LIVE_SCENE, EngineSettings(sources={"suit": f"vmc://127.0.0.1:{port}"}, **SMALL)
        )
        with pytest.raises(LiveSourceError) as error:
            engine.render(0.0)
        engine.close()
    message = str(error.value)
    assert message.startswith("Live binding 'suit' of /World/Hero: Live source 'suit'")
    assert "is in use" in message and "enabled = false" in message


def test_a_source_of_another_scheme_does_not_inherit_the_old_sources_bone_map(capsys):
    """live.usda's suit binding maps Unity bone names for vmc://; --source suit=bvh+tcp://...
    is a CMU-style BVH sender, so that map, the axes and units reset to the bvh preset's."""
    from pxr import Usd

    from rigspace.runtime.live.engine import with_source
    from rigspace.sdk import schema

    stage = Usd.Stage.Open(str(LIVE_SCENE))
    (suit,) = schema.read_live_bindings(stage.GetPrimAtPath("/World/Hero"))
    assert suit.url.startswith("vmc://") and suit.source_bones
    same = with_source(suit, "vmc://127.0.0.1:40000")
    assert same.source_bones == suit.source_bones and same.url == "vmc://127.0.0.1:40000"
    assert capsys.readouterr().err == ""
    other = with_source(suit, "bvh+tcp://127.0.0.1:40001")
    assert other.source_bones == () and other.target_joints == () and other.enabled
    assert other.bone_preset == "auto" and other.source_meters_per_unit == 1.0
    note = capsys.readouterr().err
    assert "a bvh+tcp:// source replaces vmc://" in note and "sourceBones" in note

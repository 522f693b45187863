"""A gamepad mapped on the binding (gamepadOffsets, gamepadClips) driving the engine's pose."""

from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd

from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.runtime.live.binding import open_binding
from rigspace.runtime.live.decoders.evdev import (
    ABS_CODES,
    BTN_CODES,
    EV_ABS,
    EV_KEY,
    EV_SYN,
    EVENT,
    SYN_REPORT,
    EvdevDecoder,
    parse_axes,
    parse_clips,
)
from rigspace.runtime.live.retarget import blend_transforms
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.runtime.live.transports import LiveSourceError
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.rotations import matrix_from_quat, quat_from_matrix
from rigspace.sdk.schema import read_live_bindings
from tests.conftest import REPO
from tests.runtime.live.conftest import wait_for

PREVIS = REPO / "samples" / "scenes" / "previs.usda"
SMALL = {"width": 96, "height": 54, "max_level": 32, "prim_samples": 1}
OFFSETS = ["ABS_RX:head:Y:-60", "BTN_TL:spine_02:Z:15"]
CLIPS = ["ABS_RZ:wave", "BTN_SOUTH:wave"]


def ev(kind: int, code: int, value: int, t: float = 5.0) -> bytes:
    return EVENT.pack(int(t), round((t % 1) * 1e6), kind, code, value)


def report(t: float = 5.0) -> bytes:
    return ev(EV_SYN, SYN_REPORT, 0, t)


def about(axis_index: int, degrees: float) -> np.ndarray:
    q = np.zeros(4)
    q[0] = np.cos(np.radians(degrees) / 2)
    q[1 + axis_index] = np.sin(np.radians(degrees) / 2)
    return q


def pad_scene(tmp_path: Path, offsets=OFFSETS, clips=CLIPS, name: str = "pad") -> Path:
    """previs.usda with a `pad` binding whose controller map is authored on the binding."""

    def array(items):
        return "[" + ", ".join(f'"{i}"' for i in items) + "]"

    path = tmp_path / f"{name}.usda"  # a new name: USD caches an opened layer by path
    path.write_text(
        '#usda 1.0\n(\n    defaultPrim = "World"\n    endTimeCode = 1619\n'
        "    framesPerSecond = 30\n    metersPerUnit = 0.01\n    startTimeCode = 0\n"
        f'    subLayers = [@{PREVIS}@]\n    timeCodesPerSecond = 30\n    upAxis = "Y"\n)\n'
        'over "World"\n{\n    over "Hero" (\n'
        '        prepend apiSchemas = ["RigspaceLiveBindingAPI:pad"]\n    )\n    {\n'
        '        uniform string rigspace:live:pad:url = "gamepad:///dev/input/event0"\n'
        f"        uniform string[] rigspace:live:pad:gamepadOffsets = {array(offsets)}\n"
        f"        uniform string[] rigspace:live:pad:gamepadClips = {array(clips)}\n"
        "    }\n}\n"
    )
    return path


def test_recorded_events_drive_offsets_from_buttons_and_clip_blends():
    decoder = EvdevDecoder(parse_axes(OFFSETS), parse_clips([*CLIPS, "ABS_Z:walk:0:255"]))
    assert decoder.bones == ("head", "spine_02") and decoder.clip_names == ("wave", "walk")
    data = (
        ev(EV_KEY, BTN_CODES["BTN_TL"], 1)
        + ev(EV_ABS, ABS_CODES["ABS_RZ"], 512)
        + ev(EV_ABS, ABS_CODES["ABS_Z"], 51)
    )
    (frame,) = decoder.feed(data + report(6.5), 0.0)
    assert frame.timestamp == pytest.approx(6.5)
    assert quat_angle(frame.rotations[1], about(2, 15.0)) < 1e-9  # held: full 15 deg lean
    assert quat_angle(frame.rotations[0], [1.0, 0, 0, 0]) < 1e-12
    np.testing.assert_allclose(decoder.clip_weights, [512 / 1023, 0.2])
    # The button and the trigger blend the same clip: the stronger one counts.
    decoder.feed(ev(EV_KEY, BTN_CODES["BTN_SOUTH"], 1) + report(6.6), 0.0)
    np.testing.assert_allclose(decoder.clip_weights, [1.0, 0.2])
    (frame,) = decoder.feed(
        ev(EV_KEY, BTN_CODES["BTN_SOUTH"], 0) + ev(EV_KEY, BTN_CODES["BTN_TL"], 0) + report(6.7),
        0.0,
    )
    assert quat_angle(frame.rotations[1], [1.0, 0, 0, 0]) < 1e-12  # released
    np.testing.assert_allclose(decoder.clip_weights, [512 / 1023, 0.2])
    for bad in ("BTN_NOPE:wave", "ABS_RZ", "ABS_RZ:wave:9:1"):
        with pytest.raises(ValueError):
            parse_clips(bad)
    for bad in ("ABS_RX:head:W:10", "ABS_RX:head:Y:nan", "BTN_TL:head:Y"):
        with pytest.raises(ValueError):
            parse_axes([bad])


def test_blend_transforms_slerps_rotations_and_lerps_translations():
    a = np.tile(np.eye(4), (2, 1, 1))
    b = a.copy()
    b[:, :3, :3] = matrix_from_quat(np.tile(about(1, 80.0), (2, 1))).swapaxes(1, 2) * 2.0
    b[:, 3, :3] = [4.0, 0.0, -2.0]
    half = blend_transforms(a, b, 0.5)
    scale = np.linalg.norm(half[:, :3, :3], axis=2)
    np.testing.assert_allclose(scale, 1.5)
    rotation = quat_from_matrix((half[:, :3, :3] / 1.5).swapaxes(1, 2))
    assert np.all(quat_angle(rotation, about(1, 40.0)) < 1e-9)
    np.testing.assert_allclose(half[:, 3, :3], [[2.0, 0.0, -1.0]] * 2)
    np.testing.assert_allclose(blend_transforms(a, b, 1.0), b, atol=1e-12)
    assert blend_transforms(a, b, 0.0) is a


def test_the_binding_map_turns_joints_and_blends_the_stage_towards_a_clip(tmp_path):
    read_end, write_end = os.pipe()  # a real fd read through select/os.read, as /dev/input
    url = f"gamepad:///proc/self/fd/{read_end}"
    try:
        with Engine(pad_scene(tmp_path), EngineSettings(sources={"pad": url}, **SMALL)) as engine:
            engine.open_live()
            hero = engine.characters[0]
            live = engine.live.characters[hero.path]
            (runtime,) = live.runtimes
            assert runtime.clip_ranges == {"wave": (360.0, 599.0)}
            os.write(
                write_end,
                ev(EV_ABS, ABS_CODES["ABS_RX"], 32767)
                + ev(EV_KEY, BTN_CODES["BTN_TL"], 1)
                + ev(EV_ABS, ABS_CODES["ABS_RZ"], 1023)
                + report(),
            )
            assert wait_for(lambda: runtime.buffer.samples == 2)
            now = time.monotonic()
            first, _ = engine.live.merged(hero, 100.0, now)
            half, _ = engine.live.merged(hero, 100.0, now + 0.125)  # 0.25 s fade: half way
            full, poses = engine.live.merged(hero, 100.0, now + 1.0)
            assert poses[0][1].status == "stale" and poses[0][1].weight == 1.0  # held
            stage = np.asarray(hero.rig.local_transforms(100.0))
            wave = np.asarray(hero.rig.local_transforms(360.0 + (100.0 - 360.0) % 239.0))
            joints = [j.rsplit("/", 1)[-1] for j in runtime.retargeter.target_joints]
    finally:
        os.close(read_end)
        os.close(write_end)
    head, spine = joints.index("head"), joints.index("spine_02")
    others = [j for j in range(len(joints)) if j not in (head, spine)]
    np.testing.assert_allclose(first[others], stage[others], atol=1e-9)  # eases in from 0
    for got, weight in ((half, 0.5), (full, 1.0)):
        want = blend_transforms(stage, wave, weight)
        np.testing.assert_allclose(got[others], want[others], atol=1e-9)
        for joint, offset in ((head, about(1, -60.0)), (spine, about(2, 15.0))):
            base = quat_from_matrix(want[joint, :3, :3].T / np.linalg.norm(want[joint, 0, :3]))
            expected = quat_from_matrix(matrix_from_quat(base) @ matrix_from_quat(offset))
            turned = quat_from_matrix(got[joint, :3, :3].T / np.linalg.norm(got[joint, 0, :3]))
            assert quat_angle(turned, expected) < 1e-7
    assert not np.allclose(full[others], stage[others], atol=1e-3)  # the clip really differs


def test_a_url_map_overrides_the_binding_and_unknown_clips_are_named(tmp_path):
    read_end, write_end = os.pipe()
    try:
        url = f"gamepad:///proc/self/fd/{read_end}?axes=ABS_X:neck_01:X:10"
        with Engine(pad_scene(tmp_path), EngineSettings(sources={"pad": url}, **SMALL)) as engine:
            engine.open_live()
            (runtime,) = engine.live.characters[engine.characters[0].path].runtimes
            assert runtime.source.bones == ("neck_01",)  # the URL's axes=, the stage's clips
            assert runtime.source.decoder.clip_names == ("wave",)
        # Inspect stops a scene whose pad names a clip the character lacks, before any frame.
        scene = pad_scene(tmp_path, clips=["ABS_RZ:dance"], name="dance")
        with pytest.raises(RigspaceError, match=r"gamepadClips entry 'ABS_RZ:dance'.*walk, wave"):
            Engine(
                scene,
                EngineSettings(sources={"pad": f"gamepad:///proc/self/fd/{read_end}"}, **SMALL),
            )
        # open_binding itself names it too (for callers that skip validation).
        stage = Usd.Stage.Open(str(PREVIS))
        (binding,) = [b for b in read_live_bindings(stage.GetPrimAtPath("/World/Hero"))]
        binding = replace(
            binding, url=f"gamepad:///proc/self/fd/{read_end}", gamepad_clips=("ABS_RZ:dance",)
        )
        skeleton = stage.GetPrimAtPath("/World/Hero/Asset/Skel")
        with pytest.raises(LiveSourceError, match=r"'suit'.*'dance'.*clipNames: walk\)"):
            open_binding(binding, skeleton, 0.01, clips={"walk": (0.0, 359.0)})
    finally:
        os.close(read_end)
        os.close(write_end)

"""`rigspace live` end to end over real UDP: the CMU clip sent over VMC, rendered, recorded."""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom
from pythonosc.osc_message_builder import build_msg

from rigspace.runtime.live.binding import LiveBindingRuntime, open_binding
from rigspace.runtime.live.buffer import LivePose
from rigspace.runtime.live.record import read_take
from rigspace.sdk import schema
from rigspace.sdk.cli import main
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.rotations import quat_from_matrix
from tests.conftest import REPO, free_port
from tests.runtime.live.conftest import CMU_CLIP, FrameDriver, Sender, udp_port_bound, wait_for
from tests.runtime.live.vmc_sender import cmu_clip

LIVE_SCENE = REPO / "samples" / "scenes" / "live.usda"
TURN = 90.0
"""How far a second sender turns the clip's hips: poses the clip never has."""


@pytest.fixture(scope="module")
def clip():
    return cmu_clip()


def streaming(url: str) -> None:
    """Wait until a sender streams to `url`'s port (one datagram seen there), so a receiver
    that binds the port next finds the data flowing: the first packet is an event, not a
    guess of how long a sender process takes to start."""
    port = int(url.rsplit(":", 1)[1])
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", port))
        sock.settimeout(60.0)
        sock.recv(65536)


def scene_with(tmp_path: Path, **attributes) -> Path:
    """live.usda under a layer that authors more of the suit binding's attributes."""
    lines = "\n".join(f"        {decl} = {value}" for decl, value in attributes.items())
    path = tmp_path / "scene.usda"
    path.write_text(
        '#usda 1.0\n(\n    defaultPrim = "World"\n    endTimeCode = 1619\n'
        "    framesPerSecond = 30\n    metersPerUnit = 0.01\n    startTimeCode = 0\n"
        f'    subLayers = [@{LIVE_SCENE}@]\n    timeCodesPerSecond = 30\n    upAxis = "Y"\n)\n'
        f'over "World"\n{{\n    over "Hero"\n    {{\n{lines}\n    }}\n}}\n'
    )
    return path


def expected_locals(clip, scene: Path, url: str, time_code: float) -> np.ndarray:
    """(F, J, 4) each clip frame retargeted as the receiver does (the documented conversion:
    HumanBodyBones in VmcDecoder's frame, the unity preset, the T-pose rest aligned)."""
    stage = Usd.Stage.Open(str(scene))
    hero = stage.GetPrimAtPath("/World/Hero")
    rig = CharacterRig(hero)
    binding = schema.read_live_bindings(hero)[0]
    runtime = open_binding(
        schema.LiveBinding(**{**binding.__dict__, "url": url}),
        rig.skeleton.GetPrim(),
        UsdGeom.GetStageMetersPerUnit(stage),
    )  # built, never started: only its retargeter is used
    bones = runtime.source.bones
    index = [bones.index(b) for b in clip.bones]
    stage_local = np.asarray(rig.local_transforms(time_code))
    out = []
    for rotations in clip.rotations:
        full = np.tile([1.0, 0.0, 0.0, 0.0], (len(bones), 1))
        full[index] = rotations
        valid = np.zeros(len(bones), dtype=bool)
        valid[index] = True
        pose = LivePose(full, valid, None, "connected", 1.0, 0.0)
        local = runtime.retargeter.apply(stage_local, pose)
        out.append(quat_from_matrix(np.swapaxes(local[:, :3, :3], 1, 2)))
    return np.array(out)


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (rad) between unit quaternions, broadcast over leading axes."""
    dot = np.abs(np.sum(a * b, axis=-1))
    return 2 * np.arccos(np.clip(dot, 0.0, 1.0))


def assert_the_take_plays_the_clip_forward(recorded, clip, url: str) -> None:
    """Every tick recorded after the connect's fade from the stage animation is one of the
    clip's frames, converted, within 1e-3 rad per joint, running forward with the clip."""
    expected = expected_locals(clip, LIVE_SCENE, url, 0.0)
    errors = angles(recorded.rotations[:, None], expected[None]).max(axis=2)  # (T, F)
    matched = np.flatnonzero(errors.min(axis=1) < 1e-3)
    assert len(matched) >= 20 and np.all(np.diff(matched) == 1), matched
    assert matched[-1] == len(recorded.times) - 1
    frames = errors.argmin(axis=1)[matched]
    steps = np.diff(frames) % len(clip.rotations)  # the sender loops the clip
    assert np.all(steps < len(clip.rotations) // 2) and steps.sum() > 2 * len(steps)


@pytest.mark.slow
def test_live_records_the_clip_sent_over_vmc_and_render_replays_the_take(tmp_path, clip, capsys):
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    out = tmp_path / "out"
    take = tmp_path / "take.usda"
    sender = Sender(url)
    try:
        streaming(url)
        code = main(
            ["live", str(LIVE_SCENE), "--out", str(out), "--seconds", "2", "--source",
             f"suit={url}", "--record", str(take), "--resolution", "96x54", "--max-level", "32",
             "--video", str(out / "live.mp4")]
        )  # fmt: skip
    finally:
        sender.close()
    assert code == 0
    assert "rigspace live: ready: 60 ticks at 30 fps" in capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    assert report["ticks"] == 60 and report["rendered"] + report["dropped"] == 60
    assert report["rendered"] >= 3 and len(list(out.glob("frame_*.png"))) == report["rendered"]
    (binding,) = report["bindings"]
    assert binding["binding"] == "suit" and binding["samples"] > 1000
    assert binding["malformed"] == 0
    latency = report["latency_ms"]["suit"]
    assert 0 < latency["p50"] <= latency["p99"]
    for frame in report["frames"]:  # received, at most a timeout before the tick's due time
        if "suit" in frame["latency_ms"]:
            since_due = frame["written_seconds"] - frame["tick"] / 30
            assert 0 <= frame["latency_ms"]["suit"] <= (since_due + 0.5) * 1e3 + 1, frame
    last = report["frames"][-1]
    assert last["live"][0]["status"] == "connected" and last["live"][0]["url"] == url
    assert last["characters"][0]["live"] == [
        {"binding": "suit", "status": "connected", "weight": 1.0}
    ]
    assert (out / "live.mp4").stat().st_size > 1000
    recorded = read_take(take)
    assert len(recorded.times) == 60  # the stage's rate, whatever was dropped
    assert_the_take_plays_the_clip_forward(recorded, clip, url)
    # `rigspace render` re-renders the take: the shot stage poses the character by it.
    shot = tmp_path / "take.shot.usda"
    stage = Usd.Stage.Open(str(shot))
    rig = CharacterRig(stage.GetPrimAtPath("/World/Hero"))
    t = float(stage.GetStartTimeCode() + 10)
    local = np.asarray(rig.local_transforms(t))
    k = int(np.argmin(np.abs(recorded.times * 30 + stage.GetStartTimeCode() - t)))
    q = quat_from_matrix(np.swapaxes(local[:, :3, :3], 1, 2))
    assert angles(q, recorded.rotations[k]).max() < 1e-5
    assert main(["render", str(shot), "--out", str(tmp_path / "rr"), "--frames", f"{t:g}:{t:g}",
                 "--resolution", "96x54", "--max-level", "32"]) == 0  # fmt: skip
    rendered = json.loads((tmp_path / "rr" / "report.json").read_text())
    assert rendered["frames"][0]["characters"][0]["decision"] == "evaluated"
    assert "live" not in rendered["frames"][0]  # the take, not a live source, drives it


def degrees_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per joint, degrees between two sets of (J, 4) quaternions."""
    return np.degrees(angles(a, b))


NEW_SENDER_SAMPLES = 30
"""Samples the restarted binding counts before the run may end: a second of the new sender's."""


class StopThenRestart:
    """on_frame (FrameDriver) of a run whose sender stops and a new one starts: a sender once
    the engine is loaded; once the binding has settled (connected, no fade) for three frames,
    that sender stops; once the character blends back from lost, a new sender process starts
    (its /VMC/Ext/T from 0, poses turned by TURN) while another socket sends four absurd
    /VMC/Ext/T; done when the binding has settled again. Keeps each phase's binding entries,
    what every frame showed, and the engine's ticks."""

    def __init__(self, url: str, port: int) -> None:
        self.url, self.port = url, port
        self.senders: list[Sender] = []
        self.phases: dict[str, list] = {"first": [], "paused": [], "restarted": []}
        self.shown: dict[float, np.ndarray] = {}
        self.phase, self.settled = "warm-up", 0
        self.samples_at_restart = 0
        self.ticks = None

    def __call__(self, engine, frame) -> bool:
        live = engine.live.characters["/World/Hero"]
        if self.phase == "warm-up":  # the engine is loaded and its source open
            self.senders.append(Sender(self.url))
            self.phase = "first"
            return False
        self.ticks = getattr(engine.live, "ticks", None)
        self.shown[frame.report.time] = live.last_local.copy()  # what this frame used
        entry = frame.report.characters[0]["live"][0]
        self.phases[self.phase].append(entry)
        samples = live.runtimes[0].counters().samples
        settled = entry["status"] == "connected" and not live.runtimes[0].fading
        self.settled = self.settled + 1 if settled else 0
        if self.phase == "first" and self.settled >= 3:
            self.senders.pop().close()
            self.phase = "paused"
        elif self.phase == "paused":
            lost = [e for e in self.phases["paused"] if e["status"] == "lost"]
            if len(lost) >= 2 and min(e["weight"] for e in lost) < 1.0:  # blending back
                self.samples_at_restart = samples
                self.restart()
        # Done once the new sender's own samples arrive (its process may start late on a
        # loaded machine: the four absurd /VMC/Ext/T alone must not end the run) and the
        # binding has settled on them.
        arrived = samples >= self.samples_at_restart + NEW_SENDER_SAMPLES
        return self.phase == "restarted" and arrived and self.settled >= 3

    def restart(self) -> None:
        self.senders.append(Sender(self.url, TURN))  # a new process: a new port, T from 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
            for t in (1e12, -1e12, 3e38, 0.0):
                other.sendto(build_msg("/VMC/Ext/T", [t]).dgram, ("127.0.0.1", self.port))
        self.phase, self.settled = "restarted", 0


def record_evaluations(monkeypatch) -> dict[float, str]:
    """Local time -> status, of every evaluation of a live pose (LiveBindingRuntime.apply_frame)
    from now on."""
    evaluated: dict[float, str] = {}
    real_apply_frame = LiveBindingRuntime.apply_frame

    def apply_frame(runtime, stage_local, now=None, sample=None, time_code=None):
        out = real_apply_frame(runtime, stage_local, now, sample, time_code)
        evaluated[now] = out[1].status
        return out

    monkeypatch.setattr(LiveBindingRuntime, "apply_frame", apply_frame)
    return evaluated


def assert_the_take_holds_what_was_shown(recorded, shown: dict, scene: Path) -> None:
    """The take holds what each rendered frame showed, tick for tick."""
    codes = np.round(recorded.times * 30).astype(int)  # the stage's rate; ticks from 0
    assert np.array_equal(codes, np.arange(len(codes)))
    stage = Usd.Stage.Open(str(scene))
    joints = CharacterRig(stage.GetPrimAtPath("/World/Hero")).joints
    root = joints.index(next(j for j in joints if "/" not in j))
    rendered = [t for t in sorted(shown) if t < len(codes)]
    assert len(rendered) >= 10
    for t in rendered:
        q = quat_from_matrix(np.swapaxes(shown[t][:, :3, :3], 1, 2))
        assert degrees_between(q, recorded.rotations[int(t)]).max() < 1e-3, t
        np.testing.assert_allclose(
            shown[t][root, 3, :3], recorded.root_positions[int(t)], atol=1e-3
        )


def assert_no_pop_through_the_gap(recorded, status: list[str]) -> None:
    """No pop through the gap: held, blending back, then the reconnect's fade from what was
    shown (before: the take froze, then turned 59 deg and moved 108 cm in one tick)."""
    ticks = len(status)
    gap = [k for k in range(1, ticks) if status[k - 1] != "connected"]
    gap = [k for k in gap if k > min(k for k in range(ticks) if status[k] == "stale")]
    assert status[gap[-1]] == "connected" and {"stale", "lost"} <= {status[k] for k in gap}
    # Tick by tick: connected -> stale -> lost -> connected (the pause, then the new sender).
    steps = [s for k, s in enumerate(status) if k == 0 or s != status[k - 1]]
    assert any(steps[k : k + 4] == ["connected", "stale", "lost", "connected"]
               for k in range(len(steps))), steps  # fmt: skip
    turn = degrees_between(recorded.rotations[gap], recorded.rotations[np.subtract(gap, 1)])
    move = np.linalg.norm(
        recorded.root_positions[gap] - recorded.root_positions[np.subtract(gap, 1)], axis=1
    )
    row = int(np.argmax(turn.max(axis=1)))
    worst, joint = gap[row], int(np.argmax(turn[row]))
    assert turn.max() < 25.0 and move.max() < 25.0, (
        f"tick {worst}: {turn.max():.1f} deg at joint {joint}, statuses around it "
        f"{status[max(worst - 3, 0) : worst + 3]}, gap ticks {gap[0]}-{gap[-1]}",
        turn.max(axis=1),
        move,
    )


@pytest.mark.slow
def test_sender_stopping_goes_stale_then_lost_frames_keep_coming_and_it_reconnects(
    tmp_path, monkeypatch
):
    """A sender stops (stale, then lost: frames keep coming while the character blends back),
    then a new sender process starts (its /VMC/Ext/T from 0, poses of its own) while another
    sends four absurd /VMC/Ext/T: the binding reconnects, and the take holds what the screen
    showed at every rendered tick (one evaluation for both: the blends included, no pop), then
    the new sender's frames. Every phase waits on what the run renders, never on the clock."""
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    scene = scene_with(tmp_path, **{"uniform float rigspace:live:suit:timeoutSeconds": "0.5"})
    out, take = tmp_path / "out", tmp_path / "take.usda"
    second_clip = cmu_clip(TURN)
    script = StopThenRestart(url, port)
    evaluated = record_evaluations(monkeypatch)
    FrameDriver(monkeypatch, script)
    try:
        code = main(
            ["live", str(scene), "--out", str(out), "--seconds", "120", "--source", f"suit={url}",
             "--record", str(take), "--resolution", "64x36", "--max-level", "32"]
        )  # fmt: skip
    finally:
        for sender in script.senders:
            sender.close()
    assert code == 0 and script.phase == "restarted" and script.settled >= 3
    # Frames kept coming while nothing arrived (on a loaded machine a frame can take longer
    # than the stale stage, so the frames may show lost alone; the ticks below show each).
    paused = [e["status"] for e in script.phases["paused"]]
    sequence = [s for k, s in enumerate(paused) if k == 0 or s != paused[k - 1]]
    assert sequence[-1] == "lost" and "connected" not in sequence[1:], paused
    assert script.phases["restarted"][-1]["status"] == "connected"
    frames = json.loads((out / "report.json").read_text())["frames"]
    assert frames[-1]["live"][0]["samples"] > frames[0]["live"][0]["samples"]
    recorded = read_take(take)
    assert_the_take_holds_what_was_shown(recorded, script.shown, scene)
    status = [evaluated[script.ticks.due(k)] for k in range(len(recorded.times))]
    assert_no_pop_through_the_gap(recorded, status)
    # After the restart, the take follows the new sender (before: the old stream replayed).
    expected = expected_locals(second_clip, scene, url, 0.0)
    errors = angles(recorded.rotations[-3:, None], expected[None]).max(axis=2)
    assert errors.min(axis=1).max() < 1e-3


def test_a_port_in_use_is_one_error_naming_the_binding_and_no_output(tmp_path, capsys):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        code = main(["live", str(LIVE_SCENE), "--out", str(tmp_path / "out"), "--source",
                     f"suit=vmc://127.0.0.1:{port}", "--seconds", "1"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2
    assert "Live binding 'suit' of /World/Hero" in err and f"UDP port {port}" in err
    assert "--source suit=URL" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_an_unknown_source_name_is_refused(tmp_path, capsys):
    code = main(["live", str(LIVE_SCENE), "--out", str(tmp_path / "o"), "--source",
                 "body=vmc://127.0.0.1:1"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "--source body" in err and "they have: suit" in err


def probe_on(port: int) -> tuple[threading.Thread, list[int]]:
    """`live probe` on `port`, listening until 30 frames arrived (120 s: only a bound), once
    its socket is bound or it ended: its thread and (once ended) exit code."""
    url = f"vmc://127.0.0.1:{port}"
    result: list[int] = []
    probe = threading.Thread(
        target=lambda: result.append(
            main(["live", "probe", url, "--frames", "30", "--seconds", "120"])
        )
    )
    probe.start()
    # The probe's first run on a fresh clone imports and compiles for a while: wait for its
    # socket (or its end), bounded only by its own 120 s.
    assert wait_for(lambda: udp_port_bound(port) or not probe.is_alive(), timeout=120.0)
    return probe, result


def started_probe(capsys) -> tuple[str, threading.Thread, list[int]]:
    """A listening probe_on a free port: its URL, thread and result. A port another program
    took between the pick and the probe's bind (seen once on a loaded machine) is picked
    again."""
    for _ in range(5):
        port = free_port()
        probe, result = probe_on(port)
        if probe.is_alive() or "in use by another program" not in capsys.readouterr().err:
            break
    assert probe.is_alive(), f"live probe ended before it listened: {result}"
    return f"vmc://127.0.0.1:{port}", probe, result


def test_send_and_probe_subcommands(capsys):
    url, probe, result = started_probe(capsys)
    assert main(["live", "send", url, "--bvh", str(CMU_CLIP), "--seconds", "0.8"]) == 0
    probe.join()
    lines = capsys.readouterr().out.strip().splitlines()
    assert result == [0] and any(line.startswith("sent ") for line in lines)
    status = json.loads([line for line in lines if line.startswith("{")][-1])
    assert status["frames"] >= 30 and status["seconds"] < 120  # stopped by the frames
    assert status["bones_seen"] == 23 and status["malformed"] == 0
    assert main(["live", "send", "udp://127.0.0.1:1", "--bvh", str(CMU_CLIP)]) == 2
    assert "rigspace live send: error" in capsys.readouterr().err


def test_calibrate_stores_the_sources_rest_pose(tmp_path, clip, capsys):
    scene = scene_with(tmp_path)
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    sender = Sender(url)
    try:
        streaming(url)  # the performer holds the rest pose before calibrate listens
        code = main(["live", "calibrate", str(scene), "--binding", "suit", "--source", url,
                     "--seconds", "0.5"])  # fmt: skip
    finally:
        sender.close()
    assert code == 0 and "restPose of 22 bones" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(scene))
    binding = schema.read_live_bindings(stage.GetPrimAtPath("/World/Hero"))[0]
    assert len(binding.rest_pose) == len(binding.source_bones) == len(binding.target_joints) == 22
    assert (
        dict(zip(binding.source_bones, binding.target_joints, strict=True))["LeftHand"] == "hand_l"
    )
    rest = np.array(binding.rest_pose)
    np.testing.assert_allclose(np.linalg.norm(rest, axis=1), 1.0, atol=1e-6)
    # The stored rest is one of the clip's poses (the one streaming when it was taken).
    hips = list(clip.bones).index("Hips")
    assert angles(rest[0], clip.rotations[:, hips]).min() < 1e-3
    # Nothing arrives: one clear error, the scene untouched.
    before = scene.read_text()
    code = main(["live", "calibrate", str(scene), "--binding", "suit", "--source",
                 f"vmc://127.0.0.1:{free_port()}", "--seconds", "0.2"])  # fmt: skip
    assert code == 2 and "received nothing" in capsys.readouterr().err
    assert scene.read_text() == before


@pytest.mark.slow
def test_a_take_holds_every_tick_even_when_the_recorder_stalls(tmp_path, clip, monkeypatch):
    """A recorder that falls behind (here: stalled on one tick until the sender has sent 30 more
    frames, as a compile holding the GIL stalls it) records the ticks it missed with the poses
    the binding held at their due times."""
    from rigspace.runtime.live.engine import LiveInput

    real = LiveInput.merged
    stall: dict = {}

    def stalling(self, character, time_code, now=None, take=False):
        out = real(self, character, time_code, now, take)
        runtime = self.characters[character.path].runtimes[0]
        settled = out[1][0][1].status == "connected" and not runtime.fading
        if take and settled and "tick" not in stall:  # the connect's fade is over: stall
            stall["tick"] = int(time_code)
            samples = runtime.buffer.samples
            assert wait_for(lambda: runtime.buffer.samples >= samples + 30 * 23, timeout=60)
            stall["until"] = time.monotonic()
        return out

    def on_frame(engine, frame) -> bool:
        stall["ticks"] = engine.live.ticks
        after = [f for f in rendered if "until" in stall and f > stall["until"]]
        rendered.append(time.monotonic())
        return len(after) >= 3

    rendered: list[float] = []
    monkeypatch.setattr(LiveInput, "merged", stalling)
    FrameDriver(monkeypatch, on_frame)
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    take = tmp_path / "take.usda"
    sender = Sender(url)
    try:
        streaming(url)
        code = main(
            ["live", str(LIVE_SCENE), "--out", str(tmp_path / "out"), "--seconds", "120",
             "--source", f"suit={url}", "--record", str(take), "--resolution", "64x36",
             "--max-level", "16"]
        )  # fmt: skip
    finally:
        sender.close()
    assert code == 0 and "until" in stall
    recorded = read_take(take)
    codes = np.round(recorded.times * 30).astype(int)
    assert np.array_equal(codes, np.arange(len(codes)))  # every tick, from the first on
    # The ticks due while the recorder stalled are the clip's frames too, moving forward with
    # it (not one held pose): 30 frames at 120 Hz arrived meanwhile, about 7 ticks' worth.
    ticks = stall["ticks"]
    late = [k for k in range(stall["tick"] + 1, len(codes)) if ticks.due(k) < stall["until"]]
    assert len(late) >= 5, late
    expected = expected_locals(clip, LIVE_SCENE, url, 0.0)
    errors = angles(recorded.rotations[late][:, None], expected[None]).max(axis=2)
    assert np.all(errors.min(axis=1) < 1e-3)
    frames = errors.argmin(axis=1)
    steps = np.diff(frames) % len(clip.rotations)  # the sender loops the clip
    assert np.all(steps < len(clip.rotations) // 2) and len(set(frames)) >= 4

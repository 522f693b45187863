"""`rigspace live` end to end over real UDP: the CMU clip sent over VMC, rendered, recorded."""

from __future__ import annotations

import json
import socket
import threading
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from rigspace.runtime.live.binding import open_binding
from rigspace.runtime.live.buffer import LivePose
from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.record import read_take
from rigspace.runtime.live.send import humanoid_clip, send_vmc
from rigspace.sdk import schema
from rigspace.sdk.cli import main
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.rotations import quat_from_matrix
from tests.conftest import REPO, free_port
from tests.runtime.live.conftest import CMU_CLIP, udp_port_bound, wait_for

LIVE_SCENE = REPO / "samples" / "scenes" / "live.usda"


@pytest.fixture(scope="module")
def clip():
    skeleton, motion, frame_time = read_bvh(CMU_CLIP)
    rotations, roots = skeleton.pose(motion)
    return humanoid_clip(skeleton, rotations, roots, frame_time)


class Sender:
    """The clip over VMC on a thread, in real time, looping, until stopped."""

    def __init__(self, clip, url: str) -> None:
        self.stop = threading.Event()
        self.thread = threading.Thread(
            target=send_vmc, args=(url, clip, 1.0, True, self.stop), daemon=True
        )
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join()


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


@pytest.mark.slow
def test_live_records_the_clip_sent_over_vmc_and_render_replays_the_take(tmp_path, clip, capsys):
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    out = tmp_path / "out"
    take = tmp_path / "take.usda"
    sender = Sender(clip, url)
    try:
        code = main(
            ["live", str(LIVE_SCENE), "--out", str(out), "--seconds", "2", "--source",
             f"suit={url}", "--record", str(take), "--resolution", "96x54", "--max-level", "32",
             "--video", str(out / "live.mp4")]
        )  # fmt: skip
    finally:
        sender.close()
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert report["ticks"] == 60 and report["rendered"] + report["dropped"] == 60
    assert report["rendered"] >= 3 and len(list(out.glob("frame_*.png"))) == report["rendered"]
    (binding,) = report["bindings"]
    assert binding["binding"] == "suit" and binding["samples"] > 1000
    assert binding["malformed"] == 0
    latency = report["latency_ms"]["suit"]
    assert 0 < latency["p50"] <= latency["p99"] < 2000
    last = report["frames"][-1]
    assert last["live"][0]["status"] == "connected" and last["live"][0]["url"] == url
    assert last["characters"][0]["live"] == [
        {"binding": "suit", "status": "connected", "weight": 1.0}
    ]
    assert (out / "live.mp4").stat().st_size > 1000
    # Every recorded pose is one of the clip's frames, converted, within 1e-3 rad per joint.
    recorded = read_take(take)
    assert len(recorded.times) >= 55  # the stage's rate, whatever was dropped
    expected = expected_locals(clip, LIVE_SCENE, url, 0.0)
    errors = angles(recorded.rotations[:, None], expected[None]).max(axis=2)  # (T, F)
    best = errors.min(axis=1)
    matched = np.flatnonzero(best < 1e-3)
    assert len(matched) >= len(best) - 2, best  # the first tick may precede the first packet
    frames = errors.argmin(axis=1)[matched]
    assert np.all(np.diff(frames) >= 0) and frames[-1] - frames[0] > 150  # forward, ~2 s of 120 Hz
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


@pytest.mark.slow
def test_sender_stopping_goes_stale_then_lost_frames_keep_coming_and_it_reconnects(tmp_path, clip):
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    scene = scene_with(tmp_path, **{"uniform float rigspace:live:suit:timeoutSeconds": "0.15"})
    out = tmp_path / "out"
    phases: list[str] = []

    def perform() -> None:
        first = Sender(clip, url)
        threading.Event().wait(1.6)  # the engine loads, then ~0.5 s of stream
        first.close()
        phases.append("stopped")
        threading.Event().wait(1.2)  # stale after 0.15 s, lost after 0.6 s
        second = Sender(clip, url)
        phases.append("restarted")
        threading.Event().wait(1.4)
        second.close()

    performer = threading.Thread(target=perform, daemon=True)
    performer.start()
    code = main(
        ["live", str(scene), "--out", str(out), "--seconds", "3.2", "--source", f"suit={url}",
         "--resolution", "64x36", "--max-level", "32", "--prim-samples", "1"]
    )  # fmt: skip
    performer.join()
    assert code == 0 and phases == ["stopped", "restarted"]
    frames = json.loads((out / "report.json").read_text())["frames"]
    statuses = [f["live"][0]["status"] for f in frames]
    # Collapse repeats: the binding went connected -> stale -> lost -> connected.
    sequence = [s for k, s in enumerate(statuses) if k == 0 or s != statuses[k - 1]]
    assert ["connected", "stale", "lost", "connected"] == [s for s in sequence if s != "waiting"][
        :4
    ], statuses
    lost = [f for f in frames if f["live"][0]["status"] == "lost"]
    assert len(lost) >= 2  # frames kept coming while nothing arrived
    assert min(f["characters"][0]["live"][0]["weight"] for f in lost) < 1.0  # blending back
    assert frames[-1]["live"][0]["samples"] > frames[0]["live"][0]["samples"]


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


def test_send_and_probe_subcommands(tmp_path, capsys):
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    result: list[int] = []
    probe = threading.Thread(
        target=lambda: result.append(main(["live", "probe", url, "--seconds", "1.2"]))
    )
    probe.start()
    assert wait_for(lambda: udp_port_bound(port))
    assert main(["live", "send", url, "--bvh", str(CMU_CLIP), "--seconds", "0.8"]) == 0
    probe.join()
    lines = capsys.readouterr().out.strip().splitlines()
    assert result == [0] and any(line.startswith("sent ") for line in lines)
    status = json.loads([line for line in lines if line.startswith("{")][-1])
    assert status["bones_seen"] == 23 and status["malformed"] == 0
    assert main(["live", "send", "udp://127.0.0.1:1", "--bvh", str(CMU_CLIP)]) == 2
    assert "rigspace live send: error" in capsys.readouterr().err


def test_calibrate_stores_the_sources_rest_pose(tmp_path, clip, capsys):
    scene = scene_with(tmp_path)
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    sender = Sender(clip, url)
    try:
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
    """A recorder that falls behind (here: stalled 0.5 s on one tick, as a compile holding the
    GIL does) records the ticks it missed with the poses the binding held then."""
    from rigspace.runtime.live.engine import LiveInput

    real = LiveInput.merged
    stalled: list[float] = []

    def stalling(self, character, time_code, now=None, past=False):
        if threading.current_thread().name == "rigspace-live-take" and time_code >= 5:
            if not stalled:
                stalled.append(time_code)
                threading.Event().wait(0.5)  # 15 ticks at 30 fps
        return real(self, character, time_code, now, past)

    monkeypatch.setattr(LiveInput, "merged", stalling)
    port = free_port()
    url = f"vmc://127.0.0.1:{port}"
    take = tmp_path / "take.usda"
    sender = Sender(clip, url)
    try:
        code = main(
            ["live", str(LIVE_SCENE), "--out", str(tmp_path / "out"), "--seconds", "1.5",
             "--source", f"suit={url}", "--record", str(take), "--resolution", "64x36",
             "--max-level", "16"]
        )  # fmt: skip
    finally:
        sender.close()
    assert code == 0 and stalled
    recorded = read_take(take)
    assert len(recorded.times) == 45  # every tick of 1.5 s at 30 fps
    assert np.allclose(np.diff(recorded.times), 1 / 30)
    # The ticks recorded late are the clip's frames too, moving forward (not one held pose).
    expected = expected_locals(clip, LIVE_SCENE, url, 0.0)
    errors = angles(recorded.rotations[:, None], expected[None]).max(axis=2)
    late = slice(6, 20)
    assert np.all(errors[late].min(axis=1) < 1e-3)
    assert len(set(errors[late].argmin(axis=1))) > 5

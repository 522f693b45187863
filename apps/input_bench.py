"""Measure live input: `python -m rigspace.apps.input_bench [--json FILE]` (docs/live.md)."""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from rigspace.runtime.live.buffer import BufferSettings, LiveBuffer
from rigspace.runtime.live.decoders.bvh import BvhStreamDecoder, read_bvh
from rigspace.runtime.live.decoders.vmc import HUMAN_BODY_BONES, VmcDecoder, encode_frame
from rigspace.runtime.live.decoders.ximu3 import Ximu3Decoder
from rigspace.runtime.live.source_frame import SourceFrame, quat_angle, quat_slerp
from rigspace.runtime.live.sources import open_source
from rigspace.sdk.files import write_atomic

REPO = Path(__file__).resolve().parents[1]
CLIP = REPO / "samples" / "motion" / "cmu_131_01.bvh"
CHARACTER = REPO / "samples" / "character" / "sample_character.usda"


def _rate(feed, chunks: list[bytes], seconds: float) -> tuple[float, int]:
    """Passes over `chunks` per CPU second of this (single-threaded) process, for about
    `seconds` of CPU time: CPU time, not wall time, so other load on a shared machine does not
    count against the decoder."""
    passes, start = 0, time.process_time()
    while time.process_time() - start < seconds:
        for chunk in chunks:
            feed(chunk, 0.0)
        passes += 1
    return passes / (time.process_time() - start), passes


def decode_rates(seconds: float) -> dict:
    rng = np.random.default_rng(0)
    q = rng.normal(size=(len(HUMAN_BODY_BONES), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    frames = [encode_frame(HUMAN_BODY_BONES, q, np.zeros(3), None, k / 60) for k in range(60)]
    vmc = VmcDecoder()
    per_second, _ = _rate(vmc.feed, [d for f in frames for d in f], seconds)
    bone_messages = per_second * 60 * (len(HUMAN_BODY_BONES) + 1)
    skeleton, motion, _ = read_bvh(CLIP)
    lines = [(" ".join(f"{v:.4f}" for v in row) + "\n").encode() for row in motion[:120]]
    bvh = BvhStreamDecoder(skeleton)
    bvh_rate, _ = _rate(bvh.feed, lines, seconds)
    ximu = Ximu3Decoder(("pelvis",))
    q_lines = [
        f"Q,{1000 * k},0.850093,-0.040743,-0.524145,-0.034592\r\n".encode() for k in range(200)
    ]
    ximu_rate, _ = _rate(ximu.feed, q_lines, seconds)
    return {
        "vmc_bone_messages_per_s": round(bone_messages),
        "vmc_frames_per_s": round(per_second * 60),
        "bvh_frames_per_s": round(bvh_rate * 120),
        "bvh_joint_samples_per_s": round(bvh_rate * 120 * len(skeleton.names)),
        "ximu3_messages_per_s": round(ximu_rate * 200),
    }


def receive_to_pose(frames: int) -> dict:
    """VMC over real UDP on 127.0.0.1 at 120 Hz: read-to-available latency and pose() cost."""
    source = open_source("vmc://127.0.0.1:0", "bench")
    buffer = LiveBuffer(source.bones)
    source.start(buffer)
    try:
        address = source.address
        sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rng = np.random.default_rng(1)
        q = rng.normal(size=(len(HUMAN_BODY_BONES), 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        for k in range(frames):
            for dgram in encode_frame(HUMAN_BODY_BONES, q, np.zeros(3), None, k / 120):
                sender.sendto(dgram, address)
            time.sleep(1 / 120)
        time.sleep(0.1)
        pose_times = []
        for mode in ("latest", "delayed"):
            b = buffer if mode == "latest" else LiveBuffer(source.bones, BufferSettings("delayed"))
            if mode == "delayed":
                for k in range(100):
                    b.push(SourceFrame(0, k / 120, np.arange(56), np.tile(q[0], (56, 1))), k / 120)
            t = []
            for _ in range(2000):
                start = time.perf_counter()
                b.pose(0.8)
                t.append(time.perf_counter() - start)
            pose_times.append(np.array(t))
        c = source.counters()
    finally:
        source.stop()
    return {
        "frames_sent": frames,
        "samples_received": c.samples,
        "receive_to_pose_p50_ms": round(c.latency_p50_ms or 0, 3),
        "receive_to_pose_p99_ms": round(c.latency_p99_ms or 0, 3),
        "pose_latest_p50_ms": round(float(np.percentile(pose_times[0], 50)) * 1e3, 4),
        "pose_delayed_p50_ms": round(float(np.percentile(pose_times[1], 50)) * 1e3, 4),
        "pose_delayed_p99_ms": round(float(np.percentile(pose_times[1], 99)) * 1e3, 4),
    }


def retarget_cost(repeats: int) -> dict:
    """Retargeting a CMU pose onto the sample character's 22 joints, per frame."""
    from pxr import Usd, UsdSkel

    from rigspace.runtime.live.buffer import LivePose
    from rigspace.runtime.live.retarget import PRESETS, Retargeter, target_skeleton

    skeleton, motion, _ = read_bvh(CLIP)
    rotations, roots = skeleton.pose(motion[:repeats])
    stage = Usd.Stage.Open(str(CHARACTER))
    joints, rest = target_skeleton(stage.GetPrimAtPath("/Character/Skel"))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    stage_local = np.array(
        UsdSkel.MakeTransforms(
            anim.GetTranslationsAttr().Get(0),
            anim.GetRotationsAttr().Get(0),
            anim.GetScalesAttr().Get(0),
        )
    )
    p = PRESETS["cmu"]
    r = Retargeter(
        skeleton.names,
        skeleton.parents,
        "local",
        joints,
        rest,
        p.bone_map,
        p.basis,
        p.meters_per_unit / 0.01,
    )
    valid = np.ones(len(skeleton.names), bool)
    t = []
    for k in range(repeats):
        pose = LivePose(rotations[k], valid, roots[k], "connected", 1.0, 0.0)
        start = time.perf_counter()
        r.apply(stage_local, pose)
        t.append(time.perf_counter() - start)
    return {
        "retarget_p50_ms": round(float(np.percentile(t, 50)) * 1e3, 3),
        "retarget_p99_ms": round(float(np.percentile(t, 99)) * 1e3, 3),
    }


def jitter_error(jitter_ms: float = 10.0, latency_ms: float = 20.0, delay_ms: float = 20.0) -> dict:
    """The CMU clip at 120 Hz, each packet delayed by latency +- jitter (uniform), read at 60 Hz.

    Error: mean and p99 joint angle (degrees) against the clean clip (slerped between its
    frames) shown at the constant delay that fits each mode best (searched in 1 ms steps), so
    neither mode is charged for its latency, only for the jitter that shows.
    """
    skeleton, motion, frame_time = read_bvh(CLIP)
    rotations, _ = skeleton.pose(motion)
    rng = np.random.default_rng(2)
    ts = np.arange(len(rotations)) * frame_time
    arrival = ts + (latency_ms + rng.uniform(-jitter_ms, jitter_ms, len(ts))) * 1e-3
    order = np.argsort(arrival, kind="stable")
    idx = np.arange(len(skeleton.names))

    def truth(t: np.ndarray) -> np.ndarray:
        k = np.clip(t / frame_time, 0, len(rotations) - 1.001)
        i = k.astype(int)
        return quat_slerp(rotations[i], rotations[i + 1], np.repeat((k - i)[:, None], 31, 1))

    nows = np.arange(0.5, ts[-1] - 0.1, 1 / 60)
    results = {}
    for mode in ("latest", "delayed"):
        b = LiveBuffer(skeleton.names, BufferSettings(mode, delay_ms * 1e-3))
        collected = []
        pushed = 0
        for now in nows:
            while pushed < len(order) and arrival[order[pushed]] <= now:
                k = order[pushed]
                b.push(SourceFrame(0, ts[k], idx, rotations[k]), arrival[k])
                pushed += 1
            collected.append(b.pose(now).rotations)
        poses = np.array(collected)
        best = None
        for display in np.arange(0.0, 0.08, 0.001):
            e = np.degrees(quat_angle(poses, truth(nows - display)))
            if best is None or e.mean() < best[1].mean():
                best = (display, e)
        assert best is not None
        results[f"{mode}_error_mean_deg"] = round(float(best[1].mean()), 4)
        results[f"{mode}_error_p99_deg"] = round(float(np.percentile(best[1], 99)), 4)
        results[f"{mode}_display_delay_ms"] = round(float(best[0]) * 1e3, 1)
        results[f"{mode}_dropped_late"] = b.out_of_order
    return results


LIVE_SCENE = REPO / "samples" / "scenes" / "live.usda"


class _Performer:
    """`rigspace live send` of the CMU clip to a free local port, looping, in its own process
    (as in real use: the sender's work must not count against the frame's thread)."""

    def __init__(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            self.url = f"vmc://127.0.0.1:{s.getsockname()[1]}"
        self.process: subprocess.Popen | None = None

    def __enter__(self) -> _Performer:
        command = [sys.executable, "-m", "rigspace.apps.live_send", self.url, "--bvh",
                   str(CLIP), "--loop"]  # fmt: skip
        self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL)
        return self

    def __exit__(self, *exc: object) -> None:
        assert self.process is not None
        self.process.terminate()
        self.process.wait()


def frame_cost(frames: int = 40, size: int = 256) -> dict:
    """The same time codes of live.usda rendered from the stage animation and with its suit
    binding fed over real UDP (both evaluate the network: both poses change every frame),
    alternating; and the live work alone per frame (pose, retarget, report)."""
    from rigspace.runtime.engine import Engine, EngineSettings

    codes = 100.0 + np.arange(frames)
    shape = {"width": size, "height": size}
    with _Performer() as performer:
        with (
            Engine(LIVE_SCENE, EngineSettings(live=False, **shape)) as stage,
            Engine(LIVE_SCENE, EngineSettings(sources={"suit": performer.url}, **shape)) as live,
        ):
            live.open_live()
            end = time.monotonic() + 10.0  # the sender starts (an interpreter, the clip)
            while live.live.report()[0]["samples"] == 0 and time.monotonic() < end:
                time.sleep(0.05)
            seconds: dict[str, list] = {"stage": [], "live": [], "stage_rig": [], "live_rig": []}
            work, own = [], []
            hero = live.characters[0]
            runtimes = live.live.characters[hero.path].runtimes
            for t in codes:
                for name, engine in (("stage", stage), ("live", live)):
                    report = engine.render(float(t)).report
                    seconds[name].append(report.seconds["total"])
                    seconds[f"{name}_rig"].append(report.seconds["rig"])
                start = time.perf_counter()
                live.live.local(hero, float(t), {})
                live.live.report()
                work.append(time.perf_counter() - start)
                # What the binding adds to a frame that reads the stage anyway: its pose,
                # retarget and counters (the stage read is the stage path's too).
                local = np.asarray(hero.rig.local_transforms(float(t)), dtype=np.float64)
                start = time.perf_counter()
                for runtime in runtimes:
                    local, _ = runtime.apply(local, None, hero.rig.local_transforms, float(t))
                live.live.report()
                own.append(time.perf_counter() - start)
            status = live.live.report()[0]["status"]

    def ms(values, q=50):
        return round(float(np.percentile(values, q)) * 1e3, 3)

    return {
        "frames": frames,
        "resolution": f"{size}x{size}",
        "binding_status": status,
        "stage_frame_ms_p50": ms(seconds["stage"]),
        "live_frame_ms_p50": ms(seconds["live"]),
        "stage_rig_ms_p50": ms(seconds["stage_rig"]),
        "live_rig_ms_p50": ms(seconds["live_rig"]),
        "live_work_ms_p50": ms(work),
        "live_work_ms_p99": ms(work, 99),
        "binding_own_ms_p50": ms(own),
        "binding_own_ms_p99": ms(own, 99),
    }


def end_to_end(seconds: float = 5.0, size: int = 256) -> dict:
    """`rigspace live` on live.usda for `seconds` at size x size with the CMU clip arriving over
    VMC: frames rendered and dropped, and sample received to frame written (PNG), p50/p99."""
    import contextlib
    import io
    import tempfile

    from rigspace.sdk.cli import main as rigspace

    with _Performer() as performer, tempfile.TemporaryDirectory() as out:
        argv = ["live", str(LIVE_SCENE), "--out", out, "--seconds", str(seconds),
                "--source", f"suit={performer.url}", "--resolution", f"{size}x{size}"]  # fmt: skip
        with contextlib.redirect_stdout(io.StringIO()):
            code = rigspace(argv)
        if code != 0:
            raise RuntimeError(f"rigspace live exited {code}")
        report = json.loads((Path(out) / "report.json").read_text())
    return {
        "resolution": f"{size}x{size}",
        "seconds": report["seconds"],
        "ticks": report["ticks"],
        "rendered": report["rendered"],
        "dropped": report["dropped"],
        "frame_ms": report["frame_ms"],
        "received_to_written_ms": report["latency_ms"]["suit"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.input_bench", description=__doc__
    )
    parser.add_argument("--seconds", type=float, default=2.0, help="per decode-rate measurement")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument(
        "--frames",
        type=int,
        default=40,
        help="frames for the engine's frame cost and seconds of `rigspace live` for the "
        "end-to-end latency (0: skip both)",
    )
    args = parser.parse_args(argv)
    results = {
        "decode": decode_rates(args.seconds),
        "udp": receive_to_pose(240),
        "retarget": retarget_cost(300),
        "jitter": jitter_error(),
    }
    if args.frames > 0:
        results["frame"] = frame_cost(args.frames)
        results["end_to_end"] = end_to_end(max(2.0, args.frames / 8))
    text = json.dumps(results, indent=2)
    print(text)
    if args.json:
        write_atomic(args.json, text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

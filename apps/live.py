"""`rigspace live`: render a stage in real time with its live bindings; send, probe, calibrate."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

from rigspace.sdk.cli import CommandSpec
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.files import write_atomic
from rigspace.sdk.predictors import add_predictor_argument

DESCRIPTION = """\
rigspace live SCENE --out DIR [--seconds S] [--record TAKE.usda] [--source NAME=URL ...] [--video FILE]
    Render SCENE in real time at its frame rate with its enabled live bindings (RigspaceLiveBindingAPI)
    driving their characters: a PNG per rendered frame, report.json (per frame: each binding's status
    and counters; overall: frames rendered and dropped, end-to-end latency from sample received to
    frame written while the binding is connected, p50/p99). A frame that is not ready in time is dropped, never queued (the video
    repeats the last frame there, so it plays in real time). --record writes the received, retargeted
    poses at the stage's rate as a UsdSkel SkelAnimation (TAKE.usda) and a stage that plays it
    (TAKE.shot.usda: `rigspace render TAKE.shot.usda --out DIR` re-renders the take). Ctrl-C stops
    early and still writes everything.
rigspace live send URL --bvh FILE [--speed 1] [--loop] [--seconds S]
    Stream a BVH clip to a VMC receiver (vmc://HOST:PORT) or serve it as an Axis Neuron BVH stream
    (bvh+tcp://HOST:PORT).
rigspace live probe URL [--seconds S] [--frames N]
    Listen on a live-source URL and print one JSON status line a second (bones, rate, status),
    for S seconds or until N frames have arrived.
rigspace live calibrate SCENE --binding NAME [--seconds S] [--source URL]
    Hold the performer in the character's rest pose: the source's pose after S seconds is stored
    in the binding's restPose (with its sourceBones and targetJoints) in SCENE's root layer.
"""
SUBCOMMANDS = ("send", "probe", "calibrate")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "argv",
        nargs=argparse.REMAINDER,
        metavar="SCENE ... | send ... | probe ... | calibrate ...",
        help="see above; `rigspace live SCENE --help` for every option",
    )


def run(args: argparse.Namespace) -> int:
    argv = list(args.argv)
    if not argv:
        raise RigspaceError(
            "rigspace live needs a scene or a subcommand.",
            "run `rigspace live SCENE --out DIR`, or `rigspace live send|probe|calibrate ...`.",
        )
    if argv[0] == "send":
        from rigspace.apps.live_send import main as send_main

        return send_main(argv[1:], prog="rigspace live send")
    if argv[0] == "probe":
        from rigspace.apps.live_probe import main as probe_main

        return probe_main(argv[1:], prog="rigspace live probe")
    if argv[0] == "calibrate":
        return calibrate(_calibrate_parser().parse_args(argv[1:]))
    return live(_live_parser().parse_args(argv))


def _live_parser() -> argparse.ArgumentParser:
    from rigspace.runtime.options import (
        add_regions_argument,
        add_source_argument,
        add_view_arguments,
        positive,
        positive_seconds,
    )

    parser = argparse.ArgumentParser(
        prog="rigspace live",
        description="Render a stage in real time with its live bindings driving its characters.",
    )
    parser.add_argument("scene", help="the .usd* stage (its enabled live bindings drive it)")
    parser.add_argument("--out", required=True, help="folder for frames and report.json")
    parser.add_argument("--seconds", type=positive_seconds, default=10.0, help="how long to run")
    parser.add_argument("--record", metavar="TAKE.usda", help="record the live poses as a take")
    add_source_argument(parser, "give binding NAME this source URL (and enable it); repeatable")
    parser.add_argument("--video", help="also write this mp4 (H.264), in real time")
    add_view_arguments(parser)
    parser.add_argument("--start", type=float, help="first time code (default: the stage's start)")
    add_predictor_argument(parser)
    parser.add_argument("--prim-samples", type=positive, default=1, metavar="N",
                        help="N x N samples per pixel for the prims (default 1: real time first)")  # fmt: skip
    parser.add_argument("--max-level", type=positive, metavar="R", help="cap the level of detail")
    add_regions_argument(parser)
    return parser


def _calibrate_parser() -> argparse.ArgumentParser:
    from rigspace.runtime.options import positive_seconds

    parser = argparse.ArgumentParser(
        prog="rigspace live calibrate",
        description="Store a live binding's rest pose: the performer holds the character's rest "
        "pose (a T-pose for a T-posed character) while the source streams.",
    )
    parser.add_argument(
        "scene", help="the stage whose binding to calibrate (its root layer is saved)"
    )
    parser.add_argument("--binding", required=True, help="the RigspaceLiveBindingAPI instance name")
    parser.add_argument("--seconds", type=positive_seconds, default=3.0,
                        help="how long to wait before taking the pose (default 3)")  # fmt: skip
    parser.add_argument("--source", help="listen on this URL instead of the binding's")
    return parser


FIRST_FRAME_NOTE = 2.0
"""Seconds a warm-up frame may take before `live` says why it was slow."""


class _TakeThread(threading.Thread):
    """Records every live character's merged pose at each stage tick, whatever the renderer is
    doing: the take keeps the stage's rate even when frames are dropped. Each tick is what the
    screen shows at it (`LiveInput.merged`: one evaluation of the tick's pose, transitions
    included, for the frame and the take). A tick this thread reaches late (a stall: the GIL
    held by a compile, a loaded machine) is recorded all the same, with the pose its bindings
    held at the tick's due time (LiveBuffer.pose_at): every tick of the run is in the take,
    stamped with its time code."""

    def __init__(self, engine, start_code: float, fps: float, t0: float, ticks: int) -> None:
        super().__init__(name="rigspace-live-take", daemon=True)
        from rigspace.runtime.live.record import TakeRecorder

        self.engine, self.start_code, self.fps, self.t0, self.ticks = (
            engine, start_code, fps, t0, ticks,
        )  # fmt: skip
        self.takes = {
            path: TakeRecorder(
                live.character.rig.joints,
                live.character.rig.blend_shapes,
                [c.name for c in live.character.rig.controls],
            )
            for path, live in engine.live.characters.items()
        }
        self.halt = threading.Event()
        self.end = math.inf
        """Local time the run ended (finish): ticks due after it are not recorded."""
        self.error: BaseException | None = None

    def finish(self, end: float) -> None:
        """Record every tick due up to local time `end` (those missed included), then stop."""
        self.end = end
        self.halt.set()

    def run(self) -> None:
        try:
            for k in range(self.ticks):
                due = self.t0 + k / self.fps
                wait = due - time.monotonic()
                if wait > 0:
                    self.halt.wait(wait)  # woken early by finish(): catch up, then stop
                if due > self.end:
                    return
                code = self.start_code + k
                for path, live in self.engine.live.characters.items():
                    local, poses = self.engine.live.merged(live.character, code, take=True)
                    if local is not None:
                        weights = self.engine.live.weights(live.character, code, poses)
                        if weights is None and live.character.rig.scalar_names:
                            weights = live.character.rig.scalars(code)  # the stage's
                        self.takes[path].add(code, local, weights)
        except BaseException as exc:  # reported by the main thread, which owns the exit
            self.error = exc


def live(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from rigspace.apps.render import make_folder
    from rigspace.runtime.engine import Engine, EngineSettings
    from rigspace.runtime.live.engine import Ticks
    from rigspace.sdk.color import linear_to_srgb

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise RigspaceError(f"--out {out} is a file, not a folder.", "choose a folder.")
    width, height = args.resolution
    engine = Engine(args.scene, EngineSettings(
        camera=args.camera, width=width, height=height, renderer=args.renderer,
        aovs=("beauty",), prim_samples=args.prim_samples, max_level=args.max_level,
        sources=dict(args.source), predictor=args.predictor, regions=not args.no_regions,
    ))  # fmt: skip
    video = recorder = None
    result = None
    try:
        _check_bindings(args, engine)
        engine.open_live()  # a port in use fails here, before the output folder exists
        stage = engine.stage
        fps = stage.GetTimeCodesPerSecond()
        start_code = stage.GetStartTimeCode() if args.start is None else args.start
        ticks = max(1, int(args.seconds * fps))
        created = make_folder(out)
        if args.video:
            video = _open_video(args.video, width, height, fps, created)
        _warm_up(engine, start_code)
        _print_ready(args, ticks, fps, start_code)
        t0 = time.monotonic()
        # Frames and the take share each tick's live pose, evaluated at the tick's due time.
        engine.live.ticks = Ticks(t0, fps, start_code, recording=bool(args.record))
        if args.record:
            recorder = _TakeThread(engine, start_code, fps, t0, ticks)
            recorder.start()
        result = _loop(engine, out, video, start_code, fps, t0, ticks, cv2, np, linear_to_srgb)
    finally:
        if recorder is not None:
            # A run that went its length records every tick; an interrupted one up to now.
            stopped = result is None or result[3]
            recorder.finish(time.monotonic() if stopped else recorder.t0 + ticks / fps)
            recorder.join()
        bindings = engine.live.report() if engine.live.active else []
        engine.close()
        if video is not None:
            video.close()
    frames, latencies, dropped, stopped = result
    summary = _summary(args, frames, latencies, dropped, ticks, fps, time.monotonic() - t0)
    summary["bindings"] = bindings
    if recorder is not None:
        if recorder.error is not None:
            raise recorder.error
        summary["takes"] = _write_takes(args, engine, recorder, fps)
    write_atomic(out / "report.json", json.dumps({**summary, "frames": frames}, indent=2) + "\n")
    _print_summary(summary, out, args.video, stopped)
    return 0


def _open_video(path: str, width: int, height: int, fps: float, created: Path | None):
    """--video's writer; when it cannot be written, the folders just made are removed again
    and the error names the path."""
    from rigspace.apps.render import remove_empty
    from rigspace.runtime.output import VideoWriter

    try:
        return VideoWriter(path, width, height, fps)
    except (OSError, ValueError) as exc:
        remove_empty(created)
        raise RigspaceError(
            f"--video {path} cannot be written ({exc}).",
            "choose a writable .mp4 path in an existing folder.",
        ) from exc


def _print_ready(args: argparse.Namespace, ticks: int, fps: float, start_code: float) -> None:
    """The engine is loaded and its sources listen: a script driving senders waits for this line."""
    print(
        f"rigspace live: ready: {ticks} ticks at {fps:g} fps from time code {start_code:g}"
        + (f", recording {args.record}" if args.record else "")
        + " (Ctrl-C stops)",
        file=sys.stderr,
        flush=True,
    )


def _check_bindings(args: argparse.Namespace, engine) -> None:
    """Warn when no live binding is enabled; refuse --record then (nothing to record)."""
    if not engine.live.active:
        print(
            "rigspace live: warning: no enabled live binding: the stage animation plays "
            "(enable one, or give one a source with --source NAME=URL).",
            file=sys.stderr,
        )
    if args.record and not engine.live.active:
        raise RigspaceError(
            "--record: there is no live binding to record.",
            "enable a binding (rigspace:live:NAME:enabled = true) or pass --source NAME=URL.",
        )


def _warm_up(engine, start_code: float) -> None:
    """Render one frame before the clock starts, saying so when it was slow."""
    # One frame before the clock starts: sessions, GL buffers, shadow maps, and on a first
    # run numba's compile of the shadow and texture kernels (cached on disk after; .ci/setup
    # compiles them ahead), so that the first live frame is on time.
    began = time.monotonic()
    engine.render(float(start_code))
    if time.monotonic() - began > FIRST_FRAME_NOTE:
        print(
            f"rigspace live: the first frame took {time.monotonic() - began:.1f} s (numba "
            "compiled the shadow and texture kernels; they are cached for later runs): the "
            "clock starts now",
            file=sys.stderr,
        )


def _loop(engine, out, video, start_code, fps, t0, ticks, cv2, np, linear_to_srgb):
    """Render at the stage's rate until `ticks` ticks have passed: each frame is the tick now
    due; the ticks that passed while the last frame rendered are dropped (counted, and the
    video holds the last frame through them)."""
    frames: list[dict[str, Any]] = []
    latencies: dict[str, list[float]] = {}
    dropped = 0
    k = 0
    last_rgb = None
    stopped = False
    try:
        while True:
            now = time.monotonic()
            due = int((now - t0) * fps)
            if due >= ticks:
                break
            if due > k:  # late: skip to the tick now due
                dropped += due - k
                if video is not None and last_rgb is not None:
                    for _ in range(due - k):
                        video.write(last_rgb)
                k = due
            code = start_code + k
            frame = engine.render(float(code))
            rgb = (linear_to_srgb(frame.beauty) * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(out / f"frame_{code:08.1f}.png"), rgb[..., ::-1])
            if video is not None:
                video.write(rgb)
            written = time.monotonic()
            last_rgb = rgb
            report = frame.report.to_json()
            report["tick"] = k
            report["written_seconds"] = round(written - t0, 4)
            latency = {}
            for name, received in engine.live.received_times().items():
                if math.isfinite(received):
                    latency[name] = round((written - received) * 1e3, 3)
                    latencies.setdefault(name, []).append(written - received)
            report["latency_ms"] = latency
            frames.append(report)
            k += 1
            wait = t0 + k / fps - time.monotonic()
            if wait > 0:
                time.sleep(wait)
    except KeyboardInterrupt:
        stopped = True
    if not stopped:  # the ticks the run ended in, while its last frame rendered
        if video is not None and last_rgb is not None:
            for _ in range(ticks - k):
                video.write(last_rgb)
        dropped += ticks - k
    return frames, latencies, dropped, stopped


def _summary(args, frames, latencies, dropped, ticks, fps, elapsed) -> dict[str, Any]:
    import numpy as np

    def ms(values: list[float], q: float) -> float | None:
        return round(float(np.percentile(values, q)) * 1e3, 3) if values else None

    totals = [f["seconds"]["total"] for f in frames]
    return {
        "scene": str(args.scene),
        "resolution": list(args.resolution),
        "frames_per_second": fps,
        "seconds": round(elapsed, 3),
        "ticks": ticks,
        "rendered": len(frames),
        "dropped": dropped,
        "frame_ms": {"p50": ms(totals, 50), "p99": ms(totals, 99)},
        "latency_ms": {
            name: {"p50": ms(v, 50), "p99": ms(v, 99), "frames": len(v)}
            for name, v in latencies.items()
        },
    }


def _write_takes(args, engine, recorder: _TakeThread, fps: float) -> list[dict[str, Any]]:
    """Each live character's take (TAKE.usda; TAKE_<character>.usda for several) and a stage
    that plays it on the scene (TAKE.shot.usda)."""
    from pxr import UsdGeom

    stage = engine.stage
    base = Path(args.record)
    written = []
    for path, take in recorder.takes.items():
        if not len(take):
            continue
        name = path.rsplit("/", 1)[-1]
        target = base if len(recorder.takes) == 1 else base.with_name(f"{base.stem}_{name}.usda")
        take.write(
            target, fps, UsdGeom.GetStageMetersPerUnit(stage),
            "Z" if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z else "Y",
        )  # fmt: skip
        live = engine.live.characters[path]
        shot = write_take_stage(
            target, args.scene, path, [b.name for b in live.bindings], stage, min(take._frames),
            max(take._frames),
        )  # fmt: skip
        written.append(
            {"character": path, "take": str(target), "shot": str(shot), "frames": len(take)}
        )
    return written


def write_take_stage(take, scene, character, bindings, source_stage, first, last) -> Path:
    """A stage beside `take` that sublayers `scene`, turns the character's live bindings off and
    binds the take as its animation (rigspace:animationSource), over the take's time range."""
    from pxr import Sdf, Usd, UsdGeom

    take = Path(take)
    path = take.with_suffix(".shot.usda")
    stage = Usd.Stage.CreateNew(str(path))
    layer = stage.GetRootLayer()
    layer.subLayerPaths.append(os.path.relpath(Path(scene).resolve(), path.parent.resolve()))
    stage.SetTimeCodesPerSecond(source_stage.GetTimeCodesPerSecond())
    stage.SetFramesPerSecond(source_stage.GetFramesPerSecond())
    stage.SetStartTimeCode(first)
    stage.SetEndTimeCode(last)
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.GetStageMetersPerUnit(source_stage))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.GetStageUpAxis(source_stage))
    if source_stage.GetDefaultPrim():
        stage.SetDefaultPrim(stage.GetPrimAtPath(source_stage.GetDefaultPrim().GetPath()))
    over = stage.OverridePrim(Sdf.Path(character))
    for name in bindings:
        over.CreateAttribute(f"rigspace:live:{name}:enabled", Sdf.ValueTypeNames.Bool, custom=False,
                             variability=Sdf.VariabilityUniform).Set(False)  # fmt: skip
    anim = stage.DefinePrim(Sdf.Path(character).AppendChild("LiveTake"))
    anim.GetReferences().AddReference(os.path.relpath(take.resolve(), path.parent.resolve()))
    over.CreateRelationship("rigspace:animationSource", custom=False).SetTargets([anim.GetPath()])
    layer.Save()
    return path


def _print_summary(summary: dict[str, Any], out: Path, video: str | None, stopped: bool) -> None:
    frame = summary["frame_ms"]
    print(
        f"rigspace live: {summary['rendered']} frames rendered, {summary['dropped']} dropped of "
        f"{summary['ticks']} at {summary['frames_per_second']:g} fps in {summary['seconds']:.1f} s"
        f" (frame p50 {frame['p50']} ms) into {out}"
        + (f"; video {video}" if video else "")
        + ("; stopped by Ctrl-C" if stopped else "")
    )
    for b in summary["bindings"]:
        lat = summary["latency_ms"].get(b["binding"], {})
        kernel = b.get("kernel_dropped")
        by_kernel = f" ({kernel} by the kernel: its receive buffer was full)" if kernel else ""
        print(
            f"  {b['binding']} ({b['url']}): {b['status']}, {b['samples']} samples, "
            f"{b['malformed']} malformed, {b['dropped']} dropped{by_kernel}, "
            f"{b['reconnects']} reconnects; "
            f"sample received to frame written p50 {lat.get('p50')} ms, p99 {lat.get('p99')} ms"
        )
    for t in summary.get("takes", []):
        print(
            f"  take {t['take']} ({t['frames']} frames); re-render: rigspace render {t['shot']} --out DIR"
        )


def _find_binding(stage, scene: str, name: str):
    """(character prim, LiveBinding) of the first neural character with the live binding NAME."""
    from rigspace.sdk import schema

    found = [
        (prim, b)
        for prim in schema.neural_characters(stage)
        for b in schema.read_live_bindings(prim)
        if b.name == name
    ]
    if not found:
        raise RigspaceError(
            f"{scene} has no live binding named {name!r}.",
            "pass --binding with a RigspaceLiveBindingAPI instance name (rigspace inspect lists them).",
        )
    return found[0]


def _author_rest_pose(prim, binding: str, bones, targets, rest) -> None:
    """The binding's sourceBones, targetJoints and restPose (w, x, y, z quaternions) on PRIM."""
    from pxr import Gf, Sdf, Vt

    ns = f"rigspace:live:{binding}"

    def put(name: str, kind, value) -> None:
        attr = prim.GetAttribute(f"{ns}:{name}") or prim.CreateAttribute(
            f"{ns}:{name}", kind, custom=False, variability=Sdf.VariabilityUniform
        )
        attr.Set(value)

    put("sourceBones", Sdf.ValueTypeNames.TokenArray, Vt.TokenArray(bones))
    put("targetJoints", Sdf.ValueTypeNames.TokenArray, Vt.TokenArray(targets))
    quats = [Gf.Quatf(float(q[0]), Gf.Vec3f(*map(float, q[1:]))) for q in rest]
    put("restPose", Sdf.ValueTypeNames.QuatfArray, Vt.QuatfArray(quats))


def calibrate(args: argparse.Namespace) -> int:
    """Wait for the source, take its pose as the rest pose, author it into the scene."""
    import dataclasses

    from pxr import Usd, UsdGeom

    from rigspace.runtime.live.binding import open_binding
    from rigspace.sdk.posing import CharacterRig
    from rigspace.sdk.stage import open_stage

    stage: Usd.Stage = open_stage(args.scene)
    prim, binding = _find_binding(stage, args.scene, args.binding)
    if args.source:
        binding = dataclasses.replace(binding, url=args.source)
    rig = CharacterRig(prim)
    runtime = open_binding(binding, rig.skeleton.GetPrim(), UsdGeom.GetStageMetersPerUnit(stage))
    runtime.start()
    try:
        print(
            f"hold the rest pose: taking it from {binding.url} in {args.seconds:g} s",
            file=sys.stderr,
        )
        time.sleep(args.seconds)
        pose = runtime.pose()
    finally:
        runtime.stop()
    if not pose.valid.any():
        raise RigspaceError(
            f"Live binding {binding.name!r} ({binding.url}) received nothing in {args.seconds:g} s.",
            "start the sender (check the URL and port; `rigspace live probe URL` shows what arrives).",
        )
    runtime.retargeter.calibrate(pose)
    bones, rest = runtime.rest_pose_attributes()
    r = runtime.retargeter
    targets = [r.target_joints[t].rsplit("/", 1)[-1] for t in r.map_target]
    missing = [b for b, ok in zip(r.source_bones, pose.valid, strict=True) if not ok and b in bones]
    _author_rest_pose(prim, binding.name, bones, targets, rest)
    stage.GetRootLayer().Save()
    print(
        f"calibrated {binding.name!r} on {prim.GetPath()}: restPose of {len(bones)} bones saved "
        f"in {stage.GetRootLayer().identifier}"
        + (
            f" ({len(missing)} never arrived, kept at identity: {', '.join(missing)})"
            if missing
            else ""
        )
    )
    return 0


COMMAND = CommandSpec(
    name="live",
    help="render a stage in real time with live mocap/controller input; send, probe, calibrate",
    description=DESCRIPTION,
    add_arguments=add_arguments,
    run=run,
)

"""The engine's live input: enabled bindings replace their characters' stage animation per frame."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from pxr import Usd, UsdGeom, Vt

from rigspace.runtime.live.transports import LiveSourceError
from rigspace.sdk import schema

if TYPE_CHECKING:
    from rigspace.runtime.character import NeuralCharacter
    from rigspace.runtime.live.binding import LiveBindingRuntime


@dataclass
class LiveCharacter:
    """One character's enabled bindings (applied in authored order) and its last live pose."""

    character: NeuralCharacter
    bindings: list[schema.LiveBinding]
    runtimes: list[LiveBindingRuntime] = field(default_factory=list)
    last: dict[str, Any] = field(default_factory=dict)
    """binding name -> {status, weight, received} of the last frame's pose."""
    last_local: np.ndarray | None = None
    """(J, 4, 4) the last frame's merged local transforms."""
    last_poses: list = field(default_factory=list)
    """(binding runtime, LivePose) of the last frame, for its blend shape weights."""
    weight_ranges: tuple[np.ndarray, np.ndarray] | None = None
    """(low, high) per blend shape and control (the rig's `scalar_names` order) that live
    weights and control values are clamped into."""
    shown: dict[int, tuple[np.ndarray, list]] = field(default_factory=dict)
    """Tick -> (local transforms, poses) evaluated and still wanted by a frame or the take."""
    next_tick: int = 0
    """The first tick not evaluated yet (ticks are evaluated in order)."""
    frame_tick: int = 0
    """The tick of the last frame (frames only go forward)."""
    take_tick: int = 0
    """The next tick the take will ask for."""
    lock: threading.Lock = field(default_factory=threading.Lock)
    """Frames and the take recorder evaluate ticks from two threads."""


@dataclass(frozen=True)
class Ticks:
    """A real-time run's clock (`rigspace live`): tick k, time code `start + k`, is due at local
    monotonic time `t0 + k / fps`. With it, a frame and a take tick of the same time code share
    one evaluation of the live pose at the tick's due time: the take records what the screen
    shows, transitions included."""

    t0: float
    fps: float
    start: float
    recording: bool
    """A take records every tick: each is evaluated (in order) and kept until it took it."""

    def tick(self, time_code: float) -> int | None:
        """The tick of `time_code`, or None for a time code that is none (the warm-up frame)."""
        k = round(time_code - self.start)
        return k if k >= 0 and abs(time_code - (self.start + k)) < 1e-6 else None

    def due(self, k: int) -> float:
        return self.t0 + k / self.fps


SOURCE_DESCRIPTION = {
    "source_bones": ("sourceBones", ()),
    "target_joints": ("targetJoints", ()),
    "source_up_axis": ("sourceUpAxis", "Y"),
    "source_handedness": ("sourceHandedness", "right"),
    "source_meters_per_unit": ("sourceMetersPerUnit", 1.0),
    "rest_pose": ("restPose", ()),
    "bone_preset": ("bonePreset", "auto"),
}
"""What a binding says about its source (bone map, axes, units, calibration), at the schema's
fallbacks: the new scheme's preset then applies."""


def scheme(url: str) -> str:
    return url.partition("://")[0].lower()


def with_source(binding: schema.LiveBinding, url: str) -> schema.LiveBinding:
    """`binding` with --source NAME=URL: that URL, enabled whatever the stage says. A URL of
    another scheme is another kind of sender: what the binding authors about its source (bone
    map, axes, handedness, units, calibration), written for the old one, is reset to the
    schema's fallbacks so the new scheme's preset applies (said on stderr)."""
    fields = {**binding.__dict__, "url": url, "enabled": True}
    old, new = scheme(binding.url), scheme(url)
    if old and old != new:
        authored = [
            attribute
            for name, (attribute, fallback) in SOURCE_DESCRIPTION.items()
            if fields[name] != fallback
        ]
        fields |= {name: fallback for name, (_, fallback) in SOURCE_DESCRIPTION.items()}
        if authored:
            print(
                f"rigspace live: --source {binding.name}={url}: a {new}:// source replaces "
                f"{old}://; the binding's {', '.join(authored)} (authored for {old}://) are "
                f"reset, so the {new}:// preset applies",
                file=sys.stderr,
            )
    return schema.LiveBinding(**fields)


def weight_ranges(prim: Usd.Prim, shapes: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) per name of `shapes` (blend shapes, then controls: `CharacterRig.
    scalar_names`): a control's own range (RigspaceControlAPI), the capture ring's
    blendShapeRanges where it declares a shape (the weights the network was trained on), else
    WEIGHT_RANGE."""
    from rigspace.runtime.live.binding import WEIGHT_RANGE

    shapes = list(shapes)
    low, high = np.full(len(shapes), WEIGHT_RANGE[0]), np.full(len(shapes), WEIGHT_RANGE[1])
    if schema.has_capture_ring(prim):
        ring = schema.read_capture_ring(prim)
        for name, (lo, hi) in zip(ring.blend_shape_names, ring.blend_shape_ranges, strict=False):
            if name in shapes:
                low[shapes.index(name)], high[shapes.index(name)] = lo, hi
    for control in schema.read_controls(prim):
        if control.name in shapes and not control.problem():
            k = shapes.index(control.name)
            low[k], high[k] = control.low, control.high
    return low, high


def _clip_ranges(prim: Usd.Prim) -> dict[str, tuple[float, float]]:
    """The character's named clips (capture ring clipNames -> clipRanges), for clip blends."""
    if not schema.has_capture_ring(prim):
        return {}
    ring = schema.read_capture_ring(prim)
    return dict(zip(ring.clip_names, ring.clip_ranges, strict=False))


class LiveInput:
    """The live bindings of an Engine's characters: opened lazily, merged into each frame's pose.

    Receivers run on their sources' threads and push into each binding's LiveBuffer; a frame
    takes one consistent pose per binding from `LiveBuffer.pose` (a constant-time copy under
    the buffer's lock), so a frame never waits on the network. The merged local transforms
    go through the same UsdSkel concatenation as the stage's, so a source that holds still
    gives the same joint transforms, and the engine's pose comparison reuses the layer.
    """

    def __init__(
        self,
        stage: Usd.Stage,
        characters: Sequence[NeuralCharacter],
        sources: dict[str, str],
        enabled: bool,
    ) -> None:
        self.meters_per_unit = UsdGeom.GetStageMetersPerUnit(stage)
        self.characters: dict[str, LiveCharacter] = {}
        self._lock = threading.Lock()  # open/close may race with a recorder thread's reads
        self._opened = False
        self.ticks: Ticks | None = None
        """Set by a real-time run (`rigspace live`): frames and takes then share each tick's
        pose (`merged`); None: each frame's live pose is the one at the time it is asked."""
        named: set[str] = set()
        for character in characters:
            chosen = []
            for binding in schema.read_live_bindings(character.prim):
                named.add(binding.name)
                if binding.name in sources:
                    binding = with_source(binding, sources[binding.name])
                if binding.enabled and enabled:
                    chosen.append(binding)
            if chosen:
                self.characters[character.path] = LiveCharacter(character, chosen)
        unknown = sorted(set(sources) - named)
        if unknown:
            raise LiveSourceError(
                f"--source {', '.join(unknown)}: the stage's neural characters have no live "
                f"binding of that name (they have: {', '.join(sorted(named)) or 'none'}).",
                "name a RigspaceLiveBindingAPI instance of the stage, as in --source suit=URL.",
            )

    @property
    def active(self) -> bool:
        """Whether any character is driven by a live binding."""
        return bool(self.characters)

    def open(self) -> None:
        """Build and start every binding's source (idempotent). A source that cannot start
        stops the ones already started and raises one error naming the binding and the fix."""
        if self._opened or not self.characters:
            return
        from rigspace.runtime.live.binding import open_binding

        with self._lock:
            started: list[LiveBindingRuntime] = []
            try:
                for live in self.characters.values():
                    skeleton = live.character.rig.skeleton.GetPrim()
                    clips = _clip_ranges(live.character.prim)
                    for binding in live.bindings:
                        where = f"Live binding {binding.name!r} of {live.character.path}"
                        try:
                            runtime = open_binding(
                                binding, skeleton, self.meters_per_unit, clips=clips
                            )
                            runtime.start()
                        except LiveSourceError as exc:
                            raise LiveSourceError(
                                f"{where}: {exc.what}",
                                f"{exc.fix} Or give the binding another source (--source "
                                f"{binding.name}=URL), or author rigspace:live:{binding.name}:"
                                "enabled = false to render the stage animation.",
                            ) from None
                        started.append(runtime)
                        live.runtimes.append(runtime)
            except BaseException:
                for runtime in started:
                    runtime.stop()
                for live in self.characters.values():
                    live.runtimes.clear()
                raise
            self._opened = True

    def close(self) -> None:
        """Stop every started source (their sockets, ports and threads are released)."""
        with self._lock:
            for live in self.characters.values():
                for runtime in live.runtimes:
                    runtime.stop()
                live.runtimes.clear()
            self._opened = False

    def merged(
        self,
        character: NeuralCharacter,
        time_code: float,
        now: float | None = None,
        take: bool = False,
    ):
        """(J, 4, 4) the character's local transforms at `time_code` with its bindings' poses
        merged in (None without live bindings), and each binding's pose: what the screen shows
        (LiveBindingRuntime.apply_frame: the pose at the time, with the connect, reconnect and
        loss transitions). At local time `now` (default: now); in a real-time run (`ticks`)
        a tick's at its due time, evaluated once for the frame and the take (`take`: the
        recorder asks, and the tick is not kept for it any more)."""
        live = self.characters.get(character.path)
        if live is None or not live.runtimes:
            return None, []
        tick = None if self.ticks is None or now is not None else self.ticks.tick(time_code)
        if tick is None:
            with live.lock:
                return self._shown(live, time_code, time.monotonic() if now is None else now)
        return self._at_tick(live, tick, take)

    def _at_tick(self, live: LiveCharacter, tick: int, take: bool):
        """The evaluation of `tick` (ticks in order: a frame ahead of the take evaluates the
        ticks before it first; without a take, frames skip the ticks they dropped)."""
        ticks = self.ticks
        assert ticks is not None
        with live.lock:
            while live.next_tick <= tick:
                k, live.next_tick = live.next_tick, live.next_tick + 1
                if k == tick or ticks.recording:
                    code = ticks.start + k
                    live.shown[k] = self._shown(live, code, ticks.due(k))
            found = live.shown.get(tick)
            if take:
                live.take_tick = tick + 1
            else:
                live.frame_tick = tick
            keep = min(live.frame_tick, live.take_tick if ticks.recording else tick)
            for k in [k for k in live.shown if k < keep]:
                del live.shown[k]
            if found is None:  # a tick asked for again after it was let go: as it is now
                found = self._shown(live, ticks.start + tick, time.monotonic())
            return found

    def _shown(self, live: LiveCharacter, time_code: float, when: float):
        """The character's merged local transforms and poses shown at local time `when`."""
        rig = live.character.rig
        local = np.asarray(rig.local_transforms(time_code), dtype=np.float64)
        poses = []
        for runtime in live.runtimes:
            local, pose = runtime.apply_frame(local, when, rig.local_transforms, time_code)
            poses.append((runtime, pose))
        return local, poses

    def local(
        self, character: NeuralCharacter, time_code: float, entry: dict[str, Any]
    ) -> Vt.Matrix4dArray | None:
        """The frame's local transforms for `character` (None: the stage animation's), noting
        each binding's status and weight in the character's report entry."""
        local, poses = self.merged(character, time_code)
        if local is None:
            return None
        live = self.characters[character.path]
        entry["live"] = []
        for runtime, pose in poses:
            state = {"status": pose.status, "weight": round(pose.weight, 4)}
            live.last[runtime.name] = {**state, "received": pose.received}
            entry["live"].append({"binding": runtime.name, **state})
        live.last_local = local
        live.last_poses = poses
        return Vt.Matrix4dArray.FromNumpy(local)

    def weights(
        self, character: NeuralCharacter, time_code: float, poses: list | None = None
    ) -> np.ndarray | None:
        """(B + C,) the character's blend shape weights and controls' values (its
        `rig.scalar_names` order) with the live values of `poses` ((runtime, LivePose) pairs;
        default the last frame's) merged in by each binding's weight (a lost source lets go as
        its bones do); None when no binding sent a value for one of its shapes or controls
        (the stage's apply). A source names a control as it names a shape (VMC
        /VMC/Ext/Blend/Val, or the plain OSC /rigspace/control NAME VALUE). Live values are
        clamped into their ranges (`weight_ranges`): a source's 5.0 is its shape's high end,
        never a pose the network was not trained on (the frames, and so the takes, hold only
        those)."""
        live = self.characters.get(character.path)
        shapes = character.rig.scalar_names
        if live is None or not shapes:
            return None
        if live.weight_ranges is None:
            live.weight_ranges = weight_ranges(character.prim, shapes)
        low, high = live.weight_ranges
        out = None
        for runtime, pose in live.last_poses if poses is None else poses:
            indices, values = runtime.blend_weights(pose, shapes)
            if len(indices):
                out = character.rig.scalars(time_code) if out is None else out
                values = np.clip(values, low[indices], high[indices])
                out[indices] += (values - out[indices]) * float(pose.weight)
        return out

    def received_times(self) -> dict[str, float]:
        """binding name -> local monotonic time the newest sample in the last frame's pose
        arrived, for the bindings that were connected (a held or lost pose's age is not a
        latency)."""
        return {
            name: state["received"]
            for live in self.characters.values()
            for name, state in live.last.items()
            if state["status"] == "connected"
        }

    def report(self, now: float | None = None) -> list[dict[str, Any]]:
        """Every binding's status, blend weight and counters, for the frame's report."""
        now = time.monotonic() if now is None else now
        out = []
        for path, live in self.characters.items():
            for runtime in live.runtimes:
                last = live.last.get(runtime.name, {})
                out.append(
                    {
                        "character": path,
                        "binding": runtime.name,
                        "url": runtime.source.url,
                        "weight": last.get("weight"),
                        **runtime.counters(now).as_dict(),
                    }
                )
        return out

"""Linux evdev game-controller events (`struct input_event`) -> additive joint rotations."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from rigspace.runtime.live.source_frame import DecodeCounters, SourceFrame, quat_from_euler
from rigspace.sdk.input_codes import (  # noqa: F401  (re-exported for the fuzzer and tests)
    ABS_CODES,
    BTN_CODES,
    CONTROL_CODES,
    EV_ABS,
    EV_KEY,
    EV_SYN,
)

EVENT = struct.Struct("@qqHHi")
"""struct input_event on 64-bit Linux: timeval (seconds, microseconds), type, code, value."""
EV_MAX = 0x1F
SYN_REPORT, SYN_DROPPED = 0, 3
TRIGGERS = ("ABS_Z", "ABS_RZ", "ABS_GAS", "ABS_BRAKE")
TRIGGER_RANGE = (0, 1023)
"""Analogue triggers rest at their minimum (the xpad driver reports 0 to 1023)."""
STICK_RANGE = (-32768, 32767)


@dataclass(frozen=True)
class AxisMap:
    """One controller axis (or button) driving one joint rotation axis."""

    code: int
    """EV_ABS code (ABS_CODES), or EV_KEY code (BTN_CODES) when `kind` is EV_KEY."""
    joint: str
    axis: str
    """Joint-local rotation axis: X, Y or Z."""
    degrees: float
    """Rotation at full deflection (sign flips the direction)."""
    minimum: int = -32768
    maximum: int = 32767
    """The axis range (the device's absinfo; Xbox-style sticks by default)."""
    deadzone: float = 0.1
    """Fraction of half the range around the centre that reads as zero (stick drift)."""
    kind: int = EV_ABS
    """EV_ABS (deflection in [-1, 1]) or EV_KEY (a button: 1 while held, else 0)."""


@dataclass(frozen=True)
class ClipControl:
    """One trigger, axis or button that blends the stage animation towards a named clip."""

    kind: int
    code: int
    clip: str
    minimum: int = TRIGGER_RANGE[0]
    maximum: int = TRIGGER_RANGE[1]
    """The blend is the control's position in [minimum, maximum], clipped to [0, 1]."""


DEFAULT_AXES = (
    AxisMap(ABS_CODES["ABS_RX"], "head", "Y", -60.0),  # right stick: look left/right
    AxisMap(ABS_CODES["ABS_RY"], "head", "X", 40.0),  # right stick: look up/down
    AxisMap(ABS_CODES["ABS_X"], "spine_02", "Z", -25.0),  # left stick: lean sideways
    AxisMap(ABS_CODES["ABS_Y"], "spine_02", "X", 25.0),  # left stick: bend forward/back
)
"""Head yaw/pitch and spine lean for the sample character's joints."""


class EvdevDecoder:
    """evdev bytes -> frames of additive rotations (one per mapped joint, on SYN_REPORT).

    Each frame carries, for every mapped joint, the rotation its axes ask for (composed X then Y
    then Z), to be applied on top of the stage animation's local rotation (space "additive").
    Axis values are normalised to [-1, 1] around the range centre with a dead zone. Events the
    map does not use (buttons, other axes) are counted as ignored; SYN_DROPPED (the kernel's
    buffer overran) discards the partial state until the next report, as the evdev protocol
    asks. Timestamps are the events' own (kernel monotonic or realtime, per device).
    """

    space = "additive"

    def __init__(
        self,
        axes: tuple[AxisMap, ...] = DEFAULT_AXES,
        clips: tuple[ClipControl, ...] = (),
        shapes: tuple[ClipControl, ...] = (),
    ) -> None:
        """`shapes`: controls that set blend shape weights (a ClipControl's `clip` names the
        shape): each report's frame carries every shape's weight, the strongest control's."""
        self.axes = axes
        self.clips = clips
        self.shapes = shapes
        self._shape_value = np.zeros(len(shapes))
        self._shape_by_code: dict[tuple[int, int], list[int]] = {}
        for i, s in enumerate(shapes):
            self._shape_by_code.setdefault((s.kind, s.code), []).append(i)
        self.bones: tuple[str, ...] = tuple(dict.fromkeys(a.joint for a in axes))
        self.clip_names: tuple[str, ...] = tuple(dict.fromkeys(c.clip for c in clips))
        self.clip_weights = np.zeros(len(self.clip_names))
        """Blend per clip name in [0, 1] as of the last report (replaced whole on each report:
        the frame thread reads it without a lock); the strongest control of a clip wins."""
        self.counters = DecodeCounters()
        self._buffer = bytearray()
        self._value = np.zeros(len(axes))  # normalised deflection per mapped axis
        self._clip_value = np.zeros(len(clips))
        self._by_code: dict[tuple[int, int], list[int]] = {}
        for i, a in enumerate(axes):
            self._by_code.setdefault((a.kind, a.code), []).append(i)
        self._clip_by_code: dict[tuple[int, int], list[int]] = {}
        for i, c in enumerate(clips):
            self._clip_by_code.setdefault((c.kind, c.code), []).append(i)
        self._clip_column = np.array([self.clip_names.index(c.clip) for c in clips], dtype=int)
        # Per-frame constants: which output row and Euler column each axis feeds.
        index = {b: k for k, b in enumerate(self.bones)}
        self._row = np.array([index[a.joint] for a in axes], dtype=int)
        self._col = np.array([{"X": 0, "Y": 1, "Z": 2}[a.axis] for a in axes], dtype=int)
        self._degrees = np.array([a.degrees for a in axes], dtype=np.float64)
        self._dropping = False
        self._changed = False

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def reset(self) -> None:
        self._buffer.clear()
        self._dropping = False

    def feed(self, data: bytes, received: float) -> list[SourceFrame]:
        c = self.counters
        c.packets += 1
        self._buffer += data
        whole = len(self._buffer) // EVENT.size * EVENT.size
        frames = []
        for sec, usec, kind, code, value in EVENT.iter_unpack(bytes(self._buffer[:whole])):
            c.messages += 1
            if kind == EV_SYN and code == SYN_DROPPED:
                self._dropping = True
            elif kind == EV_SYN and code == SYN_REPORT:
                if self._dropping:
                    self._dropping = False
                elif self._changed:
                    frames.append(self._frame(sec + usec * 1e-6))
            elif self._dropping:
                continue
            elif (
                (kind, code) in self._by_code
                or (kind, code) in self._clip_by_code
                or (kind, code) in self._shape_by_code
            ):
                for i in self._by_code.get((kind, code), ()):
                    a = self.axes[i]
                    self._value[i] = (
                        float(value != 0) if kind == EV_KEY else self._normalise(a, value)
                    )
                for i in self._clip_by_code.get((kind, code), ()):
                    self._clip_value[i] = self._position(self.clips[i], kind, value)
                for i in self._shape_by_code.get((kind, code), ()):
                    self._shape_value[i] = self._position(self.shapes[i], kind, value)
                self._changed = True
            elif kind > EV_MAX or not (0 <= usec < 1_000_000):
                c.malformed += 1  # not an event the kernel can send
            else:
                c.ignored += 1
        del self._buffer[:whole]
        return frames

    @staticmethod
    def _normalise(a: AxisMap, value: int) -> float:
        half = (a.maximum - a.minimum) / 2.0
        if half <= 0:
            return 0.0
        x = float(np.clip((value - (a.minimum + half)) / half, -1.0, 1.0))
        if abs(x) <= a.deadzone:
            return 0.0
        return float(np.sign(x) * (abs(x) - a.deadzone) / (1.0 - a.deadzone))

    @staticmethod
    def _position(c: ClipControl, kind: int, value: int) -> float:
        if kind == EV_KEY:
            return float(value != 0)  # pressed (1) or auto-repeat (2); released is 0
        span = c.maximum - c.minimum
        return float(np.clip((value - c.minimum) / span, 0.0, 1.0)) if span > 0 else 0.0

    def _frame(self, timestamp: float) -> SourceFrame:
        self._changed = False
        angles = np.zeros((len(self.bones), 3))
        np.add.at(angles, (self._row, self._col), self._degrees * self._value)
        rotations = quat_from_euler(angles, "XYZ")
        if len(self.clips):
            weights = np.zeros(len(self.clip_names))
            np.maximum.at(weights, self._clip_column, self._clip_value)
            self.clip_weights = weights
        shapes: dict[str, float] | None = None
        if self.shapes:
            shapes = {}
            for control, value in zip(self.shapes, self._shape_value, strict=True):
                shapes[control.clip] = max(shapes.get(control.clip, 0.0), float(value))
        self.counters.frames += 1
        self.counters.samples += len(self.bones)
        indices = np.arange(len(self.bones), dtype=np.int64)
        return SourceFrame(0, timestamp, indices, rotations, None, shapes)


def _range(name: str, parts: list[str]) -> tuple[int, int]:
    if parts:
        return int(parts[0]), int(parts[1])
    return TRIGGER_RANGE if name in TRIGGERS else STICK_RANGE


def parse_axes(text: str | list[str] | tuple[str, ...]) -> tuple[AxisMap, ...]:
    """`CONTROL:JOINT:AXIS:DEGREES[:MIN:MAX]` items (a comma-separated string, as the URL's
    axes= option, or a sequence, as the binding's gamepadOffsets) -> axis maps. CONTROL is an
    axis (ABS_RX; range MIN:MAX, default the stick's or the trigger's) or a button (BTN_TL)."""
    axes = []
    for item in text.split(",") if isinstance(text, str) else text:
        parts = item.split(":")
        if (
            len(parts) not in (4, 6)
            or parts[0] not in CONTROL_CODES
            or parts[2] not in ("X", "Y", "Z")
        ):
            raise ValueError(item)
        kind, code = CONTROL_CODES[parts[0]]
        low, high = _range(parts[0], parts[4:])
        degrees = float(parts[3])
        if not (np.isfinite(degrees) and high > low):
            raise ValueError(item)
        axes.append(AxisMap(code, parts[1], parts[2], degrees, low, high, kind=kind))
    return tuple(axes)


def parse_clips(text: str | list[str] | tuple[str, ...]) -> tuple[ClipControl, ...]:
    """`CONTROL:CLIP[:MIN:MAX]` items (a comma-separated string, as the URL's clips= option,
    or a sequence, as the binding's gamepadClips) -> clip controls (default range 0:1023)."""
    clips = []
    for item in text.split(",") if isinstance(text, str) else text:
        parts = item.split(":")
        if len(parts) not in (2, 4) or parts[0] not in CONTROL_CODES or not parts[1]:
            raise ValueError(item)
        kind, code = CONTROL_CODES[parts[0]]
        low, high = (int(parts[2]), int(parts[3])) if len(parts) == 4 else TRIGGER_RANGE
        if high <= low:
            raise ValueError(item)
        clips.append(ClipControl(kind, code, parts[1], low, high))
    return tuple(clips)

"""Linux evdev game-controller events (`struct input_event`) -> additive joint rotations."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from rigspace.runtime.live.frames import DecodeCounters, Frame, quat_from_euler

EVENT = struct.Struct("@qqHHi")
"""struct input_event on 64-bit Linux: timeval (seconds, microseconds), type, code, value."""
EV_SYN, EV_KEY, EV_ABS = 0, 1, 3
EV_MAX = 0x1F
SYN_REPORT, SYN_DROPPED = 0, 3
ABS_CODES = {"ABS_X": 0, "ABS_Y": 1, "ABS_Z": 2, "ABS_RX": 3, "ABS_RY": 4, "ABS_RZ": 5}
ABS_CODES |= {"ABS_HAT0X": 16, "ABS_HAT0Y": 17}


@dataclass(frozen=True)
class AxisMap:
    """One controller axis driving one joint rotation axis."""

    code: int
    """EV_ABS code (ABS_CODES)."""
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

    def __init__(self, axes: tuple[AxisMap, ...] = DEFAULT_AXES) -> None:
        self.axes = axes
        self.bones: tuple[str, ...] = tuple(dict.fromkeys(a.joint for a in axes))
        self.counters = DecodeCounters()
        self._buffer = bytearray()
        self._value = np.zeros(len(axes))  # normalised deflection per mapped axis
        self._by_code: dict[int, list[int]] = {}
        for i, a in enumerate(axes):
            self._by_code.setdefault(a.code, []).append(i)
        self._dropping = False
        self._changed = False

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def reset(self) -> None:
        self._buffer.clear()
        self._dropping = False

    def feed(self, data: bytes, received: float) -> list[Frame]:
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
            elif kind == EV_ABS and code in self._by_code:
                for i in self._by_code[code]:
                    self._value[i] = self._normalise(self.axes[i], value)
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

    def _frame(self, timestamp: float) -> Frame:
        self._changed = False
        angles = np.zeros((len(self.bones), 3))
        column = {"X": 0, "Y": 1, "Z": 2}
        index = {b: k for k, b in enumerate(self.bones)}
        for i, a in enumerate(self.axes):
            angles[index[a.joint], column[a.axis]] += a.degrees * self._value[i]
        rotations = quat_from_euler(angles, "XYZ")
        self.counters.frames += 1
        self.counters.samples += len(self.bones)
        return Frame(0, timestamp, np.arange(len(self.bones), dtype=np.int64), rotations)


def parse_axes(text: str) -> tuple[AxisMap, ...]:
    """`CODE:JOINT:AXIS:DEGREES[:MIN:MAX],...` (e.g. `ABS_RX:head:Y:-60`) -> axis maps."""
    axes = []
    for item in text.split(","):
        parts = item.split(":")
        if len(parts) not in (4, 6) or parts[0] not in ABS_CODES or parts[2] not in ("X", "Y", "Z"):
            raise ValueError(item)
        extra = {"minimum": int(parts[4]), "maximum": int(parts[5])} if len(parts) == 6 else {}
        axes.append(AxisMap(ABS_CODES[parts[0]], parts[1], parts[2], float(parts[3]), **extra))
    return tuple(axes)

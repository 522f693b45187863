"""x-IMU3 ASCII messages: `Q,timestamp,w,x,y,z` quaternion lines, one sensor per channel."""

from __future__ import annotations

import numpy as np

from rigspace.runtime.live.source_frame import DecodeCounters, SourceFrame, unit_quaternions

QUATERNION = b"Q"
MICROSECONDS = 1e-6
"""x-IMU3 timestamps count microseconds of the device's own clock."""


class Ximu3Decoder:
    """x-IMU3 ASCII lines -> world orientations, one bone per channel (device).

    Channel i (the i-th serial port of a source) carries one sensor mapped to `bones[i]`; its
    timestamps form stream i (each device has its own clock). Other well-formed x-IMU3 messages
    (inertial `I,...`, magnetometer `M,...`, ...: a letter and comma-separated values) are
    counted as ignored. The quaternion is the sensor's orientation in its Earth frame (the
    x-IMU3 default, NWU: X north, Z up, right-handed).
    """

    space = "world"
    MAX_LINE = 256
    """Longest line kept while waiting for its newline, in bytes (a Q line is under 60)."""

    def __init__(self, bones: tuple[str, ...]) -> None:
        if not bones:
            raise ValueError("Ximu3Decoder needs at least one bone (one per sensor).")
        self.bones = tuple(bones)
        self.counters = DecodeCounters()
        self._buffers = [bytearray() for _ in self.bones]
        self._skip = [False] * len(self.bones)

    @property
    def buffered(self) -> int:
        return sum(len(b) for b in self._buffers)

    def reset(self) -> None:
        for b in self._buffers:
            b.clear()
        self._skip = [False] * len(self.bones)

    def feed(self, data: bytes, received: float, channel: int = 0) -> list[SourceFrame]:
        self.counters.packets += 1
        buffer = self._buffers[channel]
        buffer += data
        frames: list[SourceFrame] = []
        while True:
            end = buffer.find(b"\n")
            if end < 0:
                break
            line = bytes(buffer[:end])
            del buffer[: end + 1]
            if self._skip[channel]:
                self._skip[channel] = False
                continue
            frame = self.decode_line(line, channel)
            if frame is not None:
                frames.append(frame)
        if len(buffer) > self.MAX_LINE:
            self.counters.malformed += 1
            buffer.clear()
            self._skip[channel] = True
        return frames

    def decode_line(self, line: bytes, channel: int = 0) -> SourceFrame | None:
        """One message line -> a frame, or None (blank, ignored, or counted as malformed)."""
        c = self.counters
        fields = line.strip().split(b",")
        if fields == [b""]:
            return None
        c.messages += 1
        kind = fields[0]
        if kind != QUATERNION:
            if len(kind) == 1 and kind.isalpha() and len(fields) > 1:
                c.ignored += 1
            else:
                c.malformed += 1
            return None
        if len(fields) != 6:
            c.malformed += 1
            return None
        try:
            ticks = int(fields[1])
            values = np.array([float(f) for f in fields[2:]], dtype=np.float64)
        except ValueError:
            c.malformed += 1
            return None
        quat, ok = unit_quaternions(values[None])
        if not ok[0] or ticks < 0 or ticks > 1 << 63:
            c.malformed += 1
            return None
        c.frames += 1
        c.samples += 1
        return SourceFrame(channel, ticks * MICROSECONDS, np.array([channel], dtype=np.int64), quat)

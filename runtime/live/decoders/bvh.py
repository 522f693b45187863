"""BVH hierarchies (mixed rotation orders per joint) and the Axis Neuron BVH data stream."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigspace.runtime.live.source_frame import (
    MAX_ANGLE_DEGREES,
    MAX_POSITION,
    DecodeCounters,
    SourceFrame,
    quat_from_euler,
)
from rigspace.sdk.errors import RigspaceError


class BvhError(RigspaceError):
    """A BVH file that cannot be read: names the file, the line and the fix."""


@dataclass(frozen=True)
class BvhSkeleton:
    """A BVH HIERARCHY: joints in file order, each with its own channels.

    Rotation channels listed as `Zrotation Yrotation Xrotation` mean v' = Rz Ry Rx v (degrees);
    the order may differ per joint (the CMU conversions mix ZYX and ZXY). Joints are Y up,
    right-handed, and their rest frames are aligned with the world (BVH has no rest rotations).
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    """Index of each joint's parent, -1 for the root."""
    offsets: np.ndarray
    """(J, 3) rest offset of each joint from its parent, in file units."""
    channels: tuple[tuple[str, ...], ...]
    """Per joint, its channel names in file order (e.g. Xposition, Zrotation)."""

    @property
    def channel_count(self) -> int:
        return sum(len(c) for c in self.channels)

    def rest_positions(self) -> np.ndarray:
        """(J, 3) joint positions in the rest pose (all rotations zero), in file units."""
        positions = np.zeros((len(self.names), 3))
        for j, parent in enumerate(self.parents):  # BVH lists parents before children
            positions[j] = self.offsets[j] + (positions[parent] if parent >= 0 else 0.0)
        return positions

    def pose(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F, C) channel values -> local rotations (F, J, 4) and root positions (F, 3)."""
        values = np.asarray(values, dtype=np.float64)
        frames = values.shape[0]
        rotations = np.zeros((frames, len(self.names), 4))
        rotations[..., 0] = 1.0
        for order, (joints, columns) in self._rotation_groups().items():
            rotations[:, joints] = quat_from_euler(values[:, columns], order)
        root = np.repeat(self.offsets[:1], frames, axis=0)
        for axis, column in self._root_position_columns():
            root[:, axis] = values[:, column]
        return rotations, root

    def _rotation_groups(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Joints grouped by rotation order: order -> (joint indices, (Jg, 3) channel columns)."""
        cached = self.__dict__.get("_groups")
        if cached is not None:
            return cached
        groups: dict[str, tuple[list[int], list[list[int]]]] = {}
        column = 0
        for j, channels in enumerate(self.channels):
            rot = [(c[0], column + k) for k, c in enumerate(channels) if c.endswith("rotation")]
            if rot:
                order = "".join(axis for axis, _ in rot)
                joints, cols = groups.setdefault(order, ([], []))
                joints.append(j)
                cols.append([col for _, col in rot])
            column += len(channels)
        result = {o: (np.array(j), np.array(c)) for o, (j, c) in groups.items()}
        object.__setattr__(self, "_groups", result)  # frozen dataclass: cache once
        return result

    def _root_position_columns(self) -> list[tuple[int, int]]:
        return [
            ("XYZ".index(c[0]), k) for k, c in enumerate(self.channels[0]) if c.endswith("position")
        ]


_ROTATION_CHANNELS = {"Xrotation", "Yrotation", "Zrotation"}
_POSITION_CHANNELS = {"Xposition", "Yposition", "Zposition"}


def parse_bvh(text: str, source: str = "BVH") -> tuple[BvhSkeleton, np.ndarray, float]:
    """A BVH file's text -> (skeleton, (F, C) motion values, frame time in seconds)."""
    reader = _Tokens.of(text, source)
    skeleton = _parse_hierarchy(reader)
    tokens, pos = reader.tokens, reader.pos
    if pos >= len(tokens) or tokens[pos][0] != "MOTION":
        return skeleton, np.zeros((0, skeleton.channel_count)), 0.0
    motion, frame_time = _parse_motion(reader, skeleton, tokens[pos][1])
    return skeleton, motion, frame_time


@dataclass
class _Tokens:
    """A BVH file's whitespace-separated tokens with their line numbers, read in turn."""

    source: str
    """What the errors call the file (its path)."""
    lines: list[str]
    tokens: list[tuple[str, int]]
    pos: int = 0
    """The next token's index."""

    @classmethod
    def of(cls, text: str, source: str) -> _Tokens:
        """The tokens of a BVH file's text."""
        lines = text.splitlines()
        tokens: list[tuple[str, int]] = [
            (t, n + 1) for n, line in enumerate(lines) for t in line.split()
        ]
        return cls(source, lines, tokens)

    def fail(self, what: str, line: int) -> BvhError:
        """The error for a problem at `line` of the file."""
        return BvhError(
            f"{self.source}, line {line}: {what}.",
            "export the file again as BVH (HIERARCHY with ROOT/JOINT/End Site blocks, then MOTION).",
        )

    def take(self) -> tuple[str, int]:
        """The next token and its line; the end of the file here is an error."""
        if self.pos >= len(self.tokens):
            raise self.fail("the file ends inside the HIERARCHY", len(self.lines))
        self.pos += 1
        return self.tokens[self.pos - 1]

    def number(self, what: str) -> float:
        """The next token as a number (`what` names it in the error)."""
        t, line = self.take()
        try:
            return float(t)
        except ValueError:
            raise self.fail(f"{what} {t!r} is not a number", line) from None


def _parse_hierarchy(reader: _Tokens) -> BvhSkeleton:
    """The HIERARCHY block's joints, from the first token to the root's closing brace."""
    fail, take = reader.fail, reader.take
    tokens = reader.tokens
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    if not tokens or tokens[0][0] != "HIERARCHY":
        raise fail("it does not start with HIERARCHY", tokens[0][1] if tokens else 1)
    reader.pos = 1
    stack: list[int] = []  # joint indices of open blocks; -2 marks an End Site
    while True:
        t, line = take()
        if t in ("ROOT", "JOINT"):
            if (t == "ROOT") != (not stack):
                raise fail(f"{t} {'outside' if t == 'JOINT' else 'inside'} a joint", line)
            name, _ = take()
            if take()[0] != "{":
                raise fail(f"joint {name!r} has no opening brace", line)
            parents.append(stack[-1] if stack else -1)
            names.append(name)
            offsets.append([0.0, 0.0, 0.0])
            channels.append(())
            stack.append(len(names) - 1)
        elif t == "End":
            take()  # "Site"
            if take()[0] != "{":
                raise fail("End Site has no opening brace", line)
            stack.append(-2)
        elif t == "OFFSET":
            offset = [reader.number("OFFSET value") for _ in range(3)]
            if stack and stack[-1] >= 0:
                offsets[stack[-1]] = offset
        elif t == "CHANNELS":
            count_text, _ = take()
            if not count_text.isdigit() or not stack or stack[-1] < 0:
                raise fail("CHANNELS must give a count inside a joint", line)
            names_ = tuple(take()[0] for _ in range(int(count_text)))
            bad = [c for c in names_ if c not in _ROTATION_CHANNELS | _POSITION_CHANNELS]
            if bad:
                raise fail(f"unknown channel {bad[0]!r}", line)
            channels[stack[-1]] = names_
        elif t == "}":
            if not stack:
                raise fail("a closing brace without a joint", line)
            stack.pop()
            if not stack:
                break
        else:
            raise fail(f"unexpected {t!r} in the HIERARCHY", line)
    return BvhSkeleton(
        tuple(names), tuple(parents), np.array(offsets, dtype=np.float64), tuple(channels)
    )


def _parse_motion(
    reader: _Tokens, skeleton: BvhSkeleton, motion_line: int
) -> tuple[np.ndarray, float]:
    """The MOTION block at `motion_line` (1-based): (F, C) values and the frame time."""
    fail, lines = reader.fail, reader.lines
    header = lines[motion_line : motion_line + 2]
    try:
        count = int(header[0].split(":")[1])
        frame_time = float(header[1].split(":")[1])
    except (IndexError, ValueError):
        raise fail(
            "MOTION must be followed by 'Frames: N' and 'Frame Time: T'", motion_line + 1
        ) from None
    rows = [line.split() for line in lines[motion_line + 2 :] if line.strip()]
    if len(rows) < count or any(len(r) != skeleton.channel_count for r in rows[:count]):
        raise fail(
            f"MOTION needs {count} lines of {skeleton.channel_count} values each", motion_line + 3
        )
    try:
        motion = np.array(rows[:count], dtype=np.float64)
    except ValueError as exc:
        raise fail(f"a MOTION value is not a number ({exc})", motion_line + 3) from None
    if not (frame_time > 0 and np.isfinite(frame_time)):
        raise fail(f"Frame Time {frame_time} is not a positive number of seconds", motion_line + 2)
    return motion, frame_time


def read_bvh(path: str | Path) -> tuple[BvhSkeleton, np.ndarray, float]:
    """Read a BVH file: (skeleton, (F, C) motion values, frame time in seconds)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise BvhError(
            f"BVH file {path} cannot be read ({exc.strerror or exc}).",
            "check the path (relative paths are relative to the working directory).",
        ) from None
    return parse_bvh(text, str(path))


class BvhStreamDecoder:
    """The Axis Neuron BVH data stream: one line of channel values per frame, for a known
    hierarchy. Lines may carry Axis Neuron's prefix (an index and the avatar name); a frame ends
    at a newline or at Axis Neuron's `||` terminator, which need not be followed by one. The
    stream has no timestamps: frames get the receive time, and lines that arrive in one read (a
    burst) are spaced BURST_STEP apart so they stay distinct and ordered."""

    space = "local"
    BURST_STEP = 1e-6
    """Seconds between frames that arrived together (far below any frame interval)."""
    MAX_LINE = 1 << 16
    """Longest line kept while waiting for its newline, in bytes (a 60-joint frame is ~2 KB)."""

    def __init__(self, skeleton: BvhSkeleton) -> None:
        self.skeleton = skeleton
        self.bones: tuple[str, ...] = skeleton.names
        self.counters = DecodeCounters()
        self._buffer = bytearray()
        self._skip = False  # inside an over-long line: drop bytes until its newline
        self._indices = np.arange(len(self.bones), dtype=np.int64)
        self._last_time = -np.inf

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def reset(self) -> None:
        self._buffer.clear()
        self._skip = False

    def feed(self, data: bytes, received: float) -> list[SourceFrame]:
        self.counters.packets += 1
        self._buffer += data
        frames: list[SourceFrame] = []
        while True:
            end, size = self._line_end()
            if end < 0:
                break
            line = bytes(self._buffer[:end])
            del self._buffer[: end + size]
            if self._skip:
                self._skip = False
                continue
            frame = self.decode_line(line, max(received, self._last_time + self.BURST_STEP))
            if frame is not None:
                frames.append(frame)
                self._last_time = frame.timestamp
        if len(self._buffer) > self.MAX_LINE:
            self.counters.malformed += 1
            self._buffer.clear()
            self._skip = True
        return frames

    def _line_end(self) -> tuple[int, int]:
        """(where the first frame in the buffer ends, the terminator's length): a newline, or
        Axis Neuron's `||`, which ends a frame with or without a newline after it (a newline
        that follows is then a blank line); (-1, 0) while no frame is complete."""
        newline, bars = self._buffer.find(b"\n"), self._buffer.find(b"||")
        if bars >= 0 and (newline < 0 or bars < newline):
            return bars, 2
        return newline, 1

    def decode_line(self, line: bytes, timestamp: float) -> SourceFrame | None:
        """One line of channel values -> a frame, or None (blank, or counted as malformed)."""
        c = self.counters
        tokens = line.split()
        if not tokens:
            return None
        c.messages += 1
        n = self.skeleton.channel_count
        if len(tokens) == n + 2 and not _is_number(tokens[1]):
            tokens = tokens[2:]  # Axis Neuron's "<index> <avatar name>" prefix
        if len(tokens) != n:
            c.malformed += 1
            return None
        try:
            values = np.array([float(t) for t in tokens], dtype=np.float64)
        except ValueError:
            c.malformed += 1
            return None
        with np.errstate(invalid="ignore"):
            if not np.all(np.abs(values) <= max(MAX_ANGLE_DEGREES, MAX_POSITION)):
                c.malformed += 1  # NaN, Inf or absurd
                return None
        rotations, root = self.skeleton.pose(values[None])
        c.frames += 1
        c.samples += len(self.bones)
        return SourceFrame(0, timestamp, self._indices, rotations[0], root[0])


def _is_number(token: bytes) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True

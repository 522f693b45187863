"""Decoded live data: timestamped joint samples, decoder counters and quaternion helpers."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np

from rigspace.sdk.rotations import quat_multiply

UNIT_TOLERANCE = 1e-2
"""A received quaternion whose norm is within 1 +- this is renormalised; beyond, it is dropped as
malformed. Senders round to 6 decimals or send float32 (norm errors near 1e-6), so 1 % only
rejects data that is not a rotation (zero, scaled, garbage)."""

MAX_POSITION = 1e5
"""Largest root-position component accepted, in source units (a kilometre in metres): beyond is
an absurd value, dropped as malformed."""

MAX_ANGLE_DEGREES = 1e5
"""Largest Euler channel accepted, in degrees (BVH writers unwrap angles, so hundreds of turns
still pass; beyond is garbage)."""


@dataclass(frozen=True, slots=True)
class SourceFrame:
    """Joint samples of one source instant: some bones' rotations and maybe the root position
    (a source's frame; the engine's rendered frame is rigspace.runtime.engine.Frame).

    Rotations are unit quaternions (w, x, y, z) in the source's right-handed frame (decoders
    convert handedness at the edge); `space` on the decoder says whether they are local (relative
    to the parent bone) or world orientations.
    """

    stream: int
    """Clock domain: samples of one stream share a clock (one per device of a multi-device
    source); ordering and clock mapping are per stream."""
    timestamp: float
    """Source time in seconds (the sender's clock), or the receive time where the protocol has
    no timestamps."""
    indices: np.ndarray
    """(k,) int64 indices into the decoder's `bones`."""
    rotations: np.ndarray
    """(k, 4) float64 unit quaternions (w, x, y, z)."""
    root_position: np.ndarray | None = None
    """(3,) float64 root position in source units, or None when the frame carries none."""
    weights: dict[str, float] | None = None
    """Blend shape weights the frame applies, by the source's names (VMC /VMC/Ext/Blend/Val,
    applied by /VMC/Ext/Blend/Apply); None when it carries none. A weight holds until the
    source sends another value for that name."""


@dataclass
class DecodeCounters:
    """What a decoder saw; malformed input is counted here and dropped, never raised."""

    packets: int = 0
    """Datagrams or reads fed in."""
    messages: int = 0
    """Protocol messages parsed (OSC messages, BVH lines, x-IMU3 lines)."""
    frames: int = 0
    """Frames emitted."""
    samples: int = 0
    """Joint samples emitted (a frame of k bones counts k)."""
    malformed: int = 0
    """Messages dropped: truncated, wrong types, NaN/Inf, non-unit quaternions, absurd values."""
    ignored: int = 0
    """Well-formed messages the source does not use (blend shapes, other message types)."""
    unknown_bones: int = 0
    """Bone messages naming a bone the source does not know."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class Decoder(Protocol):
    """Sans-IO: bytes in, frames out; no sockets, no threads, never raises on input.

    A decoder whose class sets `by_sender = True` gets each datagram's source address as
    `feed(..., sender=ADDRESS)` from a UDP transport (VMC keeps senders apart)."""

    bones: tuple[str, ...]
    space: str
    """"local" (rotations relative to the parent bone) or "world" (orientation sensors)."""
    counters: DecodeCounters

    def feed(self, data: bytes, received: float) -> list[SourceFrame]:
        """Frames completed by `data`, received at local monotonic time `received`."""
        ...

    def reset(self) -> None:
        """Forget partial input (after a reconnect the next bytes start a new stream)."""
        ...


def unit_quaternions(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(k, 4) -> (normalised (k, 4), valid (k,) mask): finite and of norm 1 within UNIT_TOLERANCE."""
    q = np.asarray(q, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.linalg.norm(q, axis=-1)
        ok = np.isfinite(norm) & (np.abs(norm - 1.0) <= UNIT_TOLERANCE)
    safe = np.where(ok, norm, 1.0)
    return np.where(ok[:, None], q / safe[:, None], 0.0), ok


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Inverse of unit quaternions (w, x, y, z)."""
    return np.asarray(q) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical interpolation between unit quaternions a and b (..., 4) along the short arc."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None] if np.ndim(t) else np.float64(t)
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    near = sin < 1e-6  # nearly equal: lerp is exact to rounding and avoids 0/0
    safe = np.where(near, 1.0, sin)
    wa = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    wb = np.where(near, t, np.sin(t * theta) / safe)
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle in radians between unit quaternions a and b (q and -q are one rotation)."""
    dot = np.abs(np.sum(np.asarray(a) * np.asarray(b), axis=-1))
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0))


_AXIS = {"X": 1, "Y": 2, "Z": 3}


def quat_from_euler(angles_deg: np.ndarray, order: str) -> np.ndarray:
    """(..., 3) angles in degrees applied as R = R_order[0] R_order[1] R_order[2] -> (..., 4).

    BVH's convention: channels listed `Zrotation Yrotation Xrotation` mean v' = Rz Ry Rx v.
    """
    half = np.radians(np.asarray(angles_deg, dtype=np.float64)) / 2.0
    out = None
    for i, axis in enumerate(order):
        q = np.zeros((*half.shape[:-1], 4))
        q[..., 0] = np.cos(half[..., i])
        q[..., _AXIS[axis]] = np.sin(half[..., i])
        out = q if out is None else quat_multiply(out, q)
    assert out is not None
    return out

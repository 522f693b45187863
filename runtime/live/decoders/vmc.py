"""The VMC protocol (OSC over UDP, Unity conventions) decoded with python-osc, frames on OK/T.

Besides VMC's own messages, a plain OSC control message `/rigspace/control NAME VALUE` sets a
character's named control (RigspaceControlAPI) or blend shape: any OSC sender (a fader box,
a DCC's OSC out) drives a rig's controls without speaking VMC.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Hashable

import numpy as np
from pythonosc.osc_packet import OscPacket

from rigspace.runtime.live.source_frame import (
    MAX_POSITION,
    DecodeCounters,
    SourceFrame,
    unit_quaternions,
)

HUMAN_BODY_BONES = (
    "Hips", "LeftUpperLeg", "RightUpperLeg", "LeftLowerLeg", "RightLowerLeg", "LeftFoot",
    "RightFoot", "Spine", "Chest", "Neck", "Head", "LeftShoulder", "RightShoulder",
    "LeftUpperArm", "RightUpperArm", "LeftLowerArm", "RightLowerArm", "LeftHand", "RightHand",
    "LeftToes", "RightToes", "LeftEye", "RightEye", "Jaw",
    "LeftThumbProximal", "LeftThumbIntermediate", "LeftThumbDistal",
    "LeftIndexProximal", "LeftIndexIntermediate", "LeftIndexDistal",
    "LeftMiddleProximal", "LeftMiddleIntermediate", "LeftMiddleDistal",
    "LeftRingProximal", "LeftRingIntermediate", "LeftRingDistal",
    "LeftLittleProximal", "LeftLittleIntermediate", "LeftLittleDistal",
    "RightThumbProximal", "RightThumbIntermediate", "RightThumbDistal",
    "RightIndexProximal", "RightIndexIntermediate", "RightIndexDistal",
    "RightMiddleProximal", "RightMiddleIntermediate", "RightMiddleDistal",
    "RightRingProximal", "RightRingIntermediate", "RightRingDistal",
    "RightLittleProximal", "RightLittleIntermediate", "RightLittleDistal",
    "UpperChest",
)  # fmt: skip
"""Unity's HumanBodyBones in enum order (LastBone excluded): the names VMC senders use."""

ROOT = "Root"
"""The avatar root (/VMC/Ext/Root/Pos) as a bone of its own, parent of Hips."""

ROOT_POS = "/VMC/Ext/Root/Pos"
BONE_POS = "/VMC/Ext/Bone/Pos"
OK = "/VMC/Ext/OK"
BLEND_VAL = "/VMC/Ext/Blend/Val"
BLEND_APPLY = "/VMC/Ext/Blend/Apply"
MAX_BLEND_NAMES = 256
"""Distinct blend shape names a sender may name (ARKit has 52, VRM presets 18): a flood of
invented names is counted as malformed instead of growing memory."""
MAX_BLEND_WEIGHT = 10.0
"""Largest blend shape weight magnitude accepted: ARKit's and VRM's are in [0, 1] and rigs
overdrive a shape to 2 at most, so a weight beyond 10 is garbage (1e30 turned the network's
output into NaN), counted as malformed like NaN. Within it, the runtime clamps each weight
into its shape's range (binding.WEIGHT_RANGE, or the capture ring's blendShapeRanges)."""
CONTROL = "/rigspace/control"
MAX_CONTROL_VALUE = 1e6
"""Largest control value magnitude accepted: a control's units are its own (degrees, cm, a
0-1 slider), so the bound only stops garbage (NaN, Inf, 1e30); within it the runtime clamps
each value into its control's range (RigspaceControlAPI range)."""
TIME = "/VMC/Ext/T"
MAX_SENDERS = 8
"""Senders (source addresses) whose frames are assembled apart at once; one more forgets the one
heard from least recently (a flood from many ports cannot grow memory)."""

_NUMBER = (float, int)


class _QuietPythonOsc(logging.Filter):
    """Drops python-osc's per-packet warnings: it logs every malformed datagram to the root
    logger (logging.warning), so a flood of garbage would flood the log; the decoder counts
    them as malformed instead."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "pythonosc" not in record.pathname


if not any(isinstance(f, _QuietPythonOsc) for f in logging.getLogger().filters):
    logging.getLogger().addFilter(_QuietPythonOsc())


def unity_to_right_handed(pos: np.ndarray, quat_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unity (left-handed, Y up) -> right-handed Y up: position (x, y, -z), quaternion
    (-x, -y, z, w) (mirroring Z flips the rotation's X and Y axis components); returns
    positions (..., 3) and quaternions (..., 4) in (w, x, y, z) order."""
    p = np.asarray(pos, dtype=np.float64) * np.array([1.0, 1.0, -1.0])
    q = np.asarray(quat_xyzw, dtype=np.float64)
    return p, np.stack([q[..., 3], -q[..., 0], -q[..., 1], q[..., 2]], axis=-1)


class VmcDecoder:
    """VMC datagrams -> frames of local bone rotations (right-handed, metres).

    A VMC frame spans several datagrams (Root alone, the bones in a bundle that fragments, blend
    shapes apart), so bone values collect until /VMC/Ext/OK or /VMC/Ext/T closes the frame. Once
    a sender has sent T, only T closes frames and its value is the frame's timestamp (the
    sender's clock); senders without T get the receive time. Packets are parsed with python-osc's
    OscPacket, never its dispatcher, so a bundle's future timetag cannot stall the receiver.

    Root motion (one rule, whichever the sender moves): the hips' position in the sender's
    space, Root/Pos's position plus Root's rotation applied to the Hips Bone/Pos position (its
    local offset). A sender that moves the avatar root (Root/Pos) and one that moves the hips
    bone with Root fixed (as Unity-based senders do) both move the character; other bones'
    positions are not used (retargeting takes rotations). A value with NaN or Inf is malformed
    where it arrives (counted; the bone's last good value in the frame stays).

    Several senders (source addresses, `feed(..., sender=)`) are assembled apart, each its own
    clock domain: a second sender's /VMC/Ext/T closes none of the first's frames, and a jump of
    its clock starts only its own clock over in the buffer.
    """

    space = "local"
    by_sender = True
    """The transport passes each datagram's source address (`feed(..., sender=)`)."""

    def __init__(self, bones: tuple[str, ...] = HUMAN_BODY_BONES) -> None:
        self.bones: tuple[str, ...] = (ROOT, *bones)
        self._index = {name: i for i, name in enumerate(self.bones)}
        self.counters = DecodeCounters()
        self._hips = self._index["Hips"] if "Hips" in self._index else -1
        self._senders: dict[Hashable, _Sender] = {}
        """Each sender's partial frame, least recently heard first (at most MAX_SENDERS)."""
        self._blend_names: set[str] = set()

    @property
    def buffered(self) -> int:
        """Bone values waiting for their frames to close (at most one per known bone and
        sender)."""
        return sum(len(sender.pending) for sender in self._senders.values())

    def reset(self) -> None:
        for sender in self._senders.values():
            sender.pending.clear()

    def _sender(self, key: Hashable) -> _Sender:
        """The state of the sender at `key`, the most recently heard from now."""
        sender = self._senders.pop(key, None)
        if sender is None:
            slots = {s.slot for s in self._senders.values()}
            if len(self._senders) >= MAX_SENDERS:
                slots.discard(self._senders.pop(next(iter(self._senders))).slot)
            sender = _Sender(min(set(range(MAX_SENDERS)) - slots))
        self._senders[key] = sender
        return sender

    def feed(self, data: bytes, received: float, sender: Hashable = None) -> list[SourceFrame]:
        """The frames `data` completes; `sender` (the datagram's source address) keeps each
        sender's frames and clock apart."""
        c = self.counters
        c.packets += 1
        if not bundle_sizes_fit(data):
            c.malformed += 1  # python-osc would take the element's claimed size on trust
            return []
        state = self._sender(sender)
        frames: list[SourceFrame] = []
        flat = _flat_messages(data)
        if flat is None:  # nested bundles (python-osc orders them by time tag) or not OSC
            try:
                messages = OscPacket(data).messages
            except Exception:  # python-osc raises ParseError, IndexError, struct errors
                c.malformed += 1
                return []
            for timed in messages:
                self._message(state, timed.message.address, timed.message.params, received, frames)
            return frames
        for element in flat:
            fast = _bone_message(element)
            if fast is not None:  # the hot path: one struct unpack, no python-osc objects
                self._message(state, fast[0], fast[1], received, frames)
                continue
            try:
                messages = OscPacket(element).messages
            except Exception:
                c.malformed += 1
                continue
            for timed in messages:
                self._message(state, timed.message.address, timed.message.params, received, frames)
        return frames

    def _message(
        self, state: _Sender, address: str, params: list, received: float, frames: list[SourceFrame]
    ) -> None:
        """One OSC message of a sender: a bone value collected, a frame closed, or a count."""
        c = self.counters
        c.messages += 1
        if address == BONE_POS or address == ROOT_POS:
            self._bone_value(state, address, params)
        elif address == BLEND_VAL:
            if self._accept_named_value(params, MAX_BLEND_WEIGHT):
                state.blend_pending[params[0]] = float(params[1])
        elif address == BLEND_APPLY:
            state.blend_applied.update(state.blend_pending)
            state.blend_pending.clear()
        elif address == CONTROL:
            if self._accept_named_value(params, MAX_CONTROL_VALUE):
                state.blend_applied[params[0]] = float(params[1])  # applied at once: no Apply
                if not state.pending and not state.sender_time:
                    # Between frames (or from a sender that sends controls alone): a frame of
                    # its own now; inside a VMC frame, OK or T carries it.
                    self._close_into(frames, state, received)
        elif address == OK:
            if not state.sender_time:
                self._close_into(frames, state, received)
        elif address == TIME:
            if not params or type(params[0]) not in _NUMBER or not math.isfinite(params[0]):
                c.malformed += 1
                return
            state.sender_time = True
            self._close_into(frames, state, float(params[0]))
        else:
            c.ignored += 1

    def _bone_value(self, state: _Sender, address: str, params: list) -> None:
        """A Root/Pos or Bone/Pos message (name, position, quaternion) collected for the
        sender's frame, or counted as malformed or an unknown bone."""
        c = self.counters
        if (
            len(params) < 8
            or type(params[0]) is not str
            or any(type(v) not in _NUMBER for v in params[1:8])
        ):
            c.malformed += 1
            return
        if not all(math.isfinite(v) for v in params[1:8]):
            c.malformed += 1  # counted here: a later value in the frame would hide it
            return
        if address == ROOT_POS:
            index = 0
        else:
            index = self._index.get(params[0], -1)
            if index <= 0:  # unknown, or a bone calling itself Root
                c.unknown_bones += 1
                return
        state.pending[index] = params[1:8]

    def _accept_named_value(self, params: list, bound: float) -> bool:
        """Whether a blend shape or control message is (name, number) with the number within
        `bound` (not NaN, Inf or absurd) and a name already heard or room for one more
        (MAX_BLEND_NAMES): the name is then kept; else the message is counted as malformed."""
        if (
            len(params) < 2
            or type(params[0]) is not str
            or type(params[1]) not in _NUMBER
            or not abs(params[1]) <= bound  # NaN, Inf or absurd
            or (params[0] not in self._blend_names and len(self._blend_names) >= MAX_BLEND_NAMES)
        ):
            self.counters.malformed += 1
            return False
        self._blend_names.add(params[0])
        return True

    def _close_into(self, frames: list[SourceFrame], state: _Sender, timestamp: float) -> None:
        """Close the sender's frame (`_close`) and append it to `frames` if there is one."""
        frame = self._close(state, timestamp)
        if frame is not None:
            frames.append(frame)

    def _close(self, state: _Sender, timestamp: float) -> SourceFrame | None:
        """The sender's frame of the bone values collected so far, or None if none is valid."""
        c = self.counters
        weights, state.blend_applied = state.blend_applied or None, {}
        # T's clock and the receive clock are different streams (the first frames of a sender
        # that sends T close on OK with receive times): no false clock reset between them.
        stream = 2 * state.slot + (1 if state.sender_time else 0)
        if not state.pending:
            if weights is None:
                return None
            c.frames += 1  # a face stream's frame: weights, no bones
            empty = np.zeros(0, dtype=np.int64)
            return SourceFrame(stream, timestamp, empty, np.zeros((0, 4)), None, weights)
        indices = np.fromiter(state.pending, dtype=np.int64, count=len(state.pending))
        values = np.array(list(state.pending.values()), dtype=np.float64)  # (k, 7)
        state.pending.clear()
        with np.errstate(invalid="ignore"):
            finite_pos = np.all(np.abs(values[:, :3]) <= MAX_POSITION, axis=1)
        positions, quats = unity_to_right_handed(values[:, :3], values[:, 3:7])
        quats, ok = unit_quaternions(quats)
        ok &= finite_pos
        c.malformed += int(np.count_nonzero(~ok))
        if not ok.any():
            if weights is None:
                return None
            c.frames += 1
            return SourceFrame(stream, timestamp, indices[:0], quats[:0], None, weights)
        root_position = self._root_motion(state, indices, positions, quats, ok)
        c.frames += 1
        c.samples += int(np.count_nonzero(ok))
        return SourceFrame(stream, timestamp, indices[ok], quats[ok], root_position, weights)

    def _root_motion(
        self,
        state: _Sender,
        indices: np.ndarray,
        positions: np.ndarray,
        quats: np.ndarray,
        ok: np.ndarray,
    ) -> np.ndarray | None:
        """The frame's root position by the class's rule (None when this frame moved neither
        Root nor Hips: the buffer keeps the last one)."""
        moved = False
        for k in np.flatnonzero(ok & ((indices == 0) | (indices == self._hips))):
            if indices[k] == 0:
                state.root_pose = (positions[k], quats[k])
            else:
                state.hips_offset = positions[k]
            moved = True
        if not moved:
            return None
        offset = np.zeros(3) if state.hips_offset is None else state.hips_offset
        if state.root_pose is None:
            return offset.copy()
        position, rotation = state.root_pose
        return position + _rotate(rotation, offset)


class _Sender:
    """What one sender has sent towards its next frame, and what its frames carry over."""

    __slots__ = (
        "blend_applied", "blend_pending", "hips_offset", "pending", "root_pose", "sender_time",
        "slot",
    )  # fmt: skip

    def __init__(self, slot: int) -> None:
        self.slot = slot
        """Its place among the senders (0..MAX_SENDERS-1): its streams are 2 slot (receive
        times) and 2 slot + 1 (its /VMC/Ext/T clock)."""
        self.pending: dict[int, list] = {}
        self.sender_time = False
        """Whether it has sent /VMC/Ext/T: then only T closes its frames, with T's time."""
        self.root_pose: tuple[np.ndarray, np.ndarray] | None = None
        """The last good Root/Pos (position, (w, x, y, z)), right-handed."""
        self.hips_offset: np.ndarray | None = None
        """The last good Hips Bone/Pos position (its local offset), right-handed."""
        self.blend_pending: dict[str, float] = {}
        """Blend/Val values waiting for Blend/Apply."""
        self.blend_applied: dict[str, float] = {}
        """Values applied since the last frame closed: the next frame carries them."""


BUNDLE = b"#bundle\0"


def bundle_sizes_fit(data: bytes) -> bool:
    """Whether every element of an OSC bundle (nested ones too) has a size that is positive, a
    multiple of 4 (OSC 1.0) and within its bundle; True for a plain message. python-osc slices
    an element by its claimed size without checking it against the data."""
    spans = [(0, len(data))]
    while spans:
        start, end = spans.pop()
        if data[start : start + 8] != BUNDLE:
            continue
        at = start + 16  # "#bundle\0" and the 8-byte time tag
        while at < end:
            if at + 4 > end:
                return False
            size = int.from_bytes(data[at : at + 4], "big", signed=True)
            if size <= 0 or size % 4 or at + 4 + size > end:
                return False
            spans.append((at + 4, at + 4 + size))
            at += 4 + size
    return True


_FAST_ADDRESSES = {
    (BONE_POS + "\0" * (4 - len(BONE_POS) % 4)).encode(): BONE_POS,
    (ROOT_POS + "\0" * (4 - len(ROOT_POS) % 4)).encode(): ROOT_POS,
}
"""The padded OSC address strings of the messages a frame is made of (20 bytes each)."""
_FAST_TAGS = b",sfffffff\0\0\0"
"""Their type tags as reference senders write them: a name and seven float32."""
_SEVEN = struct.Struct(">7f")


def _flat_messages(data: bytes) -> list[bytes] | None:
    """The messages of a datagram: itself, or a bundle's elements when none is a bundle
    (element sizes already checked, bundle_sizes_fit); None for nested bundles."""
    if data[:8] != BUNDLE:
        return [data]
    out, at = [], 16
    while at < len(data):
        size = int.from_bytes(data[at : at + 4], "big")
        element = data[at + 4 : at + 4 + size]
        if element[:8] == BUNDLE:
            return None
        out.append(element)
        at += 4 + size
    return out


def _bone_message(message: bytes) -> tuple[str, list] | None:
    """(address, params) of a Bone/Pos or Root/Pos message typed `,sfffffff` (what every VMC
    sender sends, 95 % of a frame's bytes), parsed with one struct unpack: about 5x faster
    than python-osc's general parser (a 60 KB bundle decoded on the receiver's thread takes the
    GIL from the frame's). None for anything else (python-osc parses it, and judges it)."""
    address = _FAST_ADDRESSES.get(message[:20])
    if address is None or message[20:32] != _FAST_TAGS:
        return None
    end = message.find(b"\0", 32)
    if end < 0:
        return None
    start = 32 + ((end - 32) // 4 + 1) * 4  # the name's padded end
    if len(message) != start + 28:
        return None
    try:
        name = message[32:end].decode("utf-8")
    except UnicodeDecodeError:
        return None
    return address, [name, *_SEVEN.unpack_from(message, start)]


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vector `v` rotated by the unit quaternion `q` (w, x, y, z)."""
    w, u = q[0], q[1:]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def encode_frame(
    bones: tuple[str, ...],
    rotations: np.ndarray,
    root_position: np.ndarray | None = None,
    root_rotation: np.ndarray | None = None,
    sender_time: float | None = None,
    positions: np.ndarray | None = None,
) -> list[bytes]:
    """One VMC frame as a reference sender sends it: Root/Pos alone, the bones in one bundle,
    then OK and (when `sender_time` is given) T. Takes right-handed (w, x, y, z) rotations and
    positions and converts them to Unity's frame (the conversion is its own inverse).
    `positions` (B, 3): each bone's local position (its offset from its parent, metres), as
    Bone/Pos carries it; None sends zeros."""
    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
    from pythonosc.osc_message_builder import build_msg

    datagrams = []
    if root_position is not None:
        q = np.array([1.0, 0.0, 0.0, 0.0]) if root_rotation is None else root_rotation
        p, (w, x, y, z) = np.asarray(root_position) * [1, 1, -1], q
        args = [ROOT, *map(float, p), float(-x), float(-y), float(z), float(w)]
        datagrams.append(build_msg(ROOT_POS, args).dgram)
    bundle = OscBundleBuilder(IMMEDIATELY)
    offsets = np.zeros((len(bones), 3)) if positions is None else np.asarray(positions, float)
    for name, (w, x, y, z), (px, py, pz) in zip(
        bones, np.asarray(rotations, dtype=np.float64), offsets * [1, 1, -1], strict=True
    ):
        args = [name, float(px), float(py), float(pz), float(-x), float(-y), float(z), float(w)]
        bundle.add_content(build_msg(BONE_POS, args))
    datagrams.append(bundle.build().dgram)
    datagrams.append(build_msg(OK, [1]).dgram)
    if sender_time is not None:
        datagrams.append(build_msg(TIME, [float(sender_time)]).dgram)
    return datagrams

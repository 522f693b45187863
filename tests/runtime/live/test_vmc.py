"""VMC decoding (python-osc packets, frames on OK/T, Unity conversion) and the UDP receiver."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pythonosc.osc_bundle_builder import OscBundleBuilder
from pythonosc.osc_message_builder import build_msg
from pythonosc.udp_client import SimpleUDPClient, UDPClient

from rigspace.runtime.live.buffer import LiveBuffer
from rigspace.runtime.live.decoders.vmc import (
    BONE_POS,
    HUMAN_BODY_BONES,
    OK,
    TIME,
    VmcDecoder,
    encode_frame,
    unity_to_right_handed,
)
from rigspace.runtime.live.sources import open_source
from rigspace.runtime.live.transports import LiveSourceError, UdpSource
from rigspace.sdk.rotations import matrix_from_quat
from tests.runtime.live.conftest import started_source, wait_for

RNG = np.random.default_rng(7)


def random_quats(n: int) -> np.ndarray:
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def feed_all(decoder: VmcDecoder, datagrams: list[bytes], received: float = 1.0) -> list:
    return [f for d in datagrams for f in decoder.feed(d, received)]


def test_unity_conversion_is_the_mirror_of_z():
    # A rotation in Unity's frame, mirrored through z = 0, must equal the converted quaternion.
    q_xyzw = np.array([0.2, -0.4, 0.3, 0.843])
    q_xyzw /= np.linalg.norm(q_xyzw)
    _, q = unity_to_right_handed(np.zeros(3), q_xyzw)
    r_unity = matrix_from_quat(np.r_[q_xyzw[3], q_xyzw[:3]])
    mirror = np.diag([1.0, 1.0, -1.0])
    np.testing.assert_allclose(matrix_from_quat(q), mirror @ r_unity @ mirror, atol=1e-12)
    p, _ = unity_to_right_handed(np.array([1.0, 2.0, 3.0]), q_xyzw)
    np.testing.assert_allclose(p, [1.0, 2.0, -3.0])


def test_frame_assembles_over_datagrams_and_closes_on_t():
    q = random_quats(len(HUMAN_BODY_BONES))
    decoder = VmcDecoder()
    first = feed_all(decoder, encode_frame(HUMAN_BODY_BONES, q, np.array([1.0, 2, 3]), None, 10.0))
    # The first frame closes on OK (T not seen yet), the next ones only on T, with T's time.
    assert len(first) == 1 and first[0].timestamp == 1.0
    frames = feed_all(decoder, encode_frame(HUMAN_BODY_BONES, q, np.array([1.0, 2, 3]), None, 10.5))
    assert len(frames) == 1 and frames[0].timestamp == 10.5
    f = frames[0]
    assert f.indices[0] == 0 and len(f.indices) == len(HUMAN_BODY_BONES) + 1
    np.testing.assert_allclose(f.root_position, [1.0, 2.0, 3.0], atol=1e-6)
    order = np.argsort(f.indices)
    np.testing.assert_allclose(np.abs(np.sum(f.rotations[order][1:] * q, axis=1)), 1.0, atol=1e-6)
    assert decoder.counters.malformed == 0 and decoder.buffered == 0


def test_malformed_messages_are_counted_and_dropped():
    decoder = VmcDecoder()
    bad = [
        b"\x00\x01garbage",  # not OSC
        build_msg(BONE_POS, ["Hips", 0.0, 0.0, 0.0, 0.0, 0.0]).dgram,  # truncated
        build_msg(BONE_POS, ["Hips", "x", 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).dgram,  # wrong type
        build_msg(BONE_POS, ["Spine", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]).dgram,  # zero quat
        build_msg(BONE_POS, ["Chest", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0]).dgram,  # non-unit
        build_msg(BONE_POS, ["Neck", 0.0, 0.0, 0.0, float("nan"), 0.0, 0.0, 1.0]).dgram,
        build_msg(BONE_POS, ["Head", 1e9, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).dgram,  # absurd
        build_msg(TIME, ["soon"]).dgram,
    ]
    unknown = build_msg(BONE_POS, ["Tail", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).dgram
    good = build_msg(BONE_POS, ["LeftHand", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).dgram
    frames = feed_all(decoder, [*bad, unknown, good, build_msg(OK, [1]).dgram])
    c = decoder.counters
    assert c.malformed == len(bad) and c.unknown_bones == 1
    assert len(frames) == 1
    assert [decoder.bones[i] for i in frames[0].indices] == ["LeftHand"]


def test_future_timetag_does_not_stall_or_reorder():
    # A bundle timetagged an hour ahead is decoded at once (no dispatcher sleeping on it).
    bundle = OscBundleBuilder(time.time() + 3600)
    bundle.add_content(build_msg(BONE_POS, ["Hips", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    bundle.add_content(build_msg(OK, [1]))
    frames = VmcDecoder().feed(bundle.build().dgram, 1.0)
    assert len(frames) == 1


osc_values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.integers(-(2**31), 2**31 - 1),
    st.text(alphabet=st.characters(min_codepoint=33, max_codepoint=126), max_size=8),
    st.sampled_from(["Hips", "LeftHand", "Tail", "Root"]),
)


@settings(max_examples=100, deadline=None)
@given(
    messages=st.lists(
        st.tuples(
            st.sampled_from([BONE_POS, "/VMC/Ext/Root/Pos", OK, TIME, "/VMC/Ext/Blend/Val", "/x"]),
            st.lists(osc_values, max_size=10),
        ),
        max_size=30,
    ),
    cut=st.integers(0, 64),
)
def test_fuzz_osc_messages(messages, cut):
    decoder = VmcDecoder()
    for address, args in messages:
        dgram = build_msg(address, args).dgram
        for data in (dgram, dgram[: len(dgram) - cut]):
            for f in decoder.feed(data, 1.0):
                assert np.all(np.isfinite(f.rotations))
                np.testing.assert_allclose(np.linalg.norm(f.rotations, axis=1), 1.0, atol=1e-9)
    assert decoder.buffered <= len(decoder.bones)


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=512))
def test_fuzz_raw_bytes(data):
    decoder = VmcDecoder()
    decoder.feed(data, 0.0)
    decoder.feed(b"#bundle\x00" + data, 0.0)
    assert decoder.counters.packets == 2


def test_udp_receiver_with_python_osc_client():
    source, buffer = started_source("vmc://127.0.0.1:0", "suit")
    assert isinstance(source, UdpSource)
    try:
        host, port = source.address
        assert host == "127.0.0.1"
        client = UDPClient(host, port)
        q = random_quats(len(HUMAN_BODY_BONES))
        for k in range(5):
            for dgram in encode_frame(HUMAN_BODY_BONES, q, np.zeros(3), None, 1.0 + k / 60):
                client._sock.sendto(dgram, (host, port))
        SimpleUDPClient(host, port).send_message(BONE_POS, ["Tail", 0.0, 0, 0, 0, 0, 0, 1.0])
        assert wait_for(lambda: source.decoder.counters.unknown_bones == 1)
        counters = source.counters()
        assert counters.status == "connected" and counters.samples == 5 * 56
        assert counters.latency_p99_ms is not None
        pose = buffer.pose()
        np.testing.assert_allclose(np.abs(np.sum(pose.rotations[1:] * q, axis=1)), 1.0, atol=1e-6)
    finally:
        source.stop()


def test_port_in_use_names_the_source_and_the_fix():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        source = open_source(f"vmc://127.0.0.1:{port}", "suit")
        with pytest.raises(LiveSourceError, match=rf"'suit'.*UDP port {port}.*in use.*Fix"):
            source.start(LiveBuffer(source.bones))


def test_a_flood_is_counted_and_bounded_and_the_receiver_keeps_going():
    source, buffer = started_source("vmc://127.0.0.1:0", "suit")
    try:
        address = source.address
        rng = np.random.default_rng(5)
        unknown = build_msg(BONE_POS, ["Tail", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).dgram
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for k in range(3000):
                s.sendto(rng.bytes(int(rng.integers(1, 1400))) if k % 2 else unknown, address)
            # Every datagram of the flood read or dropped by the kernel (its buffer full on a
            # loaded machine): the receiver has drained it, and a frame now arrives whole.
            assert wait_for(
                lambda: source.decoder.counters.packets + (source.kernel_dropped() or 0) == 3000,
                timeout=60,
            )
            q = random_quats(len(HUMAN_BODY_BONES))
            for dgram in encode_frame(HUMAN_BODY_BONES, q, np.zeros(3), None, 5.0):
                s.sendto(dgram, address)
            assert wait_for(lambda: source.decoder.counters.frames >= 1)
        c = source.decoder.counters
        assert c.malformed > 0 and c.unknown_bones > 0 and source.decoder.buffered == 0
        assert len(buffer._snapshots) <= buffer.settings.history
        assert source._threads[0].is_alive()
    finally:
        source.stop()


def _kernel_drops(sock: socket.socket) -> int:
    """The kernel's own count of datagrams it dropped for `sock`: the drops column of
    /proc/net/udp on the socket's inode line."""
    import os

    inode = str(os.fstat(sock.fileno()).st_ino)
    with open("/proc/net/udp") as table:
        for line in table:
            fields = line.split()
            if fields[9] == inode:
                return int(fields[-1])
    raise AssertionError("the socket is not in /proc/net/udp")


@pytest.mark.skipif(not Path("/proc/net/udp").exists(), reason="Linux's /proc/net/udp")
def test_datagrams_the_kernel_drops_are_counted_as_dropped():
    """A receive buffer overflowing (a tiny SO_RCVBUF, a burst while the reader is held) loses
    datagrams in the kernel before the receiver sees them: counted, as the kernel counts them."""
    source, _ = started_source("vmc://127.0.0.1:0", "suit")
    try:
        source.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        message = build_msg(BONE_POS, ["Hips", 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]).dgram
        sent = 3000
        with source._deliver_lock, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            # The receiver waits for the lock with at most one datagram read: the rest queue.
            for _ in range(sent):
                s.sendto(message, source.address)
        kernel = _kernel_drops(source.sock)
        assert kernel > sent // 2  # the burst overflowed the buffer
        assert wait_for(lambda: source.decoder.counters.packets == sent - kernel)
        counters = source.counters()
        assert counters.kernel_dropped == kernel
        assert counters.dropped == kernel + counters.duplicates + counters.out_of_order
    finally:
        source.stop()
    assert source.counters().kernel_dropped == kernel  # still reported once stopped


def test_switching_to_sender_time_is_a_new_stream_not_a_clock_reset():
    decoder = VmcDecoder()
    buffer = LiveBuffer(decoder.bones)
    q = random_quats(len(HUMAN_BODY_BONES))
    for k in range(3):  # T runs from 0 while receive times are ~1000 s
        for f in feed_all(
            decoder, encode_frame(HUMAN_BODY_BONES, q, None, None, k / 60), 1000.0 + k
        ):
            buffer.push(f, 1000.0 + k)
    assert buffer.samples == 3 * len(HUMAN_BODY_BONES)
    assert buffer.clock_resets == buffer.out_of_order == buffer.duplicates == 0


def test_sender_stops_and_restarts_stale_lost_connected():
    from rigspace.runtime.live.buffer import BufferSettings

    source = open_source("vmc://127.0.0.1:0", "suit")
    buffer = LiveBuffer(source.bones, BufferSettings(timeout=0.1, blend=0.2))
    source.start(buffer)
    q = random_quats(len(HUMAN_BODY_BONES))

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # one sender, one address

    def send(count: int, sender_time: float) -> None:
        for k in range(count):
            for d in encode_frame(HUMAN_BODY_BONES, q, None, None, sender_time + k / 60):
                sock.sendto(d, source.address)

    try:
        send(5, 100.0)
        assert wait_for(lambda: buffer.pose().status == "connected")
        assert wait_for(lambda: buffer.pose().status == "stale")
        held = buffer.pose()
        assert held.weight == 1.0 and held.valid[1:].all()  # the last pose is held
        assert wait_for(lambda: buffer.pose().status == "lost")
        assert wait_for(lambda: buffer.pose().weight == 0.0)  # blended back
        send(5, 0.0)  # the sender restarts: its clock starts again
        assert wait_for(lambda: buffer.pose().status == "connected")
        assert buffer.pose().weight == 1.0 and buffer.clock_resets == 1
    finally:
        sock.close()
        source.stop()


def _unity_sender_frame(root: tuple, hips: tuple, nan_first: bool = False) -> list[bytes]:
    """One frame as a Unity-based sender writes it, from the VMC spec (not encode_frame):
    /VMC/Ext/Root/Pos (name, p.xyz, q.xyzw), the bones' /VMC/Ext/Bone/Pos in one bundle (Hips
    with its local position: where such senders put root motion), /VMC/Ext/OK."""
    identity = [0.0, 0.0, 0.0, 1.0]
    dgrams = [build_msg("/VMC/Ext/Root/Pos", ["root", *map(float, root), *identity]).dgram]
    bundle = OscBundleBuilder(0)  # timetag 0 (spec: "immediately")
    if nan_first:  # a bad value the next message of the same frame overwrites
        bundle.add_content(build_msg(BONE_POS, ["Hips", float("nan"), 0.0, 0.0, *identity]))
    bundle.add_content(build_msg(BONE_POS, ["Hips", *map(float, hips), *identity]))
    bundle.add_content(build_msg(BONE_POS, ["Spine", 0.0, 0.1, 0.0, *identity]))
    dgrams.append(bundle.build().dgram)
    dgrams.append(build_msg("/VMC/Ext/OK", [1]).dgram)
    return dgrams


def test_root_motion_follows_the_hips_bone_when_the_sender_keeps_root_still():
    decoder = VmcDecoder()
    roots = []
    for k, (x, y) in enumerate([(0.0, 0.98), (0.5, 1.20), (1.0, 0.98)]):  # travel and a hop
        frames = []
        for dgram in _unity_sender_frame((0.0, 0.0, 0.0), (x, y, 0.25)):
            frames += decoder.feed(dgram, float(k))
        (frame,) = frames
        roots.append(frame.root_position)
    # Right-handed: Unity's z mirrored; the hips' travel and its 22 cm hop both arrive.
    np.testing.assert_allclose(roots, [[0.0, 0.98, -0.25], [0.5, 1.2, -0.25], [1.0, 0.98, -0.25]])


def test_root_motion_of_a_sender_that_moves_root_is_unchanged_by_a_still_hips_offset():
    decoder = VmcDecoder()
    for k, x in enumerate([0.0, 2.0]):
        frames = [
            f
            for d in _unity_sender_frame((x, 0.0, 0.0), (0.0, 0.98, 0.0))
            for f in decoder.feed(d, k)
        ]
    assert frames[0].root_position == pytest.approx([2.0, 0.98, 0.0])


def test_a_nan_value_overwritten_within_its_frame_is_still_counted():
    decoder = VmcDecoder()
    frames = [
        f
        for d in _unity_sender_frame((0, 0, 0), (0, 1, 0), nan_first=True)
        for f in decoder.feed(d, 0.0)
    ]
    assert decoder.counters.malformed == 1
    assert frames[0].root_position == pytest.approx([0.0, 1.0, 0.0])  # the good value stays


def test_a_bundle_element_claiming_more_bytes_than_it_has_is_malformed():
    """From the OSC 1.0 spec: a bundle element is an int32 size then that many bytes."""
    import struct

    bundle = OscBundleBuilder(0)
    bundle.add_content(build_msg(BONE_POS, ["Hips", 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    good = bundle.build().dgram
    decoder = VmcDecoder()
    decoder.feed(good, 0.0)
    assert decoder.counters.malformed == 0 and decoder.buffered == 1
    for size in (0x7FFFFFFF, 3, -4, 0):
        bad = good[:16] + struct.pack(">i", size) + good[20:]
        decoder.feed(bad, 0.0)
    assert decoder.counters.malformed == 4
    nested = OscBundleBuilder(0)
    nested.add_content(bundle.build())
    outer = nested.build().dgram
    decoder.feed(outer[:36] + struct.pack(">i", 10**6) + outer[40:], 0.0)  # the inner one's
    assert decoder.counters.malformed == 5


@settings(max_examples=200, deadline=None)
@given(
    name=st.text(max_size=40).filter(lambda t: "\0" not in t),
    values=st.lists(st.floats(width=32, allow_nan=False), min_size=7, max_size=7),
    root=st.booleans(),
)
def test_the_fast_bone_parser_reads_what_python_osc_reads(name, values, root):
    from pythonosc.osc_packet import OscPacket

    from rigspace.runtime.live.decoders.vmc import ROOT_POS, _bone_message

    message = build_msg(ROOT_POS if root else BONE_POS, [name, *values]).dgram
    (timed,) = OscPacket(message).messages
    assert _bone_message(message) == (timed.message.address, timed.message.params)
    assert _bone_message(message[:-4]) is None  # truncated: left to python-osc, which judges
    other = build_msg(BONE_POS, [name, *values[:6], 1]).dgram  # an int among the floats
    assert _bone_message(other) is None


def test_a_large_bundle_decodes_the_same_on_the_fast_path_as_through_python_osc():
    bundle = OscBundleBuilder(0)
    for k in range(20):
        for name in HUMAN_BODY_BONES:
            q = [0.0, 0.0, float(np.sin(0.05 * k)), float(np.cos(0.05 * k))]  # x, y, z, w
            bundle.add_content(build_msg(BONE_POS, [name, 0.0, 1.0, 0.0, *q]))
    bundle.add_content(build_msg(OK, [1]))
    data = bundle.build().dgram
    assert len(data) > 60_000
    (fast,) = VmcDecoder().feed(data, 0.0)
    slow_decoder = VmcDecoder()
    nested = OscBundleBuilder(0)  # nested: the python-osc path
    nested.add_content(bundle.build())
    (slow,) = slow_decoder.feed(nested.build().dgram, 0.0)
    np.testing.assert_array_equal(fast.indices, slow.indices)
    np.testing.assert_array_equal(fast.rotations, slow.rotations)


def _osc(address: str, *args) -> bytes:
    from pythonosc.osc_message_builder import build_msg

    return build_msg(address, list(args)).dgram


def test_blend_shape_values_apply_on_blend_apply_and_travel_with_the_frame():
    """VMC's face messages (the protocol's spec: Blend/Val name value, repeated, then one
    Blend/Apply): values wait for Apply, the frame that closes next carries them, a frame with
    weights and no bones is still a frame, bad values are malformed."""
    decoder = VmcDecoder()
    assert decoder.feed(_osc("/VMC/Ext/Blend/Val", "jawOpen", 0.7), 1.0) == []
    (frame,) = decoder.feed(_osc("/VMC/Ext/OK", 1), 1.0) or [None]  # not applied yet: none
    assert frame is None
    for d in (_osc("/VMC/Ext/Blend/Val", "Blink", 1.0), _osc("/VMC/Ext/Blend/Apply")):
        assert decoder.feed(d, 1.0) == []
    (frame,) = decoder.feed(_osc("/VMC/Ext/OK", 1), 1.0)
    assert frame.weights == {"jawOpen": pytest.approx(0.7), "Blink": 1.0}  # float32 on the wire
    assert len(frame.indices) == 0
    # Bones and weights in one frame; the weights are only the ones applied since.
    for d in (
        _osc("/VMC/Ext/Bone/Pos", "Head", 0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 1.0),
        _osc("/VMC/Ext/Blend/Val", "jawOpen", 0.2),
        _osc("/VMC/Ext/Blend/Apply"),
    ):
        decoder.feed(d, 2.0)
    (frame,) = decoder.feed(_osc("/VMC/Ext/OK", 1), 2.0)
    assert frame.weights == {"jawOpen": pytest.approx(0.2)} and len(frame.indices) == 1
    before = decoder.counters.malformed
    for bad in (
        _osc("/VMC/Ext/Blend/Val", "jawOpen", float("nan")),
        _osc("/VMC/Ext/Blend/Val", "jawOpen"),
        _osc("/VMC/Ext/Blend/Val", 3, 0.5),
    ):
        decoder.feed(bad, 3.0)
    assert decoder.counters.malformed == before + 3
    for k in range(300):  # invented names: bounded
        decoder.feed(_osc("/VMC/Ext/Blend/Val", f"shape{k}", 0.5), 4.0)
    assert decoder.counters.malformed == before + 3 + (300 - (256 - 2))  # 2 names known


def _turned_frame(degrees: float, t: float) -> list[bytes]:
    """One frame as a VMC sender writes it, from the protocol with python-osc's builders (not
    encode_frame): Root/Pos at the origin, Hips (0.95 m up) turned `degrees` about Unity's Y in
    a bundle, /VMC/Ext/OK, then /VMC/Ext/T `t`."""
    h = np.radians(degrees) / 2
    root = build_msg("/VMC/Ext/Root/Pos", ["root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).dgram
    bundle = OscBundleBuilder(0)
    bundle.add_content(
        build_msg(BONE_POS, ["Hips", 0.0, 0.95, 0.0, 0.0, np.sin(h), 0.0, np.cos(h)])
    )
    return [root, bundle.build().dgram, build_msg(OK, [1]).dgram, build_msg(TIME, [t]).dgram]


def _hips_degrees(pose) -> float:
    """The Hips' turn about Y (degrees) in a pose (Unity's Y turn, mirrored: -Y right-handed)."""
    w, _, y, _ = pose.rotations[1]  # bones[1] is Hips (Root first)
    return float(np.degrees(2 * np.arctan2(-y, w)))


def _send_and_wait(source, buffer, sock: socket.socket, datagrams: list[bytes]) -> None:
    """Send one frame's datagrams and wait until the buffer has the frame."""
    before = buffer.samples
    for dgram in datagrams:
        sock.sendto(dgram, source.address)
    assert wait_for(lambda: buffer.samples > before)


@pytest.mark.parametrize("same_address", [False, True], ids=["new process", "same port"])
def test_after_a_sender_restarts_every_reader_follows_the_new_stream(same_address):
    """A sender restarted (a new process whose /VMC/Ext/T starts again at 0, or one that binds
    the same port again): the pose now (`pose`) and the pose at a time (`pose_at`, what a take
    records) both show the new sender's frames, never the old stream's."""
    source, buffer = started_source("vmc://127.0.0.1:0", "suit")
    try:
        first = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        first.bind(("127.0.0.1", 0))
        for k in range(90):  # 1.5 s of the first sender's clock, its frames turned 0..89 deg
            _send_and_wait(source, buffer, first, _turned_frame(k, k / 60))
        address = first.getsockname()
        first.close()
        second = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        second.bind(address if same_address else ("127.0.0.1", 0))
        with second:
            for k in range(30):  # the new sender's clock from 0, its frames turned 120 + k
                _send_and_wait(source, buffer, second, _turned_frame(120 + k, k / 60))
                now = time.monotonic()
                assert _hips_degrees(buffer.pose(now)) == pytest.approx(120 + k, abs=1e-3)
                assert _hips_degrees(buffer.pose_at(now)) == pytest.approx(120 + k, abs=1e-3)
    finally:
        source.stop()


ABSURD_CLOCKS = (1e12, -1e12, 3e38, 0.0)


def test_a_second_senders_absurd_clocks_do_not_spoil_the_first_senders_stream():
    """Four well-formed /VMC/Ext/T datagrams with absurd times from another sender, one of them
    between the first sender's bone bundle and its own T: every later frame of the first sender
    is what `pose` and `pose_at` give, the hips where it puts them."""
    source, buffer = started_source("vmc://127.0.0.1:0", "suit")
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for k in range(120):
            frame = _turned_frame(k % 90, 2.0 + k / 60)
            if k in (60, 70, 80, 90):  # the other sender, between this frame's bones and its T
                packets = source.decoder.counters.packets
                for dgram in frame[:2]:
                    sender.sendto(dgram, source.address)
                other.sendto(build_msg(TIME, [ABSURD_CLOCKS[(k - 60) // 10]]).dgram, source.address)
                assert wait_for(lambda p=packets: source.decoder.counters.packets == p + 3)
                frame = frame[2:]
            _send_and_wait(source, buffer, sender, frame)
            now = time.monotonic()
            for pose in (buffer.pose(now), buffer.pose_at(now)):
                assert _hips_degrees(pose) == pytest.approx(k % 90, abs=1e-3), k
                np.testing.assert_allclose(pose.root_position, [0.0, 0.95, 0.0], atol=1e-6)
    finally:
        sender.close()
        other.close()
        source.stop()


def test_a_senders_own_clock_jumps_start_its_clock_over():
    """One sender whose /VMC/Ext/T jumps to absurd values and back: its clock is trusted only
    while it is plausible, so each jump starts its clock over and every frame is followed."""
    source, buffer = started_source("vmc://127.0.0.1:0", "suit")
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            for k in range(120):
                t = ABSURD_CLOCKS[(k - 60) // 10] if k in (60, 70, 80, 90) else 2.0 + k / 60
                _send_and_wait(source, buffer, sender, _turned_frame(k % 90, t))
                now = time.monotonic()
                for pose in (buffer.pose(now), buffer.pose_at(now)):
                    assert _hips_degrees(pose) == pytest.approx(k % 90, abs=1e-3), k
        assert buffer.clock_resets >= 7  # to each absurd clock and back (0.0: back only)
    finally:
        source.stop()


def test_an_absurd_blend_weight_is_malformed_and_one_out_of_range_passes_to_be_clamped():
    """/VMC/Ext/Blend/Val with a finite but absurd weight (1e30: no rig's) is malformed like NaN;
    5.0 and -3.0 are weights, passed on for the runtime to clamp into the shape's range."""
    decoder = VmcDecoder()
    for name, value in (("jawOpen", 1e30), ("mouthSmileLeft", 5.0), ("eyeBlinkLeft", -3.0)):
        decoder.feed(_osc("/VMC/Ext/Blend/Val", name, value), 1.0)
    decoder.feed(_osc("/VMC/Ext/Blend/Apply"), 1.0)
    (frame,) = decoder.feed(_osc("/VMC/Ext/OK", 1), 1.0)
    assert frame.weights == {"mouthSmileLeft": 5.0, "eyeBlinkLeft": -3.0}
    assert decoder.counters.malformed == 1


def test_a_plain_osc_control_message_applies_at_once_and_is_checked():
    """`/rigspace/control NAME VALUE` (any OSC sender, no VMC framing): between frames it is a
    frame of its own at once; inside a VMC frame the frame's OK carries it; its values are
    checked like Blend/Val's, with a bound that fits a control's own units."""
    decoder = VmcDecoder()
    (frame,) = decoder.feed(_osc("/rigspace/control", "bulge", 0.5), 1.0)
    assert frame.weights == {"bulge": 0.5} and len(frame.indices) == 0 and frame.timestamp == 1.0
    (frame,) = decoder.feed(_osc("/rigspace/control", "twist", -45), 1.5)  # an int, degrees
    assert frame.weights == {"twist": -45.0}
    decoder.feed(_osc("/VMC/Ext/Bone/Pos", "Head", 0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 1.0), 2.0)
    assert decoder.feed(_osc("/rigspace/control", "bulge", 0.75), 2.0) == []  # inside a frame
    (frame,) = decoder.feed(_osc("/VMC/Ext/OK", 1), 2.0)
    assert frame.weights == {"bulge": 0.75} and len(frame.indices) == 1
    before = decoder.counters.malformed
    for bad in (
        _osc("/rigspace/control", "bulge", float("nan")),
        _osc("/rigspace/control", "bulge", 1e30),
        _osc("/rigspace/control", "bulge"),
        _osc("/rigspace/control", 3, 0.5),
    ):
        assert decoder.feed(bad, 3.0) == []
    assert decoder.counters.malformed == before + 4

"""x-IMU3 quaternion lines through pyserial: loop:// and a pty pair."""

from __future__ import annotations

import os
import tty

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rigspace.runtime.live.buffer import LiveBuffer
from rigspace.runtime.live.decoders.ximu3 import Ximu3Decoder
from rigspace.runtime.live.sources import open_source
from rigspace.runtime.live.transports import LiveSourceError, SerialSource
from tests.runtime.live.conftest import started_source, wait_for


def q_lines(ticks: list[int], quats: np.ndarray) -> bytes:
    return b"".join(
        f"Q,{t},{w:.6f},{x:.6f},{y:.6f},{z:.6f}\r\n".encode()
        for t, (w, x, y, z) in zip(ticks, quats, strict=True)
    )


QUATS = np.array([[0.850093, -0.040743, -0.524145, -0.034592], [1.0, 0.0, 0.0, 0.0]])


def test_decoder_reads_q_lines_ignores_other_messages_and_counts_bad_ones():
    decoder = Ximu3Decoder(("pelvis", "thigh_l"))
    data = q_lines([917418209, 917438268], QUATS)
    data += b"I,917438270,0.1,0.2,0.3,0.0,0.0,1.0\r\n"  # inertial: ignored
    bad = [b"Q,1,0,0,0,0\r\n", b"Q,2,1,0,0\r\n", b"Q,x,1,0,0,0\r\n", b"Q,3,nan,0,0,0\r\n"]
    bad += [b"Q,-4,1,0,0,0\r\n", b"hello world\r\n"]
    frames = decoder.feed(data + b"".join(bad), 0.0, channel=1)
    assert [f.timestamp for f in frames] == pytest.approx([917.418209, 917.438268])
    assert all(f.stream == 1 and list(f.indices) == [1] for f in frames)
    np.testing.assert_allclose(frames[0].rotations[0], QUATS[0] / np.linalg.norm(QUATS[0]))
    assert decoder.counters.ignored == 1 and decoder.counters.malformed == len(bad)


@settings(max_examples=150, deadline=None)
@given(chunks=st.lists(st.binary(max_size=200), max_size=20))
def test_fuzz(chunks):
    decoder = Ximu3Decoder(("a", "b"))
    for i, chunk in enumerate(chunks):
        for f in decoder.feed(chunk, 0.0, channel=i % 2):
            assert np.all(np.isfinite(f.rotations)) and f.timestamp >= 0
        assert decoder.buffered <= 2 * (Ximu3Decoder.MAX_LINE + 200)


def test_loop_url_end_to_end():
    source, buffer = started_source("serial://loop://?baud=115200&format=ximu3&bones=pelvis", "imu")
    assert isinstance(source, SerialSource)
    try:
        source.ports[0].write(q_lines([1000, 21000], QUATS))
        assert wait_for(lambda: buffer.samples == 2)
        pose = buffer.pose()
        np.testing.assert_allclose(pose.rotations[0], QUATS[1], atol=1e-9)
        assert source.space == "world" and pose.status == "connected"
    finally:
        source.stop()


def test_two_sensors_on_a_pty_pair_each():
    pairs = [os.openpty() for _ in range(2)]
    for _, follower in pairs:
        tty.setraw(follower)
    devices = ",".join(os.ttyname(f) for _, f in pairs)
    source, buffer = started_source(f"serial://{devices}?format=ximu3&bones=thigh_l,calf_l", "legs")
    try:
        # Each device has its own clock: stream 1's timestamps are far behind stream 0's.
        os.write(pairs[0][0], q_lines([5_000_000, 5_020_000], QUATS))
        os.write(pairs[1][0], q_lines([10, 20_010], QUATS[::-1]))
        assert wait_for(lambda: buffer.samples == 4)
        pose = buffer.pose()
        assert pose.valid.all() and buffer.out_of_order == 0
        np.testing.assert_allclose(pose.rotations, [QUATS[1], QUATS[0] / np.linalg.norm(QUATS[0])])
    finally:
        source.stop()
        for leader, follower in pairs:
            os.close(leader)
            os.close(follower)


def test_missing_device_and_bad_options_name_the_fix():
    source = open_source("serial:///dev/rigspace-no-such-tty?format=ximu3", "imu")
    with pytest.raises(LiveSourceError, match=r"'imu'.*no-such-tty.*cannot be opened.*Fix: plug"):
        source.start(LiveBuffer(source.bones))
    with pytest.raises(LiveSourceError, match="2 devices but 1 bones"):
        open_source("serial://loop://,loop://?bones=a", "imu")
    with pytest.raises(LiveSourceError, match="format 'csv'"):
        open_source("serial://loop://?format=csv", "imu")
    with pytest.raises(LiveSourceError, match="unknown option 'baudd'"):
        open_source("serial://loop://?baudd=9600", "imu")

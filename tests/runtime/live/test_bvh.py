"""BVH hierarchies with mixed rotation orders, the BVH line stream, and the reconnecting TCP client."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rigspace.runtime.live.decoders.bvh import BvhError, BvhStreamDecoder, parse_bvh, read_bvh
from rigspace.runtime.live.sources import open_source
from rigspace.runtime.live.transports import LiveSourceError
from rigspace.sdk.rotations import matrix_from_quat
from tests.conftest import axis_rotations
from tests.runtime.live.conftest import CMU_CLIP, started_source, wait_for


@pytest.fixture(scope="module")
def cmu():
    return read_bvh(CMU_CLIP)


def test_cmu_clip_parses_with_mixed_orders(cmu):
    skeleton, motion, frame_time = cmu
    assert len(skeleton.names) == 31 and motion.shape == (994, 96)
    assert frame_time == pytest.approx(1 / 120, rel=1e-3)
    orders = {"".join(c[0] for c in ch if c.endswith("rotation")) for ch in skeleton.channels if ch}
    assert orders == {"ZYX", "ZXY"}
    assert skeleton.names[skeleton.parents[skeleton.names.index("LeftElbow")]] == "LeftShoulder"


def test_rotations_match_matrices_in_channel_order(cmu):
    # Independent reference: each joint's channel matrices multiplied in the order listed.
    skeleton, motion, _ = cmu
    rotations, root = skeleton.pose(motion[::97])
    column = 0
    for j, channels in enumerate(skeleton.channels):
        expected = np.broadcast_to(np.eye(3), (len(rotations), 3, 3))
        for k, channel in enumerate(channels):
            if channel.endswith("rotation"):
                expected = expected @ axis_rotations(channel[0], motion[::97, column + k])
        column += len(channels)
        np.testing.assert_allclose(matrix_from_quat(rotations[:, j]), expected, atol=1e-12)
    np.testing.assert_allclose(root, motion[::97, :3])


def test_bad_bvh_names_file_and_line(tmp_path):
    path = tmp_path / "bad.bvh"
    path.write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 zero\n}\n")
    with pytest.raises(BvhError, match=r"bad.bvh, line 4: OFFSET value 'zero'"):
        read_bvh(path)
    with pytest.raises(BvhError, match="cannot be read"):
        read_bvh(tmp_path / "missing.bvh")
    with pytest.raises(BvhError, match="Rotation"):
        parse_bvh("HIERARCHY\nROOT a\n{\nCHANNELS 1 Rotation\n}\n")


def clip_lines(motion: np.ndarray, frames: range) -> list[bytes]:
    return [(" ".join(f"{v:.4f}" for v in motion[i]) + "\n").encode() for i in frames]


def test_stream_decodes_lines_split_anywhere_and_axis_neuron_prefix(cmu):
    skeleton, motion, _ = cmu
    decoder = BvhStreamDecoder(skeleton)
    data = b"".join(clip_lines(motion, range(10)))
    data += b"0 Avatar00 " + clip_lines(motion, range(10, 11))[0].rstrip() + b" ||\n"
    frames = []
    for start in range(0, len(data), 37):  # TCP splits lines anywhere
        frames += decoder.feed(data[start : start + 37], float(start))
    assert len(frames) == 11
    expected, _ = skeleton.pose(np.round(motion[:11], 4))
    np.testing.assert_allclose(np.stack([f.rotations for f in frames]), expected, atol=1e-12)
    assert decoder.counters.malformed == 0


def test_stream_frames_ended_by_the_axis_neuron_terminator_alone_decode(cmu):
    """Axis Neuron ends each frame with `||`, not always followed by a newline: every frame
    decodes, whether `||` ends the read, is split across reads or is followed by CR LF."""
    skeleton, motion, _ = cmu
    decoder = BvhStreamDecoder(skeleton)
    frames = [b"0 Avatar00 " + line.rstrip() + b" ||" for line in clip_lines(motion, range(6))]
    frames[4] += b"\r\n"  # some versions end the terminator's line too
    data = b"".join(frames)
    got = decoder.feed(data[:-1], 0.0)  # the last frame's terminator cut in two
    assert len(got) == 5 and decoder.counters.malformed == 0
    got += decoder.feed(data[-1:], 1.0)
    assert len(got) == 6 and decoder.counters.malformed == 0
    expected, _ = skeleton.pose(np.round(motion[:6], 4))
    np.testing.assert_allclose(np.stack([f.rotations for f in got]), expected, atol=1e-12)
    assert decoder.buffered == 0


def test_stream_counts_malformed_lines(cmu):
    skeleton, motion, _ = cmu
    decoder = BvhStreamDecoder(skeleton)
    good = clip_lines(motion, range(1))[0]
    bad = [
        good[: len(good) // 2] + b"\n",  # truncated
        good.replace(b" ", b" x", 1),  # not a number
        b"nan " + good.split(b" ", 1)[1],
        b"1e9 " + good.split(b" ", 1)[1],  # absurd
        b"7" * (BvhStreamDecoder.MAX_LINE + 10) + b"\n",  # over-long line
    ]
    frames = [f for line in [*bad, good] for f in decoder.feed(line, 0.0)]
    assert len(frames) == 1 and decoder.counters.malformed == len(bad)
    assert decoder.buffered == 0


@settings(max_examples=150, deadline=None)
@given(chunks=st.lists(st.binary(max_size=300), max_size=20), keep=st.integers(0, 3))
def test_fuzz_stream(cmu, chunks, keep):
    skeleton, motion, _ = cmu
    decoder = BvhStreamDecoder(skeleton)
    good = clip_lines(motion, range(keep))
    for chunk in [*chunks, *good]:
        for f in decoder.feed(chunk, 0.0):
            assert np.all(np.isfinite(f.rotations))
        assert decoder.buffered <= BvhStreamDecoder.MAX_LINE


def serve_lines(server: socket.socket, lines: list[bytes], done: threading.Event) -> None:
    conn, _ = server.accept()
    with conn:
        conn.sendall(b"".join(lines))
        done.wait(60)  # until the test has read the lines (a bound, never waited out)


def test_tcp_client_reads_and_reconnects(cmu, free_tcp_port):
    _, motion, _ = cmu
    url = f"bvh+tcp://127.0.0.1:{free_tcp_port}?skeleton={CMU_CLIP}&retry=0.05"
    source, buffer = started_source(url, "neuron")  # nothing listens yet: the client keeps trying
    try:
        assert wait_for(lambda: source.error is not None)
        server = socket.create_server(("127.0.0.1", free_tcp_port))
        for round_ in range(2):
            done = threading.Event()
            thread = threading.Thread(
                target=serve_lines, args=(server, clip_lines(motion, range(5)), done)
            )
            thread.start()
            assert wait_for(lambda r=round_: buffer.samples >= 31 * 5 * (r + 1))
            done.set()  # the server closes the connection: the client reconnects
            thread.join()
        assert source.reconnects == 1 and source.decoder.counters.frames == 10
        server.close()
    finally:
        source.stop()


def test_bvh_tcp_needs_a_skeleton(tmp_path):
    with pytest.raises(LiveSourceError, match=r"'n'.*skeleton=FILE.bvh"):
        open_source("bvh+tcp://127.0.0.1:7001", "n")
    with pytest.raises(LiveSourceError, match=r"nope\.bvh cannot be read"):
        open_source(f"bvh+tcp://127.0.0.1:7001?skeleton={tmp_path}/nope.bvh", "n")

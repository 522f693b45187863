"""The rigspace.sources plugin kind: discovery by scheme, clear errors, and the replay source."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rigspace.runtime.live.buffer import LiveBuffer
from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.runtime.live.sources import open_source
from rigspace.runtime.live.transports import LiveSourceError, ReplaySource
from rigspace.sdk.plugins import SOURCES, SourceSpec, discover
from tests.runtime.live.conftest import CMU_CLIP, started_source, wait_for


def test_built_in_sources_come_from_entry_points():
    found = discover(SOURCES)  # what open_source looks a scheme up in
    assert {"vmc", "bvh+tcp", "serial", "replay"} <= set(found.specs)
    assert all(isinstance(s, SourceSpec) and s.doc for s in found)


def test_unknown_scheme_names_the_url_and_the_known_schemes():
    with pytest.raises(LiveSourceError) as err:
        open_source("osc://127.0.0.1:9000", "suit")
    text = str(err.value)
    assert "'suit' (osc://127.0.0.1:9000)" in text and "scheme 'osc'" in text
    assert "vmc://" in text and "replay://" in text
    with pytest.raises(LiveSourceError, match="without scheme://"):
        open_source("127.0.0.1:9000", "suit")


def test_extra_plugins_and_failed_plugins():
    made = []
    fake = SourceSpec("fake", lambda url, name: made.append((url, name)) or "source", "fake://")

    def broken():
        raise ImportError("No module named 'mido'")

    extra = {"fake": lambda: fake, "midi": broken}
    assert open_source("fake://x", "pad", extra=extra) == "source"
    assert made == [("fake://x", "pad")]
    with pytest.raises(LiveSourceError, match=r"'midi' source plugin failed.*mido"):
        open_source("midi://", "pad", extra=extra)


def test_replay_plays_the_clip_in_order_at_speed():
    skeleton, motion, frame_time = read_bvh(CMU_CLIP)
    source = open_source(f"replay://{CMU_CLIP}?speed=20&loop=0", "take")
    assert isinstance(source, ReplaySource)
    buffer = LiveBuffer(source.bones)
    start = time.monotonic()
    source.start(buffer)
    try:
        assert source.finished.wait(60)
        elapsed = time.monotonic() - start
    finally:
        source.stop()
    assert elapsed >= 993 * frame_time / 20 * 0.95  # real time, scaled by speed
    assert buffer.samples == 994 * 31 and buffer.duplicates == buffer.out_of_order == 0
    expected, roots = skeleton.pose(motion[-1:])
    assert quat_angle(buffer.pose().rotations, expected[0]).max() < 1e-6
    np.testing.assert_allclose(buffer.pose().root_position, roots[0])


def test_replay_loops_with_increasing_timestamps():
    source, buffer = started_source(f"replay://{CMU_CLIP}?speed=200&loop=1", "take")
    try:
        assert wait_for(lambda: buffer.samples >= 31 * 1200, timeout=60)
    finally:
        source.stop()
    assert buffer.samples >= 31 * 1200 and buffer.out_of_order == buffer.clock_resets == 0


def test_replay_errors_name_the_file(tmp_path):
    with pytest.raises(LiveSourceError, match=r"'take'.*missing\.bvh cannot be read"):
        open_source(f"replay://{tmp_path}/missing.bvh", "take")
    with pytest.raises(LiveSourceError, match=r"neither a \.bvh file nor a recorded take"):
        open_source(f"replay://{tmp_path}/take.mp4", "take")
    with pytest.raises(LiveSourceError, match=r"speed='0'"):
        open_source(f"replay://{CMU_CLIP}?speed=0", "take")

"""Time-code tolerance: drifted exporter samples compare equal, frames apart never do."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.sdk import timecodes
from rigspace.sdk.timecodes import clamp_range, same_time, snap

# What a real exporter wrote: frame k at k * (1 + 5.2e-8).
DRIFT = 1 + 5.2e-8
DRIFTED = np.arange(1, 3024) * DRIFT


def test_drifted_samples_are_the_same_time_and_frames_are_not():
    frames = np.arange(1.0, 3024.0)
    assert same_time(frames, DRIFTED).all()
    assert not same_time(frames[:-1], DRIFTED[1:]).any()  # one frame apart
    assert not same_time(3000.0, 3000.05)  # a twentieth of a frame is another time
    assert not same_time(0.0, 0.001)
    assert same_time(0.0, 0.0) and same_time(-5.0, -5.0 - 1e-7)


def test_tolerance_scales_with_magnitude():
    assert timecodes.tolerance(0.5) == pytest.approx(timecodes.TOLERANCE)
    assert timecodes.tolerance(3000) == pytest.approx(3000 * timecodes.TOLERANCE)
    # Far below a frame even at an hour of 30 fps.
    assert timecodes.tolerance(108_000) < 0.2


def test_snap_takes_the_authored_sample_within_tolerance_only():
    times = np.array([1.0, 2.0, 2.5, 120.0, 3023.0, 5000.0])
    snapped = snap(times, DRIFTED)
    assert snapped[0] == DRIFTED[0] and snapped[1] == DRIFTED[1]
    assert snapped[3] == DRIFTED[119] and snapped[4] == DRIFTED[-1]
    assert snapped[2] == 2.5 and snapped[5] == 5000.0  # between samples, beyond them
    assert snap(times, []).tolist() == times.tolist()
    assert snap(7.0, [7.0000001]).tolist() == [7.0000001]


def test_clamp_range():
    lo, hi = DRIFTED[0], DRIFTED[-1]
    # Ends that round into the range become its ends exactly; inner ends are kept.
    assert clamp_range(1.0, 120.0, lo, hi) == (lo, 120.0)
    assert clamp_range(1.0, 3023.0, lo, hi) == (lo, hi)
    # Partly outside: clamped.
    assert clamp_range(0.0, 10.0, lo, hi) == (lo, 10.0)
    assert clamp_range(3000.0, 4000.0, lo, hi) == (3000.0, hi)
    # Wholly outside: nothing.
    assert clamp_range(4000.0, 5000.0, lo, hi) is None
    assert clamp_range(1e12, 1e12, lo, hi) is None
    # A single frame at the range's end that drifted past it.
    assert clamp_range(3023.0, 3023.0, lo, hi) == (hi, hi)
    with pytest.raises(ValueError, match="finite"):
        clamp_range(float("nan"), float("nan"), lo, hi)


def test_a_clip_sampled_off_the_integer_grid_is_captured_at_its_own_samples():
    """An export at 0.9867 time codes per sample: captured at its samples, not between them
    (the issue 22 asset); integer, drifted, dense and sparse keys keep the grid."""
    import numpy as np

    from rigspace.capture.settings import Clip

    clip = Clip("walk", 0.0, 40.0)
    off_grid = np.arange(41) * 0.9867
    np.testing.assert_array_equal(clip.times(samples=off_grid), off_grid[off_grid <= 40.0])
    drifted = np.arange(41) + 1e-7
    np.testing.assert_array_equal(clip.times(samples=drifted), drifted)
    dense = np.arange(81) * 0.5  # twice the rate: the integer frames are samples
    np.testing.assert_array_equal(clip.times(samples=dense), np.arange(41.0))
    sparse = np.arange(0, 41, 10.0)  # keys every 10 frames: every frame, interpolated
    np.testing.assert_array_equal(clip.times(samples=sparse), np.arange(41.0))


def test_whole_takes_a_drifted_time_code_to_its_frame_and_leaves_others():
    assert timecodes.whole(1.0000000521540642) == 1.0
    assert timecodes.whole(3023.0001577) == 3023.0
    assert timecodes.whole(2.5) == 2.5 and timecodes.whole(0.9867) == 0.9867
    assert timecodes.whole(-4.0000000001) == -4.0

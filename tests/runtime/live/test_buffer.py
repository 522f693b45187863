"""LiveBuffer: latest/delayed, One Euro against hand-computed values, ordering, status, counters."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from rigspace.runtime.live.buffer import (
    DELAYED,
    LATEST,
    BufferSettings,
    LiveBuffer,
    OneEuroFilter,
    one_euro_alpha,
)
from rigspace.runtime.live.source_frame import SourceFrame, quat_angle, quat_slerp
from tests.runtime.live.conftest import wait_for

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def yaw(degrees: float) -> np.ndarray:
    h = np.radians(degrees) / 2
    return np.array([np.cos(h), 0.0, np.sin(h), 0.0])


def frame(ts: float, q: np.ndarray, stream: int = 0, bone: int = 0, root=None) -> SourceFrame:
    return SourceFrame(stream, ts, np.array([bone]), q[None], root)


def test_one_euro_alpha_and_filter_match_hand_computed_values():
    # Casiez et al. 2012: alpha = 1 / (1 + tau / Te), tau = 1 / (2 pi fc); values worked by hand.
    assert one_euro_alpha(1.0, 0.1) == pytest.approx(0.3858695450950375, abs=1e-12)
    f = OneEuroFilter(1, 1, min_cutoff=1.0, beta=0.0, d_cutoff=1.0)
    out = [
        f(np.array([0]), np.array([[x]]), t)[0, 0] for t, x in ((0, 0.0), (0.1, 1.0), (0.2, 1.0))
    ]
    assert out == pytest.approx([0.0, 0.3858695450950375, 0.6228437843582239], abs=1e-12)
    # beta = 1: the derivative (smoothed at 1 Hz) opens the cutoff to 4.8587 Hz, then 4.3218 Hz.
    f = OneEuroFilter(1, 1, min_cutoff=1.0, beta=1.0, d_cutoff=1.0)
    out = [
        f(np.array([0]), np.array([[x]]), t)[0, 0] for t, x in ((0, 0.0), (0.1, 1.0), (0.2, 1.0))
    ]
    assert out == pytest.approx([0.0, 0.7532575181149229, 0.9335909750997666], abs=1e-12)
    assert f.dx[0, 0] == pytest.approx(3.3218464850380154, abs=1e-12)


def test_latest_drops_duplicates_and_out_of_order_and_survives_clock_reset():
    b = LiveBuffer(("a",))
    assert b.push(frame(10.0, yaw(10)), 100.0)
    assert not b.push(frame(10.0, yaw(20)), 100.1)  # duplicate
    assert not b.push(frame(9.9, yaw(30)), 100.2)  # late
    np.testing.assert_allclose(b.pose(100.3).rotations[0], yaw(10))
    assert b.push(frame(0.5, yaw(40)), 100.4)  # 9.5 s back: a restarted sender
    np.testing.assert_allclose(b.pose(100.5).rotations[0], yaw(40))
    c = b.counters(100.5)
    assert (c.duplicates, c.out_of_order, c.dropped, c.clock_resets) == (1, 1, 2, 1)
    assert c.samples == 2


def test_delayed_slerps_on_source_timestamps_and_hides_jitter():
    settings = BufferSettings(mode="delayed", delay=0.05)
    b = LiveBuffer(("a",), settings)
    # Source samples every 10 ms; arrival jitters by up to 8 ms (the least delayed sample fixes
    # the clock offset: 1000.0 - 0.0).
    rng = np.random.default_rng(1)
    for k in range(20):
        b.push(frame(k * 0.01, yaw(k)), 1000.0 + k * 0.01 + rng.uniform(0, 0.008))
    b.push(frame(0.20, yaw(20)), 1000.20)
    pose = b.pose(1000.155 + 0.05)  # source time 0.155 -> halfway between samples 15 and 16
    expected = quat_slerp(yaw(15), yaw(16), 0.5)
    assert quat_angle(pose.rotations[0], expected) < 1e-6
    assert b.counters(1000.2).jitter_p99_ms < 10


def test_interpolate_uses_one_sample_interval():
    b = LiveBuffer(("a",), BufferSettings(mode="delayed", delay=None))
    for k in range(5):
        b.push(frame(k * 0.02, yaw(10 * k)), 5.0 + k * 0.02)
    pose = b.pose(5.08)  # one interval (20 ms) behind the newest sample
    assert quat_angle(pose.rotations[0], yaw(30)) < 1e-6


def test_status_connected_stale_lost_and_blend_weight():
    b = LiveBuffer(("a",), BufferSettings(timeout=0.5, blend=0.5))
    assert b.pose(0.0).status == "waiting" and b.pose(0.0).weight == 0
    b.push(frame(1.0, yaw(10)), 10.0)
    assert (b.pose(10.4).status, b.pose(10.4).weight) == ("connected", 1.0)
    stale = b.pose(11.0)
    assert stale.status == "stale" and stale.weight == 1.0
    np.testing.assert_allclose(stale.rotations[0], yaw(10))  # holds the last pose
    lost = b.pose(12.25)  # lost at 10 + 4 * 0.5 = 12; half-way through the blend
    assert lost.status == "lost" and lost.weight == pytest.approx(0.5)
    assert b.pose(13.0).weight == 0.0
    b.push(frame(1.1, yaw(20)), 13.0)
    assert b.pose(13.0).status == "connected"


def test_exponential_and_one_euro_smoothing_reduce_noise():
    rng = np.random.default_rng(3)
    noisy = [quat_slerp(IDENTITY, yaw(rng.normal(0, 5)), 1.0) for _ in range(200)]
    errors = {}
    for smoothing in ("none", "exponential", "oneEuro"):
        b = LiveBuffer(("a",), BufferSettings(smoothing=smoothing, strength=0.7))
        out = []
        for k, q in enumerate(noisy):
            b.push(frame(k / 60, q), k / 60)
            out.append(b.pose(k / 60).rotations[0])
        errors[smoothing] = float(np.mean(quat_angle(np.array(out[50:]), IDENTITY)))
    assert errors["exponential"] < 0.6 * errors["none"]
    assert errors["oneEuro"] < 0.6 * errors["none"]


@pytest.mark.slow
def test_history_is_bounded_and_pose_does_not_wait_for_a_flood():
    b = LiveBuffer(tuple(f"j{i}" for i in range(55)), BufferSettings(mode="delayed", history=64))
    quats = np.tile(IDENTITY, (55, 1))
    stop = threading.Event()

    def flood():
        k = 0
        while not stop.is_set():
            b.push(SourceFrame(0, k * 1e-4, np.arange(55), quats), time.monotonic())
            k += 1

    thread = threading.Thread(target=flood)
    thread.start()
    durations = []
    try:
        assert wait_for(lambda: b.samples >= 55 * 200)
        for _ in range(300):
            t = time.perf_counter()
            b.pose()
            durations.append(time.perf_counter() - t)
            b.note_latency(1e-4)  # as a second receiver thread would, while counters() reads
            assert b.counters().samples > 0
    finally:
        stop.set()
        thread.join()
    assert len(b._snapshots) == 64 and b.samples > 0
    assert np.percentile(durations, 50) < 0.005  # generous: the machine is shared


def test_settings_from_the_binding_tokens():
    from types import SimpleNamespace

    def b(buffering, seconds=0.08, lost=0.0):
        return SimpleNamespace(
            buffering=buffering, buffer_seconds=seconds, smoothing="oneEuro",
            smoothing_strength=0.3, timeout_seconds=0.25, lost_seconds=lost,
        )  # fmt: skip

    assert BufferSettings.from_binding(b("latest")).mode == "latest"
    delayed = BufferSettings.from_binding(b("delayed"))
    assert (delayed.mode, delayed.delay, delayed.lost_after) == ("delayed", 0.08, 1.0)
    one_sample = BufferSettings.from_binding(b("delayed", seconds=0.0, lost=3.0))
    assert (one_sample.delay, one_sample.smoothing, one_sample.lost_after) == (None, "oneEuro", 3.0)
    with pytest.raises(ValueError, match="buffering 'buffered'"):
        BufferSettings.from_binding(b("buffered"))  # the reader maps old tokens; this does not
    with pytest.raises(ValueError, match="buffer mode"):
        LiveBuffer(("a",), BufferSettings(mode="later"))


def test_lost_seconds_sets_the_lost_threshold():
    b = LiveBuffer(("a",), BufferSettings(timeout=0.1, lost=0.3, blend=0.5))
    b.push(SourceFrame(0, 1.0, np.array([0]), np.array([[1.0, 0, 0, 0]])), received=10.0)
    assert b.pose(10.05).status == "connected"
    assert b.pose(10.2).status == "stale"  # past timeoutSeconds, before lostSeconds: held
    assert b.pose(10.29).weight == 1.0
    lost = b.pose(10.55)
    assert lost.status == "lost" and lost.weight == pytest.approx(0.5)  # 0.25 s into the blend


# casiez/OneEuroFilter groundTruth.csv (BSD-3-Clause, Inria): the first 30 rows of
# (timestamp, noisy, filtered) for freq 120 Hz, mincutoff 1 Hz, beta 0.1, dcutoff 1 Hz; the
# reference's own test accepts 0.001; the CSV's six significant digits allow about 1e-5.
GROUND_TRUTH = [
    (0, -0.0385099, -0.0385099),
    (0.00833333, -0.0280664, -0.0379872),
    (0.0166667, 0.048622, -0.0334427),
    (0.025, 0.111498, -0.0252696),
    (0.0333333, 0.053026, -0.0207099),
    (0.0416667, 0.120548, -0.0119912),
    (0.05, 0.00972308, -0.0106507),
    (0.0583333, 0.074193, -0.00526521),
    (0.0666667, -0.0236801, -0.00641239),
    (0.075, 0.0462396, -0.00308863),
    (0.0833333, 0.0892027, 0.00291027),
    (0.0916667, 0.158329, 0.0135545),
    (0.1, 0.0423086, 0.01552),
    (0.108333, 0.0887203, 0.0206024),
    (0.116667, 0.039102, 0.0218784),
    (0.125, 0.140277, 0.030313),
    (0.133333, 0.156938, 0.0396331),
    (0.141667, 0.0961089, 0.0438101),
    (0.15, 0.216881, 0.0572083),
    (0.158333, 0.067538, 0.057997),
    (0.166667, 0.0737634, 0.0591871),
    (0.175, 0.0989231, 0.0621793),
    (0.183333, 0.148209, 0.0687489),
    (0.191667, 0.0959887, 0.0708137),
    (0.2, 0.225627, 0.0829925),
    (0.208333, 0.292078, 0.100305),
    (0.216667, 0.185221, 0.107391),
    (0.225, 0.133595, 0.109553),
    (0.233333, 0.216387, 0.118501),
    (0.241667, 0.316189, 0.135759),
]


def test_one_euro_matches_the_reference_ground_truth():
    f = OneEuroFilter(1, 1, min_cutoff=1.0, beta=0.1, d_cutoff=1.0)
    for t, noisy, filtered in GROUND_TRUTH:
        assert f(np.array([0]), np.array([[noisy]]), t)[0, 0] == pytest.approx(filtered, abs=1e-5)


def test_counter_percentiles_are_numpys_from_one_partition():
    rng = np.random.default_rng(3)
    b = LiveBuffer(("a",))
    values = rng.exponential(0.004, 1500)
    b._jitter.extend(values)  # bounded: the last 1024 are kept
    b._latency.extend(values[:7])
    c = b.counters()
    assert c.jitter_p50_ms == pytest.approx(np.percentile(values[-1024:], 50) * 1e3, rel=1e-12)
    assert c.jitter_p99_ms == pytest.approx(np.percentile(values[-1024:], 99) * 1e3, rel=1e-12)
    assert c.latency_p99_ms == pytest.approx(np.percentile(values[:7], 99) * 1e3, rel=1e-12)
    b.note_latency(1.0)  # a new value invalidates the cached figures
    assert b.counters().latency_p99_ms == pytest.approx(
        np.percentile([*values[:7], 1.0], 99) * 1e3, rel=1e-12
    )
    assert b.counters().as_dict()["latency_p50_ms"] == b.counters().latency_p50_ms


@pytest.mark.parametrize("mode", [LATEST, DELAYED])
def test_pose_never_waits_for_a_push_in_progress(mode):
    b = LiveBuffer(("a", "b"), BufferSettings(mode, 0.01))
    q = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
    now = time.monotonic()
    for k in range(3):
        b.push(SourceFrame(0, 0.01 * k, np.array([0, 1]), q), now + 0.01 * k)
    before = b.pose(now + 0.05)
    with b._lock:  # a receiver mid-push (it can lose the GIL while holding the lock)
        start = time.perf_counter()
        during = b.pose(now + 0.05)
        counters = b.counters(now + 0.05)
        waited = time.perf_counter() - start
    assert waited < 0.05  # a blocking pose would wait here forever
    assert during.status == before.status == "connected" and counters.samples == 6
    np.testing.assert_array_equal(during.rotations, before.rotations)
    np.testing.assert_array_equal(during.valid, before.valid)

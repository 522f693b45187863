"""The live measurements: delayed buffering removes most of the jitter's pose error."""

from __future__ import annotations

from rigspace.apps.input_bench import decode_rates, jitter_error


def test_delayed_removes_most_of_the_jitter_error():
    r = jitter_error(jitter_ms=10.0)
    assert r["delayed_error_mean_deg"] < 0.5 * r["latest_error_mean_deg"]
    assert r["delayed_error_p99_deg"] < 0.5 * r["latest_error_p99_deg"]


def test_decode_rates_are_measured():
    r = decode_rates(0.05)
    assert set(r) >= {"vmc_bone_messages_per_s", "bvh_frames_per_s", "ximu3_messages_per_s"}
    assert all(v > 0 for v in r.values())


def test_frame_cost_compares_live_and_stage_frames():
    from rigspace.apps.input_bench import frame_cost

    r = frame_cost(frames=2, size=48)
    assert r["binding_status"] == "connected"  # the live engine really rendered the stream
    assert r["live_frame_ms_p50"] > 0 and r["stage_frame_ms_p50"] > 0
    assert 0 < r["live_work_ms_p50"] <= r["live_work_ms_p99"]
    assert 0 < r["binding_own_ms_p50"] <= r["binding_own_ms_p99"]

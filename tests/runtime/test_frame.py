"""The frame's report (runtime/frame.py): FrameReport as report.json writes it."""

from __future__ import annotations

import json

from rigspace.runtime.frame import FrameReport


def _report() -> FrameReport:
    report = FrameReport(3.0, "/World/Cam", 2, "numba")
    entry = {"path": "/World/Hero", "decision": "evaluated", "level": 64, "top_level": 128}
    report.characters.append(entry)
    report.scene_prims = {"meshes": 5, "reused": False, "lit_reused": False}
    report.shadows = {"maps_drawn": 1, "casters": 1}
    report.counts = {"evaluated": 1, "reused": 0}
    report.seconds = {"scene": 0.001, "total": 0.01}
    return report


def test_to_json_keeps_report_json_s_keys_in_order_and_leaves_out_what_is_none():
    out = _report().to_json()
    assert list(out) == [
        "time", "camera", "scene_prims", "lights", "lighting_on", "characters", "shadows",
        "counts", "composite_reused", "background", "seconds",
    ]  # fmt: skip
    assert json.loads(json.dumps(out)) == out  # plain JSON values
    report = _report()
    report.lights_left_out, report.cpu_seconds = ["/World/Lamp: NaN intensity"], {"scene": 0.0}
    keys = list(report.to_json())
    assert keys.index("lights_left_out") == keys.index("characters") + 1
    assert keys[-1] == "cpu_seconds"


def test_a_repeated_frame_s_report_says_so_and_reuses_every_drawn_character():
    first = _report()
    again = first.repeated(start=0.0)
    assert again.repeat_of_last_frame and again.composite_reused
    assert again.characters[0]["decision"] == "reused" and again.counts["reused"] == 1
    assert first.characters[0]["decision"] == "evaluated"  # the first report is unchanged
    assert list(again.to_json())[-1] == "repeat_of_last_frame"
    assert "repeat_of_last_frame" not in first.to_json()

"""`rigspace bench --quick`: every part runs and writes its numbers, tables and plots."""

from __future__ import annotations

import json

import pytest

from rigspace.apps.bench import PARTS
from rigspace.sdk.cli import main


@pytest.mark.slow
def test_quick_bench_writes_json_markdown_and_plots(tmp_path):
    """The parts with a table and a plot of their own, through the command (every part's
    measurement is tested by its own module's tests; the whole quick bench is 13 parts and
    two minutes, too long for the suite)."""
    out = tmp_path / "bench"
    parts = ["pareto", "skips", "stability", "texture", "premise"]
    assert set(parts) <= set(PARTS)
    assert main(["bench", "--quick", "--out", str(out), "--only", *parts]) == 0
    result = json.loads((out / "results.json").read_text())
    assert result["mode"] == "quick" and set(parts) <= set(result)
    assert result["machine"]["cores"] >= 1 and result["command"].startswith("rigspace")
    # Each skip case did skip what it is named for (behaviour; its time is measured, not
    # tested: on a loaded machine a quick run's ratios swing past 1).
    rows = result["skips"]["int8"]["rows"]
    assert rows["full, still camera"]["fraction_of_full"] == 1.0
    assert all(r["fraction_of_full"] > 0 for r in rows.values())
    assert all(d.startswith("skipped") for d in rows["off-screen"]["decisions"])
    assert rows["off-screen"]["levels"] == []
    assert all(d.startswith("reused") for d in rows["unchanged"]["decisions"])
    assert max(rows["far away"]["levels"]) < min(rows["full, still camera"]["levels"])
    assert rows["unlit and unoccluded"]["branches"] == ["albedo"]
    assert result["stability"]["stress"]["violations"] == {}
    textured = [r for r in result["texture"] if r["mode"] == "textures"]
    assert textured and all(0 < r["beauty_flip"] < 1 for r in textured)  # FLIP beside PSNR
    variants = {r["variant"] for r in result["pareto"]["rows"]}
    assert {"fp32 level 128", "int8 level 8", "gl 2x2"} <= variants
    text = (out / "README.md").read_text()
    for heading in ("Run time against error", "What each skip costs", "Numerical stability"):
        assert heading in text
    assert (out / "pareto.png").stat().st_size > 10_000 and (out / "skips.png").is_file()
    rows = result["premise"]["rows"]
    assert [r["triangles"] for r in rows] == [22_956, 4 * 22_956]
    assert all(r["mesh_ms"] > 0 and r["network_ms"] > 0 for r in rows)
    assert rows[1]["mesh_mib"] > 3 * rows[0]["mesh_mib"]  # the mesh path's memory grows
    assert rows[1]["network_mib"] == rows[0]["network_mib"]  # the network's does not
    assert "The premise" in text and (out / "premise.png").is_file()


def test_an_unknown_part_is_refused(tmp_path, capsys):
    assert main(["bench", "--quick", "--out", str(tmp_path), "--only", "speed"]) != 0
    assert "Unknown bench part speed" in capsys.readouterr().err


@pytest.mark.slow
def test_re_running_a_part_on_another_machine_keeps_the_other_parts(tmp_path):
    """`--only` into a folder measured on another machine: the other parts stay, each says
    the machine it was measured on (a re-run once wiped them all)."""
    out = tmp_path / "bench"
    assert main(["bench", "--quick", "--out", str(out), "--only", "efficiency"]) == 0
    path = out / "results.json"
    kept = json.loads(path.read_text())
    kept["machine"] = dict(kept["machine"], cpu="An older CPU")
    del kept["parts"]["efficiency"]["machine"]  # as results written before parts had one
    path.write_text(json.dumps(kept))
    assert main(["bench", "--quick", "--out", str(out), "--only", "predictors"]) == 0
    result = json.loads(path.read_text())
    assert {"efficiency", "predictors"} <= set(result)
    assert result["parts"]["efficiency"]["machine"]["cpu"] == "An older CPU"
    assert result["parts"]["predictors"]["machine"]["cpu"] != "An older CPU"
    text = (out / "README.md").read_text()
    assert "(Measured on another machine:" in text

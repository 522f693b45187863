"""The ablation's cost table (python -m rigspace.apps.ablation DATASET --cost R): MFLOP and
fp32/int8 ms of each distinct architecture, untrained, through real onnxruntime graphs."""

from __future__ import annotations

import pytest

pytest.importorskip("torch", reason="the cost table builds the variants' networks with torch")

from rigspace.apps import ablation


def _rows(table: str) -> dict[str, list[str]]:
    rows = {}
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[0]] = cells[1:]
    return rows


@pytest.mark.slow
def test_cost_groups_variants_with_the_same_graphs_and_times_both_precisions(tiny_dataset, capsys):
    # 64 on a 32x32 capture: cost reads rig rows only; width32 differs from paper at 64x64.
    names = ["paper", "mask-bce", "paper-seed1", "width32"]
    code = ablation.main(
        [str(tiny_dataset), "--out", str(tiny_dataset.parent / "abl"), "--cost", "64",
         "--variants", *names]
    )  # fmt: skip
    assert code == 0
    rows = _rows(capsys.readouterr().out)
    # Losses and seeds do not change the graphs: one row for the three.
    assert set(rows) == {"`paper`, `mask-bce`, `paper-seed1`", "`width32`"}
    mflop = {k: float(v[1]) for k, v in rows.items()}
    paper = mflop["`paper`, `mask-bce`, `paper-seed1`"]
    assert mflop["`width32`"] > paper
    for params, _, fp32, int8, ratio in rows.values():
        assert params.endswith(" M") and float(fp32) > 0 and float(int8) > 0
        assert float(ratio.rstrip("x")) == pytest.approx(float(fp32) / float(int8), rel=0.02)


def test_cost_refuses_an_unknown_variant(tiny_dataset, capsys):
    code = ablation.main(
        [str(tiny_dataset), "--out", str(tiny_dataset.parent / "abl"), "--cost", "32",
         "--variants", "paper", "wider"]
    )  # fmt: skip
    assert code == 2 and "Unknown variants ['wider']" in capsys.readouterr().err

"""--predictor on render, live and view: the one asked for runs (report.json says which), an
unknown one is a named error."""

from __future__ import annotations

import json

import pytest

from rigspace.sdk.cli import main
from tests.conftest import REPO

PREVIS = REPO / "samples" / "scenes" / "previs.usda"
SMALL = ["--frames", "300:300", "--resolution", "64x36", "--max-level", "16"]


def test_render_runs_the_predictor_asked_for_and_reports_it(tmp_path):
    pytest.importorskip("torch")
    out = tmp_path / "torch"
    assert main(["render", str(PREVIS), "--out", str(out), *SMALL, "--predictor", "torch"]) == 0
    assert json.loads((out / "report.json").read_text())["predictors"] == ["torch cpu fp32"]
    out = tmp_path / "onnx"
    assert (
        main(["render", str(PREVIS), "--out", str(out), *SMALL, "--predictor", "onnxruntime"]) == 0
    )
    assert json.loads((out / "report.json").read_text())["predictors"] == ["onnxruntime CPU (fp32)"]


@pytest.mark.parametrize("command", ["render", "live", "view"])
def test_an_unknown_predictor_is_a_named_error(tmp_path, capsys, command):
    args = {
        "render": ["render", str(PREVIS), "--out", str(tmp_path / "r"), *SMALL],
        "live": ["live", str(REPO / "samples" / "scenes" / "live.usda"), "--out",
                 str(tmp_path / "l"), "--seconds", "0.1"],
        "view": ["view", str(PREVIS), "--port", "0"],
    }[command]  # fmt: skip
    with pytest.raises(SystemExit) as exited:  # argparse: at the flag, before anything opens
        main([*args, "--predictor", "nope"])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert "no predictor plugin called 'nope'" in err and "onnxruntime" in err

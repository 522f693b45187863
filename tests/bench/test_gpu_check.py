"""The GPU check runs (as a CPU dry run) on a machine without usd-core and OpenImageIO."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip("torch")

BLOCKED_RUN = """
import importlib.abc, importlib.util, runpy, sys
BLOCKED = ("pxr", "OpenImageIO")
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}")
find_spec = importlib.util.find_spec
importlib.util.find_spec = lambda n, *a, **k: None if n.split(".")[0] in BLOCKED else find_spec(n, *a, **k)
sys.meta_path.insert(0, Block())
sys.argv = ["gpu_check", *sys.argv[1:]]
runpy.run_module("rigspace.apps.gpu_check", run_name="__main__")
"""


@pytest.mark.slow
def test_the_gpu_check_runs_without_usd_and_openimageio(tmp_path):
    script = tmp_path / "blocked.py"
    script.write_text(BLOCKED_RUN)
    out = tmp_path / "gpu_check.json"
    args = ["--device", "cpu", "--seconds", "0.05", "--repeats", "1", "--batches", "2"]
    args += ["--resolutions", "16", "--out", str(out), "--dataset", str(tmp_path)]
    done = subprocess.run(
        [sys.executable, str(script), *args], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(out.read_text())
    parts = result["parts"]
    assert [(r["batch"], r["bf16"], r["finite"]) for r in parts["step"]] == [
        (2, False, True),
        (2, True, True),
    ]
    torch_rows = [r for r in parts["predictors"] if r["predictor"] == "torch"]
    assert [(r["level"], r["batch"]) for r in torch_rows] == [(16, 1), (16, 8)]
    assert all(r["ms_per_character"] > 0 for r in torch_rows)
    for part in ("train", "frames"):  # these need rigspace's full install: they say what
        assert "pip install usd-core OpenImageIO" in parts[part]["skipped"]
    assert "| fp32 | 2 |" in done.stdout and "sample architecture at 16" in done.stdout

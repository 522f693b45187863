"""The GPU recipe (apps/recipe.py): its smoke mode end to end on the CPU, what it brings back
and how that is unpacked, the travel check, and its start on a machine with nothing installed."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch", reason="the recipe trains (the train extra)")

from rigspace.apps import recipe
from rigspace.sdk.model import BundleModel

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    out = tmp_path_factory.mktemp("recipe") / "out"
    done = subprocess.run(
        [sys.executable, "-m", "rigspace.apps.recipe", "run", "--smoke", "--out", str(out)],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return out


@pytest.mark.slow
def test_the_smoke_run_brings_back_a_bundle_and_its_numbers_in_few_files(smoke):
    files = sorted(p for p in smoke.iterdir())
    assert len(files) <= recipe.MAX_FILES
    assert all(p.stat().st_size <= recipe.MAX_FILE_BYTES for p in files)
    numbers = json.loads((smoke / "numbers.json").read_text())
    assert "failed" not in numbers
    assert {"capture", "capture display", "train", "eval heldout-views", "eval display",
            "gpu check"} <= set(numbers["stages"])  # fmt: skip
    assert numbers["train"]["trained_levels"][-1] == 32
    views = numbers["eval"]["heldout-views"]["rows"][0]
    assert views["predictor"] == "model" and 0 <= views["mask_iou"] <= 1
    assert "albedo_flip" in views  # FLIP beside PSNR and SSIM
    assert numbers["gpu_check"]["parts"]["predictors"]
    assert "pack:" in (smoke / "log.txt").read_text()


@pytest.mark.slow
def test_unpack_puts_the_bundle_in_place_and_writes_the_gpu_table(smoke, tmp_path):
    bundle, docs = tmp_path / "models" / "sample", tmp_path / "docs"
    (bundle / "training").mkdir(parents=True)
    (bundle / "old.onnx").write_text("the bundle before")
    numbers = recipe.unpack(smoke, docs, bundle)
    assert not (bundle / "old.onnx").exists()  # replaced whole, not merged
    model = BundleModel(bundle)
    assert model.manifest.texture is not None and model.texture_branch == "texture"
    assert max(model.resolutions) == 32
    table = (docs / "gpu.md").read_text()
    assert "smoke, on the CPU" in table and "heldout-views" in table
    assert json.loads((docs / "gpu.json").read_text())["packed"] == numbers["packed"]


def test_unpack_refuses_results_that_do_not_match_their_checksum(tmp_path):
    files, bundle = tmp_path / "files", tmp_path / "bundle"
    files.mkdir()
    bundle.mkdir()
    (bundle / "manifest.json").write_text("{}")
    part = b"not what was packed"
    (files / "results.tar.000").write_bytes(part + b"!")
    packed = {"parts": ["results.tar.000"], "bytes": len(part),
              "sha256": hashlib.sha256(part).hexdigest()}  # fmt: skip
    (files / "numbers.json").write_text(json.dumps({"smoke": True, "packed": packed}))
    with pytest.raises(recipe.RecipeError, match="do not match the sha256"):
        recipe.unpack(files, tmp_path / "docs", bundle)
    assert (bundle / "manifest.json").read_text() == "{}"  # nothing touched
    assert not (tmp_path / "docs").exists()


def test_the_travel_check_counts_the_tree_and_the_payload(tmp_path, monkeypatch):
    tree = tmp_path / "tree"
    tree.mkdir()
    subprocess.run(["git", "init", "-q"], cwd=tree, check=True)
    (tree / ".gitignore").write_text("/.gpu/\n")
    (tree / "tracked.bin").write_bytes(b"x" * 3000)
    (tree / ".gpu").mkdir()
    (tree / ".gpu" / "site.tar.xz").write_bytes(b"y" * 5000)
    subprocess.run(["git", "add", "tracked.bin", ".gitignore"], cwd=tree, check=True)
    (tree / "untracked.txt").write_bytes(b"z" * 1000)  # not ignored: it travels too
    sizes = recipe.travel_check(tree, tree / ".gpu")
    assert sizes["tree"] == 3000 + 1000 + len("/.gpu/\n") and sizes["payload"] == 5000
    monkeypatch.setattr(recipe, "TRAVEL_LIMIT", 8000)
    monkeypatch.setattr(recipe, "TRAVEL_MARGIN", 0)
    with pytest.raises(recipe.RecipeError, match=r"come to 0\.0 MiB; a device call carries"):
        recipe.travel_check(tree, tree / ".gpu")


def test_run_starts_with_the_standard_library_alone_and_names_prepare(tmp_path):
    """On a machine where nothing of rigspace's is installed (the GPU machine before its
    install), the script starts, and without a payload it says how to make one."""
    python = Path("/usr/bin/python3")
    probe = [python, "-c", "import numpy"]
    if not python.is_file() or subprocess.run(probe, capture_output=True).returncode == 0:
        pytest.skip("needs a Python without rigspace's dependencies at /usr/bin/python3")
    done = subprocess.run(
        [python, "apps/recipe.py", "run", "--out", str(tmp_path / "out"), "--payload",
         str(tmp_path / "none")],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert "rigspace is not installed here" in done.stderr
    assert "python -m rigspace.apps.recipe prepare" in done.stderr
    assert "Traceback" not in done.stderr
    numbers = json.loads((tmp_path / "out" / "numbers.json").read_text())
    assert "not installed" in numbers["failed"]


def test_the_test_verb_runs_pytest_and_brings_back_its_counts(tmp_path):
    """`recipe test` (part of the suite on the GPU machine) here, where rigspace is installed:
    pytest's output, its junit XML and the counts come back under --out; a failing test makes
    the exit 1."""
    tests = tmp_path / "test_probe.py"
    tests.write_text(
        "def test_passes():\n    assert True\n\n\ndef test_fails():\n    assert 1 == 2\n"
    )
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "rigspace.apps.recipe", "test", "--out", str(out), "--minutes",
         "5", "--", "-q", str(tests)],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 1, done.stderr[-2000:]
    numbers = json.loads((out / "numbers.json").read_text())
    assert numbers["pytest"] == {"exit": 1, "tests": 2, "failures": 1, "errors": 0, "skipped": 0}
    assert "test_fails" in (out / "pytest.txt").read_text()
    assert (out / "junit.xml").is_file() and (out / "log.txt").is_file()

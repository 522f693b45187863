"""Every writer of a bundle's manifest goes through sdk.bundle's write contract: a manifest a
reader refuses stops it before it writes anything, and a document it produces wrong is refused
before the manifest is replaced."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch", reason="the writers are the train extra's (torch, onnx)")

from rigspace.apps.graph_rewrite import main as rewrite_main
from rigspace.apps.train import record_metrics
from rigspace.sdk.bundle import BundleError
from rigspace.sdk.capsules import Capsules, add_to_bundle
from rigspace.train import graph_rewrite, quantize
from tests.conftest import REPO

SAMPLE = REPO / "samples" / "models" / "sample"
RESULT = {"samples": 1, "rows": [{"predictor": "model", "albedo_psnr": 30.0}]}
CAPSULES = Capsules(("hips",), np.zeros((1, 3)), np.ones((1, 3)), np.array([0.1]))

WRITERS: dict[str, Callable[[Path], object]] = {
    "eval --record": lambda b: record_metrics(b, "heldout-views", "fp32", RESULT),
    "capsules": lambda b: add_to_bundle(CAPSULES, b),
    "graph rewrite": lambda b: graph_rewrite.rewrite_bundle(b),
    "requantize": lambda b: quantize.requantize_bundle(b, b / "no-dataset"),
    "recheck": lambda b: quantize.recheck_bundle(b, b / "no-dataset"),
}


def files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir()}


@pytest.mark.parametrize("writer", list(WRITERS))
def test_a_writer_stops_on_a_manifest_a_reader_refuses_and_writes_nothing(tmp_path, writer):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    manifest = json.loads((SAMPLE / "manifest.json").read_text())
    del manifest["levels"][0]["graphs"]
    (bundle / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    before = files(bundle)
    with pytest.raises(BundleError, match=r"'levels\[0\]\.graphs' is missing"):
        WRITERS[writer](bundle)
    assert files(bundle) == before


def test_a_writer_that_produces_a_wrong_document_is_refused(tmp_path):
    """quantize's manifest writer, handed a level without graphs, replaces nothing."""
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    shutil.copy(SAMPLE / "manifest.json", bundle / "manifest.json")
    before = files(bundle)
    manifest = json.loads((SAMPLE / "manifest.json").read_text())
    manifest["trunk"]["int8"] = {"trunk": None}  # no int8 graph to record (none copied here)
    for level in manifest["levels"]:
        level["int8"] = {}
    del manifest["levels"][0]["graphs"]
    with pytest.raises(BundleError, match=r"Refused to write .*'levels\[0\]\.graphs' is missing"):
        quantize._write_manifest(bundle, manifest)
    assert files(bundle) == before


def test_eval_record_keeps_every_other_byte_of_the_manifest(tmp_path):
    """A writer changes its own section; the rest of the document passes through as it was."""
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    shutil.copy(SAMPLE / "manifest.json", bundle / "manifest.json")
    record_metrics(bundle, "heldout-views", "fp32", RESULT)
    after = json.loads((bundle / "manifest.json").read_text())
    committed = json.loads((SAMPLE / "manifest.json").read_text())
    assert after["metrics"]["heldout-views"]["fp32"] == RESULT
    after["metrics"]["heldout-views"]["fp32"] = committed["metrics"]["heldout-views"]["fp32"]
    assert json.dumps(after, indent=2) == json.dumps(committed, indent=2)  # order kept too


def test_an_export_whose_manifest_is_refused_leaves_no_manifest(tmp_path, tiny_run, monkeypatch):
    """The export writes its manifest through the contract, last: refused, there is none (so no
    reader takes the graphs for a bundle)."""
    from rigspace.train import export

    written = export.write_manifest_document

    def spoilt(folder, document):
        del document["levels"][0]["graphs"]
        return written(folder, document)

    monkeypatch.setattr(export, "write_manifest_document", spoilt)
    out = tmp_path / "model"
    with pytest.raises(BundleError, match="Refused to write"):
        export.export_bundle(tiny_run, out, int8=False)
    assert (out / "trunk.onnx").is_file() and not (out / "manifest.json").exists()
    assert not list(out.glob(".*"))  # no temporary left


def test_the_graph_rewrite_command_says_why_it_refuses(tmp_path, capsys):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text('{"format": "rigspace.bundle", "format_version": 9}')
    assert rewrite_main([str(bundle)]) == 1
    err = capsys.readouterr().err
    assert "error:" in err and "format version 9" in err and "Traceback" not in err

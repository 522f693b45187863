"""The bundle manifest's one write contract (sdk.bundle): a document read and written back is
the same bytes, and a document no reader would accept is refused before anything is written."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil

import pytest

from rigspace.sdk.bundle import (
    BundleError,
    read_manifest,
    read_manifest_document,
    write_manifest_document,
)
from tests.conftest import REPO

MODELS = REPO / "samples" / "models"


def manifest_only(bundle, tmp_path):
    """A folder holding a copy of `bundle`'s manifest.json alone."""
    folder = tmp_path / bundle.name
    folder.mkdir()
    shutil.copy(bundle / "manifest.json", folder / "manifest.json")
    return folder


@pytest.mark.parametrize("name", ["sample", "film"])
def test_a_committed_bundle_is_written_back_byte_for_byte(tmp_path, name):
    folder = manifest_only(MODELS / name, tmp_path)
    written = write_manifest_document(folder, read_manifest_document(folder))
    assert (folder / "manifest.json").read_bytes() == (MODELS / name / "manifest.json").read_bytes()
    committed = read_manifest(MODELS / name)
    regions = tuple(  # a region's bundle folder is where the manifest is read from
        dataclasses.replace(r, folder=folder / r.folder.relative_to(MODELS / name))
        for r in committed.regions
    )
    assert written == dataclasses.replace(committed, path=folder / "manifest.json", regions=regions)
    assert [p.name for p in folder.iterdir()] == ["manifest.json"]


def _without_graphs(data):
    del data["levels"][0]["graphs"]


def _no_joints(data):
    data["joints"] = []


def _version_as_text(data):
    data["format_version"] = "4"


def _negative_depth_scale(data):
    data["depth"]["scale"] = -1.0


@pytest.mark.parametrize(
    ("spoil", "said"),
    [
        (_without_graphs, "'levels[0].graphs' is missing"),
        (_no_joints, "'joints' must be a non-empty list"),
        (_version_as_text, "format_version must be an integer"),
        (_negative_depth_scale, "'depth.scale' is -1.0"),
    ],
    ids=lambda x: getattr(x, "__name__", "")[1:],
)
def test_a_document_no_reader_accepts_is_refused_before_anything_is_written(tmp_path, spoil, said):
    folder = manifest_only(MODELS / "sample", tmp_path)
    before = (folder / "manifest.json").read_bytes()
    document = read_manifest_document(folder)
    spoil(document)
    with pytest.raises(BundleError, match="Refused to write") as info:
        write_manifest_document(folder, document)
    assert said in str(info.value) and "nothing was written" in str(info.value)
    assert (folder / "manifest.json").read_bytes() == before
    assert [p.name for p in folder.iterdir()] == ["manifest.json"]  # no temporary left


def test_reading_the_document_checks_it_as_read_manifest_does(tmp_path):
    folder = manifest_only(MODELS / "sample", tmp_path)
    data = json.loads((folder / "manifest.json").read_text())
    spoilt = copy.deepcopy(data)
    _without_graphs(spoilt)
    (folder / "manifest.json").write_text(json.dumps(spoilt))
    with pytest.raises(BundleError, match=r"'levels\[0\]\.graphs' is missing.*Fix: re-export"):
        read_manifest_document(folder)
    (folder / "manifest.json").write_text("{oops")
    with pytest.raises(BundleError, match="not readable JSON"):
        read_manifest_document(folder)
    with pytest.raises(BundleError, match=r"no manifest\.json"):
        read_manifest_document(tmp_path / "nowhere")

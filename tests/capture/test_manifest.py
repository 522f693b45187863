"""The dataset manifest, typed (capture.dataset.DatasetManifest): finalize writes its
to_json, read_manifest gives it back equal, and a hand-written or damaged one is read with
defaults or refused by name."""

from __future__ import annotations

import json
import shutil

import pytest

from rigspace.capture import dataset as ds

MINIMAL = {
    "format": ds.FORMAT,
    "format_version": ds.FORMAT_VERSION,
    "resolution": 32,
    "joints": ["hips", "hips/spine"],
    "ring": {"radius": 3.0, "horizontal_aperture": 20.955, "focal_length": 50.0},
}
"""What the reader needs (capture.dataset.DATASET_MANIFEST's required fields)."""


def test_finalize_writes_the_manifest_read_manifest_returns(dataset):
    manifest = ds.read_manifest(dataset.folder)
    assert manifest == dataset.manifest
    written = (dataset.folder / ds.MANIFEST_FILE).read_text()
    assert json.dumps(manifest.to_json(), indent=2) + "\n" == written
    assert manifest.folder == dataset.folder and manifest.charts is not None
    assert manifest.counts["samples"] == 6 * len(manifest.ring.views) == 6 * (4 + 4)
    assert manifest.clips[0].name == "frames" and manifest.renderer is not None
    assert [v.index for v in manifest.ring.views] == list(range(len(manifest.ring.views)))


def test_a_minimal_manifest_reads_with_defaults_and_round_trips(tmp_path):
    manifest = ds.DatasetManifest.from_json(MINIMAL, tmp_path / ds.MANIFEST_FILE)
    assert manifest.joints == ("hips", "hips/spine") and manifest.ring.views == ()
    assert manifest.scene == "" and manifest.up_axis == "Y" and manifest.checksum == ""
    assert manifest.charts is None and manifest.coverage is None and manifest.blend_shapes == ()
    document = manifest.to_json()
    assert "charts" not in document and "meters_per_unit" not in document
    assert ds.DatasetManifest.from_json(document, manifest.path) == manifest


def test_a_view_key_that_is_no_view_is_a_named_error(tmp_path, dataset):
    folder = tmp_path / "ds"
    folder.mkdir()
    shutil.copy(dataset.folder / ds.PARAMS_FILE, folder / ds.PARAMS_FILE)
    data = dataset.manifest.to_json()
    data["coverage"]["empty_by_view"] = {"front": 3}
    (folder / ds.MANIFEST_FILE).write_text(json.dumps(data))
    with pytest.raises(ds.DatasetError, match=r"'coverage\.empty_by_view\.front' is 3.*Fix:"):
        ds.read_manifest(folder)


@pytest.mark.parametrize("data", [[], {**MINIMAL, "format": "rigspace.bundle"}])
def test_another_document_is_refused_by_name(tmp_path, data):
    path = tmp_path / ds.MANIFEST_FILE
    with pytest.raises(ds.DatasetError, match=f"{path} is not a rigspace.dataset manifest"):
        ds.DatasetManifest.from_json(data, path)

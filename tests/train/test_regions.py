"""`rigspace train` on a dataset with regions (capture --regions): each region's network is
trained after the body's into MODEL/regions/NAME, a bundle of its own, and the body's manifest
lists them; the budget is shared by image size."""

from __future__ import annotations

import json

import pytest

from rigspace.apps.train import budget_shares
from rigspace.sdk.bundle import BundleError, read_manifest
from rigspace.sdk.cli import main
from tests.blendshapes import write_blendshape_character
from tests.capture.test_regions import _with_region


@pytest.fixture(scope="module")
def region_dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("regions")
    scene = _with_region(write_blendshape_character(folder), joint="head", resolution=16)
    out = folder / "ds"
    args = ["capture", str(scene), "--out", str(out), "--views", "2", "--every", "6",
            "--resolution", "32", "--workers", "1", "--regions"]  # fmt: skip
    assert main(args) == 0
    return out


@pytest.mark.slow
def test_train_trains_each_region_into_a_bundle_the_body_lists(region_dataset, tmp_path, capsys):
    out = tmp_path / "model"
    args = ["train", str(region_dataset), "--out", str(out), "--preset", "tiny", "--steps", "3",
            "--no-int8"]  # fmt: skip
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "region face: training at 16x16" in printed and "regions in" in printed
    body = read_manifest(out)
    assert [(r.name, r.joint) for r in body.regions] == [("face", "neck/head")]
    face = read_manifest(body.regions[0].folder)
    assert body.regions[0].folder == out / "regions" / "face"
    assert face.look_at_joint == "neck/head" and face.training_resolution == 16
    assert max(level.resolution for level in face.levels) == 16
    # --force replaces the bundle and its regions; --no-regions trains the body alone.
    assert main([*args, "--force", "--no-regions"]) == 0
    assert read_manifest(out).regions == () and not (out / "regions").exists()


def test_the_budget_is_shared_by_image_size():
    assert budget_shares(128, [64, 64], None) == [None, None, None]
    body, face, hand = budget_shares(128, [64, 32], 21.0)
    assert body + face + hand == pytest.approx(21.0)
    assert body == pytest.approx(4 * face) and face == pytest.approx(4 * hand)


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"name": "face", "joint": "head", "bundle": "../elsewhere"}, "not a folder inside"),
        ({"name": "face", "joint": "head", "bundle": "/abs/face"}, "not a folder inside"),
        ({"name": "face", "joint": "head"}, "regions[0].bundle"),
        ({"name": "face", "joint": 3, "bundle": "regions/face"}, "regions[0].joint"),
    ],
)
def test_a_bad_regions_entry_is_named(tmp_path, entry, message):
    manifest = {"format": "rigspace.bundle", "format_version": 2, "joints": ["root"],
                "rotation_encoding": "rot6d", "regions": [entry]}  # fmt: skip
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match=message.replace("[", r"\[").replace("]", r"\]")):
        read_manifest(tmp_path)


def test_a_region_listed_twice_is_named(tmp_path):
    entry = {"name": "face", "joint": "head", "bundle": "regions/face"}
    manifest = {"format": "rigspace.bundle", "format_version": 2, "joints": ["root"],
                "rotation_encoding": "rot6d", "regions": [entry, entry]}  # fmt: skip
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match="listed twice"):
        read_manifest(tmp_path)

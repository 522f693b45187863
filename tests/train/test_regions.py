"""`rigspace train` on a dataset with regions (capture --regions): each region's network is
trained after the body's into MODEL/regions/NAME, a bundle of its own, and the body's manifest
lists them; the budget is shared by image size."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rigspace.apps.train import budget_shares, region_training_config
from rigspace.sdk.bundle import BundleError, read_manifest
from rigspace.sdk.cli import main
from rigspace.sdk.errors import RigspaceError
from rigspace.train.config import preset
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
    # eval measures each region's network on its own dataset, beside the body's.
    assert main(["eval", str(out), str(region_dataset), "--no-baselines", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["rows"][0]["predictor"] == "model"
    face_result = result["regions"]["face"]
    assert face_result["dataset"].endswith("regions/face") and face_result["samples"] > 0
    assert main(["eval", str(out), str(region_dataset), "--no-baselines", "--limit", "2",
                 "--shapes", "jawOpen", "blink"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert f"region face ({out / 'regions' / 'face'} on" in printed
    assert "shape response of the model" in printed and "shape response of region face" in printed
    assert main(["eval", str(out), str(region_dataset), "--no-baselines", "--limit", "2",
                 "--json", "--shapes", "--shape-samples", "3"]) == 0  # fmt: skip
    result = json.loads(capsys.readouterr().out)
    shapes = {r["shape"]: r for r in result["regions"]["face"]["shapes"]}
    assert {r["samples"] for r in shapes.values()} == {3}
    assert main(["eval", str(out), str(region_dataset), "--no-baselines", "--shapes",
                 "--shape-samples", "0"]) == 2  # fmt: skip
    assert "--shape-samples is 0" in capsys.readouterr().err
    assert set(shapes) == set(read_manifest(out / "regions" / "face").blend_shapes)
    blink = shapes["blink"]  # the eyes' points pulled in: the mesh's face moves where seen
    assert blink["samples"] > 0 and blink["mesh_change"] > 0 and blink["network_change"] >= 0
    # The region reads its own shapes alone: jawOpen drops the lowest ring, on the neck, so
    # nothing of the face moves with it and the face's network does not read it.
    assert set(shapes) == {"blink", "brow"}
    # The body cannot be measured on the region's dataset (its own inputs): named, with the fix.
    assert main(["eval", str(out), str(region_dataset / "regions" / "face"), "--no-baselines"]) == 2
    err = capsys.readouterr().err
    assert "records 2 joints and 2 blend shapes" in err and "region face's dataset" in err
    assert main(["eval", str(out / "regions" / "face"), str(region_dataset / "regions" / "face"),
                 "--no-baselines"]) == 0  # fmt: skip
    # --force replaces the bundle and its regions; --no-regions trains the body alone.
    assert main([*args, "--force", "--no-regions"]) == 0
    assert read_manifest(out).regions == () and not (out / "regions").exists()


@pytest.mark.slow
def test_the_shape_response_moves_the_shape_s_weight_alone(region_dataset, tmp_path, monkeypatch):
    """Each measured pair of rows differs in the shape's weight alone, 0 then 1: the weights
    follow the rotations' joints x 6 columns (not joints columns)."""
    from rigspace.sdk.model import BundleModel
    from rigspace.train.shapes import shape_response

    out = tmp_path / "model"
    assert main(["train", str(region_dataset), "--out", str(out), "--preset", "tiny",
                 "--steps", "3", "--no-int8", "--no-regions"]) == 0  # fmt: skip
    seen: list[np.ndarray] = []
    predict = BundleModel.predict

    def recording(self, rows, *args, **kwargs):
        seen.append(np.array(rows))
        return predict(self, rows, *args, **kwargs)

    monkeypatch.setattr(BundleModel, "predict", recording)
    shape_response(out, region_dataset, ["smile"], limit=2)
    manifest = read_manifest(out)
    column = 6 * len(manifest.joints) + list(manifest.blend_shapes).index("smile")
    assert len(seen) == 2
    for rows in seen:
        assert np.flatnonzero(rows[0] != rows[1]).tolist() == [column]
        assert rows[:, column].tolist() == [0.0, 1.0]


@pytest.mark.slow
def test_regions_only_adds_regions_to_a_body_trained_before(region_dataset, tmp_path, capsys):
    out = tmp_path / "model"
    args = ["train", str(region_dataset), "--out", str(out), "--preset", "tiny", "--steps", "3",
            "--no-int8"]  # fmt: skip
    # Nothing to add the regions to yet: named, nothing written.
    assert main([*args, "--regions-only"]) == 2
    assert "holds none" in capsys.readouterr().err and not out.exists()
    assert main([*args, "--no-regions"]) == 0
    body_files = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    before = read_manifest(out)
    assert before.regions == ()
    assert main([*args, "--regions-only"]) == 0
    assert "region face: training at 16x16" in capsys.readouterr().out
    after = read_manifest(out)
    assert [(r.name, r.folder) for r in after.regions] == [("face", out / "regions" / "face")]
    # The body is untouched but for its manifest's list of regions.
    for name, data in body_files.items():
        if name != "manifest.json":
            assert (out / name).read_bytes() == data, name
    document = json.loads((out / "manifest.json").read_text())
    del document["regions"]
    assert document == json.loads(body_files["manifest.json"])
    # Again: the region's run is there; without --resume or --force it is refused, by name.
    capsys.readouterr()
    assert main([*args, "--regions-only"]) == 2
    assert "region face was trained into" in capsys.readouterr().err
    assert main([*args, "--regions-only", "--force"]) == 0
    assert read_manifest(out).regions[0].name == "face"
    # --region picks the regions to train again; one the dataset lacks is named before any work.
    assert main([*args, "--regions-only", "--force", "--region", "face"]) == 0
    assert "region face: training at 16x16" in capsys.readouterr().out
    assert main([*args, "--regions-only", "--force", "--region", "leftHand"]) == 2
    assert "--region leftHand" in capsys.readouterr().err and (out / "regions" / "face").is_dir()
    assert main([*args, "--region", "face"]) == 2
    assert "--region picks the regions --regions-only trains" in capsys.readouterr().err
    # The body trained on (--resume, a new export of it): its regions stay listed.
    assert main([*args, "--no-regions", "--resume", "--steps", "5"]) == 0
    assert [r.name for r in read_manifest(out).regions] == ["face"]


def test_the_budget_is_shared_by_image_size():
    assert budget_shares(128, [64, 64], None) == [None, None, None]
    body, face, hand = budget_shares(128, [64, 32], 21.0)
    assert body + face + hand == pytest.approx(21.0)
    assert body == pytest.approx(4 * face) and face == pytest.approx(4 * hand)


def test_a_region_trains_at_its_own_resolution_and_width():
    body = preset("small")
    region = region_training_config(body, 64, None)
    assert (region.resolution, region.start_resolution) == (64, 16)
    assert region.base_width == body.base_width and region.latent == body.latent
    assert region_training_config(body, 64, 64).base_width == 64
    assert region_training_config(preset("tiny"), 8, None).start_resolution == 8
    with pytest.raises(RigspaceError, match="--region-width is 0"):
        region_training_config(body, 64, 0)


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


def test_the_shape_response_compares_the_network_s_change_with_the_mesh_s():
    from rigspace.sdk.render import Maps
    from rigspace.train.shapes import change, summarise

    def maps(albedo):
        h, w = albedo.shape[:2]
        return Maps(albedo=albedo, normal=np.zeros((h, w, 3), np.float32),
                    depth=np.ones((h, w), np.float32), mask=np.ones((h, w), np.float32))  # fmt: skip

    rng = np.random.default_rng(0)
    a = maps(rng.random((8, 8, 3)).astype(np.float32))
    b = maps(a.albedo + np.where(np.arange(8)[:, None, None] < 4, 0.5, 0.0).astype(np.float32))
    moved = change(a, b)
    pixels = np.ones((8, 8), bool)
    same = summarise("jawOpen", [(moved, moved, pixels)])  # the network moves as the mesh does
    assert same.ratio == pytest.approx(1.0) and same.correlation == pytest.approx(1.0)
    elsewhere = summarise("jawOpen", [(moved, moved[::-1], pixels)])  # as much, other pixels
    assert elsewhere.ratio == pytest.approx(1.0) and elsewhere.correlation < -0.9
    still = summarise("jawOpen", [(moved, np.zeros_like(moved), pixels)])  # ignores the shape
    assert still.ratio == 0.0 and np.isnan(still.correlation)
    assert np.isnan(summarise("jawOpen", [(moved, moved, ~pixels)]).ratio)  # no pixel: no number


def test_shape_weight_without_texture_charts_is_named_before_anything_is_written(
    region_dataset, tmp_path, capsys
):
    out = tmp_path / "model"
    args = ["train", str(region_dataset), "--out", str(out), "--preset", "tiny", "--steps", "1",
            "--no-int8", "--shape-weight", "4"]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--shape-weight" in err and "texture charts" in err and "Traceback" not in err
    assert not out.exists()

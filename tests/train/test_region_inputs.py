"""A region reads its own inputs (issue 33): CesiumMan's head region records and reads the joints
from the root to the head (5 of the skeleton's 19), not the arms and legs; it trains with pose
conditioning on that closed tree, and the runtime feeds its network the same rows at a ring
camera."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pxr import Sdf, Usd

from rigspace.capture.pipeline import capture
from rigspace.sdk.cli import main
from tests.capture.conftest import CHARACTER, SCENE, SMALL, scene_variant
from tests.regions import ring_rows

pytest.importorskip("torch", reason="training needs the train extra (torch)")

HEAD = "Skeleton_neck_joint_2"
CHAIN = 5
"""The root's torso joints (3), the neck and the head."""


@pytest.fixture(scope="module")
def head_region(tmp_path_factory):
    """(scene, dataset, bundle): the head region captured SMALL at 16x16 and trained with the
    tiny preset for 3 steps with bones2d conditioning."""
    folder = tmp_path_factory.mktemp("head_region")
    scene = scene_variant(folder, "head", SCENE.read_text())
    stage = Usd.Stage.Open(str(scene))
    prim = stage.GetPrimAtPath(CHARACTER)
    prim.ApplyAPI("RigspaceRegionAPI", "head")
    prim.CreateAttribute("rigspace:region:head:joint", Sdf.ValueTypeNames.Token).Set(HEAD)
    prim.CreateAttribute("rigspace:region:head:resolution", Sdf.ValueTypeNames.Int).Set(16)
    stage.GetRootLayer().Save()
    dataset = folder / "ds"
    result = capture(scene, CHARACTER, dataset, SMALL, workers=1, progress=False,
                     warn=lambda _: None, region="head")  # fmt: skip
    assert result.complete
    bundle = folder / "bundle"
    train = ["train", str(dataset), "--out", str(bundle), "--preset", "tiny", "--steps", "3",
             "--no-int8", "--conditioning", "bones2d", "--resolution", "16"]  # fmt: skip
    assert main(train) == 0
    return scene, dataset, bundle


def test_the_region_records_its_chain_not_the_limbs(head_region):
    _, dataset, _ = head_region
    manifest = json.loads((dataset / "manifest.json").read_text())
    joints = manifest["joints"]
    assert len(joints) == CHAIN and joints[-1].endswith(HEAD)
    assert not [j for j in joints if "arm" in j or "leg" in j]
    assert all(j == joints[0] or j.rsplit("/", 1)[0] in joints for j in joints)  # a closed tree
    with np.load(dataset / "params.npz") as table:
        assert table["rig"].shape[1:] == (CHAIN, 6) and "blend" not in table.files
    settings = json.loads((dataset / "capture.json").read_text())
    assert len(settings["joints"]) == 19 and settings["input_joints"] == joints


def test_the_bundle_reads_the_chain_and_the_runtime_feeds_the_recorded_rows(head_region):
    from rigspace.runtime.character import NeuralCharacter
    from rigspace.sdk.model import BundleModel
    from rigspace.sdk.stage import open_stage

    scene, dataset, bundle = head_region
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert len(manifest["joints"]) == CHAIN
    assert len(manifest["conditioning"]["skeleton"]["parents"]) == CHAIN
    stage = open_stage(scene)
    # The region's bundle as the part that draws it: it looks at the head.
    part = NeuralCharacter(stage.GetPrimAtPath(CHARACTER), BundleModel(bundle))
    assert len(part.order) == CHAIN
    table = np.load(dataset / "params.npz")
    for rows, recorded, _ in ring_rows(part, part.pose, table, range(0, len(table["time"]), 7)):
        assert rows.shape == (1, CHAIN * 6)
        assert np.abs(rows[0] - recorded).max() < 1e-4
        out = part.model.predict(rows, 16)
        assert np.isfinite(out["albedo"]).all()

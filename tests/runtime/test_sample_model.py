"""The committed sample model: it loads without torch, fits the previs skeleton, and is trained."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rigspace.runtime.character import NeuralCharacter
from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import RenderSettings, choose_renderer
from rigspace.sdk.stage import open_stage
from rigspace.train.metrics import mask_iou, psnr
from tests.conftest import REPO
from tests.runtime.conftest import evaluate_layer, view_character

MODEL = REPO / "samples" / "models" / "sample"
PREVIS = REPO / "samples" / "scenes" / "previs.usda"
BUNDLE_BUDGET = 20 * 2**20
# The model's held-out-view means are 28.4 dB and 0.85 IoU (docs/training.md); one training
# view of one frame must clear these floors, far above what an untrained network gives.
PSNR_FLOOR = 22.0
IOU_FLOOR = 0.75


def test_bundle_is_complete_and_small():
    manifest = json.loads((MODEL / "manifest.json").read_text())
    size = sum(f["bytes"] for f in manifest["files"].values())
    assert size < BUNDLE_BUDGET
    assert [level["resolution"] for level in manifest["levels"]] == [8, 16, 32, 64, 128]
    assert {"heldout-views", "heldout-clips", "train"} <= set(manifest["metrics"])
    for precision in ("fp32", "int8"):
        model = BundleModel(MODEL, precision)
        for r in model.resolutions:
            out = model.predict(np.zeros((2, 22 * 6), np.float32), r)
            assert out["albedo"].shape == (2, 3, r, r) and np.all(np.isfinite(out["depth"]))


@pytest.fixture(scope="module")
def hero():
    stage = open_stage(PREVIS)
    character = NeuralCharacter(stage.GetPrimAtPath("/World/Hero"), BundleModel(MODEL))
    character.stage = stage  # keep the stage alive with the character
    return character


def test_the_model_draws_what_the_mesh_draws(hero):
    """At a ring camera (the billboard fills the image), the network's maps match the mesh's."""
    time = 700.0  # mid-stretch, a training clip; 30 degrees is a training view of the ring
    offset = np.array([np.sin(np.radians(30.0)), 0.0, np.cos(np.radians(30.0))]) * 450.0
    world, _, camera, billboard = view_character(hero, time, offset, 128, 128, near=10, far=5000)
    layer = evaluate_layer(hero, world, billboard, camera, ("albedo", "geometry"))
    assert layer.level == 128 and (layer.x0, layer.y0) == (0, 0)
    renderer = choose_renderer("auto").create(RenderSettings())
    truth = renderer.render(hero.rig.posed_meshes(time), camera)
    renderer.close()
    assert psnr(layer.albedo, truth.albedo) > PSNR_FLOOR
    assert mask_iou(layer.mask, truth.mask) > IOU_FLOOR

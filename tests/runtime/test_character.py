"""A neural character evaluated into a frame: placement, level of detail, maps and errors."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="these tests train a tiny model (the train extra)")

from rigspace.runtime.character import NeuralCharacter, joint_order  # noqa: E402
from rigspace.sdk.camera import Camera  # noqa: E402
from rigspace.sdk.errors import SceneError  # noqa: E402
from rigspace.sdk.model import BundleModel  # noqa: E402
from rigspace.sdk.stage import open_stage  # noqa: E402
from rigspace.train.config import preset  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402
from rigspace.train.loop import train  # noqa: E402
from tests.runtime.conftest import evaluate_layer, view_character  # noqa: E402
from tests.train.conftest import CHARACTER, SCENE  # noqa: E402


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory, tiny_dataset):
    run = tmp_path_factory.mktemp("model")
    train(tiny_dataset, run / "training", preset("tiny"), progress=False)
    export_bundle(run / "training", run, int8=False)
    return BundleModel(run)


@pytest.fixture(scope="module")
def hero(tiny_model):
    stage = open_stage(SCENE)
    character = NeuralCharacter(stage.GetPrimAtPath(CHARACTER), tiny_model)
    character.stage = stage  # keep the stage alive with the character
    return character


def test_layer_sits_on_the_joint_at_its_depth(hero):
    world, joint, camera, billboard = view_character(hero, 10.0, [0.4, 0.3, 3.0], 96, 64)
    assert billboard.visible
    layer = evaluate_layer(hero, world, billboard, camera, ("albedo", "geometry"))
    assert layer.level == hero.model.level_for(billboard.size_px)
    h, w = layer.mask.shape
    assert 0 <= layer.x0 and layer.x0 + w <= 96 and 0 <= layer.y0 and layer.y0 + h <= 64
    assert layer.albedo.shape == (h, w, 3) and layer.normal.shape == (h, w, 3)
    covered = layer.mask > 0.5
    if covered.any():
        assert np.allclose(np.linalg.norm(layer.normal[covered], axis=-1), 1, atol=1e-3)
        distance = np.linalg.norm(camera.to_camera(joint[None])[0])
        assert np.all(np.abs(layer.depth[covered] - distance) < 1.5)  # within the character
    x, y = camera.project(joint[None])[0][0]
    assert layer.x0 <= x <= layer.x0 + w and layer.y0 <= y <= layer.y0 + h


def test_small_on_screen_picks_a_small_level(hero):
    world, _, far, billboard = view_character(hero, 1.0, [0.0, 0.0, 60.0], 128, 128)
    assert billboard.size_px < 8  # the smallest level that covers it is 8x8
    assert evaluate_layer(hero, world, billboard, far, ("albedo", "geometry")).level == 8


def test_rig_parameters_at_a_ring_camera_equal_the_captured_ones(hero, tiny_dataset):
    with np.load(tiny_dataset / "params.npz") as table:
        k = 5
        camera_to_world, time, rig = (
            table["camera_to_world"][k],
            float(table["time"][k]),
            table["rig"][k],
        )
    camera = Camera(camera_to_world, 32, 32, focal_length=35, horizontal_aperture=20.955)
    world = hero.pose(time)
    billboard = hero.place(world, camera)
    assert np.allclose(billboard.rotation, np.eye(3), atol=1e-6)  # the ring looks at the joint
    ours = hero.parameters(world, billboard, camera).reshape(-1, 6)
    assert np.abs(ours - rig[hero.order]).max() < 1e-4


def test_missing_joints_are_named():
    with pytest.raises(SceneError, match="lacks: tail, wing"):
        joint_order(["hips", "tail", "wing"], ["hips", "hips/spine"], "Neural character /Hero")


def test_nan_animation_is_a_clear_error(hero, monkeypatch):
    real = hero.rig.world_transforms
    monkeypatch.setattr(hero.rig, "world_transforms", lambda t, local=None: real(t) * np.nan)
    with pytest.raises(SceneError, match="NaN or Inf joint transforms at time 3"):
        hero.pose(3.0)

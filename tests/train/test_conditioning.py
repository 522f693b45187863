"""Pose-guided conditioning end to end: FK joints, training, the exported graphs, the runtime."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

import onnxruntime as ort  # noqa: E402

from rigspace.capture.dataset import DatasetError, read_manifest  # noqa: E402
from rigspace.runtime.character import NeuralCharacter  # noqa: E402
from rigspace.sdk.camera import Camera  # noqa: E402
from rigspace.sdk.conditioning import joints2d  # noqa: E402
from rigspace.sdk.model import BundleModel  # noqa: E402
from rigspace.sdk.posing import CharacterRig  # noqa: E402
from rigspace.sdk.stage import open_stage  # noqa: E402
from rigspace.train.conditioning import ConditionMaps, dataset_skeleton  # noqa: E402
from rigspace.train.config import ConfigError, preset  # noqa: E402
from rigspace.train.data import SampleSet  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402
from rigspace.train.loop import build_model, train  # noqa: E402
from rigspace.train.loss import coverage_loss, edge_weights  # noqa: E402
from rigspace.train.network import Rig2Image, UpBlock  # noqa: E402
from tests.runtime.conftest import evaluate_layer, view_character  # noqa: E402
from tests.train.conftest import CHARACTER, SCENE  # noqa: E402

TOLERANCE = 1e-5
"""fp32 ONNX against torch, per output element."""


@pytest.fixture(scope="module")
def conditioned(tmp_path_factory, tiny_dataset):
    """A tiny bones2d run and its bundle (fp32 only: int8 is tested in test_int8_conditioned)."""
    folder = tmp_path_factory.mktemp("conditioned")
    config = preset("tiny", conditioning="bones2d")
    result = train(tiny_dataset, folder / "training", config, progress=False)
    assert result.stopped == "done"
    export_bundle(folder / "training", folder / "bundle", int8=False)
    return folder


def test_joints2d_is_the_posed_skeleton_seen_by_the_capture_camera(tiny_dataset):
    """FK from the captured rig parameters lands on UsdSkel's joints projected by each sample's
    own camera (params.npz intrinsics), for every sample of the dataset."""
    manifest = read_manifest(tiny_dataset)
    skeleton = dataset_skeleton(tiny_dataset, manifest)
    stage = open_stage(SCENE)
    rig = CharacterRig(stage.GetPrimAtPath(CHARACTER))
    with np.load(tiny_dataset / "params.npz") as table:
        columns = {k: table[k] for k in ("rig", "time", "camera_to_world", "intrinsics")}
    ours = joints2d(columns["rig"], skeleton).reshape(len(columns["rig"]), -1, 2)
    size = manifest.resolution
    for k in range(len(ours)):
        world = rig.world_transforms(float(columns["time"][k]))[:, :3, 3]
        to_camera = np.linalg.inv(columns["camera_to_world"][k])
        p = world @ to_camera[:3, :3].T + to_camera[:3, 3]
        fx, fy, cx, cy = columns["intrinsics"][k]
        pixels = np.stack([cx + fx * p[:, 0] / -p[:, 2], cy - fy * p[:, 1] / -p[:, 2]], axis=1)
        assert np.abs(ours[k] - (pixels / size * 2 - 1)).max() < 1e-5


@pytest.fixture(scope="module")
def added(tmp_path_factory, tiny_dataset):
    """A tiny bones2d run whose maps are 1x1-projected and added, computed up to 16x16 only."""
    folder = tmp_path_factory.mktemp("added")
    config = preset("tiny", conditioning="bones2d", conditioning_mode="add", conditioning_top=16)
    assert train(tiny_dataset, folder / "training", config, progress=False).stopped == "done"
    export_bundle(folder / "training", folder / "bundle", int8=False)
    return folder


def test_conditioned_bundle_records_its_input_and_matches_torch(conditioned, tiny_dataset):
    manifest = json.loads((conditioned / "bundle" / "manifest.json").read_text())
    assert manifest["conditioning"]["kind"] == "bones2d"
    assert manifest["conditioning"]["mode"] == "concat"
    # Format 3: a rigspace that cannot feed joints2d refuses the bundle by its version.
    assert manifest["format_version"] == 3
    assert "joints2d" in manifest["inputs"]
    assert all(not level["int8"] for level in manifest["levels"])
    _bundle_matches_torch(conditioned, tiny_dataset)


def test_added_conditioning_keeps_the_paper_convolutions_and_matches_torch(added, tiny_dataset):
    """conditioning_mode add: every 3x3 convolution has the paper's channels; one 1x1 projection
    per block; the 32x32 block adds the 16x16 maps' projection upsampled; the exported graphs,
    fed joints2d by the runtime, match torch."""
    manifest = json.loads((added / "bundle" / "manifest.json").read_text())
    assert manifest["conditioning"]["mode"] == "add" and manifest["conditioning"]["top"] == 16
    model = _bundle_matches_torch(added, tiny_dataset)
    paper = Rig2Image(model.shape, replace(model.config, conditioning="none"))
    theirs = dict(paper.named_modules())
    blocks = [(name, m) for name, m in model.named_modules() if isinstance(m, UpBlock)]
    assert len(blocks) == 5  # the trunk's, and 16x16 and 32x32 per branch
    for name, block in blocks:
        assert block.conv1.weight.shape == theirs[name].conv1.weight.shape, name
        assert block.project is not None and block.project.kernel_size == (1, 1), name
    assert [b.maps_scale for b in model.albedo.blocks] == [1, 2]  # 16x16, 32x32
    bundle = BundleModel(added / "bundle")
    level = bundle.levels[32]["albedo"]
    graph = ort.InferenceSession(str(added / "bundle" / level), providers=["CPUExecutionProvider"])
    assert [i.name for i in graph.get_inputs()] == ["features", "joints2d"]


def test_conditioning_top_must_be_a_level():
    with pytest.raises(ConfigError, match="--conditioning-top is 24"):
        preset("tiny", conditioning="bones2d", conditioning_top=24)
    with pytest.raises(ConfigError, match="--conditioning-mode is 'mul'"):
        preset("tiny", conditioning="bones2d", conditioning_mode="mul")


def _bundle_matches_torch(conditioned, tiny_dataset) -> Rig2Image:
    """The bundle's graphs (joints2d fed by BundleModel, as the runtime does) against torch."""
    bundle = conditioned / "bundle"
    model, _, _ = build_model(conditioned / "training")
    samples = SampleSet(tiny_dataset, "heldout-views")
    samples.skeleton = dataset_skeleton(tiny_dataset, samples.manifest)
    batch = samples.batch(np.arange(6))
    rig, j2d = batch["rig"], batch["joints2d"]
    assert j2d.shape == (6, 2 * len(samples.joints))
    bundle_model = BundleModel(bundle)
    assert np.array_equal(bundle_model.joints2d(rig), j2d)  # the runtime's input is training's
    trunk = ort.InferenceSession(str(bundle / "trunk.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in trunk.get_inputs()] == ["rig", "joints2d"]
    with torch.no_grad():
        heads = model(torch.from_numpy(rig), 32, joints2d=torch.from_numpy(j2d))
        features = model.features(torch.from_numpy(rig), torch.from_numpy(j2d)).numpy()
    # The trunk's features are unbounded (about 3.5 here): within 1e-5 of their magnitude; the
    # maps below, in [0, 1] or depth units, within 1e-5 absolute. (With one onnxruntime thread
    # the features differed by 1.3e-5 absolute: float32 rounding, 4e-6 of their magnitude.)
    scale = max(1.0, float(np.abs(features).max()))
    assert np.abs(trunk.run(None, {"rig": rig, "joints2d": j2d})[0] - features).max() < (
        TOLERANCE * scale
    )
    for k, resolution in enumerate(bundle_model.resolutions):
        out = bundle_model.predict(rig, resolution)
        albedo = torch.sigmoid(heads["albedo"][k][:, 0:3]).numpy()
        mask = torch.sigmoid(heads["geometry"][k][:, 4:5]).numpy()
        depth = heads["geometry"][k][:, 0:1].numpy()
        assert np.abs(out["albedo"] - albedo).max() < TOLERANCE, resolution
        assert np.abs(out["mask"] - mask).max() < TOLERANCE, resolution
        assert np.abs(out["depth"] - depth).max() < TOLERANCE, resolution
    return model


@pytest.fixture(scope="module")
def hero(conditioned):
    stage = open_stage(SCENE)
    character = NeuralCharacter(stage.GetPrimAtPath(CHARACTER), BundleModel(conditioned / "bundle"))
    character.stage = stage  # keep the stage alive with the character
    return character


def test_runtime_conditioning_equals_training_at_ring_cameras(hero, tiny_dataset):
    """At every ring camera (training and held-out views) the runtime's joints2d and maps,
    from the posed skeleton and the billboard's virtual camera, equal the dataset item's."""
    samples = {s: SampleSet(tiny_dataset, s) for s in ("train", "heldout-views")}
    skeleton = dataset_skeleton(tiny_dataset, samples["train"].manifest)
    maps = ConditionMaps("bones2d", skeleton.parents, 0.05)
    with np.load(tiny_dataset / "params.npz") as table:
        c2w, times = table["camera_to_world"], table["time"]
    for split, sample_set in samples.items():
        sample_set.skeleton = skeleton
        for k in range(len(sample_set)):
            row = int(sample_set.rows[k])
            if times[row] != times[sample_set.rows[0]]:
                continue  # one pose, every view of the ring
            camera = Camera(c2w[row], 32, 32, focal_length=35, horizontal_aperture=20.955)
            world = hero.pose(float(times[row]))
            billboard = hero.place(world, camera)
            runtime = hero.model.joints2d(hero.parameters(world, billboard, camera))
            training = sample_set.item(k)["joints2d"][None]
            assert np.abs(runtime - training).max() < 1e-4, (split, k)
            with torch.no_grad():
                a = maps(torch.from_numpy(runtime), 32)
                b = maps(torch.from_numpy(training), 32)
            assert torch.abs(a - b).max() < 1e-3, (split, k)


def test_runtime_renders_a_conditioned_character(hero, monkeypatch):
    # The lit layer's pixels are moved by their depth's parallax, the unlit one has no depth
    # (runtime/parallax.py); the colour contract below is about premultiplying, so both are
    # drawn as the network drew them.
    monkeypatch.setattr("rigspace.runtime.character.reseen", lambda out, *_: out)
    world, joint, camera, billboard = view_character(hero, 2.0, [0.5, 0.2, 3.0], 64, 64)
    layer = evaluate_layer(hero, world, billboard, camera, ("albedo", "geometry"))
    assert layer.albedo is not None and np.isfinite(layer.albedo).all()
    assert np.isfinite(layer.mask).all() and np.isfinite(layer.depth).any()
    # Even a 40-step model puts more coverage on the character's centre than on the edges.
    x, y = camera.project(joint[None])[0][0]
    centre = layer.mask[int(y) - layer.y0, int(x) - layer.x0]
    border = np.concatenate([layer.mask[0], layer.mask[-1], layer.mask[:, 0], layer.mask[:, -1]])
    assert centre > 2 * border.mean()
    unlit = evaluate_layer(hero, world, billboard, camera, ("albedo",))
    # The same colour, premultiplied by each layer's own coverage (the albedo branch's alpha
    # unlit, the geometry's mask lit: sdk.texturing.repremultiplied).
    both = (unlit.mask > 0.01) & (layer.mask > 0.01)
    assert both.any()
    straight = lambda x: x.albedo[both] / x.mask[both][:, None]  # noqa: E731
    assert np.allclose(straight(unlit), straight(layer), atol=1e-5)


def test_unconditioned_bundles_keep_their_single_input(tiny_run, tmp_path):
    export_bundle(tiny_run, tmp_path / "bundle", int8=False)
    model = BundleModel(tmp_path / "bundle")
    assert model.manifest.conditioning is None and model.skeleton is None
    assert model.manifest.format_version == 2
    trunk = ort.InferenceSession(
        str(tmp_path / "bundle" / "trunk.onnx"), providers=["CPUExecutionProvider"]
    )
    assert [i.name for i in trunk.get_inputs()] == ["rig"]
    assert model.joints2d(np.zeros((1, 6 * len(model.joints)), np.float32)) is None


def test_conditioning_needs_the_dataset_scene(tiny_dataset, tmp_path):
    manifest = replace(read_manifest(tiny_dataset), scene=str(tmp_path / "gone.usda"))
    with pytest.raises(DatasetError, match=r"gone\.usda, which does not exist"):
        dataset_skeleton(tiny_dataset, manifest)


def test_unknown_options_name_the_flag():
    with pytest.raises(ConfigError, match="--conditioning is 'heatmaps'"):
        preset("tiny", conditioning="heatmaps")
    with pytest.raises(ConfigError, match="--mask-loss"):
        preset("tiny", mask_loss="dice")


def test_mask_loss_options():
    target = torch.zeros(1, 1, 8, 8)
    target[..., 2:6, 2:6] = 1.0
    weight = edge_weights(target, 4.0)
    assert weight[0, 0, 0, 0] == 1.0 and weight[0, 0, 3, 3] == 1.0  # far outside, deep inside
    assert weight[0, 0, 2, 2] == 5.0 and weight[0, 0, 1, 1] == 5.0  # on and beside the edge
    logits = torch.where(target > 0.5, 8.0, -8.0)
    for name in ("mixed", "bce", "soft-iou"):
        config = preset("tiny", mask_loss=name)
        good = coverage_loss(logits, target, config, weight)
        bad = coverage_loss(-logits, target, config, weight)
        assert 0 <= good < 0.01 and bad > 0.5, name

"""The texture head: its targets (numpy and torch agree), a loss that never compares coordinates
across charts, the device-clean network (meta device), and a textured run exported and read."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")
onnx = pytest.importorskip("onnx", reason="the export needs the train extra (onnx)")

from rigspace.sdk.model import BundleModel  # noqa: E402
from rigspace.train import graph_rewrite, loop  # noqa: E402
from rigspace.train import loss as loss_module  # noqa: E402
from rigspace.train.config import preset  # noqa: E402
from rigspace.train.data import SampleSet, chart_boxes, chart_targets  # noqa: E402
from rigspace.train.export import export_bundle  # noqa: E402
from rigspace.train.loss import chart_downsample, texture_loss  # noqa: E402
from rigspace.train.network import Rig2Image, Shape, texture_channels, texture_maps  # noqa: E402
from rigspace.train.quantize import softmax_nodes  # noqa: E402
from tests.conftest import write_bundle_manifest  # noqa: E402

TINY = preset("tiny", texture=True)
BOXES = (
    np.array([[0, 0], [0.25, 0.5], [0.75, 0.5]], np.float32),
    np.array([[1, 1], [0.25, 0.5], [0.25, 0.5]], np.float32),
)
"""Two charts: the left and right halves of the texture."""


def _labels(size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A chart image with blocks of charts 0, 1, 2 and uvs inside each chart's box."""
    rng = np.random.default_rng(seed)
    chart = rng.integers(0, 3, (size // 2, size // 2)).repeat(2, 0).repeat(2, 1)
    chart[rng.random((size, size)) < 0.2] = rng.integers(0, 3)
    uv = BOXES[0][chart] + BOXES[1][chart] * rng.uniform(-1, 1, (size, size, 2))
    return chart.astype(np.int32), np.where(chart[..., None] > 0, uv, 0).astype(np.float32)


def test_chart_targets_take_each_boxes_commonest_chart_and_its_own_mean():
    chart = np.array([[1, 1, 2, 0], [1, 2, 2, 0], [0, 0, 0, 0], [0, 0, 2, 2]], np.int32)
    uv = np.zeros((4, 4, 2), np.float32)
    uv[..., 0] = np.where(chart == 1, 0.1, np.where(chart == 2, 0.9, 0))
    uv[1, 0, 0] = 0.3  # chart 1's pixels: mean u 0.1 0.1 0.3 -> 1/6 (never 0.9's)
    target_chart, local = chart_targets(chart, uv, BOXES, 2)
    np.testing.assert_array_equal(target_chart, [[1, 2], [0, 2]])
    assert local[0, 0, 0] == pytest.approx((0.5 / 3 - 0.25) / 0.25)
    assert local[0, 0, 1] == pytest.approx((0.9 - 0.75) / 0.25)
    assert np.all(local[:, 1, 0] == 0)  # chart 0: no coordinates


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_numpy_and_torch_targets_agree(factor):
    """Lower levels' targets (loss.chart_downsample, torch) equal the training resolution's
    made from the same pixels (data.chart_targets, numpy)."""
    chart, uv = _labels(16)
    full_chart, full_uv = chart_targets(chart, uv, BOXES, 1)
    expected_chart, expected_uv = chart_targets(chart, uv, BOXES, factor)
    got_chart, got_uv = chart_downsample(
        torch.from_numpy(full_chart)[None, None], torch.from_numpy(full_uv)[None], 16 // factor, 2
    )
    np.testing.assert_array_equal(got_chart[0, 0].numpy(), expected_chart)
    keep = expected_chart > 0
    np.testing.assert_allclose(got_uv[0].numpy()[:, keep], expected_uv[:, keep], atol=1e-5)


def _head(charts: int, size: int, seed: int = 0) -> torch.Tensor:
    torch.manual_seed(seed)
    return torch.randn(2, 4 + texture_channels(charts), size, size)


def test_the_loss_reads_only_the_target_charts_coordinates():
    """Changing a chart's coordinates where another chart is the target changes nothing: no
    coordinate is ever compared across a seam; changing them on its own pixels does."""
    size = 8
    chart, uv = _labels(size)
    target_chart, local = chart_targets(chart, uv, BOXES, 1)
    target = {
        "chart": torch.from_numpy(target_chart)[None, None].repeat(2, 1, 1, 1),
        "uv": torch.from_numpy(local)[None].repeat(2, 1, 1, 1),
        "mask": torch.ones(2, 1, size, size),
    }
    head = _head(2, size)

    def loss(h):
        return texture_loss(*texture_maps(h, 2), target, TINY)

    base = loss(head)
    elsewhere = head.clone()
    _, coords = texture_maps(elsewhere, 2)
    not_one = torch.from_numpy(target_chart != 1)
    coords[:, 0:2, not_one] += 100.0  # chart 1's pair where chart 1 is not the target
    assert loss(elsewhere)["uv"] == pytest.approx(float(base["uv"]))
    own = head.clone()
    texture_maps(own, 2)[1][:, 0:2, ~not_one] += 1.0
    assert loss(own)["uv"] > base["uv"] + 0.1


def test_the_shape_weight_makes_an_error_where_the_shapes_move_cost_more():
    """--shape-weight: the same albedo error costs 1 + weight times more on pixels of mobility
    1 than on still ones (a weighted mean), and nothing changes at weight 0 or without a
    mobility map."""
    size = 8
    chart, uv = _labels(size)
    target_chart, local = chart_targets(chart, uv, BOXES, 1)
    mobility = torch.zeros(2, 1, size, size)
    mobility[:, :, :4] = 1.0  # the top half moves (a mouth), the bottom half is still
    target = {
        "albedo": torch.full((2, 3, size, size), 0.5),
        "mask": torch.ones(2, 1, size, size),
        "normal": torch.nn.functional.normalize(torch.ones(2, 3, size, size), dim=1),
        "depth": torch.zeros(2, 1, size, size),
        "chart": torch.from_numpy(target_chart)[None, None].repeat(2, 1, 1, 1),
        "uv": torch.from_numpy(local)[None].repeat(2, 1, 1, 1),
        "mobility": mobility,
    }
    albedo_head = torch.zeros(2, 4 + texture_channels(2), size, size)
    albedo_head[:, 3] = 10.0  # alpha logit: covered
    geometry_head = torch.zeros(2, 5, size, size)
    geometry_head[:, :3] = 1.0
    geometry_head[:, 4] = 10.0

    def terms(weight: float, rows: slice, with_mobility: bool = True) -> dict[str, float]:
        head = albedo_head.clone()
        head[:, :3, rows] += 0.3  # an albedo error on those rows
        config = replace(TINY, shape_weight=weight)
        wanted = target if with_mobility else {k: v for k, v in target.items() if k != "mobility"}
        out = loss_module.level_loss(head, geometry_head, dict(wanted), config)
        return {k: float(v) for k, v in out.items()}

    moving, still = slice(0, 4), slice(4, 8)
    assert terms(0.0, moving)["albedo"] == pytest.approx(terms(0.0, still)["albedo"])
    ratio = terms(4.0, moving)["albedo"] / terms(4.0, still)["albedo"]
    assert ratio == pytest.approx(5.0, rel=1e-3)
    assert terms(4.0, moving, with_mobility=False) == terms(0.0, moving)


def test_a_negative_or_nan_shape_weight_is_named():
    for bad in (-1.0, float("nan")):
        with pytest.raises(Exception, match="--shape-weight"):
            replace(TINY, shape_weight=bad).check()


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"conditioning": "joints2d"},
        {"conditioning": "bones2d", "conditioning_mode": "add", "conditioning_top": 16},
        {
            "conditioning": "bones2d",
            "conditioning_mode": "concat",
            "mask_loss": "bce",
            "bf16": True,
        },
        {"mask_loss": "soft-iou", "edge_weight": 2.0},
        {"texture_branch": "geometry"},
        {"texture_branch": "texture", "conditioning": "bones2d", "conditioning_mode": "add"},
        {"shape_weight": 4.0, "edge_weight": 1.0},
    ],
)
def test_forward_loss_and_backward_on_the_meta_device(overrides):
    """Every tensor the network, its conditioning and its loss make follows its inputs'
    device: on `meta` a tensor made without device= fails as it would on CUDA."""
    config = replace(TINY, **overrides)
    parents = (-1, 0, 1, 2)
    with torch.device("meta"):
        model = Rig2Image(Shape(4, parents=parents, charts=3), config)
    meta = torch.device("meta")
    size = 32
    batch = {
        "rig": torch.empty(2, 24, device=meta),
        "joints2d": torch.empty(2, 8, device=meta) if model.conditioned else None,
        "albedo": torch.empty(2, 3, size, size, device=meta),
        "mask": torch.empty(2, 1, size, size, device=meta),
        "normal": torch.empty(2, 3, size, size, device=meta),
        "depth": torch.empty(2, 1, size, size, device=meta),
        "chart": torch.zeros(2, 1, size, size, dtype=torch.long, device=meta),
        "uv": torch.empty(2, 2, size, size, device=meta),
        "mobility": torch.empty(2, 1, size, size, device=meta) if config.shape_weight else None,
    }
    # Through the training step's own forward_loss (its autocast included), bf16 on and off.
    loss, _ = loop.forward_loss(
        model, {k: v for k, v in batch.items() if v is not None}, size, 0.5, config
    )
    loss.backward()
    assert loss.device.type == "meta"


@pytest.fixture(scope="module")
def textured_run(tmp_path_factory, tiny_dataset):
    run = tmp_path_factory.mktemp("texture") / "run"
    result = loop.train(tiny_dataset, run, replace(TINY, steps_per_level=60), progress=False)
    assert result.stopped == "done"
    return run


def test_a_textured_run_learns_and_exports_its_head(textured_run, tiny_dataset, tmp_path):
    log = [json.loads(line) for line in (textured_run / "log.jsonl").read_text().splitlines()]
    assert {"chart", "uv"} <= set(log[-1])
    first = [r for r in log if r["resolution"] == 16]

    def mean(rows, key):
        return float(np.mean([r[key] for r in rows]))

    # Over the first level (60 steps, the tiny preset), both terms fall: measured 2.70 ->
    # 2.27 (chart, ln 15 = 2.71 at chance) and 0.28 -> 0.23 (coordinates).
    assert mean(first[-15:], "chart") < 0.95 * mean(first[:10], "chart")
    assert mean(first[-15:], "uv") < 0.95 * mean(first[:10], "uv")
    run = json.loads((textured_run / "run.json").read_text())
    boxes = chart_boxes(tiny_dataset)
    assert boxes is not None and run["charts"] == len(boxes[0]) - 1
    manifest = export_bundle(textured_run, tmp_path / "model", int8=False)
    assert manifest["texture"]["charts"] == run["charts"]
    assert (tmp_path / "model" / "charts.json").is_file()
    model = BundleModel(tmp_path / "model")
    rows = SampleSet(tiny_dataset, "heldout-views")
    out = model.predict(rows.rig[rows.rows[:2]], 32, ("albedo",))
    k = run["charts"]
    assert out["chart"].shape == (2, k + 1, 32, 32) and out["uv"].shape == (2, 2 * k, 32, 32)
    assert np.allclose(out["chart"].sum(axis=1), 1, atol=1e-5)  # probabilities
    # The ONNX graph computes what the torch head does.
    trained, _, _ = loop.build_model(textured_run)
    with torch.no_grad():
        heads = trained(torch.from_numpy(rows.rig[rows.rows[:2]]), 32, ("albedo",))
        logits, coords = texture_maps(heads["albedo"][-1], k)
    np.testing.assert_allclose(out["uv"], coords.numpy(), atol=1e-4)
    np.testing.assert_allclose(out["chart"], torch.softmax(logits, 1).numpy(), atol=1e-5)
    # The softmax is in the fast form (onnxruntime's Softmax node and channel reductions
    # over NCHW were most of the head's time): nothing for the bundle rewrite to do.
    graph = onnx.load(str(tmp_path / "model" / "albedo_32.onnx"))
    ops = {n.op_type for n in graph.graph.node}
    assert not {"Softmax", "ReduceMax", "ReduceSum"} & ops
    assert graph_rewrite.rewrite_bundle(tmp_path / "model", dry_run=True) == []
    # The softmax's nodes, its summing convolution among them, stay in float in the int8
    # graphs; the logits' own convolution does not.
    kept = softmax_nodes(tmp_path / "model" / "albedo_32.onnx")
    ops = {n.op_type for n in graph.graph.node if n.name in kept}
    assert ops == {"Split", "Max", "Sub", "Exp", "Conv", "Div"}
    kept_convs = [n for n in graph.graph.node if n.op_type == "Conv" and n.name in kept]
    assert len(kept_convs) == 1 and kept_convs[0].input[1].endswith("/ones")


def test_the_int8_graphs_keep_the_chart_softmax_in_float(textured_run, tmp_path):
    export_bundle(textured_run, tmp_path / "model", int8=True)
    graph = onnx.load(str(tmp_path / "model" / "albedo_32.int8.onnx")).graph
    producer = {out: node for node in graph.node for out in node.output}
    node, path = producer["chart"], []
    while node.op_type != "Conv":  # back from the output to the logits' convolution
        path.append(node.op_type)
        node = producer[node.input[0]]
    assert path[0] == "Div" and "Exp" in path
    assert not {"QuantizeLinear", "DequantizeLinear"} & set(path)
    # The sum's convolution reads the exponentials and its weights of one unquantised.
    (summing,) = [n for n in graph.node if n.name.startswith("channel_softmax") and
                  n.op_type == "Conv"]  # fmt: skip
    assert producer[summing.input[0]].op_type == "Exp" and summing.input[1] not in producer


def test_an_older_bundle_s_channel_softmax_is_rewritten_to_the_same_outputs(tmp_path):
    """A graph ending in Softmax(axis=1), as exports before channel_softmax wrote: rewritten
    in place, its manifest entry updated, its outputs unchanged; a second run finds nothing."""
    import hashlib

    import onnxruntime as ort
    from onnx import TensorProto, helper

    node = helper.make_node("Softmax", ["logits"], ["chart"], axis=1)
    graph = helper.make_graph(
        [node], "head",
        [helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["n", 7, 5, 4])],
        [helper.make_tensor_value_info("chart", TensorProto.FLOAT, ["n", 7, 5, 4])],
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    onnx.save(model, str(bundle / "albedo_8.onnx"))
    before = (bundle / "albedo_8.onnx").read_bytes()
    entry = {"bytes": len(before), "sha256": hashlib.sha256(before).hexdigest()}
    write_bundle_manifest(bundle, ["hips"], files={"albedo_8.onnx": entry})
    assert graph_rewrite.rewrite_bundle(bundle, dry_run=True) == ["albedo_8.onnx"]
    assert (bundle / "albedo_8.onnx").read_bytes() == before  # a dry run writes nothing
    assert graph_rewrite.rewrite_bundle(bundle) == ["albedo_8.onnx"]
    after = (bundle / "albedo_8.onnx").read_bytes()
    recorded = json.loads((bundle / "manifest.json").read_text())["files"]["albedo_8.onnx"]
    assert recorded == {"bytes": len(after), "sha256": hashlib.sha256(after).hexdigest()}
    ops = [n.op_type for n in onnx.load_from_string(after).graph.node]
    assert ops == ["Split", "Max", "Sub", "Exp", "Conv", "Div"]
    logits = np.random.default_rng(0).normal(0, 10, (3, 7, 5, 4)).astype(np.float32)
    run = [ort.InferenceSession(g, providers=["CPUExecutionProvider"]).run(None, {"logits": logits})[0]
           for g in (before, after)]  # fmt: skip
    np.testing.assert_allclose(run[1], run[0], atol=1e-6)
    assert graph_rewrite.rewrite_bundle(bundle) == []


def test_an_untextured_config_trains_no_head(tiny_dataset):
    items = SampleSet(tiny_dataset, "train")
    assert "chart" not in items.item(0)  # the head's targets only when asked for
    model = Rig2Image(Shape(19, charts=5), preset("tiny"))
    assert model.charts == 0 and model.albedo.heads[0].out_channels == 4


def test_a_damaged_chart_table_is_a_named_error(textured_run, tiny_dataset, tmp_path):
    from rigspace.capture.dataset import DatasetError
    from rigspace.sdk.bundle import BundleError

    dataset = tmp_path / "ds"
    shutil.copytree(tiny_dataset, dataset)
    (dataset / "charts.json").write_text('{"format": "rigspace.charts", "charts": [{"index": 3}]}')
    with pytest.raises(DatasetError, match=r"charts\.json cannot be used: chart 1 is incomplete"):
        chart_boxes(dataset)
    model = tmp_path / "model"
    export_bundle(textured_run, model, int8=False)
    (model / "charts.json").write_text("{not json")
    with pytest.raises(BundleError, match=r"texture charts charts\.json cannot be read"):
        BundleModel(model).chart_table()


@pytest.fixture(scope="module")
def own_branch_run(tmp_path_factory, tiny_dataset):
    run = tmp_path_factory.mktemp("texture_branch") / "run"
    config = replace(TINY, steps_per_level=20, texture_branch="texture")
    assert loop.train(tiny_dataset, run, config, progress=False).stopped == "done"
    return run


def test_a_head_on_its_own_branch_leaves_the_maps_branches_their_own_channels(tiny_dataset):
    charts = 5
    model = Rig2Image(Shape(19, charts=charts), replace(TINY, texture_branch="texture"))
    assert model.branch_names == ("albedo", "geometry", "texture")
    assert model.albedo.heads[-1].out_channels == 4  # albedo and alpha only
    assert model.geometry.heads[-1].out_channels == 5
    assert model.texture is not None
    assert model.texture.heads[-1].out_channels == texture_channels(charts)
    plain = Rig2Image(
        Shape(19, charts=charts), replace(TINY, texture_branch="texture", texture=False)
    )
    assert plain.texture is None and plain.branch_names == ("albedo", "geometry")
    with pytest.raises(ValueError, match="texture_branch must be one of"):
        Rig2Image(Shape(19, charts=charts), replace(TINY, texture_branch="colour"))


def test_a_head_on_its_own_branch_exports_its_own_graphs(own_branch_run, tiny_dataset, tmp_path):
    """texture_<R>.onnx beside albedo and geometry (bundle format 4), giving chart and uv as
    the torch branch does; the albedo graphs give albedo and alpha only."""
    manifest = export_bundle(own_branch_run, tmp_path / "model", int8=True)
    assert manifest["format_version"] == 4 and manifest["texture"]["branch"] == "texture"
    top = manifest["levels"][-1]
    assert set(top["graphs"]) == {"albedo", "geometry", "texture"}
    assert set(top["int8"]) == {"albedo", "geometry", "texture"}
    model = BundleModel(tmp_path / "model")
    assert model.branch_names == ("albedo", "geometry", "texture")
    rows = SampleSet(tiny_dataset, "heldout-views")
    rig = rows.rig[rows.rows[:2]]
    assert set(model.predict(rig, 32, ("albedo",))) == {"albedo", "alpha"}
    out = model.predict(rig, 32)  # every branch by default
    k = manifest["texture"]["charts"]
    assert out["chart"].shape == (2, k + 1, 32, 32) and out["uv"].shape == (2, 2 * k, 32, 32)
    trained, _, _ = loop.build_model(own_branch_run)
    joints2d = model.joints2d(rig)
    with torch.no_grad():
        heads = trained(
            torch.from_numpy(rig), 32, ("texture",),
            joints2d=None if joints2d is None else torch.from_numpy(joints2d),
        )  # fmt: skip
        logits, coords = texture_maps(heads["texture"][-1], k, "texture")
    np.testing.assert_allclose(out["uv"], coords.numpy(), atol=1e-4)
    np.testing.assert_allclose(out["chart"], torch.softmax(logits, 1).numpy(), atol=1e-5)
    assert graph_rewrite.rewrite_bundle(tmp_path / "model", dry_run=True) == []
    # The torch predictor reads the texture branch's weights back from its graphs too.
    from rigspace.train.torch_predictor import weights_from_graphs

    state = weights_from_graphs(tmp_path / "model", model.manifest)
    assert state["texture.heads.0.weight"].shape[0] == texture_channels(k)


def test_a_rigspace_that_reads_only_versions_1_to_3_refuses_the_texture_branch(
    own_branch_run, tmp_path
):
    from rigspace.sdk import bundle

    export_bundle(own_branch_run, tmp_path / "model", int8=False)
    assert 4 in bundle.READABLE_VERSIONS
    manifest = json.loads((tmp_path / "model" / "manifest.json").read_text())
    del manifest["levels"][-1]["graphs"]["texture"]
    (tmp_path / "model" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(bundle.BundleError, match="on the texture branch, which has no graphs"):
        BundleModel(tmp_path / "model")

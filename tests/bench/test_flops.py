"""bench/flops.py: exact counts on a hand-built graph, the sample bundle's levels, peak and efficiency."""

from __future__ import annotations

import math

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from rigspace.bench.flops import bundle_flops, efficiency, graph_flops, peak_flops
from rigspace.sdk.bundle import read_manifest
from tests.conftest import REPO

SAMPLE = REPO / "samples" / "models" / "sample"
FRACTION_RANGE = (0.0, 1.5)
"""A float32 network cannot beat the machine's float32 product peak by much (timing noise)."""


def _weight(name: str, *shape: int) -> onnx.TensorProto:
    rng = np.random.default_rng(0)
    return numpy_helper.from_array(rng.standard_normal(shape).astype(np.float32), name)


def hand_built(path) -> None:
    """Grouped strided Conv -> ConvTranspose -> Flatten -> Gemm(transB), and a batched MatMul."""
    nodes = [
        helper.make_node("Conv", ["x", "wc", "bc"], ["c"], group=2, strides=[2, 2], pads=[1] * 4),
        helper.make_node("ConvTranspose", ["c", "wt"], ["t"], strides=[2, 2]),
        helper.make_node("Flatten", ["t"], ["f"]),
        helper.make_node("Gemm", ["f", "wg", "bg"], ["g"], transB=1),
        helper.make_node("MatMul", ["m", "wm"], ["mm"]),
    ]
    graph = helper.make_graph(
        nodes,
        "hand_built",
        [
            helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", 4, 10, 10]),
            helper.make_tensor_value_info("m", TensorProto.FLOAT, ["n", 3, 7, 5]),
        ],
        [
            helper.make_tensor_value_info("g", TensorProto.FLOAT, None),
            helper.make_tensor_value_info("mm", TensorProto.FLOAT, None),
        ],
        [
            _weight("wc", 6, 2, 3, 3),  # Cout 6, Cin / group = 2, 3x3
            _weight("bc", 6),
            _weight("wt", 6, 4, 2, 2),  # Cin 6, Cout 4, 2x2
            _weight("wg", 10, 400),
            _weight("bg", 10),
            _weight("wm", 5, 2),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))


def test_hand_built_graph_counts_the_formula_exactly(tmp_path):
    hand_built(tmp_path / "g.onnx")
    n = 3
    result = graph_flops(tmp_path / "g.onnx", batch=n)
    conv = 2 * (n * 6 * 5 * 5) * (2 * 3 * 3)  # 10x10 -> 5x5 at stride 2, pad 1
    transposed = 2 * (n * 6 * 5 * 5) * (4 * 2 * 2)  # each input scattered to Cout x 2x2
    gemm = 2 * n * 400 * 10  # (n, 4*10*10) x (400, 10)
    matmul = 2 * (n * 3 * 7 * 2) * 5
    assert result["flops"] == {
        "Conv": conv,
        "ConvTranspose": transposed,
        "Gemm": gemm,
        "MatMul": matmul,
    }
    assert result["total"] == conv + transposed + gemm + matmul
    assert result["uncounted"] == {"Flatten": n * 400}


def test_flops_scale_with_batch_and_match_between_precisions():
    levels = read_manifest(SAMPLE).levels
    previous = 0
    for level in sorted(entry.resolution for entry in levels):
        fp32 = bundle_flops(SAMPLE, level)
        int8 = bundle_flops(SAMPLE, level, precision="int8")
        assert fp32["total"] == int8["total"] > previous, level  # each level costs more
        assert fp32["parts"] == int8["parts"]
        previous = fp32["total"]
    four = bundle_flops(SAMPLE, 32, batch=4)
    assert four["total"] == 4 * bundle_flops(SAMPLE, 32)["total"]
    albedo_only = bundle_flops(SAMPLE, 32, branches=("albedo",))
    assert albedo_only["total"] == four["parts"]["trunk"] // 4 + four["parts"]["albedo"] // 4


def test_trunk_gemms_cost_twice_their_weights_at_batch_one():
    """An independent count: (1, K) x (K, N) is K * N multiply-adds, the weight's size."""
    trunk = read_manifest(SAMPLE).trunk.fp32["trunk"]
    model = onnx.load(str(SAMPLE / trunk))
    weights = {t.name: t for t in model.graph.initializer}
    gemm_weights = [weights[n.input[1]] for n in model.graph.node if n.op_type == "Gemm"]
    assert gemm_weights
    expected = sum(2 * math.prod(w.dims) for w in gemm_weights)
    assert graph_flops(SAMPLE / trunk)["flops"]["Gemm"] == expected


def test_peak_and_efficiency_are_plausible():
    peak = peak_flops(threads=1, size=256, repeats=3)
    for backend in ("onnxruntime", "numpy"):
        rate = peak[backend]
        assert 0 < rate["min_gflops"] <= rate["median_gflops"] <= rate["max_gflops"]
    # One thread: the figure is steadier than with the two cores shared with other work.
    result = efficiency(SAMPLE, 32, "fp32", batch=1, threads=1, repeats=5)
    assert FRACTION_RANGE[0] < result["fraction_of_peak"] < FRACTION_RANGE[1]
    assert result["flops"] == bundle_flops(SAMPLE, 32)["total"]
    int8 = efficiency(SAMPLE, 32, "int8", batch=1, threads=1, repeats=5)
    assert int8["gflops"] > 0 and int8["flops"] == result["flops"]


def test_unknown_level_is_named():
    with pytest.raises(ValueError, match="no level 48"):
        bundle_flops(SAMPLE, 48)

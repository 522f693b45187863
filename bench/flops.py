"""FLOPs of a bundle's ONNX graphs, this machine's matrix-product peak, and the bundle's share of it.

    graph_flops("samples/models/sample/albedo_32.onnx", batch=4)
    bundle_flops("samples/models/sample", 32, precision="int8")
    peak_flops(size=2048)
    efficiency("samples/models/sample", 128, "fp32", batch=1)

What is counted: 2 x multiply-accumulates of Conv, ConvTranspose, Gemm and MatMul, from the
graph's own shapes (onnx shape inference after the batch dimension is fixed). Bias adds and
every other op (activations, Resize, Sigmoid, normalisation, Quantize/DequantizeLinear) are
not counted in `total`; their output elements are listed under `uncounted` so it is visible
that they are small. A QDQ int8 graph counts its Conv/Gemm nodes exactly like the fp32 graph
(the Dequantize feeding them is not a FLOP of the model), so both precisions of a level
report the same total. Every function returns plain JSON-able dicts.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import helper, shape_inference

from rigspace.bench.timing import repeat
from rigspace.sdk.bundle import read_manifest
from rigspace.sdk.model import BundleModel

COUNTED = ("Conv", "ConvTranspose", "Gemm", "MatMul")
"""Op types whose FLOPs (2 x MACs) make up `total`."""
WARMUP = 2
"""Untimed runs before timing: session initialisation, first allocations, caches."""
PEAK_REPEATS = 10
"""At least this many products for efficiency's peak: its fastest is the peak (cheap at 512)."""


def _shapes(model: onnx.ModelProto, batch: int) -> dict[str, list[int]]:
    """Every tensor's static shape once the inputs' first (batch) dimension is `batch`."""
    graph = model.graph
    initializers = {t.name for t in graph.initializer}
    for tensor in graph.input:
        if tensor.name in initializers:
            continue
        dims = tensor.type.tensor_type.shape.dim
        if len(dims):
            dims[0].Clear()
            dims[0].dim_value = batch
    # Exporters leave stale symbolic shapes behind (the sample trunk's output reads
    # ['n', 128, 'n', ...]); inferred afresh they cannot conflict with the fixed batch.
    del graph.value_info[:]
    for tensor in graph.output:
        tensor.type.tensor_type.ClearField("shape")
    inferred = shape_inference.infer_shapes(model, strict_mode=True, data_prop=True)
    shapes: dict[str, list[int]] = {t.name: list(t.dims) for t in inferred.graph.initializer}
    for info in (*inferred.graph.input, *inferred.graph.value_info, *inferred.graph.output):
        if not info.type.tensor_type.HasField("shape"):
            continue
        dims = info.type.tensor_type.shape.dim
        if all(d.HasField("dim_value") for d in dims):
            shapes[info.name] = [d.dim_value for d in dims]
    return shapes


def _attribute(node: onnx.NodeProto, name: str, default: Any) -> Any:
    for attribute in node.attribute:
        if attribute.name == name:
            return helper.get_attribute_value(attribute)
    return default


def node_macs(node: onnx.NodeProto, shapes: dict[str, list[int]]) -> int:
    """Multiply-accumulates of one Conv, ConvTranspose, Gemm or MatMul node."""

    def shape(name: str) -> list[int]:
        if name not in shapes:
            raise ValueError(
                f"shape of {name!r} (input or output of {node.op_type} node {node.name!r}) "
                "is not resolved by onnx shape inference"
            )
        return shapes[name]

    if node.op_type == "Conv":
        # out (N, Cout, *spatial), weight (Cout, Cin / group, *kernel): each output element
        # sums Cin / group * prod(kernel) products; `group` is folded into the weight shape.
        out, weight = shape(node.output[0]), shape(node.input[1])
        return math.prod(out) * math.prod(weight[1:])
    if node.op_type == "ConvTranspose":
        # input (N, Cin, *spatial), weight (Cin, Cout / group, *kernel): each input element
        # is scattered into Cout / group * prod(kernel) outputs.
        x, weight = shape(node.input[0]), shape(node.input[1])
        return math.prod(x) * math.prod(weight[1:])
    if node.op_type == "Gemm":
        a, b = shape(node.input[0]), shape(node.input[1])
        m = a[1] if _attribute(node, "transA", 0) else a[0]
        k = a[0] if _attribute(node, "transA", 0) else a[1]
        n = b[0] if _attribute(node, "transB", 0) else b[1]
        return m * k * n
    if node.op_type == "MatMul":
        # numpy matmul semantics: a 1-D operand contributes its single axis as K.
        out, a = shape(node.output[0]), shape(node.input[0])
        return math.prod(out) * a[-1]
    raise ValueError(f"no MAC count for op type {node.op_type}")


def graph_flops(path: str | Path, batch: int = 1) -> dict[str, Any]:
    """FLOPs of one ONNX graph evaluated on `batch` samples (see the module doc for what counts)."""
    model = onnx.load(str(path))
    shapes = _shapes(model, batch)
    by_op: dict[str, int] = {}
    uncounted: dict[str, int] = {}
    nodes: dict[str, int] = {}
    for node in model.graph.node:
        nodes[node.op_type] = nodes.get(node.op_type, 0) + 1
        if node.op_type in COUNTED:
            by_op[node.op_type] = by_op.get(node.op_type, 0) + 2 * node_macs(node, shapes)
        elif node.op_type != "Constant":
            elements = sum(math.prod(shapes[o]) for o in node.output if o in shapes)
            uncounted[node.op_type] = uncounted.get(node.op_type, 0) + elements
    return {
        "path": str(path),
        "batch": batch,
        "flops": by_op,
        "total": sum(by_op.values()),
        "counted_ops": list(COUNTED),
        "uncounted": uncounted,
        "nodes": nodes,
    }


def bundle_graphs(folder: str | Path, level: int, branches, precision: str) -> dict[str, str]:
    """Graph file names BundleModel.predict runs for `level`: the trunk, then each branch."""
    manifest = read_manifest(folder)
    int8 = precision == "int8"
    levels = {e.resolution: e.files.int8 if int8 else e.files.fp32 for e in manifest.levels}
    if level not in levels or manifest.trunk is None:
        raise ValueError(f"the bundle {folder} has no level {level}; it has {sorted(levels)}")
    trunk = (manifest.trunk.int8 if int8 else manifest.trunk.fp32)["trunk"]
    return {"trunk": str(trunk), **{b: str(levels[level][b]) for b in branches}}


def bundle_flops(
    bundle_folder: str | Path,
    level: int,
    branches: tuple[str, ...] = ("albedo", "geometry"),
    precision: str = "fp32",
    batch: int = 1,
) -> dict[str, Any]:
    """FLOPs of one BundleModel.predict: the trunk plus the chosen branches at `level`."""
    folder = read_manifest(bundle_folder).folder
    graphs = {
        part: graph_flops(folder / name, batch)
        for part, name in bundle_graphs(folder, level, branches, precision).items()
    }
    return {
        "bundle": str(folder),
        "level": level,
        "branches": list(branches),
        "precision": precision,
        "batch": batch,
        "graphs": {
            part: {"file": Path(g["path"]).name, **g["flops"]} for part, g in graphs.items()
        },
        "parts": {part: g["total"] for part, g in graphs.items()},
        "total": sum(g["total"] for g in graphs.values()),
        "per_sample": sum(g["total"] for g in graphs.values()) / batch,
    }


def _rate(flops: float, seconds: list[float]) -> dict[str, float]:
    """GFLOP/s statistics; the fastest run gives the maximum."""
    return {
        "median_gflops": flops / statistics.median(seconds) / 1e9,
        "min_gflops": flops / max(seconds) / 1e9,
        "max_gflops": flops / min(seconds) / 1e9,
        "median_ms": 1e3 * statistics.median(seconds),
    }


def matmul_graph(size: int) -> onnx.ModelProto:
    """One float32 MatMul of two (size, size) graph inputs (inputs, so nothing is folded away)."""
    shape = [size, size]
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["a", "b"], ["c"])],
        "peak_matmul",
        [
            helper.make_tensor_value_info("a", onnx.TensorProto.FLOAT, shape),
            helper.make_tensor_value_info("b", onnx.TensorProto.FLOAT, shape),
        ],
        [helper.make_tensor_value_info("c", onnx.TensorProto.FLOAT, shape)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8  # opset 17's IR version: onnx may write one newer than onnxruntime reads
    return model


def peak_flops(threads: int = 0, size: int = 2048, repeats: int = 10) -> dict[str, Any]:
    """This machine's measured float32 matrix-product GFLOP/s, via onnxruntime and numpy.

    onnxruntime gets BundleModel's session options (intra-op threads when `threads` > 0)
    and providers. numpy uses its BLAS's default thread count (not set here: that would
    need threadpoolctl, which rigspace does not depend on).
    """
    import onnxruntime as ort

    rng = np.random.default_rng(0)
    a = rng.standard_normal((size, size), dtype=np.float32)
    b = rng.standard_normal((size, size), dtype=np.float32)
    flops = 2.0 * size**3
    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
    providers = ["CPUExecutionProvider"]  # the CPU's peak
    session = ort.InferenceSession(
        matmul_graph(size).SerializeToString(), options, providers=providers
    )
    ort_seconds = repeat(lambda: session.run(None, {"a": a, "b": b}), repeats, WARMUP)
    np_seconds = repeat(lambda: a @ b, repeats, WARMUP)
    return {
        "size": size,
        "repeats": repeats,
        "threads": threads,
        "providers": providers,
        "flops_per_product": flops,
        "onnxruntime": _rate(flops, ort_seconds),
        "numpy": _rate(flops, np_seconds),
    }


def efficiency(
    bundle_folder: str | Path,
    level: int,
    precision: str = "fp32",
    batch: int = 1,
    *,
    branches: tuple[str, ...] = ("albedo", "geometry"),
    threads: int = 0,
    repeats: int = 10,
    peak_size: int = 512,
) -> dict[str, Any]:
    """The bundle's achieved GFLOP/s at a level, and its fraction of this machine's peak.

    Time per evaluation is BundleModel.predict on `batch` rig vectors (after WARMUP calls,
    median of `repeats`); the peak is the fastest onnxruntime product of peak_flops measured
    in the same call with the same threads, at `peak_size` (512: on the project's 2-core
    machine one thread's product peaked there, about 105 GFLOP/s, against about 60 at 1024).
    An int8 graph's FLOPs are counted as fp32's, so its fraction compares int8 kernels with
    the float32 peak and may exceed 1.
    """
    flops = bundle_flops(bundle_folder, level, branches, precision, batch)
    model = BundleModel(bundle_folder, precision, threads=threads, predictor="onnxruntime")
    rig = np.random.default_rng(0).standard_normal((batch, len(model.joints) * 6))
    rig = (0.1 * rig).astype(np.float32)
    seconds = repeat(lambda: model.predict(rig, level, branches), repeats, WARMUP)
    peak = peak_flops(threads, peak_size, max(repeats, PEAK_REPEATS))
    gflops = flops["total"] / statistics.median(seconds) / 1e9
    # The peak is the fastest product (a busy machine slows some runs, never speeds one up),
    # so a loaded machine lowers the fraction rather than inflating it.
    best = peak["onnxruntime"]["max_gflops"]
    return {
        "bundle": flops["bundle"],
        "level": level,
        "precision": precision,
        "batch": batch,
        "branches": list(branches),
        "threads": threads,
        "flops": flops["total"],
        "ms_per_evaluation": 1e3 * statistics.median(seconds),
        "gflops": gflops,
        "peak_gflops": best,
        "fraction_of_peak": gflops / best,
        "peak": peak,
    }

"""Rewrite an exported bundle's graphs into the faster form the current export writes.

    python -m rigspace.apps.graph_rewrite BUNDLE [--check]

The texture head ends in a softmax over the channel axis of its chart logits, which
onnxruntime's CPU runs slowly in its obvious forms: a Softmax node (6.2 of the 128x128
albedo graph's 10.3 ms), or that softmax written out with ReduceMax and ReduceSum over the
channel axis (3.0 of 9.0 ms on one thread), which reduce across the channels' strides. The
fast form takes the maximum as one Max over the channels Split apart (exact) and the sum
as a 1x1 Conv with weights of one (within 6e-7): the softmax costs 1.1 ms, the graph 7.0
(4.3 on two threads). The export writes it (fast_channel_softmax after torch's export);
this command brings older bundles to it, in the fp32 and int8 graphs alike, and records
the new files' sizes and sha256 in the manifest; nothing else changes (the outputs agree
within 1e-5, checked on random inputs before a file is replaced). A bundle already in that
form is left alone. Needs the `onnx` package (the `train` extra); the runtime never imports
this module.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from rigspace.sdk.bundle import (
    MANIFEST_FILE,
    read_manifest_document,
    write_manifest_document,
)
from rigspace.sdk.files import write_atomic

AGREEMENT = 1e-5
"""Largest output difference a rewritten graph may show against the original (5e-7 seen)."""


def fast_channel_softmax(model) -> int:
    """Bring every softmax over axis 1 of a 4-D tensor in `model` (an onnx ModelProto) to
    the fast form, in place: a Softmax node, or the written-out form torch's export of
    graphs.channel_softmax gives. Returns how many it rewrote (0: nothing to do)."""
    _decompose_softmax_nodes(model)
    return _fast_reductions(model)


def _opset(model) -> int:
    return next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), 0)


def _decompose_softmax_nodes(model) -> int:
    """Every Softmax over axis 1 replaced by its written-out form (ReduceMax, Sub, Exp,
    ReduceSum, Div), which _fast_reductions then speeds up."""
    from onnx import TensorProto, helper

    graph = model.graph
    opset = _opset(model)
    replaced = 0
    for index in reversed(range(len(graph.node))):
        node = graph.node[index]
        axis = next((helper.get_attribute_value(a) for a in node.attribute if a.name == "axis"), -1)
        if node.op_type != "Softmax" or axis != 1 or opset < 13:
            continue  # before opset 13 Softmax flattens from its axis on: not a channel softmax
        x, out, tag = node.input[0], node.output[0], f"channel_softmax_{replaced}"
        axes = f"{tag}/axes"
        graph.initializer.append(helper.make_tensor(axes, TensorProto.INT64, [1], [1]))
        if opset >= 18:  # ReduceMax takes its axes as an input from opset 18 on
            reduce_max = helper.make_node("ReduceMax", [x, axes], [f"{tag}/max"], keepdims=1)
        else:
            reduce_max = helper.make_node("ReduceMax", [x], [f"{tag}/max"], axes=[1], keepdims=1)
        nodes = [
            reduce_max,
            helper.make_node("Sub", [x, f"{tag}/max"], [f"{tag}/shifted"]),
            helper.make_node("Exp", [f"{tag}/shifted"], [f"{tag}/exp"]),
            helper.make_node("ReduceSum", [f"{tag}/exp", axes], [f"{tag}/sum"], keepdims=1),
            helper.make_node("Div", [f"{tag}/exp", f"{tag}/sum"], [out]),
        ]
        _replace_node(graph, node, nodes)
        replaced += 1
    return replaced


def _replace_node(graph, old, new: list) -> None:
    """`new` (nodes) where the node `old` stands in `graph`, in its place in the order."""
    index = list(graph.node).index(old)
    del graph.node[index]
    for offset, node in enumerate(new):
        graph.node.insert(index + offset, node)


def _constants(graph) -> dict[str, np.ndarray]:
    """The graph's constant tensors by name: its initializers and its Constant nodes' values."""
    from onnx import numpy_helper

    constants = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    constants |= {  # torch's export gives the sum's axes as a Constant node
        node.output[0]: numpy_helper.to_array(node.attribute[0].t)
        for node in graph.node
        if node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value"
    }
    return constants


def _shapes(model) -> dict[str, list[int | None]]:
    """Every inferred tensor's shape (None for a dimension without a fixed size), by name."""
    from onnx import shape_inference

    return {
        v.name: [d.dim_value if d.HasField("dim_value") else None for d in
                 v.type.tensor_type.shape.dim]
        for v in (*shape_inference.infer_shapes(model).graph.value_info, *model.graph.input)
    }  # fmt: skip


def _remove_unused(graph, names: set[str]) -> None:
    """The initializers and Constant nodes of `names` that no node reads any more, removed."""
    used = {name for node in graph.node for name in node.input}
    for name in names - used:
        for tensor in [t for t in graph.initializer if t.name == name]:
            graph.initializer.remove(tensor)
        for constant in [n for n in graph.node if list(n.output) == [name]]:
            graph.node.remove(constant)


def _over_channels(node, constants: dict[str, np.ndarray]) -> bool:
    """Whether a ReduceMax or ReduceSum node reduces axis 1 alone, keeping it."""
    from onnx import helper

    attributes = {a.name: helper.get_attribute_value(a) for a in node.attribute}
    if attributes.get("keepdims", 1) != 1:
        return False
    axes = attributes.get("axes")
    if axes is None and len(node.input) > 1:
        axes = constants.get(node.input[1])
    return axes is not None and list(np.asarray(axes).reshape(-1)) == [1]


def _fast_reductions(model) -> int:
    """The written-out softmax's two reductions over the channels replaced: ReduceMax by a
    Split and one Max over its parts, ReduceSum by a 1x1 Conv with weights of one."""
    from onnx import TensorProto, helper, numpy_helper

    graph = model.graph
    constants = _constants(graph)
    shapes = _shapes(model)
    consumers: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)

    def consumer(name: str, op: str):
        return next((n for n in consumers.get(name, []) if n.op_type == op), None)

    replaced = 0
    for reduce_max in [n for n in graph.node if n.op_type == "ReduceMax"]:
        x = reduce_max.input[0]
        channels = (shapes.get(x) or [None, None])[1]
        sub = consumer(reduce_max.output[0], "Sub")
        exp = consumer(sub.output[0], "Exp") if sub is not None else None
        reduce_sum = consumer(exp.output[0], "ReduceSum") if exp is not None else None
        if (
            sub is None or exp is None or reduce_sum is None
            or not channels or len(shapes[x]) != 4
            or list(sub.input) != [x, reduce_max.output[0]]
            or not _over_channels(reduce_max, constants)
            or not _over_channels(reduce_sum, constants)
        ):  # fmt: skip
            continue
        tag = f"channel_softmax_{replaced}"
        split, ones = f"{tag}/split", f"{tag}/ones"
        graph.initializer.extend([
            helper.make_tensor(split, TensorProto.INT64, [channels], [1] * channels),
            numpy_helper.from_array(np.ones((1, channels, 1, 1), np.float32), ones),
        ])  # fmt: skip
        parts = [f"{tag}/channel_{k}" for k in range(channels)]
        fast_max = [
            helper.make_node("Split", [x, split], parts, axis=1, name=f"{tag}/split"),
            helper.make_node("Max", parts, list(reduce_max.output), name=f"{tag}/max"),
        ]
        fast_sum = helper.make_node(
            "Conv", [exp.output[0], ones], list(reduce_sum.output), name=f"{tag}/sum"
        )
        _replace_node(graph, reduce_sum, [fast_sum])
        _replace_node(graph, reduce_max, fast_max)
        _remove_unused(graph, {*reduce_max.input[1:], *reduce_sum.input[1:]})  # their axes
        for node, name in ((sub, "shifted"), (exp, "exp")):
            node.name = node.name or f"{tag}/{name}"
        division = consumer(exp.output[0], "Div")
        if division is not None:
            division.name = division.name or f"{tag}/divide"
        replaced += 1
    return replaced


def _largest_difference(before: bytes, after: bytes) -> float:
    """The largest output difference of two graphs on the same random inputs (batch 2)."""
    import onnxruntime as ort

    rng = np.random.default_rng(0)
    first = ort.InferenceSession(before, providers=["CPUExecutionProvider"])
    second = ort.InferenceSession(after, providers=["CPUExecutionProvider"])
    feeds = {
        i.name: rng.random([2 if isinstance(d, str) or d is None else d for d in i.shape]).astype(
            np.float32
        )
        for i in first.get_inputs()
    }
    return max(
        float(np.abs(a - b).max())
        for a, b in zip(first.run(None, feeds), second.run(None, feeds), strict=True)
    )


def rewrite_bundle(folder: str | Path, dry_run: bool = False) -> list[str]:
    """Rewrite the bundle's graphs whose channel softmax is not in the fast form; returns
    their names. With `dry_run`, only says which would change."""
    import onnx

    folder = Path(folder)
    if not (folder / MANIFEST_FILE).is_file():
        raise SystemExit(
            f"{folder} is not a model bundle (no manifest.json): give a bundle folder."
        )
    manifest = read_manifest_document(folder)
    changed = []
    for name in sorted(manifest.get("files", {})):
        if not name.endswith(".onnx"):
            continue
        path = folder / name
        before = path.read_bytes()
        model = onnx.load_from_string(before)
        if not fast_channel_softmax(model):
            continue
        changed.append(name)
        if dry_run:
            continue
        after = model.SerializeToString()
        gap = _largest_difference(before, after)
        if not gap <= AGREEMENT:
            raise SystemExit(f"{path}: the rewritten graph differs by {gap:.3g}; left unchanged.")
        write_atomic(path, after)
        manifest["files"][name] = {"bytes": len(after), "sha256": hashlib.sha256(after).hexdigest()}
    if changed and not dry_run:
        write_manifest_document(folder, manifest)
    return changed

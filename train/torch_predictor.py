"""The `torch` predictor: a bundle's graphs run by the network itself, from its saved weights.

The export writes the network's weights beside the ONNX graphs (`weights.safetensors`,
rigspace.sdk.weights: no pickle) with what rebuilds it (manifest `torch`: the training
config, the joints' parents, the charts), and checks this predictor against every fp32 graph
(manifest `torch.check`). A bundle whose `torch` section names no file (the committed sample
model) reads the same weights back from its fp32 graphs (weights_from_graphs). Each graph file maps to the module that was traced into it
(rigspace.train.graphs), so both compute one function. On a GPU the modules run in fp16,
channels_last, each (graph, batch size) captured once as a CUDA graph and replayed (a
frame's few small kernels cost more to launch than to run); on the CPU, fp32.

Imports torch only when a bundle is opened: the plugin loads (and `auto` ranks it) without.
"""

from __future__ import annotations

from importlib.util import find_spec
from typing import Any

import numpy as np

from rigspace.sdk.bundle import BundleError, ModelManifest
from rigspace.sdk.predictors import GraphSet, PredictorSpec, PredictorUnavailable, nvidia_driver
from rigspace.sdk.weights import read_safetensors

WEIGHTS = "weights.safetensors"
CHECK_TOLERANCE = 1e-3
"""Largest |torch - ONNX| over every output of every fp32 graph at export (fp32 on the CPU;
the two differ by float reassociation only, about 1e-6)."""
MAX_CAPTURED = 16
"""CUDA graphs kept per predictor (one per graph and batch size seen); older ones are dropped."""


def weights_from_graphs(folder, manifest: ModelManifest) -> dict[str, np.ndarray]:
    """The network's state dict read back from the bundle's own fp32 ONNX graphs: every
    parameter is an initializer named after it, except each level's 1x1 head, which the
    export slices by output (graphs.BranchAtLevel) and which is their concatenation, in the
    order the graph's Conv nodes apply them. A bundle needs no second copy of its weights."""
    import onnx
    from onnx import numpy_helper

    if manifest.trunk is None:
        raise KeyError("trunk")
    files = [(manifest.trunk.fp32["trunk"], "trunk", 0)]
    levels = sorted(manifest.levels, key=lambda level: level.resolution)
    for branch in ("albedo", "geometry", "texture"):  # the texture branch: where it has one
        files += [
            (level.files.fp32[branch], branch, k)
            for k, level in enumerate(levels)
            if branch in level.files.fp32
        ]
    state: dict[str, np.ndarray] = {}
    for file, branch, index in files:
        graph = onnx.load(str(folder / file)).graph
        values = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
        state |= {k.removeprefix("model."): v for k, v in values.items() if k.startswith("model.")}
        head = [
            (values[node.input[1]], values[node.input[2]])
            for node in graph.node
            # (not the texture head's softmax, whose sum graph_rewrite makes a Conv)
            if node.op_type == "Conv"
            and not node.input[1].startswith(("model.", "channel_softmax"))
        ]
        if branch != "trunk" and head:
            state[f"{branch}.heads.{index}.weight"] = np.concatenate([w for w, _ in head])
            state[f"{branch}.heads.{index}.bias"] = np.concatenate([b for _, b in head])
    return state


def build_network(folder, manifest: ModelManifest):
    """The Rig2Image of a bundle, its weights loaded, in eval mode on the CPU (fp32): from the
    weights file its `torch` section names (what the export writes), else from its fp32 ONNX
    graphs (weights_from_graphs)."""
    import torch

    from rigspace.train.config import TrainConfig
    from rigspace.train.network import Rig2Image, Shape

    section = manifest.torch
    if section is None:
        raise BundleError(
            f"Model bundle {folder} has no torch section (exported before it).",
            "re-export the bundle with `rigspace train`, or use --predictor onnxruntime.",
        )
    source = str(section["file"]) if section.get("file") else "fp32 graphs"
    try:
        if section.get("file"):
            tensors, _ = read_safetensors(folder / source)
        else:
            tensors = weights_from_graphs(folder, manifest)
    except (OSError, KeyError, TypeError, ValueError) as exc:  # not a WeightsError: graphs
        raise BundleError(
            f"Model bundle {folder}: the network's weights cannot be read from its {source} "
            f"({type(exc).__name__}: {str(exc).splitlines()[0][:200]}).",
            "re-export the bundle with `rigspace train`, or use --predictor onnxruntime.",
        ) from exc
    try:
        config = TrainConfig.from_json(section["config"])
        shape = Shape(
            int(section["joints"]),
            parents=tuple(int(p) for p in section.get("parents", ())),
            charts=int(section.get("charts", 0)),
            blend_shapes=int(section.get("blend_shapes", 0)),
            controls=int(section.get("controls", 0)),
        )
        model = Rig2Image(shape, config)
        model.load_state_dict({k: torch.from_numpy(v.copy()) for k, v in tensors.items()})
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise BundleError(
            f"Model bundle {folder}: its weights ({source}) do not fit the network its "
            f"manifest describes ({type(exc).__name__}: {str(exc).splitlines()[0][:200]}).",
            "re-export the bundle with `rigspace train`, or use --predictor onnxruntime.",
        ) from exc
    return model.eval()


def _require_weights(graphs: GraphSet) -> None:
    """PredictorUnavailable unless the bundle's fp32 network weights are there and the export
    found them to agree with its graphs."""
    section = graphs.manifest.torch
    if section is None:
        raise PredictorUnavailable(
            f"model bundle {graphs.folder} has no network weights ({WEIGHTS}): it was "
            "exported before the torch predictor",
            "re-export it with `rigspace train DATASET --out MODEL --resume`, or use "
            "--predictor onnxruntime.",
        )
    if graphs.precision != "fp32":
        raise PredictorUnavailable(
            "the torch predictor runs the fp32 network (int8 graphs are onnxruntime's)",
            "use --predictor onnxruntime for int8.",
        )
    check = section.get("check", {})
    if check and not check.get("ok", False):
        raise PredictorUnavailable(
            f"the export found the weights of {graphs.folder} differ from its graphs "
            f"(largest difference {check.get('max_abs')})",
            "re-export the bundle with `rigspace train`, or use --predictor onnxruntime.",
        )


def _require_gpu(device: str) -> None:
    """PredictorUnavailable when torch sees no GPU for `device` (cuda or cuda:N)."""
    import torch

    index = int(device.partition(":")[2] or 0)
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if index >= count:
        raise PredictorUnavailable(
            f"torch sees no GPU for {device} ({count} GPUs, torch {torch.__version__})",
            "install a CUDA build of torch (`pip install -e .[gpu]`), or run on the CPU.",
        )


class TorchRunner:
    """Runs a bundle's graphs with its network in torch, on `device` (None: CUDA if torch sees
    a GPU, else the CPU). `half`: fp16 (default on CUDA); `cuda_graphs`: capture and replay
    (default on CUDA)."""

    def __init__(
        self,
        graphs: GraphSet,
        device: str | None = None,
        half: bool | None = None,
        cuda_graphs: bool | None = None,
    ) -> None:
        import torch

        from rigspace.train.graphs import INPUTS, BranchAtLevel, Trunk, output_names

        _require_weights(graphs)
        if device and device.startswith("cuda"):
            _require_gpu(device)
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        cuda = self.device.type == "cuda"
        self.dtype = torch.float16 if (cuda if half is None else half) else torch.float32
        self.cuda_graphs = cuda if cuda_graphs is None else cuda_graphs
        model = build_network(graphs.folder, graphs.manifest).to(self.device, self.dtype)
        if cuda:
            model = model.to(memory_format=torch.channels_last)
        self.model = model
        self.conditioned = model.conditioned
        self.modules: dict[str, Any] = {}
        self.names: dict[str, tuple[list[str], list[str]]] = {}
        for file, (branch, resolution) in graphs.graphs.items():
            if branch == "trunk":
                self.modules[file] = Trunk(model).eval()
            else:
                self.modules[file] = BranchAtLevel(model, branch, resolution).eval()
            inputs = [INPUTS[branch]]
            # The 8x8 branch graphs have no block, so no conditioning input (as exported).
            if self.conditioned and (branch == "trunk" or resolution > 8):
                inputs.append("joints2d")
            charts = model.charts if branch == model.texture_branch else 0
            self.names[file] = (inputs, output_names(branch, charts))
        precision = "fp16" if self.dtype == torch.float16 else "fp32"
        graphs_note = ", CUDA graphs" if self.cuda_graphs else ""
        self.description = f"torch {self.device} {precision}{graphs_note}"
        self._captured: dict[tuple[str, tuple], tuple[Any, dict, tuple]] = {}

    def load(self, graph: str) -> None:
        if graph not in self.modules:
            raise BundleError(
                f"The bundle has no graph {graph}.", "re-export the bundle with `rigspace train`."
            )

    def inputs(self, graph: str) -> list[str]:
        self.load(graph)
        return list(self.names[graph][0])

    def forward(self, graph: str, tensors: dict[str, Any]) -> tuple:
        """The graph's module on tensors already on the device (outputs in the module's dtype)."""
        inputs = self.names[graph][0]
        out = self.modules[graph](*(tensors[name] for name in inputs))
        return out if isinstance(out, tuple) else (out,)

    def run(self, graph: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        import torch

        self.load(graph)
        inputs, outputs = self.names[graph]
        missing = [name for name in inputs if name not in feeds]
        if missing:
            raise BundleError(
                f"The graph {graph} reads {', '.join(missing)}, which was not given.",
                "pass every input the graph reads (BundleModel does).",
            )
        with torch.inference_mode():
            if self.cuda_graphs:
                result = self._replay(graph, {name: feeds[name] for name in inputs})
            else:
                tensors = {name: self._tensor(feeds[name]) for name in inputs}
                result = self.forward(graph, tensors)
            return {
                name: value.float().cpu().numpy()
                for name, value in zip(outputs, result, strict=True)
            }

    def _tensor(self, value: np.ndarray):
        """An input on the device in the modules' dtype (one copy: a frame's inputs are a few
        KB, less than pinning a staging buffer for them costs)."""
        import torch

        return torch.from_numpy(np.ascontiguousarray(value, dtype=np.float32)).to(
            self.device, self.dtype
        )

    def _replay(self, graph: str, feeds: dict[str, np.ndarray]) -> tuple:
        """Copy the inputs into the captured graph's static tensors and replay it (capturing
        it first for a new (graph, shapes) pair; a warm-up on a side stream, as torch asks)."""
        import torch

        key = (graph, tuple((k, v.shape) for k, v in feeds.items()))
        if key not in self._captured:
            if len(self._captured) >= MAX_CAPTURED:
                self._captured.pop(next(iter(self._captured)))
            static = {k: self._tensor(v) for k, v in feeds.items()}
            stream = torch.cuda.Stream(self.device)
            stream.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(stream):
                for _ in range(2):
                    self.forward(graph, static)
            torch.cuda.current_stream(self.device).wait_stream(stream)
            cuda_graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(cuda_graph):
                out = self.forward(graph, static)
            self._captured[key] = (cuda_graph, static, out)
        cuda_graph, static, out = self._captured[key]
        for name, value in feeds.items():
            # Straight into the captured input (copy_ moves and casts in one step).
            static[name].copy_(torch.from_numpy(np.ascontiguousarray(value, dtype=np.float32)))
        cuda_graph.replay()
        return out


def _priority() -> int | None:
    if find_spec("torch") is None:
        return None
    if not nvidia_driver():
        return 1  # runs, on the CPU, where onnxruntime is faster (docs/bench: predictors)
    import torch

    return 30 if torch.cuda.is_available() else 1


def _open(graphs: GraphSet) -> TorchRunner:
    if find_spec("torch") is None:
        raise PredictorUnavailable(
            "torch is not installed", "install it (`pip install -e .[gpu]`), or use onnxruntime."
        )
    return TorchRunner(graphs, None if graphs.device == "auto" else graphs.device)


TORCH = PredictorSpec(
    "torch",
    "the network in torch from the bundle's weights: fp16 with CUDA graphs on an NVIDIA GPU, "
    "fp32 on the CPU; needs torch and a bundle exported with weights.",
    _priority,
    _open,
)

"""Predictors: what runs a model bundle's graphs. A plugin kind (entry-point group
`rigspace.predictors`), chosen with `--predictor` on render, live, view, eval and bench.

A predictor opens a bundle's graphs by file name (`trunk.onnx`, `albedo_128.onnx`, ...) and
runs one with named numpy inputs, returning its named outputs as float32 numpy arrays, so
rigspace.sdk.model.BundleModel (level of detail, branches, conditioning, rig checks) works
the same over every predictor. Installed here:

    onnxruntime       onnxruntime on the CPU (the default where nothing faster is there)
    onnxruntime-cuda  onnxruntime's TensorRT (where installed) or CUDA execution provider,
                      outputs bound on the GPU (I/O binding); needs onnxruntime-gpu
    torch             the network itself in torch (rigspace.train.torch_predictor), from the
                      weights the export writes beside the graphs: fp16 with CUDA graphs on a
                      GPU, fp32 on the CPU; needs torch and a bundle with weights

`auto` takes the available predictor with the highest `priority` that can open the bundle
(a torch predictor cannot run int8 graphs, nor a bundle exported without weights). Checking
whether torch sees a GPU imports torch, so on Linux it is only asked where an NVIDIA driver is
loaded: a runtime on a CPU machine never imports torch.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from rigspace.sdk.bundle import BundleError, ModelManifest
from rigspace.sdk.errors import PluginError, RigspaceError
from rigspace.sdk.plugins import Kind, discover

AUTO = "auto"


class PredictorUnavailable(RigspaceError):
    """This predictor cannot run this bundle here (`auto` then tries the next one)."""


@dataclass(frozen=True)
class GraphSet:
    """What a predictor is asked to open: a bundle's graphs and how to run them."""

    manifest: ModelManifest
    precision: str
    """"fp32" or "int8" (the graph files named below are already that precision's)."""
    threads: int
    """Intra-op threads for CPU predictors (0: the library's default)."""
    graphs: dict[str, tuple[str, int]] = field(default_factory=dict)
    """Graph file -> (branch, resolution): ("trunk", 8), ("albedo", 128), ..."""
    device: str = AUTO
    """Where to run: "auto", "cpu", "cuda" or "cuda:N" (a --device value); a predictor that
    cannot run there is unavailable."""

    @property
    def gpu(self) -> int | None:
        """The CUDA device index asked for (0 for "cuda"); None for "auto" and "cpu"."""
        if not self.device.startswith("cuda"):
            return None
        return int(self.device.partition(":")[2] or 0)

    @property
    def folder(self) -> Path:
        return self.manifest.folder


class Runner(Protocol):
    """An open predictor: runs a bundle's graphs by file name."""

    description: str
    """One line for reports: the library, device and precision it runs at."""

    def load(self, graph: str) -> None:
        """Prepare `graph` now, so that a missing or damaged file fails before frames start."""

    def inputs(self, graph: str) -> list[str]:
        """The input names `graph` reads."""

    def run(self, graph: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """`graph`'s outputs by name (float32) for its inputs by name."""


@dataclass(frozen=True)
class PredictorSpec:
    """What a predictor plugin exports (entry-point group `rigspace.predictors`)."""

    name: str
    doc: str
    """One line for --help and error messages."""
    priority: Callable[[], int | None]
    """How `auto` ranks it here (higher first); None: it cannot run on this machine."""
    open: Callable[[GraphSet], Runner]
    """Open a bundle's graphs; PredictorUnavailable when this predictor cannot run them."""


PREDICTORS: Kind[PredictorSpec] = Kind("predictor", "rigspace.predictors", PredictorSpec)


def nvidia_driver() -> bool:
    """Whether an NVIDIA GPU driver is loaded (Linux: /proc/driver/nvidia; elsewhere: assume
    it may be, and let the libraries say)."""
    if os.name == "posix" and Path("/proc").is_dir():
        return Path("/proc/driver/nvidia/version").is_file()
    return True


def open_predictor(name: str, graphs: GraphSet) -> Runner:
    """Open `graphs` with the predictor called `name`, or the best available for `auto`."""
    found = discover(PREDICTORS)
    if name != AUTO:
        spec = found.get(name)  # a PluginError naming the installed ones
        if spec.priority() is None:
            raise PredictorUnavailable(
                f"The predictor {name!r} cannot run on this machine: {spec.doc}",
                f"choose --predictor auto, or one of: {', '.join(available(found))}.",
            )
        return spec.open(graphs)
    why: list[str] = []
    ranked = sorted(
        ((p, s) for s in found for p in [s.priority()] if p is not None),
        key=lambda ps: -ps[0],
    )
    for _, spec in ranked:
        try:
            return spec.open(graphs)
        except PredictorUnavailable as exc:
            why.append(f"{spec.name}: {exc.what}")
    raise PluginError(
        f"No predictor can run {graphs.folder} ({'; '.join(why) or 'none is installed'}).",
        "install onnxruntime (`pip install onnxruntime`).",
    )


def available(found: Any = None) -> list[str]:
    """The predictors that can run on this machine, best first."""
    found = found if found is not None else discover(PREDICTORS)
    ranked = sorted(((s.priority(), s.name) for s in found), key=lambda p: (-(p[0] or 0), p[1]))
    return [name for priority, name in ranked if priority is not None]


class OrtRunner:
    """onnxruntime sessions, one per graph, created when first needed."""

    def __init__(self, graphs: GraphSet, providers: list[Any], label: str) -> None:
        self.graphs = graphs
        self.providers = providers
        self.description = f"onnxruntime {label} ({graphs.precision})"
        self._sessions: dict[str, Any] = {}

    def session(self, graph: str):
        if graph not in self._sessions:
            import onnxruntime as ort

            path = self.graphs.folder / graph
            if not path.is_file():
                raise BundleError(
                    f"Model file {path} is missing from the bundle.",
                    "re-export the bundle, or restore the file.",
                )
            options = ort.SessionOptions()
            # Its threads sleep after a run instead of spinning for the next: a frame does
            # other work between network calls, which the spinning threads took the cores
            # from (256x256 previs frame on 2 cores: network stage 23.5 -> 17 ms, frame
            # 37 -> 31 ms; rigspace bench --only frames).
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
            if self.graphs.threads:
                options.intra_op_num_threads = self.graphs.threads
            try:
                self._sessions[graph] = ort.InferenceSession(
                    str(path), options, providers=self.providers
                )
            except Exception as exc:  # onnxruntime raises its own types for bad files
                raise BundleError(
                    f"Model file {path} cannot be loaded ({type(exc).__name__}: "
                    f"{str(exc).splitlines()[0][:200]}).",
                    "the file is damaged: re-export the bundle with `rigspace train`.",
                ) from exc
        return self._sessions[graph]

    def load(self, graph: str) -> None:
        self.session(graph)

    def inputs(self, graph: str) -> list[str]:
        return [i.name for i in self.session(graph).get_inputs()]

    def run(self, graph: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        session = self.session(graph)
        outputs = session.run(None, feeds)
        return dict(zip((o.name for o in session.get_outputs()), outputs, strict=True))


class OrtCudaRunner(OrtRunner):
    """onnxruntime on the GPU with I/O binding: inputs copied once, outputs bound on the device
    and copied back once (no per-run allocation of host outputs by the session)."""

    def run(self, graph: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        session = self.session(graph)
        binding = session.io_binding()
        for name, value in feeds.items():
            binding.bind_cpu_input(name, np.ascontiguousarray(value, dtype=np.float32))
        names = [o.name for o in session.get_outputs()]
        for name in names:
            binding.bind_output(name, "cuda")
        session.run_with_iobinding(binding)
        return dict(zip(names, binding.copy_outputs_to_cpu(), strict=True))


def _ort_providers() -> list[str]:
    import onnxruntime as ort

    return list(ort.get_available_providers())


def _ort_priority() -> int | None:
    try:
        _ort_providers()
    except ImportError:
        return None
    return 10


def _ort_open(graphs: GraphSet) -> Runner:
    if graphs.gpu is not None:
        raise PredictorUnavailable(
            f"onnxruntime (CPU) does not run on {graphs.device}",
            "choose --predictor onnxruntime-cuda or torch for a GPU.",
        )
    return OrtRunner(graphs, ["CPUExecutionProvider"], "CPU")


def _ort_cuda_priority() -> int | None:
    try:
        providers = _ort_providers()
    except ImportError:
        return None
    if "CUDAExecutionProvider" not in providers:
        return None
    return 25 if "TensorrtExecutionProvider" in providers else 20


def _ort_cuda_open(graphs: GraphSet) -> Runner:
    if graphs.device == "cpu":
        raise PredictorUnavailable(
            "onnxruntime-cuda runs on a GPU, not the CPU", "choose --predictor onnxruntime."
        )
    providers = _ort_providers()
    gpu = {"device_id": graphs.gpu or 0}
    chosen: list[Any] = []
    if "TensorrtExecutionProvider" in providers:
        cache = graphs.folder / ".tensorrt"  # engines built once per bundle and GPU, then reused
        chosen.append(
            (
                "TensorrtExecutionProvider",
                {
                    "trt_fp16_enable": graphs.precision == "fp32",
                    "trt_int8_enable": graphs.precision == "int8",
                    "trt_engine_cache_enable": True,
                    "trt_engine_cache_path": str(cache),
                    **gpu,
                },
            )
        )
    chosen += [("CUDAExecutionProvider", gpu), "CPUExecutionProvider"]
    label = "TensorRT" if len(chosen) > 2 else "CUDA"
    return OrtCudaRunner(graphs, chosen, label)


ONNXRUNTIME = PredictorSpec(
    "onnxruntime",
    "onnxruntime on the CPU (fp32 or int8 graphs).",
    _ort_priority,
    _ort_open,
)
ONNXRUNTIME_CUDA = PredictorSpec(
    "onnxruntime-cuda",
    "onnxruntime's TensorRT or CUDA execution provider, I/O bound; needs onnxruntime-gpu "
    "(`pip install -e .[gpu]`) and an NVIDIA GPU.",
    _ort_cuda_priority,
    _ort_cuda_open,
)


def predictor_name(text: str) -> str:
    """argparse type for --predictor: auto or an installed predictor's name (checked before
    anything opens, so `view` fails at its flag and does not serve an error page)."""
    found = discover(PREDICTORS)
    if text == AUTO or text in found.specs:
        return text
    import argparse

    raise argparse.ArgumentTypeError(
        f"there is no predictor plugin called {text!r}; installed: "
        f"{', '.join([AUTO, *sorted(found.specs)])}"
    )


def add_predictor_argument(parser) -> None:
    """`--predictor NAME` on a command that runs a bundle (render, live, view, eval, bench)."""
    parser.add_argument(
        "--predictor",
        type=predictor_name,
        default=AUTO,
        metavar="NAME",
        help="what runs the network: auto (default: the fastest that can run the bundle here), "
        "onnxruntime (CPU), onnxruntime-cuda (TensorRT/CUDA; needs onnxruntime-gpu) or torch "
        "(the bundle's weights; fp16 CUDA graphs on a GPU); `rigspace bench --only predictors` "
        "times them",
    )


def device_spec(text: str) -> str:
    """A --device value for the predictors: auto, cpu, cuda or cuda:N (argparse type)."""
    value = text.strip().lower()
    kind, colon, index = value.partition(":")
    if value in (AUTO, "cpu", "cuda") or (kind == "cuda" and colon and index.isdigit()):
        return value
    import argparse

    raise argparse.ArgumentTypeError(f"{text!r} is not a device: give auto, cpu, cuda or cuda:N")


def add_device_argument(parser) -> None:
    """`--device` on a command that runs a bundle through the predictors (eval, bench)."""
    parser.add_argument(
        "--device",
        type=device_spec,
        default=AUTO,
        help="where the model runs: auto (default), cpu, cuda or cuda:N; predictors that "
        "cannot run there are passed over",
    )

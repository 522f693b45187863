"""`rigspace bench`: run time against error, skip costs, memory and stability, in one run.

    rigspace bench --quick --out /tmp/bench          # a few minutes
    rigspace bench --out docs/bench --dataset /tmp/sample_ds

Writes results.json (every raw number, the command line and the machine), README.md
(the summary tables) and PNG plots (pareto.png, skips.png) into --out.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from rigspace.bench import report
from rigspace.sdk.cli import CommandSpec
from rigspace.sdk.files import write_atomic
from rigspace.sdk.predictors import add_device_argument, add_predictor_argument

DESCRIPTION = """\
Measure the whole pipeline side by side in one run and write the results: run time
against error for every model variant (levels of detail, fp32 and int8), the
ground-truth renderers and (with --dataset) the captured-view baselines; the runtime
against the model (per map, three framings); per-frame time by stage for 1 and 4
characters; the character at its size on screen; the premise (the mesh path against the
network as the character grows from 23k to 5.9M triangles); what each skip costs; the
network's FLOPs against this machine's measured peak; capture and training throughput; peak memory with 1 and 8 characters; and
numerical stability (adversarial rigs through the network, fp32 against int8). Every
timing is a median after a warm-up, with min and max. --quick takes about two minutes;
the full run about 7 minutes on 2 cores (with --dataset, longer).
"""


@dataclass(frozen=True)
class BenchPlan:
    """How much of each measurement a run does."""

    per_split: int
    repeats: int
    frames: int
    accuracy_samples: int
    frame_sizes: tuple[int, ...]
    skip_frames: int
    levels: tuple[int, ...]
    capture_resolutions: tuple[int, ...]
    capture_frames: tuple[float, float]
    capture_views: int
    presets: tuple[str, ...]
    training_steps: int
    memory_frames: int
    stress_rigs: int
    drift_rigs: int
    stability_steps: int
    display_sizes: tuple[tuple[int, int], ...] = ((640, 360), (1920, 1080))
    display_frames: int = 17
    premise_steps: tuple[int, ...] = (0, 1, 2, 3, 4)
    """Subdivision steps of the premise part (23k to 5.9M triangles)."""
    predictor: str = "auto"
    """--predictor: what runs the fp32 networks in the frame and pareto parts."""
    device: str = "auto"
    """--device: where the predictors part (and the predictor of `predictor`) runs."""


QUICK = BenchPlan(
    per_split=6, repeats=5, frames=4, accuracy_samples=6, frame_sizes=(256,), skip_frames=8,
    levels=(32, 128), capture_resolutions=(128,), capture_frames=(0.0, 7.0), capture_views=4,
    presets=("tiny", "small"), training_steps=3, memory_frames=2, stress_rigs=2_000,
    drift_rigs=32, stability_steps=0, display_sizes=((640, 360),), display_frames=2,
    premise_steps=(0, 1),
)  # fmt: skip
FULL = BenchPlan(
    per_split=48, repeats=20, frames=12, accuracy_samples=24, frame_sizes=(256, 512),
    skip_frames=24, levels=(8, 16, 32, 64, 128), capture_resolutions=(64, 128, 256),
    capture_frames=(0.0, 31.0), capture_views=12, presets=("tiny", "small", "paper"),
    training_steps=4, memory_frames=8, stress_rigs=100_000, drift_rigs=256, stability_steps=400,
)  # fmt: skip


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    import numpy as np
    import onnxruntime as ort
    from pxr import Usd

    cpu = ""
    info = Path("/proc/cpuinfo")
    if info.is_file():
        for line in info.read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    memory = ""
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        kib = int(meminfo.read_text().split("MemTotal:")[1].split()[0])
        memory = f"{kib / 2**20:.1f} GiB"
    versions = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "onnxruntime": ort.__version__,
        "usd": ".".join(map(str, Usd.GetVersion())),
    }
    try:
        import torch

        versions["torch"] = torch.__version__
    except ImportError:
        versions["torch"] = "not installed"
    return {
        "cpu": cpu or platform.processor(),
        "cores": os.cpu_count(),
        "memory": memory,
        "platform": platform.platform(),
        "onnxruntime_providers": ort.get_available_providers(),
        "versions": versions,
        "gpu": "none" if "CUDAExecutionProvider" not in ort.get_available_providers() else "CUDA",
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="a few minutes: fewer samples")
    parser.add_argument(
        "--out",
        required=True,
        help="folder for results (docs/bench holds the committed ones: pass it to replace them)",
    )
    parser.add_argument(
        "--dataset",
        help="a capture of the sample scene (`rigspace capture samples/scenes/previs.usda`): "
        "adds the captured-view baselines and a training-stability run on it",
    )
    parser.add_argument(
        "--only",
        nargs="+",
        metavar="PART",
        help=f"run only these parts: {', '.join(PARTS)}",
    )
    add_predictor_argument(parser)
    add_device_argument(parser)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from rigspace.sdk.errors import RigspaceError

    plan = replace(QUICK if args.quick else FULL, predictor=args.predictor, device=args.device)
    parts = tuple(args.only or PARTS)
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise RigspaceError(
            f"Unknown bench part {', '.join(unknown)}.", f"choose from {', '.join(PARTS)}."
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dataset = Path(args.dataset) if args.dataset else None
    command = "rigspace " + " ".join(sys.argv[1:]) if sys.argv else "rigspace bench"
    now = datetime.now(UTC).isoformat(timespec="seconds")
    mode = "quick" if args.quick else "full"
    result: dict[str, Any] = {
        "command": command,
        "date": now,
        "mode": mode,
        "machine": machine(),
        "seconds": {},
        "parts": {},
    }
    previous = out / "results.json"
    if args.only and previous.is_file():
        # Re-running some parts: the others keep their numbers, each part its own date, and
        # its own machine where it was measured on another one (never dropped: a part re-run
        # on a new machine once wiped every other part of the folder).
        kept = json.loads(previous.read_text())
        if kept.get("mode") == mode:
            if kept.get("machine") != result["machine"]:
                for part in (p for p in PARTS if p in kept):
                    kept.setdefault("parts", {}).setdefault(part, {}).setdefault(
                        "machine", kept.get("machine")
                    )
            result = kept
            result.setdefault("parts", {})
    with tempfile.TemporaryDirectory() as tmp:
        bar = tqdm(parts, unit="part", file=sys.stderr, dynamic_ncols=True)
        for part in bar:
            bar.set_postfix_str(part)
            start = time.monotonic()
            spec = BY_NAME[part]
            result[part] = spec.measure(plan, Path(tmp), dataset)
            result["seconds"][part] = round(time.monotonic() - start, 1)
            result["parts"][part] = {"command": command, "date": now, "machine": machine()}
            if spec.plot is not None:
                spec.plot(result[part], out)
            _write(out, result)  # every part is kept even if a later one fails
    _write(out, result)
    print(f"bench results in {out}: results.json, README.md" + _pngs(out))
    return 0


def _pngs(out: Path) -> str:
    names = sorted(p.name for p in out.glob("*.png"))
    return (", " + ", ".join(names)) if names else ""


def _write(out: Path, result: dict[str, Any]) -> None:
    from rigspace.bench.report import markdown

    write_atomic(out / "results.json", json.dumps(result, indent=1, default=_plain) + "\n")
    write_atomic(out / "README.md", markdown(result, SECTIONS))


def _plain(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON")


# -- the parts ------------------------------------------------------------------------------


def _pareto(plan: BenchPlan, tmp: Path, dataset: Path | None) -> dict[str, Any]:
    from rigspace.bench import pareto

    result = pareto.measure(
        plan.per_split, plan.repeats, 256, plan.frames, dataset, predictor=plan.predictor
    )
    return result


def _accuracy(plan: BenchPlan, tmp: Path, dataset: Path | None) -> dict[str, Any]:
    from rigspace.bench import accuracy

    return accuracy.measure(samples=plan.accuracy_samples)


def _frames(plan: BenchPlan, tmp: Path, dataset: Path | None) -> list[dict[str, Any]]:
    from rigspace.bench import frame_stages

    return frame_stages.measure(
        tmp, plan.frame_sizes, (1, 4), plan.frames, predictor=plan.predictor
    )


def _skips(plan: BenchPlan, tmp: Path, dataset: Path | None) -> dict[str, Any]:
    from rigspace.bench import skips

    return {
        precision: skips.measure(tmp, 256, precision, plan.skip_frames)
        for precision in ("int8", "fp32")
    }


def _efficiency(plan: BenchPlan, tmp: Path, dataset: Path | None) -> dict[str, Any]:
    from rigspace.bench import flops
    from rigspace.bench.scenes import ROOT

    bundle = ROOT / "samples" / "models" / "sample"
    rows = [
        flops.efficiency(bundle, level, precision, threads=threads, repeats=plan.repeats)
        for threads in (1, 0)
        for level in plan.levels
        for precision in ("fp32", "int8")
    ]
    return {"peak": flops.peak_flops(repeats=plan.repeats), "rows": rows}


def _capture(plan: BenchPlan, tmp: Path, dataset: Path | None) -> list[dict[str, Any]]:
    from rigspace.bench import throughput

    return throughput.capture_throughput(
        ("gl", "embree"), plan.capture_resolutions, plan.capture_frames, plan.capture_views
    )


def _training(plan: BenchPlan, tmp: Path, dataset: Path | None) -> dict[str, Any]:
    from rigspace.bench import throughput

    rows = throughput.training_throughput(plan.presets, plan.training_steps, device=plan.device)
    result: dict[str, Any] = {"throughput": rows}
    if dataset is not None and plan.stability_steps:
        result["stability"] = training_stability(dataset, tmp, plan.stability_steps)
    return result


def training_stability(dataset: Path, tmp: Path, steps: int) -> dict[str, Any]:
    """The `small` preset's real loop on the sample dataset, every level in `steps` steps:
    the loss of every step, checked finite."""
    from dataclasses import replace

    from rigspace.train.config import preset
    from rigspace.train.loop import train

    config = replace(preset("small"), steps_per_level=steps // 4, eval_every=10**9)
    run_folder = tmp / "stability_run"
    result = train(dataset, run_folder, config, steps=steps, progress=False)
    losses = [json.loads(line)["loss"] for line in (run_folder / "log.jsonl").open()]
    import math

    return {
        "preset": "small",
        "steps": result.step,
        "levels": list(config.levels()),
        "finite": all(math.isfinite(x) for x in losses),
        "first_loss": losses[0],
        "last_loss": losses[-1],
        "max_loss": max(losses),
        "images_per_s": result.images_per_second,
    }


def _texture(plan: BenchPlan, tmp: Path, dataset: Path | None) -> list[dict[str, Any]]:
    from rigspace.bench import texture

    return texture.measure(plan.display_sizes, plan.display_frames)


def _premise(plan: BenchPlan, tmp: Path, dataset: Path | None) -> dict[str, Any]:
    from rigspace.bench import premise

    rows = premise.measure(plan.premise_steps)
    return {"rows": rows, "crossover": premise.crossover(rows)}


def _predictors(plan: BenchPlan, tmp: Path, dataset: Path | None) -> list[dict[str, Any]]:
    from rigspace.bench import predictors
    from rigspace.bench.scenes import ROOT

    bundle = ROOT / "samples" / "models" / "sample"
    return predictors.measure(bundle, plan.repeats, plan.levels, plan.device)


def _data(plan: BenchPlan, tmp: Path, dataset: Path | None) -> dict[str, Any]:
    from rigspace.bench import data

    return data.measure(dataset, 8 * plan.per_split)


def _memory(plan: BenchPlan, tmp: Path, dataset: Path | None) -> list[dict[str, Any]]:
    from rigspace.bench import memory

    return [memory.peak_rss(n, 256, "fp32", plan.memory_frames) for n in (1, 8)]


def _stability(plan: BenchPlan, tmp: Path, dataset: Path | None) -> dict[str, Any]:
    import numpy as np

    from rigspace.bench import stability
    from rigspace.bench.scenes import PREVIS, ROOT
    from rigspace.sdk.model import BundleModel

    bundle = ROOT / "samples" / "models" / "sample"
    fp32, int8 = BundleModel(bundle), BundleModel(bundle, "int8")
    result: dict[str, Any] = {
        "stress": stability.stress(fp32, plan.stress_rigs, 0, stability.LONG_LEVEL)
    }
    rng = np.random.default_rng(0)
    sets = {
        "random rotations": stability.rigs(
            stability.haar(rng, plan.drift_rigs, len(fp32.joints)),
            stability.camera_frames(rng, plan.drift_rigs),
        ),
        "animation": stability.animation_rigs(PREVIS, "/World/Hero", fp32, plan.drift_rigs),
    }
    result["drift"] = {
        f"{name}, level {level}": stability.drift(fp32, int8, rigs, level)
        for name, rigs in sets.items()
        for level in plan.levels
    }
    return result


@dataclass(frozen=True)
class BenchPart:
    """One part of the bench: how it measures, its README section, and its plot (if any)."""

    name: str
    measure: Callable[[BenchPlan, Path, Path | None], Any]
    section: Callable[[Any], list[str]]
    plot: Callable[[Any, Path], None] | None = None
    """Writes the part's PNG into the output folder."""


def _plot_pareto(value: Any, out: Path) -> None:
    from rigspace.bench import pareto

    pareto.plot(value, out / "pareto.png")


def _plot_premise(value: Any, out: Path) -> None:
    from rigspace.bench import premise

    premise.plot(value, out / "premise.png")


def _plot_skips(value: Any, out: Path) -> None:
    from rigspace.bench import skips

    skips.plot(value["int8"], out / "skips.png")


BENCH_PARTS = (
    BenchPart("pareto", _pareto, report._pareto, _plot_pareto),
    BenchPart("accuracy", _accuracy, report._accuracy),
    BenchPart("frames", _frames, report._frames),
    BenchPart("texture", _texture, report._texture),
    BenchPart("premise", _premise, report._premise, _plot_premise),
    BenchPart("skips", _skips, report._skips, _plot_skips),
    BenchPart("efficiency", _efficiency, report._efficiency),
    BenchPart("predictors", _predictors, report._predictors),
    BenchPart("capture", _capture, report._capture),
    BenchPart("training", _training, report._training),
    BenchPart("data", _data, report._data),
    BenchPart("memory", _memory, report._memory),
    BenchPart("stability", _stability, report._stability),
)
"""The bench's parts, in the order they run and report: one spec per part (what used to be
parallel dicts of measurements and sections, and a chain of ifs for the plots)."""
BY_NAME = {p.name: p for p in BENCH_PARTS}
PARTS = tuple(BY_NAME)
SECTIONS = [(p.name, p.section) for p in BENCH_PARTS]


COMMAND = CommandSpec(
    name="bench",
    help="benchmark run time against error, skips, memory and stability; write JSON, Markdown, plots",
    description=DESCRIPTION,
    add_arguments=add_arguments,
    run=run,
)

"""Measure the shadow stage on the previs scene: compiled kernels against numpy, split by sub-step.

`python -m rigspace.apps.shadow_timing [--scene S] [--frames N] [--sizes 256x256 640x360]
[--kernels numba numpy]`: per size, two engines (ShadowBackend kernel "numba" and "numpy", or
those named) render the same frames of the previs scene (samples/scenes/previs.usda of the
source checkout, or --scene) with the sample character, one frame each in turn in one
process (so that load on a shared machine falls on both alike); printed per engine: the
median frame and stage milliseconds from the engine's own report, the shadow stage's
fraction of the frame, its split into sub-steps (each one's own time, callees excluded:
the shadows package's functions below are wrapped while a frame renders), and the first
frame's time (for numba, loading or compiling the kernels); then the same fraction in CPU
time (the process's, all threads: the report's shadows `cpu_seconds`, Engine.report_cpu,
against the whole render), which a loaded machine distorts less than the wall clock; then
the prims' shadow passes and the character layer's of one frame (Engine.shadows.record) run
again and again on the same inputs, both ways: the best and the median CPU milliseconds of
the thread they run in, the least noisy comparison on a shared machine.
"""

from __future__ import annotations

import argparse
import statistics
import time as clock
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from rigspace.runtime import shadows
from rigspace.runtime.engine import STAGES, Engine, EngineSettings
from rigspace.runtime.shadows import ShadowBackend
from rigspace.runtime.shadows import kernels as shadow_kernels
from rigspace.runtime.shadows import passes as shadow_pass

KERNELS = ("numba", "numpy")
SCENE = Path(__file__).resolve().parents[1] / "samples" / "scenes" / "previs.usda"
"""The previs scene of the source checkout (runtime/shadows/ -> the repository root): the
installed package has no samples/, so there --scene is needed."""
TIMES = np.linspace(100.0, 1400.0, 64)
"""The frames rendered (the first a warm-up): bench/frame_stages.py's."""
PASSES = {"prims": "prims' passes", "layer": "layer"}
"""The names in Engine.shadows.record, and what the lines call them."""

# Sub-step: the functions whose own time it is (module or class, attribute).

SUBSTEPS: dict[str, list[tuple[object, str]]] = {
    "draw maps": [(shadows.PrimShadows, "_render")],
    "screen regions": [
        (shadows, "shadow_regions"), (shadows.PrimShadows, "shadow_regions"),
        (shadows.PrimShadows, "regions"),
    ],
    "kernels": [(shadow_kernels, "sparse_pass"), (shadow_kernels, "points_visibility")],
    "kernel inputs": [(shadow_pass, "sets_data"), (shadow_pass, "maps_data")],
    "capsule occlusion (numpy)": [(shadows, "capsule_visibility")],
    "map lookups (numpy)": [(shadows.ShadowMap, "visibility")],
}  # fmt: skip


class _Timers:
    """Exclusive time per sub-step: a wrapped call's time less its wrapped callees'."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = dict.fromkeys(SUBSTEPS, 0.0)
        self._stack: list[float] = []
        self._saved: list[tuple[object, str, object]] = []

    def wrap(self) -> None:
        for name, places in SUBSTEPS.items():
            for owner, attribute in places:
                original = getattr(owner, attribute)
                self._saved.append((owner, attribute, original))
                setattr(owner, attribute, self._timed(name, original))

    def unwrap(self) -> None:
        for owner, attribute, original in reversed(self._saved):
            setattr(owner, attribute, original)
        self._saved = []

    def _timed(self, name: str, function: Callable) -> Callable:
        def timed(*args, **kwargs):
            self._stack.append(0.0)
            start = clock.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                spent = clock.perf_counter() - start
                inner = self._stack.pop()
                self.seconds[name] += spent - inner
                if self._stack:
                    self._stack[-1] += spent

        return timed


def measure(
    scene: Path, sizes: Sequence[tuple[int, int]], frames: int, kernels: Sequence[str] = KERNELS
) -> list[str]:
    """The lines printed: per size and kernel, the frame, the shadow stage and its split."""
    lines = []
    times = TIMES[: frames + 1]
    for width, height in sizes:
        runs: dict[str, tuple[Engine, list[dict], float, _Timers]] = {}
        try:
            for kernel in kernels:
                settings = EngineSettings(
                    width=width, height=height, prim_samples=1, shadow_backend=ShadowBackend(kernel)
                )
                engine = Engine(scene, settings)
                engine.report_cpu = True  # the report's cpu_seconds per stage
                start = clock.perf_counter()
                engine.render(float(times[0]))  # warm-up (numba: load or compile the kernels)
                runs[kernel] = (engine, [], clock.perf_counter() - start, _Timers())
            for t in times[1:]:
                for _kernel, (engine, reports, _, timers) in runs.items():
                    timers.wrap()
                    start = clock.process_time()
                    try:
                        report = engine.render(float(t)).report
                    finally:
                        timers.unwrap()
                    assert report.cpu_seconds is not None  # report_cpu
                    seconds = dict(report.seconds)
                    seconds["cpu"] = clock.process_time() - start
                    seconds["cpu shadows"] = report.cpu_seconds["shadows"]
                    reports.append(seconds)
        finally:
            for engine, _, _, _ in runs.values():
                engine.close()
        for kernel, (_, reports, first, timers) in runs.items():
            ms = {k: 1e3 * statistics.median(r[k] for r in reports) for k in (*STAGES, "total")}
            stages = " ".join(f"{k} {ms[k]:.1f}" for k in STAGES)
            lines.append(
                f"{width}x{height} {kernel}: frame {ms['total']:.1f} ms, shadows "
                f"{ms['shadows']:.1f} ms = {ms['shadows'] / ms['total']:.2f} of the frame "
                f"({stages}); first frame {1e3 * first:.0f} ms"
            )
            total = 1e3 * sum(r["shadows"] for r in reports) / len(reports)
            split = {k: 1e3 * v / len(reports) for k, v in timers.seconds.items() if v > 0}
            split["rest (glue, blending in numpy)"] = total - sum(split.values())
            cpu = statistics.median(r["cpu shadows"] / r["cpu"] for r in reports)
            cpu_ms = 1e3 * statistics.median(r["cpu shadows"] for r in reports)
            frame_cpu = 1e3 * statistics.median(r["cpu"] for r in reports)
            lines.append(
                f"    CPU time: frame {frame_cpu:.1f} ms, shadows {cpu_ms:.1f} ms = {cpu:.2f} of "
                "the frame (median of per-frame fractions)"
            )
            lines.append(
                "    shadows per frame (mean): "
                + ", ".join(f"{k} {v:.2f}" for k, v in split.items())
                + f" ms (of {total:.2f})"
            )
    return lines


def passes(
    scene: Path,
    sizes: Sequence[tuple[int, int]],
    repeats: int = 15,
    kernels: Sequence[str] = KERNELS,
) -> list[str]:
    """Lines: per size, the prims' passes (their maps drawn) and the character layer's of
    the frame at time 600 (Engine.shadows.record) again and again on the same inputs, numba
    against numpy (best and median CPU milliseconds of this thread, where both run: the
    process's would count onnxruntime's threads spinning after the frame's inference)."""
    lines = []
    for width, height in sizes:
        engine = Engine(scene, EngineSettings(width=width, height=height, prim_samples=1))
        found: dict[tuple[str, str], tuple[float, float]] = {}
        try:
            engine.render(500.0)
            engine.shadows.record = {}  # the next frame's passes, kept to run again
            engine.render(600.0)
            recorded = dict(engine.shadows.record)
            for name, run in recorded.items():
                for kernel in kernels:
                    engine.use_shadow_backend(ShadowBackend(kernel))
                    spent = []
                    for _ in range(repeats):
                        start = clock.thread_time()
                        run()
                        spent.append(clock.thread_time() - start)
                    found[name, kernel] = (1e3 * min(spent), 1e3 * statistics.median(spent))
        finally:
            engine.close()
        for name, what in PASSES.items():
            mine = {k: found[name, k] for k in kernels if (name, k) in found}
            if not mine:
                continue
            line = (
                f"{width}x{height} {what}, thread CPU ms best (median) of {repeats}: "
                + ", ".join(f"{k} {best:.2f} ({median:.2f})" for k, (best, median) in mine.items())
            )
            if len(mine) == 2:
                line += f": {mine['numpy'][0] / mine['numba'][0]:.1f}x"
            lines.append(line)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scene", type=Path, default=SCENE,
        help="the previs scene (default: samples/scenes/previs.usda of the source checkout)",
    )  # fmt: skip
    parser.add_argument("--frames", type=int, default=12, help="frames after the warm-up")
    parser.add_argument("--sizes", nargs="+", default=["256x256", "640x360"])
    parser.add_argument(
        "--kernels", nargs="+", choices=KERNELS, default=list(KERNELS),
        help="which ways to measure (numba alone: half the time, for before/after runs)",
    )  # fmt: skip
    args = parser.parse_args()
    if not args.scene.is_file():
        parser.error(
            f"no scene at {args.scene}: pass --scene PATH to the previs scene (samples/ comes "
            "with the source checkout, not with the installed package)"
        )
    sizes = [(int(w), int(h)) for w, h in (s.split("x") for s in args.sizes)]
    for line in [
        *measure(args.scene, sizes, args.frames, args.kernels),
        *passes(args.scene, sizes, 15, args.kernels),
    ]:
        print(line, flush=True)


if __name__ == "__main__":
    main()

"""Measure the shadow stage on the previs scene: compiled kernels against numpy, split by sub-step.

`python -m rigspace.runtime.shadow_bench [--frames N] [--sizes 256x256 640x360]`: per size,
two engines (SHADOW_KERNEL "numba" and "numpy") render the same frames of
samples/scenes/previs.usda with the sample character, one frame each in turn in one
process (so that load on a shared machine falls on both alike); printed per engine: the
median frame and stage milliseconds from the engine's own report, the shadow stage's
fraction of the frame, its split into sub-steps (each one's own time, callees excluded),
and the first frame's time (for numba, loading or compiling the kernels).
"""

from __future__ import annotations

import argparse
import statistics
import time as clock
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from rigspace.runtime import engine as engine_module
from rigspace.runtime import shadow_kernels, shadow_pass, shadows
from rigspace.runtime.engine import STAGES, Engine

SCENE = Path(__file__).resolve().parents[1] / "samples" / "scenes" / "previs.usda"
TIMES = np.linspace(100.0, 1400.0, 64)
"""The frames rendered (the first a warm-up): bench/frames.py's."""

# Sub-step: the functions whose own time it is (module or class, attribute).
SUBSTEPS: dict[str, list[tuple[object, str]]] = {
    "draw maps": [(shadows.PrimShadows, "_render")],
    "screen regions": [
        (shadows, "shadow_regions"), (engine_module, "shadow_regions"),
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


def measure(sizes: Sequence[tuple[int, int]], frames: int) -> list[str]:
    """The lines printed: per size and kernel, the frame, the shadow stage and its split."""
    lines = []
    times = TIMES[: frames + 1]
    for width, height in sizes:
        runs: dict[str, tuple[Engine, list[dict], float, _Timers]] = {}
        try:
            for kernel in ("numba", "numpy"):
                shadows.SHADOW_KERNEL = kernel
                engine = Engine(SCENE, width=width, height=height, prim_samples=1)
                start = clock.perf_counter()
                engine.render(float(times[0]))  # warm-up (numba: load or compile the kernels)
                runs[kernel] = (engine, [], clock.perf_counter() - start, _Timers())
            for t in times[1:]:
                for kernel, (engine, reports, _, timers) in runs.items():
                    shadows.SHADOW_KERNEL = kernel
                    timers.wrap()
                    try:
                        reports.append(engine.render(float(t)).report["seconds"])
                    finally:
                        timers.unwrap()
        finally:
            shadows.SHADOW_KERNEL = "numba"
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
            lines.append(
                "    shadows per frame (mean): "
                + ", ".join(f"{k} {v:.2f}" for k, v in split.items())
                + f" ms (of {total:.2f})"
            )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=12, help="frames after the warm-up")
    parser.add_argument("--sizes", nargs="+", default=["256x256", "640x360"])
    args = parser.parse_args()
    sizes = [(int(w), int(h)) for w, h in (s.split("x") for s in args.sizes)]
    for line in measure(sizes, args.frames):
        print(line, flush=True)


if __name__ == "__main__":
    main()

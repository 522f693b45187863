"""Per-frame time of the runtime split by stage: sizes, character counts, fp32 and int8.

For each size, number of characters and precision: one warm-up frame, then the median
over distinct frames of each stage's seconds from the engine's own report (the previs
scene with its moving camera and props: every stage works every frame), and the cost of
rendering the last frame again (nothing changed: the frame cache) as a fraction of a
full frame, measured in the same run.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.bench.predictors import for_precision
from rigspace.bench.scenes import PREVIS, crowd_scene
from rigspace.bench.timing import summary
from rigspace.runtime.engine import STAGES, Engine, EngineSettings

TIMES = np.linspace(100.0, 1400.0, 64)


def frame_reports(
    scene: Path, times, size: int, again: bool = False, **engine_options
) -> list[dict[str, Any]]:
    """The Engine's reports of the frames at times[1:], after a warm-up frame at times[0]
    (sessions, GL buffers); with `again`, the last frame once more at the end."""
    engine = Engine(scene, EngineSettings(width=size, height=size, **engine_options))
    try:
        engine.render(float(times[0]))
        reports = [engine.render(float(t)).report.to_json() for t in times[1:]]
        if again:
            reports.append(engine.render(float(times[-1])).report.to_json())
    finally:
        engine.close()
    return reports


def total_ms(reports: list[dict[str, Any]]) -> dict[str, float]:
    """Median, min and max of the reports' total milliseconds."""
    return summary([1e3 * r["seconds"]["total"] for r in reports])


def measure_one(
    scene: Path,
    size: int,
    precision: str,
    frames: int,
    prim_samples: int = 1,
    predictor: str = "auto",
) -> dict[str, Any]:
    reports = frame_reports(
        scene,
        TIMES[: frames + 1],
        size,
        again=True,
        precision=precision,
        prim_samples=prim_samples,
        predictor=for_precision(predictor, precision),
    )
    repeat = reports.pop()
    ms = {k: 1e3 * statistics.median(r["seconds"][k] for r in reports) for k in (*STAGES, "total")}
    totals = total_ms(reports)
    return {
        "characters": len(reports[0]["characters"]),
        "drawn": min(r["counts"]["evaluated"] + r["counts"]["reused"] for r in reports),
        "size": size,
        "precision": precision,
        "prim_samples": prim_samples,
        "ms": ms,
        "min_ms": totals["min_ms"],
        "max_ms": totals["max_ms"],
        "repeat_ms": 1e3 * repeat["seconds"]["total"],
        "repeat_fraction": repeat["seconds"]["total"] * 1e3 / ms["total"],
    }


def measure(
    folder: Path,
    sizes: tuple[int, ...] = (256, 512),
    characters: tuple[int, ...] = (1, 4),
    frames: int = 8,
    prim_samples: int = 1,
    predictor: str = "auto",
) -> list[dict[str, Any]]:
    rows = []
    for count in characters:
        scene = PREVIS if count == 1 else crowd_scene(folder, count)
        for size in sizes:
            for precision in ("fp32", "int8"):
                rows.append(measure_one(scene, size, precision, frames, prim_samples, predictor))
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    head = " | ".join(STAGES)
    lines = [
        f"| chars | size | precision | total ms (min-max) | {head} | repeat ms (fraction) |",
        "|---|---|---|---|" + "---|" * len(STAGES) + "---|",
    ]
    for r in rows:
        ms = r["ms"]
        stages = " | ".join(f"{ms.get(stage, 0.0):.1f}" for stage in STAGES)
        lines.append(
            f"| {r['characters']} | {r['size']} | {r['precision']} | {ms['total']:.1f} "
            f"({r['min_ms']:.1f}-{r['max_ms']:.1f}) | {stages} | "
            f"{r['repeat_ms']:.2f} ({r['repeat_fraction']:.3f}) |"
        )
    return "\n".join(lines)

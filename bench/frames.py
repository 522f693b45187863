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

from rigspace.bench.scenes import PREVIS, crowd_scene
from rigspace.runtime.engine import STAGES, Engine

TIMES = np.linspace(100.0, 1400.0, 64)


def measure_one(
    scene: Path, size: int, precision: str, frames: int, prim_samples: int = 1
) -> dict[str, Any]:
    engine = Engine(scene, width=size, height=size, precision=precision, prim_samples=prim_samples)
    try:
        engine.render(float(TIMES[0]))  # warm-up: sessions, GL buffers
        reports = [engine.render(float(t)).report for t in TIMES[1 : frames + 1]]
        repeat = engine.render(float(TIMES[frames])).report
    finally:
        engine.close()
    ms = {k: 1e3 * statistics.median(r["seconds"][k] for r in reports) for k in (*STAGES, "total")}
    totals = [1e3 * r["seconds"]["total"] for r in reports]
    return {
        "characters": len(reports[0]["characters"]),
        "drawn": min(r["counts"]["evaluated"] + r["counts"]["reused"] for r in reports),
        "size": size,
        "precision": precision,
        "prim_samples": prim_samples,
        "ms": ms,
        "min_ms": min(totals),
        "max_ms": max(totals),
        "repeat_ms": 1e3 * repeat["seconds"]["total"],
        "repeat_fraction": repeat["seconds"]["total"] * 1e3 / ms["total"],
    }


def measure(
    folder: Path,
    sizes: tuple[int, ...] = (256, 512),
    characters: tuple[int, ...] = (1, 4),
    frames: int = 8,
    prim_samples: int = 1,
) -> list[dict[str, Any]]:
    rows = []
    for count in characters:
        scene = PREVIS if count == 1 else crowd_scene(folder, count)
        for size in sizes:
            for precision in ("fp32", "int8"):
                rows.append(measure_one(scene, size, precision, frames, prim_samples))
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| chars | size | precision | total ms (min-max) | scene | rig | network | lighting | composite | repeat ms (fraction) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ms = r["ms"]
        lines.append(
            f"| {r['characters']} | {r['size']} | {r['precision']} | {ms['total']:.1f} "
            f"({r['min_ms']:.1f}-{r['max_ms']:.1f}) | {ms['scene']:.1f} | {ms['rig']:.1f} | "
            f"{ms['network']:.1f} | {ms['lighting']:.1f} | {ms['composite']:.1f} | "
            f"{r['repeat_ms']:.2f} ({r['repeat_fraction']:.3f}) |"
        )
    return "\n".join(lines)

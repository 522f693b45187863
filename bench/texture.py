"""The character at the size it is seen: its own textures against the albedo branch alone.

The previs shot at display sizes (640x360, 1920x1080): per frame, the network's frame with
the texture head's colour (`rigspace render`'s default), the same with the albedo branch
alone (`--no-textures`) and the skinned mesh drawn by the renderer (`--reference`), rendered
one after the other at each time; the character region's albedo and beauty PSNR, its beauty
FLIP (and the ceiling: the mesh's region squeezed to the network's level and back,
runtime.reference.region_flip) and its own coverage's IoU against the mesh's, and each frame's
milliseconds (total, network stage, and the texture sampler's own). The two network modes
differ only in the colour of the pixels the textures cover: their time difference is the
sampler's cost per character.
"""

from __future__ import annotations

import statistics
from typing import Any

import numpy as np

from rigspace.bench.scenes import PREVIS
from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.runtime.reference import compare_regions, coverages

TIMES = np.linspace(0.0, 1600.0, 17)
"""The shot's frames every 100 time codes (the README's `--step 100` comparison)."""
MODES = ("textures", "albedo branch")


def measure(sizes: tuple[tuple[int, int], ...], frames: int) -> list[dict[str, Any]]:
    rows = []
    times = TIMES[np.unique(np.linspace(0, len(TIMES) - 1, frames).round().astype(int))]
    for width, height in sizes:
        engines = {
            "textures": Engine(PREVIS, EngineSettings(width=width, height=height)),
            "albedo branch": Engine(
                PREVIS, EngineSettings(width=width, height=height, textures=False)
            ),
        }
        truth = Engine(PREVIS, EngineSettings(width=width, height=height, reference=True))
        records: dict[str, list[dict[str, Any]]] = {m: [] for m in MODES}
        try:
            for engine in (*engines.values(), truth):  # warm-up: sessions, kernels, buffers
                engine.render(float(times[0]) + 1.0)
            for t in times:
                reference = truth.render(float(t))
                for mode, engine in engines.items():
                    frame = engine.render(float(t))
                    regions = [
                        r
                        for r in compare_regions(frame, reference, coverages(engine, truth, t))
                        if r["psnr"] is not None
                    ]
                    (entry,) = frame.report.characters  # the shot's one character
                    records[mode].append(
                        {
                            "time": float(t),
                            "total_ms": 1e3 * frame.report.seconds["total"],
                            "network_ms": 1e3 * frame.report.seconds["network"],
                            "texture_ms": entry.get("texture_ms"),
                            "size_px": entry.get("size_px"),
                            "regions": regions,
                        }
                    )
        finally:
            for engine in (*engines.values(), truth):
                engine.close()
        for mode in MODES:
            rows.append(_row(width, height, mode, records[mode]))
    return rows


def _median(values: list[Any]) -> float | None:
    values = [v for v in values if v is not None]
    return float(statistics.median(values)) if values else None


def _row(width: int, height: int, mode: str, records: list[dict[str, Any]]) -> dict[str, Any]:
    regions = [r for rec in records for r in rec["regions"]]
    return {
        "size": f"{width}x{height}",
        "mode": mode,
        "frames": len(records),
        "character_px": _median([r["size_px"] for r in records]),
        "albedo_psnr": _median([r["albedo_psnr"] for r in regions]),
        "beauty_psnr": _median([r["psnr"] for r in regions]),
        "beauty_psnr_min": min((r["psnr"] for r in regions), default=None),
        "mask_iou": _median([r.get("mask_iou") for r in regions]),
        "beauty_flip": _median([r.get("flip") for r in regions]),
        "flip_ceiling": _median([r.get("flip_ceiling") for r in regions]),
        "total_ms": _median([r["total_ms"] for r in records]),
        "network_ms": _median([r["network_ms"] for r in records]),
        "texture_ms": _median([r["texture_ms"] for r in records]),
    }


def table(rows: list[dict[str, Any]]) -> list[str]:
    def f(value: Any, digits: int = 2) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    lines = [
        "| size | colour | character px | albedo dB | beauty dB (min) | beauty FLIP (ceiling) | mask IoU | frame ms | network ms | sampler ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['size']} | {r['mode']} | {f(r['character_px'], 0)} | {f(r['albedo_psnr'])} | "
            f"{f(r['beauty_psnr'])} ({f(r['beauty_psnr_min'])}) | "
            f"{f(r.get('beauty_flip'), 4)} ({f(r.get('flip_ceiling'), 4)}) | {f(r['mask_iou'], 3)} | "
            f"{f(r['total_ms'], 1)} | {f(r['network_ms'], 1)} | {f(r['texture_ms'])} |"
        )
    return lines

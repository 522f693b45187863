"""Capture throughput per renderer and resolution, with the time split per sample.

    python -m rigspace.apps.capture_rates [--scene S] [--character P] [--frames A:B] [--json F]

Runs real captures (every core, the scene's ring with --views views at one elevation)
into a temporary folder, each renderer and resolution in turn within one run, and
prints samples/s and the per-sample split: pose (UsdSkel), render (draw, read-back),
EXR write. The split is per sample on one core (summed over workers), so it adds up to
more than the wall time per sample.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from rigspace.capture.pipeline import capture
from rigspace.capture.settings import CaptureOverrides

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCENE = ROOT / "samples" / "scenes" / "previs.usda"
DEFAULT_CHARACTER = "/World/Hero"


def run(scene: Path, character: str, frames: tuple[float, float], views: int, sizes, renderers):
    rows = []
    for renderer in renderers:
        for size in sizes:
            overrides = CaptureOverrides(
                views=views, elevations=(0.0,), resolution=size, frames=frames, renderer=renderer
            )
            with tempfile.TemporaryDirectory() as tmp:
                result = capture(scene, character, Path(tmp) / "ds", overrides, progress=False)
            n = result.samples_done
            rows.append(
                {
                    "renderer": renderer,
                    "resolution": size,
                    "samples": n,
                    "seconds": result.seconds,
                    "samples_per_s": n / result.seconds,
                    "ms_per_sample_one_core": {k: 1e3 * v / n for k, v in result.timings.items()},
                    "bytes_per_sample": result.manifest.bytes / n if result.manifest else None,
                }
            )
            print(_row(rows[-1]), flush=True)
    return rows


def _row(r) -> str:
    t = r["ms_per_sample_one_core"]
    return (
        f"| {r['renderer']} | {r['resolution']} | {r['samples_per_s']:.1f} | {t['pose']:.2f} | "
        f"{t['render']:.1f} | {t.get('render.draw', float('nan')):.1f} | "
        f"{t.get('render.readback', float('nan')):.1f} | {t['write']:.1f} | "
        f"{r['bytes_per_sample'] / 1024:.0f} |"
    )

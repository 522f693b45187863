"""Capture throughput per renderer and resolution, with the time split per sample.

    python -m rigspace.capture.rates [--scene S] [--character P] [--frames A:B] [--json F]

Runs real captures (every core, the scene's ring with --views views at one elevation)
into a temporary folder, each renderer and resolution in turn within one run, and
prints samples/s and the per-sample split: pose (UsdSkel), render (draw, read-back),
EXR write. The split is per sample on one core (summed over workers), so it adds up to
more than the wall time per sample.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
from pathlib import Path

from rigspace.capture.pipeline import capture
from rigspace.capture.settings import CaptureOverrides
from rigspace.sdk.files import write_atomic
from rigspace.sdk.render import renderer_plugins

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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--character", default=DEFAULT_CHARACTER)
    parser.add_argument("--frames", default="0:47", help="time codes A:B")
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--renderers", nargs="+", default=["gl", "embree"])
    parser.add_argument("--json", type=Path, help="also write the raw numbers here")
    args = parser.parse_args(argv)
    first, last = (float(x) for x in args.frames.split(":"))
    usable = [r for r in args.renderers if r in renderer_plugins()]
    print(
        f"# capture throughput: {args.scene.name} {args.character}, frames {args.frames}, "
        f"{args.views} views, {platform.processor() or platform.machine()}"
    )
    print(
        "| renderer | size | samples/s | pose ms | render ms | draw ms | read-back ms | "
        "write ms | KiB/sample |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    rows = run(args.scene, args.character, (first, last), args.views, args.sizes, usable)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(
            args.json,
            json.dumps({"command": "python -m rigspace.capture.rates", "rows": rows}, indent=2),
        )


if __name__ == "__main__":
    main()

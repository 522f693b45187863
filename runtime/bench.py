"""Per-frame time of the runtime: split by stage, 1 and 4 characters, fp32 and int8, repeats.

    python -m rigspace.runtime.bench [--sizes 256 512] [--frames 8] [--json FILE]

Renders the previs scene (and a copy with three more heroes, internal references of the
first placed beside it) with the committed sample model. For each size, character count
and precision: one warm-up frame, then the median over --frames distinct frames of each
stage's seconds from the engine's own report, and the cost of rendering the last frame
again (pose and camera unchanged: prims' G-buffer and characters' maps reused) as a
fraction of a full frame, measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from pxr import Gf, Usd, UsdGeom

from rigspace.runtime.engine import STAGES, Engine
from rigspace.sdk.stage import overlay_layer

ROOT = Path(__file__).resolve().parents[1]
PREVIS = ROOT / "samples" / "scenes" / "previs.usda"
TIMES = np.linspace(100.0, 1500.0, 64)


def crowd_scene(folder: Path, extra: int = 3) -> Path:
    """A layer over the previs scene with `extra` more heroes beside the first."""
    layer = overlay_layer(folder / "crowd.usda", PREVIS)
    stage = Usd.Stage.Open(layer)
    for k in range(extra):
        prim = stage.DefinePrim(f"/World/Hero{k + 1}")
        prim.GetReferences().AddInternalReference("/World/Hero")
        UsdGeom.XformCommonAPI(prim).SetTranslate(Gf.Vec3d(-120.0 * (k + 1), 0, -80.0 * k))
    layer.Save()
    return folder / "crowd.usda"


def measure(scene: Path, size: int, precision: str, frames: int) -> dict:
    engine = Engine(scene, width=size, height=size, precision=precision)
    try:
        engine.render(float(TIMES[0]))  # warm-up: sessions, GL buffers
        reports = [engine.render(float(t)).report for t in TIMES[1 : frames + 1]]
        repeat = engine.render(float(TIMES[frames])).report
    finally:
        engine.close()
    median = {k: float(np.median([r["seconds"][k] for r in reports])) for k in (*STAGES, "total")}
    return {
        "characters": len(reports[0]["characters"]),
        "size": size,
        "precision": precision,
        "ms": {k: 1e3 * v for k, v in median.items()},
        "repeat_ms": 1e3 * repeat["seconds"]["total"],
        "repeat_fraction": repeat["seconds"]["total"] / median["total"],
        "decisions": sorted({c["decision"] for r in reports for c in r["characters"]}),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    rows = []
    print(
        "| chars | size | precision | total ms | scene | rig | network | lighting | composite | repeat ms (fraction) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        scenes = {"one hero": PREVIS, "four heroes": crowd_scene(Path(tmp))}
        for scene in scenes.values():
            for size in args.sizes:
                for precision in ("fp32", "int8"):
                    row = measure(scene, size, precision, args.frames)
                    rows.append(row)
                    ms = row["ms"]
                    print(
                        f"| {row['characters']} | {size} | {precision} | {ms['total']:.1f} | {ms['scene']:.1f} | "
                        f"{ms['rig']:.1f} | {ms['network']:.1f} | {ms['lighting']:.1f} | "
                        f"{ms['composite']:.1f} | {row['repeat_ms']:.1f} ({row['repeat_fraction']:.2f}) |",
                        flush=True,
                    )
    if args.json:
        args.json.write_text(
            json.dumps({"command": "python -m rigspace.runtime.bench", "rows": rows}, indent=2)
        )


if __name__ == "__main__":
    main()

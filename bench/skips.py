"""What each of the runtime's skips saves: frame time per case as a fraction of a full frame.

Every case is the previs scene through an overlay layer, rendered by the same Engine
settings in the same run, one warm-up frame then the median (min, max) of the frames:

- full, moving camera: the previs shot as authored (prims redrawn and re-lit each frame);
- full, still camera: the shot camera held at one pose and the two moving props removed;
  the character walks (evaluated, lit, composited each frame; the prims' G-buffer and
  lighting are reused) — the "full frame" every skip is a fraction of, and the cases below
  share its camera and set;
- off-screen: the character moved 5000 units to the side, out of the view;
- unchanged: the yoga hold (frames 1340-1550 hold one pose) under the still camera;
- far away: the character 6000 units behind the set, a few pixels tall (a small level);
- unlit and unoccluded: no lights, no prims, and only the beauty asked for: the albedo
  branch alone (the unlit mode).
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Gf, Usd, UsdGeom

from rigspace.bench.frame_stages import frame_reports, total_ms
from rigspace.runtime.engine import AOVS
from rigspace.sdk.stage import overlay_layer

ROOT = Path(__file__).resolve().parents[1]
PREVIS = ROOT / "samples" / "scenes" / "previs.usda"
CAMERA = "/World/ShotCam"
HERO = "/World/Hero"
MOVING_PROPS = ("/World/Set/PassingCrate", "/World/Set/RollingBall")
WALK = np.linspace(20.0, 340.0, 33)
HOLD = np.linspace(1340.0, 1550.0, 33)


def _scene(folder: Path, name: str, *, still: bool, offset=None, inactive=()) -> Path:
    layer = overlay_layer(folder / f"{name}.usda", PREVIS)
    stage = Usd.Stage.Open(layer)
    if still:
        camera = UsdGeom.Xformable(stage.GetPrimAtPath(CAMERA))
        pose = camera.ComputeLocalToWorldTransform(Usd.TimeCode(200.0))
        over = UsdGeom.Xformable(stage.OverridePrim(CAMERA))
        op = over.AddTransformOp(opSuffix="still")
        op.Set(pose)
        over.SetXformOpOrder([op])
    if offset is not None:
        UsdGeom.XformCommonAPI(stage.OverridePrim(HERO)).SetTranslate(Gf.Vec3d(*offset))
    for path in (*(MOVING_PROPS if still else ()), *inactive):
        stage.OverridePrim(path).SetActive(False)
    layer.Save()
    return folder / f"{name}.usda"


def cases(folder: Path) -> dict[str, dict[str, Any]]:
    return {
        "full, moving camera": {"scene": _scene(folder, "moving", still=False), "times": WALK},
        "full, still camera": {"scene": _scene(folder, "still", still=True), "times": WALK},
        "off-screen": {
            "scene": _scene(folder, "off", still=True, offset=(5000.0, 0.0, 0.0)),
            "times": WALK,
        },
        "unchanged": {"scene": _scene(folder, "still_hold", still=True), "times": HOLD},
        "far away": {
            "scene": _scene(folder, "far", still=True, offset=(0.0, 0.0, -6000.0)),
            "times": WALK,
        },
        "unlit and unoccluded": {
            "scene": _scene(folder, "unlit", still=True, inactive=("/World/Lights", "/World/Set")),
            "times": WALK,
            "aovs": ("beauty",),
        },
    }


def measure(
    folder: Path, size: int = 256, precision: str = "int8", frames: int = 16, prim_samples: int = 1
) -> dict[str, Any]:
    """Median (min, max) ms per frame of each case and its fraction of the still full frame."""
    rows: dict[str, dict[str, Any]] = {}
    for name, case in cases(folder).items():
        reports = frame_reports(
            case["scene"],
            case["times"][: frames + 1],
            size,
            camera=CAMERA,
            precision=precision,
            prim_samples=prim_samples,
            aovs=case.get("aovs", AOVS),
        )
        hero = [c for r in reports for c in r["characters"] if c["path"] == HERO]
        rows[name] = {
            **total_ms(reports),
            "stages_ms": {
                k: 1e3 * statistics.median(r["seconds"][k] for r in reports)
                for k in reports[0]["seconds"]
            },
            "decisions": sorted(
                {f"{c['decision']}: {c.get('reason', c.get('mode', ''))}" for c in hero}
            ),
            "levels": sorted({c["level"] for c in hero if "level" in c}),
            "branches": sorted({b for c in hero for b in c.get("branches", ())}),
        }
    full = rows["full, still camera"]["median_ms"]
    for row in rows.values():
        row["fraction_of_full"] = row["median_ms"] / full
    return {
        "size": size,
        "precision": precision,
        "prim_samples": prim_samples,
        "frames": frames,
        "rows": rows,
    }


def plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["rows"])
    medians = [result["rows"][n]["median_ms"] for n in names]
    lows = [m - result["rows"][n]["min_ms"] for n, m in zip(names, medians, strict=True)]
    highs = [result["rows"][n]["max_ms"] - m for n, m in zip(names, medians, strict=True)]
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.barh(names, medians, xerr=[lows, highs], color="C0", alpha=0.8)
    for y, n in enumerate(names):
        ax.annotate(
            f"{medians[y]:.1f} ms ({result['rows'][n]['fraction_of_full']:.0%})",
            (medians[y], y), xytext=(4, 4), textcoords="offset points", fontsize=8,
        )  # fmt: skip
    ax.invert_yaxis()
    ax.set_xlabel(
        f"ms per frame, median (min-max), {result['size']}x{result['size']}, {result['precision']}"
    )
    ax.set_title("What each skip costs (fraction of a full frame, still camera)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)

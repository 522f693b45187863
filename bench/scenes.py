"""Scenes the benchmarks render: the previs sample and overlays of it."""

from __future__ import annotations

import math
from pathlib import Path

from pxr import Gf, Usd, UsdGeom

from rigspace.sdk.stage import overlay_layer

ROOT = Path(__file__).resolve().parents[1]
PREVIS = ROOT / "samples" / "scenes" / "previs.usda"
SPACING = 60.0
"""Scene units (cm in previs) between heroes on the crowd's spiral: a golden-angle spiral
this tight keeps eight heroes in the shot camera's view over time codes 100-1400 (checked
with the engine's report: every hero drawn)."""
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def crowd_scene(folder: Path, characters: int) -> Path:
    """A layer over the previs scene with `characters` heroes in all (internal references
    of /World/Hero, sharing its model bundle), on a spiral around the first."""
    path = folder / f"crowd_{characters}.usda"
    layer = overlay_layer(path, PREVIS)
    stage = Usd.Stage.Open(layer)
    for k in range(1, characters):
        prim = stage.DefinePrim(f"/World/Hero{k}")
        prim.GetReferences().AddInternalReference("/World/Hero")
        radius, angle = SPACING * math.sqrt(k), GOLDEN_ANGLE * k
        offset = Gf.Vec3d(radius * math.cos(angle), 0.0, radius * math.sin(angle))
        UsdGeom.XformCommonAPI(prim).SetTranslate(offset)
    layer.Save()
    return path

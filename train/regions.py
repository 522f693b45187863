"""Regions of the character's surface that an evaluation measures apart: the face.

A film character's face is a small part of its image and the part people look at first; its
blend shapes move it in ways the joints do not. `blend_shape_region` finds the surface the
character's blend shapes move (every vertex any shape at full weight displaces) and keeps it
as masks in texture space, one per texture chart (sdk/charts.py). A captured sample says, per
pixel, which chart and which texture coordinates it shows (the maps' `uv` and `chart`), so the
region's pixels in any view are known exactly from the ground truth, with no second render.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.render import Maps

TEXELS = 512
"""Resolution of each chart's region mask over the region's uv box on that chart."""
MOVED = 1e-5
"""A vertex moves when a shape displaces it by more than this fraction of the character's size."""
SUBPIXEL_BITS = 4
"""cv2.fillPoly's fixed-point bits: the masks are drawn at 1/16 texel."""


class Region(Protocol):
    """A set of pixels an evaluation measures apart, found from the ground truth's maps."""

    @property
    def name(self) -> str: ...

    @property
    def description(self) -> str: ...

    def pixels(self, maps: Maps) -> np.ndarray | None: ...


@dataclass(frozen=True)
class WholeCharacter:
    """Every pixel the character covers (mask >= 0.5): the region the others compare with."""

    name: str = "character"
    description: str = "every pixel the character covers"

    def pixels(self, maps: Maps) -> np.ndarray | None:
        return maps.mask >= 0.5


@dataclass(frozen=True)
class SurfaceRegion:
    """Part of the character's surface, as a mask over texture coordinates per chart."""

    name: str
    description: str
    masks: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
    """chart -> (uv_min (2,), uv_max (2,), (TEXELS, TEXELS) bool over that box, row = v)."""

    def pixels(self, maps: Maps) -> np.ndarray | None:
        """(H,W) bool: the covered pixels (mask >= 0.5) that show this region, from the maps'
        uv and chart (None when the maps have no texture coordinates)."""
        if maps.uv is None or maps.chart is None:
            return None
        out = np.zeros(maps.chart.shape, bool)
        for chart, (lo, hi, mask) in self.masks.items():
            sel = maps.chart == chart
            if not sel.any():
                continue
            texel = (maps.uv[sel] - lo) / np.maximum(hi - lo, 1e-12) * TEXELS
            inside = np.all((texel >= 0) & (texel < TEXELS), axis=1)
            col = np.clip(texel[:, 0].astype(np.int64), 0, TEXELS - 1)
            row = np.clip(texel[:, 1].astype(np.int64), 0, TEXELS - 1)
            out[sel] = inside & mask[row, col]
        return out & (maps.mask >= 0.5)


def moved_vertices(rig: CharacterRig, time: float) -> list[np.ndarray]:
    """Per posed mesh (posed_meshes order), (N,) bool: the vertices some blend shape moves."""
    zero = np.zeros(len(rig.blend_shapes), np.float32)
    base = rig.posed_meshes(time, weights=zero)
    size = max(float(np.ptp(np.concatenate([m.points for m in base]), axis=0).max()), 1e-12)
    moved = [np.zeros(len(m.points), bool) for m in base]
    for k in range(len(rig.blend_shapes)):
        weights = zero.copy()
        weights[k] = 1.0
        for flags, rest, posed in zip(
            moved, base, rig.posed_meshes(time, weights=weights), strict=True
        ):
            flags |= np.linalg.norm(posed.points - rest.points, axis=1) > MOVED * size
    return moved


def blend_shape_region(rig: CharacterRig, time: float = 0.0) -> SurfaceRegion | None:
    """The surface the character's blend shapes move (its face, for a character whose shapes
    are facial), or None for a rig without blend shapes or without texture charts there."""
    if not rig.blend_shapes:
        return None
    meshes = rig.posed_meshes(time, charts=True)
    corners: dict[int, list[np.ndarray]] = {}
    for mesh, flags in zip(meshes, moved_vertices(rig, time), strict=True):
        if mesh.chart is None or mesh.corner_uv is None:
            continue
        face = flags[mesh.triangles].any(axis=1)
        for chart in np.unique(mesh.chart[face]):
            corners.setdefault(int(chart), []).append(mesh.corner_uv[face & (mesh.chart == chart)])
    masks = {}
    for chart, parts in corners.items():
        uv = np.concatenate(parts).astype(np.float64)  # (n, 3, 2)
        lo, hi = uv.reshape(-1, 2).min(axis=0), uv.reshape(-1, 2).max(axis=0)
        scale = (1 << SUBPIXEL_BITS) * TEXELS / np.maximum(hi - lo, 1e-12)
        points = np.rint((uv - lo) * scale).astype(np.int32)
        mask = np.zeros((TEXELS, TEXELS), np.uint8)
        for triangle in points:  # one by one: fillPoly would cancel overlapping ones (even-odd)
            cv2.fillConvexPoly(mask, triangle, 1, lineType=cv2.LINE_8, shift=SUBPIXEL_BITS)
        # Triangles far smaller than a texel can fall between texel centres: close the gaps.
        closed = cv2.dilate(mask, np.ones((3, 3), np.uint8)).astype(bool)
        masks[chart] = (lo.astype(np.float32), hi.astype(np.float32), closed)
    if not masks:
        return None
    return SurfaceRegion(
        "face",
        f"the surface the {len(rig.blend_shapes)} blend shapes move",
        masks,
    )


def dataset_regions(capture: dict, warn: Callable[[str], None] = print) -> list[Region]:
    """The regions to measure on a dataset (its capture.json settings): the whole character
    and, for a character with blend shapes, the surface they move; [] when the scene the
    dataset was captured from cannot be opened here (said through `warn`)."""
    from rigspace.sdk.stage import open_stage

    scene = Path(capture.get("scene", ""))
    if not scene.is_file():
        warn(f"the face region needs the captured scene, and {scene} is not here")
        return []
    stage = open_stage(scene)
    rig = CharacterRig(stage.GetPrimAtPath(capture["character"]))
    if not rig.blend_shapes:
        return []
    regions: list[Region] = [WholeCharacter()]
    face = blend_shape_region(rig)
    if face is None:
        warn(
            "the surface the blend shapes move is found through the texture charts, and "
            f"{capture['character']} has none there (no texture): measured as a whole only"
        )
    else:
        regions.append(face)
    return regions

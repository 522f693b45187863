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
            col, row, inside = _texels(maps.uv[sel], lo, hi, TEXELS)
            out[sel] = inside & mask[row, col]
        return out & (maps.mask >= 0.5)


def _texels(
    uv: np.ndarray, lo: np.ndarray, hi: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 2) uv points on a size x size grid over the box [lo, hi] (row = v): each one's
    column and row (clipped into the grid) and whether it lies inside the box."""
    texel = (uv - lo) / np.maximum(hi - lo, 1e-12) * size
    inside = np.all((texel >= 0) & (texel < size), axis=1)
    col = np.clip(texel[:, 0].astype(np.int64), 0, size - 1)
    row = np.clip(texel[:, 1].astype(np.int64), 0, size - 1)
    return col, row, inside


def shape_displacements(rig: CharacterRig, time: float) -> tuple[list[np.ndarray], float]:
    """Per posed mesh (posed_meshes order), (S, N): how far each of the S blend shapes at full
    weight moves each vertex (scene units, posed at `time`); and the character's size."""
    zero = np.zeros(len(rig.blend_shapes), np.float32)
    base = rig.posed_meshes(time, weights=zero)
    size = max(float(np.ptp(np.concatenate([m.points for m in base]), axis=0).max()), 1e-12)
    moved = [np.zeros((len(rig.blend_shapes), len(m.points))) for m in base]
    for k in range(len(rig.blend_shapes)):
        weights = zero.copy()
        weights[k] = 1.0
        for out, rest, posed in zip(
            moved, base, rig.posed_meshes(time, weights=weights), strict=True
        ):
            out[k] = np.linalg.norm(posed.points - rest.points, axis=1)
    return moved, size


def moved_vertices(rig: CharacterRig, time: float) -> list[np.ndarray]:
    """Per posed mesh (posed_meshes order), (N,) bool: the vertices some blend shape moves."""
    displacements, size = shape_displacements(rig, time)
    return [np.asarray((d > MOVED * size).any(axis=0)) for d in displacements]


MOBILITY_TEXELS = 128
"""Resolution of each chart's mobility over the chart's whole uv box."""


@dataclass(frozen=True)
class ShapeMobility:
    """Where the blend shapes move the surface, in texture space: per chart, a (T, T) grid over
    its uv box (row = v) of the mobility in [0, 1] (`shape_mobility`)."""

    grids: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
    """chart -> (uv_min (2,), uv_max (2,), (T, T) float32 over that box)."""

    def pixels(self, chart: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(H, W) float32 the mobility of the surface each pixel shows, from its (H, W) chart and
        (H, W, 2) uv maps; 0 where no chart or a chart the shapes do not move."""
        out = np.zeros(chart.shape, np.float32)
        for k, (lo, hi, grid) in self.grids.items():
            sel = chart == k
            if not sel.any():
                continue
            col, row, _ = _texels(uv[sel], lo, hi, grid.shape[0])
            out[sel] = grid[row, col]
        return out


def shape_mobility(
    rig: CharacterRig, center: np.ndarray, half: np.ndarray, time: float = 0.0
) -> ShapeMobility | None:
    """The mobility of the character's surface, per texture chart over its uv box (`center`
    and `half`: (K+1, 2), row k chart k's; a dataset's charts.json, train.data.chart_boxes,
    or CharacterRig.texture_charts().boxes()): each blend shape's displacement of a vertex
    over that shape's largest, the most of these over the shapes, and per triangle the most
    of its corners' (a blink's eyelid and an open jaw's chin both reach 1; the neck a shape
    never moves, 0). None for a rig without blend shapes, or when no shape moves a charted
    triangle."""
    if not rig.blend_shapes:
        return None
    displacements, size = shape_displacements(rig, time)
    largest = np.max([d.max(axis=1) for d in displacements], axis=0)  # (S,) over every mesh
    largest = np.where(largest > MOVED * size, largest, np.inf)  # a shape that moves nothing
    boxes = {k: (center[k] - half[k], center[k] + half[k]) for k in range(1, len(center))}
    grids: dict[int, np.ndarray] = {}
    for mesh, d in zip(rig.posed_meshes(time, charts=True), displacements, strict=True):
        if mesh.chart is None or mesh.corner_uv is None:
            continue
        vertex = (d / largest[:, None]).max(axis=0)  # (N,) in [0, 1]
        triangle = vertex[mesh.triangles].max(axis=1)
        order = np.argsort(triangle, kind="stable")  # the most mobile drawn last, on top
        for t in order[triangle[order] > 0]:
            chart = int(mesh.chart[t])
            if chart not in boxes:
                continue
            lo, hi = boxes[chart]
            grid = grids.setdefault(chart, np.zeros((MOBILITY_TEXELS, MOBILITY_TEXELS), np.float32))
            scale = (1 << SUBPIXEL_BITS) * MOBILITY_TEXELS / np.maximum(hi - lo, 1e-12)
            corners = np.rint((mesh.corner_uv[t] - lo) * scale).astype(np.int32)
            cv2.fillConvexPoly(grid, corners, float(triangle[t]), cv2.LINE_8, SUBPIXEL_BITS)
    if not grids:
        return None
    closed = {}  # triangles far smaller than a texel can fall between texel centres
    for k, grid in grids.items():
        lo, hi = boxes[k]
        wider = cv2.dilate(grid, np.ones((3, 3), np.uint8))  # a 3x3 maximum
        closed[k] = (lo.astype(np.float32), hi.astype(np.float32), wider)
    return ShapeMobility(closed)


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

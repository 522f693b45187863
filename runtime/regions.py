"""Regions drawn over the body (docs/regions.md, "Runtime"): whether a region adds detail this
frame, and its layer merged into its character's by depth before the lighting.

A region (the face, a hand) is drawn by a bundle of its own at its own billboard
(runtime/character.py, NeuralPart); its maps replace the body's where it is at or in front of
the body's surface, with a feathered edge where the body goes on beyond it (the neck under
the face, the wrist): there the two networks' pixels blend over a few frame pixels. Against
the background the region's own coverage is the edge, so the silhouette stays as sharp as the
region draws it. The merged layer is then lit, shadowed and composited as the body's is.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from rigspace.runtime.billboard import Billboard
from rigspace.runtime.character import COVERAGE_EPSILON, Layer

FEATHER_PX = 4.0
"""Frame pixels over which a region's weight falls from 1 to 0 towards a seam: a pixel the body
covers (at least SOLID) and the region does not draw. One pixel from the seam it is 0.16
(smoothstep of 1/4), from four pixels on 1."""
DEPTH_TOLERANCE = 0.02
"""A region's pixel is at or in front of the body's where its depth is at most the body's times
1 + this. The body's depth is the coarser one (the sample model's depth error is 1.23 % of the
character's height, about 2 cm, 0.7 % of the depth at 3 m): 2 % lets the face win over the
body's blurred head, while a hand 10 cm before the face at 3 m (3.3 %) keeps it."""
SOLID = 0.5
"""Body coverage from which a pixel the region does not draw is a seam (the body's anti-aliased
fringe beside the region's silhouette is not)."""


def region_skip(body: Billboard, body_level: int, region: Billboard, region_level: int) -> str:
    """Why a region is not evaluated this frame, "" when it is: its billboard cannot be drawn
    (off screen, behind the camera: the billboard's own reason), or it would add no detail:
    the body's network is not magnified on screen (its billboard's side is at most its level's
    resolution, so the body's pixels are already as fine as the screen's), or the region's
    level has no more pixels over its square than the body's level has there."""
    if not region.visible:
        return region.reason
    if body.size_px <= body_level:
        return (
            f"adds no detail: the body's level {body_level} covers its {body.size_px:.0f} px on "
            "screen (not magnified)"
        )
    beneath = body_level * region.size_px / body.size_px
    if region_level <= beneath:
        return (
            f"adds no detail: its level {region_level} is no finer than the body's "
            f"{beneath:.0f} network pixels across its square"
        )
    return ""


def region_weight(
    body: Layer, region: Layer, feather: float = FEATHER_PX, tolerance: float = DEPTH_TOLERANCE
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """(h, w) float32 the region's weight over its own rectangle, and the rectangle (x0, y0,
    x1, y1) holding both layers. The weight is 0 where the region loses: no coverage
    (COVERAGE_EPSILON), or its depth behind the body's by more than `tolerance` (relative).
    Where it wins it is 1 - (1 - f) * b, b the body's coverage (clipped to [0, 1]) and f the
    smoothstep of the distance to the nearest seam pixel over `feather` (1 without seams or
    feather): 1 where the body is empty, falling off towards a seam only where the body
    covers the pixel."""
    bh, bw = body.mask.shape
    rh, rw = region.mask.shape
    union = (
        min(body.x0, region.x0),
        min(body.y0, region.y0),
        max(body.x0 + bw, region.x0 + rw),
        max(body.y0 + bh, region.y0 + rh),
    )
    b_mask = _onto(body.mask, body, union, 0.0)
    ry, rx = region.y0 - union[1], region.x0 - union[0]
    inside = np.s_[ry : ry + rh, rx : rx + rw]
    b = np.clip(b_mask[inside], 0.0, 1.0)
    wins = region.mask > COVERAGE_EPSILON
    if body.depth is not None and region.depth is not None:
        b_depth = _onto(body.depth, body, union, np.inf)[inside]  # inf where the body is empty
        wins &= region.depth <= b_depth * np.float32(1.0 + tolerance)
    if not wins.any():
        return np.zeros((rh, rw), np.float32), union
    f = np.ones((rh, rw), np.float32)
    if feather > 0:
        # The seams within `feather` of the region's rectangle: solid body it does not draw
        # (outside its rectangle too, so a region cut by its square still blends there).
        m = math.ceil(feather) + 1
        wy0, wx0 = max(ry - m, 0), max(rx - m, 0)
        wy1, wx1 = min(ry + rh + m, union[3] - union[1]), min(rx + rw + m, union[2] - union[0])
        seam = b_mask[wy0:wy1, wx0:wx1] >= SOLID
        mine = np.s_[ry - wy0 : ry - wy0 + rh, rx - wx0 : rx - wx0 + rw]
        seam[mine] &= ~wins
        if seam.any():
            # Exact Euclidean distance of every pixel to the nearest seam pixel.
            distance = cv2.distanceTransform(
                (~seam).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
            )[mine]
            t = np.clip(distance / np.float32(feather), 0.0, 1.0)
            f = t * t * (3.0 - 2.0 * t)
    weight = np.where(wins, 1.0 - (1.0 - f) * b, 0.0).astype(np.float32)
    return weight, union


def merge_region(
    body: Layer, region: Layer, feather: float = FEATHER_PX, tolerance: float = DEPTH_TOLERANCE
) -> Layer:
    """The body's layer with a region's merged in, over the rectangle holding both: with w the
    region's weight (region_weight), coverage and premultiplied albedo are w * region + (1 -
    w) * body; normals the same blend renormalised; depth, uv and chart the winner's (the
    region's where w >= 1/2). Pixels where w is 0 keep the body's values exactly, and a
    region that wins no pixel returns `body` itself. The region has every map the body has
    (its branches include the body's); a map the body lacks stays absent."""
    if (body.albedo is None) != (region.albedo is None) or (
        body.depth is not None and (region.depth is None or region.normal is None)
    ):
        raise ValueError(
            f"a region's layer (branches {region.branches}) must have every map of the body's "
            f"(branches {body.branches})"
        )
    weight, union = region_weight(body, region, feather, tolerance)
    drawn = weight > 0
    if not drawn.any():
        return body
    rh, rw = region.mask.shape
    ry, rx = region.y0 - union[1], region.x0 - union[0]
    inside = np.s_[ry : ry + rh, rx : rx + rw]
    w = weight[..., None]
    wins = weight >= 0.5
    mask = _onto(body.mask, body, union, 0.0)
    under = mask[inside]
    np.copyto(under, weight * region.mask + (1.0 - weight) * under, where=drawn)
    albedo = depth = normal = None
    if body.albedo is not None and region.albedo is not None:
        albedo = _onto(body.albedo, body, union, 0.0)
        under = albedo[inside]  # premultiplied: blended as the coverage is
        np.copyto(under, w * region.albedo + (1.0 - w) * under, where=drawn[..., None])
    if body.depth is not None and region.depth is not None:
        depth = _onto(body.depth, body, union, np.inf)
        np.copyto(depth[inside], region.depth, where=wins)
    if body.normal is not None and region.normal is not None:
        normal = _onto(body.normal, body, union, 0.0)
        under = normal[inside]
        mixed = w * region.normal + (1.0 - w) * under
        length = np.linalg.norm(mixed, axis=-1, keepdims=True)
        mixed = np.where(length > COVERAGE_EPSILON, mixed / np.maximum(length, 1e-12), 0.0)
        np.copyto(under, mixed.astype(np.float32), where=drawn[..., None])
    uv = chart = None
    if body.uv is not None or region.uv is not None:
        uv = _onto(_or_zeros(body.uv, body, 2), body, union, 0.0)
        np.copyto(uv[inside], _or_zeros(region.uv, region, 2), where=wins[..., None])
    if body.chart is not None or region.chart is not None:
        chart = _onto(_or_zeros(body.chart, body, 0, np.int32), body, union, 0)
        np.copyto(chart[inside], _or_zeros(region.chart, region, 0, np.int32), where=wins)
    return Layer(
        union[0], union[1], albedo, mask, depth, normal, body.level, body.branches,
        dict(body.info), uv, chart,
    )  # fmt: skip


def _onto(array: np.ndarray, layer: Layer, union: tuple[int, int, int, int], fill) -> np.ndarray:
    """A copy of one of `layer`'s maps placed in the rectangle `union` (filled with `fill`)."""
    h, w = union[3] - union[1], union[2] - union[0]
    out = np.full((h, w, *array.shape[2:]), fill, array.dtype)
    y, x = layer.y0 - union[1], layer.x0 - union[0]
    out[y : y + array.shape[0], x : x + array.shape[1]] = array
    return out


def _or_zeros(array: np.ndarray | None, layer: Layer, channels: int, dtype=np.float32):
    """`array`, or zeros of a layer's size (`channels` 0: one plane) where it has none."""
    if array is not None:
        return array
    shape = layer.mask.shape if channels == 0 else (*layer.mask.shape, channels)
    return np.zeros(shape, dtype)

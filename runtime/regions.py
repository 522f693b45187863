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
import numba as nb
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
    own = (region.x0, region.y0, region.x0 + rw, region.y0 + rh)
    b = np.clip(_window(body.mask, body, own, 0.0), 0.0, 1.0)
    wins = region.mask > COVERAGE_EPSILON
    if body.depth is not None and region.depth is not None:
        b_depth = _window(body.depth, body, own, np.inf)  # inf where the body is empty
        wins &= region.depth <= b_depth * np.float32(1.0 + tolerance)
    if not wins.any():
        return np.zeros((rh, rw), np.float32), union
    f = np.ones((rh, rw), np.float32)
    if feather > 0:
        # The seams within `feather` of the region's rectangle: solid body it does not draw
        # (outside its rectangle too, so a region cut by its square still blends there).
        m = math.ceil(feather) + 1
        around = (
            max(own[0] - m, union[0]),
            max(own[1] - m, union[1]),
            min(own[2] + m, union[2]),
            min(own[3] + m, union[3]),
        )
        seam = _window(body.mask, body, around, 0.0) >= SOLID
        mine = np.s_[
            own[1] - around[1] : own[3] - around[1], own[0] - around[0] : own[2] - around[0]
        ]
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
    body: Layer,
    region: Layer,
    feather: float = FEATHER_PX,
    tolerance: float = DEPTH_TOLERANCE,
    kernel: bool = True,
) -> Layer:
    """The body's layer with a region's merged in, over the rectangle holding both: the region
    goes over the body with alpha k = w r (w its weight, region_weight; r its coverage), so
    premultiplied albedo is w A_r + (1 - k) A_b and coverage k + (1 - k) b (the body stays
    solid under the region's soft edge, and w = r = 1 replaces it); normals are k n_r + (1 -
    k) b n_b renormalised; depth, uv and chart the winner's: the region's where its share k is
    at least the body's (1 - k) b. Pixels where w is 0 keep the body's values exactly, and a
    region that wins no pixel returns `body` itself. The region has every map the body has
    (its branches include the body's); a map the body lacks stays absent. The blend is one
    compiled pass over the region's rectangle (`kernel` False: numpy, `_blend_reference`,
    which the pass is tested against)."""
    return merge_regions(body, [region], feather, tolerance, kernel)


def merge_regions(
    body: Layer,
    regions: list[Layer],
    feather: float = FEATHER_PX,
    tolerance: float = DEPTH_TOLERANCE,
    kernel: bool = True,
) -> Layer:
    """The body's layer with `regions` merged in, in order: each as merge_region merges it
    into the layer the ones before it made (a hand drawn after the face is depth-tested
    against the face), over the rectangle holding the body and all of them. The body's maps
    are copied into that rectangle once, when the first region wins a pixel (the frame merges
    its three regions with one copy, not three); `body` itself when none wins any."""
    for region in regions:
        if (body.albedo is None) != (region.albedo is None) or (
            body.depth is not None and (region.depth is None or region.normal is None)
        ):
            raise ValueError(
                f"a region's layer (branches {region.branches}) must have every map of the "
                f"body's (branches {body.branches})"
            )
    out: Layer | None = None
    for region in regions:
        # Against the layer so far: where `out` reaches beyond it, it holds the fills that
        # _window gives outside a layer (no coverage, infinite depth), so the weight is the
        # one merge_region would find against the smaller merged layer.
        weight, _ = region_weight(body if out is None else out, region, feather, tolerance)
        if not np.any(weight > 0):
            continue
        if out is None:
            out = _copied_over(body, regions)
        if kernel:
            _blend(out, region, weight)
        else:
            _blend_reference(out, region, weight)
    return body if out is None else out


def _copied_over(body: Layer, regions: list[Layer]) -> Layer:
    """The body's maps copied into the rectangle holding it and `regions` (its cached layer
    stays as it is), a uv and chart map (zeros) where a region has one and the body not."""
    union = (
        min(body.x0, *(r.x0 for r in regions)),
        min(body.y0, *(r.y0 for r in regions)),
        max(body.x0 + body.mask.shape[1], *(r.x0 + r.mask.shape[1] for r in regions)),
        max(body.y0 + body.mask.shape[0], *(r.y0 + r.mask.shape[0] for r in regions)),
    )
    uv = body.uv is not None or any(r.uv is not None for r in regions)
    chart = body.chart is not None or any(r.chart is not None for r in regions)
    return Layer(
        union[0], union[1],
        None if body.albedo is None else _onto(body.albedo, body, union, 0.0),
        _onto(body.mask, body, union, 0.0),
        None if body.depth is None else _onto(body.depth, body, union, np.inf),
        None if body.normal is None else _onto(body.normal, body, union, 0.0),
        body.level, body.branches, dict(body.info),
        _onto(_or_zeros(body.uv, body, 2), body, union, 0.0) if uv else None,
        _onto(_or_zeros(body.chart, body, 0, np.int32), body, union, 0) if chart else None,
    )  # fmt: skip


def _blend_reference(out: Layer, region: Layer, weight: np.ndarray) -> None:
    """merge_region's blend in numpy, in place in `out` (the body's maps over the union):
    only the pixels the region draws (weight > 0) change."""
    rh, rw = region.mask.shape
    oy, ox = region.y0 - out.y0, region.x0 - out.x0
    inside = np.s_[oy : oy + rh, ox : ox + rw]
    one = np.float32(1.0)
    drawn = weight > 0
    w = weight[drawn]
    b = out.mask[inside][drawn]  # the body's coverage
    k = w * region.mask[drawn]  # the region's alpha over it
    wins = np.zeros(weight.shape, bool)  # the region's share of the coverage >= the body's
    wins[drawn] = k >= (one - k) * b
    out.mask[inside][drawn] = k + (one - k) * b
    if out.albedo is not None and region.albedo is not None:
        under = out.albedo[inside]  # premultiplied: the region over the body
        under[drawn] = w[:, None] * region.albedo[drawn] + (one - k)[:, None] * under[drawn]
    if out.depth is not None and region.depth is not None:
        out.depth[inside][wins] = region.depth[wins]
    if out.normal is not None and region.normal is not None:
        under = out.normal[inside]
        n = k[:, None] * region.normal[drawn] + ((one - k) * b)[:, None] * under[drawn]
        length = np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
        under[drawn] = np.where(length > COVERAGE_EPSILON, n / np.maximum(length, 1e-12), 0.0)
    if out.uv is not None:
        out.uv[inside][wins] = _or_zeros(region.uv, region, 2)[wins]
    if out.chart is not None:
        out.chart[inside][wins] = _or_zeros(region.chart, region, 0, np.int32)[wins]


_NONE_2 = np.zeros((0, 0), np.float32)
_NONE_3 = np.zeros((0, 0, 3), np.float32)
_NONE_UV = np.zeros((0, 0, 2), np.float32)
_NONE_CHART = np.zeros((0, 0), np.int32)


def _blend(out: Layer, region: Layer, weight: np.ndarray) -> None:
    """_blend_reference's result by the compiled pass (blend_pass)."""
    albedo = out.albedo is not None and region.albedo is not None
    geometry = out.depth is not None and out.normal is not None
    blend_pass(
        weight, region.y0 - out.y0, region.x0 - out.x0,
        np.ascontiguousarray(region.mask, np.float32),
        np.ascontiguousarray(region.albedo, np.float32) if albedo else _NONE_3,
        np.ascontiguousarray(region.depth, np.float32) if geometry else _NONE_2,
        np.ascontiguousarray(region.normal, np.float32) if geometry else _NONE_3,
        np.ascontiguousarray(region.uv, np.float32) if region.uv is not None else _NONE_UV,
        np.ascontiguousarray(region.chart, np.int32) if region.chart is not None else _NONE_CHART,
        out.mask, out.albedo if albedo else _NONE_3, out.depth if geometry else _NONE_2,
        out.normal if geometry else _NONE_3, _NONE_UV if out.uv is None else out.uv,
        _NONE_CHART if out.chart is None else out.chart,
        albedo, geometry, COVERAGE_EPSILON,
    )  # fmt: skip


@nb.njit(cache=True, nogil=True)
def blend_pass(
    weight, oy, ox, r_mask, r_albedo, r_depth, r_normal, r_uv, r_chart,
    mask, albedo, depth, normal, uv, chart, with_albedo, with_geometry, epsilon,
):  # fmt: skip
    """Blend a region's maps (r_*) into the body's over the union (in place), the region's
    top-left at (oy, ox) there, the region over the body with alpha weight * r_mask:
    _blend_reference one pixel at a time, in one pass over the region's rectangle. A zero-sized r_uv or r_chart reads as zeros; a zero-sized uv or chart
    (the union has none) is left alone."""
    h, w = weight.shape
    one = np.float32(1.0)
    has_uv, has_chart = uv.shape[0] > 0, chart.shape[0] > 0
    r_has_uv, r_has_chart = r_uv.shape[0] > 0, r_chart.shape[0] > 0
    for i in range(h):
        y = oy + i
        for j in range(w):
            k = weight[i, j]  # w
            if not k > 0:
                continue
            x = ox + j
            b = mask[y, x]
            a = k * r_mask[i, j]  # the region's alpha over the body
            mask[y, x] = a + (one - a) * b
            if with_albedo:
                for c in range(3):
                    albedo[y, x, c] = k * r_albedo[i, j, c] + (one - a) * albedo[y, x, c]
            wins = a >= (one - a) * b
            if with_geometry:
                under = (one - a) * b
                n0 = a * r_normal[i, j, 0] + under * normal[y, x, 0]
                n1 = a * r_normal[i, j, 1] + under * normal[y, x, 1]
                n2 = a * r_normal[i, j, 2] + under * normal[y, x, 2]
                length = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
                scale = one / length if length > epsilon else np.float32(0.0)
                normal[y, x, 0] = n0 * scale
                normal[y, x, 1] = n1 * scale
                normal[y, x, 2] = n2 * scale
                if wins:
                    depth[y, x] = r_depth[i, j]
            if wins and has_uv:
                for c in range(2):
                    uv[y, x, c] = r_uv[i, j, c] if r_has_uv else 0.0
            if wins and has_chart:
                chart[y, x] = r_chart[i, j] if r_has_chart else 0


def _window(array: np.ndarray, layer: Layer, rect: tuple[int, int, int, int], fill) -> np.ndarray:
    """One of `layer`'s maps over the frame rectangle `rect` (x0, y0, x1, y1), `fill` where
    the layer does not reach."""
    x0, y0, x1, y1 = rect
    h, w = array.shape[:2]
    out = np.full((y1 - y0, x1 - x0, *array.shape[2:]), fill, array.dtype)
    ly0, lx0 = max(layer.y0, y0), max(layer.x0, x0)
    ly1, lx1 = min(layer.y0 + h, y1), min(layer.x0 + w, x1)
    if ly1 > ly0 and lx1 > lx0:
        out[ly0 - y0 : ly1 - y0, lx0 - x0 : lx1 - x0] = array[
            ly0 - layer.y0 : ly1 - layer.y0, lx0 - layer.x0 : lx1 - layer.x0
        ]
    return out


def _onto(array: np.ndarray, layer: Layer, union: tuple[int, int, int, int], fill) -> np.ndarray:
    """A copy of one of `layer`'s maps placed in the rectangle `union` (filled with `fill`),
    which holds it."""
    h, w = array.shape[:2]
    if (layer.x0, layer.y0, layer.x0 + w, layer.y0 + h) == union:
        return array.copy()
    return _window(array, layer, union, fill)


def _or_zeros(array: np.ndarray | None, layer: Layer, channels: int, dtype=np.float32):
    """`array`, or zeros of a layer's size (`channels` 0: one plane) where it has none."""
    if array is not None:
        return array
    shape = layer.mask.shape if channels == 0 else (*layer.mask.shape, channels)
    return np.zeros(shape, dtype)

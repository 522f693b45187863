"""The prims' and a character layer's shadow passes in numpy: the reference of passes.py's kernels.

Each pass finds, per light, the (H, W) shadow factor of the prims' G-buffer (or of a layer) from
the prims' shadow maps and the characters' capsules, coarse to fine (sparse_visibility) in the
window of the screen regions their shadows can fall on. The arithmetic is this package's
(ShadowMap.visibility, capsule_visibility), called back for every grid of every pass: the
compiled passes run the same in one kernel call per pass (passes.py, within KERNEL_TOLERANCE of
these in tests/runtime/test_shadows.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rigspace.runtime.character import Layer
from rigspace.runtime.lights import DISTANT, POINT, Light
from rigspace.runtime.shadows import PosedCapsules, PrimShadows, region_mask, sparse_visibility
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import Maps


def prim_shadows(
    shadows: PrimShadows, prims: Maps, camera: Camera, lights: list[Light], box: np.ndarray,
    casters, maps: bool,
) -> tuple[list[np.ndarray | None], list[np.ndarray | None]]:  # fmt: skip
    """Per light, the prims' (H, W) shadow factor from the shadow maps (with `maps`) and from
    the characters' capsules (`casters`: (path, PosedCapsules); None: none can fall), each found
    in the window of its own screen regions within `box`, the prims' bounds. (One pass for
    both, on the union of their windows, measured slower: the capsules' small window grew to
    the maps' and more pixels were evaluated.)"""
    passes: dict[tuple[int, str], list[tuple[int, list, Any]]] = {}  # per light and kind
    for index, light in enumerate(lights):
        if light.kind not in (DISTANT, POINT):
            continue
        if maps:
            for rects, handle in shadows.regions(index, box, camera):
                passes.setdefault((index, "map"), []).append((index, rects, handle))
        for posed, rects in _capsule_regions(shadows, casters, light, box, camera):
            passes.setdefault((index, "capsules"), []).append((index, rects, posed))
    mapped: list[np.ndarray | None] = [None] * len(lights)
    hidden: list[np.ndarray | None] = [None] * len(lights)
    for (index, kind), jobs in passes.items():
        factor = _prim_pass(shadows, prims, camera, lights, jobs)
        (mapped if kind == "map" else hidden)[index] = factor
    return mapped, hidden


def _capsule_regions(shadows: PrimShadows, casters, light: Light, box, camera: Camera):
    """Per caster, its capsules and the regions its limbs' shadows can fall on (a limb's
    region is much smaller than the whole body's)."""
    found = []
    for _, posed in casters:
        spheres = [part.bounds() for part in posed.parts()]
        centres = np.array([c for c, _ in spheres])
        reach = np.array([r for _, r in spheres])[:, None]
        rects = shadows.shadow_regions(centres - reach, centres + reach, light, box, camera)
        rects = [r for r in rects if r is not None]
        if rects:
            found.append((posed, rects))
    return found


def _prim_pass(shadows: PrimShadows, prims: Maps, camera: Camera, lights, jobs) -> np.ndarray:
    """One pass (a light's maps, or its casters' capsules) over the window of its regions."""
    window = _window([r for _, rects, _ in jobs for r in rects])
    covered = prims.mask[window] > 0
    areas = [covered & region_mask(rects, camera, window) for _, rects, _ in jobs]

    def evaluate(pixels: np.ndarray) -> np.ndarray:
        frame = _in_frame(pixels, window, camera)
        rows, cols = np.divmod(frame, camera.width)
        points, normals = world_points(
            prims.depth.reshape(-1)[frame], rows, cols, prims.normal.reshape(-1, 3)[frame],
            camera, (0, 0),
        )  # fmt: skip
        v = np.ones(pixels.size, np.float32)
        for area, (index, _, what) in zip(areas, jobs, strict=True):
            inside = np.flatnonzero(area.reshape(-1)[pixels])
            if isinstance(what, PosedCapsules):
                seen = shadows.capsule_visibility(points[:, inside], what, lights[index])
            else:
                seen = shadows.lookup(what, points[:, inside], normals[:, inside])
            v[inside] *= seen
        return v

    full = np.ones((camera.height, camera.width), np.float32)
    candidates = np.logical_or.reduce(areas)
    full[window] = sparse_visibility(candidates, evaluate, prims.depth[window])
    return full


def layer_visibility(
    shadows: PrimShadows, layer: Layer, camera: Camera, lights: list[Light], box: np.ndarray,
    others,
) -> list[np.ndarray | None]:  # fmt: skip
    """Per light, a character layer's (h, w) shadow factor from the maps whose regions reach
    it and from the other characters' capsules (its own would shadow its own surface), at
    every covered pixel (None: nothing can shadow it)."""
    assert layer.depth is not None and layer.normal is not None
    h, w = layer.mask.shape
    covered = np.flatnonzero(layer.mask > 0)
    rows, cols = np.divmod(covered, w)
    points, normals = world_points(
        layer.depth.reshape(-1)[covered], rows, cols, layer.normal.reshape(-1, 3)[covered],
        camera, (layer.x0, layer.y0),
    )  # fmt: skip
    out: list[np.ndarray | None] = []
    for index, light in enumerate(lights):
        v = None
        for rects, handle in shadows.regions(index, box, camera):
            # Only the maps whose shadows can reach the layer's rectangle.
            if any(_overlaps(_rect(r), (layer.x0, layer.y0, w, h)) for r in rects):
                seen = shadows.lookup(handle, points, normals)
                v = seen if v is None else v * seen
        if light.kind in (DISTANT, POINT):
            for _, posed in others:
                seen = shadows.capsule_visibility(points, posed, light)
                v = seen if v is None else v * seen
        if v is None:
            out.append(None)
            continue
        full = np.ones(h * w, np.float32)
        full[covered] = v
        out.append(full.reshape(h, w))
    return out


def world_points(depth, rows, cols, normal, camera: Camera, origin):
    """Planar (3, N) float32 world positions and normals of pixels (rows, cols) of a region
    at `origin`, from their camera-space depth and (N, 3) normals."""
    d = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    x = (cols.astype(np.float32) + np.float32(origin[0] + 0.5 - camera.cx)) * (d / camera.fx)
    y = (np.float32(camera.cy - origin[1] - 0.5) - rows.astype(np.float32)) * (d / camera.fy)
    z = -d
    m = camera.camera_to_world.astype(np.float32)
    n = np.ascontiguousarray(normal.T, dtype=np.float32)
    points = np.stack([m[i, 0] * x + m[i, 1] * y + m[i, 2] * z + m[i, 3] for i in range(3)])
    normals = np.stack([m[i, 0] * n[0] + m[i, 1] * n[1] + m[i, 2] * n[2] for i in range(3)])
    return points, normals


def _window(regions: list[tuple[int, int, int, int]]) -> tuple[slice, slice]:
    """The frame rows and columns holding every region (x0, y0, x1, y1)."""
    return (
        slice(min(r[1] for r in regions), max(r[3] for r in regions)),
        slice(min(r[0] for r in regions), max(r[2] for r in regions)),
    )


def _in_frame(pixels: np.ndarray, window: tuple[slice, slice], camera: Camera) -> np.ndarray:
    """Flat indices of a window's pixels as flat indices of the frame."""
    rows, cols = np.divmod(pixels, window[1].stop - window[1].start)
    return (rows + window[0].start) * camera.width + cols + window[1].start


def _rect(region: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) as (x0, y0, w, h)."""
    return region[0], region[1], region[2] - region[0], region[3] - region[1]


def _overlaps(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]

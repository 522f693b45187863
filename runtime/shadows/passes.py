"""The prims' shadow passes through the compiled kernels (kernels.py): one call per light and kind.

The engine's numpy passes (Engine._prim_shadows) call back into Python for every grid of
every pass; here each (light, maps or capsules) pass is one kernel call over its window,
with the maps' depth and the capsules' 2-D view handed over as arrays. The result is the
numpy passes' within float rounding (tests/runtime/test_shadows.py holds the tolerance);
`python -m rigspace.apps.shadow_timing` measures both.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rigspace.runtime import shadows as sh
from rigspace.runtime.lights import DISTANT, POINT, Light
from rigspace.runtime.shadows import kernels as kernels
from rigspace.sdk.camera import Camera

CONSTANTS = np.array(
    [sh.NORMAL_OFFSET_TEXELS, sh.DEPTH_BIAS_TEXELS, sh.MIN_VISIBILITY, sh.BEND_TOLERANCE,
     sh.SURFACE_TOLERANCE],
    dtype=np.float64,
)  # fmt: skip
_NO_MAPS = (np.zeros((0, kernels.MAP_FIELDS)), np.zeros(1, np.float32), np.zeros(1, np.float32))
_NO_SETS = (
    np.zeros((0, kernels.SET_FIELDS)), *(np.zeros((0, 3)),) * 2, np.zeros(0),
    *(np.zeros((0, 2)),) * 2, np.zeros(0), np.zeros((0, 7)),
)  # fmt: skip


def map_row(shadow_map: sh.ShadowMap, start: int, buffer: int) -> np.ndarray:
    """A map's MAP_FIELDS row, its padded depth starting at `start` in flat buffer `buffer`."""
    base = shadow_map.__dict__.get("_row")  # kept with the map: the still one lasts
    if base is None:
        cam = shadow_map.camera
        base = np.empty(kernels.MAP_FIELDS)
        base[:12] = cam.world_to_camera[:3].ravel()
        height, width = shadow_map.depth.shape
        base[12:19] = (cam.fx, cam.fy, cam.cx, cam.cy, cam.near, width + 2, height + 2)
        shadow_map.__dict__["_row"] = base
    row = base.copy()
    row[19:] = (start, buffer)
    return row


def maps_data(found: Sequence[sh.ShadowMap]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The maps' rows and two flat buffers of their padded depth: the largest map's own
    (no copy: the still prims' 512x512 map is most of the bytes), the others concatenated."""
    if not found:
        return _NO_MAPS
    largest = max(range(len(found)), key=lambda i: found[i].depth.size)
    rows, flats, start = [], [], 0
    for i, shadow_map in enumerate(found):
        if i == largest:
            rows.append(map_row(shadow_map, 0, 0))
            continue
        flat = shadow_map.padded.reshape(-1)
        rows.append(map_row(shadow_map, start, 1))
        flats.append(flat)
        start += flat.size
    rest = np.concatenate(flats) if flats else _NO_MAPS[2]
    return np.stack(rows), found[largest].padded.reshape(-1), rest


def capsule_set(light: Light, capsules: sh.PosedCapsules, first: int) -> np.ndarray:
    """A capsule set's SET_FIELDS row under `light` (shadows._light_plane's constants), its
    capsules at `first` onwards in the kernel's arrays; a point light's nearest capsule,
    off-axis angle and the 2-D bounds are kernels.capsule_arrays'."""
    row = np.zeros(kernels.SET_FIELDS)
    count = len(capsules.radius)
    row[21], row[22] = first, first + count
    centre, reach = capsules.bounds()
    if light.kind == DISTANT:
        w = light.direction
        e1, e2 = sh._frame_axes(w)
        row[0] = kernels.MODE_DISTANT
        row[1:10] = np.stack([e1, e2, w]).ravel()
        row[13] = float(centre @ w - reach)
        row[14] = math.tan(max(light.angle, sh.MIN_SOFTNESS))
        row[23] = max(light.angle, sh.MIN_SOFTNESS)
        row[26], row[27] = math.cos(row[23]), math.sin(row[23])
        return row
    soft = sh._soft_radius(light, capsules)
    row[10:13] = light.position
    row[14] = soft
    offset = centre - light.position
    distance = float(np.linalg.norm(offset))
    if distance <= reach * 1.05:  # the light among the capsules: every pair
        row[0] = kernels.MODE_EVERY
        return row
    w = offset / distance
    e1, e2 = sh._frame_axes(w)
    row[0] = kernels.MODE_POINT
    row[1:10] = np.stack([e1, e2, w]).ravel()
    return row


def sets_data(light: Light, sets: Sequence[sh.PosedCapsules]):
    """The capsule sets' rows and their capsules (world ends and radii, 2-D ends and radii)
    and limbs (the sets' chains where they are runs of capsules, else one per set)."""
    if not sets:
        return _NO_SETS
    rows, a2s, b2s, r2s, first, limbs, limb_count = [], [], [], [], 0, [], 0
    a, b, radius = (
        np.concatenate([getattr(c, name) for c in sets]).astype(np.float64)
        for name in ("a", "b", "radius")
    )
    position = light.position.astype(np.float64)
    for capsules in sets:
        count = len(capsules.radius)
        row = capsule_set(light, capsules, first)
        runs = _runs(capsules)
        limb = np.empty((len(runs), 7))
        # The 2-D view, bounds and limbs in one compiled call: numpy's dozens of small
        # calls per set measured about 0.25 ms.
        at = slice(first, first + count)
        flats = kernels.capsule_arrays(row, a[at], b[at], radius[at], position, runs, first, limb)
        row[24], row[25] = limb_count, limb_count + len(runs)
        limb_count += len(runs)
        limbs.append(limb)
        first += count
        rows.append(row)
        a2s.append(flats[0])
        b2s.append(flats[1])
        r2s.append(flats[2])
    if len(sets) == 1:  # the usual case: one character
        return rows[0][None], a, b, radius, a2s[0], b2s[0], r2s[0], limbs[0]
    return (
        np.stack(rows), a, b, radius, np.concatenate(a2s), np.concatenate(b2s),
        np.concatenate(r2s), np.concatenate(limbs),
    )  # fmt: skip


_RUNS: dict[int, tuple[object, np.ndarray]] = {}
"""_runs per chains tuple (a character's, the same object every frame), kept with it."""


def _runs(capsules: sh.PosedCapsules) -> np.ndarray:
    """(R, 2) the capsules' chains as (start, stop) runs when they are consecutive runs
    covering every capsule once (as shadows.chains makes them), else one run of all."""
    count = len(capsules.radius)
    cached = _RUNS.get(id(capsules.chains))
    if cached is not None and cached[0] is capsules.chains and cached[1][-1:, 1].sum() == count:
        return cached[1]
    runs: list[tuple[int, int]] = []
    at = 0
    for chain in capsules.chains:
        if len(chain) == 0 or chain[0] != at or np.any(np.diff(chain) != 1):
            runs, at = [], -1
            break
        runs.append((at, at + len(chain)))
        at += len(chain)
    if at != count:
        runs = [(0, count)] if count else []
    found = np.array(runs, dtype=np.int64).reshape(-1, 2)
    if len(_RUNS) > 64:  # characters come and go: keep it small
        _RUNS.clear()
    _RUNS[id(capsules.chains)] = (capsules.chains, found)
    return found


def shadow_regions(
    lo: np.ndarray, hi: np.ndarray, light: Light, box: np.ndarray, camera: Camera
) -> list[sh.Region | None]:
    """shadows.shadow_regions through its kernel."""
    if light.kind == DISTANT:
        packed = (0.0, *light.direction, 0.0, 0.0, 0.0, max(light.angle, sh.MIN_SOFTNESS), 0.0)
    else:
        packed = (1.0, 0.0, 0.0, 0.0, *light.position, 0.0, light.radius)
    found = kernels.shadow_regions(
        np.ascontiguousarray(lo, np.float64), np.ascontiguousarray(hi, np.float64),
        np.array([*packed, sh.MIN_SOFTNESS]), np.ascontiguousarray(box, np.float64),
        _view(camera), camera.width, camera.height,
    )  # fmt: skip
    full: sh.Region = (0, 0, camera.width, camera.height)
    return [
        None if row[0] == 0 else full if row[0] == 2 else (row[1], row[2], row[3], row[4])
        for row in found.tolist()
    ]


_VIEW: list = [None, None]
"""The last camera and its view row (asked a few times per light and frame)."""


def _view(camera: Camera) -> np.ndarray:
    """The kernels' view row of a camera: world-to-camera rows 0-2, fx, fy, cx, cy, near."""
    if _VIEW[0] is not camera:
        w2c = camera.world_to_camera
        view = (*w2c[:3].ravel(), camera.fx, camera.fy, camera.cx, camera.cy, camera.near)
        _VIEW[:] = camera, np.array(view, np.float64)
    return _VIEW[1]


def points_visibility(
    points: np.ndarray, normals: np.ndarray | None, light: Light | None = None,
    capsules: sh.PosedCapsules | None = None, shadow_map: sh.ShadowMap | None = None,
) -> np.ndarray:  # fmt: skip
    """(N,) visibility of planar (3, N) points past one map or one capsule set, compiled."""
    p = np.ascontiguousarray(points, dtype=np.float32)
    n = (
        np.zeros((3, 0), np.float32)
        if normals is None
        else np.ascontiguousarray(normals, np.float32)
    )
    if shadow_map is not None:
        return kernels.points_visibility(
            p, n, kernels.KIND_MAP, *maps_data([shadow_map]), *_NO_SETS, CONSTANTS
        )
    assert light is not None and capsules is not None
    return kernels.points_visibility(
        p, n, kernels.KIND_CAPSULES, *_NO_MAPS, *sets_data(light, [capsules]), CONSTANTS
    )


def _frame(camera: Camera) -> np.ndarray:
    """The kernels' frame row: camera-to-world rows 0-2, fx, fy, cx, cy, then the window's
    and the G-buffer's first pixel (row, column) in the frame, set per pass."""
    frame = np.zeros(20)
    frame[:12] = camera.camera_to_world[:3].ravel()
    frame[12:16] = (camera.fx, camera.fy, camera.cx, camera.cy)
    return frame


def _gbuffer(maps) -> tuple[np.ndarray, ...]:
    """Mask, depth and normal as C-contiguous float32 always: one compiled signature (a new
    layout would compile anew)."""
    return tuple(
        np.ascontiguousarray(m, dtype=np.float32) for m in (maps.mask, maps.depth, maps.normal)
    )


def _capsule_jobs(light: Light, limbs, box: np.ndarray, camera: Camera) -> list[tuple]:
    """Per caster, the regions its limbs' shadows can fall on (a limb's region is much
    smaller than the whole body's), with its capsules."""
    jobs = []
    for posed, spheres in limbs:
        centres = np.array([c for c, _ in spheres])
        reach = np.array([r for _, r in spheres])[:, None]
        found = shadow_regions(centres - reach, centres + reach, light, box, camera)
        rects = [r for r in found if r is not None]
        if rects:
            jobs.append((rects, posed))
    return jobs


def prim_shadows(
    shadows: sh.PrimShadows, prims, camera: Camera, lights: list[Light], box: np.ndarray,
    casters, maps: bool, step: int | None = None,
) -> tuple[list[np.ndarray | None], list[np.ndarray | None]]:  # fmt: skip
    """Engine._prim_shadows through the kernels: per light, the prims' (H, W) shadow factor
    from the maps (with `maps`) and from the characters' capsules (None: none falls), each
    pass one kernel call over the window of its screen regions. `step` 1: every candidate
    pixel evaluated (the reference for the blend); None: SPARSE_STEP."""
    step = sh.SPARSE_STEP if step is None else step
    mapped: list[np.ndarray | None] = [None] * len(lights)
    hidden: list[np.ndarray | None] = [None] * len(lights)
    frame, gbuffer = _frame(camera), _gbuffer(prims)
    area = (0, 0, camera.width, camera.height)
    limbs = [(posed, [part.bounds() for part in posed.parts()]) for _, posed in casters]
    for index, light in enumerate(lights):
        if light.kind not in (DISTANT, POINT):
            continue
        if maps:
            jobs = []
            for rects, handle in shadows.regions(index, box, camera):
                shadow_map = shadows.shadow_map(handle)
                if shadow_map is not None:
                    jobs.append((rects, shadow_map))
            if jobs:
                data = (kernels.KIND_MAP, *maps_data([m for _, m in jobs]), *_NO_SETS)
                mapped[index] = _pass(jobs, data, gbuffer, frame, area, step)
        jobs = _capsule_jobs(light, limbs, box, camera)
        if jobs:
            data = (kernels.KIND_CAPSULES, *_NO_MAPS, *sets_data(light, [c for _, c in jobs]))
            hidden[index] = _pass(jobs, data, gbuffer, frame, area, step)
    return mapped, hidden


def layer_visibility(
    shadows: sh.PrimShadows, layer, camera: Camera, lights: list[Light], box: np.ndarray,
    others, step: int | None = None,
) -> list[np.ndarray | None]:  # fmt: skip
    """Engine._layer_visibility through the kernels: per light, a character layer's (h, w)
    shadow factor from the maps whose regions reach it and from the other characters'
    capsules, coarse to fine over its pixels as the prims' (its depth tells its silhouette
    and creases; None: nothing can shadow it)."""
    step = sh.SPARSE_STEP if step is None else step
    h, w = layer.mask.shape
    area = (layer.x0, layer.y0, w, h)
    frame, gbuffer = _frame(camera), _gbuffer(layer)
    limbs = [(posed, [part.bounds() for part in posed.parts()]) for _, posed in others]
    out: list[np.ndarray | None] = []
    for index, light in enumerate(lights):
        factor = None
        jobs = []
        for rects, handle in shadows.regions(index, box, camera):
            mine = [r for r in rects if _clip(r, area) is not None]
            shadow_map = shadows.shadow_map(handle) if mine else None
            if shadow_map is not None:
                jobs.append((mine, shadow_map))
        if jobs:
            data = (kernels.KIND_MAP, *maps_data([m for _, m in jobs]), *_NO_SETS)
            factor = _pass(jobs, data, gbuffer, frame, area, step)
        if light.kind in (DISTANT, POINT):
            jobs = [
                (mine, posed)
                for rects, posed in _capsule_jobs(light, limbs, box, camera)
                if (mine := [r for r in rects if _clip(r, area) is not None])
            ]
            if jobs:
                data = (kernels.KIND_CAPSULES, *_NO_MAPS, *sets_data(light, [c for _, c in jobs]))
                seen = _pass(jobs, data, gbuffer, frame, area, step)
                factor = seen if factor is None else factor * seen
        out.append(factor)
    return out


def _clip(rect, area) -> tuple[int, int, int, int] | None:
    """A region (x0, y0, x1, y1) within an area (x, y, w, h) of the frame, or None."""
    x0, y0 = max(rect[0], area[0]), max(rect[1], area[1])
    x1, y1 = min(rect[2], area[0] + area[2]), min(rect[3], area[1] + area[3])
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _pass(jobs, data, gbuffer, frame, area, step: int) -> np.ndarray:
    """One kernel pass over the window of the jobs' regions within `area` (x, y, w, h of
    the G-buffer in the frame): the area's (h, w) factors."""
    rects = np.array([r for rs, _ in jobs for r in rs], dtype=np.int64).reshape(-1, 4)
    rect_job = np.repeat(np.arange(len(jobs)), [len(rs) for rs, _ in jobs])
    # Clipped to the area, all at once; those left empty dropped.
    low, high = np.array(area[:2]), np.array(area[:2]) + area[2:]
    rects[:, :2] = np.maximum(rects[:, :2], low)
    rects[:, 2:] = np.minimum(rects[:, 2:], high)
    kept = (rects[:, 2] > rects[:, 0]) & (rects[:, 3] > rects[:, 1])
    if not kept.all():
        rects, rect_job = rects[kept], rect_job[kept]
    x0, y0 = rects[:, :2].min(axis=0).tolist()
    x1, y1 = rects[:, 2:].max(axis=0).tolist()
    frame = frame.copy()  # its window's origin and its G-buffer's: each pass its own
    frame[16:20] = (y0, x0, area[1], area[0])
    full = np.ones((area[3], area[2]), np.float32)
    kernels.sparse_pass(
        full, *gbuffer, frame, y1 - y0, x1 - x0, rects, rect_job, *data, CONSTANTS, step
    )
    return full


COMPILED = sh.CompiledPasses(points_visibility, shadow_regions)
"""The kernels' entry points, for a PrimShadows whose backend computes with numba."""

"""Deterministic builder of the rigspace sample humanoid: skeleton, skinned mesh, texture, clips."""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import OpenImageIO as oiio
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

from rigspace.sdk.rotations import quat_multiply

HERE = Path(__file__).resolve().parent
USD_NAME = "sample_character.usda"
TEXTURE_NAME = "textures/albedo.png"

FPS = 30
TEXTURE_SIZE = 1024
GRID_STEP = 1.5
"""Isosurface grid spacing in cm; sets the triangle count (about 20k)."""
GRID_SHIFTS = ((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), (0.25, 0.5, 0.75), (0.75, 0.25, 0.5))
"""Grid offsets (in steps) tried in turn until the surface extracts as a clean 2-manifold."""
RELAX_ITERATIONS = 3
SKIN_SMOOTH_ITERATIONS = 28
"""Diffusion steps over the mesh that turn rigid part labels into smooth skin weights."""
MAX_INFLUENCES = 4
MIN_WEIGHT = 0.004
ARM_DROP_DEG = 40.0
"""A-pose: the arms point this far below horizontal in the bind pose."""
UV_POLE_SPAN = 0.25
"""Triangles spanning more u than this surround a cylinder pole; they collapse to one u."""
TILE_GUTTER = 8
"""Texels between atlas tiles; each tile is painted this far past its edge against bleeding."""

# The clips, played back to back: (name, frames at 30 fps).
CLIPS = (("walk", 360), ("wave", 240), ("stretch", 360), ("roll", 300), ("yoga", 360))

# ---------------------------------------------------------------------------------------
# Skeleton


@dataclass(frozen=True)
class Joint:
    """One joint of the rig: its short name, parent index, rest pose in skeleton space."""

    name: str
    parent: int
    position: tuple[float, float, float]
    rest_rz: float
    """Rest rotation about Z in degrees (the A-pose arm chain), else 0."""
    side: int
    """+1 left (+X), -1 right, 0 centre: right-side poses are mirrored left-side poses."""


def _arm_dir(side: int) -> np.ndarray:
    """Unit direction of an A-posed arm, out and down."""
    a = np.radians(ARM_DROP_DEG)
    return np.array([side * np.cos(a), -np.sin(a), 0.0])


ARM_LENGTHS = (29.0, 26.0)  # upper arm, forearm (cm)


def build_joints() -> list[Joint]:
    """The 22-joint UE-like skeleton, parents before children, 180 cm tall facing +Z."""
    joints = [
        Joint("pelvis", -1, (0.0, 98.0, -1.0), 0.0, 0),
        Joint("spine_01", 0, (0.0, 106.0, -1.5), 0.0, 0),
        Joint("spine_02", 1, (0.0, 118.0, -2.0), 0.0, 0),
        Joint("spine_03", 2, (0.0, 131.0, -2.0), 0.0, 0),
        Joint("neck_01", 3, (0.0, 149.0, -3.0), 0.0, 0),
        Joint("head", 4, (0.0, 159.0, -1.5), 0.0, 0),
    ]
    for side, tag in ((1, "l"), (-1, "r")):
        # Rounded so the authored transforms read cleanly; the chain stays straight to 1e-4.
        shoulder = np.array([17.5 * side, 145.0, -3.0])
        elbow = np.round(shoulder + ARM_LENGTHS[0] * _arm_dir(side), 4)
        wrist = np.round(elbow + ARM_LENGTHS[1] * _arm_dir(side), 4)
        base = len(joints)
        rz = -ARM_DROP_DEG * side
        joints += [
            Joint(f"clavicle_{tag}", 3, (3.0 * side, 145.5, -0.5), 0.0, side),
            Joint(f"upperarm_{tag}", base, tuple(shoulder.tolist()), rz, side),
            Joint(f"lowerarm_{tag}", base + 1, tuple(elbow.tolist()), rz, side),
            Joint(f"hand_{tag}", base + 2, tuple(wrist.tolist()), rz, side),
        ]
    for side, tag in ((1, "l"), (-1, "r")):
        base = len(joints)
        joints += [
            Joint(f"thigh_{tag}", 0, (9.5 * side, 92.0, -1.0), 0.0, side),
            Joint(f"calf_{tag}", base, (10.5 * side, 50.0, 0.0), 0.0, side),
            Joint(f"foot_{tag}", base + 1, (11.5 * side, 9.0, -3.0), 0.0, side),
            Joint(f"ball_{tag}", base + 2, (12.0 * side, 2.5, 11.0), 0.0, side),
        ]
    return joints


JOINTS = build_joints()
JOINT_INDEX = {j.name: i for i, j in enumerate(JOINTS)}
POS = {j.name: np.array(j.position) for j in JOINTS}


def joint_paths(joints: list[Joint]) -> list[str]:
    """Full UsdSkel joint paths ("pelvis/spine_01/...")."""
    paths: list[str] = []
    for j in joints:
        paths.append(j.name if j.parent < 0 else f"{paths[j.parent]}/{j.name}")
    return paths


def stable(values: np.ndarray, decimals: int) -> np.ndarray:
    """float32 rounded to `decimals` with no negative zeros, so the .usda text is stable.

    Values are computed in float64 and rounded coarsely, so last-bit differences between
    machines almost never change the written digits.
    """
    return (np.round(np.asarray(values, dtype=np.float64), decimals) + 0.0).astype(np.float32)


# ---------------------------------------------------------------------------------------
# Quaternions, (w, x, y, z), Hamilton product, column-vector convention


def quat_axis(axis: int, degrees: np.ndarray) -> np.ndarray:
    """Rotations about a coordinate axis, shape (..., 4)."""
    half = np.radians(np.asarray(degrees, dtype=np.float64)) * 0.5
    q = np.zeros((*half.shape, 4))
    q[..., 0] = np.cos(half)
    q[..., 1 + axis] = np.sin(half)
    return q


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_matrix(q: np.ndarray) -> np.ndarray:
    """3x3 column-vector rotation matrices of unit quaternions."""
    return np.stack([quat_rotate(q, np.eye(3)[i]) for i in range(3)], axis=-1)


def delta_quat(angles: np.ndarray, twist_x: bool) -> np.ndarray:
    """Euler degrees (..., 3) to a rotation about the joint's rest axes, twist innermost.

    Arms twist about X (their bone axis), everything else about Y: Rz*Ry*Rx or Rz*Rx*Ry.
    """
    qx, qy, qz = (quat_axis(k, angles[..., k]) for k in range(3))
    return quat_multiply(qz, quat_multiply(qy, qx) if twist_x else quat_multiply(qx, qy))


def rest_locals(joints: list[Joint]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(local rotations (J,4), local translations (J,3), world rotations (J,4)) of the rest pose."""
    world_q = quat_axis(2, np.array([j.rest_rz for j in joints]))
    local_q = np.empty_like(world_q)
    local_t = np.empty((len(joints), 3))
    for i, j in enumerate(joints):
        if j.parent < 0:
            local_q[i], local_t[i] = world_q[i], j.position
            continue
        inv = world_q[j.parent] * np.array([1.0, -1.0, -1.0, -1.0])
        local_q[i] = quat_multiply(inv, world_q[i])
        offset = np.subtract(j.position, joints[j.parent].position)
        local_t[i] = quat_rotate(inv, offset)
    return local_q, local_t, world_q


def forward_kinematics(local_q: np.ndarray, local_t: np.ndarray, joints: list[Joint]):
    """World (skeleton-space) rotations and positions, (F,J,4) and (F,J,3)."""
    world_q = np.empty_like(local_q)
    world_p = np.empty((*local_q.shape[:-1], 3))
    for i, j in enumerate(joints):
        if j.parent < 0:
            world_q[:, i], world_p[:, i] = local_q[:, i], local_t[:, i]
            continue
        pq = world_q[:, j.parent]
        world_q[:, i] = quat_multiply(pq, local_q[:, i])
        world_p[:, i] = world_p[:, j.parent] + quat_rotate(pq, local_t[:, i])
    return world_q, world_p


# ---------------------------------------------------------------------------------------
# Body shape: a smooth union of primitives bound to joints


TRUNK, ARM_L, ARM_R, LEG_L, LEG_R = range(5)


@dataclass(frozen=True)
class Prim:
    """A shape primitive: ellipsoid (centre, radii, axes), round cone (a, b, ra, rb) or slab.

    A slab is a rounded box: centre, half extents and rounding radius, axes.
    """

    kind: str
    a: tuple
    b: tuple
    size: tuple
    axes: tuple
    group: int
    blend: float
    """Smooth-union radius (cm) with everything before it."""


def _ell(c, r, group, blend, axes=None) -> Prim:
    axes = np.eye(3) if axes is None else axes
    return Prim("ell", tuple(c), (), tuple(r), tuple(map(tuple, axes)), group, blend)


def _cone(a, b, ra, rb, group, blend) -> Prim:
    return Prim("cone", tuple(a), tuple(b), (ra, rb), (), group, blend)


def _slab(c, half, rounding, group, blend, axes) -> Prim:
    return Prim("slab", tuple(c), (), (*half, rounding), tuple(map(tuple, axes)), group, blend)


def build_prims() -> list[Prim]:
    """The primitives of the body in the bind pose, left side mirrored to the right."""
    prims = [
        _ell((0, 97, -1.5), (15.5, 11.5, 11.0), TRUNK, 3.0),
        _ell((0, 106, -1.0), (13.5, 8.0, 9.5), TRUNK, 4.0),
        _ell((0, 114, -0.5), (14.0, 11.0, 10.0), TRUNK, 4.0),
        _ell((0, 131, -1.0), (16.5, 14.5, 11.0), TRUNK, 4.0),
        _ell((0, 141, -2.5), (15.0, 7.0, 9.0), TRUNK, 3.0),
        _cone((0, 142, -2.5), (0, 161, -1.0), 6.0, 5.2, TRUNK, 3.0),
        _ell((0, 169.5, 0.0), (8.8, 11.0, 10.4), TRUNK, 3.0),
        _ell((0, 162.0, 2.8), (6.9, 5.5, 7.3), TRUNK, 3.0),
        _ell((0, 166.8, 9.6), (1.6, 3.0, 2.6), TRUNK, 2.0),
    ]
    for side in (1, -1):
        arm, leg = (ARM_L, LEG_L) if side > 0 else (ARM_R, LEG_R)
        sx = np.array([side, 1.0, 1.0])
        d = _arm_dir(side)
        # The hand's frame: along the arm, the back of the hand's normal, forward.
        n = np.array([np.sin(np.radians(ARM_DROP_DEG)) * side, np.cos(np.radians(ARM_DROP_DEG)), 0])
        z = np.array([0.0, 0.0, 1.0])
        arm_axes = np.stack([d, n, z])
        tag = "l" if side > 0 else "r"
        shoulder, elbow, wrist = (POS[f"{j}_{tag}"] for j in ("upperarm", "lowerarm", "hand"))
        hip, knee, ankle = POS[f"thigh_{tag}"], POS[f"calf_{tag}"], POS[f"foot_{tag}"]
        prims += [
            _ell(np.array([8.2, 168.5, -0.5]) * sx, (1.4, 3.0, 2.0), TRUNK, 1.0),
            _ell(np.array([7.0, 92.5, -6.0]) * sx, (8.0, 8.5, 7.0), TRUNK, 3.0),
            _cone(np.array([4.0, 145.5, -1.5]) * sx, shoulder, 5.5, 5.5, TRUNK, 3.0),
            _ell(shoulder + np.array([0.0, -0.5, 0.0]), (6.2, 6.5, 6.2), arm, 3.0),
            _cone(shoulder, elbow, 5.0, 3.9, arm, 2.5),
            _ell(shoulder + 13 * d + (0, 0, 0.8), (9.0, 4.7, 4.7), arm, 2.5, arm_axes),
            _cone(elbow, wrist, 3.9, 2.9, arm, 2.5),
            _ell(elbow + 7 * d, (7.0, 4.0, 4.2), arm, 2.5, arm_axes),
            _slab(wrist + 9.0 * d, (7.0, 0.2, 2.2), 2.4, arm, 2.0, arm_axes),
            _cone(
                wrist + 2.5 * d + 2.8 * z - 0.3 * n, wrist + 7.5 * d + 5.6 * z, 1.8, 1.6, arm, 1.2
            ),
            _cone(hip, knee, 8.0, 5.3, leg, 2.5),
            _ell(hip + 0.4 * (knee - hip) + (0, 0, 1), (7.0, 14.0, 7.5), leg, 2.5),
            _cone(knee, ankle, 5.0, 3.6, leg, 2.5),
            _ell(knee + 0.3 * (ankle - knee) + (0, 0, -1.5), (5.0, 10.0, 5.3), leg, 2.5),
            _ell(np.array([11.5, 4.5, -2.0]) * sx, (4.8, 6.0, 7.0), leg, 2.5),
            _ell(np.array([12.0, 3.5, 10.5]) * sx, (5.1, 3.9, 9.8), leg, 2.5),
        ]
    return prims


SOLE_BLEND = 1.0
"""The body is cut flat at y = 0 (shoe soles), with this rounding in cm."""


def prim_sdf(prim: Prim, p: np.ndarray) -> np.ndarray:
    """Approximate signed distance of points (..., 3) to one primitive."""
    if prim.kind == "ell":
        q = (p - np.array(prim.a)) @ np.array(prim.axes).T
        r = np.array(prim.size)
        k0 = np.linalg.norm(q / r, axis=-1)
        k1 = np.maximum(np.linalg.norm(q / (r * r), axis=-1), 1e-9)
        return k0 * (k0 - 1.0) / k1
    if prim.kind == "slab":
        q = np.abs((p - np.array(prim.a)) @ np.array(prim.axes).T) - np.array(prim.size[:3])
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
        return outside + np.minimum(q.max(axis=-1), 0.0) - prim.size[3]
    # Round cone (Inigo Quilez): exact distance to the convex hull of two spheres.
    a, b = np.array(prim.a), np.array(prim.b)
    r1, r2 = prim.size
    ba = b - a
    l2 = ba @ ba
    rr = r1 - r2
    a2 = l2 - rr * rr
    pa = p - a
    y = pa @ ba
    z = y - l2
    x2 = np.sum((pa * l2 - y[..., None] * ba) ** 2, axis=-1)
    y2, z2 = y * y * l2, z * z * l2
    k = np.sign(rr) * rr * rr * x2
    d_end = np.sqrt(x2 + z2) / l2 - r2
    d_start = np.sqrt(x2 + y2) / l2 - r1
    d_side = (np.sqrt(x2 * a2 / l2) + y * rr) / l2 - r1
    return np.where(
        np.sign(z) * a2 * z2 > k, d_end, np.where(np.sign(y) * a2 * y2 < k, d_start, d_side)
    )


def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum: a blend of radius k where a and b are close."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def prim_bounds(prim: Prim) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds of a primitive."""
    if prim.kind in ("ell", "slab"):
        r = max(prim.size) if prim.kind == "ell" else max(prim.size[:3]) + prim.size[3]
        return np.array(prim.a) - r, np.array(prim.a) + r
    ends = np.array([prim.a, prim.b])
    r = max(prim.size)
    return ends.min(0) - r, ends.max(0) + r


def body_sdf(prims: list[Prim], p: np.ndarray) -> np.ndarray:
    """Signed distance of the body at points (..., 3): smooth union, cut flat at the floor."""
    d = np.full(p.shape[:-1], np.inf)
    for prim in prims:
        d = smin(d, prim_sdf(prim, p), prim.blend)
    return -smin(-d, p[..., 1], SOLE_BLEND)


def body_sdf_grid(prims: list[Prim], origin: np.ndarray, shape: tuple, step: float) -> np.ndarray:
    """body_sdf on a grid, each primitive evaluated only in its box (elsewhere it cannot matter).

    Outside a primitive's box grown by its blend radius the primitive is farther than the
    blend, so the smooth minimum there equals the plain minimum and the primitive never wins.
    """
    axes = [origin[k] + step * np.arange(shape[k]) for k in range(3)]
    d = np.full(shape, np.inf)
    for prim in prims:
        lo, hi = prim_bounds(prim)
        grow = prim.blend + 2 * step
        sl = []
        for k in range(3):
            i0 = max(int(np.floor((lo[k] - grow - origin[k]) / step)), 0)
            i1 = min(int(np.ceil((hi[k] + grow - origin[k]) / step)) + 1, shape[k])
            sl.append(slice(i0, i1))
        grid = np.stack(
            np.meshgrid(*(ax[s] for ax, s in zip(axes, sl, strict=True)), indexing="ij"), -1
        )
        d[tuple(sl)] = smin(d[tuple(sl)], prim_sdf(prim, grid), prim.blend)
    y = axes[1][None, :, None]
    return -smin(-d, np.broadcast_to(y, shape), SOLE_BLEND)


def sdf_gradient(prims: list[Prim], p: np.ndarray, eps: float = 0.05) -> np.ndarray:
    """Central-difference gradient of body_sdf at points (N, 3)."""
    g = np.empty_like(p)
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        g[:, k] = (body_sdf(prims, p + e) - body_sdf(prims, p - e)) / (2 * eps)
    return g


# ---------------------------------------------------------------------------------------
# Isosurface: vectorised surface nets with manifold guarantees


def _corner_graph_ok() -> np.ndarray:
    """(256,) bool: cube corner sign configurations whose inside and outside sets are both connected.

    Only those give one surface sheet per cell, so one surface-nets vertex per cell is manifold.
    """
    edges = [(a, a | (1 << k)) for a in range(8) for k in range(3) if not a & (1 << k)]
    ok = np.zeros(256, dtype=bool)
    for config in range(256):
        good = True
        for want in (0, 1):
            members = {c for c in range(8) if (config >> c) & 1 == want}
            if not members:
                continue
            seen, todo = set(), [min(members)]
            while todo:
                c = todo.pop()
                if c in seen:
                    continue
                seen.add(c)
                todo += [b for a, b in edges if a == c and b in members]
                todo += [a for a, b in edges if b == c and a in members]
            good &= seen == members
        ok[config] = good
    return ok


CELL_OK = _corner_graph_ok()


def _slice(axis: int, lo: bool) -> tuple:
    s = [slice(None)] * 3
    s[axis] = slice(0, -1) if lo else slice(1, None)
    return tuple(s)


def _cell_corners() -> list[tuple]:
    """Slices picking each of a cell's 8 corners (bit k of the corner number = +1 along k)."""
    return [
        tuple(slice(1, None) if (c >> k) & 1 else slice(0, -1) for k in range(3)) for c in range(8)
    ]


def grid_problems(field: np.ndarray) -> np.ndarray:
    """Flat grid indices of the corner nearest the surface in each cell that is not a disk.

    A cell is not a disk when its inside or outside corners are split (CELL_OK), or when one of
    its faces has checkerboard corners (an ambiguous face, shared by four quads' edges).
    """
    inside = field < 0
    config = np.zeros(tuple(np.array(field.shape) - 1), dtype=np.int64)
    for c, sl in enumerate(_cell_corners()):
        config |= inside[sl].astype(np.int64) << c
    bad = ~CELL_OK[config]
    for n in range(3):
        u, v = (n + 1) % 3, (n + 2) % 3
        for lo in (True, False):
            face = inside[_slice(n, lo)]
            s00 = face[_slice(u, True)][_slice(v, True)]
            s11 = face[_slice(u, False)][_slice(v, False)]
            s01 = face[_slice(u, True)][_slice(v, False)]
            s10 = face[_slice(u, False)][_slice(v, True)]
            bad |= (s00 == s11) & (s01 == s10) & (s00 != s01)
    cells = np.argwhere(bad)
    if not len(cells):
        return np.zeros(0, dtype=np.int64)
    offsets = np.array([[(c >> k) & 1 for k in range(3)] for c in range(8)])
    corners = cells[:, None, :] + offsets[None]
    flat = np.ravel_multi_index(corners.reshape(-1, 3).T, field.shape).reshape(-1, 8)
    nearest = np.argmin(np.abs(field.reshape(-1)[flat]), axis=1)
    return np.unique(flat[np.arange(len(flat)), nearest])


def clean_signs(field: np.ndarray, rounds: int = 8) -> np.ndarray | None:
    """The field with near-surface corners flipped until every cell is a disk, or None.

    Where the surface grazes a grid plane, corners within a hair of it take checkerboard
    signs; flipping the one nearest the surface moves the surface by less than that hair.
    """
    field = field.copy()
    flat = field.reshape(-1)
    for _ in range(rounds):
        bad = grid_problems(field)
        if not len(bad):
            return field
        # Mirror the value (a zero becomes a hair on the other side).
        flat[bad] = np.where(flat[bad] < 0, 1.0, -1.0) * np.maximum(np.abs(flat[bad]), 1e-6)
    return None


def surface_nets(field: np.ndarray, origin: np.ndarray, step: float):
    """Quads over one vertex per sign-changing cell: (points (V,3), quads (Q,4)), CCW outside."""
    inside = field < 0
    ncell = tuple(np.array(field.shape) - 1)
    rings, crossings, owners = [], [], []
    for axis in range(3):
        e = np.argwhere(inside[_slice(axis, True)] != inside[_slice(axis, False)])
        unit = np.eye(3, dtype=np.int64)[axis]
        f0, f1 = field[tuple(e.T)], field[tuple((e + unit).T)]
        point = origin + step * (e + (f0 / (f0 - f1))[:, None] * unit)
        b, c = (axis + 1) % 3, (axis + 2) % 3
        cells = []
        # The four cells around the edge, counter-clockwise seen from +axis (b x c = axis).
        for db, dc in ((1, 1), (0, 1), (0, 0), (1, 0)):
            cell = e.copy()
            cell[:, b] -= db
            cell[:, c] -= dc
            cells.append(np.ravel_multi_index(cell.T, ncell))
        ring = np.stack(cells, 1)
        # Outward is from inside to outside: flip quads whose inside end is the upper one.
        flip = ~inside[tuple(e.T)]
        ring[flip] = ring[flip, ::-1]
        rings.append(ring)
        crossings.append(np.repeat(point, 4, axis=0))
        owners.append(ring.reshape(-1))
    owner = np.concatenate(owners)
    cross = np.concatenate(crossings)
    used, inverse = np.unique(owner, return_inverse=True)
    counts = np.bincount(inverse)
    points = np.stack([np.bincount(inverse, cross[:, k]) for k in range(3)], 1) / counts[:, None]
    quads = np.searchsorted(used, np.concatenate(rings))
    return points, quads


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Undirected edges (E,2), sorted, of polygons given as (F,k) vertex indices."""
    k = faces.shape[1]
    e = np.concatenate([faces[:, [i, (i + 1) % k]] for i in range(k)])
    return np.unique(np.sort(e, axis=1), axis=0)


def neighbour_mean(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Mean of each vertex's neighbours' values, (V, ...) given undirected edges."""
    src = np.concatenate([edges[:, 0], edges[:, 1]])
    dst = np.concatenate([edges[:, 1], edges[:, 0]])
    order = np.argsort(src, kind="stable")
    src, dst = src[order], dst[order]
    starts = np.flatnonzero(np.r_[True, src[1:] != src[:-1]])
    sums = np.add.reduceat(values[dst], starts, axis=0)
    count = np.diff(np.r_[starts, len(src)])
    return sums / count.reshape((-1,) + (1,) * (values.ndim - 1))


def relax(points: np.ndarray, quads: np.ndarray, prims: list[Prim]) -> np.ndarray:
    """Even out the vertices along the surface: Laplacian steps, each projected back on it."""
    edges = unique_edges(quads)
    for _ in range(RELAX_ITERATIONS):
        points = points + 0.5 * (neighbour_mean(points, edges) - points)
        points = project(points, prims)
    return project(points, prims)


def project(points: np.ndarray, prims: list[Prim]) -> np.ndarray:
    """One Newton step of each point onto the zero set of the body SDF."""
    f = body_sdf(prims, points)
    g = sdf_gradient(prims, points)
    return points - (f / np.maximum(np.sum(g * g, 1), 1e-6))[:, None] * g


def triangulate_quads(points: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Split each quad along its shorter diagonal (better shaped triangles)."""
    p = points[quads]
    short02 = np.linalg.norm(p[:, 0] - p[:, 2], axis=1) <= np.linalg.norm(p[:, 1] - p[:, 3], axis=1)
    a = np.where(short02[:, None], quads[:, [0, 1, 2]], quads[:, [0, 1, 3]])
    b = np.where(short02[:, None], quads[:, [0, 2, 3]], quads[:, [1, 2, 3]])
    return np.concatenate([a, b]).astype(np.int32)


def check_closed_manifold(points: np.ndarray, tris: np.ndarray) -> dict:
    """Raise unless the mesh is a closed, consistently oriented, genus-0 2-manifold.

    Every undirected edge is used by exactly two triangles in opposite directions, every
    vertex has one fan of triangles, no triangle is degenerate, the volume is positive.
    """
    v = len(points)
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]).astype(np.int64)
    keys = directed[:, 0] * v + directed[:, 1]
    if len(np.unique(keys)) != len(keys):
        raise RuntimeError("mesh: a directed edge is used twice (inconsistent orientation)")
    twin_keys = directed[:, 1] * v + directed[:, 0]
    order = np.argsort(keys)
    pos = np.searchsorted(keys[order], twin_keys)
    pos = np.minimum(pos, len(keys) - 1)
    twin = order[pos]
    if not np.array_equal(keys[twin], twin_keys):
        raise RuntimeError("mesh: an edge has no opposite twin (hole or non-manifold edge)")
    # Fans: half-edge h = slot * T + triangle starts at a corner. Its twin (b->a) lies in the
    # neighbouring triangle, whose next half-edge starts at `a` again: stepping h -> next(twin)
    # walks round a vertex, so a manifold vertex is exactly one cycle of that permutation.
    t = len(tris)
    step = ((twin // t + 1) % 3) * t + twin % t
    label = np.arange(len(directed))
    for _ in range(int(np.ceil(np.log2(len(directed)))) + 1):
        label = np.minimum(label, label[step])
        step = step[step]
    fans = len(np.unique(label))
    if fans != v or len(np.unique(directed[:, 0])) != v:
        raise RuntimeError(f"mesh: {fans - v} non-manifold (pinched) vertices")
    p = points[tris]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    if area.min() <= 1e-6:
        raise RuntimeError("mesh: degenerate triangle")
    volume = np.sum(cross * p[:, 0]) / 6.0
    euler = v - len(keys) // 2 + t
    if euler != 2 or volume <= 0:
        raise RuntimeError(f"mesh: Euler characteristic {euler}, volume {volume:.1f}")
    return {"min_area": float(area.min()), "volume": float(volume)}


def build_surface(prims: list[Prim]) -> tuple[np.ndarray, np.ndarray]:
    """The watertight body mesh (points (V,3) cm, triangles (T,3)), trying grid shifts in turn."""
    bounds = np.array([prim_bounds(p) for p in prims])
    lo = bounds[:, 0].min(0) - 3 * GRID_STEP
    lo[1] = -3 * GRID_STEP  # nothing lies below the floor cut
    hi = bounds[:, 1].max(0) + 3 * GRID_STEP
    failure = "signs could not be cleaned"
    for shift in GRID_SHIFTS:
        origin = lo - np.array(shift) * GRID_STEP
        shape = tuple(int(s) for s in np.ceil((hi - origin) / GRID_STEP).astype(int) + 1)
        field = clean_signs(body_sdf_grid(prims, origin, shape, GRID_STEP))
        if field is None:
            continue
        points, quads = surface_nets(field, origin, GRID_STEP)
        points = relax(points, quads, prims)
        tris = triangulate_quads(points, quads)
        try:
            check_closed_manifold(points, tris)
            check_no_folds(points, tris, prims)
        except RuntimeError as error:
            failure = str(error)
            continue
        return points, tris
    raise RuntimeError(f"no grid shift gives a clean isosurface ({failure}); change GRID_STEP")


def check_no_folds(points: np.ndarray, tris: np.ndarray, prims: list[Prim]) -> None:
    """Raise if relaxing folded a triangle over: its normal must follow the SDF gradient."""
    p = points[tris]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    if np.any(np.sum(normal * sdf_gradient(prims, p.mean(1)), axis=1) <= 0):
        raise RuntimeError("mesh: a triangle faces into the body")


# ---------------------------------------------------------------------------------------
# Segmentation: which joint and which texture tile each bit of surface belongs to


def prim_groups(prims: list[Prim], p: np.ndarray) -> np.ndarray:
    """The body group (trunk, arm or leg) of the nearest primitive at each point."""
    d = np.stack([prim_sdf(prim, p) for prim in prims])
    return np.array([prim.group for prim in prims])[np.argmin(d, axis=0)]


def _chain_t(p: np.ndarray, side: int) -> np.ndarray:
    """Distance along an A-posed arm from its shoulder."""
    shoulder = POS["upperarm_l" if side > 0 else "upperarm_r"]
    return (p - shoulder) @ _arm_dir(side)


def _arm_segments(p: np.ndarray, side: int, tag: str, index: dict[str, int]) -> np.ndarray:
    """Per point, `index`'s number of the arm segment it lies along (upper arm, forearm or
    hand, by its distance from the shoulder): a joint's (JOINT_INDEX) or a tile's (PART_INDEX)."""
    t = _chain_t(p, side)
    return np.select(
        [t < ARM_LENGTHS[0], t < sum(ARM_LENGTHS)],
        [index[f"upperarm_{tag}"], index[f"lowerarm_{tag}"]],
        index[f"hand_{tag}"],
    )


def joint_labels(p: np.ndarray, group: np.ndarray) -> np.ndarray:
    """The joint each point rigidly follows (the bone it lies on), before smoothing."""
    y = p[:, 1]
    label = np.zeros(len(p), dtype=np.int64)  # pelvis
    # Trunk slices: each spine joint owns the surface from its height to the next joint's.
    for name in ("spine_01", "spine_02", "spine_03", "neck_01", "head"):
        label[y >= POS[name][1]] = JOINT_INDEX[name]
    for side, tag, arm, leg in ((1, "l", ARM_L, LEG_L), (-1, "r", ARM_R, LEG_R)):
        shoulder_zone = (side * p[:, 0] > 11.0) & (y > 137.0) & (y < POS["neck_01"][1] + 2)
        label[(group == TRUNK) & shoulder_zone] = JOINT_INDEX[f"clavicle_{tag}"]
        label = np.where(group == arm, _arm_segments(p, side, tag, JOINT_INDEX), label)
        leg_label = np.select(
            [
                y >= POS[f"calf_{tag}"][1],
                y >= POS[f"foot_{tag}"][1],
                p[:, 2] < POS[f"ball_{tag}"][2],
            ],
            [JOINT_INDEX[f"thigh_{tag}"], JOINT_INDEX[f"calf_{tag}"], JOINT_INDEX[f"foot_{tag}"]],
            JOINT_INDEX[f"ball_{tag}"],
        )
        label = np.where(group == leg, leg_label, label)
    return label


@dataclass(frozen=True)
class Part:
    """A texture tile: a cylindrical projection about an axis through a body part."""

    name: str
    origin: np.ndarray
    axis: np.ndarray
    ref: np.ndarray
    """The direction of u = 0.5 (front, or top for feet)."""
    side: int
    emphasis: float
    """Texel density relative to the rest (the face gets more)."""


def build_parts() -> list[Part]:
    """The 15 texture tiles: head, torso, and per side upper arm .. foot."""
    up, front = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    parts = [
        Part("head", np.array([0.0, 0.0, -0.5]), up, front, 0, 1.8),
        Part("torso", np.array([0.0, 0.0, -1.5]), up, front, 0, 1.15),
    ]
    for side, tag in ((1, "l"), (-1, "r")):
        d = _arm_dir(side)
        shoulder = POS[f"upperarm_{tag}"]
        hip, knee, ankle = POS[f"thigh_{tag}"], POS[f"calf_{tag}"], POS[f"foot_{tag}"]
        thigh_axis = (knee - hip) / np.linalg.norm(knee - hip)
        calf_axis = (ankle - knee) / np.linalg.norm(ankle - knee)
        parts += [
            Part(f"upperarm_{tag}", shoulder, d, front, side, 1.0),
            Part(f"lowerarm_{tag}", POS[f"lowerarm_{tag}"], d, front, side, 1.0),
            Part(f"hand_{tag}", POS[f"hand_{tag}"], d, front, side, 1.1),
            Part(f"thigh_{tag}", hip, thigh_axis, front, side, 0.9),
            Part(f"calf_{tag}", knee, calf_axis, front, side, 0.9),
            Part(f"foot_{tag}", np.array([ankle[0], 5.0, ankle[2]]), front, up, side, 1.0),
        ]
    return parts


PARTS = build_parts()
PART_INDEX = {p.name: i for i, p in enumerate(PARTS)}


def part_labels(p: np.ndarray, group: np.ndarray) -> np.ndarray:
    """The texture tile of each point (triangle centroids, in practice)."""
    y = p[:, 1]
    neck = np.hypot(p[:, 0], p[:, 2] + 2.0)
    # Above the shoulders' slope only the neck and head remain.
    head = (y >= 151.0) & ((neck < 8.0) | (y >= 155.0))
    label = np.where(head, PART_INDEX["head"], PART_INDEX["torso"])
    hips = (group == TRUNK) & (y < 94.0)
    label = np.where(hips & (p[:, 0] >= 0), PART_INDEX["thigh_l"], label)
    label = np.where(hips & (p[:, 0] < 0), PART_INDEX["thigh_r"], label)
    for side, tag, arm, leg in ((1, "l", ARM_L, LEG_L), (-1, "r", ARM_R, LEG_R)):
        label = np.where(group == arm, _arm_segments(p, side, tag, PART_INDEX), label)
        leg_part = np.select(
            [y >= POS[f"calf_{tag}"][1], y >= POS[f"foot_{tag}"][1]],
            [PART_INDEX[f"thigh_{tag}"], PART_INDEX[f"calf_{tag}"]],
            PART_INDEX[f"foot_{tag}"],
        )
        label = np.where(group == leg, leg_part, label)
    return label


# ---------------------------------------------------------------------------------------
# Skin weights


def skin_weights(points: np.ndarray, tris: np.ndarray, labels: np.ndarray):
    """Smooth weights: rigid labels diffused over the surface, top 4 kept, rounded, summing to 1."""
    edges = unique_edges(tris)
    w = np.eye(len(JOINTS))[labels]
    for _ in range(SKIN_SMOOTH_ITERATIONS):
        w = 0.5 * w + 0.5 * neighbour_mean(w, edges)
    order = np.argsort(-w, axis=1, kind="stable")[:, :MAX_INFLUENCES]
    top = np.take_along_axis(w, order, axis=1)
    top = np.where(top < MIN_WEIGHT, 0.0, top)
    top /= top.sum(1, keepdims=True)
    # Round for stable text, then give the rounding remainder to the largest influence.
    top = np.round(top, 4)
    top[:, 0] = 1.0 - top[:, 1:].sum(1)
    order = np.where(top > 0, order, 0)
    return order.astype(np.int32), top.astype(np.float32)


# ---------------------------------------------------------------------------------------
# UVs: per-part cylindrical projections packed into an atlas


def part_frames(part_ids: np.ndarray):
    """Per-item origin, axis, reference and binormal arrays of the parts given."""
    o = np.array([p.origin for p in PARTS])[part_ids]
    a = np.array([p.axis for p in PARTS])[part_ids]
    r = np.array([p.ref for p in PARTS])[part_ids]
    # Mirror the angle direction on the right so left and right tiles mirror each other.
    sign = np.array([1.0 if p.side >= 0 else -1.0 for p in PARTS])[part_ids]
    r = r - np.sum(r * a, -1, keepdims=True) * a
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    b = np.cross(a, r) * sign[..., None]
    return o, a, r, b


def cylinder_coords(p: np.ndarray, part_ids: np.ndarray):
    """(theta in [-pi, pi), h along the axis, radius) of points in their parts' cylinders."""
    o, a, r, b = part_frames(part_ids)
    q = p - o
    h = np.sum(q * a, -1)
    theta = np.arctan2(np.sum(q * b, -1), np.sum(q * r, -1))
    radius = np.linalg.norm(q - h[..., None] * a, axis=-1)
    return theta, h, radius


@dataclass(frozen=True)
class Tile:
    """Where a part lands in the atlas: texel rect and the h range it spans."""

    x: int
    y: int
    w: int
    h: int
    h0: float
    h1: float
    radius: float
    u_max: float


def pack_tiles(sizes: list[tuple[float, float]], size: int) -> tuple[float, list[tuple]]:
    """Largest uniform scale whose skyline packing of (w, h) rects fits a size x size atlas."""

    def place(scale: float):
        rects = [(int(np.ceil(w * scale)), int(np.ceil(h * scale))) for w, h in sizes]
        order = sorted(range(len(rects)), key=lambda i: (-rects[i][1], -rects[i][0], i))
        skyline = np.zeros(size, dtype=np.int64)
        out: list[tuple] = [()] * len(rects)
        for i in order:
            w, h = rects[i][0] + TILE_GUTTER, rects[i][1] + TILE_GUTTER
            if w > size:
                return None
            # Bottom-left rule: the lowest spot the rect fits, leftmost among equals.
            tops = np.lib.stride_tricks.sliding_window_view(skyline, w).max(axis=1)
            x = int(np.argmin(tops))
            y = int(tops[x])
            if y + h > size:
                return None
            skyline[x : x + w] = y + h
            out[i] = (x + TILE_GUTTER // 2, y + TILE_GUTTER // 2, rects[i][0], rects[i][1])
        return out

    lo, hi = 0.1, 50.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if place(mid) else (lo, mid)
    return lo, place(lo)


def build_uvs(points: np.ndarray, tris: np.ndarray, tri_part: np.ndarray):
    """faceVarying st (values, per-corner indices) and the atlas tiles of the parts."""
    corner_p = points[tris]
    corner_part = np.repeat(tri_part[:, None], 3, axis=1)
    theta, h, radius = cylinder_coords(corner_p, corner_part)
    u = theta / (2 * np.pi) + 0.5
    # Seams: a triangle straddling the wrap gets its low corners moved past u = 1.
    span = u.max(1) - u.min(1)
    u = np.where((span > 0.5)[:, None] & (u < 0.5), u + 1.0, u)
    # Poles (head top, finger and toe tips): u is meaningless there, use one u per triangle.
    pole = (u.max(1) - u.min(1)) > UV_POLE_SPAN
    u = np.where(pole[:, None], u.mean(1, keepdims=True), u)
    tiles_sizes, ranges = [], []
    for i, part in enumerate(PARTS):
        sel = corner_part == i
        h0, h1 = h[sel].min() - 0.5, h[sel].max() + 0.5
        rad = float(np.median(radius[sel]))
        # The tile covers u in [0, u_max): one turn plus the widest seam triangle's overhang.
        u_max = float(np.ceil(max(u[sel].max(), 1.0) * 100 + 1) / 100)
        ranges.append((h0, h1, rad, u_max))
        circumference = 2 * np.pi * rad * u_max
        tiles_sizes.append((circumference * part.emphasis, (h1 - h0) * part.emphasis))
    _, rects = pack_tiles(tiles_sizes, TEXTURE_SIZE)
    tiles = [
        Tile(x, y, w, hh, h0, h1, rad, u_max)
        for (x, y, w, hh), (h0, h1, rad, u_max) in zip(rects, ranges, strict=True)
    ]
    tx = np.array([[t.x, t.y, t.w, t.h, t.h0, t.h1, t.u_max] for t in tiles])[corner_part]
    col = tx[..., 0] + u / tx[..., 6] * tx[..., 2]
    row = tx[..., 1] + (1 - (h - tx[..., 4]) / (tx[..., 5] - tx[..., 4])) * tx[..., 3]
    # USD st: s right, t up from the image's bottom row.
    st = np.stack([col / TEXTURE_SIZE, 1.0 - row / TEXTURE_SIZE], -1).reshape(-1, 2)
    st = np.round(st, 6)
    vertex = tris.reshape(-1)
    keys = np.column_stack([vertex, np.round(st * 1e6).astype(np.int64)])
    _, first, index = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return stable(st[first], 6), index.reshape(-1).astype(np.int32), tiles


# ---------------------------------------------------------------------------------------
# Texture: painted per tile in body coordinates (angle around the part, height along it)

SKIN = (224, 172, 140)
HAIR = (62, 40, 26)
NAVY = (30, 45, 92)
WHITE = (236, 234, 226)
TROUSERS = (58, 60, 70)
BOOTS = (72, 46, 30)
GLOVES = (232, 122, 28)
BELT = (92, 58, 30)
GOLD = (212, 172, 58)


@dataclass
class Canvas:
    """Texel coordinates of one tile in body terms, and the colour being painted."""

    theta: np.ndarray
    h: np.ndarray
    s: np.ndarray
    """Arc length around the part (cm): theta * radius, so shapes keep their proportions."""
    radius: float
    side: int
    world_y: np.ndarray
    """Height above the floor in the bind pose (along the part's axis, close enough)."""
    rgb: np.ndarray

    def fill(self, mask: np.ndarray, color) -> None:
        """Paint a colour where mask is true."""
        self.rgb[mask] = color

    def blend(self, coverage: np.ndarray, color) -> None:
        """Paint a colour over by coverage in [0, 1] (anti-aliased stamps)."""
        c = np.clip(coverage, 0, 1)[..., None]
        self.rgb[:] = self.rgb * (1 - c) + np.array(color, dtype=np.float64) * c


def ellipse(c: Canvas, s0: float, h0: float, rs: float, rh: float) -> np.ndarray:
    """Inside-ness of an ellipse in (s, h)."""
    return ((c.s - s0) / rs) ** 2 + ((c.h - h0) / rh) ** 2 < 1.0


def stamp(c: Canvas, image: np.ndarray, s0: float, h0: float, half: float) -> np.ndarray:
    """Coverage of a square grey image centred at (s0, h0), `half` cm across each way."""
    n = image.shape[0]
    map_x = ((c.s - s0) / (2 * half) + 0.5) * n - 0.5
    map_y = ((h0 - c.h) / (2 * half) + 0.5) * n - 0.5
    return cv2.remap(
        image.astype(np.float32) / 255.0,
        map_x.astype(np.float32),
        map_y.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )


def glyph(text: str, size: int = 128, scale: float = 3.2, thickness: int = 9) -> np.ndarray:
    """A white-on-black image of text, centred."""
    img = np.zeros((size, size), np.uint8)
    font = cv2.FONT_HERSHEY_DUPLEX
    (w, h), _ = cv2.getTextSize(text, font, scale, thickness)
    cv2.putText(
        img, text, ((size - w) // 2, (size + h) // 2), font, scale, 255, thickness, cv2.LINE_AA
    )
    return img


def periodic(x: np.ndarray, period: float, width: float) -> np.ndarray:
    """Thin lines: where x lies within width of a multiple of period."""
    f = np.mod(x / period, 1.0)
    return np.minimum(f, 1 - f) * period < width * 0.5


def paint_trousers(c: Canvas) -> None:
    """Charcoal cloth with fine pinstripes and a faint cross-check."""
    c.fill(np.ones_like(c.h, bool), TROUSERS)
    c.fill(periodic(c.h, 1.2, 0.25), (78, 80, 92))
    c.fill(periodic(c.s, 1.2, 0.25), (190, 192, 202))


def paint_head(c: Canvas, rng: np.random.Generator) -> None:
    """Face on the front (eyes, brows, nose, mouth), ears, hair on top and back."""
    c.fill(np.ones_like(c.h, bool), SKIN)
    for sx in (-1, 1):
        s_eye = sx * 2.9
        c.fill(ellipse(c, sx * 3.6, 166.5, 1.6, 1.0), (232, 150, 130))  # cheeks
        c.fill(ellipse(c, s_eye, 170.2, 1.5, 0.72), (248, 248, 244))
        c.fill(ellipse(c, s_eye, 170.2, 0.62, 0.62), (60, 110, 160))
        c.fill(ellipse(c, s_eye, 170.2, 0.28, 0.28), (10, 10, 12))
        c.fill(ellipse(c, s_eye + 0.18, 170.42, 0.1, 0.1), (255, 255, 255))
        lid = ellipse(c, s_eye, 170.25, 1.6, 0.82) & ~ellipse(c, s_eye, 170.15, 1.55, 0.72)
        c.fill(lid & (c.h > 170.1), (40, 25, 20))
        brow = np.abs(c.h - (172.4 - 0.12 * (c.s - s_eye) ** 2)) < 0.22
        c.fill(brow & (np.abs(c.s - s_eye) < 1.7), HAIR)
        c.fill(ellipse(c, sx * 0.55, 165.6, 0.35, 0.22), (120, 70, 60))  # nostrils
        ear_s = sx * np.pi / 2 * c.radius
        c.fill(ellipse(c, ear_s, 168.3, 1.4, 2.6), (206, 150, 120))
        c.fill(
            ellipse(c, ear_s, 168.3, 0.7, 1.6) & ~ellipse(c, ear_s, 168.0, 0.5, 1.2), (170, 110, 90)
        )
    c.fill(ellipse(c, 0.0, 163.0, 2.3, 0.55), (180, 70, 70))
    c.fill((np.abs(c.h - 163.0) < 0.08) & (np.abs(c.s) < 2.3), (90, 30, 30))
    freckles = rng.uniform([-5.0, 164.5], [5.0, 168.0], size=(24, 2))
    for fs, fh in freckles:
        if abs(abs(fs) - 2.9) > 1.3 or fh < 166.0:
            c.fill(ellipse(c, fs, fh, 0.12, 0.12), (176, 112, 84))
    hairline = np.interp(
        np.abs(c.theta),
        [0, 0.9, 1.25, 1.85, 2.2, np.pi],
        [176.5, 175.5, 172.5, 172.0, 158.5, 157.0],
    )
    hair = c.h > hairline
    c.fill(hair, HAIR)
    strands = periodic(c.s + 0.4 * np.sin(c.h * 0.9 + rng.uniform(0, 6)), 0.45, 0.1)
    c.fill(hair & strands, (96, 66, 44))


def paint_torso(c: Canvas, rng: np.random.Generator) -> None:
    """Striped shirt with a numbered chest emblem and a collar, belt with buckle, trousers."""
    paint_trousers(c)
    shirt = c.h >= 100.5
    stripe = np.mod(c.h, 4.0) < 2.0
    c.fill(shirt & stripe, NAVY)
    c.fill(shirt & ~stripe, WHITE)
    c.fill(shirt & ~stripe & periodic(c.h - 1.0, 4.0, 0.12), (180, 40, 40))
    # Collar: a white band where the shirt meets the neck, edged in navy.
    c.fill(c.h > 149.5, WHITE)
    c.fill(np.abs(c.h - 149.5) < 0.15, (20, 30, 60))
    belt = (c.h >= 95.0) & (c.h < 100.5)
    c.fill(belt, BELT)
    stitch_rows = (np.abs(c.h - 95.6) < 0.1) | (np.abs(c.h - 99.9) < 0.1)
    c.fill(belt & stitch_rows & periodic(c.s, 0.5, 0.3), (200, 170, 120))
    c.fill(belt & (np.abs(c.h - 97.75) < 0.35) & periodic(c.s - 8.0, 2.5, 0.5), (40, 25, 12))
    buckle = (np.abs(c.s) < 3.2) & (np.abs(c.h - 97.75) < 2.9)
    c.fill(buckle, GOLD)
    c.fill(buckle & (np.abs(c.s) < 2.3) & (np.abs(c.h - 97.75) < 2.0), BELT)
    c.fill((np.abs(c.s + 0.3) < 1.5) & (np.abs(c.h - 97.75) < 0.25), (180, 180, 185))
    emblem = ellipse(c, 0.0, 129.0, 5.6, 5.6)
    c.fill(emblem, (240, 200, 40))
    c.fill(emblem & ~ellipse(c, 0.0, 129.0, 5.0, 5.0), (170, 30, 30))
    number = str(int(rng.integers(10, 100)))
    c.blend(stamp(c, glyph(number), 0.0, 129.0, 4.6), (170, 30, 30))


def paint_upperarm(c: Canvas, _rng: np.random.Generator) -> None:
    """Short striped sleeve with a hem, then bare skin."""
    c.fill(np.ones_like(c.h, bool), SKIN)
    sleeve = c.h < 17.0
    stripe = np.mod(c.h, 4.0) < 2.0
    c.fill(sleeve & stripe, NAVY)
    c.fill(sleeve & ~stripe, WHITE)
    c.fill((c.h >= 15.5) & sleeve, NAVY)


def paint_lowerarm(c: Canvas, _rng: np.random.Generator) -> None:
    """Skin with arm hair; the left wrist alone wears a watch (left/right asymmetry)."""
    c.fill(np.ones_like(c.h, bool), SKIN)
    c.fill(periodic(c.s * 1.7 + c.h * 0.6, 0.9, 0.05), (200, 150, 120))
    if c.side > 0:
        strap = (c.h > ARM_LENGTHS[1] - 5.2) & (c.h < ARM_LENGTHS[1] - 3.0)
        c.fill(strap, (25, 25, 28))
        s_face, h_face = -np.pi / 2 * c.radius, ARM_LENGTHS[1] - 4.1
        c.fill(ellipse(c, s_face, h_face, 1.6, 1.6), (170, 172, 178))
        c.fill(ellipse(c, s_face, h_face, 1.3, 1.3), (250, 250, 245))
        ticks = np.zeros((64, 64), np.uint8)
        for k in range(12):
            a = k * np.pi / 6
            p0 = (32 + int(26 * np.cos(a)), 32 + int(26 * np.sin(a)))
            p1 = (32 + int(30 * np.cos(a)), 32 + int(30 * np.sin(a)))
            cv2.line(ticks, p0, p1, 255, 3)
        cv2.line(ticks, (32, 32), (32, 12), 255, 3)
        cv2.line(ticks, (32, 32), (46, 38), 255, 3)
        c.blend(stamp(c, ticks, s_face, h_face, 1.3), (15, 15, 20))


def paint_hand(c: Canvas, _rng: np.random.Generator) -> None:
    """Orange gloves with a dark cuff and stitched lines on the back."""
    c.fill(np.ones_like(c.h, bool), GLOVES)
    c.fill(c.h < 2.6, (150, 70, 20))
    c.fill((c.h > 6) & (c.h < 15) & periodic(c.s + 4.0, 1.5, 0.12), (120, 55, 15))


def paint_leg(c: Canvas, _rng: np.random.Generator) -> None:
    """Trousers above the boot shaft; boots below 20 cm with a rim."""
    paint_trousers(c)
    boot = c.world_y < 20.0
    c.fill(boot, BOOTS)
    c.fill(boot & (c.world_y > 18.3), (40, 26, 18))


def paint_foot(c: Canvas, _rng: np.random.Generator) -> None:
    """Boot with laces over the instep, a toe-cap seam and a pale sole."""
    c.fill(np.ones_like(c.h, bool), BOOTS)
    lace_zone = (np.abs(c.s) < 2.0) & (c.h > -1.0) & (c.h < 8.0)
    zig = np.abs(np.abs(np.mod(c.h, 1.2) - 0.6) * 3.3 - np.abs(c.s)) < 0.18
    c.fill(lace_zone, (40, 26, 18))
    c.fill(lace_zone & zig, (235, 230, 215))
    c.fill(np.abs(c.h - 10.5) < 0.12, (150, 110, 80))
    c.fill(np.abs(c.theta) > 2.6, (210, 196, 170))


PAINTERS = {
    "head": paint_head,
    "torso": paint_torso,
    "upperarm": paint_upperarm,
    "lowerarm": paint_lowerarm,
    "hand": paint_hand,
    "thigh": paint_leg,
    "calf": paint_leg,
    "foot": paint_foot,
}


def paint_texture(tiles: list[Tile], rng: np.random.Generator) -> np.ndarray:
    """The 1024x1024 sRGB albedo atlas (uint8 RGB, first row = top = highest t)."""
    image = np.full((TEXTURE_SIZE, TEXTURE_SIZE, 3), 128.0)
    pad = TILE_GUTTER // 2
    for part, tile in zip(PARTS, tiles, strict=True):
        x0, x1 = max(tile.x - pad, 0), min(tile.x + tile.w + pad, TEXTURE_SIZE)
        y0, y1 = max(tile.y - pad, 0), min(tile.y + tile.h + pad, TEXTURE_SIZE)
        cols, rows = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
        u = (cols - tile.x) / tile.w * tile.u_max
        h = tile.h0 + (1 - (rows - tile.y) / tile.h) * (tile.h1 - tile.h0)
        theta = (np.mod(u, 1.0) - 0.5) * 2 * np.pi
        world_y = part.origin[1] + h * part.axis[1]
        c = Canvas(
            theta, h, theta * tile.radius, tile.radius, part.side, world_y, image[y0:y1, x0:x1]
        )
        PAINTERS[part.name.split("_")[0]](c, rng)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def write_png(path: Path, image: np.ndarray) -> None:
    """8-bit sRGB PNG through OpenImageIO."""
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], 3, "uint8")
    spec.attribute("oiio:ColorSpace", "sRGB")
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise RuntimeError(f"cannot write {path}: {oiio.geterror()}")
    out.write_image(np.ascontiguousarray(image))
    out.close()


# ---------------------------------------------------------------------------------------
# Motion: procedural clips in anatomical angles, root placed by ground contact


def smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    """0 before a, 1 after b, smooth between."""
    t = np.clip((np.asarray(x, dtype=np.float64) - a) / (b - a), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def bump(phase: np.ndarray, centre: float, width: float) -> np.ndarray:
    """A periodic Gaussian bump over the gait cycle (phase and centre in cycles)."""
    d = np.mod(phase - centre + 0.5, 1.0) - 0.5
    return np.exp(-((d / width) ** 2))


# Angle conventions: degrees about a joint's rest axes, written for the left side; the
# right side mirrors them (build_motion flips its y and z), so equal values are symmetric.
#   spine_*, neck_01, head: x+ bends forward, y+ turns left, z+ bends to the right side
#   clavicle, upperarm: z+ raises the arm, y- swings it forward, x twists it
#   lowerarm: y- bends the elbow; hand: y and z bend the wrist
#   thigh: x- swings the leg forward, z+ spreads it out, y+ turns the knee out
#   calf: x+ bends the knee; foot: x+ points the toes, z+ turns the sole out; ball: x- lifts toes
#   pelvis: the whole body; `heading` turns it about the vertical on top of that


class Pose:
    """Anatomical angles (F,J,3) in degrees, left-side convention for both sides, plus heading."""

    def __init__(self, frames: int) -> None:
        self.angles = np.zeros((frames, len(JOINTS), 3))
        self.heading = np.zeros(frames)
        self.forward_only = np.zeros(frames, dtype=bool)
        """Frames whose root may not drift backwards (a walk slowing to a stop)."""

    def add(self, joint: str, axis: int, values, sides: tuple[str, ...] = ("",)) -> None:
        """Add degrees to a joint's angle; `sides` ("l", "r") repeats it on both sides."""
        for tag in sides:
            name = f"{joint}_{tag}" if tag else joint
            self.angles[:, JOINT_INDEX[name], axis] += values


BOTH = ("l", "r")


def neutral(pose: Pose, weight) -> None:
    """Relaxed standing: arms lowered from the A-pose, elbows soft."""
    pose.add("upperarm", 2, -25.0 * weight, BOTH)
    pose.add("lowerarm", 1, -12.0 * weight, BOTH)


def clip_walk(t: np.ndarray, rng: np.random.Generator) -> Pose:
    """A walk around a loop: heading turns 360 degrees, arms swing, heels strike, toes roll off."""
    pose = Pose(len(t))
    neutral(pose, 1.0)
    env = smoothstep(0.0, 1.2, t) * (1 - smoothstep(t[-1] - 1.2, t[-1], t))
    cadence = 0.9 * (1 + rng.uniform(-0.03, 0.03))
    phase = np.cumsum(env) * cadence / FPS
    pose.heading = 360.0 * np.cumsum(env) / np.sum(env)
    pose.forward_only[:] = True
    for tag, ph in (("l", phase), ("r", phase + 0.5)):
        hip = 24.0 * np.cos(2 * np.pi * ph) + 6.0
        knee = 12.0 * bump(ph, 0.12, 0.1) + 60.0 * bump(ph, 0.72, 0.12) + 4.0
        ankle = (
            6 * bump(ph, 0.07, 0.05)
            - 10 * bump(ph, 0.4, 0.14)
            + 18 * bump(ph, 0.62, 0.06)
            - 8 * bump(ph, 0.82, 0.1)
        )
        pose.add(f"thigh_{tag}", 0, -hip * env)
        pose.add(f"calf_{tag}", 0, knee * env)
        pose.add(f"foot_{tag}", 0, ankle * env)
        pose.add(f"ball_{tag}", 0, -28.0 * bump(ph, 0.58, 0.06) * env)
        swing = -np.cos(2 * np.pi * ph)  # the arm swings forward with the other leg
        pose.add(f"upperarm_{tag}", 1, -18.0 * swing * env)
        pose.add(f"lowerarm_{tag}", 1, -10.0 * np.maximum(swing, 0) * env)
    cyc = 2 * np.pi * phase
    pose.add("pelvis", 1, -5.0 * np.cos(cyc) * env)
    pose.add("pelvis", 2, 3.0 * np.sin(cyc) * env)
    pose.add("spine_01", 0, 3.0 * env)
    pose.add("spine_03", 1, 6.0 * np.cos(cyc) * env)
    pose.add("head", 1, -1.5 * np.cos(cyc) * env)
    return pose


def clip_wave(t: np.ndarray, rng: np.random.Generator) -> Pose:
    """Raise the right arm and wave the forearm side to side, turning the head to it."""
    pose = Pose(len(t))
    neutral(pose, 1.0)
    up = smoothstep(0.2, 1.4, t) * (1 - smoothstep(6.4, 7.7, t))
    wave = (
        np.sin(2 * np.pi * 1.6 * (t - 1.4))
        * smoothstep(1.2, 1.8, t)
        * (1 - smoothstep(5.6, 6.4, t))
    )
    pose.add("upperarm_r", 2, 75.0 * up)
    pose.add("upperarm_r", 0, -90.0 * up)
    pose.add("lowerarm_r", 1, -66.0 * up + 28.0 * wave)  # elbow -78 with the neutral -12
    pose.add("hand_r", 1, 12.0 * wave)
    pose.add("clavicle_r", 2, 8.0 * up)
    look = smoothstep(0.8, 1.8, t) * (1 - smoothstep(6.0, 7.2, t))
    pose.add("head", 1, -32.0 * look)
    pose.add("head", 0, -6.0 * look + 3.0 * np.sin(2 * np.pi * 0.4 * t) * look)
    pose.add("spine_02", 2, -3.0 * up)
    pose.add("spine_03", 2, -3.0 * up)
    pose.add("upperarm_l", 2, 6.0 * np.sin(np.pi * t / t[-1]))
    return pose


def clip_stretch(t: np.ndarray, rng: np.random.Generator) -> Pose:
    """Arms up overhead, side bends left and right, then a deep squat with arms forward."""
    pose = Pose(len(t))
    neutral(pose, 1.0)
    overhead = smoothstep(0.2, 2.2, t) * (1 - smoothstep(6.8, 7.8, t))
    pose.add("upperarm", 2, 143.0 * overhead, BOTH)
    pose.add("lowerarm", 1, 12.0 * overhead, BOTH)
    pose.add("clavicle", 2, 12.0 * overhead, BOTH)
    bend = (
        np.sin(2 * np.pi * (t - 2.6) / 3.6)
        * smoothstep(2.4, 3.0, t)
        * (1 - smoothstep(5.6, 6.4, t))
    )
    for spine in ("spine_01", "spine_02", "spine_03"):
        pose.add(spine, 2, -8.0 * bend)
    squat = smoothstep(7.2, 8.8, t) * (1 - smoothstep(10.0, 11.6, t))
    pose.add("thigh", 0, -100.0 * squat, BOTH)
    pose.add("thigh", 2, 8.0 * squat, BOTH)
    pose.add("calf", 0, 130.0 * squat, BOTH)
    pose.add("foot", 0, -30.0 * squat, BOTH)
    pose.add("foot", 2, -8.0 * squat, BOTH)
    pose.add("spine_01", 0, 16.0 * squat)
    pose.add("spine_02", 0, 12.0 * squat)
    pose.add("spine_03", 0, 6.0 * squat)
    pose.add("head", 0, -20.0 * squat)
    pose.add("upperarm", 1, -85.0 * squat, BOTH)
    pose.add("upperarm", 2, 25.0 * squat, BOTH)
    return pose


def clip_roll(t: np.ndarray, rng: np.random.Generator) -> Pose:
    """A full turn on the spot with small steps, then a cartwheel to the character's left."""
    pose = Pose(len(t))
    turn = smoothstep(0.3, 4.2, t)
    pose.heading = 360.0 * turn
    stepping = smoothstep(0.2, 0.6, t) * (1 - smoothstep(4.0, 4.4, t))
    for tag, ph in (("l", 0.0), ("r", 0.5)):
        lift = np.maximum(np.sin(2 * np.pi * (t - ph)), 0.0) ** 2 * stepping
        pose.add(f"thigh_{tag}", 0, -20.0 * lift)
        pose.add(f"calf_{tag}", 0, 40.0 * lift)
        pose.add(f"foot_{tag}", 0, -10.0 * lift)
    wheel_t = t - 4.5
    ready = smoothstep(0.0, 1.0, wheel_t) * (1 - smoothstep(3.4, 4.6, wheel_t))
    neutral(pose, 1.0 - ready)
    pose.add("upperarm", 2, 10.0 * stepping, BOTH)
    pose.add("upperarm", 2, 118.0 * ready, BOTH)
    pose.add("clavicle", 2, 10.0 * ready, BOTH)
    pose.add("thigh", 2, 28.0 * ready, BOTH)
    pose.add("foot", 2, -28.0 * ready, BOTH)
    # Step the feet apart and back together (lifted, so the other foot stays planted).
    for tag, start in (("l", 0.05), ("r", 3.5)):
        lift = np.sin(np.pi * np.clip((wheel_t - start) / 0.95, 0.0, 1.0)) ** 2
        pose.add(f"thigh_{tag}", 0, -22.0 * lift)
        pose.add(f"calf_{tag}", 0, 45.0 * lift)
        pose.add(f"foot_{tag}", 0, -12.0 * lift)
    roll = smoothstep(1.0, 3.3, wheel_t)
    pose.add("pelvis", 2, -360.0 * roll)
    # Bend sideways towards the hands going down, then towards the foot coming down, and
    # split the legs overhead: a straight star would roll like a 5 m wheel, a bending body
    # plants hand and foot about a metre apart as a gymnast does.
    lean = np.sin(2 * np.pi * roll)
    for spine in ("spine_01", "spine_02", "spine_03"):
        pose.add(spine, 2, -15.0 * lean)
    pose.add("thigh_l", 2, 30.0 * np.maximum(lean, 0) + 12.0 * np.sin(np.pi * roll) ** 2)
    pose.add("thigh_r", 2, 30.0 * np.maximum(-lean, 0) + 12.0 * np.sin(np.pi * roll) ** 2)
    return pose


TREE_POSE = {
    # Left leg stands, hip shifted over it; the right knee turns out and the right sole rests
    # against the inside of the left thigh (angles fitted once to place the foot there).
    ("thigh_l", 2): -3.0,
    ("foot_l", 2): 3.0,
    ("thigh_r", 0): -31.0,
    ("thigh_r", 1): 60.0,
    ("thigh_r", 2): 47.0,
    ("calf_r", 0): 133.0,
    ("foot_r", 0): 9.0,
    ("foot_r", 2): -35.0,
    ("upperarm_l", 2): 130.0,
    ("upperarm_r", 2): 130.0,
    ("clavicle_l", 2): 10.0,
    ("clavicle_r", 2): 10.0,
    ("lowerarm_l", 1): -22.0,
    ("lowerarm_r", 1): -22.0,
    ("head", 0): -4.0,
}


def clip_yoga(t: np.ndarray, rng: np.random.Generator) -> Pose:
    """Transition into a one-leg tree pose, hold it perfectly still, come back down."""
    pose = Pose(len(t))
    into = smoothstep(0.2, 2.6, t) * (1 - smoothstep(9.8, 11.6, t))
    neutral(pose, 1.0 - into)
    # Raise the right leg a touch before the arms so the weight shift reads first.
    leg = smoothstep(0.0, 0.8, into)
    for (name, axis), value in TREE_POSE.items():
        weight = leg if ("thigh" in name or "calf" in name or "foot" in name) else into
        pose.add(name, axis, value * weight)
    return pose


CLIP_FUNCTIONS = {
    "walk": clip_walk,
    "wave": clip_wave,
    "stretch": clip_stretch,
    "roll": clip_roll,
    "yoga": clip_yoga,
}

# Contact points: (joint, offset in the joint's rest-local frame, radius) used to put the
# lowest point of the body on the floor and to keep whatever touches the floor from sliding.
CONTACTS = [
    (f"{j}_{tag}", off, r)
    for tag, sx in (("l", 1), ("r", -1))
    for j, off, r in (
        ("foot", (0.0, -9.0, -6.0), 0.0),
        ("foot", (sx * -4.0, -8.5, -1.0), 0.0),
        ("foot", (sx * 4.0, -8.5, -1.0), 0.0),
        ("ball", (sx * -4.0, -2.4, 0.5), 0.0),
        ("ball", (sx * 4.5, -2.4, 0.5), 0.0),
        ("ball", (0.0, -2.2, 8.0), 0.0),
        ("hand", (sx * 17.0, 0.0, 0.0), 2.0),
        ("hand", (sx * 9.0, 0.0, 0.0), 2.4),
    )
]
CONTACT_SOFTNESS = 0.4
"""cm: contacts within this of the lowest share the anchoring (both feet flat, heel and toe)."""


def root_motion(world_q: np.ndarray, world_p: np.ndarray, heading, forward_only) -> np.ndarray:
    """Root offsets (F,3): the lowest contact touches y = 0; the contact does not slide.

    Where `forward_only`, a step against the heading is dropped: shrinking strides at the
    end of a walk would otherwise pull the body back over its planted rear foot.
    """
    idx = np.array([JOINT_INDEX[j] for j, _, _ in CONTACTS])
    off = np.array([o for _, o, _ in CONTACTS])
    radius = np.array([r for _, _, r in CONTACTS])
    pts = world_p[:, idx] + quat_rotate(world_q[:, idx], off)
    low = pts[..., 1] - radius
    lift = -low.min(axis=1)
    weight = np.exp(-(low - low.min(1, keepdims=True)) / CONTACT_SOFTNESS)
    weight /= weight.sum(1, keepdims=True)
    # Horizontal: cancel the weighted contacts' motion relative to the root from frame to frame.
    step = np.sum(weight[:-1, :, None] * (pts[1:] - pts[:-1]), axis=1)
    ahead = np.stack(
        [np.sin(np.radians(heading)), np.zeros_like(heading), np.cos(np.radians(heading))], 1
    )[1:]
    back = np.minimum(np.sum(-step * ahead, axis=1), 0.0) * forward_only[1:]
    step += back[:, None] * ahead
    slide = np.concatenate([np.zeros((1, 3)), -np.cumsum(step, axis=0)])
    return np.stack([slide[:, 0], lift, slide[:, 2]], axis=1)


def build_motion(rng: np.random.Generator):
    """All clips back to back: local rotations (F,J,4), translations (F,J,3), clip ranges."""
    poses, ranges, start = [], {}, 0
    for name, frames in CLIPS:
        t = np.arange(frames) / FPS
        poses.append(CLIP_FUNCTIONS[name](t, rng))
        ranges[name] = (start, start + frames - 1)
        start += frames
    angles = np.concatenate([p.angles for p in poses])
    heading = np.concatenate([p.heading for p in poses])
    # Right-side joints mirror the left convention: X angles keep their sign, Y and Z flip.
    sides = np.array([j.side for j in JOINTS])
    angles = angles * np.where(sides[:, None] < 0, [1.0, -1.0, -1.0], 1.0)
    twist_x = np.array(["arm" in j.name or "hand" in j.name for j in JOINTS])
    delta = np.where(twist_x[:, None], delta_quat(angles, True), delta_quat(angles, False))
    rest_q, rest_t, _ = rest_locals(JOINTS)
    local_q = quat_multiply(rest_q[None], delta)
    local_q[:, 0] = quat_multiply(quat_axis(1, heading), local_q[:, 0])
    local_t = np.broadcast_to(rest_t, (*local_q.shape[:-1], 3)).copy()
    world_q, world_p = forward_kinematics(local_q, local_t, JOINTS)
    forward_only = np.concatenate([p.forward_only for p in poses])
    local_t[:, 0] += root_motion(world_q, world_p, heading, forward_only)
    # Keep each joint's quaternion on one hemisphere from frame to frame (no sign flips).
    flips = np.sign(np.sum(local_q[1:] * local_q[:-1], axis=-1))
    local_q[1:] *= np.cumprod(np.where(flips == 0, 1.0, flips), axis=0)[..., None]
    local_q *= np.where(local_q[:1, :, :1] < 0, -1.0, 1.0)
    return stable(local_q, 6), stable(local_t, 4), ranges


# ---------------------------------------------------------------------------------------
# USD


def _matrix(q: np.ndarray, t) -> Gf.Matrix4d:
    """A USD (row-vector) matrix rotating by q then translating by t, rounded for stable text."""
    m = np.eye(4)
    m[:3, :3] = quat_matrix(q).T
    m[3, :3] = t
    # Adding 0.0 turns the -0.0 that rounding leaves into 0.0.
    return Gf.Matrix4d(*(np.round(m, 9) + 0.0).reshape(-1).tolist())


def _xyzw(q: np.ndarray) -> np.ndarray:
    """Vt quaternion arrays store the imaginary part first."""
    return np.ascontiguousarray(q[..., [1, 2, 3, 0]], dtype=np.float32)


def author_skeleton(stage: Usd.Stage, paths: list[str]) -> UsdSkel.Skeleton:
    """/Character/Skel with bind (skeleton-space) and rest (parent-space) transforms."""
    rest_q, rest_t, world_q = rest_locals(JOINTS)
    skel = UsdSkel.Skeleton.Define(stage, "/Character/Skel")
    skel.CreateJointsAttr(Vt.TokenArray(paths))
    world_p = [j.position for j in JOINTS]
    skel.CreateBindTransformsAttr(
        Vt.Matrix4dArray([_matrix(q, p) for q, p in zip(world_q, world_p, strict=True)])
    )
    skel.CreateRestTransformsAttr(
        Vt.Matrix4dArray([_matrix(q, t) for q, t in zip(rest_q, rest_t, strict=True)])
    )
    return skel


def author_animation(stage, skel, paths, local_q, local_t, ranges) -> None:
    """/Character/Skel/Anim: per-frame rotations and translations, unit scales, clip table."""
    anim = UsdSkel.Animation.Define(stage, "/Character/Skel/Anim")
    anim.CreateJointsAttr(Vt.TokenArray(paths))
    rot = anim.CreateRotationsAttr()
    tr = anim.CreateTranslationsAttr()
    quats = _xyzw(local_q)
    trans = local_t.astype(np.float32)
    for f in range(len(quats)):
        rot.Set(Vt.QuatfArray.FromNumpy(quats[f]), f)
        tr.Set(Vt.Vec3fArray.FromNumpy(trans[f]), f)
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * len(paths)))
    for name, (first, last) in ranges.items():
        anim.GetPrim().SetCustomDataByKey(f"rigspace:clips:{name}", Gf.Vec2f(first, last))
    binding = UsdSkel.BindingAPI.Apply(skel.GetPrim())
    binding.CreateAnimationSourceRel().SetTargets([anim.GetPath()])


def author_material(stage: Usd.Stage) -> UsdShade.Material:
    """UsdPreviewSurface with the albedo texture read through the st primvar."""
    UsdGeom.Scope.Define(stage, "/Character/Looks")
    material = UsdShade.Material.Define(stage, "/Character/Looks/BodyMaterial")
    surface = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("Surface"))
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.65)
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    reader = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("StReader"))
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    texture = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("AlbedoTexture"))
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(TEXTURE_NAME))
    texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
    texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
    texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result"
    )
    texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.ConnectableAPI(), "rgb"
    )
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    return material


def author_mesh(stage, skel, mesh_data: dict, material) -> None:
    """/Character/Body: the skinned triangle mesh with UVs, display colours and normals."""
    mesh = UsdGeom.Mesh.Define(stage, "/Character/Body")
    points = mesh_data["points"]
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(mesh_data["tris"])))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(mesh_data["tris"].reshape(-1)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(mesh_data["normals"]))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateExtentAttr(
        Vt.Vec3fArray([Gf.Vec3f(*map(float, points.min(0))), Gf.Vec3f(*map(float, points.max(0)))])
    )
    primvars = UsdGeom.PrimvarsAPI(mesh)
    st = primvars.CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    )
    st.Set(Vt.Vec2fArray.FromNumpy(mesh_data["st"]))
    st.SetIndices(Vt.IntArray.FromNumpy(mesh_data["st_index"]))
    color = mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
    color.Set(Vt.Vec3fArray.FromNumpy(mesh_data["display"]))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    binding.CreateJointIndicesPrimvar(False, MAX_INFLUENCES).Set(
        Vt.IntArray.FromNumpy(mesh_data["joint_index"].reshape(-1))
    )
    binding.CreateJointWeightsPrimvar(False, MAX_INFLUENCES).Set(
        Vt.FloatArray.FromNumpy(mesh_data["joint_weight"].reshape(-1))
    )
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)


def write_stage(path: Path, mesh_data: dict, local_q, local_t, ranges, seed: int) -> None:
    """The whole sample as one .usda layer."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    stage = Usd.Stage.Open(layer)
    last = max(b for _, b in ranges.values())
    layer.documentation = (
        f"rigspace sample humanoid, generated by samples/character/build_character.py --seed {seed}. "
        "Do not edit: rebuild with the script."
    )
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(FPS)
    stage.SetFramesPerSecond(FPS)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(last)
    root = UsdSkel.Root.Define(stage, "/Character")
    Usd.ModelAPI(root.GetPrim()).SetKind("component")
    stage.SetDefaultPrim(root.GetPrim())
    paths = joint_paths(JOINTS)
    skel = author_skeleton(stage, paths)
    author_animation(stage, skel, paths, local_q, local_t, ranges)
    material = author_material(stage)
    author_mesh(stage, skel, mesh_data, material)
    layer.Export(str(path))


# ---------------------------------------------------------------------------------------
# Build


def vertex_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    p = points[tris]
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n = np.stack(
        [np.bincount(tris.reshape(-1), np.repeat(face[:, k], 3), len(points)) for k in range(3)], 1
    )
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def build_mesh(rng: np.random.Generator) -> tuple[dict, np.ndarray]:
    """Mesh arrays ready for USD (points rounded to 0.01 mm) and the albedo image."""
    prims = build_prims()
    points, tris = build_surface(prims)
    points = np.round(points, 3) + 0.0
    check_closed_manifold(points, tris)
    group = prim_groups(prims, points)
    joint_index, joint_weight = skin_weights(points, tris, joint_labels(points, group))
    centroid = points[tris].mean(1)
    tri_part = part_labels(centroid, prim_groups(prims, centroid))
    st, st_index, tiles = build_uvs(points, tris, tri_part)
    image = paint_texture(tiles, rng)
    # displayColor: the texture under each vertex, linear (the fallback where textures are off).
    corner_st = st[st_index]
    _, first_corner = np.unique(tris.reshape(-1), return_index=True)
    s, t = corner_st[first_corner].T
    texel = image[
        ((1 - t) * TEXTURE_SIZE).astype(int).clip(0, TEXTURE_SIZE - 1),
        (s * TEXTURE_SIZE).astype(int).clip(0, TEXTURE_SIZE - 1),
    ]
    srgb = texel / 255.0
    display = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    data = {
        "points": stable(points, 3),
        "tris": tris,
        "normals": stable(vertex_normals(points, tris), 4),
        "st": st,
        "st_index": st_index,
        "display": stable(display, 3),
        "joint_index": joint_index,
        "joint_weight": joint_weight,
    }
    return data, image


def build(out_dir: Path, seed: int = 0) -> dict:
    """Write sample_character.usda and textures/albedo.png into out_dir; return a summary."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    mesh_data, image = build_mesh(rng)
    local_q, local_t, ranges = build_motion(rng)
    write_png(out_dir / TEXTURE_NAME, image)
    write_stage(out_dir / USD_NAME, mesh_data, local_q, local_t, ranges, seed)
    return {
        "joints": len(JOINTS),
        "points": len(mesh_data["points"]),
        "triangles": len(mesh_data["tris"]),
        "frames": len(local_q),
        "clips": ranges,
        "seconds": time.perf_counter() - start,
    }


def main(argv: list[str] | None = None) -> None:
    """Command line: build into --out with --seed, print a one-line summary."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--out", type=Path, default=HERE, help="output folder (default: next to this script)"
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the texture details and motion jitter"
    )
    args = parser.parse_args(argv)
    s = build(args.out, args.seed)
    clips = ", ".join(f"{k} {a}-{b}" for k, (a, b) in s["clips"].items())
    print(
        f"{args.out / USD_NAME}: {s['joints']} joints, {s['points']} points, {s['triangles']} "
        f"triangles, {s['frames']} frames ({clips}) in {s['seconds']:.1f} s"
    )


if __name__ == "__main__":
    main()

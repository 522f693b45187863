"""The mesh path as a user runs it on a CPU: blend shapes, linear blend skinning and normals
compiled with numba, equal to UsdSkel's own skinning within SKINNING_TOLERANCE.

sdk/posing.py's CharacterRig is the reference: UsdSkel's blend shapes and
SkinningQuery.ComputeSkinnedPoints (C++ on one thread, through Vt arrays), then the world
transform and the normals in numpy. CompiledRig poses the same meshes the way a game
engine's CPU path does: the joints' skinning matrices (inverse bind * joint, the mesh's
geomBindTransform folded in) computed once a frame, then one pass over the vertices that
blends each vertex's influences and moves it to world space, after the active blend shapes'
sparse offsets (UsdSkel's sub-shape weights: inbetweens included); normals as
sdk.render.vertex_normals (area-weighted face normals) in one pass over the triangles.
Everything read from the stage (influences in skeleton joint order, triangles, blend shape
offsets) is read once, at construction. One thread, as the project's other kernels: numba's
parallel loops measured slower here on a 23k-triangle character (the frame's threads and a
loaded 2-core machine make each parallel region wait), and at 1.5M triangles the raster, not
the skinning, is most of the mesh path (docs/bench/README.md).

Dual-quaternion meshes (skel:skinningMethod) are left to UsdSkel (the reference path).
Compiled on first use and cached on disk (cache=True).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from pxr import Usd, UsdSkel, Vt

from rigspace.sdk.camera import from_gf
from rigspace.sdk.posing import CharacterRig, _SkinnedMesh

SKINNING_TOLERANCE = 1e-6
"""Largest distance between CompiledRig's posed points and UsdSkel's, as a fraction of the
posed mesh's extent: both skin float32 points with float64 matrices and write float32, so
they differ by float32 rounding (a few 1e-8 of the extent measured on the sample character,
CesiumMan and the blend shape face)."""
NORMAL_TOLERANCE = 1e-6
"""Largest difference of a unit normal's components from sdk.render.vertex_normals (the
same points: the same float32 face normals summed in float64 in the same order)."""


@nb.njit(cache=True)
def skin_points(rest, joints, weights, matrices, to_world, out):  # pragma: no cover - numba
    """Linear blend skinning in place into `out` (N, 3) float32: each of `rest`'s (N, 3)
    points moved by its influences' `matrices` (J, 4, 4) float64, row-vector (p' = p M, as
    UsdSkel), weighted as authored (not renormalised, as UsdSkel), then by `to_world` (4, 4)
    row-vector. `joints` (N, K) int32 index `matrices`; a zero weight is skipped."""
    for i in range(rest.shape[0]):
        x, y, z = float(rest[i, 0]), float(rest[i, 1]), float(rest[i, 2])
        sx = sy = sz = 0.0
        for k in range(joints.shape[1]):
            w = float(weights[i, k])
            if w == 0.0:
                continue
            m = matrices[joints[i, k]]
            sx += w * (x * m[0, 0] + y * m[1, 0] + z * m[2, 0] + m[3, 0])
            sy += w * (x * m[0, 1] + y * m[1, 1] + z * m[2, 1] + m[3, 1])
            sz += w * (x * m[0, 2] + y * m[1, 2] + z * m[2, 2] + m[3, 2])
        # UsdSkel writes float32 skeleton-space points; the world transform follows (posing).
        sx, sy, sz = float(np.float32(sx)), float(np.float32(sy)), float(np.float32(sz))
        t = to_world
        out[i, 0] = sx * t[0, 0] + sy * t[1, 0] + sz * t[2, 0] + t[3, 0]
        out[i, 1] = sx * t[0, 1] + sy * t[1, 1] + sz * t[2, 1] + t[3, 1]
        out[i, 2] = sx * t[0, 2] + sy * t[1, 2] + sz * t[2, 2] + t[3, 2]


@nb.njit(cache=True)
def apply_shapes(points, subs, sub_weights, starts, indices, offsets):  # pragma: no cover
    """UsdSkel's blend shapes in place on `points` (N, 3) float32: for each active sub-shape
    `subs[a]` with weight `sub_weights[a]`, its offsets `offsets[starts[s]:starts[s + 1]]` added
    at its points `indices[...]` (sub-shapes in order, as UsdSkel applies them)."""
    for a in range(subs.shape[0]):
        s, w = subs[a], np.float32(sub_weights[a])
        if w == 0.0:
            continue
        for e in range(starts[s], starts[s + 1]):
            p = indices[e]
            for c in range(3):
                points[p, c] += offsets[e, c] * w


@nb.njit(cache=True)
def vertex_normals(points, triangles, sums, out):  # pragma: no cover - numba
    """sdk.render.vertex_normals into `out` (N, 3) float32: each face's cross product (twice
    its area: the weighting) added at its corners into `sums` (N, 3) float64, then each
    vertex's sum normalised (zero where it is)."""
    sums[:] = 0.0
    for f in range(triangles.shape[0]):
        a, b, c = triangles[f, 0], triangles[f, 1], triangles[f, 2]
        ux, uy, uz = (
            points[b, 0] - points[a, 0],
            points[b, 1] - points[a, 1],
            points[b, 2] - points[a, 2],
        )
        vx, vy, vz = (
            points[c, 0] - points[a, 0],
            points[c, 1] - points[a, 1],
            points[c, 2] - points[a, 2],
        )
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        for v in (a, b, c):
            sums[v, 0] += nx
            sums[v, 1] += ny
            sums[v, 2] += nz
    for v in range(points.shape[0]):
        nx, ny, nz = sums[v, 0], sums[v, 1], sums[v, 2]
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length > 0.0:
            out[v, 0], out[v, 1], out[v, 2] = nx / length, ny / length, nz / length
        else:
            out[v, 0] = out[v, 1] = out[v, 2] = 0.0


@dataclass
class _Shapes:
    """A mesh's blend shapes flattened for apply_shapes: each sub-shape's (point, offset)
    entries at starts[s]:starts[s + 1]."""

    starts: np.ndarray
    indices: np.ndarray
    offsets: np.ndarray


@dataclass
class _Compiled:
    """One skinned mesh's arrays, read once."""

    rest: np.ndarray
    """(N, 3) float32 rest points."""
    joints: np.ndarray
    """(N, K) int32 influences as indices into the frame's matrices (skeleton order, plus an
    identity at the end for a joint the skeleton lacks)."""
    weights: np.ndarray
    """(N, K) float32, as authored."""
    geom_bind: np.ndarray
    """(4, 4) the mesh's geomBindTransform, row-vector."""
    triangles: np.ndarray
    """(T, 3) int32, every part's triangles."""
    shapes: _Shapes | None

    def nbytes(self) -> int:
        arrays = [self.rest, self.joints, self.weights, self.triangles]
        if self.shapes is not None:
            arrays += [self.shapes.starts, self.shapes.indices, self.shapes.offsets]
        return sum(a.nbytes for a in arrays)


class CompiledRig(CharacterRig):
    """CharacterRig whose posed meshes are skinned by the compiled kernels (module docstring);
    the same meshes, parts, charts and errors."""

    def __init__(self, character: Usd.Prim) -> None:
        super().__init__(character)
        skeleton = list(self.skeleton.GetJointsAttr().Get())
        self._compiled = {id(m): self._compile(m, skeleton) for m in self._meshes}

    @staticmethod
    def _compile(mesh: _SkinnedMesh, skeleton: list[str]) -> _Compiled | None:
        query = mesh.query
        if query.GetSkinningMethod() != UsdSkel.Tokens.classicLinear:
            return None  # dual quaternions: UsdSkel's (the reference path)
        rest = np.ascontiguousarray(mesh.parts[0].rest_points, dtype=np.float32)
        influences = query.ComputeVaryingJointInfluences(len(rest))
        k = query.GetNumInfluencesPerComponent()
        indices = np.asarray(influences[0], dtype=np.int64).reshape(-1, k)
        weights = np.asarray(influences[1], dtype=np.float32).reshape(-1, k)
        order = query.GetJointOrder()
        # A mesh's own skel:joints order names the joints its indices count; one the skeleton
        # lacks reads the identity appended after the skeleton's joints.
        names = list(order) if order else skeleton
        to_skeleton = np.array(
            [skeleton.index(n) if n in skeleton else len(skeleton) for n in names] + [0],
            dtype=np.int32,
        )
        if len(indices) != len(rest) or np.any((indices < 0) | (indices >= len(names))):
            return None  # UsdSkel refuses these: the reference path says why (SceneError)
        try:
            shapes = _flatten(mesh, len(rest))
        except _Refused:
            return None
        joints = to_skeleton[indices]
        triangles = np.ascontiguousarray(
            np.concatenate([p.triangles for p in mesh.parts]), dtype=np.int32
        )
        return _Compiled(
            rest, np.ascontiguousarray(joints), np.ascontiguousarray(weights),
            from_gf(query.GetGeomBindTransform()).T, triangles, shapes,
        )  # fmt: skip

    def held_bytes(self) -> int:
        """The arrays the compiled path keeps between frames (rest points, influences,
        triangles, the vertex -> triangle table, blend shape offsets)."""
        return sum(c.nbytes() for c in self._compiled.values() if c is not None)

    def _world_points(self, mesh, skinning, to_world, weights, time):
        compiled = self._compiled.get(id(mesh))
        if compiled is None:
            return super()._world_points(mesh, skinning, to_world, weights, time)
        points = compiled.rest
        if compiled.shapes is not None and mesh.shapes is not None and weights is not None:
            mesh_weights = Vt.FloatArray.FromNumpy(
                np.asarray(weights, dtype=np.float32)[mesh.shapes.order]
            )
            sub_weights, _, subs = mesh.shapes.query.ComputeSubShapeWeights(mesh_weights)
            if len(subs):
                points = points.copy()
                shapes = compiled.shapes
                apply_shapes(points, np.asarray(subs, dtype=np.int64),
                             np.asarray(sub_weights, dtype=np.float32), shapes.starts,
                             shapes.indices, shapes.offsets)  # fmt: skip
        # Row-vector, as UsdSkel: geomBind, then inverse bind * skeleton-space joint; an
        # identity after the skeleton's joints for a joint it lacks.
        matrices = np.concatenate([np.asarray(skinning, dtype=np.float64), np.eye(4)[None]])
        matrices = np.ascontiguousarray(compiled.geom_bind @ matrices)
        out = np.empty_like(compiled.rest)
        skin_points(points, compiled.joints, compiled.weights, matrices,
                    np.ascontiguousarray(to_world.T), out)  # fmt: skip
        return out

    def _normals(self, mesh, world):
        compiled = self._compiled.get(id(mesh))
        if compiled is None:
            return super()._normals(mesh, world)
        out = np.empty_like(world)
        vertex_normals(world, compiled.triangles, np.empty(world.shape), out)
        return out


class _Refused(Exception):
    """Data UsdSkel refuses to deform with: the reference path raises its SceneError."""


def _flatten(mesh: _SkinnedMesh, points: int) -> _Shapes | None:
    """A mesh's sub-shapes (each blend shape and its inbetweens, UsdSkel's order) as one
    table of (point index, offset) entries; a shape without pointIndices covers every point,
    a sub-shape without offsets (UsdSkel's null shape) none.
    None without blend shapes; _Refused for shapes UsdSkel refuses to apply (offsets and
    indices of other lengths, an index past the mesh)."""
    if mesh.shapes is None:
        return None
    query = mesh.shapes.query
    starts, indices, offsets = [0], [], []
    for s, sub in enumerate(mesh.shapes.sub_offsets):
        where = np.asarray(mesh.shapes.point_indices[query.GetBlendShapeIndex(s)], np.int64)
        delta = np.asarray(sub, dtype=np.float32).reshape(-1, 3)
        if not len(delta):  # the null shape at weight 0 of a shape with inbetweens
            where = where[:0]
        elif not len(where):
            where = np.arange(points)
        if len(where) != len(delta) or (len(where) and int(where.max()) >= points):
            raise _Refused
        indices.append(where.astype(np.int32))
        offsets.append(delta)
        starts.append(starts[-1] + len(where))
    return _Shapes(
        np.asarray(starts, dtype=np.int64),
        np.ascontiguousarray(np.concatenate(indices)),
        np.ascontiguousarray(np.concatenate(offsets)),
    )

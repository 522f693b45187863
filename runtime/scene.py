"""The scene's other prims as renderer meshes: UsdGeom gprims tessellated and placed at a time.

Mesh, Cube, Sphere, Cylinder, Cone, Capsule and Plane are supported, coloured by their
UsdPreviewSurface diffuse colour or texture, else displayColor (rigspace.sdk.geometry).
Prims under a neural character are its source asset and are not drawn (the network draws
the character), nor are the point-cached meshes a character declares wherever they are
(RigspacePointCacheAPI: they are the character). Invisible prims and prims whose purpose is guide or proxy are skipped. A
prim whose world transform and points did not change since the last call returns the very
same DrawMesh, so renderers reuse what they uploaded and the engine can tell that nothing
moved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom

from rigspace.sdk import schema
from rigspace.sdk.camera import from_gf
from rigspace.sdk.character_rules import point_cached_meshes
from rigspace.sdk.geometry import MeshSource, read_albedo, read_mesh_source
from rigspace.sdk.render import DrawMesh, vertex_normals
from rigspace.sdk.stage import might_vary

SEGMENTS = 48
"""Around the axis of spheres, cylinders, cones and capsules."""
RINGS = 24
"""Along the axis of spheres and capsule caps."""
DRAWN_PURPOSES = (UsdGeom.Tokens.default_, UsdGeom.Tokens.render)


def _axis_frame(axis: str) -> np.ndarray:
    """Columns map local (x, y, z) with the shape's axis along local Z onto the prim's axis."""
    if axis == "X":
        return np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=np.float64)
    if axis == "Y":
        return np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], dtype=np.float64)
    return np.eye(3)


def _grid(rings: int, segments: int, profile_z: np.ndarray, profile_r: np.ndarray):
    """A surface of revolution about Z from a profile (z, r) of rings + 1 samples."""
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    points = np.stack(
        [
            profile_r[:, None] * np.cos(phi)[None, :],
            profile_r[:, None] * np.sin(phi)[None, :],
            np.broadcast_to(profile_z[:, None], (rings + 1, segments)),
        ],
        axis=-1,
    ).reshape(-1, 3)
    i, j = np.mgrid[:rings, :segments]
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    triangles = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    return points, triangles


def _cap(points: np.ndarray, ring: np.ndarray, z: float, up: bool):
    """A fan closing a ring of point indices at height z, on copies of the ring's points so
    the cap's edge stays sharp in shading."""
    copies = np.arange(len(points), len(points) + len(ring))
    centre = len(points) + len(ring)
    points = np.vstack([points, points[ring], [[0.0, 0.0, z]]])
    ring = copies
    nxt = np.roll(ring, -1)
    fan = (
        np.stack([np.full_like(ring, centre), ring, nxt], -1)
        if up
        else np.stack([np.full_like(ring, centre), nxt, ring], -1)
    )
    return points, fan


def tessellate(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[np.ndarray, np.ndarray]:
    """Local-space (points, triangles) of an implicit UsdGeom shape."""
    if prim.IsA(UsdGeom.Cube):
        h = float(UsdGeom.Cube(prim).GetSizeAttr().Get(time)) / 2
        corners = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)])
        faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        # Flat shading needs its own vertices per face.
        points = np.concatenate([corners[list(f)] for f in faces])
        quads = np.arange(24).reshape(6, 4)
        triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        return points, triangles
    if prim.IsA(UsdGeom.Sphere):
        r = float(UsdGeom.Sphere(prim).GetRadiusAttr().Get(time))
        theta = np.linspace(np.pi, 0, RINGS + 1)
        points, triangles = _grid(RINGS, SEGMENTS, r * np.cos(theta), r * np.sin(theta))
        return points, triangles
    if prim.IsA(UsdGeom.Plane):
        plane = UsdGeom.Plane(prim)
        w = float(plane.GetWidthAttr().Get(time)) / 2
        length = float(plane.GetLengthAttr().Get(time)) / 2
        # The plane's normal is its axis; width along the next axis, length along the one after.
        local = np.array([[-w, -length, 0], [w, -length, 0], [w, length, 0], [-w, length, 0]])
        frame = _axis_frame(str(plane.GetAxisAttr().Get(time)))
        return local @ frame.T, np.array([[0, 1, 2], [0, 2, 3]])
    for kind in (UsdGeom.Cylinder, UsdGeom.Cone, UsdGeom.Capsule):
        if prim.IsA(kind):
            shape = kind(prim)
            r = float(shape.GetRadiusAttr().Get(time))
            h = float(shape.GetHeightAttr().Get(time)) / 2
            frame = _axis_frame(str(shape.GetAxisAttr().Get(time)))
            if kind is UsdGeom.Capsule:
                cap = np.linspace(np.pi, np.pi / 2, RINGS // 2 + 1)
                z = np.concatenate([-h + r * np.cos(cap), (h - r * np.cos(cap))[::-1]])
                rad = np.concatenate([r * np.sin(cap), (r * np.sin(cap))[::-1]])
                points, triangles = _grid(len(z) - 1, SEGMENTS, z, rad)
                return points @ frame.T, triangles
            top_r = 0.0 if kind is UsdGeom.Cone else r
            points, triangles = _grid(1, SEGMENTS, np.array([-h, h]), np.array([r, top_r]))
            ring = np.arange(SEGMENTS)
            points, bottom = _cap(points, ring, -h, up=False)
            caps = [bottom]
            if top_r > 0:
                points, top = _cap(points, ring + SEGMENTS, h, up=True)
                caps.append(top)
            return points @ frame.T, np.concatenate([triangles, *caps])
    raise TypeError(f"{prim.GetPath()} ({prim.GetTypeName()}) is not a supported gprim")


SHAPES = (
    UsdGeom.Cube,
    UsdGeom.Sphere,
    UsdGeom.Plane,
    UsdGeom.Cylinder,
    UsdGeom.Cone,
    UsdGeom.Capsule,
)


@dataclass
class _Static:
    """What is read once per prim: topology, UVs, albedo, and whether its shape is animated."""

    triangles: np.ndarray
    local: np.ndarray
    """(N, 3) float32 local points at the default time (re-read per frame when animated)."""
    animated: bool
    source: MeshSource | None = None
    """Meshes: UVs and albedo to draw with."""
    color: np.ndarray | None = None
    """Implicit shapes: their albedo colour."""


@dataclass
class _Cached:
    key: bytes
    mesh: DrawMesh | None
    """None: not drawn (invisible, or a guide) at that time."""


class SceneGeometry:
    """The stage's drawable prims other than neural characters, posed per time code."""

    def __init__(self, stage: Usd.Stage) -> None:
        self.stage = stage
        found = schema.neural_characters(stage)
        characters = [str(p.GetPath()) for p in found]
        cached = {str(m.GetPath()) for p in found for m in point_cached_meshes(p)[0]}
        self.prims: list[Usd.Prim] = []
        for prim in stage.Traverse():
            path = str(prim.GetPath())
            if any(path == c or path.startswith(c + "/") for c in characters) or path in cached:
                continue
            if prim.IsA(UsdGeom.Mesh) or any(prim.IsA(t) for t in SHAPES):
                self.prims.append(prim)
        self._statics: dict[str, _Static] = {}
        self._cache: dict[str, _Cached] = {}
        self._still: dict[str, bool] = {}
        """Per prim: nothing of it or its ancestors is time-varying (read once, then reused)."""
        self.moving: set[int] = set()
        """ids of the last meshes() call's meshes whose prims may vary in time (the rest never
        move: their shadow map is drawn once)."""

    def _drawn(self, prim: Usd.Prim, time: Usd.TimeCode) -> bool:
        imageable = UsdGeom.Imageable(prim)
        return (
            imageable.ComputeVisibility(time) != UsdGeom.Tokens.invisible
            and imageable.ComputePurpose() in DRAWN_PURPOSES
        )

    def _static(self, prim: Usd.Prim) -> _Static:
        path = str(prim.GetPath())
        if path not in self._statics:
            if prim.IsA(UsdGeom.Mesh):
                source = read_mesh_source(prim)
                animated = UsdGeom.Mesh(prim).GetPointsAttr().ValueMightBeTimeVarying()
                self._statics[path] = _Static(
                    source.triangles, source.rest_points, animated, source
                )
            else:
                points, triangles = tessellate(prim, Usd.TimeCode.Default())
                # Size, radius, height... animated: tessellate per frame; transforms are separate.
                animated = any(
                    a.ValueMightBeTimeVarying()
                    for a in prim.GetAuthoredAttributes()
                    if not a.GetName().startswith("xformOp")
                )
                albedo = read_albedo(prim)
                color = albedo.color if albedo.color.ndim == 1 else albedo.color.mean(axis=0)
                self._statics[path] = _Static(
                    triangles.astype(np.int32), points.astype(np.float32), animated, color=color
                )
        return self._statics[path]

    def _local_points(self, prim: Usd.Prim, static: _Static, when: Usd.TimeCode) -> np.ndarray:
        if not static.animated:
            return static.local
        if prim.IsA(UsdGeom.Mesh):  # topology and UVs stay as read; points follow the time
            return np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(when), dtype=np.float32)
        return tessellate(prim, when)[0].astype(np.float32)

    def meshes(self, time: float) -> list[DrawMesh]:
        """World-space meshes at `time`; unchanged prims give the same DrawMesh object."""
        when = Usd.TimeCode(time)
        xf_cache = UsdGeom.XformCache(when)
        out = []
        self.moving = set()
        for prim in self.prims:
            path = str(prim.GetPath())
            still = self._still.get(path)
            if still is None:
                still = self._still[path] = not might_vary(prim)
            cached = self._cache.get(path)
            if still and cached is not None:  # the same at every time: no stage reads at all
                if cached.mesh is not None:
                    out.append(cached.mesh)
                continue
            if not self._drawn(prim, when):
                self._cache[path] = _Cached(b"", None)
                continue
            static = self._static(prim)
            if not still:
                self.moving.add(len(out))  # its index for now: made an id below
            to_world = from_gf(xf_cache.GetLocalToWorldTransform(prim))
            local = self._local_points(prim, static, when)
            key = to_world.tobytes() + (local.tobytes() if static.animated else b"")
            if cached is not None and cached.key == key and cached.mesh is not None:
                out.append(cached.mesh)
                continue
            world = (local @ to_world[:3, :3].T + to_world[:3, 3]).astype(np.float32)
            normals = vertex_normals(world, static.triangles)
            if static.source is not None:
                mesh = static.source.draw_mesh(world, normals)
            else:
                mesh = DrawMesh(world, static.triangles, normals, color=static.color, name=path)
            self._cache[path] = _Cached(key, mesh)
            out.append(mesh)
        self.moving = {id(out[i]) for i in self.moving}
        return out

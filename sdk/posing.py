"""Pose a neural character at a time: joint transforms, skinned meshes (UsdSkel), point caches.

`CharacterRig` is the one place that turns "stage + character + time" into joint
transforms. Local joint transforms come from a SkelAnimation (the character's
rigspace:animationSource, else the one UsdSkel binds to the skeleton, its own or one
inherited from the SkelRoot: sdk/bindings.py) through UsdSkel's AnimQuery/AnimMapper,
so a live source can later replace them before `UsdSkel.ConcatJointTransforms` (the
seam the runtime uses). Skinning is USD's own
`SkinningQuery.ComputeSkinnedPoints` (the reference; sdk.skinning.CompiledRig replaces it and
the normals with compiled kernels, the mesh path a CPU user runs). Matrices leave this module as numpy in the
column-vector convention (p' = M @ p); Gf matrices are row-vector (camera.from_gf).

A character whose rig no game engine runs (docs/point_caches.md) brings point-cached meshes
(RigspacePointCacheAPI): they are drawn as the stage evaluates them at each time code, after
the skinned ones, and never skinned; its named float controls (RigspaceControlAPI) are rig
parameters after the blend shape weights (`scalar_names`, `scalars`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

from rigspace.sdk import schema
from rigspace.sdk.camera import from_gf
from rigspace.sdk.character_rules import blend_shape_names, resolve_character
from rigspace.sdk.charts import ChartTable, chart_table
from rigspace.sdk.controls import Control
from rigspace.sdk.errors import SceneError
from rigspace.sdk.geometry import MeshSource, read_mesh_parts
from rigspace.sdk.render import DrawMesh, freeze, vertex_normals


@dataclass
class _SkinnedMesh:
    query: UsdSkel.SkinningQuery
    parts: list[MeshSource]
    """The mesh by material (sdk.geometry.read_mesh_parts), skinned once for all of them."""
    shapes: _BlendShapes | None = None
    """Its blend shapes (skel:blendShapes), when it has any."""


@dataclass
class _BlendShapes:
    """A mesh's UsdSkel blend shapes, read once: UsdSkel.BlendShapeQuery's point indices and
    sub-shape offsets (each shape and its inbetweens), and where each of the mesh's shapes
    sits in the character's weight vector."""

    query: UsdSkel.BlendShapeQuery
    point_indices: list
    sub_offsets: list
    order: np.ndarray
    """(S,) index into CharacterRig.blend_shapes per shape of this mesh (its skel:blendShapes
    order)."""

    def apply(self, weights: np.ndarray, points: Vt.Vec3fArray) -> bool:
        """Deform `points` in place by the character-order `weights`, exactly as UsdSkel
        specifies (inbetweens included), before skinning."""
        mesh_weights = Vt.FloatArray.FromNumpy(weights[self.order].astype(np.float32))
        sub_weights, shape_indices, sub_indices = self.query.ComputeSubShapeWeights(mesh_weights)
        return self.query.ComputeDeformedPoints(
            sub_weights, shape_indices, sub_indices, self.point_indices, self.sub_offsets, points
        )


@dataclass
class _CachedMesh:
    """A point-cached mesh: its points as the stage evaluates them at each time code."""

    prim: Usd.Prim
    parts: list[MeshSource]
    """The mesh by material, read at its first cached frame (the topology and the charts'
    rest points)."""
    points: Usd.Attribute

    def samples(self) -> list[float]:
        return list(self.points.GetTimeSamples())


def _cached_mesh(prim: Usd.Prim) -> _CachedMesh:
    points = UsdGeom.Mesh(prim).GetPointsAttr()
    samples = points.GetTimeSamples()
    first = Usd.TimeCode(samples[0]) if samples else None
    return _CachedMesh(prim, read_mesh_parts(prim, first), points)


class CharacterRig:
    """A neural character's skeleton, animation, skinned and point-cached meshes and controls,
    ready to pose per time."""

    def __init__(self, character: Usd.Prim) -> None:
        # The validation rule's look-up and words: inspect reports what this refuses.
        found, problem = resolve_character(character)
        if found is None:
            assert problem is not None  # resolve_character gives one or the other
            raise problem.as_error()
        self.character = character
        self.stage = character.GetStage()
        self.skeleton = UsdSkel.Skeleton(found.skeleton)
        self.joints: list[str] = found.joints
        self._cache = found.skel.cache
        self._skel_query = found.skel.query
        self._topology = UsdSkel.Topology(self.skeleton.GetJointsAttr().Get())
        self._rest = self.skeleton.GetRestTransformsAttr().Get()
        self.animation = found.animation
        self._anim_query = self._cache.GetAnimQuery(UsdSkel.Animation(self.animation))
        self._mapper = UsdSkel.AnimMapper(
            self._anim_query.GetJointOrder(), self.skeleton.GetJointsAttr().Get()
        )
        # Constant per skeleton: inverted once, not per pose.
        self._bind_inverse = [m.GetInverse() for m in self.skeleton.GetBindTransformsAttr().Get()]
        self._meshes = [
            _SkinnedMesh(query, read_mesh_parts(query.GetPrim())) for query in found.skel.skinning
        ]
        self.blend_shapes: tuple[str, ...] = self._read_blend_shapes()
        """The character's blend shapes (character_rules.blend_shape_names): the weight
        vector's order."""
        animated = list(self._anim_query.GetBlendShapeOrder() or ())
        index = {name: k for k, name in enumerate(animated)}
        self._animated = np.array([index.get(n, -1) for n in self.blend_shapes], dtype=np.int64)
        """Per character blend shape, its index in the animation's blendShapes (-1: not
        animated, weight 0 as UsdSkel says)."""
        self._cached = [_cached_mesh(prim) for prim in found.cached]
        """Its point-cached meshes (RigspacePointCacheAPI), drawn after the skinned ones."""
        self.controls: tuple[Control, ...] = schema.read_controls(character)
        """Its named float controls (RigspaceControlAPI), in applied order."""
        self._control_values = [
            schema.control_value_attribute(character, c.name) for c in self.controls
        ]
        self.scalar_names: tuple[str, ...] = self.blend_shapes + tuple(
            c.name for c in self.controls
        )
        """The rig vector's names after the joints: the blend shapes, then the controls (the
        order of `scalars`, of a live source's weights and of `rigspace view`'s sliders)."""
        self._charts: ChartTable | None = None

    def _read_blend_shapes(self) -> tuple[str, ...]:
        names = list(blend_shape_names(m.query for m in self._meshes))
        for mesh in self._meshes:
            if mesh.query.HasBlendShapes():
                query = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(mesh.query.GetPrim()))
                order = [names.index(str(n)) for n in mesh.query.GetBlendShapeOrder()]
                mesh.shapes = _BlendShapes(
                    query,
                    query.ComputeBlendShapePointIndices(),
                    query.ComputeSubShapePointOffsets(),
                    np.array(order, dtype=np.int64),
                )
        return tuple(names)

    def blend_weights(self, time: float) -> np.ndarray:
        """(B,) the animation's blend shape weights at `time`, in `blend_shapes` order (0 for a
        shape the animation does not name)."""
        out = np.zeros(len(self.blend_shapes), dtype=np.float32)
        if not len(out):
            return out
        weights = self._anim_query.ComputeBlendShapeWeights(Usd.TimeCode(time))
        values = np.asarray(weights if weights is not None else (), dtype=np.float32)
        have = (self._animated >= 0) & (self._animated < len(values))
        out[have] = values[self._animated[have]]
        return out

    def control_values(self, time: float) -> np.ndarray:
        """(C,) the controls' values at `time` (as the stage evaluates them: held or
        interpolated between samples), in `controls` order."""
        code = Usd.TimeCode(time)
        values = [attr.Get(code) if attr else None for attr in self._control_values]
        return np.array([0.0 if v is None else v for v in values], dtype=np.float32)

    def scalars(self, time: float) -> np.ndarray:
        """(B + C,) the rig parameters after the joints at `time`: the animation's blend shape
        weights, then the controls' values (`scalar_names` order)."""
        if not self.controls:
            return self.blend_weights(time)
        return np.concatenate([self.blend_weights(time), self.control_values(time)])

    @property
    def has_skinned_meshes(self) -> bool:
        """Whether the skeleton skins any of the character's meshes (else all are cached)."""
        return bool(self._meshes)

    @property
    def cached_meshes(self) -> list[Usd.Prim]:
        """The point-cached Mesh prims, in drawing order."""
        return [m.prim for m in self._cached]

    # -- texture charts -----------------------------------------------------------------

    @property
    def triangle_count(self) -> int:
        """Triangles a posed frame draws (every skinned and cached mesh, after triangulation)."""
        return sum(len(part.triangles) for part in self.mesh_sources())

    def mesh_name(self, mesh: MeshSource) -> str:
        """A skinned mesh's (or material subset's) path relative to the character prim (how
        bundles name it)."""
        return str(Sdf.Path(mesh.path).MakeRelativePath(self.character.GetPath()))

    def texture_charts(self) -> ChartTable:
        """The texture charts of the character's textured meshes (rigspace.sdk.charts), from
        their rest points; computed once."""
        if self._charts is None:
            self._charts = chart_table(
                [
                    (
                        self.mesh_name(part),
                        part.rest_points,
                        part.triangles,
                        part.corner_uv if part.albedo.texture is not None else None,
                        max(part.albedo.texture.shape[:2])
                        if part.albedo.texture is not None
                        else 1,
                    )
                    for part in self.mesh_sources()
                ]
            )
        return self._charts

    def mesh_sources(self) -> list[MeshSource]:
        """The meshes' parts (topology, uvs and albedo): the skinned ones in skinning order,
        then the point-cached ones (posed_meshes order)."""
        meshes: list[_SkinnedMesh | _CachedMesh] = [*self._meshes, *self._cached]
        return [part for m in meshes for part in m.parts]

    def dominant_joints(self) -> list[np.ndarray]:
        """Per posed mesh (posed_meshes order), (N,) int: the skeleton index (`joints`) of the
        joint with the largest skinning weight on each of its points (-1: no joint weighs
        on it). A rigidly deformed mesh gives every point its one influence set's; a
        point-cached mesh, which no joint skins, -1 everywhere."""
        out = []
        for mesh in self._meshes:
            query = mesh.query
            indices, weights = query.ComputeJointInfluences()
            n = max(query.GetNumInfluencesPerComponent(), 1)
            idx = np.asarray(indices, dtype=np.int64).reshape(-1, n)
            w = np.asarray(weights, dtype=np.float64).reshape(-1, n)
            local = idx[np.arange(len(idx)), w.argmax(axis=1)]
            local[w.max(axis=1) <= 0] = -1
            order = query.GetJointOrder()
            if order:  # the mesh's own skel:joints order -> the skeleton's
                lookup = np.array([self.joints.index(str(j)) for j in order] + [-1])
                local = lookup[local]
            points = len(mesh.parts[0].rest_points)
            if query.IsRigidlyDeformed() or len(local) == 1:
                local = np.full(points, local[0] if len(local) else -1)
            out += [local] * len(mesh.parts)
        for cached in self._cached:
            out += [np.full(len(cached.parts[0].rest_points), -1)] * len(cached.parts)
        return out

    # -- time range ---------------------------------------------------------------------

    def time_samples(self) -> np.ndarray:
        """Every authored time code of what poses the character, sorted: the animation's
        joints, and the point caches' and controls' samples (a cached character's pose space
        is its cached frames; validation holds those to the same samples)."""
        anim = UsdSkel.Animation(self.animation)
        times: list[float] = []
        for attr in (anim.GetTranslationsAttr(), anim.GetRotationsAttr(), anim.GetScalesAttr()):
            times += attr.GetTimeSamples()
        for cached in self._cached:
            times += cached.samples()
        for value in self._control_values:
            times += value.GetTimeSamples() if value else []
        return np.unique(np.asarray(times, dtype=np.float64))

    def time_range(self) -> tuple[float, float] | None:
        """First and last time sample of the animation's rotations and translations, and of
        the point caches (None when none is time-sampled)."""
        samples: list[float] = []
        anim = UsdSkel.Animation(self.animation)
        for attr in (anim.GetRotationsAttr(), anim.GetTranslationsAttr()):
            samples += attr.GetTimeSamples()
        for cached in self._cached:
            samples += cached.samples()
        return (min(samples), max(samples)) if samples else None

    # -- joint transforms ---------------------------------------------------------------

    def local_transforms(self, time: float) -> Vt.Matrix4dArray:
        """Joint-local transforms in skeleton order (rest transforms where the animation is sparse).

        Rotations are normalised first, as sdk/rotations does: UsdSkel builds a joint's matrix as
        if its quaternion were unit, so 3q would shear and scale the joint (and its children).
        """
        translations, rotations, scales = self._anim_query.ComputeJointLocalTransformComponents(
            Usd.TimeCode(time)
        )
        rotations = Vt.QuatfArray([q.GetNormalized() for q in rotations])
        local = UsdSkel.MakeTransforms(translations, rotations, scales)
        if not self._mapper.IsIdentity():
            local = self._mapper.Remap(local, self._rest)
        return local

    def rest_local(self) -> Vt.Matrix4dArray:
        """The skeleton's rest transforms (joint-local, skeleton order): its rest pose (empty
        when the skeleton has none)."""
        return Vt.Matrix4dArray(self._rest or [])

    def skeleton_to_world(self, time: float) -> np.ndarray:
        """(4, 4) skeleton-space to world transform at `time`."""
        xf = UsdGeom.XformCache(Usd.TimeCode(time))
        return from_gf(xf.GetLocalToWorldTransform(self.skeleton.GetPrim()))

    def skel_transforms(self, local: Vt.Matrix4dArray) -> Vt.Matrix4dArray:
        """Joint transforms in skeleton space from local ones (the live-source seam)."""
        return UsdSkel.ConcatJointTransforms(self._topology, local)

    def world_transforms(self, time: float, local: Vt.Matrix4dArray | None = None) -> np.ndarray:
        """(J, 4, 4) joint-to-world transforms at `time` (from `local` when given)."""
        skel = self.skel_transforms(self.local_transforms(time) if local is None else local)
        return self.skeleton_to_world(time) @ from_gf(skel)

    # -- skinned meshes -----------------------------------------------------------------

    def _world_points(
        self,
        mesh: _SkinnedMesh,
        skinning: Vt.Matrix4dArray,
        to_world: np.ndarray,
        weights: np.ndarray | None,
        time: float,
    ) -> np.ndarray:
        """(N, 3) float32 world points of `mesh`: its blend shapes at `weights`, UsdSkel's
        skinning by `skinning` (inverse bind * skeleton-space joint), then `to_world`
        (column-vector). The seam sdk.skinning.CompiledRig replaces."""
        points = Vt.Vec3fArray.FromNumpy(mesh.parts[0].rest_points)
        if mesh.shapes is not None and weights is not None:
            if not mesh.shapes.apply(np.asarray(weights, dtype=np.float32), points):
                raise SceneError(
                    f"UsdSkel could not apply the blend shapes of "
                    f"{mesh.query.GetPrim().GetPath()} at time {time}.",
                    "check its skel:blendShapes, skel:blendShapeTargets and each "
                    "BlendShape's offsets and pointIndices (rigspace inspect names them).",
                )
        if not mesh.query.ComputeSkinnedPoints(skinning, points, Usd.TimeCode(time)):
            raise SceneError(
                f"UsdSkel could not skin {mesh.query.GetPrim().GetPath()} at time {time}.",
                "check its jointIndices/jointWeights against the skeleton's joints.",
            )
        p = np.asarray(points, dtype=np.float64)
        return (p @ to_world[:3, :3].T + to_world[:3, 3]).astype(np.float32)

    def _cached_points(self, mesh: _CachedMesh, time: float) -> np.ndarray:
        """(N, 3) float32 world points of a point-cached mesh at `time`: its points as the
        stage evaluates them, through its own local-to-world transform."""
        value = mesh.points.Get(Usd.TimeCode(time))
        expected = len(mesh.parts[0].rest_points)
        p = np.asarray(value if value is not None else (), dtype=np.float64).reshape(-1, 3)
        if len(p) != expected or not np.all(np.isfinite(p)):
            what = f"{len(p)} points for its {expected}" if len(p) != expected else "NaN or Inf"
            raise SceneError(
                f"Point cache {mesh.prim.GetPath()} has {what} at time {time:g}.",
                "re-export the cache with the mesh's topology and finite points at every frame "
                "(rigspace inspect names each bad frame).",
            )
        xf = UsdGeom.XformCache(Usd.TimeCode(time))
        to_world = from_gf(xf.GetLocalToWorldTransform(mesh.prim))
        return (p @ to_world[:3, :3].T + to_world[:3, 3]).astype(np.float32)

    def _normals(self, mesh: _SkinnedMesh | _CachedMesh, world: np.ndarray) -> np.ndarray:
        """(N, 3) float32 unit vertex normals of `mesh` posed at `world`."""
        return vertex_normals(world, np.concatenate([p.triangles for p in mesh.parts]))

    def posed_meshes(
        self,
        time: float,
        local: Vt.Matrix4dArray | None = None,
        charts: bool = False,
        weights: np.ndarray | None = None,
    ) -> list[DrawMesh]:
        """The character's meshes at `time`, in world space: blend shapes applied (`weights`, in
        `blend_shapes` order, or `scalar_names` order: the controls after them change no
        mesh; default the animation's at `time`), then skinned by UsdSkel; then the
        point-cached meshes as the stage evaluates them at `time`. With `charts`, textured
        meshes carry their texture charts (renderers then give uv and chart maps)."""
        charted = {}
        if charts:
            charted = {m.mesh: m.triangle_chart for m in self.texture_charts().meshes}
        skel = self.skel_transforms(self.local_transforms(time) if local is None else local)
        # UsdSkel skinning transforms: inverse(bind) * skel-space joint (row-vector order).
        skinning = Vt.Matrix4dArray([b * s for b, s in zip(self._bind_inverse, skel, strict=True)])
        to_world = self.skeleton_to_world(time)
        if self.blend_shapes and weights is None:
            weights = self.blend_weights(time)
        elif weights is not None:
            weights = np.asarray(weights)[: len(self.blend_shapes)]
        meshes = []
        posed: list[tuple[_SkinnedMesh | _CachedMesh, np.ndarray]] = [
            (m, self._world_points(m, skinning, to_world, weights, time)) for m in self._meshes
        ]
        posed += [(m, self._cached_points(m, time)) for m in self._cached]
        for mesh, world in posed:
            # Normals once per pose, not once per camera that renders it.
            normals = self._normals(mesh, world)
            freeze(world, normals)  # renderers keep what they build from them (DrawMesh)
            for part in mesh.parts:
                drawn = part.draw_mesh(world, normals)
                drawn.chart = charted.get(self.mesh_name(part))
                meshes.append(drawn)
        return meshes


def centre_joint(
    rig: CharacterRig, times: np.ndarray
) -> tuple[int, np.ndarray, list[np.ndarray]] | None:
    """(the joint nearest the skinned meshes' bounding-box centre on average over `times`,
    (T, J, 3) joint positions, the posed points per time); None without skinned meshes.
    `rigspace init` aims the capture ring at that joint; capture warns when a ring is aimed far
    from it."""
    centres, joints, points = [], [], []
    for t in times:
        meshes = rig.posed_meshes(float(t))
        if not meshes:
            return None
        p = np.concatenate([m.points for m in meshes])
        points.append(p)
        centres.append((p.min(axis=0) + p.max(axis=0)) / 2)
        joints.append(rig.world_transforms(float(t))[:, :3, 3])  # column vectors
    positions = np.array(joints)
    mean = np.mean(centres, axis=0)
    return int(np.argmin(np.linalg.norm(positions.mean(axis=0) - mean, axis=1))), positions, points

"""Shadow capsules: one capsule per bone, fitted to a character's skinned mesh, joint-relative.

Unreal's capsule shadows stand in for a skinned character with one capsule per bone; the
runtime poses them with the joint transforms it already computes and casts soft shadows
from them analytically (runtime/shadows/__init__.py). The fit is made once, at the skeleton's bind
pose (where UsdSkel's skinning is the identity, so joint-relative coordinates hold in every
pose for the vertices a joint dominates):

- each vertex belongs to the joint with its largest skin weight;
- a joint's capsule runs along its bone (towards its only child) or, for a joint with no or
  several children, along the principal axis of its vertices; it passes through their mean;
- its radius is the RADIUS_QUANTILE of the vertices' distances from that axis, and its
  segment spans their extent along the axis (END_QUANTILE at each end) less one radius, so
  the rounded caps end where the vertices do.

A character with no skinned mesh, only point caches (docs/point_caches.md), is fitted at its
first cached frame instead: each cached point belongs to the joint whose bone (the segment
to its only child; a leaf's continues its parent's; a fork's is the joint) is nearest, in that frame's joint transforms, which
then stand in for the bind pose (the capsules ride the joints as the cache deforms).

    rig = CharacterRig(stage.GetPrimAtPath("/World/Hero"))
    write_capsules(fit_capsules(rig), "dataset/capsules.json")

The file is JSON: per capsule the joint's path in the skeleton and the segment's two ends
`a`, `b` in the joint's frame (scene units of the fitted stage) and the `radius`. Capture
writes it beside the dataset and export copies it into the model bundle. For a bundle made
before capsules existed, `python -m rigspace.apps.capsules SCENE CHARACTER BUNDLE` fits them
on the scene's character and adds them to the bundle (its manifest gains "capsules").
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom, UsdSkel

from rigspace.sdk.bundle import MANIFEST_FILE, read_manifest_document, write_manifest_document
from rigspace.sdk.camera import from_gf
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.files import write_atomic
from rigspace.sdk.posing import CharacterRig

FORMAT = "rigspace.capsules"
FORMAT_VERSION = 1
FILE_NAME = "capsules.json"
MIN_POINTS = 12
"""A joint dominating fewer vertices than this (a clavicle, a toe) gets no capsule: its few
vertices are better covered by its neighbours' capsules than by a sliver of its own."""
RADIUS_QUANTILE = 0.75
"""Of the vertices' distances from the axis: a limb's round cross-section gives its radius; a
torso's oval one a radius between its half-width and half-depth."""
END_QUANTILE = 0.02
"""Of the vertices' positions along the axis at each end: a stray vertex does not stretch it."""


class CapsuleError(RigspaceError):
    """A capsules file that cannot be used, or a character that has none to fit."""


@dataclass(frozen=True)
class Capsules:
    """Capsules in their joints' frames: joint paths, segment ends a, b (K, 3), radii (K,)."""

    joints: tuple[str, ...]
    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return len(self.joints)


def _dominant_points(rig: CharacterRig) -> tuple[np.ndarray, np.ndarray]:
    """Skeleton-space bind points of every skinned mesh (N, 3) and their dominant joint (N,)."""
    skeleton = rig.skeleton.GetPrim()
    root = UsdSkel.Root.Find(skeleton)
    cache = UsdSkel.Cache()
    cache.Populate(root, Usd.TraverseInstanceProxies())
    points, owners = [], []
    for binding in cache.ComputeSkelBindings(root, Usd.TraverseInstanceProxies()):
        if binding.GetSkeleton().GetPrim() != skeleton:
            continue
        for query in binding.GetSkinningTargets():
            prim = query.GetPrim()
            if not prim.IsA(UsdGeom.Mesh) or not query.HasJointInfluences():
                continue
            if UsdGeom.Imageable(prim).ComputeVisibility() == UsdGeom.Tokens.invisible:
                continue
            local = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(), dtype=np.float64)
            geom_bind = from_gf(query.GetGeomBindTransform())
            k = query.GetNumInfluencesPerComponent()
            indices, weights = query.ComputeJointInfluences()
            indices = np.asarray(indices, dtype=np.int64).reshape(-1, k)
            weights = np.asarray(weights, dtype=np.float64).reshape(-1, k)
            dominant = indices[np.arange(len(indices)), weights.argmax(axis=1)]
            if query.IsRigidlyDeformed():  # one influence set for the whole mesh
                dominant = np.repeat(dominant[:1], len(local))
            order = query.GetJointOrder()
            if order:  # the mesh's own joint order: map it onto the skeleton's
                remap = np.array([rig.joints.index(str(j)) for j in order])
                dominant = remap[dominant]
            points.append(local @ geom_bind[:3, :3].T + geom_bind[:3, 3])
            owners.append(dominant)
    if not points:
        raise CapsuleError(
            f"Character {rig.character.GetPath()}: no skinned mesh to fit shadow capsules to.",
            "bind the character's meshes to its skeleton with skin weights.",
        )
    return np.concatenate(points), np.concatenate(owners)


def _nearest_bones(rig: CharacterRig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A point-cached character's points at its first cached frame in skeleton space (N, 3),
    the joint whose bone is nearest each (N,), and the joints' skeleton-space transforms
    then (J, 4, 4), which stand in for the bind pose."""
    time = float(rig.time_samples()[0])
    to_skel = np.linalg.inv(rig.skeleton_to_world(time))
    frames = to_skel @ rig.world_transforms(time)
    meshes = rig.posed_meshes(time)
    points = np.concatenate([m.points for m in meshes]).astype(np.float64)
    points = points @ to_skel[:3, :3].T + to_skel[:3, 3]
    parents = np.asarray(UsdSkel.Topology(rig.skeleton.GetJointsAttr().Get()).GetParentIndices())
    heads = frames[:, :3, 3]
    tails = heads.copy()
    for j in range(len(heads)):
        children = np.flatnonzero(parents == j)
        if len(children) == 1:
            tails[j] = heads[children[0]]
        elif not len(children) and parents[j] >= 0:  # a leaf: its parent's bone, continued
            tails[j] = 2 * heads[j] - heads[parents[j]]
    bone = tails - heads  # (J, 3); zero for a fork: the joint itself
    length2 = np.maximum((bone**2).sum(axis=1), 1e-12)
    s = np.clip(((points[:, None] - heads[None]) * bone[None]).sum(axis=2) / length2, 0.0, 1.0)
    nearest = heads[None] + s[..., None] * bone[None]
    owners = np.linalg.norm(points[:, None] - nearest, axis=2).argmin(axis=1)
    return points, owners, frames


def fit_capsules(rig: CharacterRig) -> Capsules:
    """One capsule per joint that dominates at least MIN_POINTS vertices (module docstring)."""
    if rig.has_skinned_meshes:
        points, owners = _dominant_points(rig)
        bind = from_gf(rig.skeleton.GetBindTransformsAttr().Get())
    else:  # point caches only: the first cached frame stands in for the bind pose
        points, owners, bind = _nearest_bones(rig)
    parents = np.asarray(UsdSkel.Topology(rig.skeleton.GetJointsAttr().Get()).GetParentIndices())
    joints, ends_a, ends_b, radii = [], [], [], []
    for j in np.flatnonzero(np.bincount(owners, minlength=len(rig.joints)) >= MIN_POINTS):
        to_joint = np.linalg.inv(bind[j])
        p = points[owners == j] @ to_joint[:3, :3].T + to_joint[:3, 3]
        centre = p.mean(axis=0)
        children = np.flatnonzero(parents == j)
        if len(children) == 1:  # along the bone: towards the child joint's bind position
            axis = to_joint[:3, :3] @ bind[children[0]][:3, 3] + to_joint[:3, 3]
        else:  # the principal axis of its vertices
            axis = np.linalg.svd(p - centre, full_matrices=False)[2][0]
        norm = np.linalg.norm(axis)
        axis = axis / norm if norm > 0 else np.array([0.0, 1.0, 0.0])
        along = (p - centre) @ axis
        radial = np.linalg.norm(p - centre - along[:, None] * axis, axis=1)
        r = float(np.quantile(radial, RADIUS_QUANTILE))
        lo, hi = np.quantile(along, [END_QUANTILE, 1 - END_QUANTILE])
        lo, hi = (lo + r, hi - r) if hi - lo > 2 * r else ((lo + hi) / 2,) * 2
        joints.append(rig.joints[j])
        ends_a.append(centre + lo * axis)
        ends_b.append(centre + hi * axis)
        radii.append(r)
    return Capsules(tuple(joints), np.array(ends_a), np.array(ends_b), np.array(radii))


def write_capsules(capsules: Capsules, path: str | Path) -> Path:
    """Write capsules as JSON, atomically; returns the path."""
    path = Path(path)
    data = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "fitted_at": "bind pose",
        "units": "the fitted stage's scene units, in each joint's frame",
        "capsules": [
            {"joint": j, "a": a.round(4).tolist(), "b": b.round(4).tolist(), "radius": round(r, 4)}
            for j, a, b, r in zip(
                capsules.joints, capsules.a, capsules.b, capsules.radius.tolist(), strict=True
            )
        ],
    }
    return write_atomic(path, json.dumps(data, indent=2) + "\n")


def read_capsules(path: str | Path) -> Capsules:
    """Read a capsules file (CapsuleError naming the file and the fix when it is unusable)."""
    path = Path(path)
    fix = "fit them again: `python -m rigspace.apps.capsules SCENE CHARACTER BUNDLE`."
    try:
        data = json.loads(path.read_text())
        if data.get("format") != FORMAT or data.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"format {data.get('format')!r} {data.get('format_version')!r}")
        rows = data["capsules"]
        a = np.array([c["a"] for c in rows], dtype=np.float64).reshape(-1, 3)
        b = np.array([c["b"] for c in rows], dtype=np.float64).reshape(-1, 3)
        radius = np.array([c["radius"] for c in rows], dtype=np.float64).reshape(-1)
        joints = tuple(str(c["joint"]) for c in rows)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CapsuleError(f"Shadow capsules {path} are not readable ({exc}).", fix) from exc
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(radius >= 0)):
        raise CapsuleError(f"Shadow capsules {path} hold NaN, Inf or negative radii.", fix)
    return Capsules(joints, a, b, radius)


def add_to_bundle(capsules: Capsules, bundle: str | Path) -> Path:
    """Write capsules into a model bundle and name them in its manifest ("capsules"), leaving
    every other manifest field as it was. The manifest is read and checked first (a
    BundleError, and nothing written, when a reader would refuse it)."""
    bundle = Path(bundle)
    if not (bundle / MANIFEST_FILE).is_file():
        raise CapsuleError(
            f"{bundle} is not a model bundle (no manifest.json).", "pass the bundle's folder."
        )
    data = read_manifest_document(bundle)
    written = write_capsules(capsules, bundle / FILE_NAME)
    data["capsules"] = FILE_NAME
    write_manifest_document(bundle, data)
    return written

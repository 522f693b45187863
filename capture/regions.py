"""Regions: the face or a hand captured around its own joint, at its own resolution, alone.

A character's body network draws the whole character at 128x128, where its face covers about
40 pixels. A region (RigspaceRegionAPI, rigspace.sdk.schema.Region) gets a dataset of its own
(`rigspace capture SCENE --out DATASET/regions/NAME --region NAME`, or every region after the
body with `--regions`), made by the same pipeline with these settings (region_settings):

- the capture ring looks at the region's joint and follows it; its radius frames a square of
  the region's `size` at the joint (derived, when 0, from how far the region's surface reaches
  from the joint over the clips); its resolution is the region's; its views and elevations
  are the region's or the ring's;
- the region's surface is the skinned points whose largest skinning weight is on one of the
  region's joints (CharacterRig.dominant_joints; by default the joint and every joint below
  it): a triangle belongs when two of its three corners do (region_triangles);
- each sample shows that surface alone and whole (CaptureSettings.region_surface): an arm
  raised before the head does not cut it, since the region's network does not read the arm
  and could not foresee the hole; on screen the body's arm goes in front of it by depth
  (runtime/regions.py). Captures before kept it only where it was the character's nearest
  surface (visible_region; "visible"), which cut a quarter of the film face's yoga views;
- the region's blend shapes (authored, or every shape that moves a point of its surface) are
  drawn in every frame, whatever the animation does, so the region's network sees each
  shape's weight apart from the pose (said when capture starts): each at rest or uniformly
  within its range, the share at work drawn per frame (CaptureSettings.shape_draws), so that
  a face at rest, one shape alone and all of them at once are all learned;
- the dataset records the region's own inputs (input_joints): its joint's chain from the root
  and its own joints, its own blend shapes (a hand's none) and the character's controls; its
  network reads those alone, whatever the rest of the body does;
- with `upright = "joint"` its cameras keep the joint's own up upright (the local direction
  that is the stage's up in the rest pose; CaptureSettings.upright_axis), not the stage's: a
  head tilted, or a hand rolled, as no clip turns it is then a view its network learned, and
  the runtime's billboard turns with the joint instead (runtime/character.py).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from rigspace.capture.ring import stage_axes
from rigspace.capture.settings import (
    BOUNDS_FRAMES,
    CaptureError,
    CaptureSettings,
    Clip,
    Warn,
    fit_radius,
)
from rigspace.sdk import schema
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.render import DrawMesh, Maps, freeze
from rigspace.sdk.rotations import rest_up_axis
from rigspace.sdk.validation import MAX_RESOLUTION, MIN_RESOLUTION

CORNERS_INSIDE = 2
"""A triangle is the region's when this many of its corners are (the seam at the neck or the
wrist falls between triangles, not through them)."""
VISIBLE_DEPTH = 1e-3
"""A region pixel is visible when its depth is within this share of the nearest surface's."""
NEAR_SHARE = 0.05
"""The region ring's near clipping plane, as a share of its radius: what comes between the
camera and the region (a hand before the face) must be drawn to hide it."""
FAR_REACHES = 4.0
"""The region ring's far plane: this many of the region's reaches beyond the joint."""
MOVED = 1e-5
"""A blend shape moves a point when it displaces it by over this share of the character's size."""


def find_region(prim, name: str) -> schema.Region:
    """The character's region `name` (RigspaceRegionAPI:name), or a CaptureError listing the
    ones it has."""
    regions = {r.name: r for r in schema.read_regions(prim)}
    if name not in regions:
        have = ", ".join(regions) or "none"
        raise CaptureError(
            f"{prim.GetPath()} has no region {name!r} (its regions: {have}).",
            "apply RigspaceRegionAPI:NAME to the character (docs/regions.md), or pass one of "
            "its regions to --region.",
        )
    return regions[name]


def region_joints(rig: CharacterRig, region: schema.Region) -> tuple[int, ...]:
    """Skeleton indices of the region's joints: the authored ones, else its joint and every
    joint below it; a CaptureError naming a joint the skeleton does not have."""
    if not region.joint:
        raise CaptureError(
            f"Region {region.name!r} names no joint (rigspace:region:{region.name}:joint).",
            "author the joint its cameras follow: the head for a face, a hand for a hand.",
        )
    try:
        joint = schema.find_joint(region.joint, rig.joints)
        if region.joints:
            return tuple(sorted({schema.find_joint(j, rig.joints) for j in region.joints}))
    except schema.JointLookupError as exc:
        raise CaptureError(
            f"Region {region.name!r}: {exc.args[0]}.", "name joints of the skeleton."
        ) from exc
    root = rig.joints[joint]
    below = [k for k, path in enumerate(rig.joints) if path.startswith(root + "/")]
    return (joint, *below)


def input_joints(rig: CharacterRig, joint: int, joints: tuple[int, ...]) -> tuple[str, ...]:
    """The joints a region's network reads, in skeleton order: its joint's chain from the
    root (what places and turns it) and its own joints with theirs (what moves its surface),
    not the rest of the body. A face reads the spine, neck and head, not the arms: with every joint,
    an arm pose the clips never showed makes the face's input new (samples/film_character
    README, "The face's yaw"). The head and its parent alone were tried (2026-11-28): better
    on the face's own held-out views, 0.9 dB worse on screen (samples/film_character README,
    "Upright to the head")."""
    paths = [rig.joints[k] for k in (joint, *joints)]
    return tuple(
        name
        for name in rig.joints  # a joint read is read with its ancestors: a closed tree
        if any(path == name or path.startswith(name + "/") for path in paths)
    )


def region_points(rig: CharacterRig, joints: tuple[int, ...]) -> list[np.ndarray]:
    """Per posed mesh, (N,) bool: the points whose largest skinning weight is on `joints`."""
    chosen = np.asarray(joints, dtype=np.int64)
    return [np.isin(dominant, chosen) for dominant in rig.dominant_joints()]


def region_triangles(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(T,) bool: the triangles with CORNERS_INSIDE or more corners on the region's points."""
    return points[triangles].sum(axis=1) >= CORNERS_INSIDE


class RegionMeshes:
    """The posed frames' meshes cut down to a region's triangles; the cut arrays are made once
    (a renderer keeps what it builds from arrays it has seen), the points are each frame's."""

    def __init__(self, rig: CharacterRig, joints: tuple[int, ...]) -> None:
        self.points = region_points(rig, joints)
        self._cut: dict[int, tuple[np.ndarray, np.ndarray | None, np.ndarray | None]] = {}

    def of(self, meshes: list[DrawMesh]) -> list[DrawMesh]:
        out = []
        for k, (mesh, points) in enumerate(zip(meshes, self.points, strict=True)):
            if k not in self._cut:
                keep = region_triangles(mesh.triangles, points)
                cut = (
                    np.ascontiguousarray(mesh.triangles[keep]),
                    None if mesh.corner_uv is None else np.ascontiguousarray(mesh.corner_uv[keep]),
                    None if mesh.chart is None else np.ascontiguousarray(mesh.chart[keep]),
                )
                freeze(*(a for a in cut if a is not None))
                self._cut[k] = cut
            triangles, corner_uv, chart = self._cut[k]
            if len(triangles):
                out.append(replace(mesh, triangles=triangles, corner_uv=corner_uv, chart=chart))
        return out


def visible_region(whole: Maps, region: Maps) -> Maps:
    """The region's maps where its surface is the nearest (within VISIBLE_DEPTH of the whole
    character's depth), empty elsewhere (the dataset's conventions: mask 0, depth +inf)."""
    nearest = np.where(np.isfinite(whole.depth), whole.depth, np.inf)
    visible = (region.mask > 0) & (region.depth <= nearest * (1.0 + VISIBLE_DEPTH))
    chart = None if region.chart is None else np.where(visible, region.chart, 0)
    uv = None if region.uv is None else np.where(visible[..., None], region.uv, 0.0)
    return Maps(
        albedo=np.where(visible[..., None], region.albedo, 0.0).astype(np.float32),
        normal=np.where(visible[..., None], region.normal, 0.0).astype(np.float32),
        depth=np.where(visible, region.depth, np.inf).astype(np.float32),
        mask=np.where(visible, region.mask, 0.0).astype(np.float32),
        uv=None if uv is None else uv.astype(np.float32),
        chart=None if chart is None else chart.astype(np.int32),
    )


def region_reach(
    rig: CharacterRig, joint: int, points: list[np.ndarray], clips: tuple[Clip, ...]
) -> float:
    """The farthest a point of the region gets from its joint over the clips (scene units)."""
    times = np.concatenate([c.times() for c in clips])
    picks = times[np.linspace(0, len(times) - 1, min(BOUNDS_FRAMES, len(times))).astype(int)]
    reach = 0.0
    for t in picks:
        centre = rig.world_transforms(float(t))[joint][:3, 3]
        for mesh, inside in zip(rig.posed_meshes(float(t)), points, strict=True):
            if inside.any():
                distance = np.linalg.norm(mesh.points[inside] - centre, axis=1)
                reach = max(reach, float(distance.max()))
    return reach


def moving_shapes(rig: CharacterRig, points: list[np.ndarray], time: float) -> tuple[str, ...]:
    """The blend shapes that move a point of the region (at full weight, at `time`'s pose)."""
    if not rig.blend_shapes:
        return ()
    zero = np.zeros(len(rig.blend_shapes), np.float32)
    base = rig.posed_meshes(time, weights=zero)
    size = max(float(np.ptp(np.concatenate([m.points for m in base]), axis=0).max()), 1e-12)
    moving = []
    for k, name in enumerate(rig.blend_shapes):
        weights = zero.copy()
        weights[k] = 1.0
        posed = rig.posed_meshes(time, weights=weights)
        for rest, moved, inside in zip(base, posed, points, strict=True):
            shift = np.linalg.norm(moved.points[inside] - rest.points[inside], axis=1)
            if shift.size and float(shift.max()) > MOVED * size:
                moving.append(name)
                break
    return tuple(moving)


def region_settings(
    body: CaptureSettings, rig: CharacterRig, region: schema.Region, warn: Warn
) -> CaptureSettings:
    """The capture settings of `region`'s dataset from the body's (module doc); every bad
    value a CaptureError naming the attribute and the fix, before any work."""
    where = f"rigspace:region:{region.name}"
    joints = region_joints(rig, region)
    joint = joints[0] if not region.joints else schema.find_joint(region.joint, rig.joints)
    points = region_points(rig, joints)
    if not any(p.any() for p in points):
        names = ", ".join(rig.joints[j].rsplit("/", 1)[-1] for j in joints)
        raise CaptureError(
            f"Region {region.name!r}: no skinned point has its largest weight on {names}, so "
            "the region has no surface.",
            f"name the joints that move its surface ({where}:joints).",
        )
    _check_resolution_and_shapes(rig, region, where)
    resolution = region.resolution
    low, high = region.blend_shape_range
    shapes = region.blend_shapes or moving_shapes(rig, points, body.clips[0].first)
    reach = region_reach(rig, joint, points, body.clips)
    half = region.size / 2 if region.size > 0 else reach
    if not half > 0:
        raise CaptureError(
            f"{where}:size is {region.size:g}.", "author the region's side in scene units (> 0)."
        )
    radius = fit_radius(half, body.focal_length, body.horizontal_aperture)
    views, elevations = _region_rings(body, region, where)
    if shapes:
        warn(
            f"region {region.name}: the weights of {', '.join(shapes)} are drawn in every "
            f"frame apart from the animation, each at rest or within [{low:g}, {high:g}] (how "
            "many are at work uniform from none to all), so that its network learns each shape "
            "apart from the pose and the others"
        )
    return replace(
        body,
        look_at_joint=rig.joints[joint],
        radius=float(radius),
        resolution=int(resolution),
        views_per_ring=int(views),
        elevations=tuple(float(e) for e in elevations),
        held_out_views_per_ring=min(body.held_out_views_per_ring, int(views)),
        clipping_range=(NEAR_SHARE * radius, radius + FAR_REACHES * max(reach, half)),
        blend_draws=tuple(("*", s, float(low), float(high)) for s in shapes),
        region=region.name,
        region_joints=tuple(rig.joints[j] for j in joints),
        input_joints=input_joints(rig, joint, joints),
        input_shapes=tuple(s for s in rig.blend_shapes if s in shapes),
        upright_axis=_upright_axis(rig, joint, region, body),
    )


def _upright_axis(
    rig: CharacterRig, joint: int, region: schema.Region, body: CaptureSettings
) -> tuple[float, ...]:
    """The joint's local up that a region's cameras keep upright (`upright = "joint"`): the
    direction that is the stage's up in the skeleton's rest pose; () for the stage's own."""
    if region.upright == schema.UPRIGHT_STAGE:
        return ()
    rest_local = rig.rest_local()
    if not rest_local:
        raise CaptureError(
            f'rigspace:region:{region.name}:upright is "joint", but the skeleton has no '
            "restTransforms to find the joint's up in.",
            'author the skeleton\'s restTransforms, or set upright to "stage".',
        )
    rest = rig.world_transforms(body.clips[0].first, rest_local)[joint]
    up, _, _ = stage_axes(body.up_axis)
    return tuple(round(float(v), 9) for v in rest_up_axis(rest, up))


def _check_resolution_and_shapes(rig: CharacterRig, region: schema.Region, where: str) -> None:
    """The region's resolution is a power of two in range, its blendShapeRange a finite
    (low, high) and its blendShapes the character's (else CaptureError)."""
    resolution = region.resolution
    if resolution < MIN_RESOLUTION or resolution > MAX_RESOLUTION or resolution & (resolution - 1):
        raise CaptureError(
            f"{where}:resolution is {resolution}.",
            f"use a power of two from {MIN_RESOLUTION} to {MAX_RESOLUTION}.",
        )
    low, high = region.blend_shape_range
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise CaptureError(
            f"{where}:blendShapeRange is ({low:g}, {high:g}).",
            "author a finite (low, high) with low <= high, e.g. (0, 1).",
        )
    if region.upright not in schema.UPRIGHT_TOKENS:
        raise CaptureError(
            f"{where}:upright is {region.upright!r}.",
            f"use {' or '.join(repr(t) for t in schema.UPRIGHT_TOKENS)}.",
        )
    unknown = [s for s in region.blend_shapes if s not in rig.blend_shapes]
    if unknown:
        raise CaptureError(
            f"{where}:blendShapes names {', '.join(unknown)}, which the character's meshes do "
            f"not have (they have {', '.join(rig.blend_shapes) or 'none'}).",
            "name shapes of the skinned meshes' skel:blendShapes.",
        )


def _region_rings(
    body: CaptureSettings, region: schema.Region, where: str
) -> tuple[int, tuple[float, ...]]:
    """The region's views per ring and elevations, else the body's (CaptureError when out of
    range)."""
    views = region.views_per_ring or body.views_per_ring
    elevations = region.elevations or body.elevations
    if any(not -89 <= e <= 89 for e in elevations) or not 1 <= views <= 360:
        raise CaptureError(
            f"{where}: {views} views per ring at elevations {list(elevations)}.",
            "use 1-360 views and elevations within [-89, 89] degrees.",
        )
    return views, elevations

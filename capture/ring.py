"""The capture ring: where the dataset's cameras sit around the character, and which are held out.

Views sit on rings around the look-at joint, one ring per elevation, evenly spaced in
azimuth. Azimuth 0 is the stage's front: +Z for a Y-up stage, -Y for a Z-up stage (the
usual "character faces the camera" direction of each convention); azimuth grows
counter-clockwise seen from above. Held-out views sit halfway between training views,
and held-out elevations add whole rings for evaluation only. Cameras follow the joint by
translation only (`RingView.camera(joint_position)`), so the joint is always at the image
centre and every view keeps one fixed orientation, as the runtime's billboard expects.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigspace.sdk.camera import Camera
from rigspace.sdk.rotations import upright_usable

TRAIN = "train"
HELDOUT_VIEWS = "heldout-views"
HELDOUT_CLIPS = "heldout-clips"
SPLITS = (TRAIN, HELDOUT_VIEWS, HELDOUT_CLIPS)


@dataclass(frozen=True)
class Lens:
    """The ring's shared camera settings."""

    resolution: int
    focal_length: float
    """Tenths of a scene unit."""
    horizontal_aperture: float
    """Tenths of a scene unit; images are square."""
    near: float
    far: float


@dataclass(frozen=True)
class RingView:
    """One camera of the ring: a fixed direction from the look-at joint."""

    index: int
    """Position in the ring's view list (training views first, then held-out ones)."""
    elevation: float
    """Degrees above the horizontal plane through the joint."""
    azimuth: float
    """Degrees, 0 = the stage's front, counter-clockwise seen from above."""
    held_out: bool
    offset: np.ndarray
    """(3,) from the joint to the camera, scene units."""
    up: np.ndarray
    """(3,) the stage's up axis."""

    def camera(
        self, joint_position: np.ndarray, lens: Lens, up: np.ndarray | None = None
    ) -> Camera:
        """This view's camera for a joint at `joint_position` (world, scene units), upright
        to `up` (world; a region's joint's own up) or, without it or looking along it, to the
        stage's up axis."""
        joint = np.asarray(joint_position, dtype=np.float64)
        upright = self.up if up is None or not upright_usable(-self.offset, up) else up
        return Camera.look_at(
            joint + self.offset,
            joint,
            upright,
            width=lens.resolution,
            height=lens.resolution,
            focal_length=lens.focal_length,
            horizontal_aperture=lens.horizontal_aperture,
            near=lens.near,
            far=lens.far,
        )


def stage_axes(up_axis: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(up, front, side) unit vectors of a stage whose upAxis is "Y" or "Z"."""
    if up_axis == "Y":
        return np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    if up_axis == "Z":
        return np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    raise ValueError(f"upAxis must be 'Y' or 'Z', got {up_axis!r}")


def direction(azimuth_deg: float, elevation_deg: float, up_axis: str) -> np.ndarray:
    """Unit vector from the joint towards a camera at this azimuth and elevation."""
    up, front, side = stage_axes(up_axis)
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.cos(el) * (np.cos(az) * front + np.sin(az) * side) + np.sin(el) * up


def ring_views(
    views_per_ring: int,
    elevations: tuple[float, ...],
    radius: float,
    up_axis: str,
    held_out_views_per_ring: int = 0,
    held_out_elevations: tuple[float, ...] = (),
) -> list[RingView]:
    """Every view of the ring: training views, then held-out views, then held-out rings.

    Held-out views of a ring take every (views / held_out)-th midpoint between training
    views, so 12 views with 12 held out gives all 12 midpoints, with 4 held out every third.
    """
    up, _, _ = stage_axes(up_axis)
    step = 360.0 / views_per_ring
    planned: list[tuple[float, float, bool]] = []
    for elevation in elevations:
        planned += [(elevation, k * step, False) for k in range(views_per_ring)]
    for elevation in elevations:
        if held_out_views_per_ring:
            picks = np.linspace(0, views_per_ring, held_out_views_per_ring, endpoint=False)
            planned += [(elevation, (int(k) + 0.5) * step, True) for k in picks]
    for elevation in held_out_elevations:
        # Offset by half a step so these rings share no azimuth with the training views.
        planned += [(elevation, (k + 0.5) * step, True) for k in range(views_per_ring)]
    return [
        RingView(
            index=i,
            elevation=float(elevation),
            azimuth=float(azimuth),
            held_out=held_out,
            offset=radius * direction(azimuth, elevation, up_axis),
            up=up,
        )
        for i, (elevation, azimuth, held_out) in enumerate(planned)
    ]

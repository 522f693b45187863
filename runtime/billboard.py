"""Billboard placement (Borer et al. 2021, "Scene Composition"): where a character's maps go.

Training cameras looked straight at the look-at joint from a distance D with focal length
f and aperture A, so a training image shows a square of side L = D * A / f (scene units)
centred on the joint, perpendicular to the line of sight. At run time the same square is
placed at the joint, perpendicular to the ray from the render camera through the joint:

- the virtual camera that "took" the network's image is the render camera rotated by R,
  a rotation taking the camera's centre ray (-Z) to the ray through the joint (the paper's
  off-centre correction q^ = R q~): rig parameters are expressed in the frame C R, and
  predicted normals come back as R n. The paper's R is the minimal such rotation; it
  leaves the virtual camera rolled about the ray (by about 1 degree for a character 15
  degrees right and 10 up of centre), a roll the training ring (cameras upright, looking
  at the joint) never showed the network. Here R keeps the stage's up axis upright, as
  the ring did, and the roll goes into the billboard's corners instead (measured in
  docs/runtime.md: the off-centre loss halves);
- projecting the square's corners gives the exact homography from the network's image to
  the frame (a tilted plane is not a screen-space square off-centre);
- the plane's depth at each pixel is a ray-plane intersection; the network's depth offset
  along the virtual camera's axis adds its component along the render camera's -Z.
The on-screen size ratio s of the paper is implicit: the corners carry it, and depth
offsets are in scene units (scaled by the character's own world scale, if any).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigspace.sdk.camera import Camera
from rigspace.sdk.rotations import UPRIGHT_LIMIT

# Within UPRIGHT_LIMIT of looking along the up axis the upright virtual camera is undefined:
# R falls back to the minimal rotation (`upright_rotation` returns None).

MIN_DEPTH_FACTOR = 1.0
"""A joint closer than near * this (or behind the camera) cannot be drawn as a billboard."""


@dataclass(frozen=True)
class TrainingView:
    """The training cameras, from a bundle manifest's training_camera."""

    distance: float
    focal_length: float
    horizontal_aperture: float

    @property
    def side(self) -> float:
        """Side of the square the training image shows at the joint, scene units."""
        return self.distance * self.horizontal_aperture / self.focal_length


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross's generality costs 20 us a call)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The minimal rotation taking unit vector a onto unit vector b (Rodrigues)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = cross(a, b)
    c = float(np.dot(a, b))
    if c < -1 + 1e-12:  # opposite: any half turn about an axis perpendicular to a
        axis = cross(a, np.array([1.0, 0.0, 0.0]))
        if np.linalg.norm(axis) < 1e-6:
            axis = cross(a, np.array([0.0, 1.0, 0.0]))
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


@dataclass(frozen=True)
class Billboard:
    joint_camera: np.ndarray
    """(3,) the look-at joint in render-camera space."""
    rotation: np.ndarray
    """(3, 3) R: virtual-camera axes expressed in render-camera space."""
    corners: np.ndarray
    """(4, 2) image coordinates of the training image's corners: top-left, top-right,
    bottom-right, bottom-left (the training image's own row 0 at the top)."""
    side: float
    """Side of the square in scene units (training side times the character's scale)."""
    visible: bool
    """Whether the square overlaps the viewport (and lies in front of the camera)."""
    reason: str = ""

    @property
    def size_px(self) -> float:
        """The billboard's largest on-screen extent in pixels (picks the level of detail)."""
        span = self.corners.max(axis=0) - self.corners.min(axis=0)
        return float(span.max())

    def region(self, camera: Camera) -> tuple[int, int, int, int]:
        """(x0, y0, w, h): the frame pixels the billboard's square covers, clipped to the view."""
        lo = np.floor(self.corners.min(axis=0)).astype(int)
        hi = np.ceil(self.corners.max(axis=0)).astype(int)
        x0, y0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
        x1, y1 = min(int(hi[0]), camera.width), min(int(hi[1]), camera.height)
        return x0, y0, max(x1 - x0, 1), max(y1 - y0, 1)

    def virtual_camera_to_world(self, camera: Camera) -> np.ndarray:
        """(3, 3) rotation of the virtual training camera in world space (C R)."""
        return camera.camera_to_world[:3, :3] @ self.rotation

    def homography(self, resolution: int) -> np.ndarray:
        """3x3 map from the network's pixel coordinates (resolution^2) to frame pixels."""
        import cv2

        src = np.array(
            [[0, 0], [resolution, 0], [resolution, resolution], [0, resolution]], np.float32
        )
        return cv2.getPerspectiveTransform(src, self.corners.astype(np.float32))

    def plane_depth(
        self, camera: Camera, depth_offset: np.ndarray, origin: tuple[int, int] = (0, 0)
    ) -> np.ndarray:
        """Render-camera depth of pixels given the network's depth offset there.

        depth_offset (h, w) is in scene units along the virtual camera's viewing axis, already
        resampled into the frame; it covers the region whose top-left pixel is `origin`.
        """
        h, w = depth_offset.shape
        x0, y0 = origin
        x = (np.arange(w) + x0 + 0.5 - camera.cx) / camera.fx
        y = (camera.cy - np.arange(h) - y0 - 0.5) / camera.fy
        rays = np.stack(np.broadcast_arrays(x[None, :], y[:, None], -np.ones((h, w))), axis=-1)
        normal = -self.rotation[:, 2]  # the virtual camera's viewing direction
        # Ray r with r_z = -1 hits the plane n.(X - p) = 0 at X = t r, depth = t.
        plane = float(normal @ self.joint_camera) / np.maximum(rays @ normal, 1e-9)
        return (plane + depth_offset * (-normal[2])).astype(np.float32)


def upright_rotation(ray: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    """Axes (columns X, Y, Z) of a camera looking along `ray` with `up` upright, or None when
    the ray is (nearly) parallel to up. Both in the same frame."""
    forward = ray / np.linalg.norm(ray)
    right = cross(forward, up)
    norm = np.linalg.norm(right)
    if norm < UPRIGHT_LIMIT:
        return None
    right /= norm
    return np.stack([right, cross(right, forward), -forward], axis=-1)


def place(
    joint_world: np.ndarray,
    camera: Camera,
    view: TrainingView,
    scale: float = 1.0,
    up: np.ndarray | None = None,
    fallback_up: np.ndarray | None = None,
) -> Billboard:
    """The billboard of a character whose look-at joint is at `joint_world`.

    With `up` (world space: the stage's up axis, or a region's joint's own) the virtual
    camera keeps it upright, as the training ring's cameras did; looking along it,
    `fallback_up` (the stage's, as a region's ring fell back to: capture.ring.RingView.camera);
    without either, or looking along both, R is the minimal rotation from the centre ray (the
    paper's)."""
    p = camera.to_camera(np.asarray(joint_world, dtype=np.float64)[None])[0]
    side = view.side * scale
    if not -p[2] > camera.near * MIN_DEPTH_FACTOR:
        if -p[2] > 0:  # in front, but nearer than what the camera draws
            why = (
                f"nearer than the camera's near clipping plane ({camera.near:g} scene units; "
                f"the look-at joint is {-p[2]:.3g} away): author a smaller clippingRange on "
                "the camera (USD's fallback near plane is 1)"
            )
        else:
            why = "behind the camera"
        return Billboard(p, np.eye(3), np.zeros((4, 2)), side, False, why)
    if np.linalg.norm(p) < side / 2:
        # Within the character's extent: a flat image of it cannot stand in for it here.
        return Billboard(
            p, np.eye(3), np.zeros((4, 2)), side, False, "the camera is inside the billboard"
        )
    rotation = rotation_between(np.array([0.0, 0.0, -1.0]), p / np.linalg.norm(p))
    for axis in (up, fallback_up):
        if axis is not None:
            upright = upright_rotation(p, camera.world_to_camera[:3, :3] @ np.asarray(axis, float))
            if upright is not None:
                rotation = upright
                break
    right, up = rotation[:, 0], rotation[:, 1]
    half = side / 2
    corners_cam = np.stack(
        [p - half * right + half * up, p + half * right + half * up,
         p + half * right - half * up, p - half * right - half * up]
    )  # fmt: skip
    if np.any(-corners_cam[:, 2] <= camera.near):
        # The square reaches behind the near plane although the joint is more than half a side
        # away: seen edge-on, far off-centre (at 89 degrees off-axis, 1000 units away, say).
        return Billboard(
            p,
            rotation,
            np.zeros((4, 2)),
            side,
            False,
            f"the billboard crosses the camera's near clipping plane ({camera.near:g} scene "
            "units): author a smaller clippingRange on the camera",
        )
    xy = np.stack(
        [camera.cx + camera.fx * corners_cam[:, 0] / -corners_cam[:, 2],
         camera.cy - camera.fy * corners_cam[:, 1] / -corners_cam[:, 2]], axis=-1
    )  # fmt: skip
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    visible = bool(hi[0] > 0 and hi[1] > 0 and lo[0] < camera.width and lo[1] < camera.height)
    return Billboard(p, rotation, xy, side, visible, "" if visible else "outside the view")

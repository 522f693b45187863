"""The pinhole camera shared by capture and runtime: pose, lens, projection and rays."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from pxr import Gf, Usd, UsdGeom

from rigspace.sdk.errors import SceneError

# Conventions (DESIGN.md "Conventions"; docs/renderers.md spells them out with pictures in words):
# - Camera space is USD's: the camera looks down -Z, +Y is up, +X is right, right-handed.
# - numpy matrices are 4x4 float64 in the COLUMN-vector convention, p' = M @ p. USD's Gf matrices are
#   row-vector (p' = p * M), so `from_gf` / `to_gf` transpose.
# - Lens values are in tenths of a scene unit, as UsdGeomCamera stores them.
# - Image coordinates: x to the right, y DOWN, in pixels; pixel (row i, col j) covers
#   [j, j+1) x [i, i+1) and has its centre at (j + 0.5, i + 0.5); row 0 is the top of the image.
# - Projection: x = cx + fx * X / (-Z), y = cy - fy * Y / (-Z), cx = W/2, cy = H/2.

RIGID_TOLERANCE = 1e-5
"""How far camera_to_world's 3x3 block may be from a rotation (max abs entry of R^T R - I); a
float32 round trip of a rotation stays well inside it, a scale of 1.0001 does not."""

CV_FROM_USD = np.diag([1.0, -1.0, -1.0])
"""Camera-space axes of the computer-vision convention (x right, y down, z forward) from USD's."""


def from_gf(matrix) -> np.ndarray:
    """USD (row-vector) matrices, one or an array of them, as numpy float64 column-vector ones."""
    return np.swapaxes(np.asarray(matrix, dtype=np.float64), -1, -2).copy()


def to_gf(matrix: np.ndarray) -> Gf.Matrix4d:
    """A numpy 4x4 column-vector matrix as a USD (row-vector) Gf.Matrix4d."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"to_gf expects a 4x4 matrix, got shape {m.shape}.")
    return Gf.Matrix4d(m.T.tolist())


def _positive(name: str, value: Any) -> None:
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"Camera {name} must be a positive finite number, got {value!r}.")


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: USD pose and lens plus the image size in pixels."""

    camera_to_world: np.ndarray
    """(4,4) float64, column-vector convention; must be rigid (rotation + translation)."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    focal_length: float
    """Tenths of a scene unit (UsdGeomCamera focalLength)."""
    horizontal_aperture: float
    """Tenths of a scene unit (UsdGeomCamera horizontalAperture); spans the image width."""
    vertical_aperture: float | None = None
    """Tenths of a scene unit; None -> horizontal_aperture * height / width (square pixels)."""
    near: float = 0.1
    """Near clipping distance along -Z, scene units."""
    far: float = 1e4
    """Far clipping distance along -Z, scene units."""

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value <= 0:
                raise ValueError(
                    f"Camera {name} must be a positive whole number of pixels, got {value!r}."
                )
            object.__setattr__(self, name, int(value))
        _positive("focal_length", self.focal_length)
        _positive("horizontal_aperture", self.horizontal_aperture)
        if self.vertical_aperture is not None:
            _positive("vertical_aperture", self.vertical_aperture)
        _positive("near", self.near)
        _positive("far", self.far)
        if not self.near < self.far:
            raise ValueError(f"Camera near ({self.near}) must be less than far ({self.far}).")
        m = np.array(self.camera_to_world, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"Camera camera_to_world must be 4x4, got shape {m.shape}.")
        if not np.all(np.isfinite(m)):
            raise ValueError(f"Camera camera_to_world has non-finite entries:\n{m}")
        if not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), rtol=0.0, atol=RIGID_TOLERANCE):
            raise ValueError(
                f"Camera camera_to_world's last row must be (0, 0, 0, 1) (column-vector "
                f"convention; a USD matrix needs from_gf), got {m[3]}."
            )
        r = m[:3, :3]
        off = np.abs(r.T @ r - np.eye(3)).max()
        if off > RIGID_TOLERANCE or np.linalg.det(r) <= 0:
            raise ValueError(
                "Camera camera_to_world must be a rotation plus a translation (no scale, shear or "
                f"mirror); its 3x3 block is off by {off:.3g}. Camera.from_usd removes scale."
            )
        m.flags.writeable = False
        object.__setattr__(self, "camera_to_world", m)

    # --- pose ---------------------------------------------------------------------------------
    @property
    def world_to_camera(self) -> np.ndarray:
        """(4,4) float64 inverse of camera_to_world (exact for a rigid pose)."""
        r = self.camera_to_world[:3, :3]
        t = self.camera_to_world[:3, 3]
        m = np.eye(4)
        m[:3, :3] = r.T
        m[:3, 3] = -r.T @ t
        return m

    @property
    def position(self) -> np.ndarray:
        """(3,) camera centre in world space."""
        return self.camera_to_world[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit viewing direction in world space (the camera's -Z axis)."""
        return -self.camera_to_world[:3, 2].copy()

    # --- lens ---------------------------------------------------------------------------------
    @property
    def effective_vertical_aperture(self) -> float:
        """The vertical aperture in use: given, or the square-pixel horizontal fit."""
        if self.vertical_aperture is not None:
            return float(self.vertical_aperture)
        return self.horizontal_aperture * self.height / self.width

    @property
    def fx(self) -> float:
        """Horizontal focal length in pixels."""
        return self.focal_length / self.horizontal_aperture * self.width

    @property
    def fy(self) -> float:
        """Vertical focal length in pixels."""
        return self.focal_length / self.effective_vertical_aperture * self.height

    @property
    def cx(self) -> float:
        return self.width / 2.0

    @property
    def cy(self) -> float:
        return self.height / 2.0

    @property
    def intrinsics(self) -> np.ndarray:
        """(3,3) K in the computer-vision convention: (x, y, 1) ~ K @ CV_FROM_USD @ p_camera."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    K = intrinsics

    @property
    def gl_projection(self) -> np.ndarray:
        """(4,4) OpenGL clip matrix for camera-space points (column-vector convention).

        NDC x = 2 x_img / W - 1 and NDC y = 1 - 2 y_img / H (GL's window y is bottom-up, so a
        read-back image is flipped to put row 0 at the top); NDC z maps near..far to -1..1.
        """
        n, f = self.near, self.far
        return np.array(
            [
                [2.0 * self.fx / self.width, 0.0, 0.0, 0.0],
                [0.0, 2.0 * self.fy / self.height, 0.0, 0.0],
                [0.0, 0.0, -(f + n) / (f - n), -2.0 * f * n / (f - n)],
                [0.0, 0.0, -1.0, 0.0],
            ]
        )

    # --- projection and rays --------------------------------------------------------------------
    def to_camera(self, points_world: npt.ArrayLike) -> np.ndarray:
        """(N,3) world points in camera space (float64)."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        m = self.world_to_camera
        return p @ m[:3, :3].T + m[:3, 3]

    def project(self, points_world: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates (N,2) (x right, y down, pixels) and depth (N,) along -Z.

        Points with depth <= 0 (at or behind the camera plane) get NaN image coordinates.
        """
        pc = self.to_camera(points_world)
        depth = -pc[:, 2]
        ahead = depth > 0
        inv = np.divide(1.0, depth, out=np.full_like(depth, np.nan), where=ahead)
        xy = np.stack([self.cx + self.fx * pc[:, 0] * inv, self.cy - self.fy * pc[:, 1] * inv], 1)
        return xy, depth

    def sample_offsets(self, samples_per_axis: int) -> np.ndarray:
        """(s,) sub-pixel sample positions (k + 0.5) / s, shared by every renderer."""
        if int(samples_per_axis) != samples_per_axis or samples_per_axis < 1:
            raise ValueError(
                f"samples_per_axis must be a positive integer, got {samples_per_axis!r}."
            )
        s = int(samples_per_axis)
        return (np.arange(s) + 0.5) / s

    def rays(self, samples_per_axis: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """World-space ray origins and unit directions, (H*s * W*s, 3) float64 each.

        One ray per sub-sample, row-major over the supersampled image (row 0 = top): reshape to
        (H, s, W, s, 3), and [i, a, j, b] is pixel (i, j)'s sub-sample (a, b), which passes through
        image point (j + (b + 0.5) / s, i + (a + 0.5) / s).
        """
        s = int(samples_per_axis)
        off = self.sample_offsets(s)
        ys = (np.arange(self.height)[:, None] + off[None, :]).reshape(-1)  # (H*s,) image y
        xs = (np.arange(self.width)[:, None] + off[None, :]).reshape(-1)  # (W*s,) image x
        # Camera-space direction through image point (x, y) at -Z = 1: project() inverted.
        d = np.empty((len(ys), len(xs), 3))
        d[..., 0] = ((xs - self.cx) / self.fx)[None, :]
        d[..., 1] = ((self.cy - ys) / self.fy)[:, None]
        d[..., 2] = -1.0
        flat = d.reshape(-1, 3)
        flat /= np.linalg.norm(flat, axis=1, keepdims=True)
        dirs = flat @ self.camera_to_world[:3, :3].T
        origins = np.broadcast_to(self.camera_to_world[:3, 3], dirs.shape)
        return origins, dirs

    # --- construction -------------------------------------------------------------------------
    @classmethod
    def look_at(
        cls,
        eye: npt.ArrayLike,
        target: npt.ArrayLike,
        up: npt.ArrayLike = (0.0, 1.0, 0.0),
        *,
        width: int,
        height: int,
        focal_length: float,
        horizontal_aperture: float,
        vertical_aperture: float | None = None,
        near: float = 0.1,
        far: float = 1e4,
    ) -> Camera:
        """A camera at `eye` whose -Z axis points at `target`, with +Y as close to `up` as possible."""
        eye = np.asarray(eye, dtype=np.float64)
        back = eye - np.asarray(target, dtype=np.float64)  # camera +Z points away from the target
        length = np.linalg.norm(back)
        if not length > 0:
            raise ValueError(f"Camera.look_at: eye and target are the same point {eye}.")
        z = back / length
        x = np.cross(np.asarray(up, dtype=np.float64), z)
        if not np.linalg.norm(x) > RIGID_TOLERANCE:
            raise ValueError(
                f"Camera.look_at: up {tuple(np.asarray(up).tolist())} is parallel to the "
                "viewing direction."
            )
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
        return cls(
            m, width, height, focal_length, horizontal_aperture, vertical_aperture, near, far
        )

    @classmethod
    def from_usd(
        cls,
        camera: UsdGeom.Camera | Usd.Prim,
        time: float | Usd.TimeCode | None,
        width: int,
        height: int,
        *,
        square_pixels: bool = True,
    ) -> Camera:
        """The camera of a UsdGeom.Camera prim at `time` (None: the default time), width x height.

        Pose from ComputeLocalToWorldTransform (any scale in the prim's ancestry is removed, so
        depth stays in scene units); lens and clipping range from GetCamera(time). With
        `square_pixels` (default) the horizontal aperture spans the image width and the vertical
        extent follows from the image aspect; otherwise the authored verticalAperture is used.
        """
        cam = UsdGeom.Camera(camera)
        if not cam:
            path = camera.GetPath() if hasattr(camera, "GetPath") else camera
            raise SceneError(f"{path} is not a UsdGeom.Camera.", "name a Camera prim.")
        path = cam.GetPath()
        time = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
        gf_cam = cam.GetCamera(time)
        if gf_cam.projection != Gf.Camera.Perspective:
            raise SceneError(
                f"Camera {path} is orthographic; rigspace renders perspective cameras only.",
                f'set {path}.projection to "perspective".',
            )
        if gf_cam.horizontalApertureOffset != 0 or gf_cam.verticalApertureOffset != 0:
            raise SceneError(
                f"Camera {path} has an aperture offset ({gf_cam.horizontalApertureOffset}, "
                f"{gf_cam.verticalApertureOffset}); rigspace cameras are centred.",
                "set horizontalApertureOffset and verticalApertureOffset to 0.",
            )
        m = from_gf(cam.ComputeLocalToWorldTransform(time))
        # USD allows scale on a camera's xform; strip it so camera space stays in scene units.
        scale = np.linalg.norm(m[:3, :3], axis=0)
        if np.any(scale <= 0) or not np.all(np.isfinite(m)):
            raise SceneError(f"Camera {path} has a degenerate transform.", "fix its xformOps.")
        m[:3, :3] /= scale
        clip = gf_cam.clippingRange
        return cls(
            m,
            width,
            height,
            float(gf_cam.focalLength),
            float(gf_cam.horizontalAperture),
            None if square_pixels else float(gf_cam.verticalAperture),
            float(clip.min),
            float(clip.max),
        )

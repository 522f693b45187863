"""Deferred shading of camera-space G-buffers: Lambert diffuse plus Blinn-Phong specular.

The same function lights the neural character's maps and the scene prims' maps, so the
two match. Game-engine convention: diffuse = albedo * sum(radiance * max(0, n.l)), no
1/pi; specular = SPECULAR * (n.h)^SHININESS * radiance * max(0, n.l); ambient (DomeLight)
= albedo * radiance. Albedo is premultiplied by coverage, and so is the result.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rigspace.runtime.lights import AMBIENT, DISTANT, POINT, Light
from rigspace.sdk.camera import Camera

SPECULAR = 0.04
"""Specular reflectance at normal incidence: the usual 4% of dielectrics (skin, cloth, paint)."""
SHININESS = 32.0
"""Blinn-Phong exponent: a soft highlight, neither matte nor glossy."""
MIN_DISTANCE = 1e-6
"""Guards the inverse-square falloff of a point light sitting on a surface (scene units)."""


def camera_positions(
    depth: np.ndarray, camera: Camera, origin: tuple[int, int] = (0, 0)
) -> np.ndarray:
    """(H, W, 3) camera-space points of each pixel centre at its depth (0 where empty).

    `origin` (x0, y0) places a region's pixel (0, 0) at that pixel of the camera's image.
    """
    h, w = depth.shape
    x0, y0 = origin
    x = (np.arange(w, dtype=np.float32) + x0 + 0.5 - camera.cx) / camera.fx
    y = (camera.cy - np.arange(h, dtype=np.float32) - y0 - 0.5) / camera.fy
    d = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    return np.stack([x[None, :] * d, y[:, None] * d, -d], axis=-1)


def shade(
    albedo: np.ndarray,
    normal: np.ndarray,
    depth: np.ndarray,
    mask: np.ndarray,
    camera: Camera,
    lights: Sequence[Light],
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Lit, premultiplied colour (H, W, 3) of a G-buffer in `camera`'s space.

    The G-buffer may be a region of the camera's image whose top-left pixel is `origin`.
    Only covered pixels are shaded (empty ones are black: premultiplied albedo is 0 there),
    which halves the cost of a frame whose sky is empty.
    """
    out = np.zeros(albedo.shape, dtype=np.float32)
    covered = mask > 0
    if covered.any():
        position = camera_positions(depth, camera, origin)[covered]
        out[covered] = shade_pixels(
            albedo[covered],
            normal[covered],
            position,
            mask[covered],
            camera.world_to_camera,
            lights,
        )
    return out


def shade_pixels(
    albedo: np.ndarray,
    normal: np.ndarray,
    position: np.ndarray,
    mask: np.ndarray,
    world_to_camera: np.ndarray,
    lights: Sequence[Light],
) -> np.ndarray:
    """The shading of pixels given as (..., 3) arrays: camera-space position, normal, albedo."""
    rotation = world_to_camera[:3, :3]
    view = -position / np.maximum(np.linalg.norm(position, axis=-1, keepdims=True), MIN_DISTANCE)
    n = normal.astype(np.float32)
    diffuse = np.zeros(albedo.shape, dtype=np.float32)
    specular = np.zeros(albedo.shape, dtype=np.float32)
    for light in lights:
        radiance = light.radiance.astype(np.float32)
        if light.kind == AMBIENT:
            diffuse += radiance
            continue
        if light.kind == DISTANT:
            to_light = np.broadcast_to(-(rotation @ light.direction).astype(np.float32), n.shape)
            irradiance = np.broadcast_to(radiance, n.shape)
        elif light.kind == POINT:
            offset = (rotation @ light.position + world_to_camera[:3, 3]).astype(
                np.float32
            ) - position
            distance = np.maximum(np.linalg.norm(offset, axis=-1, keepdims=True), MIN_DISTANCE)
            to_light = offset / distance
            irradiance = radiance * (light.area / distance**2)
        else:
            raise ValueError(f"unknown light kind {light.kind!r}")
        cosine = np.maximum(np.sum(n * to_light, axis=-1, keepdims=True), 0.0)
        diffuse += irradiance * cosine
        half = to_light + view
        half /= np.maximum(np.linalg.norm(half, axis=-1, keepdims=True), MIN_DISTANCE)
        highlight = np.maximum(np.sum(n * half, axis=-1, keepdims=True), 0.0) ** SHININESS
        specular += irradiance * cosine * highlight
    coverage = mask[..., None].astype(np.float32)
    return (albedo * diffuse + SPECULAR * specular * coverage).astype(np.float32)

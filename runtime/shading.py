"""Deferred shading of camera-space G-buffers: Lambert diffuse plus Blinn-Phong specular.

The same function lights the neural character's maps and the scene prims' maps, so the
two match. Game-engine convention: diffuse = albedo * sum(radiance * max(0, n.l)), no
1/pi; specular = SPECULAR * (n.h)^SHININESS * radiance * max(0, n.l); ambient (DomeLight)
= albedo * radiance. Albedo is premultiplied by coverage, and so is the result. A light's
shadow (runtime/shadows/__init__.py) scales its diffuse and specular terms, never the ambient one.
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


def pixel_positions(
    depth: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    camera: Camera,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """(N, 3) camera-space points of the pixel centres (rows, cols) at `depth` (0 if not finite)."""
    d = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    x = (cols.astype(np.float32) + np.float32(origin[0] + 0.5 - camera.cx)) / np.float32(camera.fx)
    y = (np.float32(camera.cy - origin[1] - 0.5) - rows.astype(np.float32)) / np.float32(camera.fy)
    return np.stack([x * d, y * d, -d], axis=-1)


def shade(
    albedo: np.ndarray,
    normal: np.ndarray,
    depth: np.ndarray,
    mask: np.ndarray,
    camera: Camera,
    lights: Sequence[Light],
    origin: tuple[int, int] = (0, 0),
    visibility: Sequence[np.ndarray | None] | None = None,
) -> np.ndarray:
    """Lit, premultiplied colour (H, W, 3) of a G-buffer in `camera`'s space.

    The G-buffer may be a region of the camera's image whose top-left pixel is `origin`.
    Only covered pixels are shaded (empty ones are black: premultiplied albedo is 0 there),
    which halves the cost of a frame whose sky is empty. `visibility`, per light, is None
    (unshadowed) or its (H, W) shadow factor in [0, 1].
    """
    out = np.zeros(albedo.shape, dtype=np.float32)
    covered = np.flatnonzero(mask > 0)  # flat indices: one take per array, not a 2-D gather
    if covered.size:
        rows, cols = np.divmod(covered, mask.shape[1])
        out.reshape(-1, 3)[covered] = shade_pixels(
            albedo.reshape(-1, 3)[covered],
            normal.reshape(-1, 3)[covered],
            pixel_positions(depth.reshape(-1)[covered], rows, cols, camera, origin),
            mask.reshape(-1)[covered],
            camera.world_to_camera,
            lights,
            None
            if visibility is None
            else [None if v is None else v.reshape(-1)[covered] for v in visibility],
        )
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products of planar (3, N) vectors, (N,): three contiguous multiply-adds, several
    times faster than a reduction over the short last axis of (N, 3) arrays."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _power(x: np.ndarray, exponent: float) -> np.ndarray:
    """x ** exponent; by repeated squaring for a power of two (32: five multiplies, several
    times faster than np.power)."""
    if exponent >= 1 and float(exponent).is_integer() and int(exponent).bit_count() == 1:
        for _ in range(int(exponent).bit_length() - 1):
            x = x * x
        return x
    return x**exponent


def shade_pixels(
    albedo: np.ndarray,
    normal: np.ndarray,
    position: np.ndarray,
    mask: np.ndarray,
    world_to_camera: np.ndarray,
    lights: Sequence[Light],
    visibility: Sequence[np.ndarray | None] | None = None,
) -> np.ndarray:
    """The shading of pixels given as (..., 3) arrays: camera-space position, normal, albedo;
    `mask` (...) their coverage; `visibility` per light None or its shadow factor (...).
    Works on planar (3, N) copies of the vectors."""
    shape = np.shape(albedo)
    rotation = world_to_camera[:3, :3]
    p = np.ascontiguousarray(np.reshape(position, (-1, 3)).T, dtype=np.float32)
    n = np.ascontiguousarray(np.reshape(normal, (-1, 3)).T, dtype=np.float32)
    view = p * (-1.0 / np.maximum(np.sqrt(_dot(p, p)), MIN_DISTANCE))
    diffuse = np.zeros(p.shape, dtype=np.float32)  # per channel, planar
    specular = np.zeros(p.shape, dtype=np.float32)
    for index, light in enumerate(lights):
        radiance = light.radiance.astype(np.float32)[:, None]
        if light.kind == AMBIENT:
            diffuse += radiance
            continue
        if light.kind == DISTANT:
            direction = -(rotation @ light.direction).astype(np.float32)
            strength = np.maximum(direction @ n, 0.0)  # one matrix-vector product
            half = view + direction[:, None]
        elif light.kind == POINT:
            to_light = (rotation @ light.position + world_to_camera[:3, 3]).astype(np.float32)
            to_light = to_light[:, None] - p
            distance2 = np.maximum(_dot(to_light, to_light), MIN_DISTANCE**2)
            to_light *= 1.0 / np.sqrt(distance2)
            strength = np.maximum(_dot(n, to_light), 0.0) * (light.area / distance2)
            half = to_light
            half += view
        else:
            raise ValueError(f"unknown light kind {light.kind!r}")
        shadow = None if visibility is None else visibility[index]
        if shadow is not None:
            strength = strength * np.reshape(shadow, -1).astype(np.float32)
        diffuse += radiance * strength
        half *= 1.0 / np.maximum(np.sqrt(_dot(half, half)), MIN_DISTANCE)
        highlight = _power(np.maximum(_dot(n, half), 0.0), SHININESS)
        specular += radiance * (strength * highlight)
    coverage = np.reshape(mask, -1).astype(np.float32)
    lit = np.reshape(albedo, (-1, 3)).T * diffuse + (SPECULAR * coverage) * specular
    return np.ascontiguousarray(lit.T, dtype=np.float32).reshape(shape)


def light_uniforms(
    lights: Sequence[Light], camera: Camera
) -> list[tuple[int, np.ndarray, np.ndarray, float]]:
    """Per light, (kind, radiance, camera-space vector, area) as the compiled kernel and the
    fragment shader read them: kind 0 ambient, 1 distant, 2 point; the direction towards a
    DistantLight, a point light's position (as shade_pixels computes them)."""
    rotation = camera.world_to_camera[:3, :3]
    out = []
    for light in lights:
        if light.kind == AMBIENT:
            out.append((0, light.radiance, np.zeros(3), 0.0))
        elif light.kind == DISTANT:
            towards = -(rotation @ light.direction).astype(np.float32)
            out.append((1, light.radiance, towards, 0.0))
        elif light.kind == POINT:
            position = (rotation @ light.position + camera.world_to_camera[:3, 3]).astype(
                np.float32
            )
            out.append((2, light.radiance, position, float(light.area)))
        else:
            raise ValueError(f"unknown light kind {light.kind!r}")
    return out


def shadow_layers(
    visibility: Sequence[np.ndarray | None] | None, count: int
) -> tuple[list[np.ndarray], np.ndarray]:
    """The shadowed lights' factors as layers, for the compiled kernel and the fragment
    shader: the arrays given (in light order), and per each of `count` lights its layer among
    them, -1 for an unshadowed one."""
    stacked: list[np.ndarray] = []
    layers = np.full(count, -1, np.int64)
    for index, factor in enumerate(visibility or ()):
        if factor is not None:
            layers[index] = len(stacked)
            stacked.append(factor)
    return stacked, layers

"""runtime/shading.shade compiled with numba: the same Lambert plus Blinn-Phong, one covered
pixel at a time with every light in one loop (numpy makes a dozen planar temporaries per
light). The engine's lighting on a machine without a GPU; shading.shade stays the reference
it is tested against (within 1e-5 of the brightest pixel: this computes in float64 and
rounds once). Compiled on first use and cached on disk (cache=True)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba as nb
import numpy as np

from rigspace.runtime.lights import Light
from rigspace.runtime.shading import (
    MIN_DISTANCE,
    SHININESS,
    SPECULAR,
    light_uniforms,
    shadow_layers,
)
from rigspace.sdk.camera import Camera

_NO_SHADOW = np.ones((0, 0, 0), np.float32)


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
    """shading.shade's lit, premultiplied colour (H, W, 3), by the compiled kernel."""
    h, w = mask.shape
    out = np.zeros((h, w, 3), np.float32)
    if not lights or h == 0 or w == 0:
        return out
    uniforms = light_uniforms(lights, camera)
    kinds = np.array([u[0] for u in uniforms], np.int64)
    radiance = np.array([u[1] for u in uniforms], np.float64).reshape(-1, 3)
    vectors = np.array([u[2] for u in uniforms], np.float64).reshape(-1, 3)
    areas = np.array([u[3] for u in uniforms], np.float64)
    stacked, layers = shadow_layers(visibility, len(lights))
    shadows = np.ascontiguousarray(np.stack(stacked), np.float32) if stacked else _NO_SHADOW
    lens = np.array([camera.fx, camera.fy, camera.cx, camera.cy], np.float64)
    shade_region(
        np.ascontiguousarray(albedo, np.float32), np.ascontiguousarray(normal, np.float32),
        np.ascontiguousarray(depth, np.float32), np.ascontiguousarray(mask, np.float32),
        lens, float(origin[0]), float(origin[1]), kinds, radiance, vectors, areas, layers,
        shadows, float(SPECULAR), float(SHININESS), _squarings(SHININESS), float(MIN_DISTANCE),
        out,
    )  # fmt: skip
    return out


def _squarings(exponent: float) -> int:
    """How many squarings raise to `exponent` (a power of two), else -1."""
    whole = int(exponent)
    if exponent != whole or whole < 1 or whole.bit_count() != 1:
        return -1
    return whole.bit_length() - 1


@nb.njit(cache=True, nogil=True)
def shade_region(
    albedo, normal, depth, mask, lens, x0, y0, kinds, radiance, vectors, areas, layers,
    shadows, specular, shininess, squarings, min_distance, out,
):  # fmt: skip
    """Shade every covered pixel of a region into `out` (see shading.shade_pixels for the
    terms); `kinds` 0 ambient, 1 distant (vector: towards it), 2 point (vector: its
    position), all in camera space; `layers` per light its visibility in `shadows`, -1 none."""
    fx, fy, cx, cy = lens[0], lens[1], lens[2], lens[3]
    h, w = mask.shape
    for i in range(h):
        for j in range(w):
            coverage = mask[i, j]
            if not coverage > 0.0:
                continue
            d = depth[i, j]
            if not math.isfinite(d):
                d = 0.0
            px = (j + x0 + 0.5 - cx) / fx * d
            py = (cy - y0 - 0.5 - i) / fy * d
            pz = -d
            length = max(math.sqrt(px * px + py * py + pz * pz), min_distance)
            vx, vy, vz = -px / length, -py / length, -pz / length
            nx, ny, nz = normal[i, j, 0], normal[i, j, 1], normal[i, j, 2]
            dr = dg = db = 0.0
            sr = sg = sb = 0.0
            for k in range(len(kinds)):
                if kinds[k] == 0:
                    dr += radiance[k, 0]
                    dg += radiance[k, 1]
                    db += radiance[k, 2]
                    continue
                if kinds[k] == 1:
                    lx, ly, lz = vectors[k, 0], vectors[k, 1], vectors[k, 2]
                    strength = max(lx * nx + ly * ny + lz * nz, 0.0)
                else:
                    lx, ly, lz = vectors[k, 0] - px, vectors[k, 1] - py, vectors[k, 2] - pz
                    distance2 = max(lx * lx + ly * ly + lz * lz, min_distance * min_distance)
                    inverse = 1.0 / math.sqrt(distance2)
                    lx, ly, lz = lx * inverse, ly * inverse, lz * inverse
                    strength = max(nx * lx + ny * ly + nz * lz, 0.0) * (areas[k] / distance2)
                if layers[k] >= 0:
                    strength *= shadows[layers[k], i, j]
                dr += radiance[k, 0] * strength
                dg += radiance[k, 1] * strength
                db += radiance[k, 2] * strength
                hx, hy, hz = vx + lx, vy + ly, vz + lz
                norm = max(math.sqrt(hx * hx + hy * hy + hz * hz), min_distance)
                highlight = max((nx * hx + ny * hy + nz * hz) / norm, 0.0)
                if squarings >= 0:  # a power of two: repeated squaring, not pow (4x faster)
                    for _ in range(squarings):
                        highlight *= highlight
                else:
                    highlight = highlight**shininess
                sr += radiance[k, 0] * strength * highlight
                sg += radiance[k, 1] * strength * highlight
                sb += radiance[k, 2] * strength * highlight
            scale = specular * coverage
            out[i, j, 0] = albedo[i, j, 0] * dr + scale * sr
            out[i, j, 1] = albedo[i, j, 1] * dg + scale * sg
            out[i, j, 2] = albedo[i, j, 2] * db + scale * sb

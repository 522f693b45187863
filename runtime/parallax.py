"""Parallax: a network's maps re-seen from the render camera's distance (docs/runtime.md,
"Parallax").

A network's image is a perspective view of its look-at joint from its training distance D: a
surface point at depth offset z from the joint's plane (along the line of sight, positive
away from the camera) and at lateral offset x on it shows at x D / (D + z) from the image's
centre. The billboard (runtime/billboard.py) lays that image on the plane at the joint as the
render camera sees it, from its own distance D' to the joint, where the same point shows at
x D' / (D' + z). So each point belongs at

    s = (D + z) / D * D' / (D' + z)

times its distance from the centre: a face 10 cm before a head joint captured from 83 cm
and seen from 3.3 m is drawn 9 % too far from the joint without it, 1.5 of its 64 network
pixels at the hairline (measured on the film character, samples/film_character/README.md).
`reseen` moves every map's pixels so, before the billboard's warp: the network's own depth
gives z, per pixel (the maps' inverse map found by a fixed point, since s is read where the
point lands). Where the render camera is at the training distance nothing moves.
"""

from __future__ import annotations

import math

import cv2
import numba as nb
import numpy as np

STEPS = 4
"""Fixed-point steps of the inverse map p = c + (q - c) / s(p): s changes by a few percent
across the image, so each step divides the error by about twenty."""
STILL_PX = 0.02
"""Network pixels: a largest move below this at the image's edge leaves the maps as they are."""
FILL_PX = 0.5
"""Network pixels: the blur that carries the depth offset out of the mask, so that the
silhouette's fringe moves with the surface beside it (wider blurs measured worse on the film
face: 0.5 px 20.72 dB, 1 px 20.52, 4 px 19.88)."""


def parallax_factors(
    depth: np.ndarray, mask: np.ndarray, distance: float, seen_from: float
) -> np.ndarray:
    """(R, R) float32 s per network pixel: its depth offset `depth` (R, R, scene units along
    the line of sight, positive away) seen from `seen_from` instead of the training
    `distance`; outside `mask` (R, R coverage) the offset of the surface nearby (a normalised
    blur), 0 far from it."""
    m = np.clip(np.asarray(mask, np.float32), 0.0, 1.0)
    z = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    weight = cv2.GaussianBlur(m, (0, 0), FILL_PX)
    nearby = cv2.GaussianBlur(z * m, (0, 0), FILL_PX) / np.maximum(weight, 1e-6)
    z = m * z + (1.0 - m) * np.where(weight > 1e-3, nearby, 0.0)
    # A point at or behind the camera (D' + z <= 0) is not drawable; keep it where it is.
    eye = np.float32(1e-3 * seen_from)
    return ((distance + z) / distance * seen_from / np.maximum(seen_from + z, eye)).astype(
        np.float32
    )


def reseen(
    out: dict[str, np.ndarray], distance: float, seen_from: float, depth_to_world: float
) -> dict[str, np.ndarray]:
    """One sample's network maps (`out`: name -> (1, C, R, R)) as the training camera would
    have drawn them from `seen_from` instead of `distance` (scene units; the module's s per
    pixel, from the geometry branch's `depth` times `depth_to_world` and its `mask`). Maps
    without "depth" and "mask" (the unlit mode), or whose largest move is under STILL_PX,
    come back as they are (the same dict)."""
    if "depth" not in out or "mask" not in out or not distance > 0 or not seen_from > 0:
        return out
    depth = out["depth"][0, 0] * np.float32(depth_to_world)
    s = parallax_factors(depth, out["mask"][0, 0], distance, seen_from)
    r = s.shape[0]
    centre = r / 2 - 0.5  # OpenCV's pixel centres sit at integers
    if float(np.abs(s - 1.0).max()) * r / 2 < STILL_PX:
        return out
    qy, qx = np.mgrid[0:r, 0:r].astype(np.float32)
    px, py = qx, qy
    for _ in range(STEPS):
        at = cv2.remap(s, px, py, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        px = centre + (qx - centre) / at
        py = centre + (qy - centre) / at
    px, py = np.ascontiguousarray(px), np.ascontiguousarray(py)
    mask = np.ascontiguousarray(out["mask"][0], np.float32)
    moved_mask = np.zeros_like(mask)
    gather_bilinear(
        mask, np.arange(r * r, dtype=np.int64), *bilinear_taps(px, py, None), moved_mask
    )
    # The other maps only matter where the moved coverage is, and a pixel beyond (the warp's
    # bilinear taps); elsewhere (two thirds of a body's square, whose 256 chart and texture
    # channels dominate the cost) they are 0, as beyond the network's image.
    near = cv2.dilate((moved_mask[0] > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
    pixels = np.flatnonzero(near).astype(np.int64)
    index, weight = bilinear_taps(px, py, pixels)  # once for every map
    moved = {"mask": moved_mask[None].astype(out["mask"].dtype, copy=False)}
    for name, value in out.items():
        if name != "mask":
            target = np.zeros(value.shape[1:], np.float32)
            source = np.ascontiguousarray(value[0], np.float32)
            gather_bilinear(source, pixels, index, weight, target)
            moved[name] = target[None].astype(value.dtype, copy=False)
    return moved


def bilinear_taps(
    px: np.ndarray, py: np.ndarray, pixels: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """The four bilinear taps (flat index, weight; 0 outside the image) of each flat pixel of
    `pixels` (None: every pixel) read at (px, py) (R, R, OpenCV's pixel centres at
    integers): computed once a frame and shared by every map's gather_bilinear."""
    if pixels is None:
        pixels = np.arange(px.size, dtype=np.int64)
    return _taps(np.ascontiguousarray(px, np.float32), np.ascontiguousarray(py, np.float32), pixels)


@nb.njit(cache=True, nogil=True)
def _taps(px, py, pixels):  # pragma: no cover - compiled
    h, w = px.shape
    count = pixels.shape[0]
    index = np.empty(4 * count, np.int64)
    weight = np.empty(4 * count, np.float32)
    flat_x, flat_y = px.reshape(-1), py.reshape(-1)
    for i in range(count):
        k = 4 * i
        fx, fy = flat_x[pixels[i]], flat_y[pixels[i]]
        x0, y0 = math.floor(fx), math.floor(fy)
        ax, ay = fx - x0, fy - y0
        for t in range(4):
            xi = x0 + (t & 1)
            yi = y0 + (t >> 1)
            wx = ax if t & 1 else 1.0 - ax
            wy = ay if t >> 1 else 1.0 - ay
            inside = 0 <= xi < w and 0 <= yi < h
            index[k + t] = yi * w + xi if inside else 0
            weight[k + t] = wx * wy if inside else 0.0
    return index, weight


@nb.njit(cache=True, nogil=True)
def gather_bilinear(source, pixels, index, weight, target):  # pragma: no cover - compiled
    """target[c].flat[p] = source[c] read through the taps (bilinear_taps) of each flat index
    p of `pixels`; the other pixels of `target` are left as they are. Every channel of a
    (C, R, R) map, plane by plane (cv2.remap in its (R, R, C) layout took 43 ms for a 128x128
    body's 256 channels, mostly in transposes; this about 8 on a busy machine)."""
    channels, h, w = source.shape
    count = pixels.shape[0]
    flat_source = source.reshape(channels, h * w)
    flat_target = target.reshape(channels, h * w)
    for c in range(channels):
        plane = flat_source[c]
        out = flat_target[c]
        for i in range(count):
            k = 4 * i
            out[pixels[i]] = (
                weight[k] * plane[index[k]]
                + weight[k + 1] * plane[index[k + 1]]
                + weight[k + 2] * plane[index[k + 2]]
                + weight[k + 3] * plane[index[k + 3]]
            )

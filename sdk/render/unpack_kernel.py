"""The gl renderer's read-back at one sample per pixel unpacked in one compiled pass:
maps_from_samples' s == 1 rules (tested equal to them) over the RGBA attachments as read,
rows bottom-up, without numpy's strided temporaries (1.0 against 0.15 ms at 256x256)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def unpack(fine_albedo, fine_geometry, albedo, normal, depth, mask):
    """(H, W, 4) albedo-and-hit and normal-and-depth attachments, GL's row 0 at the bottom,
    into (H, W, 3) albedo, (H, W, 3) normal (0 off the prims), (H, W) depth (inf off the
    prims) and (H, W) mask, row 0 at the top."""
    h, w = mask.shape
    for i in range(h):
        r = h - 1 - i
        for j in range(w):
            hit = fine_albedo[r, j, 3] > 0
            mask[i, j] = 1.0 if hit else 0.0
            for c in range(3):
                albedo[i, j, c] = fine_albedo[r, j, c]
                normal[i, j, c] = fine_geometry[r, j, c] if hit else 0.0
            depth[i, j] = fine_geometry[r, j, 3] if hit else np.inf


@nb.njit(cache=True, nogil=True)
def unpack_surface(fine_surface, fine_albedo, uv, chart):
    """The charted attachment's (H, W, 2) uv and (H, W) chart, 0 off a chart or the prims."""
    h, w = chart.shape
    for i in range(h):
        r = h - 1 - i
        for j in range(w):
            k = np.int32(np.rint(fine_surface[r, j, 2])) if fine_albedo[r, j, 3] > 0 else 0
            chart[i, j] = k
            for c in range(2):
                uv[i, j, c] = fine_surface[r, j, c] if k > 0 else 0.0

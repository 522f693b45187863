"""The texture sampler compiled with numba: rigspace.sdk.texturing's sample_region_reference,
one pixel at a time, fused into one loop (no temporaries; about a microsecond per pixel in
numpy, tens of nanoseconds here). Compiled on first use and cached on disk (cache=True)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, inline="always")
def _fold(x, mode):
    """Mirror wrap folds a coordinate into [0, 1]; the other modes leave it."""
    if mode != 1:
        return x
    m = x - 2.0 * math.floor(x / 2.0)
    return 2.0 - m if m > 1.0 else m


@nb.njit(cache=True, inline="always")
def _index(i, n, mode):
    """Repeat takes texel indices modulo n; every other mode clamps to the edge."""
    if mode == 0:
        return i % n
    return min(max(i, 0), n - 1)


@nb.njit(cache=True)
def _bilinear(texels, levels, image, level, s, t, wrap_s, wrap_t, rgb):
    """Bilinear read of one mip level at texture coordinates (s, t), as the renderers do."""
    offset, width, height = (
        levels[image, level, 0],
        levels[image, level, 1],
        levels[image, level, 2],
    )
    if (wrap_s == 3 and (s < 0.0 or s > 1.0)) or (wrap_t == 3 and (t < 0.0 or t > 1.0)):
        rgb[0] = rgb[1] = rgb[2] = 0.0
        return
    x = _fold(s, wrap_s) * width - 0.5
    y = _fold(t, wrap_t) * height - 0.5
    xf, yf = math.floor(x), math.floor(y)
    fx, fy = x - xf, y - yf
    c0, c1 = _index(int(xf), width, wrap_s), _index(int(xf) + 1, width, wrap_s)
    r0 = height - 1 - _index(int(yf), height, wrap_t)
    r1 = height - 1 - _index(int(yf) + 1, height, wrap_t)
    for c in range(3):
        a = (
            texels[offset + r0 * width + c0, c] * (1 - fx)
            + texels[offset + r0 * width + c1, c] * fx
        )
        b = (
            texels[offset + r1 * width + c0, c] * (1 - fx)
            + texels[offset + r1 * width + c1, c] * fx
        )
        rgb[c] = a * (1 - fy) + b * fy


@nb.njit(cache=True, inline="always")
def _argmax(probabilities, i, j):
    """The index of the largest of probabilities[:, i, j], the first of equal ones."""
    k, value = 0, probabilities[0, i, j]
    for c in range(1, probabilities.shape[0]):
        if probabilities[c, i, j] > value:
            k, value = c, probabilities[c, i, j]
    return k


@nb.njit(cache=True, nogil=True)
def sample_region(
    inverse, x0, y0, coverage, best, probabilities, coordinates, threshold, lod_bias, max_taps,
    minor_taps, center, half, image, transform, wrap, bounds, texels, levels, level_count, out, used, st_out,
    chart_out,
):  # fmt: skip
    """See rigspace.sdk.texturing (the module doc and sample_region_reference)."""
    h, w = coverage.shape
    r = best.shape[0]
    rgb = np.zeros(3)
    low = np.zeros(3)
    mean = np.zeros(3)
    rows = np.zeros(2, np.int64)
    cols = np.zeros(2, np.int64)
    wy = np.zeros(2)
    wx = np.zeros(2)
    for i in range(h):
        for j in range(w):
            if coverage[i, j] <= 0:
                continue
            px, py = x0 + j + 0.5, y0 + i + 0.5
            qx = inverse[0, 0] * px + inverse[0, 1] * py + inverse[0, 2]
            qy = inverse[1, 0] * px + inverse[1, 1] * py + inverse[1, 2]
            qw = inverse[2, 0] * px + inverse[2, 1] * py + inverse[2, 2]
            if qw <= 0:
                continue
            nx, ny = qx / qw, qy / qw
            dxdx = (inverse[0, 0] - nx * inverse[2, 0]) / qw
            dxdy = (inverse[0, 1] - nx * inverse[2, 1]) / qw
            dydx = (inverse[1, 0] - ny * inverse[2, 0]) / qw
            dydy = (inverse[1, 1] - ny * inverse[2, 1]) / qw
            xs, ys = nx - 0.5, ny - 0.5
            if xs < -0.5 or ys < -0.5 or xs > r - 0.5 or ys > r - 0.5:
                continue
            j0, i0 = math.floor(xs), math.floor(ys)
            fx, fy = xs - j0, ys - i0
            rows[0], rows[1] = min(max(i0, 0), r - 1), min(max(i0 + 1, 0), r - 1)
            cols[0], cols[1] = min(max(j0, 0), r - 1), min(max(j0 + 1, 0), r - 1)
            wy[0], wy[1] = 1.0 - fy, fy
            wx[0], wx[1] = 1.0 - fx, fx
            for a in range(2):  # the most likely chart of each, found when first read
                for b in range(2):
                    if best[rows[a], cols[b]] < 0:
                        best[rows[a], cols[b]] = _argmax(probabilities, rows[a], cols[b])
            # Of the charts the four network pixels show, the one with the largest bilinearly
            # interpolated probability: a chart border follows the probabilities' level line
            # between network pixels, not their squares. Its confidence: that probability
            # given some chart (not the silhouette's falloff).
            none = 0.0
            for a in range(2):
                for b in range(2):
                    none += wy[a] * wx[b] * probabilities[0, rows[a], cols[b]]
            chart, score = 0, -1.0
            for a in range(2):
                for b in range(2):
                    k = best[rows[a], cols[b]]
                    if k > 0 and k != chart:
                        p = 0.0
                        for a2 in range(2):
                            for b2 in range(2):
                                p += wy[a2] * wx[b2] * probabilities[k, rows[a2], cols[b2]]
                        if p > score:
                            chart, score = k, p
            if chart == 0 or score < threshold * max(1.0 - none, 1e-6) or image[chart] < 0:
                continue
            # The nearest of the four that shows the chart (its coordinates if none other does).
            ci, cj, weight = 0, 0, -1.0
            for a in range(2):
                for b in range(2):
                    if best[rows[a], cols[b]] == chart and wy[a] * wx[b] > weight:
                        ci, cj, weight = rows[a], cols[b], wy[a] * wx[b]
            cu, cv = 2 * chart - 2, 2 * chart - 1
            u = v = total = 0.0
            for a in range(2):
                for b in range(2):
                    if best[rows[a], cols[b]] == chart:
                        wgt = wy[a] * wx[b]
                        u += wgt * coordinates[cu, rows[a], cols[b]]
                        v += wgt * coordinates[cv, rows[a], cols[b]]
                        total += wgt
            if total > 0:
                u, v = u / total, v / total
            else:
                u, v = coordinates[cu, ci, cj], coordinates[cv, ci, cj]
            # Derivatives along network x (row pairs) and y (column pairs), same chart only.
            du0 = dv0 = acc = 0.0
            if cols[0] != cols[1]:
                for a in range(2):
                    if best[rows[a], cols[0]] == chart and best[rows[a], cols[1]] == chart:
                        du0 += wy[a] * (
                            coordinates[cu, rows[a], cols[1]] - coordinates[cu, rows[a], cols[0]]
                        )
                        dv0 += wy[a] * (
                            coordinates[cv, rows[a], cols[1]] - coordinates[cv, rows[a], cols[0]]
                        )
                        acc += wy[a]
            if acc > 0:
                du0, dv0 = du0 / acc, dv0 / acc
            du1 = dv1 = acc = 0.0
            if rows[0] != rows[1]:
                for b in range(2):
                    if best[rows[0], cols[b]] == chart and best[rows[1], cols[b]] == chart:
                        du1 += wx[b] * (
                            coordinates[cu, rows[1], cols[b]] - coordinates[cu, rows[0], cols[b]]
                        )
                        dv1 += wx[b] * (
                            coordinates[cv, rows[1], cols[b]] - coordinates[cv, rows[0], cols[b]]
                        )
                        acc += wx[b]
            if acc > 0:
                du1, dv1 = du1 / acc, dv1 / acc
            hu, hv = half[chart, 0], half[chart, 1]
            s = min(max(center[chart, 0] + hu * u, bounds[chart, 0]), bounds[chart, 2])
            t = min(max(center[chart, 1] + hv * v, bounds[chart, 1]), bounds[chart, 3])
            su, sv = transform[chart, 0], transform[chart, 1]
            img = image[chart]
            width0, height0 = levels[img, 0, 1], levels[img, 0, 2]
            dsx = hu * su * (du0 * dxdx + du1 * dydx) * width0
            dtx = hv * sv * (dv0 * dxdx + dv1 * dydx) * height0
            dsy = hu * su * (du0 * dxdy + du1 * dydy) * width0
            dty = hv * sv * (dv0 * dxdy + dv1 * dydy) * height0
            # The pixel's footprint, a parallelogram of axes (dsx, dtx) and (dsy, dty) in
            # level-0 texels, read as a grid of taps, each covering at most `cell` texels along
            # both axes, from the mip level of that size (trilinear): a supersampled,
            # anisotropic box filter of the pixel.
            length_x = math.sqrt(dsx * dsx + dtx * dtx)
            length_y = math.sqrt(dsy * dsy + dty * dty)
            cell = max(
                1.0, min(length_x, length_y) / minor_taps, max(length_x, length_y) / max_taps
            )
            taps_x = min(max_taps, max(1, math.ceil(length_x / cell - 1e-9)))
            taps_y = min(max_taps, max(1, math.ceil(length_y / cell - 1e-9)))
            lod = min(max(math.log2(cell) + lod_bias, 0.0), level_count[img] - 1.0)
            level = math.floor(lod)
            blend = lod - level
            st_out[i, j, 0], st_out[i, j, 1] = s, t
            chart_out[i, j] = chart
            # The footprint's axes in st (texels / image size / the st -> image scale).
            xs_s, xs_t = dsx / (width0 * su), dtx / (height0 * sv)
            ys_s, ys_t = dsy / (width0 * su), dty / (height0 * sv)
            for c in range(3):
                mean[c] = 0.0
            count = taps_x * taps_y
            for kx in range(taps_x):
                ox = (kx + 0.5) / taps_x - 0.5
                for ky in range(taps_y):
                    oy = (ky + 0.5) / taps_y - 0.5
                    # Each tap's st stays in the chart's bounds (a UDIM chart's tile), then
                    # goes to the image.
                    ts = min(max(s + ox * xs_s + oy * ys_s, bounds[chart, 0]), bounds[chart, 2])
                    tt = min(max(t + ox * xs_t + oy * ys_t, bounds[chart, 1]), bounds[chart, 3])
                    ts, tt = ts * su + transform[chart, 2], tt * sv + transform[chart, 3]
                    _bilinear(
                        texels, levels, img, level, ts, tt, wrap[chart, 0], wrap[chart, 1], rgb
                    )
                    if blend > 0 and level + 1 < level_count[img]:
                        _bilinear(
                            texels, levels, img, level + 1, ts, tt, wrap[chart, 0], wrap[chart, 1],
                            low,
                        )  # fmt: skip
                        for c in range(3):
                            rgb[c] = rgb[c] * (1 - blend) + low[c] * blend
                    for c in range(3):
                        mean[c] += rgb[c] / count
            for c in range(3):
                rgb[c] = mean[c]
            for c in range(3):
                out[i, j, c] = rgb[c]
            used[i, j] = True

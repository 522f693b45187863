"""Compiled (numba) shadow kernels: shadow-map lookups, capsule occlusion and coarse-to-fine passes.

The maths is runtime/shadows/__init__.py's numpy, pixel by pixel: a shadow map's normal offset and
2x2 bilinear taps (ShadowMap.visibility), a capsule's 2-D cull in the light's view
(_light_plane, _candidate_pairs) and its cone occlusion (capsule_visibility), and the
coarse-to-fine blend of sparse_visibility. Fused into one loop per pass they skip numpy's
per-call cost and temporaries: one call evaluates a light's whole pass over a frame window,
deciding blends and evaluating the pixels that need it as it goes. Compiled on first use
and cached on disk (numba's cache=True), so a process pays the compile once and later
processes load it.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

MAP_FIELDS = 21
"""Per shadow map in a pass (float64): world-to-camera rows 0-2 (12), fx, fy, cx, cy, near,
the padded map's width and height, its first texel in its flat buffer and which buffer (0:
the pass's largest map, handed over without a copy; 1: the others, concatenated)."""
SET_FIELDS = 28
"""Per capsule set (one character under one light): mode (0 distant, 1 point, 2 every
pair), the light's 2-D frame rows (9), the light's position (3), front or nearest, the
softness (tangent or radius), the point light's off-axis base angle, the 2-D bounds of all
capsules (4), their largest 2-D radius, first and end capsule, the light's angle, first and end limb (rows of `chains`:
first and end capsule, 2-D bounds (4), largest 2-D radius), and the cosine and sine of a
DistantLight's angle."""
MODE_DISTANT, MODE_POINT, MODE_EVERY = 0, 1, 2
KIND_MAP, KIND_CAPSULES = 0, 1
FAR_OFF_AXIS = math.radians(80.0)


@nb.njit(cache=True, error_model="numpy", inline="always")
def _map_lookup(par, flat0, flat1, px, py, pz, nx, ny, nz, has_normal, offset_texels, bias_texels):
    """ShadowMap.visibility at one point."""
    fx, fy, cx, cy, near = par[12], par[13], par[14], par[15], par[16]
    if has_normal:
        depth0 = -(par[8] * px + par[9] * py + par[10] * pz + par[11])
        off = max(depth0, 0.0) * (offset_texels / fx)
        px, py, pz = px + nx * off, py + ny * off, pz + nz * off
    d = -(par[8] * px + par[9] * py + par[10] * pz + par[11])
    if d <= near:  # behind the map's camera: nothing it drew can shadow
        return 1.0
    inv = 1.0 / d
    x = (par[0] * px + par[1] * py + par[2] * pz + par[3]) * (fx * inv) + cx + 0.5
    y = (par[4] * px + par[5] * py + par[6] * pz + par[7]) * (-fy * inv) + cy + 0.5
    width, height, start = int(par[17]), int(par[18]), int(par[19])
    flat = flat0 if par[20] == 0 else flat1
    x = min(max(x, 0.0), width - 2.0)
    y = min(max(y, 0.0), height - 2.0)
    x0, y0 = math.floor(x), math.floor(y)
    fxx, fyy = x - x0, y - y0
    index = start + int(y0) * width + int(x0)
    limit = d - (bias_texels / fx) * d
    t00 = 1.0 if flat[index] >= limit else 0.0
    t01 = 1.0 if flat[index + 1] >= limit else 0.0
    t10 = 1.0 if flat[index + width] >= limit else 0.0
    t11 = 1.0 if flat[index + width + 1] >= limit else 0.0
    top = t00 * (1 - fxx) + t01 * fxx
    bottom = t10 * (1 - fxx) + t11 * fxx
    return top * (1 - fyy) + bottom * fyy


@nb.njit(cache=True, error_model="numpy", inline="always")
def _acos(x):
    """arccos within 2e-8 (Abramowitz and Stegun 4.4.46): a few times faster than libm's,
    and the pairs that overlap call it three or four times each."""
    t = abs(x)
    p = -0.0012624911
    p = p * t + 0.0066700901
    p = p * t - 0.0170881256
    p = p * t + 0.0308918810
    p = p * t - 0.0501743046
    p = p * t + 0.0889789874
    p = p * t - 0.2145988016
    p = p * t + 1.5707963050
    angle = math.sqrt(max(1.0 - t, 0.0)) * p
    return angle if x >= 0 else math.pi - angle


@nb.njit(cache=True, error_model="numpy", inline="always")
def _cone_occlusion(r1, r2, d):
    """shadows.cone_occlusion for one pair."""
    if d >= r1 + r2:
        return 0.0
    if d <= abs(r1 - r2):
        area = math.pi * min(r1, r2) ** 2
    else:
        d_safe = max(d, 1e-9)
        c1 = min(max((d * d + r1 * r1 - r2 * r2) / (2 * d_safe * r1), -1.0), 1.0)
        c2 = min(max((d * d + r2 * r2 - r1 * r1) / (2 * d_safe * max(r2, 1e-9)), -1.0), 1.0)
        kite = (-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2)
        kite = math.sqrt(max(kite, 0.0))
        area = r1 * r1 * _acos(c1) + r2 * r2 * _acos(c2) - 0.5 * kite
    return min(max(area / (math.pi * r1 * r1), 0.0), 1.0)


@nb.njit(cache=True, error_model="numpy", inline="always")
def _pair(a, b, radius, k, px, py, pz, dx, dy, dz, light_angle, cos_light, sin_light):
    """One capsule's occlusion of the light's cone seen from a point (capsule_visibility);
    `cos_light`, `sin_light` of `light_angle`."""
    ax, ay, az = a[k, 0], a[k, 1], a[k, 2]
    ux, uy, uz = b[k, 0] - ax, b[k, 1] - ay, b[k, 2] - az
    wx, wy, wz = ax - px, ay - py, az - pz
    uu = ux * ux + uy * uy + uz * uz
    ud = ux * dx + uy * dy + uz * dz
    uw = ux * wx + uy * wy + uz * wz
    dw = dx * wx + dy * wy + dz * wz
    denominator = uu - ud * ud
    s = (ud * dw - uw) / denominator if denominator > 1e-9 else 0.0
    s = min(max(s, 0.0), 1.0)
    cx, cy, cz = wx + s * ux, wy + s * uy, wz + s * uz
    distance = max(math.sqrt(cx * cx + cy * cy + cz * cz), 1e-6)
    r = radius[k]
    if distance <= r:  # a receiver inside a capsule: not its caster
        return 0.0
    sin_sphere = min(r / distance, 1.0)
    cosine = min(max((cx * dx + cy * dy + cz * dz) / distance, -1.0), 1.0)
    # Cones apart (their axes at least the sum of their angles apart) hide nothing: told
    # by cosines (cos(a + b)), without the inverse sines and cosines. The pairs that the
    # 2-D cull keeps are mostly such (its bounds are boxes around each capsule's shadow).
    cos_sphere = math.sqrt(1.0 - sin_sphere * sin_sphere)
    if cosine < cos_light * cos_sphere - sin_light * sin_sphere - 1e-12:
        return 0.0
    return _cone_occlusion(light_angle, 0.5 * math.pi - _acos(sin_sphere), _acos(cosine))


@nb.njit(cache=True, error_model="numpy", inline="always")
def _capsules_at(sp, a, b, radius, a2, b2, r2, chains, px, py, pz, min_visibility):
    """The visibility of a light past one capsule set at one point: the 2-D cull of
    _light_plane / _candidate_pairs, then the pairs it keeps."""
    mode = int(sp[0])
    every = mode == MODE_EVERY
    u = v = margin = 0.0
    factor = 1.0
    if mode == MODE_DISTANT:
        u = sp[1] * px + sp[2] * py + sp[3] * pz
        v = sp[4] * px + sp[5] * py + sp[6] * pz
        depth = sp[7] * px + sp[8] * py + sp[9] * pz
        margin = max(depth - sp[13], 0.0) * sp[14]
    elif mode == MODE_POINT:
        qx, qy, qz = px - sp[10], py - sp[11], pz - sp[12]
        z = sp[7] * qx + sp[8] * qy + sp[9] * qz
        if z <= 0:  # behind the light's view of the capsules: out of their shadow
            return 1.0
        x = sp[1] * qx + sp[2] * qy + sp[3] * qz
        y = sp[4] * qx + sp[5] * qy + sp[6] * qz
        u, v = x / z, y / z
        far = math.sqrt(x * x + y * y + z * z)
        nearest = sp[13]
        margin = sp[14] * max(far - nearest, 0.0) / (max(far, nearest) * nearest)
        off_axis = sp[15] + margin
        if off_axis < FAR_OFF_AXIS:
            factor = 1.0 / math.cos(off_axis) ** 2
        else:
            every = True  # too far off the light's axis to bound: every pair
    if not every:
        reach = (sp[20] + margin) * factor
        if u < sp[16] - reach or u > sp[18] + reach or v < sp[17] - reach or v > sp[19] + reach:
            return 1.0
    visibility = 1.0
    for chain in range(int(sp[24]), int(sp[25])):
        start, stop = int(chains[chain, 0]), int(chains[chain, 1])
        if not every:  # a limb's 2-D bounds first: most receivers miss all but one limb
            reach = (chains[chain, 6] + margin) * factor
            if u < chains[chain, 2] - reach or u > chains[chain, 4] + reach:
                continue
            if v < chains[chain, 3] - reach or v > chains[chain, 5] + reach:
                continue
        visibility *= _limb(sp, a, b, radius, a2, b2, r2, start, stop, every, u, v, margin,
                            factor, px, py, pz, min_visibility)  # fmt: skip
    return visibility


@nb.njit(cache=True, error_model="numpy", inline="always")
def _limb(sp, a, b, radius, a2, b2, r2, first, end, every, u, v, margin, factor, px, py, pz,
          min_visibility):  # fmt: skip
    """The visibility past capsules first..end (one limb) at a point seen at u, v."""
    mode = int(sp[0])
    visibility = 1.0
    dx = dy = dz = light_angle = cos_light = sin_light = 0.0
    towards = False  # the light's direction and angular radius, found with the first pair
    for k in range(first, end):
        if not every:
            limit = (r2[k] + margin) * factor
            au, av, bu, bv = a2[k, 0], a2[k, 1], b2[k, 0], b2[k, 1]
            if u < min(au, bu) - limit or u > max(au, bu) + limit:
                continue
            if v < min(av, bv) - limit or v > max(av, bv) + limit:
                continue
            su, sv = bu - au, bv - av
            length2 = max(su * su + sv * sv, 1e-18)
            t = min(max(((u - au) * su + (v - av) * sv) / length2, 0.0), 1.0)
            du, dv = u - au - t * su, v - av - t * sv
            if du * du + dv * dv > limit * limit:
                continue
        if not towards:  # _towards_light
            towards = True
            if mode == MODE_DISTANT:
                dx, dy, dz = -sp[7], -sp[8], -sp[9]  # the frame's w row: the light's direction
                light_angle, cos_light, sin_light = sp[23], sp[26], sp[27]
            else:
                ox, oy, oz = sp[10] - px, sp[11] - py, sp[12] - pz
                dist = max(math.sqrt(ox * ox + oy * oy + oz * oz), 1e-6)
                inverse = 1.0 / dist
                dx, dy, dz = ox * inverse, oy * inverse, oz * inverse
                # The cone's sine is the ratio itself, its cosine from it: one inverse sine
                # per pixel and no cosine or sine of it.
                sin_light = min(max(sp[14] * inverse, 0.0), 1.0)
                cos_light = math.sqrt(1.0 - sin_light * sin_light)
                light_angle = 0.5 * math.pi - _acos(sin_light)
        occlusion = _pair(a, b, radius, k, px, py, pz, dx, dy, dz, light_angle, cos_light,
                          sin_light)  # fmt: skip
        visibility *= max(1.0 - occlusion, min_visibility)
    return visibility


@nb.njit(cache=True, error_model="numpy")
def points_visibility(
    points, normals, kind, maps_par, flat0, flat1, sets_par, a, b, radius, a2, b2, r2, chains, constants
):  # fmt: skip
    """(N,) visibility of planar (3, N) world points past every map (kind KIND_MAP) or every
    capsule set (KIND_CAPSULES) given; `normals` (3, N) or (3, 0)."""
    n = points.shape[1]
    out = np.ones(n, np.float32)
    has_normal = normals.shape[1] == n
    if kind == KIND_MAP:  # one loop per kind: the branch inside measured slower
        for i in range(n):
            px, py, pz = float(points[0, i]), float(points[1, i]), float(points[2, i])
            nx = ny = nz = 0.0
            if has_normal:
                nx, ny, nz = float(normals[0, i]), float(normals[1, i]), float(normals[2, i])
            value = 1.0
            for j in range(maps_par.shape[0]):
                value *= _map_lookup(maps_par[j], flat0, flat1, px, py, pz, nx, ny, nz,
                                     has_normal, constants[0], constants[1])  # fmt: skip
            out[i] = value
        return out
    for i in range(n):
        px, py, pz = float(points[0, i]), float(points[1, i]), float(points[2, i])
        value = 1.0
        for j in range(sets_par.shape[0]):
            value *= _capsules_at(
                sets_par[j], a, b, radius, a2, b2, r2, chains, px, py, pz, constants[2]
            )
        out[i] = value
    return out


@nb.njit(cache=True, error_model="numpy")
def _fill(grid, ys, xs, count, frame, depth, normal, rects, rect_job, kind, maps_par, flat0, flat1,
          sets_par, a, b, radius, a2, b2, r2, chains, constants):  # fmt: skip
    """Evaluate window pixels (ys, xs)[:count] into `grid`: the visibility past the jobs
    whose rectangles hold each (`rects` of job `rect_job`, in job order; job j the j-th map
    or capsule set)."""
    r0, c0 = int(frame[16]), int(frame[17])
    o_r, o_c = int(frame[18]), int(frame[19])  # the G-buffer's first pixel in the frame
    if kind == KIND_MAP:  # one loop per kind: a branch per pixel measured twice as slow
        for q in range(count):
            i, j = ys[q], xs[q]
            px, py, pz = _point(frame, depth, i, j)
            row, col = r0 + i, c0 + j
            gy, gx = row - o_r, col - o_c
            n0, n1, n2 = normal[gy, gx, 0], normal[gy, gx, 1], normal[gy, gx, 2]
            nx = frame[0] * n0 + frame[1] * n1 + frame[2] * n2
            ny = frame[4] * n0 + frame[5] * n1 + frame[6] * n2
            nz = frame[8] * n0 + frame[9] * n1 + frame[10] * n2
            value = 1.0
            last = -1
            for e in range(rects.shape[0]):
                job = rect_job[e]
                if job == last or not _inside(rects, e, row, col):
                    continue
                last = job  # counted once, whichever of its rectangles holds the pixel
                value *= _map_lookup(maps_par[job], flat0, flat1, px, py, pz, nx, ny, nz, True,
                                     constants[0], constants[1])  # fmt: skip
            grid[i, j] = value
        return
    if sets_par.shape[0] == 1:  # one set: every wanted pixel lies in one of its rectangles
        for q in range(count):
            i, j = ys[q], xs[q]
            px, py, pz = _point(frame, depth, i, j)
            grid[i, j] = _capsules_at(sets_par[0], a, b, radius, a2, b2, r2, chains, px, py, pz,
                                      constants[2])  # fmt: skip
        return
    for q in range(count):
        i, j = ys[q], xs[q]
        px, py, pz = _point(frame, depth, i, j)
        row, col = r0 + i, c0 + j
        value = 1.0
        last = -1
        for e in range(rects.shape[0]):
            job = rect_job[e]
            if job == last or not _inside(rects, e, row, col):
                continue
            last = job  # counted once, whichever of its rectangles holds the pixel
            value *= _capsules_at(sets_par[job], a, b, radius, a2, b2, r2, chains, px, py, pz,
                                  constants[2])  # fmt: skip
        grid[i, j] = value


@nb.njit(cache=True, error_model="numpy", inline="always")
def _point(frame, depth, i, j):
    """World position of window pixel (i, j) (the engine's _world_points)."""
    row, col = frame[16] + i, frame[17] + j
    d = float(depth[int(row - frame[18]), int(col - frame[19])])
    if not math.isfinite(d):
        d = 0.0
    x = (col + 0.5 - frame[14]) * (d / frame[12])
    y = (frame[15] - row - 0.5) * (d / frame[13])
    z = -d
    return (
        frame[0] * x + frame[1] * y + frame[2] * z + frame[3],
        frame[4] * x + frame[5] * y + frame[6] * z + frame[7],
        frame[8] * x + frame[9] * y + frame[10] * z + frame[11],
    )


@nb.njit(cache=True, error_model="numpy", inline="always")
def _bend_at(c, i, j, ny, nx):
    """_bend of a coarse grid at sample (i, j): the largest second difference along either
    axis around it (at the border, its neighbour's)."""
    out = 0.0
    if ny >= 3:
        k = min(max(i, 1), ny - 2)
        out = abs(c[k - 1, j] - 2 * c[k, j] + c[k + 1, j])
    if nx >= 3:
        k = min(max(j, 1), nx - 2)
        out = max(out, abs(c[i, k - 1] - 2 * c[i, k] + c[i, k + 1]))
    return out


@nb.njit(cache=True, error_model="numpy", inline="always")
def _inside(rects, q, row, col):
    """Whether rectangle q (x0, y0, x1, y1) holds frame pixel (row, col)."""
    return rects[q, 0] <= col < rects[q, 2] and rects[q, 1] <= row < rects[q, 3]


@nb.njit(cache=True, error_model="numpy")
def _wanted(mask, frame, size_y, size_x, h, w, rects):
    """(size_y, size_x) the pixels of the (h, w) window at (frame[16], frame[17]) that a prim
    covers (`mask`, the frame's) inside any of `rects`; row by row, each rectangle's span
    marked (overlapping rectangles cost their overlap, not a pass each over the window)."""
    r0, c0 = int(frame[16]), int(frame[17])
    o_r, o_c = int(frame[18]), int(frame[19])
    out = np.zeros((size_y, size_x), np.bool_)
    spans = np.zeros(w + 1, np.int64)
    for i in range(h):
        row = r0 + i
        spans[:] = 0
        any_span = False
        for q in range(rects.shape[0]):
            if rects[q, 1] <= row < rects[q, 3]:
                left, right = max(rects[q, 0] - c0, 0), min(rects[q, 2] - c0, w)
                if right > left:
                    spans[left] += 1
                    spans[right] -= 1
                    any_span = True
        if not any_span:
            continue
        depth = 0
        for j in range(w):
            depth += spans[j]
            if depth > 0 and mask[row - o_r, c0 + j - o_c] > 0:
                out[i, j] = True
    return out


@nb.njit(cache=True, error_model="numpy")
def sparse_pass(
    out, mask, depth, normal, frame, h, w, rects, rect_job, kind, maps_par, flat0, flat1,
    sets_par, a, b, radius, a2, b2, r2, chains, constants, step,
):  # fmt: skip
    """shadows.sparse_visibility over the (h, w) window at (frame[16], frame[17]) (rows,
    columns) of a G-buffer (mask, depth, normal: the frame's prims', or a character's layer
    whose first pixel is at (frame[18], frame[19]) in the frame), its candidates the pixels a
    prim covers inside any of `rects` (of job
    `rect_job`: the maps, or the capsule sets, in order); the `step` grid evaluated exactly,
    then each finer grid blended from the one above where smooth (constants[3]:
    BEND_TOLERANCE) and on its samples' surface (constants[4]: SURFACE_TOLERANCE), evaluated
    elsewhere (_fill, level by level). step 1: every candidate evaluated. The window's
    factors go into `out`, shaped as the G-buffer (its other pixels left as they are)."""
    r0, c0 = int(frame[16]), int(frame[17])
    o_r, o_c = int(frame[18]), int(frame[19])
    if h < 2 or w < 2:
        step = 1
    size_y = -(-(h - 1) // step) * step + 1
    size_x = -(-(w - 1) // step) * step + 1
    grid = np.ones((size_y, size_x), np.float32)
    inverse = np.zeros((size_y, size_x), np.float32)
    want = _wanted(mask, frame, size_y, size_x, h, w, rects)
    for i in range(h):
        for j in range(w):
            d = depth[r0 + i - o_r, c0 + j - o_c]
            inverse[i, j] = np.float32(1.0) / max(d, np.float32(1e-30))
    ys = np.empty(h * w, np.int64)
    xs = np.empty(h * w, np.int64)
    count = 0
    for i in range(0, size_y, step):
        for j in range(0, size_x, step):
            if want[i, j]:
                ys[count], xs[count] = i, j
                count += 1
    _fill(grid, ys, xs, count, frame, depth, normal, rects, rect_job, kind, maps_par, flat0, flat1,
          sets_par, a, b, radius, a2, b2, r2, chains, constants)  # fmt: skip
    bend_tolerance, surface = constants[3], np.float32(constants[4])
    spacing = step
    while spacing > 1:
        half = spacing // 2
        ny, nx = (size_y - 1) // spacing + 1, (size_x - 1) // spacing + 1
        c = np.empty((ny, nx), np.float32)
        for i in range(ny):
            for j in range(nx):
                c[i, j] = grid[i * spacing, j * spacing]
        # A cell is rough where a corner bends; smooth where neither it nor a neighbour is.
        bend = np.empty((ny, nx), np.bool_)
        for i in range(ny):
            for j in range(nx):
                bend[i, j] = _bend_at(c, i, j, ny, nx) > bend_tolerance
        rough = np.zeros((ny + 1, nx + 1), np.bool_)  # padded by one cell on each side
        for i in range(ny - 1):
            for j in range(nx - 1):
                rough[i + 1, j + 1] = (
                    bend[i, j] | bend[i, j + 1] | bend[i + 1, j] | bend[i + 1, j + 1]
                )
        smooth = np.empty((ny - 1, nx - 1), np.bool_)
        for i in range(ny - 1):
            for j in range(nx - 1):
                smooth[i, j] = not (
                    rough[i, j] | rough[i, j + 1] | rough[i, j + 2]
                    | rough[i + 1, j] | rough[i + 1, j + 1] | rough[i + 1, j + 2]
                    | rough[i + 2, j] | rough[i + 2, j + 1] | rough[i + 2, j + 2]
                )  # fmt: skip
        count = 0
        half32, quarter = np.float32(0.5), np.float32(0.25)
        # The middles of horizontal edges, of vertical edges, and of cells; an edge is
        # smooth where a cell beside it is (the dilation has looked at the other). Each is
        # blended where smooth and on its samples' surface, else queued for _fill.
        for i in range(ny):
            y = i * spacing
            for j in range(nx - 1):
                x = j * spacing + half
                if want[y, x]:
                    mine = inverse[y, x]
                    expected = (inverse[y, x - half] + inverse[y, x + half]) * half32
                    if smooth[min(i, ny - 2), j] and abs(expected - mine) <= surface * mine:
                        grid[y, x] = (c[i, j] + c[i, j + 1]) * half32
                    else:
                        ys[count], xs[count] = y, x
                        count += 1
        for i in range(ny - 1):
            y = i * spacing + half
            for j in range(nx):
                x = j * spacing
                if want[y, x]:
                    mine = inverse[y, x]
                    expected = (inverse[y - half, x] + inverse[y + half, x]) * half32
                    if smooth[i, min(j, nx - 2)] and abs(expected - mine) <= surface * mine:
                        grid[y, x] = (c[i, j] + c[i + 1, j]) * half32
                    else:
                        ys[count], xs[count] = y, x
                        count += 1
            for j in range(nx - 1):
                x = j * spacing + half
                if want[y, x]:
                    mine = inverse[y, x]
                    expected = (
                        inverse[y - half, x - half] + inverse[y - half, x + half]
                        + inverse[y + half, x - half] + inverse[y + half, x + half]
                    ) * quarter  # fmt: skip
                    if smooth[i, j] and abs(expected - mine) <= surface * mine:
                        corners = c[i, j] + c[i, j + 1] + c[i + 1, j] + c[i + 1, j + 1]
                        grid[y, x] = corners * quarter
                    else:
                        ys[count], xs[count] = y, x
                        count += 1
        _fill(grid, ys, xs, count, frame, depth, normal, rects, rect_job, kind, maps_par, flat0, flat1,
              sets_par, a, b, radius, a2, b2, r2, chains, constants)  # fmt: skip
        spacing = half
    for i in range(h):
        for j in range(w):
            out[r0 - o_r + i, c0 - o_c + j] = grid[i, j]


@nb.njit(cache=True, error_model="numpy")
def shadow_regions(lo, hi, light, box, view, width, height):
    """shadows.shadow_regions: per caster with bounds lo, hi (M, 3), (M, 5) int64 rows of
    what its shadow can fall on: 0 nothing in view, 1 the rectangle x0, y0, x1, y1, 2 the
    whole frame. `light`: kind (0 distant, 1 point), direction (3), position (3), angular
    radius (at least MIN_SOFTNESS) of a DistantLight, radius of a point light, MIN_SOFTNESS;
    `view`: world-to-camera rows 0-2 (12), fx, fy, cx, cy, near."""
    m = lo.shape[0]
    out = np.zeros((m, 5), np.int64)
    corners = np.empty((16, 3))
    directions = np.empty((8, 3))
    lengths = np.empty(8)
    for i in range(m):
        around = False
        if light[0] == 0:
            angle = light[7]
            for c in range(8):
                for k in range(3):
                    directions[c, k] = light[1 + k]
        else:
            distance = 0.0
            for k in range(3):
                offset = (lo[i, k] + hi[i, k]) / 2 - light[4 + k]
                distance += offset * offset
            distance = math.sqrt(distance)
            angle = max(math.asin(min(max(light[8] / max(distance, 1e-9), 0.0), 1.0)), light[9])
            around = True
            for k in range(3):
                around &= lo[i, k] <= light[4 + k] <= hi[i, k]
        size = 0.0
        thinnest = np.inf
        for k in range(3):
            size += (hi[i, k] - lo[i, k]) ** 2
            thinnest = min(thinnest, hi[i, k] - lo[i, k])
        size = max(math.sqrt(size), 1e-9)
        longest = 0.0
        for c in range(8):
            for k in range(3):
                corners[c, k] = hi[i, k] if (c >> (2 - k)) & 1 else lo[i, k]
            if light[0] != 0:
                norm = 0.0
                for k in range(3):
                    directions[c, k] = corners[c, k] - light[4 + k]
                    norm += directions[c, k] ** 2
                norm = max(math.sqrt(norm), 1e-12)
                for k in range(3):
                    directions[c, k] /= norm
            t = np.inf
            for k in range(3):
                d = directions[c, k]
                if d > 0:
                    t = min(t, (max(box[1, k], hi[i, k]) - corners[c, k]) / d)
                elif d < 0:
                    t = min(t, (min(box[0, k], lo[i, k]) - corners[c, k]) / d)
            lengths[c] = max(t, 0.0)
            longest = max(longest, lengths[c])
        if longest <= 1e-6 * size and thinnest <= 1e-6 * size:
            continue  # flat on the scene's boundary (the ground): onto nothing
        grow = longest * math.tan(angle)
        low = np.full(3, np.inf)
        high = np.full(3, -np.inf)
        for c in range(8):
            for k in range(3):
                end = corners[c, k] + directions[c, k] * lengths[c]
                low[k] = min(low[k], end)
                high[k] = max(high[k], end)
        for c in range(8):
            for k in range(3):
                corners[8 + c, k] = high[k] + grow if (c >> (2 - k)) & 1 else low[k] - grow
        behind = False
        xmin = ymin = np.inf
        xmax = ymax = -np.inf
        for c in range(16):
            px, py, pz = corners[c, 0], corners[c, 1], corners[c, 2]
            x = view[0] * px + view[1] * py + view[2] * pz + view[3]
            y = view[4] * px + view[5] * py + view[6] * pz + view[7]
            depth = -(view[8] * px + view[9] * py + view[10] * pz + view[11])
            if depth <= view[16]:
                behind = True
                break
            sx = view[14] + view[12] * x / depth
            sy = view[15] - view[13] * y / depth
            xmin, xmax = min(xmin, sx), max(xmax, sx)
            ymin, ymax = min(ymin, sy), max(ymax, sy)
        if around or behind:  # the light among it, or reaching behind the camera
            out[i, 0], out[i, 3], out[i, 4] = 2, width, height
            continue
        x0, y0 = max(math.floor(xmin) - 1, 0), max(math.floor(ymin) - 1, 0)
        x1, y1 = min(math.ceil(xmax) + 1, width), min(math.ceil(ymax) + 1, height)
        if x1 > x0 and y1 > y0:
            out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4] = 1, x0, y0, x1, y1
    return out


@nb.njit(cache=True, error_model="numpy")
def capsule_arrays(row, a, b, radius, position, runs, first, limbs):
    """shadow_pass.sets_data's per-set part in one call: the capsules' ends (K, 2) twice and
    radii (K,) in the light's 2-D view (_light_plane: a DistantLight's plane, a point
    light's projection through it, where they are angular), and into `row` a point light's
    nearest capsule and off-axis base angle and the set's 2-D bounds; into `limbs` (R, 7)
    each run's (`runs`, start and stop within the set, `first` its first capsule in the
    pass) capsules and 2-D bounds."""
    k = radius.shape[0]
    a2, b2, r2 = np.zeros((k, 2)), np.zeros((k, 2)), np.zeros(k)
    mode = row[0]
    if mode == MODE_DISTANT:
        for q in range(k):
            for c in range(2):
                a2[q, c] = (
                    row[1 + 3 * c] * a[q, 0] + row[2 + 3 * c] * a[q, 1] + row[3 + 3 * c] * a[q, 2]
                )
                b2[q, c] = (
                    row[1 + 3 * c] * b[q, 0] + row[2 + 3 * c] * b[q, 1] + row[3 + 3 * c] * b[q, 2]
                )
            r2[q] = radius[q]
    elif mode == MODE_POINT:
        widest = 0.0
        steepest = 0.0
        for q in range(k):
            closest = np.inf
            for e in range(2):
                end = a if e == 0 else b
                x, y, z = end[q, 0] - position[0], end[q, 1] - position[1], end[q, 2] - position[2]
                closest = min(closest, math.sqrt(x * x + y * y + z * z))
                lx = row[1] * x + row[2] * y + row[3] * z
                ly = row[4] * x + row[5] * y + row[6] * z
                lz = row[7] * x + row[8] * y + row[9] * z
                flat = a2 if e == 0 else b2
                flat[q, 0], flat[q, 1] = lx / lz, ly / lz
                widest = max(widest, math.sqrt(flat[q, 0] ** 2 + flat[q, 1] ** 2))
            angular = math.asin(min(max(radius[q] / max(closest, 1e-9), 0.0), 1.0))
            steepest = max(steepest, angular)
            r2[q] = math.tan(angular)
            row[13] = min(row[13], closest) if q else closest
        row[13] = max(row[13], 1e-9)
        row[15] = math.atan(widest) + steepest
    if k:
        row[16], row[17], row[18], row[19], row[20] = np.inf, np.inf, -np.inf, -np.inf, -np.inf
    for q in range(k):
        row[16] = min(row[16], a2[q, 0], b2[q, 0])
        row[17] = min(row[17], a2[q, 1], b2[q, 1])
        row[18] = max(row[18], a2[q, 0], b2[q, 0])
        row[19] = max(row[19], a2[q, 1], b2[q, 1])
        row[20] = max(row[20], r2[q])
    for n in range(runs.shape[0]):
        start, stop = runs[n, 0], runs[n, 1]
        limbs[n, 0], limbs[n, 1] = start + first, stop + first
        limbs[n, 2], limbs[n, 3], limbs[n, 4], limbs[n, 5] = np.inf, np.inf, -np.inf, -np.inf
        limbs[n, 6] = -np.inf
        for q in range(start, stop):
            limbs[n, 2] = min(limbs[n, 2], a2[q, 0], b2[q, 0])
            limbs[n, 3] = min(limbs[n, 3], a2[q, 1], b2[q, 1])
            limbs[n, 4] = max(limbs[n, 4], a2[q, 0], b2[q, 0])
            limbs[n, 5] = max(limbs[n, 5], a2[q, 1], b2[q, 1])
            limbs[n, 6] = max(limbs[n, 6], r2[q])
    return a2, b2, r2

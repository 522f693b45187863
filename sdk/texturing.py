"""Sample a character's own textures where its network says each pixel lands (the texture head).

A bundle with a texture head (train/network.py) gives, at its resolution R, per pixel the
probabilities of K + 1 texture charts (rigspace.sdk.charts; 0: none) and, for every chart,
coordinates within that chart's uv box. At the size the character has on screen (a frame
region reached through a homography from the network's pixels), each covered pixel:

1. takes, of the charts the four network pixels around it show, the one whose probability
   interpolated bilinearly there is largest (chart borders follow the probabilities' level
   lines, not the network's pixel squares), unless that probability, given some chart, is
   under CHART_CONFIDENCE (then: the albedo branch);
2. interpolates that chart's coordinates bilinearly over the network pixels around it that
   show the same chart (weights renormalised), so nothing is blended across a seam;
3. maps them to USD st (the chart's box; a UDIM chart stays inside its tile), then to the
   texture image (st * scale + offset, the wrap modes of rigspace.sdk.geometry);
4. reads the texture over the pixel's footprint (the coordinates' derivatives through the
   bilinear cell and the homography): a grid of trilinear taps from the mip chain, a
   supersampled, anisotropic box filter (MAX_TAPS along the footprint, MINOR_TAPS across
   it), so a texture seen small or at a grazing angle does not alias and one seen large
   stays sharp.

Charts whose material has no texture, and pixels the classifier is unsure of, are left to
the albedo branch (`used` is False there). sdk/texture_kernel.py's sample_region is the
numba kernel, a loop over pixels; sample_region_reference the same in vectorised numpy,
which the tests hold it to.
`sharpen_coverage` turns coverage upsampled by a large factor back into a one-pixel edge.
"""

from __future__ import annotations

import functools
import hashlib
import time
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from rigspace.sdk.charts import uv_fingerprint
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.geometry import MeshSource

CHART_CONFIDENCE = 0.5
"""A pixel whose chart probability is below this is sampled from the albedo branch instead:
the classifier is unsure there (a chart border, a silhouette)."""
MAX_LEVELS = 16
"""Mip levels kept per image (a 32768-texel side)."""
MAX_TAPS = 4
"""A pixel's texture footprint is read as a grid of at most MAX_TAPS taps along its major
axis and MINOR_TAPS across it, trilinear, from the mip level of a tap's cell (a supersampled,
anisotropic box filter): against the same views drawn with 8x8 samples per pixel the grid
of 4 x 4 scored 26.3 dB at 128x128 (the renderers' 2x2: 22.6; one isotropic trilinear read:
19.7) and 31.2 dB at 512x512 (2x2: 32.0), measured on the sample character."""
MINOR_TAPS = 2
"""Taps across the footprint's minor axis: a tap's cell is at least the minor axis' length
over MINOR_TAPS (and the major axis' over MAX_TAPS), so a round footprint of 4 texels is read
as 2 x 2 taps from mip level 1 rather than 4 x 4 from level 0. `rigspace eval
samples/models/sample /tmp/sample_hr --display --limit 40`, textures at the true coordinates
(the sampler's own accuracy) at 256x256 / 512x512, and the sampler's ms per frame at 640x360:
4 (the full grid) 34.03 / 31.54 dB, 12.4 ms; 2: 33.89 / 31.53 dB, 8.2 ms; 1 (a GPU's
anisotropic filter: the mip level of the minor axis) 32.78 / 31.18 dB, 5.1 ms."""
EDGE_PIXELS = 1.0
"""The width, in frame pixels, of the sharpened coverage's edge ramp."""
SHARP_RAMP = 1.5
"""Coverage magnified up to this many times is kept as it is (its edge ramp is at most this
many pixels wide)."""


def mip_chain(image: np.ndarray) -> list[np.ndarray]:
    """An image's mip levels, from itself down to 1x1: each level the 2x2 box mean of the one
    above (an odd side is extended by its edge texel first)."""
    levels = [np.ascontiguousarray(image, dtype=np.float32)]
    while max(levels[-1].shape[:2]) > 1 and len(levels) < MAX_LEVELS:
        a = levels[-1]
        h, w = a.shape[:2]
        if h % 2 or w % 2:
            a = np.pad(a, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        a = a.reshape(a.shape[0] // 2, 2, a.shape[1] // 2, 2, 3).mean(axis=(1, 3))
        levels.append(np.ascontiguousarray(a, dtype=np.float32))
    return levels


class _Packed:
    """Images' mip chains packed as the kernel reads them."""

    def __init__(self, textures: list[np.ndarray]):
        self.levels = np.zeros((max(len(textures), 1), MAX_LEVELS, 3), np.int64)
        """(images, MAX_LEVELS, 3) int64 offset into texels, width, height of each level."""
        self.count = np.zeros(max(len(textures), 1), np.int32)
        """(images,) int32 levels per image."""
        parts, offset = [], 0
        for n, texture in enumerate(textures):
            chain = mip_chain(texture)
            self.count[n] = len(chain)
            for level, texels in enumerate(chain):
                self.levels[n, level] = (offset, texels.shape[1], texels.shape[0])
                parts.append(texels.reshape(-1, 3))
                offset += texels.shape[0] * texels.shape[1]
        self.texels = np.concatenate(parts) if parts else np.zeros((1, 3), np.float32)
        """(n, 3) float32 every image's mip levels, one after the other, rows from the top."""


_PACKED: weakref.WeakValueDictionary[bytes, _Packed] = weakref.WeakValueDictionary()
"""Packed mip chains by their images' content: characters of one asset (a crowd, each with
its own rig and its own copy of the decoded textures) share one set, freed with the last."""


def _pack(textures: list[np.ndarray]) -> _Packed:
    digest = hashlib.blake2b(digest_size=20)
    for texture in textures:
        array = np.ascontiguousarray(texture, np.float32)
        digest.update(repr(array.shape).encode())
        digest.update(array.data)
    key = digest.digest()
    packed = _PACKED.get(key)
    if packed is None:
        packed = _Packed(textures)
        _PACKED[key] = packed
    return packed


@dataclass
class ChartTextures:
    """What to sample for each chart, packed as the kernel reads it (index 0: no chart)."""

    charts: int
    center: np.ndarray
    """(K+1, 2) float32 centre of each chart's uv box."""
    half: np.ndarray
    """(K+1, 2) float32 half size of each chart's uv box."""
    image: np.ndarray
    """(K+1,) int32 the image each chart reads, -1: none (the albedo branch colours it)."""
    transform: np.ndarray
    """(K+1, 4) float32 scale u, scale v, offset u, offset v: st -> the image's [0, 1]."""
    wrap: np.ndarray
    """(K+1, 2) int32 wrap modes along s and t (rigspace.sdk.geometry.WRAP_MODES)."""
    bounds: np.ndarray
    """(K+1, 4) float32 st box the coordinates are clamped to (a UDIM chart's tile), else
    -inf .. inf."""
    packed: _Packed = field(repr=False, compare=False)
    """The images' mip chains (texels, levels, level_count), shared by the characters of one
    asset (_pack)."""
    untextured: tuple[str, ...] = ()
    """Meshes among the charts' whose material has no texture (the albedo branch colours them)."""

    @property
    def texels(self) -> np.ndarray:
        return self.packed.texels

    def texels_per_st(self) -> np.ndarray:
        """(K+1, 2) float64 texels of each chart's texture per unit of s and t (its largest mip
        level): how far a coordinate error lands on the texture; nan for chart 0 and charts
        whose material has no texture."""
        out = np.full((self.charts + 1, 2), np.nan)
        for k in range(1, self.charts + 1):
            image = int(self.image[k])
            if image >= 0:
                size = self.packed.levels[image, 0, 1:3].astype(np.float64)  # width, height
                out[k] = np.abs(self.transform[k, :2].astype(np.float64)) * size
        return out

    @property
    def levels(self) -> np.ndarray:
        return self.packed.levels

    @property
    def level_count(self) -> np.ndarray:
        return self.packed.count

    @classmethod
    def build(
        cls,
        table: dict,
        sources: dict[str, MeshSource],
    ) -> ChartTextures:
        """From a bundle's charts.json (`table`) and the character's meshes by their names
        relative to the character prim (CharacterRig.mesh_name). Raises TextureMismatch when a
        mesh is missing or its uv layout is not the one the charts were made for."""
        charts = table.get("charts", [])
        fingerprints = {m["mesh"]: m.get("uv_fingerprint") for m in table.get("meshes", [])}
        k = len(charts)
        center = np.zeros((k + 1, 2), np.float32)
        half = np.ones((k + 1, 2), np.float32)
        image = np.full(k + 1, -1, np.int32)
        transform = np.tile(np.array([1, 1, 0, 0], np.float32), (k + 1, 1))
        wrap = np.zeros((k + 1, 2), np.int32)
        bounds = np.tile(np.array([-np.inf, -np.inf, np.inf, np.inf], np.float32), (k + 1, 1))
        images: dict[int, int] = {}
        textures: list[np.ndarray] = []
        untextured: list[str] = []
        checked: dict[str, str] = {}  # mesh -> its uv fingerprint
        for chart in charts:
            index, name = int(chart["index"]), str(chart["mesh"])
            lo, hi = (
                np.asarray(chart["uv_min"], np.float64),
                np.asarray(chart["uv_max"], np.float64),
            )
            center[index] = (lo + hi) / 2
            half[index] = np.maximum((hi - lo) / 2, 1e-6)
            source = sources.get(name)
            if source is None:
                raise TextureMismatch(f"the mesh {name} its texture charts name is not there")
            if source.albedo.texture is None or source.corner_uv is None:
                if name not in untextured:
                    untextured.append(name)
                continue
            expected = fingerprints.get(name)
            if expected is not None and name not in checked:  # once a mesh, not a chart
                checked[name] = uv_fingerprint(source.triangles, source.corner_uv)
            if expected not in (None, checked.get(name)):
                raise TextureMismatch(
                    f"the mesh {name} has other uvs than the ones its texture charts were made for"
                )
            key = id(source.albedo.texture)  # parts sharing a material share its mip chain
            if key not in images:
                images[key] = len(textures)
                textures.append(source.albedo.texture)
            albedo = source.albedo
            image[index] = images[key]
            transform[index] = (*albedo.uv_scale, *albedo.uv_offset)
            wrap[index] = albedo.wrap_codes
            if albedo.udim:
                tile = int(chart["tile"]) - 1001
                u, v = tile % 10, tile // 10
                bounds[index] = (u, v, u + 1, v + 1)
        return cls(k, center, half, image, transform, wrap, bounds, _pack(textures),
                   tuple(untextured))  # fmt: skip

    @property
    def any_texture(self) -> bool:
        return bool(np.any(self.image >= 0))

    def texture_bytes(self) -> int:
        return int(self.texels.nbytes)


class TextureMismatch(RigspaceError):
    """The scene's meshes are not the ones a bundle's texture charts were made for."""


@dataclass
class TextureSample:
    """sample_textures' result over a frame region (h, w)."""

    colour: np.ndarray
    """(h, w, 3) float32 linear texture colour, not premultiplied; 0 where not `used`."""
    used: np.ndarray
    """(h, w) bool: the textures coloured the pixel (False: the albedo branch must)."""
    st: np.ndarray
    """(h, w, 2) float32 the USD st read there (0 where not used): the uv AOV."""
    chart: np.ndarray
    """(h, w) int32 the chart read there (0 where not used): the chart AOV."""


def sample_textures(
    textures: ChartTextures,
    homography: np.ndarray,
    region: tuple[int, int, int, int],
    coverage: np.ndarray,
    probabilities: np.ndarray,
    coordinates: np.ndarray,
    kernel: bool = True,
    lod_bias: float = 0.0,
) -> TextureSample:
    """The character's own texture over a frame region (TextureSample).

    `homography` maps network pixel coordinates (pixel k spans [k, k+1)) to frame pixel
    coordinates; `region` is (x0, y0, w, h) of the frame; `coverage` (h, w) selects the
    pixels to sample (> 0); `probabilities` (K+1, R, R) and `coordinates` (2K, R, R) are the
    texture head's outputs for one character. `kernel` False runs the numpy reference."""
    x0, y0, w, h = region
    _check_head_outputs(textures, probabilities, coordinates)
    probabilities = np.ascontiguousarray(probabilities, np.float32)
    # The most likely chart per network pixel (0: none; the first of equal ones): the kernel
    # finds it where it first reads it (-1: not yet), a few thousand of the R * R pixels.
    best = (
        np.full(probabilities.shape[1:], -1, np.int32)
        if kernel
        else probabilities.argmax(axis=0).astype(np.int32)
    )
    result = TextureSample(
        np.zeros((h, w, 3), np.float32),
        np.zeros((h, w), np.bool_),
        np.zeros((h, w, 2), np.float32),
        np.zeros((h, w), np.int32),
    )
    try:
        inverse = np.linalg.inv(np.asarray(homography, np.float64))
    except np.linalg.LinAlgError:  # a billboard of no size: nothing to read a texture for
        return result
    if not textures.any_texture or not np.all(np.isfinite(inverse)):
        return result
    coverage = np.ascontiguousarray(coverage, np.float32)
    coordinates = np.ascontiguousarray(coordinates, np.float32)

    def rows(i0: int, i1: int) -> tuple:
        """The sampler's arguments for rows [i0, i1) of the region (views: the same pixels)."""
        return (
            inverse, int(x0), int(y0) + i0, coverage[i0:i1], best, probabilities, coordinates,
            np.float32(CHART_CONFIDENCE),
            np.float64(lod_bias), np.int64(MAX_TAPS), np.int64(MINOR_TAPS), textures.center,
            textures.half, textures.image, textures.transform, textures.wrap, textures.bounds,
            textures.texels, textures.levels, textures.level_count, result.colour[i0:i1],
            result.used[i0:i1], result.st[i0:i1], result.chart[i0:i1],
        )  # fmt: skip

    _sample_rows(rows, h, coverage, kernel)
    return result


def _check_head_outputs(
    textures: ChartTextures, probabilities: np.ndarray, coordinates: np.ndarray
) -> None:
    """The texture head gives one probability per chart and none, and two coordinates per
    chart (else TextureMismatch: the bundle's graphs and charts.json disagree)."""
    if probabilities.shape[0] != textures.charts + 1 or coordinates.shape[0] != 2 * textures.charts:
        raise TextureMismatch(
            f"The texture head gives {probabilities.shape[0]} chart probabilities and "
            f"{coordinates.shape[0]} coordinates; its charts.json has {textures.charts} charts "
            f"(needs {textures.charts + 1} and {2 * textures.charts}).",
            "re-export the bundle with `rigspace train` (its graphs and charts.json disagree).",
        )


def _sample_rows(
    rows: Callable[[int, int], tuple], h: int, coverage: np.ndarray, kernel: bool
) -> None:
    """Run the sampler over the region's `h` rows, given its arguments for rows [i0, i1): the
    numpy reference, else the kernel, on two threads when enough pixels are covered."""
    if not kernel:
        sample_region_reference(*rows(0, h))
        return
    covered = np.cumsum(np.count_nonzero(coverage > 0, axis=1))
    if covered[-1] < SPLIT_PIXELS:
        _kernel()(*rows(0, h))
        return
    # Two threads, each on the rows holding half the covered pixels (the kernel releases the
    # GIL; the most likely charts both may find are the same values).
    middle = int(np.searchsorted(covered, covered[-1] // 2)) + 1
    other = _helper().submit(_kernel(), *rows(middle, h))
    _kernel()(*rows(0, middle))
    other.result()


# --- the numpy reference ------------------------------------------------------------------


def sample_region_reference(
    inverse, x0, y0, coverage, best, probabilities, coordinates, threshold, lod_bias, max_taps,
    minor_taps, center, half, image, transform, wrap, bounds, texels, levels, level_count, out, used, st_out,
    chart_out,
):  # fmt: skip
    """The kernel's computation in vectorised numpy, over all covered pixels at once (the
    texture reads through the embree renderer's sample_bilinear): the reference the compiled
    kernel (sdk/texture_kernel.py) is tested against."""
    ii, jj, nx, ny, jac, ok = _network_positions(inverse, x0, y0, coverage)
    cell, ok = _network_cell(nx, ny, best, ok)
    chart, ci, cj, ok = _choose_chart(cell, probabilities, threshold, image, ok)
    u, v, du, dv = _chart_coordinates(cell, chart, ci, cj, coordinates)
    footprint = _texel_footprint(
        chart, u, v, du, dv, jac, center, half, image, transform, bounds, levels
    )
    taps = _tap_grid(footprint, max_taps, minor_taps, lod_bias, level_count)
    colour = _filter_taps(
        footprint, taps, chart, ok, max_taps, transform, wrap, bounds, texels, levels, level_count
    )
    st = np.stack([footprint.s, footprint.t], axis=1)
    out[ii[ok], jj[ok]] = colour[ok]
    used[ii[ok], jj[ok]] = True
    st_out[ii[ok], jj[ok]] = st[ok]
    chart_out[ii[ok], jj[ok]] = chart[ok]


_CORNERS = tuple((a, b) for a in (0, 1) for b in (0, 1))
"""The four network pixels around a point, as (row, column) of the bilinear cell."""


@dataclass(frozen=True)
class _NetworkCell:
    """The four network pixels around each covered pixel, in _CORNERS order, and their weights."""

    rows: np.ndarray
    """(2, n) the cell's two network rows (clamped into the image)."""
    cols: np.ndarray
    """(2, n) the cell's two network columns (clamped into the image)."""
    wy: np.ndarray
    """(2, n) the bilinear weights of the two rows."""
    wx: np.ndarray
    """(2, n) the bilinear weights of the two columns."""
    chart_at: np.ndarray
    """(4, n) the most likely chart at each corner."""
    weight: np.ndarray
    """(4, n) the bilinear weight of each corner."""


@dataclass(frozen=True)
class _Footprint:
    """Each pixel's st, the image its chart reads and its footprint there (n pixels)."""

    s: np.ndarray
    t: np.ndarray
    su: np.ndarray
    """The st -> image scale along s."""
    sv: np.ndarray
    """The st -> image scale along t."""
    img: np.ndarray
    """The image read (0 where the chart has none: those pixels are not `ok`)."""
    width0: np.ndarray
    height0: np.ndarray
    ds: list[np.ndarray]
    """The footprint's axes (network x, network y) along s, in level-0 texels."""
    dt: list[np.ndarray]
    """The footprint's axes (network x, network y) along t, in level-0 texels."""


@dataclass(frozen=True)
class _Taps:
    """The grid of taps each pixel's footprint is read with, and their mip level."""

    taps_x: np.ndarray
    taps_y: np.ndarray
    level: np.ndarray
    blend: np.ndarray
    """The share of the next (smaller) mip level in each tap (trilinear)."""


def _network_positions(
    inverse: np.ndarray, x0: int, y0: int, coverage: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[list[np.ndarray]], np.ndarray]:
    """Each covered pixel's (ii, jj) in the region, network position (nx, ny), Jacobian, `ok`."""
    ii, jj = np.nonzero(coverage > 0)
    px, py = x0 + jj + 0.5, y0 + ii + 0.5
    qx, qy, qw = (inverse[k, 0] * px + inverse[k, 1] * py + inverse[k, 2] for k in range(3))
    ok = qw > 0
    qw = np.where(ok, qw, 1.0)
    nx, ny = qx / qw, qy / qw
    # d(network position)/d(frame pixel): the homography's Jacobian.
    jac = [
        [(inverse[a, b] - n * inverse[2, b]) / qw for b in (0, 1)] for a, n in ((0, nx), (1, ny))
    ]
    return ii, jj, nx, ny, jac, ok


def _network_cell(
    nx: np.ndarray, ny: np.ndarray, best: np.ndarray, ok: np.ndarray
) -> tuple[_NetworkCell, np.ndarray]:
    """The bilinear cell of network pixels around each position; `ok` without those outside."""
    r = best.shape[0]
    xs, ys = nx - 0.5, ny - 0.5
    ok &= (xs >= -0.5) & (ys >= -0.5) & (xs <= r - 0.5) & (ys <= r - 0.5)
    j0, i0 = np.floor(xs).astype(np.int64), np.floor(ys).astype(np.int64)
    fx, fy = xs - j0, ys - i0
    rows = np.stack([np.clip(i0, 0, r - 1), np.clip(i0 + 1, 0, r - 1)])
    cols = np.stack([np.clip(j0, 0, r - 1), np.clip(j0 + 1, 0, r - 1)])
    wy, wx = np.stack([1 - fy, fy]), np.stack([1 - fx, fx])
    chart_at = np.stack([best[rows[a], cols[b]] for a, b in _CORNERS])  # (4, n)
    weight = np.stack([wy[a] * wx[b] for a, b in _CORNERS])
    return _NetworkCell(rows, cols, wy, wx, chart_at, weight), ok


def _choose_chart(
    cell: _NetworkCell,
    probabilities: np.ndarray,
    threshold: float,
    image: np.ndarray,
    ok: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's chart, the nearest corner showing it (ci, cj); `ok` without unsure pixels."""
    rows, cols, chart_at, weight = cell.rows, cell.cols, cell.chart_at, cell.weight

    def interpolated(charts):  # each pixel's probability of `charts` (n,), bilinearly
        return sum(
            weight[k] * probabilities[charts, rows[a], cols[b]] for k, (a, b) in enumerate(_CORNERS)
        )

    # Of the corners' charts, the largest interpolated probability (the first on ties).
    score = np.stack([np.where(c > 0, interpolated(c), -1.0) for c in chart_at])
    n = np.arange(chart_at.shape[1])
    chart = chart_at[score.argmax(axis=0), n]
    given = score.max(axis=0)
    none = interpolated(np.zeros(chart_at.shape[1], np.int64))
    # The nearest corner that shows the chart (its coordinates if no other does).
    pick = np.where(chart_at == chart, weight, -1.0).argmax(axis=0)
    ci = np.stack([rows[a] for a, _ in _CORNERS])[pick, n]
    cj = np.stack([cols[b] for _, b in _CORNERS])[pick, n]
    ok &= (chart > 0) & (given >= threshold * np.maximum(1.0 - none, 1e-6)) & (image[chart] >= 0)
    return chart, ci, cj, ok


def _chart_coordinates(
    cell: _NetworkCell, chart: np.ndarray, ci: np.ndarray, cj: np.ndarray, coordinates: np.ndarray
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """The chart's coordinates (u, v) interpolated over the corners showing it, and their
    derivatives (du, dv) along network x and y."""
    rows, cols, chart_at, weight = cell.rows, cell.cols, cell.chart_at, cell.weight
    pair = np.maximum(chart - 1, 0)
    u_at = np.stack([coordinates[2 * pair, rows[a], cols[b]] for a, b in _CORNERS])
    v_at = np.stack([coordinates[2 * pair + 1, rows[a], cols[b]] for a, b in _CORNERS])
    same = chart_at == chart
    total = (weight * same).sum(axis=0)
    own_u, own_v = coordinates[2 * pair, ci, cj], coordinates[2 * pair + 1, ci, cj]
    safe = np.where(total > 0, total, 1.0)
    u = np.where(total > 0, (weight * same * u_at).sum(axis=0) / safe, own_u)
    v = np.where(total > 0, (weight * same * v_at).sum(axis=0) / safe, own_v)
    du, dv = _coordinate_derivatives(cell, same, u_at, v_at, u)
    return u, v, du, dv


def _coordinate_derivatives(
    cell: _NetworkCell, same: np.ndarray, u_at: np.ndarray, v_at: np.ndarray, u: np.ndarray
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(du, dv): the chart's coordinates' derivatives, each [along network x, along y]."""
    rows, cols, wy, wx = cell.rows, cell.cols, cell.wy, cell.wx
    # Derivatives along network x (pairs in a row) and y (pairs in a column), same chart only.
    du, dv = [], []
    for first, second, row_weight, distinct in (
        ((0, 1), (2, 3), wy, cols[0] != cols[1]),
        ((0, 2), (1, 3), wx, rows[0] != rows[1]),
    ):
        acc_u, acc_v, acc_w = np.zeros_like(u), np.zeros_like(u), np.zeros_like(u)
        for k, (p, q) in enumerate((first, second)):
            valid = distinct & same[p] & same[q]
            acc_u = acc_u + np.where(valid, row_weight[k] * (u_at[q] - u_at[p]), 0.0)
            acc_v = acc_v + np.where(valid, row_weight[k] * (v_at[q] - v_at[p]), 0.0)
            acc_w = acc_w + np.where(valid, row_weight[k], 0.0)
        du.append(np.where(acc_w > 0, acc_u / np.maximum(acc_w, 1e-30), 0.0))
        dv.append(np.where(acc_w > 0, acc_v / np.maximum(acc_w, 1e-30), 0.0))
    return du, dv


def _texel_footprint(
    chart: np.ndarray, u: np.ndarray, v: np.ndarray, du: list[np.ndarray], dv: list[np.ndarray],
    jac: list[list[np.ndarray]], center: np.ndarray, half: np.ndarray, image: np.ndarray,
    transform: np.ndarray, bounds: np.ndarray, levels: np.ndarray,
) -> _Footprint:  # fmt: skip
    """Each pixel's st (in its chart's bounds) and footprint in its image's level-0 texels."""
    hu, hv = half[chart, 0], half[chart, 1]
    s = np.clip(center[chart, 0] + hu * u, bounds[chart, 0], bounds[chart, 2])
    t = np.clip(center[chart, 1] + hv * v, bounds[chart, 1], bounds[chart, 3])
    su, sv = transform[chart, 0], transform[chart, 1]
    img = np.maximum(image[chart], 0)
    width0, height0 = levels[img, 0, 1], levels[img, 0, 2]
    ds = [hu * su * (du[0] * jac[0][b] + du[1] * jac[1][b]) * width0 for b in (0, 1)]
    dt = [hv * sv * (dv[0] * jac[0][b] + dv[1] * jac[1][b]) * height0 for b in (0, 1)]
    return _Footprint(s, t, su, sv, img, width0, height0, ds, dt)


def _tap_grid(
    footprint: _Footprint, max_taps: int, minor_taps: int, lod_bias: float, level_count: np.ndarray
) -> _Taps:
    """The grid of taps each footprint is read with and the mip level (trilinear) they read."""
    ds, dt = footprint.ds, footprint.dt
    # The footprint (axes (ds[0], dt[0]) and (ds[1], dt[1]) in level-0 texels) as a grid of
    # taps, each at most `cell` texels along both axes, read at that size's mip level.
    length_x, length_y = np.hypot(ds[0], dt[0]), np.hypot(ds[1], dt[1])
    cell = np.maximum(
        np.maximum(1.0, np.minimum(length_x, length_y) / minor_taps),
        np.maximum(length_x, length_y) / max_taps,
    )
    taps_x = np.clip(np.ceil(length_x / cell - 1e-9), 1, max_taps).astype(np.int64)
    taps_y = np.clip(np.ceil(length_y / cell - 1e-9), 1, max_taps).astype(np.int64)
    lod = np.minimum(np.maximum(np.log2(cell) + lod_bias, 0.0), level_count[footprint.img] - 1.0)
    level = np.floor(lod).astype(np.int64)
    blend = lod - level
    return _Taps(taps_x, taps_y, level, blend)


def _filter_taps(
    footprint: _Footprint, taps: _Taps, chart: np.ndarray, ok: np.ndarray, max_taps: int,
    transform: np.ndarray, wrap: np.ndarray, bounds: np.ndarray, texels: np.ndarray,
    levels: np.ndarray, level_count: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """(n, 3) each pixel's colour: the mean of its taps, each a trilinear texture read."""
    from rigspace.sdk.render.embree import sample_bilinear

    s, t, su, sv, img = footprint.s, footprint.t, footprint.su, footprint.sv, footprint.img
    width0, height0, ds, dt = footprint.width0, footprint.height0, footprint.ds, footprint.dt
    taps_x, taps_y, level, blend = taps.taps_x, taps.taps_y, taps.level, taps.blend
    colour = np.zeros((len(s), 3))
    # The footprint's axes in st (texels / image size / the st -> image scale).
    axis_x = np.stack([ds[0] / (width0 * su), dt[0] / (height0 * sv)], axis=1)
    axis_y = np.stack([ds[1] / (width0 * su), dt[1] / (height0 * sv)], axis=1)
    count = (taps_x * taps_y)[:, None]
    for kx in range(int(max_taps)):
        for ky in range(int(max_taps)):
            tapping = ok & (kx < taps_x) & (ky < taps_y)
            ox = ((kx + 0.5) / taps_x - 0.5)[:, None]
            oy = ((ky + 0.5) / taps_y - 0.5)[:, None]
            # Each tap in the chart's bounds (a UDIM chart's tile), then in the image.
            tap_s = np.clip(
                s + ox[:, 0] * axis_x[:, 0] + oy[:, 0] * axis_y[:, 0],
                bounds[chart, 0],
                bounds[chart, 2],
            )
            tap_t = np.clip(
                t + ox[:, 0] * axis_x[:, 1] + oy[:, 0] * axis_y[:, 1],
                bounds[chart, 1],
                bounds[chart, 3],
            )
            at = np.stack(
                [tap_s * su + transform[chart, 2], tap_t * sv + transform[chart, 3]], axis=1
            )
            for index in np.unique(img[tapping]):
                for lvl in range(int(level_count[index])):
                    offset0, width, height = levels[index, lvl]
                    texture = texels[offset0 : offset0 + width * height].reshape(height, width, 3)
                    for k in np.unique(chart[tapping & (img == index)]):
                        mine = tapping & (chart == k)
                        here = mine & (level == lvl)
                        below = mine & (level + 1 == lvl) & (blend > 0)
                        for where, part in ((here, 1 - blend), (below, blend)):
                            if where.any():
                                read = sample_bilinear(texture, at[where], tuple(wrap[k]))
                                colour[where] += read * (part[where, None] / count[where])
    return colour


SPLIT_PIXELS = 2_000
"""Covered pixels from which the kernel samples on two threads (a 256x256 previs frame's
character covers about 2,800; half the sampler's time there, on a second core)."""


@functools.cache
def _helper() -> ThreadPoolExecutor:
    """The sampler's second thread (one per process, started on first use)."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="rigspace-texture")


def _kernel():
    """The compiled kernel (sdk/texture_kernel.py: numba, cached on disk), imported on first
    use so that reading this module needs no numba."""
    from rigspace.sdk.texture_kernel import sample_region

    return sample_region


WARP_INTERPOLATION = 1  # cv2.INTER_LINEAR
"""How the network's maps are resampled into a frame (bilinear)."""
COLOUR_EPSILON = 1e-3
"""Alpha below which the albedo branch's colour is taken as empty (no edge to follow)."""


def region_warper(homography: np.ndarray, region: tuple[int, int, int, int]):
    """A function warping a (C, R, R) network map into the frame region (x0, y0, w, h) as
    (h, w, C), bilinear, through `homography` (network pixel coordinates to frame pixel
    coordinates; pixel k spans [k, k+1) in both), zero outside the network image."""
    import cv2

    x0, y0, w, h = region
    shift = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], dtype=np.float64)
    # OpenCV maps pixel centres at integer coordinates; ours sit at +0.5.
    centre = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
    matrix = np.linalg.inv(centre) @ shift @ np.asarray(homography, np.float64) @ centre

    def warp(image: np.ndarray) -> np.ndarray:
        hwc = np.ascontiguousarray(np.moveaxis(image, 0, -1), dtype=np.float32)
        warped = cv2.warpPerspective(
            hwc, matrix, (w, h), flags=WARP_INTERPOLATION, borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )  # fmt: skip
        return warped.reshape(h, w, -1)

    return warp


def display_colour(
    out: dict[str, np.ndarray],
    homography: np.ndarray,
    region: tuple[int, int, int, int],
    coverage: np.ndarray,
    textures: ChartTextures | None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """A character's colour and coverage over a frame region from one sample's network maps
    (`out`: CHW, the bundle's names).

    Coverage (h, w): `coverage` as warped (the geometry mask, or the albedo branch's alpha)
    sharpened. Colour: from the textures where the texture head says (sample_textures), the
    albedo branch's elsewhere (its colour divided by its own alpha), premultiplied by that
    coverage, so that no pixel's colour claims more than the layer's mask (a colour
    premultiplied by the albedo branch's wider alpha lit a pale halo around the silhouette).
    Where the coverage is the alpha (unlit) and nothing is magnified, the albedo branch's
    premultiplied colour passes through unchanged. `info` holds, when there is a texture
    head, "textured" (the share of covered pixels the textures coloured), "texture_ms" (the
    sampler's milliseconds) and "sample" (the TextureSample: st and chart per pixel)."""
    warp = region_warper(homography, region)
    scale = magnification(homography, region)
    sharp = sharpen_coverage(coverage, scale)
    alpha = np.clip(warp(out["alpha"])[..., 0], 0.0, 1.0) if "alpha" in out else coverage
    colour = repremultiplied(np.clip(warp(out["albedo"]), 0.0, 1.0), alpha, sharp)
    info: dict = {}
    if textures is not None and "chart" in out:
        began = time.perf_counter()
        sample = sample_textures(textures, homography, region, sharp, out["chart"], out["uv"])
        info["texture_ms"] = round(1e3 * (time.perf_counter() - began), 3)
        colour = np.where(sample.used[..., None], sample.colour * sharp[..., None], colour)
        covered = max(int(np.count_nonzero(sharp > 0)), 1)
        info["textured"] = round(float(sample.used.sum()) / covered, 4)
        info["sample"] = sample
    return colour.astype(np.float32), sharp, info


def repremultiplied(albedo: np.ndarray, alpha: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """(..., 3) the albedo branch's colour (`albedo`, premultiplied by its own `alpha`, (...))
    premultiplied by `coverage` (...) instead, never above it; 0 where the alpha is under
    COLOUR_EPSILON. The two branches' edges differ by a pixel or two (the alpha is the wider),
    and a colour premultiplied by a wider coverage than the layer's mask lights the background
    around the silhouette (a pale halo). Exactly `albedo` where the coverage is the alpha."""
    gain = np.divide(coverage, alpha, out=np.zeros_like(coverage), where=alpha > COLOUR_EPSILON)
    return np.minimum(albedo * gain[..., None], coverage[..., None])


def magnification(homography: np.ndarray, region: tuple[int, int, int, int]) -> float:
    """Frame pixels per network pixel at a region's centre (the homography's local scale);
    1 (no sharpening) for a degenerate homography, as a billboard seen edge-on in a
    viewport a few pixels wide gives (found by tests/bench/test_stability.py)."""
    h = np.asarray(homography, np.float64)
    try:
        inverse = np.linalg.inv(h)
    except np.linalg.LinAlgError:
        return 1.0
    x0, y0, w, height = region
    centre = inverse @ np.array([x0 + w / 2, y0 + height / 2, 1.0])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        q = centre[:2] / centre[2]
        p = h @ np.array([q[0], q[1], 1.0])
        jacobian = (h[:2, :2] - np.outer(p[:2] / p[2], h[2, :2])) / p[2]
        scale = float(np.sqrt(abs(np.linalg.det(jacobian))))
    return scale if np.isfinite(scale) else 1.0


def sharpen_coverage(coverage: np.ndarray, scale: float) -> np.ndarray:
    """Coverage upsampled `scale` times from the network's image, with its edge made one frame
    pixel wide again.

    Bilinear upsampling turns the network's edge into a ramp about `scale` pixels wide around
    its 0.5 level line, where the network puts the edge. Stretching the coverage about 0.5 by
    `scale` (c' = 0.5 + scale (c - 0.5), clipped) keeps that line and makes the ramp one pixel
    wide: a crisp, anti-aliased silhouette. It is a contrast stretch, not a threshold: a limb
    thinner than a network pixel keeps a (weaker) coverage. At scale <= SHARP_RAMP (no or
    little magnification) the coverage is kept as it is.
    """
    c = np.asarray(coverage, np.float32)
    if scale <= SHARP_RAMP:
        return c
    return np.clip((c - np.float32(0.5)) * np.float32(scale / EDGE_PIXELS) + 0.5, 0.0, 1.0)

"""Texture charts: the pieces of a character's surface on which texture coordinates are continuous.

The network's texture head (train/network.py) predicts, per pixel, which chart the visible
surface belongs to and where it lands on the texture within that chart; the runtime then
samples the material's own texture there (rigspace.sdk.texturing). A chart is a set of
triangles of one textured mesh, inside one UDIM tile, whose corner uvs agree across every
edge the triangles share on the surface, so a chart's coordinate field is continuous
wherever the chart is seen and can be interpolated without ever blending across a seam:

1. Islands: triangles joined across shared edges (points welded by position, so meshes
   split at their uv seams, as glTF exports are, join too) whose two uv pairs agree within
   SEAM_TEXELS; connected components.
2. Slivers (islands of fewer than MIN_CHART_TRIANGLES, such as the one-u-per-triangle
   poles of a cylindrical projection) join the neighbour they share most edges with.
3. Wraps: an island can close on itself, a cylinder unwrapped to a rectangle whose two ends
   meet on the surface. Its seam edges join triangles of the same island, so it is split at
   the median of its triangles' uv along the jumps' direction (recursively, at most
   MAX_SPLITS deep) until no seam longer than WRAP_FRACTION of a chart's extent is left
   inside one chart.
4. UDIM tiles: a chart lies in the tile of its triangles' uv centroids; one spanning tiles
   is split by tile.

Chart 0 is "no chart": background, and surfaces whose colour no texture drives. Charts are
numbered 1..K in mesh order, then by first triangle, so the same meshes give the same table.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import numpy as np

SEAM_TEXELS = 1.0
"""Corner uvs further apart than this many texels (of the larger texture side) across a
shared edge make that edge a seam."""
MIN_CHART_TRIANGLES = 16
"""Islands smaller than this join a neighbour (poles, slivers): too small to learn apart."""
WRAP_FRACTION = 0.5
"""A seam inside an island whose uv jump exceeds this share of the island's uv extent (along
the jump) is a wrap, and the island is split across it; smaller jumps (a pole's) are kept."""
MAX_SPLITS = 1
"""How many times an island is halved at most while wraps remain inside a piece."""
WELD_DECIMALS = 6
"""Points are welded when their positions agree to this many decimals of the mesh's extent."""


@dataclass(frozen=True)
class Chart:
    """One chart: where its texture comes from and the uv box its coordinates span."""

    index: int
    """1..K; 0 is reserved for "no chart"."""
    mesh: str
    """The mesh prim's path relative to the character prim ('Body', 'Asset/Body', ...)."""
    tile: int
    """UDIM tile number (1001 + u tile + 10 v tile) of its uvs."""
    uv_min: tuple[float, float]
    uv_max: tuple[float, float]
    """The uv box of its triangles' corners: the network's coordinates are in [-1, 1] over it."""
    triangles: int

    def to_json(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "mesh": self.mesh,
            "tile": self.tile,
            "uv_min": [float(x) for x in self.uv_min],
            "uv_max": [float(x) for x in self.uv_max],
            "triangles": self.triangles,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Chart:
        return cls(
            index=int(data["index"]),
            mesh=str(data["mesh"]),
            tile=int(data["tile"]),
            uv_min=(float(data["uv_min"][0]), float(data["uv_min"][1])),
            uv_max=(float(data["uv_max"][0]), float(data["uv_max"][1])),
            triangles=int(data["triangles"]),
        )

    @property
    def center(self) -> np.ndarray:
        return (np.asarray(self.uv_min) + np.asarray(self.uv_max)) / 2

    @property
    def half(self) -> np.ndarray:
        """Half the box's size, floored so a degenerate chart does not divide by zero."""
        return np.maximum((np.asarray(self.uv_max) - np.asarray(self.uv_min)) / 2, 1e-6)


def udim_tile(uv: np.ndarray) -> np.ndarray:
    """UDIM tile numbers of uv points (..., 2): 1001 + floor(u) + 10 floor(v)."""
    tiles = np.floor(np.asarray(uv, dtype=np.float64)).astype(np.int64)
    return 1001 + tiles[..., 0] + 10 * tiles[..., 1]


def _edges(points: np.ndarray, triangles: np.ndarray, corner_uv: np.ndarray, texels: float):
    """Pairs of triangles sharing an edge on the surface (points welded by position), and the
    uv jump across each pair's edge in texels."""
    p = np.asarray(points, dtype=np.float64)
    extent = float(np.ptp(p, axis=0).max()) if len(p) else 1.0
    key = np.round(p / max(extent, 1e-30), WELD_DECIMALS)
    _, welded = np.unique(key, axis=0, return_inverse=True)
    welded = welded.reshape(-1)
    t = welded[triangles]
    a, b = t.reshape(-1), t[:, [1, 2, 0]].reshape(-1)
    uva = corner_uv.reshape(-1, 2).astype(np.float64)
    uvb = corner_uv[:, [1, 2, 0]].reshape(-1, 2).astype(np.float64)
    face = np.repeat(np.arange(len(triangles)), 3)
    swap = a > b  # each edge's uvs ordered by its welded end points
    uv_lo = np.where(swap[:, None], uvb, uva)
    uv_hi = np.where(swap[:, None], uva, uvb)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keep = lo != hi  # degenerate edges (welded ends) join nothing
    edge = lo.astype(np.int64) * (int(welded.max(initial=0)) + 1) + hi
    order = np.argsort(np.where(keep, edge, -1), kind="stable")
    order = order[keep[order]]
    sorted_edge = edge[order]
    pair = np.flatnonzero(sorted_edge[1:] == sorted_edge[:-1])
    i, j = order[pair], order[pair + 1]
    jump = np.maximum(
        np.abs(uv_lo[i] - uv_lo[j]).max(axis=1), np.abs(uv_hi[i] - uv_hi[j]).max(axis=1)
    )
    return face[i], face[j], jump * texels, (uv_lo[j] - uv_lo[i])


def components(n: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Connected components of n nodes joined by edges (i, j): each node's smallest member.

    Label hooking with pointer jumping (vectorised; a few dozen rounds for a mesh)."""
    label = np.arange(n)
    while True:
        li, lj = label[i], label[j]
        differ = li != lj
        if not differ.any():
            return label
        np.minimum.at(label, np.maximum(li, lj)[differ], np.minimum(li, lj)[differ])
        while True:
            jumped = label[label]
            if np.array_equal(jumped, label):
                break
            label = jumped


def _absorb_slivers(label: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Islands under MIN_CHART_TRIANGLES join the neighbouring island they share most edges with
    (repeated until none is left that has a neighbour)."""
    for _ in range(64):
        sizes = np.bincount(label, minlength=len(label))
        small = sizes[label] < MIN_CHART_TRIANGLES
        li, lj = label[i], label[j]
        across = li != lj
        # Edges from a small island to another island, both directions.
        src = np.concatenate([li[across], lj[across]])
        dst = np.concatenate([lj[across], li[across]])
        take = sizes[src] < MIN_CHART_TRIANGLES
        src, dst = src[take], dst[take]
        if not len(src) or not small.any():
            return label
        # The neighbour with the most shared edges (ties: the larger, then the smaller label).
        pairs, counts = np.unique(np.stack([src, dst], 1), axis=0, return_counts=True)
        order = np.lexsort((pairs[:, 1], -sizes[pairs[:, 1]], -counts, pairs[:, 0]))
        pairs = pairs[order]
        first = np.ones(len(pairs), bool)
        first[1:] = pairs[1:, 0] != pairs[:-1, 0]
        # Each small island joins its chosen neighbour: components of those joins (small
        # islands choosing each other, in a pair or a ring, end up together).
        merged = components(len(label), pairs[first, 0], pairs[first, 1])
        label = merged[label]
    return label


def _split_wraps(
    label: np.ndarray, centroid: np.ndarray, i: np.ndarray, j: np.ndarray, delta: np.ndarray, seam
) -> np.ndarray:
    """Halve islands that hold a wrap (a long seam between their own triangles), recursively."""
    for _ in range(MAX_SPLITS):
        inside = (label[i] == label[j]) & seam
        if not inside.any():
            return label
        new = label.copy()
        next_label = len(label)
        for island in np.unique(label[i[inside]]):
            members = np.flatnonzero(label == island)
            extent = np.ptp(centroid[members], axis=0)
            mine = inside & (label[i] == island)
            jumps = np.abs(delta[mine])
            axis = int(np.argmax(jumps.sum(axis=0)))
            if not (jumps[:, axis] > WRAP_FRACTION * max(extent[axis], 1e-12)).any():
                continue  # small jumps only (a pole's): not a wrap
            cut = np.median(centroid[members, axis])
            upper = members[centroid[members, axis] > cut]
            if 0 < len(upper) < len(members):
                new[upper] = next_label + island
        if np.array_equal(new, label):
            return label
        # A half may fall apart into pieces: components within each label again (over any
        # shared edge, so slivers absorbed across a small seam stay with their chart).
        join = new[i] == new[j]
        label = _absorb_slivers(components(len(label), i[join], j[join]), i, j)
    return label


def mesh_charts(
    points: np.ndarray, triangles: np.ndarray, corner_uv: np.ndarray, texture_size: int
) -> np.ndarray:
    """(T,) the chart of each triangle, numbered 0..n-1 by first triangle (see the module)."""
    triangles = np.asarray(triangles, dtype=np.int64)
    corner_uv = np.asarray(corner_uv, dtype=np.float64)
    n = len(triangles)
    if n == 0:
        return np.zeros(0, np.int32)
    fi, fj, jump, delta = _edges(points, triangles, corner_uv, float(texture_size))
    seam = jump > SEAM_TEXELS
    label = components(n, fi[~seam], fj[~seam])
    label = _absorb_slivers(label, fi, fj)
    centroid = corner_uv.mean(axis=1)
    label = _split_wraps(label, centroid, fi, fj, delta, seam)
    # UDIM: a chart whose triangles sit in several tiles becomes one chart per tile.
    tile = udim_tile(centroid)
    _, label = np.unique(np.stack([label, tile], 1), axis=0, return_inverse=True)
    label = label.reshape(-1)
    # Numbered by each chart's first triangle: independent of how labels were merged.
    first = np.full(label.max() + 1, n)
    np.minimum.at(first, label, np.arange(n))
    rank = np.argsort(np.argsort(first))
    return rank[label].astype(np.int32)


def parse_charts(data: Any) -> tuple[Chart, ...]:
    """The charts of a charts.json's content, checked; a ValueError says what is wrong (the
    caller names the file and the fix). Chart indices must be exactly 1..K in order, so an
    index read from a network's output always finds its chart."""
    if not isinstance(data, dict) or data.get("format") != "rigspace.charts":
        raise ValueError("it is not a rigspace chart table (format rigspace.charts)")
    charts = data.get("charts")
    if not isinstance(charts, list):
        raise ValueError("its 'charts' is not a list")
    out = []
    for k, entry in enumerate(charts, start=1):
        try:
            chart = Chart.from_json(entry)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ValueError(
                f"chart {k} is incomplete or mistyped ({type(exc).__name__}: {exc})"
            ) from exc
        if chart.index != k:
            raise ValueError(f"chart {k} has index {chart.index}; indices must run 1..K in order")
        box = np.array([*chart.uv_min, *chart.uv_max])
        if not np.all(np.isfinite(box)) or np.any(box[:2] > box[2:]):
            raise ValueError(f"chart {k}'s uv box {chart.uv_min} .. {chart.uv_max} is not a box")
        out.append(chart)
    meshes = data.get("meshes", [])
    if not isinstance(meshes, list) or not all(isinstance(m, dict) and "mesh" in m for m in meshes):
        raise ValueError("its 'meshes' is not a list of {mesh, triangles, uv_fingerprint}")
    return tuple(out)


@dataclass(frozen=True)
class ChartedMesh:
    """A textured mesh's charts: the global chart of each triangle (1..K)."""

    mesh: str
    triangle_chart: np.ndarray
    """(T,) int32 global chart index of each triangle."""
    fingerprint: str
    """sha256 of the mesh's triangles and corner uvs: the layout the charts were made for."""

    def __post_init__(self) -> None:
        self.triangle_chart.flags.writeable = False  # renderers cache it by identity (DrawMesh)


def uv_fingerprint(triangles: np.ndarray, corner_uv: np.ndarray) -> str:
    """A mesh's uv layout as a hash (triangles and corner uvs, float32 as stored)."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(triangles, dtype=np.int32).tobytes())
    digest.update(np.ascontiguousarray(corner_uv, dtype=np.float32).tobytes())
    return digest.hexdigest()


@dataclass(frozen=True)
class ChartTable:
    """Every chart of a character, and which triangles of which mesh belong to it."""

    charts: tuple[Chart, ...]
    meshes: tuple[ChartedMesh, ...]

    def __len__(self) -> int:
        return len(self.charts)

    def to_json(self) -> dict[str, Any]:
        return {
            "format": "rigspace.charts",
            "format_version": 1,
            "charts": [c.to_json() for c in self.charts],
            "meshes": [
                {
                    "mesh": m.mesh,
                    "triangles": len(m.triangle_chart),
                    "uv_fingerprint": m.fingerprint,
                }
                for m in self.meshes
            ],
        }

    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """(K+1, 2) centres and half sizes of the charts' uv boxes; row 0 (no chart) is (0, 1)."""
        center = np.zeros((len(self.charts) + 1, 2))
        half = np.ones((len(self.charts) + 1, 2))
        for c in self.charts:
            center[c.index], half[c.index] = c.center, c.half
        return center, half


def chart_table(
    meshes: list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None, int]],
) -> ChartTable:
    """The charts of a character's meshes, given per mesh (relative path, points, triangles,
    corner uv or None when no texture drives its colour, texture size in texels)."""
    charts: list[Chart] = []
    charted: list[ChartedMesh] = []
    for name, points, triangles, corner_uv, size in meshes:
        if corner_uv is None or len(triangles) == 0:
            continue
        local = mesh_charts(points, triangles, corner_uv, size)
        offset = len(charts)
        centroid = np.asarray(corner_uv, np.float64).mean(axis=1)
        for k in range(int(local.max()) + 1):
            members = local == k
            uv = np.asarray(corner_uv, np.float64)[members].reshape(-1, 2)
            charts.append(
                Chart(
                    index=offset + k + 1,
                    mesh=name,
                    tile=int(udim_tile(centroid[members][:1])[0]),
                    uv_min=(float(uv[:, 0].min()), float(uv[:, 1].min())),
                    uv_max=(float(uv[:, 0].max()), float(uv[:, 1].max())),
                    triangles=int(members.sum()),
                )
            )
        charted.append(
            ChartedMesh(
                name, (local + offset + 1).astype(np.int32), uv_fingerprint(triangles, corner_uv)
            )
        )
    return ChartTable(tuple(charts), tuple(charted))

"""Texture charts: islands of continuous uvs, slivers joined, wraps cut, UDIM tiles apart, and
the sample character's and CesiumMan's charts free of seams inside a chart."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.sdk.charts import (
    SEAM_TEXELS,
    _edges,
    chart_table,
    components,
    mesh_charts,
    parse_charts,
    udim_tile,
    uv_fingerprint,
)
from rigspace.sdk.geometry import read_mesh_source
from rigspace.sdk.stage import open_stage
from tests.conftest import CESIUM_MAN, REPO

TEXELS = 256


def grid(columns: int, rows: int, uv_of) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A (columns x rows) grid of quads as triangles, corner uvs from uv_of(x, y)."""
    points = np.array(
        [(x, y, 0.0) for y in range(rows + 1) for x in range(columns + 1)], np.float32
    )
    triangles, corner_uv = [], []
    for y in range(rows):
        for x in range(columns):
            a = y * (columns + 1) + x
            quad = [
                (a, x, y),
                (a + 1, x + 1, y),
                (a + columns + 2, x + 1, y + 1),
                (a + columns + 1, x, y + 1),
            ]
            for tri in ((0, 1, 2), (0, 2, 3)):
                triangles.append([quad[k][0] for k in tri])
                corner_uv.append([uv_of(quad[k][1], quad[k][2], x, y) for k in tri])
    return points, np.array(triangles, np.int32), np.array(corner_uv, np.float32)


def test_components_join_what_edges_join():
    label = components(6, np.array([0, 1, 4]), np.array([1, 2, 5]))
    assert len(set(label[[0, 1, 2]])) == 1 and label[3] not in label[[0, 4]]
    assert label[4] == label[5] and label[4] != label[0]


def test_a_continuous_sheet_is_one_chart_and_a_cut_makes_two():
    points, triangles, uv = grid(8, 4, lambda x, y, *_: (x / 8, y / 4))
    assert set(mesh_charts(points, triangles, uv, TEXELS)) == {0}
    # The same surface with its right half moved elsewhere in the texture: a seam at x = 4.
    moved = lambda x, y, cx, cy: (x / 16 + (0.5 if cx >= 4 else 0.0), y / 4)  # noqa: E731
    points, triangles, uv = grid(8, 4, moved)
    charts = mesh_charts(points, triangles, uv, TEXELS)
    assert set(charts) == {0, 1}
    left = np.array([c[:, 0].min() < 0.5 for c in uv])
    assert len(set(charts[left])) == 1 and len(set(charts[~left])) == 1


def test_a_closed_cylinder_is_cut_where_its_uvs_wrap():
    """A tube whose u runs once round: one island, whose two ends meet on the surface. It is
    halved so that no chart holds the wrap (its seam edges join triangles of two charts)."""
    segments, rings = 16, 4
    angle = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    points = np.array(
        [(np.cos(a), h, np.sin(a)) for h in range(rings + 1) for a in angle], np.float32
    )
    triangles, uv = [], []
    for r in range(rings):
        for k in range(segments):
            a, b = r * segments + k, r * segments + (k + 1) % segments
            corners = [
                (a, k, r),
                (b, k + 1, r),
                (b + segments, k + 1, r + 1),
                (a + segments, k, r + 1),
            ]
            for tri in ((0, 1, 2), (0, 2, 3)):
                triangles.append([corners[i][0] for i in tri])
                uv.append([(corners[i][1] / segments, corners[i][2] / rings) for i in tri])
    triangles, uv = np.array(triangles, np.int32), np.array(uv, np.float32)
    charts = mesh_charts(points, triangles, uv, TEXELS)
    assert len(set(charts)) == 2
    fi, fj, jump, _ = _edges(points, triangles, uv, TEXELS)
    seams = jump > SEAM_TEXELS
    assert seams.any() and not np.any(charts[fi[seams]] == charts[fj[seams]])


def test_slivers_join_a_neighbour_and_udim_tiles_stay_apart():
    # One column of quads gets its own uvs (a sliver of 8 triangles): it joins its island.
    sliver = lambda x, y, cx, cy: (x / 16 + (0.3 if cx == 7 else 0.0), y / 4)  # noqa: E731
    points, triangles, uv = grid(8, 4, sliver)
    assert set(mesh_charts(points, triangles, uv, TEXELS)) == {0}
    # The same sheet laid over two UDIM tiles: one chart per tile.
    points, triangles, uv = grid(8, 4, lambda x, y, *_: (x / 4, y / 4 * 0.9))
    charts = mesh_charts(points, triangles, uv, TEXELS)
    tiles = udim_tile(uv.mean(axis=1))
    assert set(tiles) == {1001, 1002} and len(set(charts)) == 2
    assert all(len(set(tiles[charts == c])) == 1 for c in set(charts))
    assert udim_tile(np.array([[0.5, 0.5], [1.5, 0.2], [0.2, 1.5]])).tolist() == [1001, 1002, 1011]


def test_a_table_numbers_charts_from_one_and_fingerprints_the_layout():
    points, triangles, uv = grid(8, 4, lambda x, y, *_: (x / 8, y / 4))
    table = chart_table(
        [("A", points, triangles, uv, TEXELS), ("Plain", points, triangles, None, 1)]
    )
    assert [c.index for c in table.charts] == [1] and table.charts[0].mesh == "A"
    assert table.charts[0].uv_min == (0.0, 0.0) and table.charts[0].uv_max == (1.0, 1.0)
    (mesh,) = table.meshes
    assert np.all(mesh.triangle_chart == 1) and mesh.fingerprint == uv_fingerprint(triangles, uv)
    assert uv_fingerprint(triangles, uv * 1.01) != mesh.fingerprint
    again = chart_table([("A", points, triangles, uv, TEXELS)])
    assert again.to_json() == table.to_json()  # the same meshes give the same table


@pytest.mark.parametrize(
    "path, prim, most",
    [
        (REPO / "samples" / "character" / "sample_character.usda", "/Character/Body", 32),
        (CESIUM_MAN, None, 24),
    ],
)
def test_real_characters_have_few_charts_and_few_seams_inside_them(path, prim, most):
    """The sample character (cylindrical projections per body part, 14 parts) and CesiumMan (a
    glTF export, split at its seams): a handful of charts each, and seams inside a chart only
    where a projection degenerates (a pole), under 0.5 % of the shared edges."""
    stage = open_stage(path)
    prims = (
        [stage.GetPrimAtPath(prim)]
        if prim
        else [p for p in stage.Traverse() if p.GetTypeName() == "Mesh"]
    )
    for mesh_prim in prims:
        mesh = read_mesh_source(mesh_prim)
        size = max(mesh.albedo.texture.shape[:2])
        charts = mesh_charts(mesh.rest_points, mesh.triangles, mesh.corner_uv, size)
        assert 2 <= len(set(charts)) <= most
        fi, fj, jump, _ = _edges(mesh.rest_points, mesh.triangles, mesh.corner_uv, size)
        inside = (charts[fi] == charts[fj]) & (jump > SEAM_TEXELS)
        assert inside.sum() < 0.005 * len(fi)


def test_a_chart_table_is_checked_when_read():
    points, triangles, uv = grid(4, 2, lambda x, y, *_: (x / 4, y / 2))
    good = chart_table([("A", points, triangles, uv, TEXELS)]).to_json()
    assert [c.index for c in parse_charts(good)] == [1]
    broken = [
        ({"format": "other"}, "not a rigspace chart table"),
        ({**good, "charts": {"1": {}}}, "not a list"),
        ({**good, "charts": [{**good["charts"][0], "index": 2}]}, "indices must run 1..K"),
        ({**good, "charts": [{"index": 1, "mesh": "A"}]}, "incomplete or mistyped"),
        ({**good, "charts": [{**good["charts"][0], "uv_min": [2, 0]}]}, "is not a box"),
        ({**good, "meshes": "A"}, "'meshes' is not a list"),
    ]
    for data, message in broken:
        with pytest.raises(ValueError, match=message):
            parse_charts(data)

"""The premise part's heavy characters: midpoint subdivision that keeps skinning and uvs."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.bench.premise import crossover, subdivide


def test_a_subdivision_step_quadruples_triangles_and_interpolates_at_edge_midpoints():
    points = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], float)
    triangles = np.array([(0, 1, 2), (1, 3, 2)])
    uv = points[triangles.reshape(-1), :2].copy()
    skin = np.eye(4)[[0, 1, 2, 3]]  # each corner wholly on its own joint
    new, tris, new_uv, values = subdivide(points, triangles, uv, {"skin": skin})
    assert len(tris) == 8 and len(new) == 4 + 5  # 5 edges, the diagonal shared
    corners = new[tris]
    area = 0.5 * np.abs(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
    assert area[:, 2].sum() == pytest.approx(1.0)  # the square's area kept, nothing overlaps
    np.testing.assert_allclose(new_uv, new[tris.reshape(-1), :2])  # uvs follow the points
    weights = values["skin"]
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    mid = new[4:]
    for k, p in enumerate(mid):  # a midpoint's weights: half each of its edge's ends
        ends = np.flatnonzero(weights[4 + k] > 0)
        assert len(ends) == 2
        np.testing.assert_allclose(points[ends].mean(axis=0), p)


def test_the_crossover_is_where_the_mesh_path_reaches_the_network():
    rows = [
        {"triangles": 1e4, "mesh_ms": 50.0, "network_ms": 100.0},
        {"triangles": 1e6, "mesh_ms": 150.0, "network_ms": 100.0},
    ]
    assert crossover(rows) == pytest.approx(1e5)  # halfway in log(triangles)
    assert crossover([dict(r, mesh_ms=10.0) for r in rows]) is None

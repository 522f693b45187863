"""The premise part's heavy characters: midpoint subdivision that keeps skinning and uvs."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.bench.premise import crossover, crossover_sentence, subdivide


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


def _rows(*triples):
    return [{"triangles": t, "mesh_ms": m, "network_ms": n} for t, m, n in triples]


def test_rows_where_the_mesh_path_already_costs_more_do_not_cross():
    """The first size's mesh path at 1.7x the network is no crossover at that size."""
    rows = _rows((22_956, 170.0, 100.0), (91_824, 300.0, 101.0), (5_876_736, 8_500.0, 99.0))
    assert crossover(rows) is None
    sentence = crossover_sentence(rows)
    assert sentence.startswith("The rows do not cross")
    assert "1.7x the network's at 22,956" in sentence and "85.9x" in sentence
    below = _rows((1e4, 10.0, 100.0), (1e6, 20.0, 100.0))
    assert crossover_sentence(below).startswith("The rows do not cross: the mesh path costs less")


def test_the_sentence_gives_the_interpolated_crossover():
    rows = _rows((1e4, 50.0, 100.0), (1e6, 150.0, 100.0), (1e7, 900.0, 100.0))
    assert "about 100,000 triangles" in crossover_sentence(rows)  # halfway in log(triangles)
    assert "9.0x the network's at 10,000,000" in crossover_sentence(rows)


def test_the_report_reads_its_sentence_and_columns_from_the_rows():
    """A stored crossover (an older run's) does not override what the rows say; the columns
    are the mesh path's posing + skinning + raster and the network's graphs."""
    from rigspace.bench.report import _premise

    row = {
        "triangles": 22_956, "mesh_ms": 170.0, "network_ms": 100.0,
        "mesh_pose_raster_ms": 61.5, "mesh_skinning_ms": 1.25, "network_graphs_ms": 30.5,
        "network_texture_ms": 19.0, "mesh_mib": 2.0, "network_mib": 8.3,
    }  # fmt: skip
    text = "\n".join(_premise({"rows": [row], "crossover": 22_956.0}))
    assert "The rows do not cross" in text and "about 23k" not in text
    assert "| 22,956 | 170.0 | 61.5 | 1.2 | 100.0 | 30.5 | 19.0 | 2.0 | 8.3 |" in text


def test_the_subdivided_characters_bundle_names_its_uv_layout(tmp_path):
    """The network path samples the textures of the subdivided character (as `rigspace
    render` does by default): its bundle copy's charts carry the new mesh's uv fingerprint,
    which at step 0 is the sample bundle's own."""
    import json

    from rigspace.bench.premise import BUNDLE, heavy_scene
    from rigspace.runtime.character import NeuralCharacter
    from rigspace.sdk import schema
    from rigspace.sdk.model import BundleModel
    from rigspace.sdk.stage import open_stage

    sample = json.loads((BUNDLE / "charts.json").read_text())["meshes"]
    scene, _ = heavy_scene(tmp_path / "s0", 0)
    assert json.loads((scene.parent / "model" / "charts.json").read_text())["meshes"] == sample
    scene, triangles = heavy_scene(tmp_path / "s1", 1)
    (mesh,) = json.loads((scene.parent / "model" / "charts.json").read_text())["meshes"]
    assert mesh["triangles"] == triangles == 4 * sample[0]["triangles"]
    stage = open_stage(scene)
    (prim,) = schema.neural_characters(stage)
    character = NeuralCharacter(prim, BundleModel(scene.parent / "model"))
    assert character.no_texture == "" and character.textures is not None


@pytest.mark.slow
def test_the_columns_are_parts_of_their_paths_and_the_mesh_path_grows(tmp_path):
    """At a tiny frame, 23k and 367k triangles (16x: 92k's growth at 160x90 is a few ms, within
    what a loaded 2-core machine adds to a frame): the mesh path's skinning is inside its
    posing + skinning + raster, inside its frame, and both grow with the triangles; the
    network's graphs and texture sampling are inside its frame, and it samples the textures;
    memory grows on the mesh path only."""
    from rigspace.bench.premise import TIMES, measure

    small, large = measure((0, 2), width=160, height=90, times=TIMES[:3])
    for row in (small, large):
        assert 0 < row["mesh_skinning_ms"] <= row["mesh_pose_raster_ms"] <= row["mesh_ms"]
        assert 0 < row["network_graphs_ms"] <= row["network_ms"]
        assert 0 < row["network_texture_ms"] <= row["network_ms"]
        assert row["network_colour"].startswith("its textures on")
    assert large["mesh_pose_raster_ms"] > small["mesh_pose_raster_ms"]
    assert large["mesh_skinning_ms"] > small["mesh_skinning_ms"]
    assert large["mesh_mib"] > 10 * small["mesh_mib"]
    assert large["network_mib"] == small["network_mib"]

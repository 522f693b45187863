"""A character with several materials (GeomSubsets), a UDIM texture and wrap modes: its parts,
its texture charts, and both renderers drawing its colour and texture AOVs alike."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.sdk.camera import Camera
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.render import RenderSettings, choose_renderer
from rigspace.sdk.stage import open_stage
from tests.materials import CHARACTER, write_material_character

MAX_ALBEDO_MAE = 1e-3
"""As tests/sdk/test_render.py: the renderers' texture reads differ by interpolation rounding."""
MIN_CHART_AGREEMENT = 0.99
"""Pixels whose nearest samples tie in depth at a chart border may take either chart."""
UV_DIFFERENCE_P99 = 1e-4
"""Where both give the same chart: float32 interpolation differences only..."""
MAX_UV_DIFFERENCE = 1 / 64
"""...but for a pixel or two whose samples on that chart differ (a fold seen edge-on, where
the depth order of two nearly equal samples flips): under a texel of the 64-texel textures."""


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    scene = write_material_character(tmp_path_factory.mktemp("materials"))
    stage = open_stage(scene)
    character = CharacterRig(stage.GetPrimAtPath(CHARACTER))
    character.stage = stage  # type: ignore[attr-defined]  (kept alive with the rig)
    return character


def test_a_mesh_splits_into_its_material_subsets(rig):
    parts = {rig.mesh_name(p): p for p in rig.mesh_sources()}
    assert sorted(parts) == [f"../Asset/Body/{n}" for n in ("Boots", "Shirt", "Trousers")]
    boots, trousers, shirt = (parts[f"../Asset/Body/{n}"] for n in ("Boots", "Trousers", "Shirt"))
    assert boots.albedo.texture is None and boots.corner_uv is None
    assert len(boots.triangles) + len(trousers.triangles) + len(shirt.triangles) == 16 * 24 * 2
    assert shirt.albedo.wrap == ("mirror", "repeat") and shirt.albedo.uv_scale == (1.0, 1.0)
    # The UDIM trousers: tiles 1001 and 1002 side by side in one atlas, st [0, 2) onto [0, 1).
    assert trousers.albedo.udim and trousers.albedo.texture.shape == (64, 128, 3)
    assert trousers.albedo.uv_scale == (0.5, 1.0) and trousers.albedo.wrap == ("clamp", "clamp")


def test_charts_cover_the_textured_parts_by_tile(rig):
    table = rig.texture_charts()
    by_part = {}
    for chart in table.charts:
        by_part.setdefault(chart.mesh, []).append(chart.tile)
    assert sorted(by_part) == ["../Asset/Body/Shirt", "../Asset/Body/Trousers"]  # boots: none
    assert sorted(by_part["../Asset/Body/Trousers"]) == [1001, 1002]
    meshes = {m.mesh: m.triangle_chart for m in table.meshes}
    assert set(np.unique(meshes["../Asset/Body/Trousers"])) <= {c.index for c in table.charts}


@pytest.mark.parametrize("time, azimuth", [(0.0, 0.0), (6.0, 100.0), (12.0, 215.0)])
def test_both_renderers_draw_its_colour_and_texture_aovs_alike(rig, time, azimuth):
    meshes = rig.posed_meshes(time, charts=True)
    a = np.radians(azimuth)
    camera = Camera.look_at(
        [5 * np.sin(a), 1.0, 5 * np.cos(a)], [0, 1.0, 0], width=96, height=96,
        focal_length=35, horizontal_aperture=20.955,
    )  # fmt: skip
    maps = {}
    for name in ("gl", "embree"):
        renderer = choose_renderer(name).create(RenderSettings(2))
        maps[name] = renderer.render(meshes, camera)
        renderer.close()
    gl, embree = maps["gl"], maps["embree"]
    whole = (gl.mask == 1) & (embree.mask == 1)
    assert whole.sum() > 500
    assert np.abs(gl.albedo - embree.albedo)[whole].mean() < MAX_ALBEDO_MAE
    assert (gl.chart == embree.chart)[whole].mean() >= MIN_CHART_AGREEMENT
    same = whole & (gl.chart == embree.chart) & (gl.chart > 0)
    difference = np.abs(gl.uv - embree.uv)[same]
    assert np.percentile(difference, 99) < UV_DIFFERENCE_P99
    assert difference.max() < MAX_UV_DIFFERENCE
    # The boots have no texture: no chart there; the rest is charted.
    charted = set(np.unique(gl.chart[whole]).tolist())
    assert 0 in charted and len(charted) >= 3


@pytest.mark.parametrize("samples", [1, 2, 3])
def test_the_gl_resolve_pass_equals_maps_from_samples(rig, samples):
    """The gl renderer reduces its supersamples in a fragment shader; maps_from_samples over
    the same samples read back is the reference: equal bit for bit but the uv mean (float32
    against float64 sums)."""
    from rigspace.sdk.render import gl as gl_module

    if gl_module.unavailable() is not None:
        pytest.skip(f"the gl renderer cannot run here: {gl_module.unavailable()}")
    camera = Camera.look_at([3.0, 1.2, 4.0], [0, 1.0, 0], width=80, height=64,
                            focal_length=35, horizontal_aperture=20.955)  # fmt: skip
    for charts in (True, False):
        meshes = rig.posed_meshes(6.0, charts=charts)
        maps = {}
        for resolve in ("gpu", "numpy"):
            with gl_module.GLRenderer(RenderSettings(samples), resolve) as renderer:
                maps[resolve] = renderer.render(meshes, camera)
        gpu, reference = maps["gpu"], maps["numpy"]
        assert 0.05 < (reference.mask > 0).mean() < 0.95  # the character and the background
        for name in ("albedo", "normal", "depth", "mask", "chart"):
            assert np.array_equal(getattr(gpu, name), getattr(reference, name)), name
        if charts:
            assert (reference.chart > 0).sum() > 300
            assert np.abs(gpu.uv - reference.uv).max() < 1e-6
        else:
            assert gpu.uv is None and reference.uv is None
    with pytest.raises(ValueError, match="resolve 'cuda'"):
        gl_module.GLRenderer(RenderSettings(2), "cuda")


def test_the_compiled_one_sample_unpack_equals_maps_from_samples(rig):
    """At one sample per pixel the gl renderer unpacks its read-back in a compiled pass;
    maps_from_samples over the same attachments is the reference, bit for bit."""
    from rigspace.sdk.render import gl as gl_module
    from rigspace.sdk.render import maps_from_samples

    if gl_module.unavailable() is not None:
        pytest.skip(f"the gl renderer cannot run here: {gl_module.unavailable()}")
    camera = Camera.look_at([3.0, 1.2, 4.0], [0, 1.0, 0], width=80, height=64,
                            focal_length=35, horizontal_aperture=20.955)  # fmt: skip
    for charts in (True, False):
        with gl_module.GLRenderer(RenderSettings(1), "numpy") as renderer:
            maps = renderer.render(rig.posed_meshes(6.0, charts=charts), camera)
            fine = renderer._fine[:, ::-1].copy()  # as read back, row 0 at the top
        surface = fine[2] if charts else None
        reference = maps_from_samples(
            1, fine[0, ..., 3] > 0, fine[0, ..., :3], fine[1, ..., :3], fine[1, ..., 3],
            None if surface is None else surface[..., :2],
            None if surface is None else np.rint(surface[..., 2]).astype(np.int32),
        )  # fmt: skip
        assert 0.05 < (reference.mask > 0).mean() < 0.95
        for name in ("albedo", "normal", "depth", "mask", "uv", "chart"):
            got, want = getattr(maps, name), getattr(reference, name)
            assert (got is None and want is None) or np.array_equal(got, want), name
            assert got is None or got.dtype == want.dtype, name
        if charts:
            assert (reference.chart > 0).sum() > 300

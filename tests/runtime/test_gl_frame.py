"""The frame's GPU and compiled paths against their numpy references: the lighting in a
fragment shader (runtime/gl_shading.py, forced onto llvmpipe here) and the compiled
composite (runtime/composite_kernel.py)."""

from __future__ import annotations

import numpy as np
import pytest

from rigspace.runtime.character import Layer
from rigspace.runtime.composite_kernel import composite, composite_reference
from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.runtime.lights import AMBIENT, DISTANT, POINT, Light
from rigspace.runtime.shading import shade
from rigspace.runtime.shadows import ShadowBackend
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import choose_renderer
from rigspace.sdk.render import gl as gl_module
from tests.conftest import REPO
from tests.runtime.conftest import previs_engine

PREVIS = REPO / "samples" / "scenes" / "previs.usda"
GL_TOLERANCE = 1e-5
"""Of the brightest pixel: the shader and numpy do the same float32 operations (1e-7 seen)."""


def _needs_gl() -> None:
    if gl_module.unavailable() is not None:
        pytest.skip(f"the gl renderer cannot run here: {gl_module.unavailable()}")


def _gbuffer(rng: np.random.Generator, h: int, w: int):
    albedo = rng.random((h, w, 3), dtype=np.float32)
    normal = rng.normal(size=(h, w, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    depth = (4 + rng.random((h, w))).astype(np.float32)
    mask = rng.random((h, w)).astype(np.float32)
    mask[mask < 0.3] = 0.0
    depth[mask == 0] = np.inf
    return albedo * mask[..., None], normal, depth, mask


def _lights(copies: int = 1) -> list[Light]:
    sun = np.array([0.3, -1.0, -0.4])
    return [
        Light(AMBIENT, np.array([0.1, 0.2, 0.3])),
        Light(DISTANT, np.array([2.0, 1.8, 1.5]), direction=sun / np.linalg.norm(sun)),
        Light(POINT, np.array([5.0, 4.0, 3.0]), position=np.array([1.0, 2.5, 1.0]), area=0.3),
    ] * copies


@pytest.mark.parametrize("copies", [1, 7])  # 21 lights: two draws whose colours add
@pytest.mark.parametrize("shadowed", [False, True])
def test_the_shader_lights_a_region_as_numpy_does(copies, shadowed):
    from rigspace.runtime.gl_shading import GLShading

    _needs_gl()
    rng = np.random.default_rng(copies)
    camera = Camera.look_at((0.3, 1.5, 5.0), (0, 1, 0), width=320, height=200,
                            focal_length=35.0, horizontal_aperture=36.0)  # fmt: skip
    gbuffer = _gbuffer(rng, 70, 90)
    lights = _lights(copies)
    visibility = None
    if shadowed:  # the sun and the lamp shadowed, the sky not
        visibility = [None if light.kind == AMBIENT else rng.random((70, 90)).astype(np.float32)
                      for light in lights]  # fmt: skip
    shader = GLShading()
    try:
        on_gl = shader.shade(*gbuffer, camera, lights, (100, 40), visibility)
        empty = shader.shade(*gbuffer, camera, [], (100, 40), visibility)
    finally:
        shader.close()
    reference = shade(*gbuffer, camera, lights, (100, 40), visibility)
    assert np.abs(on_gl - reference).max() < GL_TOLERANCE * reference.max()
    assert reference.max() > 0.5 and np.all(on_gl[gbuffer[3] == 0] == 0)
    assert np.all(empty == 0)
    if shadowed:  # what is compared holds the shadows: without them it is brighter
        assert shade(*gbuffer, camera, lights, (100, 40)).sum() > 1.2 * reference.sum()


@pytest.mark.parametrize("copies", [1, 7])
@pytest.mark.parametrize("shadowed", [False, True])
def test_the_compiled_shading_lights_a_region_as_numpy_does(copies, shadowed):
    from rigspace.runtime.shading_kernel import shade as compiled

    rng = np.random.default_rng(10 + copies)
    camera = Camera.look_at((0.3, 1.5, 5.0), (0, 1, 0), width=320, height=200,
                            focal_length=35.0, horizontal_aperture=36.0)  # fmt: skip
    gbuffer = _gbuffer(rng, 70, 90)
    lights = _lights(copies)
    visibility = None
    if shadowed:
        visibility = [None if light.kind == AMBIENT else rng.random((70, 90)).astype(np.float32)
                      for light in lights]  # fmt: skip
    reference = shade(*gbuffer, camera, lights, (100, 40), visibility)
    lit = compiled(*gbuffer, camera, lights, (100, 40), visibility)
    assert lit.dtype == np.float32 and lit.shape == reference.shape
    assert np.abs(lit - reference).max() < GL_TOLERANCE * reference.max()
    assert np.all(lit[gbuffer[3] == 0] == 0) and reference.max() > 0.5
    assert np.all(compiled(*gbuffer, camera, [], (100, 40)) == 0)


def test_one_shader_lights_regions_of_changing_sizes_without_mixing_them():
    """Its textures grow and are reused: a smaller region is written into a corner of the
    larger textures, and nothing of the last region leaks into the next."""
    from rigspace.runtime.gl_shading import GLShading

    _needs_gl()
    rng = np.random.default_rng(7)
    camera = Camera.look_at((0.3, 1.5, 5.0), (0, 1, 0), width=320, height=200,
                            focal_length=35.0, horizontal_aperture=36.0)  # fmt: skip
    lights = _lights()
    shader = GLShading()
    try:
        for (h, w), shadowed in (((70, 90), True), ((30, 50), False), ((100, 120), True),
                                 ((20, 20), True), ((100, 120), False)):  # fmt: skip
            gbuffer = _gbuffer(rng, h, w)
            visibility = None
            if shadowed:
                visibility = [None if light.kind == AMBIENT else
                              rng.random((h, w)).astype(np.float32) for light in lights]  # fmt: skip
            reference = shade(*gbuffer, camera, lights, (10, 20), visibility)
            on_gl = shader.shade(*gbuffer, camera, lights, (10, 20), visibility)
            assert on_gl.shape == (h, w, 3)
            assert np.abs(on_gl - reference).max() < GL_TOLERANCE * reference.max(), (h, w)
    finally:
        shader.close()


def test_a_previs_frame_lit_by_the_shader_matches_numpy():
    _needs_gl()

    def frame(where: str) -> tuple[np.ndarray, str]:
        with previs_engine(renderer="gl", gl_lighting=where) as engine:
            f = engine.render(600.0)
            return np.array(f.beauty), f.report.lighting_on

    (on_gl, used), (on_numpy, reference) = frame("always"), frame("never")
    assert reference == "numba" and used != "numba"  # the GL_RENDERER string
    assert np.abs(on_gl - on_numpy).max() < GL_TOLERANCE * on_numpy.max()


def test_the_renderers_the_lighting_and_the_capsule_shadows_share_one_gl_context(monkeypatch):
    """An Engine opens one EGL context (gl.SharedContext) for the prims' renderer, the shadow
    maps' renderer, the lighting shader and the capsule shader; closing it frees it."""
    _needs_gl()
    gl_module.software()  # the probes' own contexts, made once per process, not counted
    made = []
    real = gl_module._context
    monkeypatch.setattr(gl_module, "_context", lambda: made.append(1) or real())
    settings = EngineSettings(
        width=160, height=90, prim_samples=1, renderer="gl", gl_lighting="always",
        shadow_backend=ShadowBackend(gl_capsules="always"),
    )  # fmt: skip
    engine = Engine(PREVIS, settings)
    try:
        frame = engine.render(600.0)
        assert frame.report.lighting_on != "numba" and engine.shadows.capsule_backend == "gl"
        assert frame.report.shadows["maps_drawn"] > 0 and frame.report.shadows["casters"] == 1
        shared = engine.renderer.settings.shared
        assert shared is not None and shared._users == 5  # the engine and its four users
    finally:
        engine.close()
    assert len(made) == 1 and shared._ctx is None


def test_the_shader_is_used_only_with_the_gl_renderer_on_a_gpu():
    from rigspace.runtime.gl_shading import open_gl_shading

    assert open_gl_shading(choose_renderer("embree"), "always") is None
    assert open_gl_shading(choose_renderer("gl"), "never") is None
    with pytest.raises(ValueError, match="gl_lighting 'sometimes'"):
        open_gl_shading(choose_renderer("gl"), "sometimes")
    _needs_gl()
    spec = choose_renderer("gl")
    chosen = open_gl_shading(spec, "hardware")
    try:
        assert (chosen is None) == spec.cost_grows_with_triangles()  # None on llvmpipe
    finally:
        if chosen is not None:
            chosen.close()


def _layer(rng, x0, y0, h, w, *, depth=True, normal=True, uv=True, chart=True) -> Layer:
    albedo, n, d, mask = _gbuffer(rng, h, w)
    return Layer(
        x0, y0, albedo, mask, d if depth else None, n if depth and normal else None, 64,
        ("albedo", "geometry"),
        uv=rng.random((h, w, 2), dtype=np.float32) if uv else None,
        chart=rng.integers(0, 5, (h, w)).astype(np.int32) if chart else None,
    )  # fmt: skip


def _frame(rng, h, w):
    albedo, normal, depth, mask = _gbuffer(rng, h, w)
    beauty = rng.random((h, w, 3), dtype=np.float32) * mask[..., None]
    uv = rng.random((h, w, 2), dtype=np.float32)
    chart = rng.integers(0, 5, (h, w)).astype(np.int32)
    return [beauty, albedo, normal, depth, mask, uv, chart]


@pytest.mark.parametrize(
    "kind",
    ["lit", "unlit (no depth)", "depth without normals", "no uv on the layer",
     "no chart on the layer", "frame without texture AOVs"],
)  # fmt: skip
def test_the_compiled_composite_equals_numpy(kind):
    rng = np.random.default_rng(len(kind))
    layer = _layer(
        rng, 7, 5, 30, 40,
        depth=kind != "unlit (no depth)", normal=kind != "depth without normals",
        uv=kind != "no uv on the layer", chart=kind != "no chart on the layer",
    )  # fmt: skip
    lit = rng.random((30, 40, 3), dtype=np.float32) * layer.mask[..., None]
    frame = _frame(rng, 50, 60)
    if kind == "frame without texture AOVs":
        frame[5:] = [None, None]
    compiled = [None if a is None else a.copy() for a in frame]
    reference = [None if a is None else a.copy() for a in frame]
    composite(layer, lit, *compiled)
    composite_reference(layer, lit, *reference)
    for name, a, b, before in zip(
        ("beauty", "albedo", "normal", "depth", "mask", "uv", "chart"),
        compiled, reference, frame, strict=True,
    ):  # fmt: skip
        if b is None:
            continue
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7, err_msg=name)
        if name in ("beauty", "mask") or (name == "normal" and kind == "lit"):
            assert not np.array_equal(b, before), f"{name} unchanged: nothing was compared"


@pytest.mark.parametrize("textured", [False, True])  # a constant sky (a broadcast view), a latlong
def test_the_compiled_background_equals_numpy(textured):
    from rigspace.runtime.composite_kernel import over_background

    rng = np.random.default_rng(3)
    beauty, mask = rng.random((40, 50, 3), dtype=np.float32), rng.random((40, 50), np.float32)
    mask[:10] = 1.0  # covered: nothing shows through
    sky = np.array([0.2, 0.3, 0.5], np.float32)
    behind = rng.random((40, 50, 3), np.float32) if textured else np.broadcast_to(sky, (40, 50, 3))
    compiled = beauty.copy()
    over_background(compiled, mask, behind)
    np.testing.assert_allclose(compiled, beauty + (1.0 - mask)[..., None] * behind, rtol=1e-6)
    assert np.array_equal(compiled[:10], beauty[:10]) and not np.array_equal(compiled, beauty)

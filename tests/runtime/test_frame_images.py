"""Frames through the engine's strategies and code paths (runtime/lighting.py, the stages'
reuse): the three lightings light a previs shot alike, and a reused lighting re-shaded under
the capsules' shadows gives a fresh engine's frame to the bit."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd

from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.sdk.render import gl as gl_module
from rigspace.sdk.stage import overlay_layer
from tests.conftest import REPO
from tests.runtime.conftest import define_camera

PREVIS = REPO / "samples" / "scenes" / "previs.usda"
LIGHTING_TOLERANCE = 1e-5
"""Of the brightest pixel: shading_kernel and the shader against numpy (tests/runtime/
test_gl_frame.py holds the same bound on regions)."""
TIMES = (0.0, 40.0, 80.0, 120.0, 121.0)
"""The hero walking across the still shot: his capsules' shadow moves over still prims."""


def _still_shot(folder: Path) -> Path:
    """The previs scene (sun, lamp, sky dome, the walking hero) with its moving props turned
    off and a still camera: frames after the first reuse the prims' lighting and re-shade
    only the pixels the hero's capsules shadow."""
    layer = overlay_layer(folder / "still.usda", PREVIS)
    stage = Usd.Stage.Open(layer)
    for path in ("/World/Set/PassingCrate", "/World/Set/RollingBall", "/World/ShotCam"):
        stage.OverridePrim(path).SetActive(False)
    define_camera(stage, "/World/StillCam", 18.0, (200, 300, 800), -15.0)
    layer.Save()
    return folder / "still.usda"


@functools.cache
def _frames(scene: Path, lighting: str, times: tuple[float, ...]):
    """The beauty and the report of each frame at `times` from one engine lit by `lighting`
    ("numba", "numpy", or "gl": the fragment shader forced onto llvmpipe)."""
    settings = EngineSettings(
        width=160,
        height=90,
        prim_samples=1,
        renderer="gl" if lighting == "gl" else "auto",
        gl_lighting="always" if lighting == "gl" else "never",
        lighting_kernel="numpy" if lighting == "numpy" else "numba",
    )
    with Engine(scene, settings) as engine:
        frames = [engine.render(t) for t in times]
    return [np.array(f.beauty) for f in frames], [f.report for f in frames]


@pytest.fixture(scope="module")
def still_shot(tmp_path_factory) -> Path:
    return _still_shot(tmp_path_factory.mktemp("lighting"))


def _lightings() -> list[str]:
    return ["numba", "numpy"] + ([] if gl_module.unavailable() is not None else ["gl"])


@pytest.mark.parametrize("lighting", _lightings())
def test_a_reused_lighting_is_a_fresh_engines_frame_to_the_bit(still_shot, lighting):
    """The old way and the new way to each frame: the lit prims kept from the last frame with
    the capsules' pixels lit again (reshade), against a fresh engine lighting the whole
    frame; the capsules' shadow and the sky are in what is compared."""
    beauty, reports = _frames(still_shot, lighting, TIMES)
    assert [r.scene_prims["lit_reused"] for r in reports] == [False, True, True, True, True]
    assert all(r.shadows["casters"] == 1 and r.background for r in reports)
    for k, t in enumerate(TIMES[1:], start=1):
        (fresh,), _ = _frames(still_shot, lighting, (t,))
        assert np.array_equal(beauty[k], fresh), (t, np.abs(beauty[k] - fresh).max())
    assert not np.array_equal(beauty[1], beauty[2])  # the hero and his shadow moved


def test_the_three_lightings_light_the_previs_shot_alike(still_shot):
    found = {name: _frames(still_shot, name, TIMES) for name in _lightings()}
    reference, reports = found["numpy"]
    assert {r.lighting_on for r in reports} == {"numpy"}
    assert {r.lighting_on for r in found["numba"][1]} == {"numba"}
    for name, (beauty, _) in found.items():
        for mine, theirs in zip(beauty, reference, strict=True):
            assert np.abs(mine - theirs).max() < LIGHTING_TOLERANCE * theirs.max(), name

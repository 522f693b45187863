"""The compiled geometry resampling equals its numpy reference on a real frame and on the
edge cases the reference handles (zero-length normals, coverage at and below epsilon)."""

from __future__ import annotations

import numpy as np

from rigspace.bench.scenes import PREVIS
from rigspace.runtime.character import COVERAGE_EPSILON
from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.sdk.texturing import region_warper


def _warped(engine: Engine, time: float):
    character = engine.characters[0]
    camera, _ = engine._camera_at(time)
    world = character.pose(time)
    billboard = character.place(world, camera)
    rig = character.parameters(world, billboard, camera, character.weights(time))
    level = character.model.level_for(billboard.size_px)
    out = {k: v[0] for k, v in character.model.predict(rig, level, ("geometry",)).items()}
    region = billboard.region(camera)
    warp = region_warper(billboard.homography(level), region)
    coverage = warp(out["mask"])[..., 0]
    normal_w = warp(out["normal"] * out["mask"])
    offset_w = warp(out["depth"] * out["mask"])[..., 0]
    return character, billboard, camera, region, coverage, normal_w, offset_w


def _both(character, billboard, camera, region, coverage, normal_w, offset_w):
    args = (coverage, normal_w, offset_w, billboard, camera, region[:2])
    return (character.finish_geometry(*args), character.finish_geometry(*args, kernel=False))


def test_the_compiled_geometry_equals_the_reference():
    engine = Engine(PREVIS, EngineSettings(width=256, height=144))
    try:
        character, billboard, camera, region, coverage, normal_w, offset_w = _warped(engine, 600)
        # Edge cases on a copy: a zero-length normal, coverage at epsilon, negative coverage.
        edited = [coverage.copy(), normal_w.copy(), offset_w.copy()]
        covered = np.argwhere(coverage > 0.5)
        assert len(covered) > 100
        (i, j), (k, m), (p, q) = covered[0], covered[len(covered) // 2], covered[-1]
        edited[1][i, j] = 0.0
        edited[0][k, m] = COVERAGE_EPSILON
        edited[0][p, q] = -0.25
        for case in ((coverage, normal_w, offset_w), tuple(edited)):
            got, want = _both(character, billboard, camera, region, *case)
            for name, a, b in zip(("mask", "normal", "depth"), got, want, strict=True):
                assert a.dtype == b.dtype == np.float32 and a.shape == b.shape, name
                assert np.array_equal(np.isinf(a), np.isinf(b)), name
                finite = np.isfinite(b)
                np.testing.assert_allclose(a[finite], b[finite], rtol=2e-6, atol=2e-6, err_msg=name)
        mask, normal, depth = got
        assert np.array_equal(normal[i, j], [0.0, 0.0, 1.0])  # faces the camera
        assert np.isinf(depth[k, m]) and np.isinf(depth[p, q]) and mask[p, q] == 0.0
    finally:
        engine.close()

"""The point-cache bake of the sample character (samples/point_cache/build_point_cache.py) at a
tiny size: four frames, two of them in the wave clip (the right elbow bent, the upper arm
turned 90 degrees), one in the stretch clip (no flexion, no twist)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from tests.conftest import REPO

BUILDER = REPO / "samples" / "point_cache" / "build_point_cache.py"
FRAMES = (360, 720, 120)  # first:last:every -> 360, 480, 600, 720
LBS_TOLERANCE_CM = 1e-3
"""This script's float64 LBS against UsdSkel's float32 skinning of the same body (cm)."""


def _builder():
    spec = importlib.util.spec_from_file_location("build_point_cache", BUILDER)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    builder = _builder()
    out = tmp_path_factory.mktemp("point_cache")
    first, last, every = FRAMES
    frames = np.arange(first, last + 1, every, dtype=np.float64)
    return builder, builder.bake(frames), builder.build(out, first, last, every)


def test_the_deformations_are_centimetres_from_lbs_and_none_without_flexion_or_twist(built):
    _, baked, summary = built
    assert baked["usd_difference"] < LBS_TOLERANCE_CM  # its LBS is UsdSkel's
    offsets = np.linalg.norm(baked["baked"] - baked["lbs"], axis=2).max(axis=1)
    assert offsets[1] > 3.0 and summary["largest_offset_cm"] > 3.0  # the wave: several cm
    assert offsets[3] < 1e-3  # the stretch clip at 720 bends no elbow and turns no arm
    assert {"bicepsBulge_r", "armTwist_r"} <= set(baked["controls"])  # what these frames move
    # No clip turns a wrist: the forearm's twist never moves, so it is no control.
    assert not [c for c in baked["controls"] if c.startswith("forearmTwist")]
    assert baked["controls"]["armTwist_r"].max() == pytest.approx(90.0, abs=0.5)


def test_the_twist_keeps_the_arm_where_lbs_collapses_it(built):
    """The volume-keeping twist: at the wave's 90-degree turn the shortest edge of the body
    keeps more of its rest length than LBS's (its candy-wrapper at the shoulder), and the
    body's volume does not shrink."""
    builder, baked, _ = built
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(builder.BASE))
    tris = np.array(
        UsdGeom.Mesh(stage.GetPrimAtPath("/Character/Body")).GetFaceVertexIndicesAttr().Get()
    ).reshape(-1, 3)
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    rest = baked["rest"]
    rest_length = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)

    def shortest(points):
        return (
            np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1) / rest_length
        ).min()

    def volume(points):
        a, b, c = (points[tris[:, k]] for k in range(3))
        return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6

    assert shortest(baked["baked"][1]) > shortest(baked["lbs"][1]) + 0.02
    assert volume(baked["baked"][1]) > volume(baked["lbs"][1])


def test_the_shot_validates_and_poses_the_cache(built):
    from rigspace.sdk.posing import CharacterRig
    from rigspace.sdk.stage import open_stage
    from rigspace.sdk.validation import validate

    _, baked, summary = built
    stage = open_stage(summary["scene"])
    findings = validate(stage, include_usd=False)
    assert not [f for f in findings if f.severity == "error"], findings
    assert not [f for f in findings if f.code.startswith(("Cache", "Control"))], findings
    rig = CharacterRig(stage.GetPrimAtPath("/World/Hero"))
    assert not rig.has_skinned_meshes and len(rig.time_samples()) == 4
    assert rig.scalar_names == tuple(baked["controls"])
    (body,) = rig.posed_meshes(480.0)
    np.testing.assert_allclose(body.points, baked["baked"][1], atol=1e-3)
    assert rig.scalars(480.0) == pytest.approx([v[1] for v in baked["controls"].values()], abs=1e-3)


def test_the_rerig_shot_skins_the_same_body_by_lbs_on_the_same_ring(built):
    """The re-rig's shot (its capture is the cached character's twin, apps/rerig_report.py):
    the same capture ring and clips, the body skinned by UsdSkel (no cache, no controls), its
    LBS the bake's at every baked frame."""
    from rigspace.sdk.posing import CharacterRig
    from rigspace.sdk.stage import open_stage
    from rigspace.sdk.validation import validate

    _, baked, summary = built
    stages = [open_stage(summary[k]) for k in ("scene", "rerig")]  # kept alive
    cached, rerig = (stage.GetPrimAtPath("/World/Hero") for stage in stages)
    ring = [p.GetName() for p in cached.GetProperties() if "captureRing" in p.GetName()]
    assert "rigspace:captureRing:clipRanges" in ring
    for name in ring:
        assert rerig.GetAttribute(name).Get() == cached.GetAttribute(name).Get(), name
    findings = validate(rerig.GetStage(), include_usd=False)
    assert not [f for f in findings if f.severity == "error"], findings
    rig = CharacterRig(rerig)
    assert rig.has_skinned_meshes and not rig.controls
    for k, t in enumerate(baked["frames"]):
        (body,) = rig.posed_meshes(float(t))
        np.testing.assert_allclose(body.points, baked["lbs"][k], atol=1e-2)

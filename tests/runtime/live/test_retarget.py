"""Retargeting onto the sample character: world-delta convention checked through UsdSkel."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdSkel, Vt

from rigspace.runtime.live.buffer import LivePose
from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.decoders.vmc import VmcDecoder
from rigspace.runtime.live.retarget import (
    PRESETS,
    Retargeter,
    RetargetError,
    source_basis,
    target_skeleton,
)
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.sdk.rotations import matrix_from_quat, quat_from_matrix, quat_multiply
from tests.runtime.live.conftest import (
    CMU_CLIP,
    SAMPLE_CHARACTER,
    compose_world,
    quat_conjugate,
)


@pytest.fixture(scope="module")
def character():
    stage = Usd.Stage.Open(str(SAMPLE_CHARACTER))
    skel = stage.GetPrimAtPath("/Character/Skel")
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    joints, rest = target_skeleton(skel)
    assert tuple(anim.GetJointsAttr().Get()) == joints

    def stage_local(time: float, _stage=stage) -> np.ndarray:  # keeps the stage alive
        local = UsdSkel.MakeTransforms(
            anim.GetTranslationsAttr().Get(time),
            anim.GetRotationsAttr().Get(time),
            anim.GetScalesAttr().Get(time),
        )
        return np.array(local)

    return joints, rest, stage_local


@pytest.fixture(scope="module")
def cmu():
    skeleton, motion, _ = read_bvh(CMU_CLIP)
    rotations, roots = skeleton.pose(motion)
    return skeleton, rotations, roots


def usd_world_rotations(joints, local: np.ndarray) -> np.ndarray:
    """Skeleton-space joint rotations by UsdSkel's own concatenation (an independent reference)."""
    skel = UsdSkel.ConcatJointTransforms(
        UsdSkel.Topology(joints), Vt.Matrix4dArray.FromNumpy(local)
    )
    return quat_from_matrix(np.swapaxes(np.array(skel)[:, :3, :3], 1, 2))


def live_pose(rotations, root=None, weight=1.0) -> LivePose:
    return LivePose(rotations, np.ones(len(rotations), bool), root, "connected", weight, 0.0)


def test_presets_name_joints_of_the_sample_character(character):
    joints, _, _ = character
    leaves = {j.rsplit("/", 1)[-1] for j in joints}
    for preset in PRESETS.values():
        assert set(preset.bone_map.values()) <= leaves, preset.name
        assert len(preset.bone_map) == 22
    assert set(PRESETS["unity"].bone_map) <= set(VmcDecoder().bones)


def cmu_retargeter(character, cmu, **kw) -> Retargeter:
    joints, rest, _ = character
    skeleton, _, _ = cmu
    p = PRESETS["cmu"]
    return Retargeter(
        skeleton.names, skeleton.parents, "local", joints, rest, kw.pop("bone_map", p.bone_map),
        p.basis, p.meters_per_unit / 0.01, **kw,
    )  # fmt: skip


def test_mapped_joints_turn_as_their_source_bones(character, cmu):
    joints, rest, stage_local = character
    skeleton, rotations, _ = cmu
    r = cmu_retargeter(character, cmu)
    rest_world = usd_world_rotations(joints, rest)
    for f in (0, 400, 900):
        out = r.apply(stage_local(100.0), live_pose(rotations[f]))
        world = usd_world_rotations(joints, out)
        source_world = compose_world(rotations[f], np.array(skeleton.parents))
        for s, t in zip(r.map_source, r.map_target, strict=True):
            # W'_j W'rest_j^-1 == W_b (CMU: basis identity, rest frames world-aligned).
            delta = quat_multiply(world[t], quat_conjugate(rest_world[t]))
            assert quat_angle(delta, source_world[s]) < 1e-6, (f, joints[t])
        unmapped = np.setdiff1d(np.arange(len(joints)), r.map_target)
        np.testing.assert_array_equal(out[unmapped], stage_local(100.0)[unmapped])


def test_partial_map_keeps_the_stage_animation_elsewhere(character, cmu):
    joints, _, stage_local = character
    _, rotations, _ = cmu
    r = cmu_retargeter(
        character, cmu, bone_map={"LeftShoulder": "upperarm_l", "LeftElbow": "lowerarm_l"}
    )
    base = stage_local(30.0)
    out = r.apply(base, live_pose(rotations[500]))
    changed = np.flatnonzero(np.any(np.abs(out - base) > 1e-12, axis=(1, 2)))
    assert [joints[j].rsplit("/", 1)[-1] for j in changed] == ["upperarm_l", "lowerarm_l"]
    np.testing.assert_allclose(out[changed][:, 3], base[changed][:, 3])  # offsets untouched


def test_calibration_puts_the_rest_pose_on_the_target_rest(character, cmu):
    joints, rest, stage_local = character
    _, rotations, _ = cmu
    r = cmu_retargeter(character, cmu)
    stored = r.calibrate(live_pose(rotations[200]))
    np.testing.assert_allclose(stored, rotations[200])
    out = r.apply(stage_local(0.0), live_pose(rotations[200]))
    world, rest_world = usd_world_rotations(joints, out), usd_world_rotations(joints, rest)
    assert quat_angle(world[r.map_target], rest_world[r.map_target]).max() < 1e-6


def test_weight_blends_between_stage_and_live(character, cmu):
    _, _, stage_local = character
    _, rotations, _ = cmu
    r = cmu_retargeter(character, cmu, root_motion=False)
    base = stage_local(50.0)
    assert np.array_equal(r.apply(base, live_pose(rotations[300], weight=0.0)), base)
    full = r.apply(base, live_pose(rotations[300]))
    half = r.apply(base, live_pose(rotations[300], weight=0.5))
    q = [quat_from_matrix(np.swapaxes(m[:, :3, :3], 1, 2)) for m in (base, full, half)]
    j = r.map_target
    np.testing.assert_allclose(
        quat_angle(q[0][j], q[2][j]), quat_angle(q[1][j], q[2][j]), atol=1e-6
    )


def test_root_motion_in_stage_units(character, cmu):
    _, rest, stage_local = character
    _, rotations, roots = cmu
    r = cmu_retargeter(character, cmu)
    r.apply(stage_local(0.0), live_pose(rotations[0], roots[0]))  # the start fixes the origin
    out = r.apply(stage_local(0.0), live_pose(rotations[0], roots[0] + [10.0, 0.0, 0.0]))
    # 10 CMU units = 10 / 0.45 inch = 56.44 cm along +X, from the pelvis rest position.
    np.testing.assert_allclose(out[0, 3, :3], rest[0, 3, :3] + [56.444444, 0.0, 0.0], atol=1e-4)


def test_unity_basis_and_world_space_sources(character):
    joints, rest, stage_local = character
    decoder = VmcDecoder()
    p = PRESETS["unity"]
    r = Retargeter(decoder.bones, p.parents, "local", joints, rest, p.bone_map, p.basis, 1 / 0.01)
    rng = np.random.default_rng(0)
    q = rng.normal(size=(len(decoder.bones), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rest_world = usd_world_rotations(joints, rest)

    def world_deltas(pose: np.ndarray) -> np.ndarray:
        """The mapped joints' world rotations against their rest's, through UsdSkel."""
        world = usd_world_rotations(joints, r.apply(stage_local(0.0), live_pose(pose, np.zeros(3))))
        return quat_multiply(world[r.map_target], quat_conjugate(rest_world[r.map_target]))

    # Each mapped joint turns as its bone's world rotation, conjugated by the basis (A W A^T;
    # VMC's rest is the identity): the source composed bone by bone here.
    a = r.basis if np.linalg.det(r.basis) > 0 else -r.basis
    source_world = matrix_from_quat(compose_world(q, r.source_parents)[r.map_source])
    expected = quat_from_matrix(a @ source_world @ a.T)
    assert quat_angle(world_deltas(q), expected).max() < 1e-6
    # A turn about +Y stays a turn about +Y under the 180-degree basis.
    turn = np.array([np.cos(0.3), 0.0, np.sin(0.3), 0.0])
    ident = np.tile([1.0, 0, 0, 0], (len(decoder.bones), 1))
    ident[0] = turn  # the avatar root turns
    hips = list(r.map_source).index(decoder.bones.index("Hips"))
    assert quat_angle(world_deltas(ident)[hips], turn) < 1e-6
    np.testing.assert_allclose(source_basis("Z", "right") @ [0, 0, 1.0], [0, 1.0, 0])
    np.testing.assert_allclose(source_basis("Y", "left") @ [0, 0, 1.0], [0, 0, -1.0])


def test_bad_maps_name_the_joint(character, cmu):
    with pytest.raises(RetargetError, match=r"'tail'.*Fix: use one of"):
        cmu_retargeter(character, cmu, bone_map={"Hips": "tail"})
    with pytest.raises(RetargetError, match="maps none"):
        cmu_retargeter(character, cmu, bone_map={"NoSuchBone": "pelvis"})


def test_align_rest_puts_the_character_in_the_clips_rest_pose(character, cmu):
    joints, rest, _ = character
    skeleton, _, _ = cmu
    r = cmu_retargeter(character, cmu)
    r.align_rest(skeleton.rest_positions())
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (len(skeleton.names), 1))
    out = r.apply(rest, live_pose(identity))  # the clip's rest: a T-pose
    skel = np.array(
        UsdSkel.ConcatJointTransforms(UsdSkel.Topology(joints), Vt.Matrix4dArray.FromNumpy(out))
    )
    position = {j.rsplit("/", 1)[-1]: skel[k, 3, :3] for k, j in enumerate(joints)}
    src = dict(zip(skeleton.names, skeleton.rest_positions(), strict=True))
    for (a, b), (sa, sb) in {
        ("upperarm_l", "lowerarm_l"): ("LeftShoulder", "LeftElbow"),
        ("lowerarm_r", "hand_r"): ("RightElbow", "RightWrist"),
        ("thigh_l", "calf_l"): ("LeftHip", "LeftKnee"),
        ("spine_03", "neck_01"): ("Chest2", "Neck"),
    }.items():
        u, v = position[b] - position[a], src[sb] - src[sa]
        angle = np.arctan2(np.linalg.norm(np.cross(u, v)), np.dot(u, v))  # exact near 0
        assert angle < 1e-9, (a, b)
    # This CMU conversion rests with the arms hanging: so does the character now, not in its
    # A-pose (arms 40 degrees below horizontal).
    arm = position["lowerarm_l"] - position["upperarm_l"]
    assert arm[1] < -0.999 * np.linalg.norm(arm)


def test_cached_index_arrays_follow_the_bones_that_have_arrived(character, cmu):
    """The per-mask structure cache: bones arriving later change the mapped set; each mask's
    result equals a fresh retargeter's (no state leaks between masks or calibrations)."""
    _, _, stage_local = character
    _, rotations, _ = cmu
    r = cmu_retargeter(character, cmu)
    base = stage_local(60.0)
    full = r.apply(base, live_pose(rotations[300]))
    partial_valid = np.zeros(len(rotations[300]), bool)
    partial_valid[r.map_source[:5]] = True  # the root chain first
    partial = LivePose(rotations[300], partial_valid, None, "connected", 1.0, 0.0)
    got = r.apply(base, partial)
    assert len(r._structure) == 2
    fresh = cmu_retargeter(character, cmu).apply(base, partial)
    np.testing.assert_array_equal(got, fresh)
    untouched = np.setdiff1d(np.arange(len(base)), r.map_target[:5])
    np.testing.assert_array_equal(got[untouched], base[untouched])
    np.testing.assert_array_equal(r.apply(base, live_pose(rotations[300])), full)
    # A new calibration drops the cached rest products.
    r.calibrate_rotations(rotations[0])
    recalibrated = cmu_retargeter(character, cmu, rest_pose=rotations[0])
    np.testing.assert_allclose(
        r.apply(base, live_pose(rotations[300])),
        recalibrated.apply(base, live_pose(rotations[300])),
        atol=1e-12,
    )
    assert not np.allclose(r.apply(base, live_pose(rotations[300])), full, atol=1e-6)

"""Recording a take: retargeted poses -> a SkelAnimation that UsdSkel binds and reads back."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdSkel

from rigspace.runtime.live.buffer import LivePose
from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.frames import quat_angle
from rigspace.runtime.live.record import TakeError, TakeRecorder
from rigspace.runtime.live.retarget import PRESETS, Retargeter, target_skeleton
from rigspace.sdk.rotations import quat_from_matrix
from tests.runtime.live.conftest import CMU_CLIP, SAMPLE_CHARACTER


def test_take_binds_as_the_skeletons_animation(tmp_path):
    stage = Usd.Stage.Open(str(SAMPLE_CHARACTER))
    skel_prim = stage.GetPrimAtPath("/Character/Skel")
    joints, rest = target_skeleton(skel_prim)
    skeleton, motion, _ = read_bvh(CMU_CLIP)
    rotations, roots = skeleton.pose(motion[::4][:30])  # 30 Hz from the 120 Hz clip
    p = PRESETS["cmu"]
    r = Retargeter(
        skeleton.names, skeleton.parents, "local", joints, rest, p.bone_map, p.basis,
        p.meters_per_unit / 0.01,
    )  # fmt: skip
    recorder = TakeRecorder(joints)
    recorded = {}
    for k in range(30):
        pose = LivePose(rotations[k], np.ones(31, bool), roots[k], "connected", 1.0, 0.0)
        recorded[100 + k] = r.apply(rest, pose)
        recorder.add(100 + k, recorded[100 + k])
    take = recorder.write(tmp_path / "takes" / "take.usda", 30.0)

    # Bind the take as the character's animation (a session-layer edit) and read it through
    # UsdSkel's own query, as rigspace render and any DCC would.
    take_stage = Usd.Stage.Open(str(take))
    assert take_stage.GetTimeCodesPerSecond() == 30 and take_stage.GetStartTimeCode() == 100
    with Usd.EditContext(stage, stage.GetSessionLayer()):
        stage.DefinePrim("/Take").GetReferences().AddReference(str(take))
        UsdSkel.BindingAPI(skel_prim).CreateAnimationSourceRel().SetTargets(["/Take"])
    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(stage.GetPrimAtPath("/Character")), Usd.PrimDefaultPredicate)
    query = cache.GetSkelQuery(UsdSkel.Skeleton(skel_prim))
    for t in (100, 115, 129):
        local = np.array(query.ComputeJointLocalTransforms(Usd.TimeCode(t)))
        q_got = quat_from_matrix(np.swapaxes(local[:, :3, :3], 1, 2))
        q_want = quat_from_matrix(np.swapaxes(recorded[t][:, :3, :3], 1, 2))
        assert quat_angle(q_got, q_want).max() < 1e-6  # quatf on disk
        np.testing.assert_allclose(local[:, 3, :3], recorded[t][:, 3, :3], atol=1e-4)


def test_take_errors():
    with pytest.raises(TakeError, match="expected"):
        TakeRecorder(["a", "a/b"]).add(0, np.eye(4)[None])
    with pytest.raises(TakeError, match="empty"):
        TakeRecorder(["a"]).write("/tmp/never.usda", 30.0)

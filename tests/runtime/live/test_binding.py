"""A binding's runtime from its USD attributes: source, buffering, bone map and calibration."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from pxr import Usd, UsdSkel

from rigspace.runtime.live.binding import open_binding
from rigspace.runtime.live.decoders.vmc import HUMAN_BODY_BONES, encode_frame
from rigspace.runtime.live.frames import quat_angle
from rigspace.sdk.rotations import quat_from_matrix
from rigspace.sdk.schema import LiveBinding
from tests.runtime.live.conftest import CMU_CLIP, SAMPLE_CHARACTER, wait_for


def binding(url: str, **kw) -> LiveBinding:
    values = dict(
        name="suit", url=url, enabled=True, source_bones=(), target_joints=(),
        source_up_axis="Y", source_handedness="right", source_meters_per_unit=1.0, rest_pose=(),
        smoothing="none", smoothing_strength=0.5, buffering="latest", buffer_seconds=0.05,
        timeout_seconds=0.5,
    )  # fmt: skip
    values.update(kw)
    return LiveBinding(**values)


@pytest.fixture(scope="module")
def skel():
    stage = Usd.Stage.Open(str(SAMPLE_CHARACTER))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    local = np.array(
        UsdSkel.MakeTransforms(
            *(
                a.Get(0)
                for a in (anim.GetTranslationsAttr(), anim.GetRotationsAttr(), anim.GetScalesAttr())
            )
        )
    )
    return stage, stage.GetPrimAtPath("/Character/Skel"), local


def changed_joints(skel_prim, before, after) -> list[str]:
    joints = [str(j).rsplit("/", 1)[-1] for j in UsdSkel.Skeleton(skel_prim).GetJointsAttr().Get()]
    moved = np.any(np.abs(after - before) > 1e-9, axis=(1, 2))
    return [j for j, m in zip(joints, moved, strict=True) if m]


def test_replay_binding_uses_the_cmu_preset_and_reports(skel):
    _, skel_prim, local = skel
    runtime = open_binding(binding(f"replay://{CMU_CLIP}?speed=10"), skel_prim, 0.01)
    assert runtime.retargeter.scale == pytest.approx(0.0254 / 0.45 / 0.01)
    runtime.start()
    try:
        assert wait_for(lambda: runtime.buffer.samples > 31 * 20)
        out, pose = runtime.apply(local)
        assert pose.status == "connected" and pose.weight == 1.0
        # Every mapped joint moves; the collars only because the character's rest was aligned
        # onto the clip's (CMU's collars never turn).
        assert len(changed_joints(skel_prim, local, out)) == 22
        counters = runtime.counters()
        assert counters.samples >= 31 * 20 and counters.malformed == 0
    finally:
        runtime.stop()


def test_vmc_binding_with_an_authored_map_and_rest_pose(skel):
    _, skel_prim, local = skel
    rest = (0.9238795, 0.0, 0.3826834, 0.0)  # the performer's rest: upper arm turned 45 deg
    b = binding(
        "vmc://127.0.0.1:0",
        source_bones=("LeftUpperArm", "Hips"),
        target_joints=("upperarm_l", "pelvis"),
        source_handedness="left",  # VMC data is left-handed; the decoder converts it once
        rest_pose=(rest, (1.0, 0.0, 0.0, 0.0)),
    )
    runtime = open_binding(b, skel_prim, 0.01)
    runtime.start()
    try:
        q = np.tile([1.0, 0.0, 0.0, 0.0], (len(HUMAN_BODY_BONES), 1))
        # Unity data whose right-handed conversion is exactly `rest` (the conversion is its own
        # inverse, so encode_frame takes right-handed values).
        q[HUMAN_BODY_BONES.index("LeftUpperArm")] = rest
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for dgram in encode_frame(HUMAN_BODY_BONES, q, None, None, 1.0):
                s.sendto(dgram, runtime.source.address)
        assert wait_for(lambda: runtime.buffer.samples > 0)
        out, _ = runtime.apply(local)
        assert set(changed_joints(skel_prim, local, out)) <= {"upperarm_l", "pelvis"}
        np.testing.assert_allclose(runtime.retargeter.basis, np.diag([-1.0, 1.0, -1.0]))
        # In its calibrated rest pose the arm lands on the skeleton's rest rotation.
        skel_rest = np.array(UsdSkel.Skeleton(skel_prim).GetRestTransformsAttr().Get())
        arm = [
            str(j).rsplit("/", 1)[-1] for j in UsdSkel.Skeleton(skel_prim).GetJointsAttr().Get()
        ].index("upperarm_l")
        got = quat_from_matrix(out[arm, :3, :3].T)
        want = quat_from_matrix(skel_rest[arm, :3, :3].T)
        assert quat_angle(got, want) < 1e-6
        bones, rests = runtime.rest_pose_attributes()
        assert bones == ["LeftUpperArm", "Hips"]
        np.testing.assert_allclose(rests[0], rest, atol=1e-7)
    finally:
        runtime.stop()

"""A binding's runtime from its USD attributes: source, buffering, bone map and calibration."""

from __future__ import annotations

import socket
import warnings

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdSkel

from rigspace.runtime.live.binding import open_binding
from rigspace.runtime.live.buffer import BufferSettings
from rigspace.runtime.live.decoders.vmc import HUMAN_BODY_BONES, encode_frame
from rigspace.runtime.live.frames import quat_angle
from rigspace.runtime.live.retarget import RetargetError
from rigspace.sdk.ring_rules import check_live_binding
from rigspace.sdk.rotations import quat_from_matrix
from rigspace.sdk.schema import LiveBinding, LiveBindingDeprecationWarning, read_live_bindings
from tests.conftest import REPO
from tests.runtime.live.conftest import CMU_CLIP, SAMPLE_CHARACTER, wait_for

PREVIS = REPO / "samples" / "scenes" / "previs.usda"


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


def test_bone_preset_chooses_the_map_when_no_bones_are_authored(skel):
    _, skel_prim, _ = skel
    url = f"replay://{CMU_CLIP}"
    auto = open_binding(binding(url), skel_prim, 0.01).retargeter
    cmu = open_binding(binding(url, bone_preset="cmu"), skel_prim, 0.01).retargeter
    np.testing.assert_array_equal(auto.map_target, cmu.map_target)  # auto: replay -> cmu
    assert len(cmu.map_source) == 22
    # none: source bones onto joints of the same name; a CMU clip shares none with the sample.
    with pytest.raises(RetargetError, match="maps none of the source's bones"):
        open_binding(binding(url, bone_preset="none"), skel_prim, 0.01)
    with pytest.raises(RetargetError, match=r"bonePreset 'mixamo' names none of the bones"):
        open_binding(binding(url, bone_preset="mixamo"), skel_prim, 0.01)
    # Authored sourceBones win over any preset.
    own = binding(url, bone_preset="mixamo", source_bones=("Head",), target_joints=("head",))
    assert len(open_binding(own, skel_prim, 0.01).retargeter.map_source) == 1


_STAGES: list[Usd.Stage] = []


def hero_with(**attributes) -> Usd.Prim:
    """previs.usda's Hero with more of its `suit` binding's attributes authored."""
    stage = Usd.Stage.Open(str(PREVIS))
    _STAGES.append(stage)  # a prim does not keep its stage alive
    stage.SetEditTarget(stage.GetSessionLayer())
    hero = stage.GetPrimAtPath("/World/Hero")
    types = {
        "buffering": Sdf.ValueTypeNames.Token, "bonePreset": Sdf.ValueTypeNames.Token,
        "bufferSeconds": Sdf.ValueTypeNames.Float, "lostSeconds": Sdf.ValueTypeNames.Float,
        "timeoutSeconds": Sdf.ValueTypeNames.Float, "url": Sdf.ValueTypeNames.String,
        "gamepadOffsets": Sdf.ValueTypeNames.StringArray,
        "gamepadClips": Sdf.ValueTypeNames.StringArray,
    }  # fmt: skip
    for name, value in attributes.items():
        attr = hero.CreateAttribute(f"rigspace:live:suit:{name}", types[name], False)
        attr.Set(value)
    return hero


def codes(prim: Usd.Prim) -> dict[str, str]:
    return {i.code: i.message for i in check_live_binding(prim)}


def test_deprecated_buffering_tokens_still_read_with_a_warning():
    hero = hero_with(buffering="interpolate", bufferSeconds=0.2)
    with pytest.warns(LiveBindingDeprecationWarning, match=r"suit:buffering = 'interpolate'"):
        (b,) = read_live_bindings(hero)
    assert (b.buffering, b.buffer_seconds, b.buffering_authored) == ("delayed", 0.0, "interpolate")
    settings = BufferSettings.from_binding(b)
    assert (settings.mode, settings.delay) == ("delayed", None)  # one sample interval, as before
    hero = hero_with(buffering="buffered", bufferSeconds=0.2)
    with pytest.warns(LiveBindingDeprecationWarning):
        (b,) = read_live_bindings(hero)
    assert (b.buffering, b.buffer_seconds) == ("delayed", pytest.approx(0.2))
    with pytest.warns(LiveBindingDeprecationWarning):
        found = codes(hero)
    assert 'author buffering = "delayed"' in found["DeprecatedToken"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the current tokens warn nothing
        (b,) = read_live_bindings(hero_with(buffering="delayed"))
    assert b.buffering == "delayed" and "DeprecatedToken" not in codes(hero_with())


def test_validation_checks_the_new_attributes():
    assert codes(hero_with()) == {}  # previs.usda as committed
    found = codes(hero_with(bonePreset="unity", lostSeconds=0.3, timeoutSeconds=0.5))
    assert "bonePreset 'unity' is not a preset" in found["BadToken"]
    assert "lostSeconds is 0.3" in found["ValueOutOfRange"]
    assert "lostSeconds" not in str(codes(hero_with(lostSeconds=3.0)))
    pad = hero_with(
        url="gamepad:///dev/input/event3",
        gamepadOffsets=["ABS_RX:head:Y:-60", "ABS_RX:tail:Y:10", "ABS_Q:head:Y:5"],
        gamepadClips=["ABS_RZ:wave", "BTN_SOUTH:dance"],
    )
    found = codes(pad)
    assert "'ABS_Q:head:Y:5' is not CONTROL:JOINT:AXIS:DEGREES" in found["BadGamepadMap"]
    assert "names joint 'tail'" in found["TargetJointsMissing"]
    assert "clip 'dance'" in found["ClipMissing"] and "(walk, wave," in found["ClipMissing"]
    unused = codes(hero_with(gamepadClips=["ABS_RZ:wave"]))  # on the vmc:// suit
    assert set(unused) == {"GamepadMapUnused"}

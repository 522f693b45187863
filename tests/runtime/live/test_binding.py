"""A binding's runtime from its USD attributes: source, buffering, bone map and calibration."""

from __future__ import annotations

import itertools
import socket
import warnings

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdSkel

from rigspace.runtime.live.binding import open_binding
from rigspace.runtime.live.buffer import BufferSettings
from rigspace.runtime.live.decoders.vmc import HUMAN_BODY_BONES, encode_frame
from rigspace.runtime.live.retarget import RetargetError
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.sdk.ring_rules import check_live_binding
from rigspace.sdk.rotations import quat_from_matrix
from rigspace.sdk.schema import LiveBindingDeprecationWarning, read_live_bindings
from tests.conftest import REPO
from tests.runtime.live.conftest import (
    CMU_CLIP,
    SAMPLE_CHARACTER,
    full_pose,
    live_binding,
    sent_over_vmc,
    wait_for,
)

PREVIS = REPO / "samples" / "scenes" / "previs.usda"


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
    runtime = open_binding(live_binding(f"replay://{CMU_CLIP}?speed=10"), skel_prim, 0.01)
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
    b = live_binding(
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
    auto = open_binding(live_binding(url), skel_prim, 0.01).retargeter
    cmu = open_binding(live_binding(url, bone_preset="cmu"), skel_prim, 0.01).retargeter
    np.testing.assert_array_equal(auto.map_target, cmu.map_target)  # auto: replay -> cmu
    assert len(cmu.map_source) == 22
    # none: source bones onto joints of the same name; a CMU clip shares none with the sample.
    with pytest.raises(RetargetError, match="maps none of the source's bones"):
        open_binding(live_binding(url, bone_preset="none"), skel_prim, 0.01)
    with pytest.raises(RetargetError, match=r"bonePreset 'mixamo' names none of the bones"):
        open_binding(live_binding(url, bone_preset="mixamo"), skel_prim, 0.01)
    # Authored sourceBones win over any preset.
    own = live_binding(url, bone_preset="mixamo", source_bones=("Head",), target_joints=("head",))
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


def scaled_bvh(path, out, factor: float):
    """The CMU clip rewritten in other units, by the format (HIERARCHY OFFSETs and the root's
    three position channels, which this file's root lists first), not by the project's parser."""
    lines, motion = [], False
    for line in path.read_text().splitlines():
        words = line.split()
        if words[:1] == ["OFFSET"]:
            line = (
                line[: line.index("OFFSET")]
                + "OFFSET "
                + " ".join(f"{float(v) * factor:.6f}" for v in words[1:])
            )
        elif motion and words and words[0][0] in "-0123456789.":
            values = [float(v) for v in words]
            values[:3] = [v * factor for v in values[:3]]
            line = " ".join(f"{v:.6f}" for v in values)
        motion |= words[:1] == ["MOTION"]
        lines.append(line)
    out.write_text("\n".join(lines) + "\n")
    return out


@pytest.mark.parametrize(
    ("factor", "unit", "name"),
    [
        (1.0, 0.0254 / 0.45, "the CMU ASF unit"),
        (0.0254 / 0.45 / 0.01, 0.01, "centimetres"),  # the same clip in centimetres
        (0.0254 / 0.45, 1.0, "metres"),
    ],
)
def test_bvh_units_come_from_the_rest_pose(skel, tmp_path, capsys, factor, unit, name):
    _, skel_prim, _ = skel
    clip = scaled_bvh(CMU_CLIP, tmp_path / "clip.bvh", factor)
    runtime = open_binding(live_binding(f"replay://{clip}"), skel_prim, 0.01)
    assert runtime.retargeter.scale == pytest.approx(unit / 0.01, rel=1e-6)
    note = capsys.readouterr().err
    assert f"BVH units: {name}" in note and "1.28 m tall" in note
    authored = open_binding(
        live_binding(f"replay://{clip}", source_meters_per_unit=0.5), skel_prim, 0.01
    )
    assert authored.retargeter.scale == pytest.approx(0.5 / 0.01)  # authored wins, no guess


def test_an_unsure_unit_guess_says_what_to_author(skel, tmp_path, capsys):
    _, skel_prim, _ = skel
    clip = scaled_bvh(CMU_CLIP, tmp_path / "tiny.bvh", 0.3)  # a 38 cm figure in CMU units
    open_binding(live_binding(f"replay://{clip}"), skel_prim, 0.01)
    assert "author rigspace:live:suit:sourceMetersPerUnit" in capsys.readouterr().err


def _joint_angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per joint, the angle (deg) between two (J, 4, 4) row-vector transforms' rotations."""
    qa = quat_from_matrix(np.swapaxes(a[:, :3, :3], 1, 2))
    qb = quat_from_matrix(np.swapaxes(b[:, :3, :3], 1, 2))
    return np.degrees(quat_angle(qa, qb))


def test_connect_reconnect_and_loss_move_no_joint_more_than_10_degrees_a_tick(skel):
    """30 fps ticks through a connect (the stage pose to a pose 120 deg away), a loss (held,
    then the stage animation in place: the root stays where the performer left it) and a
    reconnect to another far pose: no joint turns more than 10 deg in one tick, no root jump."""
    from rigspace.runtime.live.source_frame import SourceFrame

    _, skel_prim, local = skel
    runtime = open_binding(live_binding("vmc://127.0.0.1:1"), skel_prim, 0.01)  # never started
    bones = runtime.source.bones
    arm = [bones.index("LeftUpperArm"), bones.index("RightUpperArm"), bones.index("Hips")]

    def frame(t: float, angle: float, x: float) -> SourceFrame:
        q = np.tile([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)], (3, 1))
        return SourceFrame(0, t, np.array(arm), q, np.array([x, 0.95, 0.0]))

    shown, roots, step, t = [], [], 1 / 30, 0.0
    for phase, (until, angle, x) in enumerate(
        [(1.0, 2.1, 0.0), (4.0, None, 0.0), (5.5, -2.1, 3.0)]
    ):
        while t < until:
            if angle is not None:  # data flows (phases 0 and 2); phase 1: the sender is gone
                runtime.buffer.push(frame(t, angle, x + (t - until) * 0.1), t)
            out, pose = runtime.apply_frame(local, now=t + 0.001)
            shown.append(out)
            roots.append(out[runtime.retargeter.target_root, 3, :3].copy())
            t += step
        assert phase != 1 or pose.status == "lost"
    per_tick = np.array([_joint_angles(a, b).max() for a, b in itertools.pairwise(shown)])
    assert per_tick.max() <= 10.0, np.argmax(per_tick)
    assert per_tick.max() > 1.0  # it did move: connect, loss and reconnect each turn the arms
    jumps = np.linalg.norm(np.diff(roots, axis=0), axis=1)
    assert jumps.max() < 0.25 * 100  # stage units (cm): under 25 cm a tick, even at reconnect
    lost = [r for r, k in zip(roots, range(len(roots)), strict=True) if 2.6 < k * step < 4.0]
    np.testing.assert_allclose(lost, [roots[int(2.0 / step)]] * len(lost), atol=1e-6)  # in place


def test_a_transition_cut_short_by_a_gap_or_a_reconnect_moves_no_joint_more_than_10_degrees(skel):
    """Transitions that do not finish: a connect's fade cut by a gap (stale), then a reconnect,
    then a loss whose fade back is cut by a reconnect. Each new fade starts from what the screen
    shows (the blend so far), so no joint turns more than 10 deg in a 30 fps tick (before: a
    reconnect during the loss's fade started from the stage animation, a 60-70 deg pop)."""
    from rigspace.runtime.live.source_frame import SourceFrame

    _, skel_prim, local = skel
    runtime = open_binding(live_binding("vmc://127.0.0.1:1"), skel_prim, 0.01)  # never started
    bones = runtime.source.bones
    arm = [bones.index("LeftUpperArm"), bones.index("RightUpperArm"), bones.index("Hips")]

    def frame(t: float, angle: float) -> SourceFrame:
        q = np.tile([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)], (3, 1))
        return SourceFrame(0, t, np.array(arm), q, np.array([0.0, 0.95, 0.0]))

    lost_after = runtime.buffer.settings.lost_after  # 2 s: 4 x the 0.5 s timeout
    phases = [  # (until, angle or None for a gap)
        (0.2, 2.1),  # a connect, its fade (0.5 s or more) cut short by...
        (0.9, None),  # ...a gap: stale
        (1.3, -2.1),  # a reconnect to a pose far away, cut short again
        (1.5 + lost_after + 0.15, None),  # lost, 0.15 s into the fade back to the stage
        (4.5 + lost_after, 2.1),  # a reconnect during that fade
    ]
    shown, statuses, step, t = [], [], 1 / 30, 0.0
    for until, angle in phases:
        while t < until:
            if angle is not None:
                runtime.buffer.push(frame(t, angle), t)
            out, pose = runtime.apply_frame(local, now=t + 0.001)
            shown.append(out)
            statuses.append(pose.status)
            t += step
    assert {"stale", "lost", "connected"} <= set(statuses)
    per_tick = np.array([_joint_angles(a, b).max() for a, b in itertools.pairwise(shown)])
    assert per_tick.max() <= 10.0, (np.argmax(per_tick), statuses[np.argmax(per_tick)])
    assert _joint_angles(shown[-1], runtime.apply(local, now=t)[0]).max() < 1e-6  # arrived


def test_a_fade_towards_a_pose_turning_through_the_opposite_one_does_not_flip(skel):
    """A fade's target can turn through the rotation opposite the one it fades from: the
    stage animation's root half a turn from where the performer left it, turning on while the
    loss fades back (or, at a connect, the stage root half a turn from the live one). The
    blend keeps turning the way it went; before, it flipped to the other short arc in one
    tick (the live reconnect test saw 172 deg at one tick of a loss on a loaded machine)."""
    from rigspace.runtime.live.source_frame import SourceFrame
    from rigspace.sdk.rotations import matrix_from_quat, quat_multiply

    _, skel_prim, local = skel
    runtime = open_binding(live_binding("vmc://127.0.0.1:1"), skel_prim, 0.01)  # never started
    bones = runtime.source.bones
    hips, root = bones.index("Hips"), runtime.retargeter.target_root
    live_root = np.array([np.cos(1.05), 0.0, 0.0, np.sin(1.05)])  # 120 deg about z

    def stage_turned(degrees: float) -> np.ndarray:
        """The stage pose, its root `degrees` about y from the live root's rotation."""
        half = np.radians(degrees) / 2
        q = quat_multiply(live_root, [np.cos(half), 0.0, np.sin(half), 0.0])
        out = local.copy()
        out[root, :3, :3] = np.swapaxes(matrix_from_quat(q), 0, 1)
        return out

    lost_after, step = runtime.buffer.settings.lost_after, 1 / 30
    shown, statuses, t, crossing = [], [], 0.0, 0.4  # the stage root at 180 deg then
    while t < 1.5 + lost_after + 2.0:
        if t < 1.5:  # connected (its fade from the stage: the connect case), then a gap
            frame = SourceFrame(0, t, np.array([hips]), live_root[None], np.zeros(3))
            runtime.buffer.push(frame, t)
        # The stage root crosses the opposite rotation 0.4 s into the connect's fade, and
        # again 0.4 s into the loss's (lost_after after the last sample), 40 deg a second.
        since = t - 0.0 if t < 1.5 else t - (1.5 + lost_after)
        out, pose = runtime.apply_frame(stage_turned(180.0 + 40.0 * (since - crossing)), t)
        shown.append(out)
        statuses.append(pose.status)
        t += step
    assert {"connected", "lost"} <= set(statuses)
    per_tick = np.array([_joint_angles(a, b)[root] for a, b in itertools.pairwise(shown)])
    worst = int(np.argmax(per_tick))
    assert per_tick.max() <= 10.0, (worst, statuses[worst], per_tick.max())


def test_a_bvh_binding_and_a_vmc_binding_pose_the_character_alike(skel):
    """Issue 21's pelvis rule through open_binding itself: the clip replayed as BVH (the cmu
    preset, the clip's own rest) and the same clip as `live send` puts it on the humanoid,
    received by a VMC binding (the T-pose rest): every joint, the pelvis included, lands on the
    same world rotation, because both bindings align their rest through the one humanoid."""
    from rigspace.runtime.live.decoders.bvh import read_bvh
    from rigspace.runtime.live.decoders.vmc import VmcDecoder
    from rigspace.runtime.live.send import humanoid_clip

    _, skel_prim, local = skel
    skeleton, motion, frame_time = read_bvh(CMU_CLIP)
    rotations, roots = skeleton.pose(motion[::150])
    clip = humanoid_clip(skeleton, rotations, roots, frame_time)
    bvh = open_binding(live_binding(f"replay://{CMU_CLIP}"), skel_prim, 0.01).retargeter
    vmc = open_binding(live_binding("vmc://127.0.0.1:0"), skel_prim, 0.01).retargeter
    decoder = VmcDecoder()
    parents = bvh.target_parents
    worst = 0.0
    for f in range(len(rotations)):
        a = vmc.apply(local, sent_over_vmc(clip, f, decoder))
        b = bvh.apply(local, full_pose(rotations[f]))
        world = []
        for out in (a, b):
            m = np.swapaxes(out[:, :3, :3], 1, 2).copy()
            for j in range(len(m)):  # parents come first in a UsdSkel joint order
                if parents[j] >= 0:
                    m[j] = m[parents[j]] @ m[j]
            world.append(quat_from_matrix(m))
        worst = max(worst, float(np.degrees(quat_angle(*world)).max()))
    assert worst < 1e-3  # float32 on the wire (was 2.7 deg at the pelvis: issue 21)

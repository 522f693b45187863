"""Recording a take: retargeted poses -> a SkelAnimation that UsdSkel binds and reads back."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdSkel

from rigspace.runtime.live.buffer import LivePose
from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.record import TakeError, TakeRecorder
from rigspace.runtime.live.retarget import PRESETS, Retargeter, target_skeleton
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.sdk.rotations import quat_from_matrix
from tests.runtime.live.conftest import CMU_CLIP, SAMPLE_CHARACTER, live_binding, started_source


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


def test_a_recorded_take_replays_onto_its_skeleton_exactly(tmp_path):
    from rigspace.runtime.live.binding import open_binding
    from tests.runtime.live.conftest import wait_for

    stage = Usd.Stage.Open(str(SAMPLE_CHARACTER))
    skel_prim = stage.GetPrimAtPath("/Character/Skel")
    joints, _ = target_skeleton(skel_prim)
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    recorder = TakeRecorder(joints)
    for t in range(360, 390):  # part of the wave clip, as the stage animates it
        local = UsdSkel.MakeTransforms(
            anim.GetTranslationsAttr().Get(t),
            anim.GetRotationsAttr().Get(t),
            anim.GetScalesAttr().Get(t),
        )
        recorder.add(t, np.array(local))
    take = recorder.write(tmp_path / "wave.usda", 30.0)
    binding = live_binding(f"replay://{take}?speed=4&loop=0", name="take")
    runtime = open_binding(binding, skel_prim, 0.01)
    runtime.start()
    try:
        assert runtime.source.finished.wait(60)  # type: ignore[attr-defined]
        assert wait_for(lambda: runtime.buffer.samples == 30 * 22)
        out, _ = runtime.apply(np.array(UsdSkel.MakeTransforms(
            anim.GetTranslationsAttr().Get(0), anim.GetRotationsAttr().Get(0), anim.GetScalesAttr().Get(0)
        )))  # fmt: skip
    finally:
        runtime.stop()
    want = np.array(
        UsdSkel.MakeTransforms(
            anim.GetTranslationsAttr().Get(389),
            anim.GetRotationsAttr().Get(389),
            anim.GetScalesAttr().Get(389),
        )
    )
    q = [quat_from_matrix(np.swapaxes(m[:, :3, :3], 1, 2)) for m in (out, want)]
    assert quat_angle(q[0], q[1]).max() < 1e-5
    np.testing.assert_allclose(out[:, 3, :3], want[:, 3, :3], atol=1e-4)


def test_replay_of_something_that_is_not_a_take(tmp_path):
    from rigspace.runtime.live.sources import open_source
    from rigspace.runtime.live.transports import LiveSourceError

    with pytest.raises(LiveSourceError, match=r"missing\.usda does not exist"):
        open_source(f"replay://{tmp_path}/missing.usda", "take")
    with pytest.raises(LiveSourceError, match="default prim must be a SkelAnimation"):
        open_source(f"replay://{SAMPLE_CHARACTER}", "take")


def _take(tmp_path, times=(10, 11, 12)):
    joints = ["hips", "hips/spine", "hips/spine/head"]
    recorder = TakeRecorder(joints)
    for t in times:
        local = np.tile(np.eye(4), (3, 1, 1))
        local[0, 3, :3] = (0, 90 + t, 0)
        recorder.add(t, local)
    return recorder.write(tmp_path / "take.usda", 30.0)


def _edit(path, change):
    """The take's layer with `change(anim_prim_spec)` applied, saved in place."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(path))
    change(layer.GetPrimAtPath("/Take"), layer)
    layer.Save()
    Sdf.Layer.Reload(layer, force=True)


def _retype(name, type_name, value):
    def change(prim, layer):
        from pxr import Sdf

        del prim.properties[name]
        attr = Sdf.AttributeSpec(prim, name, getattr(Sdf.ValueTypeNames, type_name))
        if name == "joints":
            attr.default = value
        else:
            layer.SetTimeSample(attr.path, 11, value)

    return change


def _set_sample(name, t, value):
    from pxr import Gf, Vt

    if name == "rotations":
        value = Vt.QuatfArray([Gf.Quatf(*q) for q in value])
    else:
        value = Vt.Vec3fArray([Gf.Vec3f(*v) for v in value])

    def change(prim, layer):
        layer.SetTimeSample(prim.properties[name].path, t, value)

    return change


CORPUS = {
    "empty file": (lambda p: p.write_text(""), "USD cannot read it|not a|empty"),
    "truncated": (lambda p: p.write_text(p.read_text()[:400]), "could not parse"),
    "not USD": (lambda p: p.write_bytes(b"\x00\x01garbage" * 40), "USD cannot read|not"),
    "rotations as float3[]": (
        lambda p: _edit(p, _retype("rotations", "Float3Array", [(0, 0, 0)] * 3)),
        r"'rotations' is authored as float3\[\]",
    ),
    "joints as string[]": (
        lambda p: _edit(p, _retype("joints", "StringArray", ["a", "b", "c"])),
        r"'joints' is authored as string\[\]",
    ),
    "a sample with too few rotations": (
        lambda p: _edit(p, _set_sample("rotations", 11, [(1, 0, 0, 0)] * 2)),
        r"'rotations' at time code 11 has 2 values for 3 joints",
    ),
    "a NaN quaternion": (
        lambda p: _edit(p, _set_sample("rotations", 12, [(float("nan"), 0, 0, 0)] + [(1, 0, 0, 0)] * 2)),
        r"'rotations' at time code 12 is not finite",
    ),
    "a zero quaternion": (
        lambda p: _edit(p, _set_sample("rotations", 10, [(1, 0, 0, 0), (0, 0, 0, 0), (1, 0, 0, 0)])),
        r"at time code 10 has a zero quaternion \(joint hips/spine\)",
    ),
    "translations of the wrong length": (
        lambda p: _edit(p, _set_sample("translations", 11, [(0, 0, 0)])),
        r"'translations' at time code 11 has 1 values for 3 joints",
    ),
    "an infinite root translation": (
        lambda p: _edit(p, _set_sample("translations", 12, [(0, float("inf"), 0)] * 3)),
        r"'translations' at time code 12 is not finite",
    ),
    "mis-ordered joints": (
        lambda p: _edit(p, lambda prim, layer: prim.properties["joints"].__setattr__(
            "default", ["hips/spine", "hips", "hips/spine/head"])),
        r"not a skeleton hierarchy \(Joint 0 has mis-ordered parent",
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CORPUS))
def test_a_damaged_take_is_one_named_error_from_the_reader_and_the_replay_source(tmp_path, case):
    from rigspace.runtime.live.record import read_take
    from rigspace.runtime.live.sources import open_source
    from rigspace.runtime.live.transports import LiveSourceError

    path = _take(tmp_path)
    assert read_take(path).rotations.shape == (3, 3, 4)  # sound before the damage
    damage, words = CORPUS[case]
    damage(path)
    with pytest.raises(TakeError, match=words) as info:
        read_take(path)
    assert str(path) in str(info.value) and "Fix:" in str(info.value)
    with pytest.raises(LiveSourceError, match=words):
        open_source(f"replay://{path}", "take")


def test_a_sound_take_reads_back_its_root_motion_and_times(tmp_path):
    from rigspace.runtime.live.record import read_take

    take = read_take(_take(tmp_path))
    np.testing.assert_allclose(take.root_positions[:, 1], [100, 101, 102])
    np.testing.assert_allclose(take.times, [0, 1 / 30, 2 / 30])
    np.testing.assert_allclose(take.rotations[..., 0], 1.0)
    assert take.parents == (-1, 0, 1) and take.bones == ("hips", "spine", "head")


def test_a_take_of_a_face_records_its_blend_shape_weights_and_replays_them(tmp_path):
    from rigspace.runtime.live.record import read_take
    from tests.runtime.live.conftest import wait_for

    joints, shapes = ["neck", "neck/head"], ["jawOpen", "blink"]
    recorder = TakeRecorder(joints, shapes)
    for t in range(5):
        recorder.add(t, np.tile(np.eye(4), (2, 1, 1)), np.array([t / 4, 1 - t / 4]))
    with pytest.raises(TakeError, match="expected 2 finite weights"):
        recorder.add(9, np.tile(np.eye(4), (2, 1, 1)), np.array([np.nan, 0.0]))
    path = recorder.write(tmp_path / "face.usda", 30.0)
    take = read_take(path)
    assert take.blend_shapes == tuple(shapes)
    np.testing.assert_allclose(take.blend_weights[:, 0], [0, 0.25, 0.5, 0.75, 1.0])
    # A take whose weights lost a value at one time code is named, like its rotations.
    _edit(path, lambda prim, layer: layer.SetTimeSample(
        prim.properties["blendShapeWeights"].path, 3, __import__("pxr").Vt.FloatArray([0.5])
    ))  # fmt: skip
    with pytest.raises(
        TakeError, match="'blendShapeWeights' at time code 3 has 1 values for 2 blend"
    ):
        read_take(path)
    recorder.write(path, 30.0)
    source, buffer = started_source(f"replay://{path}?speed=8&loop=0", "take")
    try:
        assert source.finished.wait(60)  # type: ignore[attr-defined]
        assert wait_for(lambda: buffer.pose().weights.get("jawOpen") == 1.0)
        assert buffer.pose().weights == {"jawOpen": 1.0, "blink": 0.0}
    finally:
        source.stop()

"""End to end over real sockets: the CMU clip sent over VMC (and BVH TCP) lands on the sample
character as the clip retargeted directly does."""

from __future__ import annotations

import dataclasses
import socket
import threading

import numpy as np
import pytest
from pxr import Usd, UsdSkel, Vt

from rigspace.runtime.live.binding import open_binding
from rigspace.runtime.live.buffer import LiveBuffer, LivePose
from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.decoders.vmc import VmcDecoder, encode_frame
from rigspace.runtime.live.retarget import (
    PRESETS,
    Retargeter,
    source_hierarchy,
    target_skeleton,
)
from rigspace.runtime.live.send import humanoid_clip, send_vmc, serve_bvh
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.runtime.live.sources import open_source
from rigspace.sdk.rotations import quat_from_matrix
from tests.runtime.live.conftest import (
    CMU_CLIP,
    SAMPLE_CHARACTER,
    full_pose,
    live_binding,
    sent_over_vmc,
    started_source,
    wait_for,
)

MATCH_RAD = 1e-3  # the bar for the received take against the clip


@pytest.fixture(scope="module")
def scene():
    stage = Usd.Stage.Open(str(SAMPLE_CHARACTER))
    skel = stage.GetPrimAtPath("/Character/Skel")
    skeleton, motion, frame_time = read_bvh(CMU_CLIP)
    rotations, roots = skeleton.pose(motion)
    return stage, skel, skeleton, motion, frame_time, rotations, roots


def local_rotations(transforms: np.ndarray) -> np.ndarray:
    return quat_from_matrix(np.swapaxes(transforms[:, :3, :3], 1, 2))


def test_cmu_over_vmc_matches_the_clip_retargeted_directly(scene):
    _stage, skel, skeleton, _, frame_time, rotations, roots = scene
    joints, rest = target_skeleton(skel)
    clip = humanoid_clip(skeleton, rotations, roots, frame_time, align=False)
    source = open_source("vmc://127.0.0.1:0", "suit")
    buffer = LiveBuffer(source.bones)
    # The plain convention, no rest alignment: the unity preset's map, basis and units.
    u = PRESETS["unity"]
    via_vmc = Retargeter(
        source.bones, source_hierarchy(source, u), source.space, joints, rest, u.bone_map,
        u.basis, u.meters_per_unit / 0.01,
    )  # fmt: skip
    p = PRESETS["cmu"]
    direct = Retargeter(
        skeleton.names, skeleton.parents, "local", joints, rest, p.bone_map, p.basis,
        p.meters_per_unit / 0.01,
    )  # fmt: skip
    worst: list[float] = []
    source.start(buffer)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for f in (0, 250, 500, 750, 993):
                before = buffer.samples
                for dgram in encode_frame(
                    clip.bones, clip.rotations[f], clip.root_positions[f], None, f * frame_time
                ):
                    s.sendto(dgram, source.address)
                # In the buffer, not only decoded: the receiver pushes after the decoder counts
                # (reading between the two, on a busy machine, saw the waiting pose).
                assert wait_for(lambda before=before: buffer.samples > before)
                received = via_vmc.apply(rest, buffer.pose())
                expected = direct.apply(
                    rest, LivePose(rotations[f], np.ones(31, bool), roots[f], "", 1, 0)
                )
                got, want = local_rotations(received), local_rotations(expected)
                worst.append(quat_angle(got, want).max())
                assert worst[-1] < MATCH_RAD, f
                np.testing.assert_allclose(received[0, 3, :3], expected[0, 3, :3], atol=1e-3)
    finally:
        source.stop()
    assert source.decoder.counters.malformed == 0
    print(f"largest joint rotation difference over VMC: {max(worst):.2e} rad")


def test_send_vmc_paces_the_clip(scene):
    _, _, skeleton, _, frame_time, rotations, roots = scene
    clip = humanoid_clip(skeleton, rotations[:48], roots[:48], frame_time)
    source, buffer = started_source("vmc://127.0.0.1:0", "suit")
    try:
        host, port = source.address
        sent = send_vmc(f"vmc://{host}:{port}", clip, speed=4.0)
        assert sent == 48
        # In the buffer, not only decoded (the receiver pushes after the decoder counts).
        decoded = source.decoder.counters
        assert wait_for(lambda: decoded.frames == 48 and buffer.samples == decoded.samples)
        # T carries the clip time: the receiver's jitter is measured against it.
        assert buffer.out_of_order == buffer.duplicates == 0
    finally:
        source.stop()


def test_serve_bvh_to_the_tcp_source(scene, free_tcp_port):
    _, _, _, motion, frame_time, rotations, _ = scene
    stop = threading.Event()
    server = threading.Thread(
        target=serve_bvh, args=("127.0.0.1", free_tcp_port, motion[:60], frame_time, 8.0, stop)
    )
    server.start()
    source, buffer = started_source(
        f"bvh+tcp://127.0.0.1:{free_tcp_port}?skeleton={CMU_CLIP}&retry=0.05", "n"
    )
    try:
        # Pushed, not only decoded: the receiver pushes a read's frames after decoding them all
        # (waiting on the decoder's count read the pose a few frames early on a busy machine).
        assert wait_for(lambda: buffer.samples >= 60 * len(source.bones))
        assert quat_angle(buffer.pose().rotations, rotations[59]).max() < 1e-5
    finally:
        source.stop()
        stop.set()
        server.join()


def test_humanoid_clip_is_a_humanoid(scene):
    _, _, skeleton, _, frame_time, rotations, roots = scene
    clip = humanoid_clip(skeleton, rotations[:2], roots[:2], frame_time)
    assert len(clip.bones) == 22 and "UpperChest" in clip.bones and "Hips" == clip.bones[0]
    np.testing.assert_allclose(np.linalg.norm(clip.rotations, axis=2), 1.0, atol=1e-12)
    assert dataclasses.is_dataclass(clip)


def two_paths(skel, skeleton, joints, rest) -> tuple[Retargeter, Retargeter]:
    """The receiver of the humanoid over VMC (aligned to the T-pose, open_binding's default)
    and the BVH retargeted straight onto the character (rest-aligned), in stage cm."""
    via_vmc = open_binding(
        live_binding("vmc://127.0.0.1:0"), skel, 0.01
    ).retargeter  # the unity preset, T-pose aligned
    p = PRESETS["cmu"]
    direct = Retargeter(
        skeleton.names, skeleton.parents, "local", joints, rest, p.bone_map, p.basis,
        p.meters_per_unit / 0.01,
    )  # fmt: skip
    direct.align_rest(skeleton.rest_positions(), p)  # through the humanoid, as open_binding does
    return via_vmc, direct


def test_aligned_send_and_receive_point_the_bones_where_the_clip_does(scene):
    """Sender on a T-posed humanoid, receiver aligned to the T-pose (open_binding's default):
    the character's limbs point where the directly retargeted, rest-aligned clip's do."""
    _stage, skel, skeleton, _, frame_time, rotations, roots = scene
    joints, rest = target_skeleton(skel)
    leaves = [j.rsplit("/", 1)[-1] for j in joints]
    clip = humanoid_clip(skeleton, rotations[::200], roots[::200], frame_time)
    via_vmc, direct = two_paths(skel, skeleton, joints, rest)
    decoder = VmcDecoder()
    for f in range(len(clip.rotations)):
        received = np.tile([1.0, 0.0, 0.0, 0.0], (len(decoder.bones), 1))
        # The wire is float32: go through the decoder like the UDP test does.
        frames = [
            x
            for d in encode_frame(clip.bones, clip.rotations[f], None, None, float(f))
            for x in decoder.feed(d, 0.0)
        ]
        for frame in frames:
            received[frame.indices] = frame.rotations
        a = via_vmc.apply(rest, LivePose(received, np.ones(len(received), bool), None, "", 1, 0))
        b = direct.apply(rest, LivePose(rotations[::200][f], np.ones(31, bool), None, "", 1, 0))
        pos = [
            np.array(
                UsdSkel.ConcatJointTransforms(
                    UsdSkel.Topology(joints), Vt.Matrix4dArray.FromNumpy(m)
                )
            )[:, 3, :3]
            for m in (a, b)
        ]
        for parent, child in (
            ("upperarm_l", "lowerarm_l"),
            ("lowerarm_r", "hand_r"),
            ("thigh_l", "calf_l"),
            ("calf_r", "foot_r"),
        ):
            u, v = (q[leaves.index(child)] - q[leaves.index(parent)] for q in pos)
            assert np.arctan2(np.linalg.norm(np.cross(u, v)), np.dot(u, v)) < 1e-4, (f, parent)


def test_send_puts_the_bones_real_offsets_on_the_wire_and_the_hips_where_the_clip_has_them(scene):
    """Read with python-osc alone, as a third-party receiver would: Bone/Pos carries each bone's
    offset (a real skeleton, not one collapsed at the origin), and Root/Pos plus the Hips offset
    is the clip's hips position."""
    from pythonosc.osc_packet import OscPacket

    _, _, skeleton, _, frame_time, rotations, roots = scene
    clip = humanoid_clip(skeleton, rotations[:3], roots[:3], frame_time)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(10.0)
        send_vmc(f"vmc://127.0.0.1:{rx.getsockname()[1]}", dataclasses.replace(clip), 50.0)
        positions, root = {}, None
        while root is None or len(positions) < len(clip.bones):
            for timed in OscPacket(rx.recv(65536)).messages:
                address, params = timed.message.address, timed.message.params
                if address == "/VMC/Ext/Bone/Pos":
                    positions.setdefault(params[0], np.array(params[1:4]))
                elif address == "/VMC/Ext/Root/Pos" and root is None:
                    root = np.array(params[1:4])
    lengths = {bone: float(np.linalg.norm(p)) for bone, p in positions.items()}
    assert lengths["Hips"] > 0.5 and lengths["LeftLowerLeg"] > 0.2 and lengths["Head"] > 0.05
    hips = (root + positions["Hips"]) * [1, 1, -1]  # Unity's frame back to right-handed
    np.testing.assert_allclose(hips, clip.root_positions[0], atol=1e-5)


def _world_rotations(joints, local: np.ndarray) -> np.ndarray:
    world = np.array(
        UsdSkel.ConcatJointTransforms(UsdSkel.Topology(joints), Vt.Matrix4dArray.FromNumpy(local))
    )
    r = world[:, :3, :3] / np.linalg.norm(world[:, :3, :3], axis=2)[:, :, None]
    return quat_from_matrix(np.swapaxes(r, 1, 2))


def test_the_pelvis_is_the_same_sent_over_vmc_and_retargeted_directly(scene):
    """The clip sent through the humanoid (live send, VMC) and retargeted straight from the BVH
    (bvh+tcp, replay) turn every joint of the character alike, the pelvis included: 15 deg apart
    when the root's rest was aligned by one child alone (issue 21), 2.7 deg (the clavicles 2.3)
    when each path fitted its own rest directly; the same to float32 now that every preset's
    rest is aligned through the canonical T-posed humanoid (measured: 1e-5 deg)."""
    _stage, skel, skeleton, _, frame_time, rotations, roots = scene
    joints, rest = target_skeleton(skel)
    leaves = [j.rsplit("/", 1)[-1] for j in joints]
    picks = list(range(0, len(rotations), 100))
    clip = humanoid_clip(skeleton, rotations[picks], roots[picks], frame_time)
    via_vmc, direct = two_paths(skel, skeleton, joints, rest)
    decoder = VmcDecoder()
    worst = np.zeros(len(joints))
    for f, k in enumerate(picks):
        a = via_vmc.apply(rest, sent_over_vmc(clip, f, decoder))
        b = direct.apply(rest, full_pose(rotations[k]))
        angle = np.degrees(quat_angle(_world_rotations(joints, a), _world_rotations(joints, b)))
        worst = np.maximum(worst, angle)
    assert worst.max() < 1e-3, dict(zip(leaves, worst.round(5), strict=True))  # 1e-5: float32


def test_the_root_moves_alike_sent_over_vmc_and_retargeted_directly(scene):
    """Root motion through live send's wire format (Root/Pos under the hips, the Hips offset
    in Bone/Pos, issue 21's rule) and straight from the BVH's root channels: the character's
    root joint lands within 2 cm on every sampled frame (the issue's aim), metres to cm."""
    _stage, skel, skeleton, _, frame_time, rotations, roots = scene
    joints, rest = target_skeleton(skel)
    picks = list(range(0, len(rotations), 50))
    clip = humanoid_clip(skeleton, rotations[picks], roots[picks], frame_time)
    via_vmc, direct = two_paths(skel, skeleton, joints, rest)
    hips = clip.offsets[clip.bones.index("Hips")]
    decoder = VmcDecoder()
    root = via_vmc.target_root
    worst = 0.0
    travel = []
    for f, k in enumerate(picks):
        received = np.tile([1.0, 0.0, 0.0, 0.0], (len(decoder.bones), 1))
        position = None
        datagrams = encode_frame(
            clip.bones, clip.rotations[f], clip.root_positions[f] - hips, None, float(f),
            clip.offsets,
        )  # fmt: skip
        for d in datagrams:
            for frame in decoder.feed(d, 0.0):
                received[frame.indices] = frame.rotations
                position = frame.root_position
        valid = np.ones(len(received), bool)
        a = via_vmc.apply(rest, LivePose(received, valid, position, "", 1, 0))
        b = direct.apply(rest, LivePose(rotations[k], np.ones(31, bool), roots[k], "", 1, 0))
        worst = max(worst, float(np.linalg.norm(a[root, 3, :3] - b[root, 3, :3])))
        travel.append(b[root, 3, :3])
    assert np.ptp(np.array(travel), axis=0).max() > 100  # the clip travels metres: a real test
    assert worst < 2.0, worst  # stage units: centimetres (measured: 6e-6, float32 on the wire)

"""Seven real x-IMU3 sensors on the lower body, replayed as x-IMU3 messages through a pty pair
each, onto the sample character's pelvis and legs (world-space retargeting, calibrated)."""

from __future__ import annotations

import os
import threading
import tty
from pathlib import Path

import numpy as np
from pxr import Usd, UsdSkel, Vt

from rigspace.runtime.live.buffer import LiveBuffer
from rigspace.runtime.live.retarget import Retargeter, source_basis, target_skeleton
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.runtime.live.sources import open_source
from rigspace.sdk.rotations import quat_from_matrix, quat_multiply
from tests.runtime.live.conftest import SAMPLE_CHARACTER, quat_conjugate, wait_for

RECORDING = Path(__file__).resolve().parents[3] / "samples" / "device_streams" / "ximu3_lower_body"
SENSORS = {
    "pelvis": "pelvis",
    "Left_Upper_Leg": "thigh_l",
    "Left_Lower_Leg": "calf_l",
    "Left_Foot": "foot_l",
    "Right_Upper_Leg": "thigh_r",
    "Right_Lower_Leg": "calf_r",
    "Right_Foot": "foot_r",
}
ROWS = 120  # about 2.4 s of the recording per sensor


def sensor_rows(prefix: str) -> np.ndarray:
    (folder,) = [p for p in RECORDING.iterdir() if p.name.startswith(prefix + "_")]
    return np.loadtxt(folder / "Quaternion.csv", delimiter=",", skiprows=1, max_rows=ROWS)


def replay_through_ptys(rows: dict[str, np.ndarray]):
    """Each sensor's rows written as x-IMU3 quaternion messages into a pty pair of its own,
    read by one serial:// source (format=ximu3) until every sample has arrived: the source
    (stopped) and its last pose."""
    pairs = [os.openpty() for _ in SENSORS]
    for _, follower in pairs:
        tty.setraw(follower)
    devices = ",".join(os.ttyname(f) for _, f in pairs)
    source = open_source(
        f"serial://{devices}?format=ximu3&bones={','.join(SENSORS.values())}", "legs"
    )
    buffer = LiveBuffer(source.bones)
    source.start(buffer)
    writers = []
    try:
        for (leader, _), data in zip(pairs, rows.values(), strict=True):
            text = "".join(
                f"Q,{int(t)},{w:.6f},{x:.6f},{y:.6f},{z:.6f}\r\n" for t, w, x, y, z in data
            )
            writer = threading.Thread(target=os.write, args=(leader, text.encode()))
            writer.start()
            writers.append(writer)
        assert wait_for(lambda: buffer.samples == ROWS * len(SENSORS), timeout=60)
        pose = buffer.pose()
    finally:
        for w in writers:
            w.join()
        source.stop()
        for leader, follower in pairs:
            os.close(leader)
            os.close(follower)
    return source, pose


def world_rotations(topology: UsdSkel.Topology, local: np.ndarray) -> np.ndarray:
    """(J, 4) world-space joint rotations of (J, 4, 4) local transforms."""
    world = UsdSkel.ConcatJointTransforms(topology, Vt.Matrix4dArray.FromNumpy(local))
    return quat_from_matrix(np.swapaxes(np.array(world)[:, :3, :3], 1, 2))


def test_lower_body_recording_through_ptys():
    rows = {name: sensor_rows(name) for name in SENSORS}
    source, pose = replay_through_ptys(rows)
    c = source.counters()
    assert c.malformed == 0 and c.dropped == 0 and c.status == "connected"
    first = np.array([r[0, 1:] for r in rows.values()])
    last = np.array([r[-1, 1:] for r in rows.values()])
    last /= np.linalg.norm(last, axis=1, keepdims=True)
    assert quat_angle(pose.rotations, last).max() < 1e-6

    stage = Usd.Stage.Open(str(SAMPLE_CHARACTER))
    joints, rest = target_skeleton(stage.GetPrimAtPath("/Character/Skel"))
    # The recording starts in its calibration pose: that first sample is the rest pose.
    basis = source_basis("Z", "right")  # x-IMU3 Earth frame: NWU, Z up
    r = Retargeter(
        source.bones, [-1] * 7, "world", joints, rest, {b: b for b in source.bones}, basis,
        rest_pose=first,
    )  # fmt: skip
    out = r.apply(rest, pose)
    topology = UsdSkel.Topology(joints)
    world = world_rotations(topology, out)
    rest_world = world_rotations(topology, rest)
    a = quat_from_matrix(basis)
    for k, joint in enumerate(source.bones):
        j = [p.rsplit("/", 1)[-1] for p in joints].index(joint)
        sensor_delta = quat_multiply(last[k], quat_conjugate(first[k] / np.linalg.norm(first[k])))
        expected = quat_multiply(quat_multiply(a, sensor_delta), quat_conjugate(a))
        got = quat_multiply(world[j], quat_conjugate(rest_world[j]))
        assert quat_angle(got, expected) < 1e-5, joint
    # The legs really moved in these 2.4 s (the test is not comparing identities).
    assert quat_angle(last, first / np.linalg.norm(first, axis=1, keepdims=True)).max() > 0.05

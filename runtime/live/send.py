"""Stream a BVH clip as a live source would: VMC over UDP, or a BVH line server over TCP."""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass
from urllib.parse import urlsplit

import numpy as np

from rigspace.runtime.live.decoders.bvh import BvhSkeleton
from rigspace.runtime.live.decoders.vmc import encode_frame
from rigspace.runtime.live.retarget import CMU, UNITY, Preset, Retargeter, humanoid_rig
from rigspace.sdk.rotations import quat_from_matrix


@dataclass(frozen=True)
class HumanoidClip:
    """A clip re-expressed on Unity's HumanBodyBones, in VmcDecoder's frame (right-handed, the
    avatar facing -Z), ready for `encode_frame`."""

    bones: tuple[str, ...]
    rotations: np.ndarray
    """(F, H, 4) local rotations (w, x, y, z); identity is each bone's rest."""
    root_positions: np.ndarray
    """(F, 3) metres: where the hips are."""
    frame_time: float
    offsets: np.ndarray | None = None
    """(H, 3) each bone's local position in the T-posed humanoid (from its parent, metres): what
    Bone/Pos carries, so that a receiver that builds the skeleton from it gets a real one."""


def humanoid_clip(
    skeleton: BvhSkeleton,
    rotations: np.ndarray,
    roots: np.ndarray,
    frame_time: float,
    preset: Preset = CMU,
    align: bool = True,
) -> HumanoidClip:
    """Re-express a BVH clip's pose on HumanBodyBones (an avatar whose rest locals are identity).

    Each humanoid bone takes the world rotation of the BVH bone that the two presets map to the
    same sample-character joint (CMU's LHipJoint, lowerneck, ... fold into their children).
    With `align` (the default) the humanoid rests in a T-pose, as VMC receivers assume, and the
    clip's rest is aligned onto it, so its bones point where the clip's do. Without, identity is
    the clip's own rest, and retargeting the result with the `unity` preset gives exactly what
    retargeting the clip with `preset` gives (tested to float32 precision through real UDP).
    """
    by_joint = {joint: bone for bone, joint in UNITY.bone_map.items()}
    bone_map = {src: by_joint[joint] for src, joint in preset.bone_map.items()}
    humanoid = humanoid_rig()
    order = [path.rsplit("/", 1)[-1] for path in humanoid.paths]
    rest = humanoid.rest
    # Humanoid frame = VMC-decoded frame; A maps the BVH frame into it (the inverse of unity's).
    basis = UNITY.basis.T @ preset.basis
    r = Retargeter(skeleton.names, skeleton.parents, "local", humanoid.paths, rest, bone_map, basis)
    if align:
        r.align_rest(skeleton.rest_positions())  # the clip's rest onto the T-posed humanoid
    frames = np.empty((len(rotations), len(order), 4))
    stage = np.tile(np.eye(4), (len(order), 1, 1))
    valid = np.ones(len(skeleton.names), dtype=bool)
    from rigspace.runtime.live.buffer import LivePose

    for f in range(len(rotations)):
        pose = LivePose(rotations[f], valid, None, "connected", 1.0, 0.0)
        local = r.apply(stage, pose)
        frames[f] = quat_from_matrix(np.swapaxes(local[:, :3, :3], 1, 2))
    metres = (basis @ roots.T).T * preset.meters_per_unit
    return HumanoidClip(tuple(order), frames, metres, frame_time, rest[:, 3, :3].copy())


def send_vmc(
    url: str,
    clip: HumanoidClip,
    speed: float = 1.0,
    loop: bool = False,
    stop: threading.Event | None = None,
    frames: int | None = None,
) -> int:
    """Send `clip` to vmc://HOST:PORT in real time (scaled by speed), with /VMC/Ext/T carrying
    the clip time; returns the frames sent. `stop` ends it early; `frames` ends it after that
    many (a sender held back by a busy machine catches up and sends them all)."""
    parts = urlsplit(url)
    address = (parts.hostname or "127.0.0.1", parts.port or 39539)
    stop = stop or threading.Event()
    step = clip.frame_time / speed
    sent = 0
    start = time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        while not stop.is_set() and (frames is None or sent < frames):
            i = sent % len(clip.rotations)
            if sent and i == 0 and not loop:
                break
            wait = start + sent * step - time.monotonic()
            if wait > 0 and stop.wait(wait):
                break
            root = clip.root_positions[i]
            if clip.offsets is not None and "Hips" in clip.bones:
                # Root/Pos under the hips, Hips' Bone/Pos its height above it: a receiver that
                # adds the two (rigspace's VmcDecoder, a Unity avatar) puts the hips on the clip's.
                root = root - clip.offsets[clip.bones.index("Hips")]
            for dgram in encode_frame(
                clip.bones, clip.rotations[i], root, None, sent * step, clip.offsets
            ):
                sock.sendto(dgram, address)
            sent += 1
    return sent


def bvh_lines(motion: np.ndarray) -> list[bytes]:
    """One data-stream line per frame of channel values (Axis Neuron's layout, no prefix)."""
    return [(" ".join(f"{v:.6f}" for v in row) + "\n").encode() for row in motion]


def serve_bvh(
    host: str,
    port: int,
    motion: np.ndarray,
    frame_time: float,
    speed: float = 1.0,
    stop: threading.Event | None = None,
    loop: bool = False,
) -> int:
    """Serve a BVH clip's lines to one TCP client at a time in real time (what a
    bvh+tcp:// source connects to). At the clip's end the connection stays open and silent
    (a paused performer) unless `loop` starts the clip again; returns the lines sent when
    `stop` is set."""
    stop = stop or threading.Event()
    lines = bvh_lines(motion)
    sent = 0
    with socket.create_server((host, port)) as server:
        server.settimeout(0.1)
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            with conn:
                start, k = time.monotonic(), 0
                while not stop.is_set():
                    if k == len(lines):
                        if not loop:
                            stop.wait()
                            break
                        start, k = start + k * frame_time / speed, 0
                    wait = start + k * frame_time / speed - time.monotonic()
                    if wait > 0 and stop.wait(wait):
                        break
                    try:
                        conn.sendall(lines[k])
                    except OSError:
                        break  # the client left: wait for the next one
                    sent += 1
                    k += 1
    return sent

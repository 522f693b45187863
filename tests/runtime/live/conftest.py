"""Live-input fixtures: the committed CMU clip, free local ports, a started source, bindings and
poses as the tests build them, and a run driven by the frames it renders."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np
import pytest

from rigspace.runtime.live.buffer import LiveBuffer, LivePose
from rigspace.runtime.live.decoders.vmc import VmcDecoder, encode_frame
from rigspace.runtime.live.sources import open_source
from rigspace.sdk.rotations import quat_multiply
from rigspace.sdk.schema import LiveBinding
from tests.conftest import REPO, free_port

CMU_CLIP = REPO / "samples" / "motion" / "cmu_131_01.bvh"
SAMPLE_CHARACTER = REPO / "samples" / "character" / "sample_character.usda"


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Inverse of unit quaternions (w, x, y, z): a reference of the tests' own."""
    return np.asarray(q) * np.array([1.0, -1.0, -1.0, -1.0])


def compose_world(local: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(N, 4) local rotations -> world rotations, each bone after its parent (a loop over
    the bones: the reference for the retargeter's composition by levels)."""
    world = np.array(local, dtype=np.float64)
    done = np.zeros(len(parents), dtype=bool)
    while not done.all():
        for b in np.flatnonzero(~done):
            p = int(parents[b])
            if p < 0 or done[p]:
                world[b] = local[b] if p < 0 else quat_multiply(world[p], local[b])
                done[b] = True
    return world


def started_source(url: str, name: str):
    """The live source of `url` (open_source), started into a LiveBuffer of its bones: both."""
    source = open_source(url, name)
    buffer = LiveBuffer(source.bones)
    source.start(buffer)
    return source, buffer


def full_pose(rotations: np.ndarray) -> LivePose:
    """A pose of (bones, 4) `rotations`, every bone valid (no root position, full weight)."""
    return LivePose(rotations, np.ones(len(rotations), bool), None, "", 1, 0)


def sent_over_vmc(clip, f: int, decoder: VmcDecoder) -> LivePose:
    """Frame `f` of a humanoid clip (live send's) as `decoder` receives it over VMC, in its
    bones' order (identity where the clip has no bone)."""
    received = np.tile([1.0, 0.0, 0.0, 0.0], (len(decoder.bones), 1))
    for d in encode_frame(clip.bones, clip.rotations[f], None, None, float(f)):
        for frame in decoder.feed(d, 0.0):
            received[frame.indices] = frame.rotations
    return full_pose(received)


def live_binding(url: str, **kw) -> LiveBinding:
    """A live binding "suit" from `url` as the schema's defaults give it, but for no smoothing,
    the latest sample buffered and half a second's timeout; `kw` overrides any field."""
    values = dict(
        name="suit", url=url, enabled=True, source_bones=(), target_joints=(),
        source_up_axis="Y", source_handedness="right", source_meters_per_unit=1.0, rest_pose=(),
        smoothing="none", smoothing_strength=0.5, buffering="latest", buffer_seconds=0.05,
        timeout_seconds=0.5,
    )  # fmt: skip
    values.update(kw)
    return LiveBinding(**values)


def wait_for(condition: Callable[[], bool], timeout: float = 15.0) -> bool:
    """Poll `condition` until it holds or `timeout` seconds pass (receivers run on threads;
    the timeout is generous because CI shares 2 cores, and a passing test never waits it out)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.005)
    return condition()


def udp_port_bound(port: int) -> bool:
    """Whether something listens on UDP 127.0.0.1:port (a receiver thread has started)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return True
    return False


@pytest.fixture
def free_tcp_port() -> int:
    return free_port()


class FrameDriver:
    """Drives a `rigspace live` run in this process by the frames it renders: every
    Engine.render (the warm-up's first) calls `on_frame(engine, frame)`; when it returns True
    the run stops as Ctrl-C stops it (it still writes its report, video and take). So a test
    waits on what the code under test does (a frame rendered, a status reached), never on the
    clock; `--seconds` is only the bound of a run that never gets there."""

    def __init__(self, monkeypatch, on_frame: Callable) -> None:
        from rigspace.runtime.engine import Engine

        self.frames = 0
        real = Engine.render

        def render(engine, time_code):
            frame = real(engine, time_code)
            self.frames += 1
            # Only inside the live loop (not the warm-up frame), where Ctrl-C is caught.
            if on_frame(engine, frame) and self.frames > 1:
                raise KeyboardInterrupt
            return frame

        monkeypatch.setattr(Engine, "render", render)


class Sender:
    """The CMU clip over VMC to `url` from a process of its own (tests/runtime/live/
    vmc_sender.py: a renderer holding this process's GIL cannot starve it), in real time,
    looping, until closed; `turn` degrees turns its hips (poses the clip never has). Each
    Sender is a new sender process: a new source port, its /VMC/Ext/T from 0."""

    def __init__(self, url: str, turn: float = 0.0) -> None:
        command = [sys.executable, "-m", "tests.runtime.live.vmc_sender", url, "--turn", str(turn)]
        self.process = subprocess.Popen(command, cwd=REPO)

    def close(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(30)
        except subprocess.TimeoutExpired:  # only a bound: SIGTERM ends it at once
            self.process.kill()
            self.process.wait()

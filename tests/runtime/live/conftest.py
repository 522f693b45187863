"""Live-input fixtures: the committed CMU clip and free local ports."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

import numpy as np
import pytest

from rigspace.sdk.rotations import quat_multiply
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

"""Shared fixtures: tiny character scenes built on the fly, the repository's paths."""

from __future__ import annotations

import json
import os
import random
import socket
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis.configuration import set_hypothesis_home_dir

import rigspace.sdk  # noqa: F401  (registers the schemas before any stage is opened)

REPO = Path(__file__).resolve().parents[1]

# Tests write only under the temporary folder: Hypothesis keeps its example database (a
# failing example is replayed on the next run) and caches there, not in .hypothesis/ of the
# working directory (the checkout).
set_hypothesis_home_dir(Path(tempfile.gettempdir()) / f"rigspace-hypothesis-{os.getuid()}")
SHARED_ASSETS = REPO.parent / "shared" / "assets"
CESIUM_MAN = REPO / "samples" / "assets" / "CesiumMan" / "CesiumMan.usdz"


def _ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_port() -> int:
    """A port on 127.0.0.1 that nothing holds now (UDP and TCP), chosen below the kernel's
    ephemeral range.

    A port from bind(0) lies in the ephemeral range, where any process's outgoing socket (a DNS
    lookup, another test run on the same machine) can take it between this call and the
    receiver's own bind: CI lost `test_probe_reports_a_vmc_sender` that way. Below the range only
    deliberate listeners collide, and a random pick makes two runs' picks unlikely to meet.
    """
    low = max(_ephemeral_low(), 12000)
    chooser = random.SystemRandom()
    for _ in range(200):
        port = chooser.randrange(10000, low)
        try:
            for k in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
                with socket.socket(socket.AF_INET, k) as s:
                    s.bind(("127.0.0.1", port))
        except OSError:
            continue
        return port
    raise RuntimeError(f"no free port on 127.0.0.1 below {low} after 200 tries")


TINY_JOINTS = ["hips", "hips/spine", "hips/spine/head", "hips/leg_l", "hips/leg_r"]


def write_tiny_scene(
    folder: Path, body: str = "", character: str = "", extra_apis: str = ""
) -> Path:
    """A valid scene: a 5-joint skeleton animated over time codes 0-10 and a neural character.

    `character` adds property lines to the character prim, `extra_apis` adds to its
    apiSchemas list, `body` adds prims under /World.
    """
    joints = ", ".join(f'"{j}"' for j in TINY_JOINTS)
    identity = ", ".join(["((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1))"] * len(TINY_JOINTS))
    rotations = ", ".join(["(1, 0, 0, 0)"] * len(TINY_JOINTS))
    turned = ", ".join(["(0.9238795, 0, 0.3826834, 0)"] * len(TINY_JOINTS))
    translations = ", ".join(["(0, 1, 0)"] * len(TINY_JOINTS))
    apis = '"RigspaceCaptureRingAPI"' + (", " + extra_apis if extra_apis else "")
    text = f"""#usda 1.0
(
    defaultPrim = "World"
    metersPerUnit = 1
    upAxis = "Y"
    startTimeCode = 0
    endTimeCode = 10
    timeCodesPerSecond = 30
)

def Xform "World"
{{
    def SkelRoot "Asset"
    {{
        def Skeleton "Skel" (prepend apiSchemas = ["SkelBindingAPI"])
        {{
            uniform token[] joints = [{joints}]
            uniform matrix4d[] bindTransforms = [{identity}]
            uniform matrix4d[] restTransforms = [{identity}]
            rel skel:animationSource = </World/Asset/Skel/Anim>

            def SkelAnimation "Anim"
            {{
                uniform token[] joints = [{joints}]
                quatf[] rotations.timeSamples = {{ 0: [{rotations}], 10: [{turned}] }}
                float3[] translations.timeSamples = {{ 0: [{translations}], 10: [{translations}] }}
                half3[] scales = [{", ".join(["(1, 1, 1)"] * len(TINY_JOINTS))}]
            }}
        }}
    }}

    def RigspaceNeuralCharacter "Hero" (prepend apiSchemas = [{apis}])
    {{
        rel rigspace:skeleton = </World/Asset/Skel>
        uniform float2[] rigspace:captureRing:clipRanges = [(0, 4), (5, 10)]
        uniform token[] rigspace:captureRing:clipNames = ["a", "b"]
        uniform token[] rigspace:captureRing:heldOutClips = ["b"]
{character}
    }}
{body}
}}
"""
    path = folder / "scene.usda"
    path.write_text(text)
    return path


def axis_rotations(axis: str, degrees) -> np.ndarray:
    """(n, 3, 3) rotation matrices about the coordinate axis X, Y or Z (either case)."""
    a = np.radians(np.asarray(degrees, dtype=np.float64))
    c, s, one, zero = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    rows = {
        "X": [[one, zero, zero], [zero, c, -s], [zero, s, c]],
        "Y": [[c, zero, s], [zero, one, zero], [-s, zero, c]],
        "Z": [[c, -s, zero], [s, c, zero], [zero, zero, one]],
    }[axis.upper()]
    return np.moveaxis(np.array(rows), (0, 1), (-2, -1))


def write_bundle_manifest(folder: Path, joints: list[str], **overrides) -> Path:
    """A model bundle folder holding only a manifest (what the validators read)."""
    folder.mkdir(parents=True, exist_ok=True)
    manifest = {
        "format": "rigspace.bundle",
        "format_version": 1,
        "joints": joints,
        "rotation_encoding": "rot6d",
        "maps": ["albedo", "normal", "depth", "mask"],
        "training_camera": {"distance": 3.0, "focal_length": 50.0, "horizontal_aperture": 20.955},
    }
    manifest.update(overrides)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


@pytest.fixture
def tiny_scene(tmp_path: Path):
    """Factory: write_tiny_scene into the test's tmp_path."""

    def make(**kwargs) -> Path:
        return write_tiny_scene(tmp_path, **kwargs)

    return make


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """A 64-sample CesiumMan dataset at 32x32, captured once per session (tests/train/conftest.py)."""
    from tests.train.conftest import captured_dataset

    return captured_dataset(tmp_path_factory)

"""The sdk tests' tiny scene: the shared one plus a skinned mesh, so its character can be posed."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import write_tiny_scene

SKINNED_MESH = """
        def Mesh "Body" (prepend apiSchemas = ["SkelBindingAPI"])
        {
            int[] faceVertexCounts = [3]
            int[] faceVertexIndices = [0, 1, 2]
            point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
            int[] primvars:skel:jointIndices = [0, 1, 2] (
                elementSize = 1
                interpolation = "vertex"
            )
            float[] primvars:skel:jointWeights = [1, 1, 1] (
                elementSize = 1
                interpolation = "vertex"
            )
            rel skel:skeleton = </World/Asset/Skel>
        }
"""
SKEL_ROOT = '    def SkelRoot "Asset"\n    {\n'


def with_skinned_mesh(path: Path) -> Path:
    """The scene at `path` with a one-triangle mesh skinned to its skeleton (under the SkelRoot)."""
    text = path.read_text()
    assert SKEL_ROOT in text
    path.write_text(text.replace(SKEL_ROOT, SKEL_ROOT + SKINNED_MESH, 1))
    return path


@pytest.fixture
def tiny_scene(tmp_path: Path):
    """Factory: the shared tiny scene (tests/conftest.py) with a skinned mesh, in tmp_path."""

    def make(**kwargs) -> Path:
        return with_skinned_mesh(write_tiny_scene(tmp_path, **kwargs))

    return make

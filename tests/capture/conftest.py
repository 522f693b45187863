"""Shared capture fixtures: a small CesiumMan capture and scene variants in a test's tmp_path."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from rigspace.capture import dataset as ds
from rigspace.capture.pipeline import CaptureResult, capture
from rigspace.capture.settings import CaptureOverrides
from tests.conftest import REPO

SCENE = REPO / "samples" / "scenes" / "cesium_man.usda"
CHARACTER = "/World/CesiumMan"
SMALL = CaptureOverrides(
    views=4, elevations=(0.0,), resolution=32, frames=(1.0, 6.0), frames_per_item=3
)
ROTATION_TOLERANCE = 1e-4  # float32 parameters of float64 transforms
IMAGE_TOLERANCE = 0.02  # mean abs albedo difference between views of a rotated character
RELATIVE_ASSET = re.compile(r"@(\.\.?/[^@]+)@")
"""An asset path relative to the scene's folder (`@../assets/...@`)."""


def small_capture(out: Path, **kwargs) -> CaptureResult:
    kwargs.setdefault("workers", 1)
    kwargs.setdefault("progress", False)
    kwargs.setdefault("warn", lambda text: None)  # kept in the result's warnings
    return capture(SCENE, CHARACTER, out, kwargs.pop("overrides", SMALL), **kwargs)


@pytest.fixture(scope="session")
def dataset(tmp_path_factory) -> CaptureResult:
    """The SMALL capture of CesiumMan: 6 frames x (4 views + 4 held-out), 32^2."""
    return small_capture(tmp_path_factory.mktemp("capture") / "ds")


def checksum(folder: Path) -> str:
    return json.loads((folder / ds.MANIFEST_FILE).read_text())["checksum"]


def with_character_ops(text: str, *ops: str) -> str:
    """The scene text with xformOp lines (and their order) added to the character prim."""
    names = ", ".join(f'"{op.split(" = ")[0].split()[-1]}"' for op in ops)
    lines = "".join(f"        {op}\n" for op in ops)
    return text.replace(
        "        rel rigspace:skeleton",
        f"{lines}        uniform token[] xformOpOrder = [{names}]\n        rel rigspace:skeleton",
    )


def scene_variant(folder: Path, name: str, text: str) -> Path:
    """A variant of the CesiumMan scene written into `folder` (a test's tmp_path, never the
    source tree), its relative asset paths made absolute so that they still resolve."""
    absolute = RELATIVE_ASSET.sub(lambda m: f"@{(SCENE.parent / m[1]).resolve()}@", text)
    assert absolute != text, "the scene's relative asset paths changed: update RELATIVE_ASSET"
    scene = folder / "scenes" / f"{name}.usda"
    scene.parent.mkdir(exist_ok=True)
    scene.write_text(absolute)
    return scene


def capture_variant(tmp_path: Path, name: str, text: str, **kwargs) -> CaptureResult:
    """Capture (SMALL) a variant of the CesiumMan scene."""
    kwargs.setdefault("workers", 1)
    kwargs.setdefault("progress", False)
    kwargs.setdefault("warn", lambda text: None)
    scene = scene_variant(tmp_path, name, text)
    return capture(scene, CHARACTER, tmp_path / name, SMALL, **kwargs)

"""Runtime test helpers: an engine of the previs scene, a test camera, a character seen from a
camera, and its layer made by the steps the Engine runs for it."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
from pxr import Gf, Usd, UsdGeom

from rigspace.runtime.billboard import Billboard
from rigspace.runtime.character import Layer, NeuralCharacter
from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.sdk.camera import Camera
from tests.conftest import REPO

PREVIS = REPO / "samples" / "scenes" / "previs.usda"


@contextlib.contextmanager
def previs_engine(width: int = 320, height: int = 180, **settings) -> Iterator[Engine]:
    """An Engine of the previs scene at `width` x `height` (int8 graphs, one sample per pixel
    for the prims, and `settings`), closed after the block."""
    engine = Engine(
        PREVIS,
        EngineSettings(width=width, height=height, precision="int8", prim_samples=1, **settings),
    )
    try:
        yield engine
    finally:
        engine.close()


def define_camera(
    stage: Usd.Stage, path: str, focal_length: float, eye, tilt: float
) -> UsdGeom.Camera:
    """A 16:9 camera at `path` (a 20.955 x 11.787 mm gate, clipping 10-10000) at `eye`,
    tilted `tilt` degrees about X."""
    camera = UsdGeom.Camera.Define(stage, path)
    camera.CreateFocalLengthAttr(focal_length)
    camera.CreateHorizontalApertureAttr(20.955)
    camera.CreateVerticalApertureAttr(11.787)
    camera.CreateClippingRangeAttr(Gf.Vec2f(10, 10000))
    camera.AddTranslateOp().Set(Gf.Vec3d(*map(float, eye)))
    camera.AddRotateXOp().Set(tilt)
    return camera


class CharacterView(NamedTuple):
    """A character posed at a time and seen by a camera that looks at its look-at joint."""

    world: np.ndarray
    """The joints' world transforms."""
    joint: np.ndarray
    """The look-at joint's world position."""
    camera: Camera
    billboard: Billboard


def view_character(
    character: NeuralCharacter, time: float, offset, width: int, height: int, **lens
) -> CharacterView:
    """`character` posed at `time`, seen by a 35 mm camera (20.955 mm aperture, `width` x
    `height` pixels, `lens`: Camera.look_at's near and far) at its look-at joint + `offset`,
    looking at the joint."""
    world = character.pose(time)
    joint = world[character.look_at][:3, 3]
    camera = Camera.look_at(joint + np.asarray(offset), joint, width=width, height=height,
                            focal_length=35, horizontal_aperture=20.955, **lens)  # fmt: skip
    return CharacterView(world, joint, camera, character.place(world, camera))


def evaluate_layer(
    character: NeuralCharacter,
    world: np.ndarray,
    billboard: Billboard,
    camera: Camera,
    branches: tuple[str, ...],
    level: int | None = None,
    weights: np.ndarray | None = None,
) -> Layer:
    """The character's maps in the frame, for a visible billboard, as Engine.render makes them
    (_evaluate_stage, _evaluate): the level covering the billboard (or `level`), the rig
    parameters, one network call, the maps resampled into the frame."""
    level = level or character.model.level_for(billboard.size_px)
    rig = character.parameters(world, billboard, camera, weights)
    out = character.model.predict(rig, level, branches)
    return character.resample(out, billboard, camera, level, branches)

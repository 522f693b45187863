"""Runtime test helpers: a character's layer made by the steps the Engine runs for it."""

from __future__ import annotations

import numpy as np

from rigspace.runtime.billboard import Billboard
from rigspace.runtime.character import Layer, NeuralCharacter
from rigspace.sdk.camera import Camera


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

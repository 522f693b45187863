"""Stage helpers: open a scene with errors a user can act on, and read its unit conventions."""

from __future__ import annotations

import re
from pathlib import Path

from pxr import Sdf, Tf, Usd, UsdGeom

from rigspace.sdk.errors import SceneError

SCENE_SUFFIXES = (".usda", ".usdc", ".usd", ".usdz")


def open_stage(path: str | Path) -> Usd.Stage:
    """Open a .usda/.usdc/.usd/.usdz stage with every payload loaded, or raise SceneError."""
    path = Path(path)
    if not path.exists():
        raise SceneError(f"Scene {path} does not exist.", "check the path.")
    if path.is_dir():
        raise SceneError(f"Scene {path} is a folder, not a USD file.", "name a .usd* file.")
    if path.suffix.lower() not in SCENE_SUFFIXES:
        raise SceneError(
            f"Scene {path} is not a USD file (suffix {path.suffix or 'none'}).",
            f"name a file ending in one of {', '.join(SCENE_SUFFIXES)}.",
        )
    try:
        layer = Sdf.Layer.FindOrOpen(str(path))
    except Tf.ErrorException as exc:
        raise SceneError(
            f"Scene {path} could not be read: {_first_line(exc)}",
            "fix the syntax error it names (or re-export the file).",
        ) from exc
    if layer is None:
        raise SceneError(f"Scene {path} could not be read as USD.", "re-export the file.")
    try:
        return Usd.Stage.Open(layer, load=Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise SceneError(f"Scene {path} could not be opened: {_first_line(exc)}") from exc


def _first_line(exc: Exception) -> str:
    """The message of a Tf error without its C++ location ("Error in '...' at line N ...")."""
    text = " ".join(str(exc).split())
    match = re.search(r"in file \S+ : (.*)$", text)
    message = match.group(1) if match else text
    return message.strip(" '\"") or type(exc).__name__


def up_axis(stage: Usd.Stage) -> str:
    return str(UsdGeom.GetStageUpAxis(stage))


def meters_per_unit(stage: Usd.Stage) -> float:
    return float(UsdGeom.GetStageMetersPerUnit(stage))

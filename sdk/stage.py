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


STAGE_METADATA = (
    "timeCodesPerSecond",
    "framesPerSecond",
    "startTimeCode",
    "endTimeCode",
    "upAxis",
    "metersPerUnit",
)
"""Root-layer metadata a stage reads from its root layer only: an overlay must repeat them."""


def overlay_layer(path: str | Path, scene: str | Path) -> Sdf.Layer:
    """A new layer at `path` whose only sublayer is `scene`, with the scene's stage metadata.

    USD reads time codes per second, frames per second, the time range, the up axis and
    metersPerUnit from the root layer alone, and rescales a sublayer whose time codes per
    second differ from the root's; an overlay without them would shift the scene's times
    and change its units.
    """
    source = Sdf.Layer.FindOrOpen(str(scene))
    if source is None:
        raise SceneError(f"Scene {scene} could not be read as USD.", "check the path.")
    layer = Sdf.Layer.Find(str(path))  # still open from an earlier overlay: start it over
    if layer is not None:
        layer.Clear()
    else:
        layer = Sdf.Layer.CreateNew(str(path))
    layer.subLayerPaths.append(str(Path(scene).resolve()))
    for key in STAGE_METADATA:
        if source.pseudoRoot.HasInfo(key):
            layer.pseudoRoot.SetInfo(key, source.pseudoRoot.GetInfo(key))
    return layer


def might_vary(prim: Usd.Prim) -> bool:
    """Whether any attribute of `prim` or of its ancestors may change with time.

    USD's ValueMightBeTimeVarying: true for more than one time sample (or value clips),
    so a prim for which this is false looks the same at every time code (until the stage
    is edited).
    """
    while prim and not prim.IsPseudoRoot():
        xformable = UsdGeom.Xformable(prim)
        if xformable and xformable.TransformMightBeTimeVarying():
            return True
        for attr in prim.GetAttributes():
            # The transform is decided above from the ops in xformOpOrder: an op left out of
            # the order (a stronger layer replacing an animated one) changes nothing.
            if xformable and attr.GetName().startswith("xformOp"):
                continue
            if attr.ValueMightBeTimeVarying():
                return True
        prim = prim.GetParent()
    return False

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
        raise _unreadable(path, _first_line(exc)) from exc
    if layer is None:
        raise _unreadable(path, "")
    try:
        return Usd.Stage.Open(layer, load=Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise SceneError(
            f"Scene {path} could not be opened: USD reports: {_sentence(_first_line(exc))}",
            "fix what USD names (a missing sublayer or reference, or a syntax error in it).",
        ) from exc


def unreadable_layers(stage: Usd.Stage) -> list[tuple[str, str]]:
    """(asset path as authored, why) for each layer the stage's layers name (sublayers,
    references, payloads, recursively) that USD cannot read: missing, empty, truncated or
    not USD. USD composes around such a layer and says nothing through Python; a character
    under it then looks like one whose skeleton does not exist."""
    bad: list[tuple[str, str]] = []
    seen: set[str] = set()
    todo = [stage.GetRootLayer()]
    while todo:
        layer = todo.pop()
        for asset in layer.GetCompositionAssetDependencies():
            if not asset:  # an internal reference (</Prim>): no layer of its own
                continue
            path = layer.ComputeAbsolutePath(asset)
            if path in seen:
                continue
            seen.add(path)
            try:
                found = Sdf.Layer.FindOrOpen(path)
            except Tf.ErrorException as exc:
                bad.append((asset, _usd_reason(_first_line(exc))))
                continue
            if found is None:
                local = Path(path)
                why = "it does not exist." if not local.exists() else "USD cannot read it."
                bad.append((asset, why))
                continue
            todo.append(found)
    return bad


def _usd_reason(text: str) -> str:
    """USD's error as a sentence: its parser's grammar rule dropped, file and line kept."""
    text = re.sub(r"^Error in '.*?' at line \d+ in file \S+ : ", "", text).strip(" '")
    parse = re.search(r"(\S+):(\d+):(\d+): parse error", text)
    if parse:
        return (
            f"a syntax error at line {parse[2]}, column {parse[3]} (truncated, or edited by hand)."
        )
    return _sentence(text)


USDA_HEADER = b"#usda "
USDC_HEADER = b"PXR-USDC"
ZIP_HEADER = b"PK\x03\x04"


def _sentence(text: str) -> str:
    text = text.strip()
    return text if text.endswith((".", "!", "?")) else text + "."


def _unreadable(path: Path, usd_error: str) -> SceneError:
    """Why USD could not read `path`, from its error and the file's first bytes, with a fix."""
    with path.open("rb") as file:
        head = file.read(16)
    said = f" USD reports: {_sentence(usd_error)}" if usd_error else ""
    if head.startswith(USDA_HEADER):
        return SceneError(
            f"Scene {path} is a USD text file that USD could not parse.{said}",
            "fix the syntax error at the line and column USD names, or re-export the file.",
        )
    if not head.strip():
        what = "is empty"
    elif head.startswith(USDC_HEADER):
        what = "is a USD crate (binary) file that is damaged or truncated"
    elif head.startswith(ZIP_HEADER):
        what = "is a zip archive but not a USD package USD can read"
    else:
        what = (
            "is not USD: it does not start with the `#usda 1.0` header of a USD text file, "
            "nor is it a USD crate or package"
        )
    return SceneError(
        f"Scene {path} {what}.{said}",
        "export the scene to USD (.usda, .usdc or .usdz) from the application that made it, "
        "or pass the right file.",
    )


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
    "defaultPrim",
)
"""Root-layer metadata a stage reads from its root layer only: an overlay must repeat them."""


def overlay_layer(path: str | Path, scene: str | Path) -> Sdf.Layer:
    """A new layer at `path` whose only sublayer is `scene`, with the scene's stage metadata.

    USD reads time codes per second, frames per second, the time range, the up axis,
    metersPerUnit and the default prim from the root layer alone, and rescales a sublayer whose time codes per
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

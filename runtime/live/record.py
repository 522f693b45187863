"""Record a live take: retargeted local transforms per stage time code -> a UsdSkel SkelAnimation."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rigspace.sdk.errors import RigspaceError
from rigspace.usd_schemas import CONTROL_NAMESPACE

if TYPE_CHECKING:  # annotations only: pxr is imported where a take is written or read
    from pxr import Usd


class TakeError(RigspaceError):
    """A take that cannot be recorded or written."""


class TakeRecorder:
    """Collects (time code, (J, 4, 4) local transforms) and writes them as one SkelAnimation.

    Transforms are the row-vector, parent-space matrices UsdSkel uses (what
    `Retargeter.apply` returns); they are decomposed with UsdSkel's own DecomposeTransforms, so
    the written translations, rotations and scales recompose to them. A time code recorded twice
    keeps the later pose. Memory: 128 bytes a joint a frame (22 joints at 30 fps: 5 MB an hour).
    A character's named controls (RigspaceControlAPI) are recorded beside the weights, as
    time-sampled `rigspace:control:NAME:value` attributes of the take's SkelAnimation prim (the
    attribute a character's control reads: copy it onto the character to play the take there).
    """

    def __init__(
        self, joints: Sequence[str], blend_shapes: Sequence[str] = (), controls: Sequence[str] = ()
    ) -> None:
        if not joints:
            raise TakeError("A take needs the skeleton's joints.", "pass Skeleton.joints.")
        self.joints = tuple(joints)
        self.blend_shapes = tuple(blend_shapes)
        """The character's blend shapes: a take of a face records their weights too."""
        self.controls = tuple(controls)
        """The character's named controls: their values follow the weights in `add`."""
        self._scalars = self.blend_shapes + self.controls
        self._frames: dict[float, np.ndarray] = {}
        self._weights: dict[float, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self._frames)

    def add(self, time_code: float, local: np.ndarray, weights: np.ndarray | None = None) -> None:
        """Record the pose at `time_code` (and the blend shape weights, `blend_shapes` order,
        then the controls' values, `controls` order)."""
        local = np.asarray(local, dtype=np.float64)
        if local.shape != (len(self.joints), 4, 4):
            raise TakeError(
                f"A take frame has shape {local.shape}, expected ({len(self.joints)}, 4, 4).",
                "record the skeleton's local transforms (one 4x4 per joint).",
            )
        if self._scalars:  # checked before anything is kept: a refused frame leaves no trace
            w = np.zeros(len(self._scalars)) if weights is None else np.asarray(weights, float)
            if w.shape != (len(self._scalars),) or not np.isfinite(w).all():
                raise TakeError(
                    f"A take frame's blend shape weights and control values have shape "
                    f"{w.shape} or are not finite; expected {len(self._scalars)} finite weights "
                    "(the blend shapes', then the controls').",
                    "record one weight per blend shape, then one value per control "
                    "(CharacterRig.scalar_names order).",
                )
            self._weights[float(time_code)] = w.astype(np.float32)
        self._frames[float(time_code)] = local.copy()

    def write(
        self,
        path: str | Path,
        time_codes_per_second: float,
        meters_per_unit: float = 0.01,
        up_axis: str = "Y",
        prim_path: str = "/Take",
    ) -> Path:
        """Write the take as a new layer whose default prim is the SkelAnimation at `prim_path`
        (time samples at the recorded time codes; the stage's rate and units, so any DCC and
        `skel:animationSource` read it as is)."""
        from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

        if not self._frames:
            raise TakeError(
                "The take is empty: nothing was recorded.", "record at least one frame."
            )
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        stage = Usd.Stage.CreateNew(str(path))
        times = sorted(self._frames)
        stage.SetTimeCodesPerSecond(time_codes_per_second)
        stage.SetFramesPerSecond(time_codes_per_second)
        stage.SetStartTimeCode(times[0])
        stage.SetEndTimeCode(times[-1])
        UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
        anim = UsdSkel.Animation.Define(stage, Sdf.Path(prim_path))
        stage.SetDefaultPrim(anim.GetPrim())
        anim.GetJointsAttr().Set(Vt.TokenArray(list(self.joints)))
        shapes = len(self.blend_shapes)
        if self.blend_shapes:
            anim.CreateBlendShapesAttr(Vt.TokenArray(list(self.blend_shapes)))
            weights = anim.CreateBlendShapeWeightsAttr()
            for t in times:
                weights.Set(Vt.FloatArray.FromNumpy(self._weights[t][:shapes]), t)
        for k, name in enumerate(self.controls):
            value = anim.GetPrim().CreateAttribute(
                f"{CONTROL_NAMESPACE}:{name}:value", Sdf.ValueTypeNames.Float
            )
            for t in times:
                value.Set(float(self._weights[t][shapes + k]), t)
        for t in times:
            translations, rotations, scales = UsdSkel.DecomposeTransforms(
                Vt.Matrix4dArray.FromNumpy(self._frames[t])
            )
            anim.GetTranslationsAttr().Set(translations, t)
            anim.GetRotationsAttr().Set(rotations, t)
            anim.GetScalesAttr().Set(scales, t)
        stage.GetRootLayer().Save()
        return path


@dataclass(frozen=True)
class Take:
    """A recorded take read back for replay: local rotations per time sample."""

    joints: tuple[str, ...]
    """Joint paths as recorded (the skeleton's)."""
    bones: tuple[str, ...]
    """Leaf joint names (the replay source's bone names)."""
    parents: tuple[int, ...]
    rotations: np.ndarray
    """(F, J, 4) unit quaternions (w, x, y, z)."""
    root_positions: np.ndarray
    """(F, 3) the first root joint's translation, in the take's units."""
    times: np.ndarray
    """(F,) seconds from the take's first sample."""
    meters_per_unit: float
    blend_shapes: tuple[str, ...] = ()
    """The names a replay sends weights for: the take's blend shapes, then its controls."""
    blend_weights: np.ndarray | None = None
    """(F, S) the blend shape weights, then the controls' values, at each rotation sample
    (None: the take has none)."""


def read_take(path: str | Path) -> Take:
    """Read a take written by TakeRecorder (any layer whose default prim is a SkelAnimation),
    checked the way the JSON files are (rigspace.sdk.fields): a damaged or hand-edited take (an
    unreadable layer, a wrong attribute type, a sample with too few rotations, a zero or NaN
    quaternion, a broken joint hierarchy) is one TakeError naming the attribute and time code,
    never a traceback or a NaN pose in the replay."""
    from pxr import Sdf, UsdGeom, UsdSkel

    path = Path(path)
    stage, prim = _open_take(path)
    anim = UsdSkel.Animation(prim)
    names = Sdf.ValueTypeNames
    joints_attr, rotations_attr, translations_attr = (
        anim.GetJointsAttr(), anim.GetRotationsAttr(), anim.GetTranslationsAttr()
    )  # fmt: skip
    _check_type(path, joints_attr, (names.TokenArray,))
    _check_type(path, rotations_attr, (names.QuatfArray, names.QuatdArray, names.QuathArray))
    _check_type(path, translations_attr, (names.Float3Array, names.Double3Array, names.Half3Array))
    joints = tuple(str(j) for j in joints_attr.Get() or ())
    times = rotations_attr.GetTimeSamples()
    if not joints or not times:
        raise TakeError(f"Take {path} has no joints or no rotation time samples.", RECORD_AGAIN)
    parents = _joint_parents(path, joints)
    rotations, roots = _pose_samples(
        path, rotations_attr, translations_attr, times, joints, parents.index(-1)
    )
    shapes, weights = _blend_channels(path, anim, times)
    controls, values = _control_channels(path, anim.GetPrim(), times)
    if controls:
        shapes = shapes + controls
        weights = values if weights is None else np.concatenate([weights, values], axis=1)
    tcps = stage.GetTimeCodesPerSecond()
    return Take(
        joints,
        tuple(j.rsplit("/", 1)[-1] for j in joints),
        parents,
        rotations,
        roots,
        (np.array(times) - times[0]) / tcps,
        UsdGeom.GetStageMetersPerUnit(stage),
        shapes,
        weights,
    )


def _open_take(path: Path) -> tuple[Usd.Stage, Usd.Prim]:
    """The take's stage and its default prim, a SkelAnimation (else a TakeError)."""
    from pxr import UsdSkel

    from rigspace.sdk.stage import SceneError, open_stage

    if not path.is_file():
        raise TakeError(f"Take {path} does not exist.", "check the path.")
    try:
        stage = open_stage(path)
    except SceneError as exc:  # its sentence names the file as a scene: here it is a take
        raise TakeError(exc.what.replace("Scene ", "Take ", 1), RECORD_AGAIN) from None
    prim = stage.GetDefaultPrim()
    if not prim or not prim.IsA(UsdSkel.Animation):
        raise TakeError(
            f"{path} is not a recorded take: its default prim must be a SkelAnimation.",
            "replay a take written by TakeRecorder (rigspace live --record).",
        )
    return stage, prim


def _joint_parents(path: Path, joints: tuple[str, ...]) -> tuple[int, ...]:
    """Each joint's parent index (-1: a root), once the joints are a UsdSkel hierarchy (else
    a TakeError)."""
    from pxr import UsdSkel

    ok, reason = UsdSkel.Topology(joints).Validate()
    if not ok or len(set(joints)) != len(joints):
        raise TakeError(
            f"Take {path}: its joints are not a skeleton hierarchy "
            f"({reason or 'a joint is listed twice'}).",
            RECORD_AGAIN,
        )
    index = {j: i for i, j in enumerate(joints)}
    return tuple(index.get(j.rsplit("/", 1)[0], -1) if "/" in j else -1 for j in joints)


def _pose_samples(
    path: Path, rotations_attr, translations_attr, times, joints: tuple[str, ...], root: int
) -> tuple[np.ndarray, np.ndarray]:
    """(F, J, 4) unit quaternions (w, x, y, z) and (F, 3) root translations at each rotation
    sample (zeros where no translation is authored), checked (a zero quaternion, a short or
    non-finite sample: a TakeError)."""
    moves = translations_attr.GetTimeSamples()
    rotations = np.empty((len(times), len(joints), 4))
    roots = np.zeros((len(times), 3))
    for k, t in enumerate(times):
        q = _sample(path, rotations_attr, t, len(joints), 4)
        norms = np.linalg.norm(q, axis=1)
        if not np.all(norms > 1e-6):
            bad = joints[int(np.argmin(norms))]
            raise TakeError(
                f"Take {path}: 'rotations' at time code {t:g} has a zero quaternion (joint {bad}).",
                RECORD_AGAIN,
            )
        rotations[k, :, 0], rotations[k, :, 1:] = q[:, 3], q[:, :3]  # Gf: (i, j, k, real)
        if moves or translations_attr.HasAuthoredValue():
            roots[k] = _sample(path, translations_attr, t, len(joints), 3)[root]
    rotations /= np.linalg.norm(rotations, axis=2, keepdims=True)
    return rotations, roots


def _blend_channels(path: Path, anim, times) -> tuple[tuple[str, ...], np.ndarray | None]:
    """A take's blendShapes and its blendShapeWeights at each rotation sample (held between
    samples, as UsdSkel interpolates them), checked like the rotations."""
    from pxr import Sdf

    names_attr, weights_attr = anim.GetBlendShapesAttr(), anim.GetBlendShapeWeightsAttr()
    _check_type(path, names_attr, (Sdf.ValueTypeNames.TokenArray,))
    _check_type(path, weights_attr, (Sdf.ValueTypeNames.FloatArray,))
    shapes = tuple(str(n) for n in names_attr.Get() or ())
    if not shapes or not (weights_attr.GetTimeSamples() or weights_attr.HasAuthoredValue()):
        return (), None
    weights = np.array([_sample(path, weights_attr, t, len(shapes), 1)[:, 0] for t in times])
    return shapes, weights


def _control_channels(path: Path, prim, times) -> tuple[tuple[str, ...], np.ndarray]:
    """A take's controls (its rigspace:control:NAME:value attributes) and their values at
    each rotation sample, checked like the rotations."""
    from pxr import Sdf

    names, columns = [], []
    prefix, suffix = CONTROL_NAMESPACE + ":", ":value"
    for attr in prim.GetAttributes():
        name = attr.GetName()
        if not (name.startswith(prefix) and name.endswith(suffix)):
            continue
        _check_type(path, attr, (Sdf.ValueTypeNames.Float, Sdf.ValueTypeNames.Double))
        names.append(name[len(prefix) : -len(suffix)])
        columns.append([_number(path, attr, t) for t in times])
    return tuple(names), np.array(columns, dtype=np.float64).T.reshape(len(times), len(names))


def _number(path: Path, attr, t: float) -> float:
    """A scalar attribute's value at time code `t`, finite, or a TakeError."""
    value = attr.Get(t)
    if value is None or not np.isfinite(float(value)):
        raise TakeError(
            f"Take {path}: '{attr.GetName()}' at time code {t:g} is missing or not finite "
            "(NaN or inf).",
            RECORD_AGAIN,
        )
    return float(value)


RECORD_AGAIN = "record the take again (rigspace live --record), or restore the file."


def _check_type(path: Path, attr, allowed: tuple) -> None:
    """Each layer's spec of `attr` has an allowed type (UsdSkel reports the schema's type
    whatever a layer authors, and hands the authored values back as they are)."""
    for spec in attr.GetPropertyStack():
        kind = spec.typeName
        if kind not in allowed:
            raise TakeError(
                f"Take {path}: '{attr.GetName()}' is authored as {kind}, not "
                f"{' or '.join(str(a) for a in allowed)}.",
                RECORD_AGAIN,
            )


def _sample(path: Path, attr, t: float, count: int, width: int) -> np.ndarray:
    """`attr` at time code `t` as a (count, width) finite float array, or a TakeError."""
    value = attr.Get(t)
    array = np.array(value, dtype=np.float64) if value is not None else np.empty((0, width))
    array = array.reshape(len(array), -1) if array.ndim == 1 else array
    if array.shape != (count, width):
        what = "joints" if width > 1 else "blend shapes"
        raise TakeError(
            f"Take {path}: '{attr.GetName()}' at time code {t:g} has {len(array)} values for "
            f"{count} {what}.",
            RECORD_AGAIN,
        )
    if not np.isfinite(array).all():
        raise TakeError(
            f"Take {path}: '{attr.GetName()}' at time code {t:g} is not finite (NaN or inf).",
            RECORD_AGAIN,
        )
    return array

"""One live binding at run time: its source, buffer and retargeter, from RigspaceLiveBindingAPI."""

from __future__ import annotations

import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl, quote

import numpy as np

from rigspace.runtime.live.buffer import (
    CONNECTED,
    LOST,
    STALE,
    WAITING,
    BindingCounters,
    BufferSettings,
    LiveBuffer,
    LivePose,
)
from rigspace.runtime.live.retarget import (
    PRESETS,
    Y_180,
    Preset,
    Retargeter,
    RetargetError,
    blend_transforms,
    fade_transforms,
    source_basis,
    source_hierarchy,
    target_skeleton,
)
from rigspace.runtime.live.source_frame import quat_angle
from rigspace.runtime.live.sources import open_source
from rigspace.runtime.live.transports import LiveSourceError, Source
from rigspace.sdk.rotations import quat_from_matrix

DEFAULT_PRESET = {"vmc": "unity", "replay": "cmu", "bvh+tcp": "cmu"}
"""The bone-name preset a scheme gets for bonePreset = auto when the binding authors no
sourceBones (and the source's bones match the preset's)."""
BONE_PRESETS = {"unityHumanoid": "unity", "cmu": "cmu", "mixamo": "mixamo"}
"""bonePreset token -> retarget.PRESETS name ("auto": DEFAULT_PRESET, "none": same names)."""
TURN_RATE = 240.0
"""Degrees per second a joint turns at most in a connect, reconnect or loss transition (8 a
tick at 30 fps): a fade that would turn a joint faster lasts longer than the blend seconds."""
CLIP_FADE_SECONDS = 0.25
"""A clip blend moves at most this fast from 0 to 1 (a button press does not pop the pose)."""
WEIGHT_RANGE = (-2.0, 2.0)
"""The range a live blend shape weight is clamped into when the character's capture ring
declares none for its shape (blendShapeRanges): the one `rigspace view`'s sliders allow."""
NATIVE_BASIS = {"vmc": Y_180}
"""Sources whose decoder already converted to right-handed Y up, but whose performer faces
-Z: their basis replaces the binding's sourceUpAxis/sourceHandedness (no double conversion)."""


@dataclass
class LiveBindingRuntime:
    """A started-on-demand binding: `apply(stage_local)` merges its live pose every frame."""

    name: str
    source: Source
    buffer: LiveBuffer
    retargeter: Retargeter
    clip_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Clip name -> (first, last) stage time code, for the source's clip controls (gamepad)."""
    clip_blend: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """The eased blend per clip of the source's clip_names, as of the last frame."""
    _last_now: float | None = None
    _shown: np.ndarray | None = None
    """The (J, 4, 4) transforms this binding gave the last frame (a transition starts there)."""
    _status: str = WAITING
    """The pose's status in the last frame."""
    _fade: tuple[float, float, np.ndarray | None] | None = None
    """(start, seconds, held from-transforms or None: from the stage animation as it plays)
    of the transition in progress."""
    _arcs: np.ndarray | None = None
    """The fade's per-joint turns at the last frame (`fade_transforms`: it turns on the way it
    went)."""
    _blend_cache: tuple[tuple[str, ...], dict[str, list[int]]] | None = None
    """(the character's shapes, source name -> indices of the shapes it drives)."""
    _anchor: np.ndarray | None = None
    """While lost: the root translation where the performer left the character, minus the
    stage's root then; the stage animation plays from there ("in place")."""

    @property
    def fading(self) -> bool:
        """Whether a connect, reconnect or loss transition was in progress at the last frame."""
        return self._fade is not None

    def start(self) -> None:
        self.source.start(self.buffer)

    def stop(self) -> None:
        self.source.stop()

    def pose(self, now: float | None = None) -> LivePose:
        return self.buffer.pose(now)

    def apply(
        self,
        stage_local: np.ndarray,
        now: float | None = None,
        sample: Callable[[float], Any] | None = None,
        time_code: float | None = None,
    ) -> tuple[np.ndarray, LivePose]:
        """The stage's (J, 4, 4) local transforms with this binding's pose at local time `now`
        (LiveBuffer.pose_at) merged in, and the pose (its status and weight belong in the
        frame's report), without the transitions of `apply_frame`. A source with clip controls
        first blends the stage pose towards its clips: `sample(time_code)` gives the stage's
        local transforms at another time code (without it, clips are not blended)."""
        now = time.monotonic() if now is None else now
        pose = self.buffer.pose_at(now)
        if self.clip_ranges and sample is not None and time_code is not None:
            stage_local = self._blend_clips(stage_local, pose, now, sample, time_code)
        return self.retargeter.apply(stage_local, pose), pose

    def apply_frame(
        self,
        stage_local: np.ndarray,
        now: float | None = None,
        sample: Callable[[float], Any] | None = None,
        time_code: float | None = None,
    ) -> tuple[np.ndarray, LivePose]:
        """The pose shown at local time `now`: `apply` with the transitions at a connect,
        reconnect or loss (`_transition`). Frames and take ticks both come here
        (`LiveInput.merged`), so a take records what the screen shows; calls come in time order
        (the binding keeps the transition in progress)."""
        now = time.monotonic() if now is None else now
        out, pose = self.apply(stage_local, now, sample, time_code)
        if self.retargeter.space == "additive":  # controller offsets ease in with their weight
            return out, pose
        return self._transition(out, stage_local, pose, now), pose

    def _transition(
        self, out: np.ndarray, stage_local: np.ndarray, pose: LivePose, now: float
    ) -> np.ndarray:
        """No pops (issue 21). On a connect: a fade from the stage animation (as it plays on)
        to the live pose; on a reconnect after a stale gap, from the held pose. Once lost: a
        fade from the held pose to the stage animation in place, its root offset to where the
        performer left the character. A fade lasts the binding's blend seconds, longer where a
        joint has further to turn than TURN_RATE allows."""
        root = self.retargeter.target_root
        previous, self._status = self._status, pose.status
        if pose.status == LOST and previous != LOST and self._shown is not None:
            self._anchor = self._shown[root, 3, :3] - stage_local[root, 3, :3]
        in_place = stage_local.copy()  # the stage animation, from where the performer left
        if self._anchor is not None and self.retargeter.root_motion:
            in_place[root, 3, :3] += self._anchor
        if pose.status == LOST:
            out = in_place
        if pose.status != previous and pose.status in (CONNECTED, LOST):
            # From what the screen shows: the held pose after a gap, or the blend of a fade cut
            # short (a reconnect while the loss blended back started from the stage animation:
            # a 60-70 deg pop); else (a first connect, or a reconnect once the loss's fade was
            # over) from the stage animation as it plays on.
            held = previous == STALE or pose.status == LOST or self._fade is not None
            frozen = self._shown.copy() if held and self._shown is not None else None
            turn = float(_turn_degrees(in_place if frozen is None else frozen, out).max())
            self._fade = (now, max(self.buffer.settings.blend, turn / TURN_RATE), frozen)
            self._arcs = None
        if self._fade is not None:
            start, seconds, frozen = self._fade
            u = (now - start) / seconds if seconds > 0 else 1.0
            if pose.status == STALE and self._shown is not None:
                out = self._shown  # a gap in a fade: hold what was shown, the fade's blend
            elif u >= 1.0 or pose.status not in (CONNECTED, LOST):
                self._fade = None
                if pose.status == CONNECTED:
                    self._anchor = None
            else:
                start_pose = in_place if frozen is None else frozen
                out, self._arcs = fade_transforms(start_pose, out, max(u, 0.0), self._arcs)
        self._shown = out
        return out

    def _blend_clips(
        self,
        stage_local: np.ndarray,
        pose: LivePose,
        now: float,
        sample: Callable[[float], Any],
        time_code: float,
    ) -> np.ndarray:
        """The stage pose blended towards each clip by its control (eased, times the binding's
        weight: a lost controller lets go); each clip loops on the stage's time code."""
        decoder = getattr(self.source, "decoder", None)
        names = getattr(decoder, "clip_names", ())
        target = np.asarray(getattr(decoder, "clip_weights", np.zeros(len(names)))) * pose.weight
        if len(self.clip_blend) != len(names):
            self.clip_blend = np.zeros(len(names))
        step = 0.0 if self._last_now is None else max(0.0, now - self._last_now) / CLIP_FADE_SECONDS
        self._last_now = now
        self.clip_blend = self.clip_blend + np.clip(target - self.clip_blend, -step, step)
        out = stage_local
        for clip, weight in zip(names, self.clip_blend, strict=True):
            if weight <= 0:
                continue
            first, last = self.clip_ranges[clip]
            length = last - first
            at = first + (time_code - first) % length if length > 0 else first
            out = blend_transforms(out, np.asarray(sample(at), dtype=np.float64), float(weight))
        return out

    def blend_weights(
        self, pose: LivePose, shapes: tuple[str, ...]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(indices into `shapes`, weights) of the pose's blend shape weights that name one of
        the character's shapes (`blend_targets`); empty when the source sent none that do."""
        if not pose.weights or not shapes:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32)
        if self._blend_cache is None or self._blend_cache[0] != shapes:
            self._blend_cache = (shapes, {})
        cache = self._blend_cache[1]
        sums: dict[int, list[float]] = {}
        for name, value in pose.weights.items():
            if name not in cache:
                cache[name] = blend_targets(name, shapes)
            for index in cache[name]:
                sums.setdefault(index, []).append(value)
        indices = np.array(sorted(sums), dtype=np.int64)
        values = np.array([np.mean(sums[i]) for i in indices], dtype=np.float32)
        return indices, values

    def counters(self, now: float | None = None) -> BindingCounters:
        return self.source.counters(now)

    def rest_pose_attributes(self) -> tuple[list[str], np.ndarray]:
        """(sourceBones, restPose) to author after calibration: the mapped bones and their rest
        rotations (w, x, y, z), parallel."""
        r = self.retargeter
        bones = [r.source_bones[i] for i in r.map_source]
        return bones, r.rest_pose[r.map_source]


VRM_TO_ARKIT: dict[str, tuple[str, ...]] = {
    "a": ("jawOpen",),
    "i": ("mouthStretchLeft", "mouthStretchRight"),
    "u": ("mouthPucker",),
    "e": ("mouthShrugLower",),
    "o": ("mouthFunnel",),
    "blink": ("eyeBlinkLeft", "eyeBlinkRight"),
    "blinkl": ("eyeBlinkLeft",),
    "blinkr": ("eyeBlinkRight",),
    "joy": ("mouthSmileLeft", "mouthSmileRight"),
    "fun": ("mouthSmileLeft", "mouthSmileRight", "cheekSquintLeft", "cheekSquintRight"),
    "angry": ("browDownLeft", "browDownRight"),
    "sorrow": ("browInnerUp", "mouthFrownLeft", "mouthFrownRight"),
    "lookup": ("eyeLookUpLeft", "eyeLookUpRight"),
    "lookdown": ("eyeLookDownLeft", "eyeLookDownRight"),
}
"""VRM 0.x preset expressions (what VMC senders send without Perfect Sync) -> the ARKit-style
names a face rig usually carries (Perfect Sync senders send the ARKit names themselves)."""


def _plain(name: str) -> str:
    """A blend shape name compared loosely: lower case, letters and digits only (JawOpen,
    jaw_open and jawOpen are one name; a namespace before ':' or '.' is dropped)."""
    name = re.split(r"[:.]", name)[-1]
    return re.sub(r"[^a-z0-9]", "", name.lower())


def blend_targets(name: str, shapes: tuple[str, ...]) -> list[int]:
    """Which of the character's blend shapes a source's weight named `name` drives: the shape
    of that name (exactly, else compared loosely: `_plain`); else a VRM preset's ARKit shapes
    (`VRM_TO_ARKIT`: "Blink" drives eyeBlinkLeft and eyeBlinkRight); else, for an ARKit sided
    name (eyeBlinkLeft), the character's unsided shape (eyeBlink), which then takes the mean
    of both sides. [] when none (the weight is ignored)."""
    if name in shapes:
        return [shapes.index(name)]
    plain = {_plain(s): k for k, s in enumerate(shapes)}
    key = _plain(name)
    if key in plain:
        return [plain[key]]
    preset = [plain[_plain(n)] for n in VRM_TO_ARKIT.get(key, ()) if _plain(n) in plain]
    if preset:
        return preset
    for side in ("left", "right", "l", "r"):
        if key.endswith(side) and key[: -len(side)] in plain:
            return [plain[key[: -len(side)]]]
    return []


def open_binding(
    binding: Any,
    skeleton_prim: Any,
    stage_meters_per_unit: float,
    preset: str | None = None,
    extra: dict[str, Callable[[], Any]] | None = None,
    clips: dict[str, tuple[float, float]] | None = None,
) -> LiveBindingRuntime:
    """Build (not start) the runtime of an sdk.schema.LiveBinding for a UsdSkel Skeleton.

    - Bone map: the binding's sourceBones -> targetJoints when authored; else `preset` (a
      retarget.PRESETS name) or the binding's bonePreset (auto: the scheme's default preset
      when the source sends its bones); else source bones onto joints of the same name.
    - Gamepad: the binding's gamepadOffsets/gamepadClips become the URL's axes=/clips= where
      the URL has none; `clips` (clip name -> (first, last) time code, the character's capture
      ring) are the clips a control may blend towards.
    - Basis: the source's native one (VMC) or the binding's up axis and handedness.
    - Rest: restPose when authored (parallel to the map's source bones); else the character's
      rest aligned onto the source's (`Retargeter.align_rest`): a BVH's own, or the preset's
      canonical T-pose (VMC); with a preset's map, through the canonical T-posed humanoid, so
      that a BVH and the same clip sent over VMC pose every joint alike.
    - Units: sourceMetersPerUnit, or the preset's when the preset supplies the map and the
      binding leaves the default 1.
    - A recorded take (replay:// of a .usd file) plays back onto its own skeleton exactly: same
      joints, identity basis, the skeleton's rest as its rest pose, the take's units.
    """
    scheme = binding.url.split("://", 1)[0].lower()
    source = open_source(_with_gamepad_map(binding, scheme), binding.name, extra)
    joints, rest = target_skeleton(skeleton_prim)
    native = bool(getattr(source, "native", False))  # a recorded take of this skeleton
    chosen = _chosen_preset(binding, scheme, preset, source, native)
    clip_ranges = _clip_ranges(binding, source, clips or {})
    bone_map, meters_per_unit = _map_bones(binding, source, joints, chosen, native)
    meters_per_unit = _file_units(binding, source, native, meters_per_unit)
    basis = _binding_basis(binding, scheme, native)
    hierarchy = source_hierarchy(source, chosen or PRESETS["unity"])
    retargeter = Retargeter(
        source.bones,
        hierarchy,
        source.space,
        joints,
        rest,
        bone_map,
        basis,
        meters_per_unit / stage_meters_per_unit,
    )
    if native:
        _native_rest(retargeter, source, joints, rest, stage_meters_per_unit, meters_per_unit)
    else:
        _source_rest(retargeter, binding, source, chosen, bone_map)
    return LiveBindingRuntime(
        binding.name,
        source,
        LiveBuffer(source.bones, BufferSettings.from_binding(binding)),
        retargeter,
        clip_ranges,
    )


def _chosen_preset(
    binding: Any, scheme: str, preset: str | None, source: Source, native: bool
) -> Preset | None:
    """The bone-name preset in play: `preset`, the binding's bonePreset, or for "auto" the
    scheme's default; an explicit one that names none of the source's bones is an error."""
    explicit = preset or BONE_PRESETS.get(binding.bone_preset)
    if explicit is None and binding.bone_preset == "auto":
        chosen = PRESETS.get(DEFAULT_PRESET.get(scheme, ""))
    else:
        chosen = PRESETS.get(explicit or "")  # "none": no preset, same-name joints
    if chosen is not None and explicit and not (binding.source_bones or native):
        if not set(chosen.bone_map) & set(source.bones):
            raise RetargetError(
                f"Live binding {binding.name!r}: bonePreset {binding.bone_preset!r} names none "
                f"of the bones {binding.url} sends ({', '.join(source.bones[:6])}, ...).",
                f'author rigspace:live:{binding.name}:bonePreset = "auto" or the source\'s '
                "family, or author sourceBones/targetJoints.",
            )
    return chosen


def _map_bones(
    binding: Any, source: Source, joints: tuple[str, ...], chosen: Preset | None, native: bool
) -> tuple[dict[str, str], float]:
    """(source bone -> target joint, the source's meters per unit): the binding's authored map,
    a take's same joints, the preset's map (with its units), or the bones of the joints' names."""
    meters_per_unit = binding.source_meters_per_unit
    if native:
        meters_per_unit = getattr(source, "meters_per_unit", None) or meters_per_unit
    if binding.source_bones:
        bone_map = dict(zip(binding.source_bones, binding.target_joints, strict=True))
    elif native:
        leaves = {j.rsplit("/", 1)[-1] for j in joints}
        bone_map = {b: b for b in source.bones if b in leaves}
    elif chosen is not None and set(chosen.bone_map) & set(source.bones):
        bone_map = chosen.bone_map
        if meters_per_unit == 1.0:
            meters_per_unit = chosen.meters_per_unit
    else:
        names = {j.rsplit("/", 1)[-1] for j in joints} | set(joints)
        bone_map = {b: b for b in source.bones if b in names}
    return bone_map, meters_per_unit


def _file_units(binding: Any, source: Source, native: bool, meters_per_unit: float) -> float:
    """The source's meters per unit: a BVH's guessed from its rest pose (and said) when the
    binding leaves sourceMetersPerUnit at 1, else `meters_per_unit`."""
    own = None if native else _own_skeleton(source)
    if binding.source_meters_per_unit == 1.0 and own is not None:
        # A BVH's units are its file's (sourceMetersPerUnit unauthored): the rest pose's height
        # says which (a CMU conversion, centimetres, inches, metres), whatever its bone names.
        meters_per_unit, note, sure = guess_units(own)
        fix = "" if sure else f"; if wrong, author rigspace:live:{binding.name}:sourceMetersPerUnit"
        print(f"rigspace live: {binding.name}: {note}{fix}", file=sys.stderr)
    return meters_per_unit


def _binding_basis(binding: Any, scheme: str, native: bool) -> np.ndarray:
    """The source's basis: identity for a recorded take of this skeleton, the scheme's native
    one (VMC), else the binding's sourceUpAxis and sourceHandedness."""
    basis = np.eye(3) if native else NATIVE_BASIS.get(scheme)
    if basis is None:
        basis = source_basis(binding.source_up_axis, binding.source_handedness)
    return basis


def _source_rest(
    retargeter: Retargeter,
    binding: Any,
    source: Source,
    chosen: Preset | None,
    bone_map: dict[str, str],
) -> None:
    """Calibrate a live source's retargeter: the character's rest aligned onto the source's
    when restPose is not authored and the source's rest is known, else to restPose."""
    if not binding.rest_pose and (positions := _rest_positions(source, chosen)) is not None:
        # The source's rest (this CMU conversion: arms hanging; VMC: a T-pose) is not the
        # character's (an A-pose): turn the character's rest onto the source's.
        # Through the canonical humanoid when the preset's map is the one in use (issue 21).
        through = chosen if chosen is not None and bone_map is chosen.bone_map else None
        retargeter.align_rest(positions, through)
    elif binding.rest_pose:
        _authored_rest(retargeter, source, bone_map, binding.rest_pose)


def _native_rest(
    retargeter: Retargeter,
    source: Source,
    joints: tuple[str, ...],
    rest: np.ndarray,
    stage_meters_per_unit: float,
    meters_per_unit: float,
) -> None:
    """Calibrate a recorded take's retargeter to its own skeleton's rest, root included."""
    # The take's rest is the skeleton's own: then each joint gets the take's rotation back.
    leaf = {j.rsplit("/", 1)[-1]: i for i, j in enumerate(joints)}
    rest_rotations = quat_from_matrix(np.swapaxes(rest[:, :3, :3], 1, 2))
    full = np.tile([1.0, 0.0, 0.0, 0.0], (len(source.bones), 1))
    for k, bone in enumerate(source.bones):
        if bone in leaf:
            full[k] = rest_rotations[leaf[bone]]
    retargeter.calibrate_rotations(full)
    root = retargeter.target_root
    retargeter.rest_root = rest[root, 3, :3] * stage_meters_per_unit / meters_per_unit


def _authored_rest(
    retargeter: Retargeter,
    source: Source,
    bone_map: dict[str, str],
    rest_pose: Sequence[Sequence[float]],
) -> None:
    """Calibrate the retargeter to the binding's restPose (parallel to the map's bones)."""
    full = np.tile([1.0, 0.0, 0.0, 0.0], (len(source.bones), 1))
    index = {b: i for i, b in enumerate(source.bones)}
    for bone, q in zip(bone_map, rest_pose, strict=False):
        if bone in index:
            full[index[bone]] = q
    retargeter.calibrate_rotations(full)


def _turn_degrees(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per joint, the angle (degrees) between two (J, 4, 4) row-vector local transforms."""
    qa = quat_from_matrix(np.swapaxes(a[:, :3, :3], 1, 2))
    qb = quat_from_matrix(np.swapaxes(b[:, :3, :3], 1, 2))
    return np.degrees(quat_angle(qa, qb))


def _with_gamepad_map(binding: Any, scheme: str) -> str:
    """The binding's URL with its gamepadOffsets/Clips/Shapes as axes=/clips=/shapes= options (the
    URL's own options win: `--source pad=gamepad://...?axes=...` overrides the stage)."""
    url = binding.url
    if scheme != "gamepad":
        return url
    query = dict(parse_qsl(url.partition("?")[2]))
    added = [
        f"{key}={quote(','.join(items), safe=':,')}"
        for key, items in (
            ("axes", getattr(binding, "gamepad_offsets", ())),
            ("clips", getattr(binding, "gamepad_clips", ())),
            ("shapes", getattr(binding, "gamepad_shapes", ())),
        )
        if items and key not in query
    ]
    if not added:
        return url
    return url + ("&" if "?" in url else "?") + "&".join(added)


def _clip_ranges(
    binding: Any, source: Source, clips: dict[str, tuple[float, float]]
) -> dict[str, tuple[float, float]]:
    """The ranges of the clips the source's controls blend towards; an unknown clip is an
    error naming the binding and the character's clips."""
    wanted = getattr(getattr(source, "decoder", None), "clip_names", ())
    missing = [c for c in wanted if c not in clips]
    if missing:
        raise LiveSourceError(
            f"Live binding {binding.name!r}: gamepadClips names {', '.join(map(repr, missing))}, "
            f"which the character's capture ring does not (clipNames: "
            f"{', '.join(clips) or 'none'}).",
            "name clips of rigspace:captureRing:clipNames (with their clipRanges).",
        )
    return {c: clips[c] for c in wanted}


UNITS = {
    "metres": 1.0,
    "centimetres": 0.01,
    "millimetres": 0.001,
    "inches": 0.0254,
    "the CMU ASF unit (1/0.45 inch)": 0.0254 / 0.45,
}
"""Length units BVH files come in, meters per unit."""
REST_HEIGHT = 1.45
"""Metres from the lowest to the highest joint of an adult's rest pose (toe to head joint;
the shipped CMU clip: 1.28, CMU's own subjects up to about 1.6)."""
SURE = 1.5
"""A guess is sure when the height it gives is within this factor of REST_HEIGHT."""


def guess_units(rest_positions: np.ndarray) -> tuple[float, str, bool]:
    """(meters per unit, a sentence saying the guess, whether it is sure) for a BVH skeleton's
    rest joint positions: the unit that makes the rest pose's height nearest an adult's."""
    positions = np.asarray(rest_positions, dtype=np.float64)
    height = float(np.ptp(positions, axis=0).max()) if len(positions) else 0.0
    if not height > 0:
        return 1.0, "the BVH rest pose has no extent: its units are taken as metres", False
    name, unit = min(UNITS.items(), key=lambda u: abs(np.log(height * u[1] / REST_HEIGHT)))
    metres = height * unit
    sure = 1 / SURE <= metres / REST_HEIGHT <= SURE
    return unit, f"BVH units: {name} (the rest pose is {metres:.2f} m tall in them)", sure


def _own_skeleton(source: Source) -> np.ndarray | None:
    """The rest joint positions of a source that brings its own skeleton (a BVH stream or
    replay), else None."""
    skeleton = getattr(getattr(source, "decoder", None), "skeleton", None)
    if skeleton is not None:
        return skeleton.rest_positions()
    return getattr(source, "rest_positions", None)


def _rest_positions(source: Source, preset: Preset | None) -> np.ndarray | None:
    """The source's rest joint positions: its own skeleton's (BVH stream and replay), else its
    preset's canonical rest (VMC: a VRM-style T-pose), else None."""
    own = _own_skeleton(source)
    if own is not None:
        return own
    return preset.rest_positions_for(source.bones) if preset is not None else None

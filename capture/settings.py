"""Capture settings: the capture ring API's values, overridden by flags, checked before any work.

`resolve_settings` reads the scene once, applies the overrides, derives what is left to
derive (the ring radius from the character's bounds, the clips from the animation) and
raises a `RigspaceError` naming the problem and the fix for every bad input, before
anything is written. The result is saved in the dataset (`capture.json`, and inside
manifest.json) and is what makes a resumed or sharded run provably the same capture.
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Usd

from rigspace.capture.ring import Lens, RingView, ring_views
from rigspace.sdk import schema, timecodes
from rigspace.sdk.controls import Control
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.posing import CharacterRig, centre_joint
from rigspace.sdk.rotations import joint_up
from rigspace.sdk.stage import meters_per_unit, open_stage, up_axis
from rigspace.sdk.validation import (
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    require_readable,
    require_valid,
)

SHAPE_DRAWS = ("sparse", "uniform")
"""How a capture draws the blend shape weights it draws apart from the animation
(CaptureSettings.shape_draws)."""
REGION_SURFACES = ("whole", "visible")
"""What of a region's surface its capture keeps (CaptureSettings.region_surface)."""
BOUNDS_MARGIN = 1.1
"""Radius derived from the bounds leaves 10% room around the character's farthest point."""
BOUNDS_FRAMES = 24
"""Frames sampled across the clips to find the character's farthest point from the joint."""
MAX_SAMPLES_PER_AXIS = 8
"""Anti-aliasing beyond 8 x 8 samples per pixel changes nothing visible and multiplies the
supersampled image past what GL render buffers hold (16384 at 2048 x 8)."""

Warn = Callable[[str], None]
"""Where a capture's warnings go: one line each (the CLI prints them to stderr)."""


def print_warning(text: str) -> None:
    print(f"rigspace capture: warning: {text}", file=sys.stderr)


class CaptureError(RigspaceError):
    """A capture request that cannot run as given."""


OFF_GRID_SPACING = (0.5, 1.5)
"""Authored samples about one time code apart (times the step) but mostly off the grid of
integer steps are the clip's frames themselves; sparser keys keep the grid (interpolated)."""


@dataclass(frozen=True)
class Clip:
    name: str
    first: float
    """Stage time code of the first frame (inclusive)."""
    last: float
    """Stage time code of the last frame (inclusive)."""
    held_out: bool = False

    def times(self, step: float = 1.0, samples: Sequence[float] | np.ndarray = ()) -> np.ndarray:
        """The clip's time codes, each snapped to an authored sample within the tolerance
        (sdk/timecodes.py), so a drifted export is posed at its own samples. An animation
        sampled about once per time code but off the integer grid (an export at 0.9867 time
        codes per sample) is captured at its own samples, not between them."""
        span = (self.last - self.first + float(timecodes.tolerance(self.last))) / step
        count = math.floor(span) + 1
        grid = timecodes.snap(self.first + step * np.arange(count), samples)
        inside = np.asarray(samples, dtype=np.float64)
        lo, hi = self.first, self.last
        inside = inside[
            (inside >= lo - timecodes.tolerance(lo)) & (inside <= hi + timecodes.tolerance(hi))
        ]
        if len(inside) < 2:
            return grid
        spacing = float(np.median(np.diff(np.unique(inside))))
        on_samples = np.mean(timecodes.same_time(grid[:, None], inside[None]).any(axis=1))
        if OFF_GRID_SPACING[0] * step < spacing < OFF_GRID_SPACING[1] * step and on_samples < 0.5:
            return np.unique(inside)
        return grid


@dataclass(frozen=True)
class CaptureOverrides:
    """Command-line values that replace the capture ring API's (None: keep the scene's)."""

    views: int | None = field(default=None, metadata={"help": "training views per ring"})
    elevations: tuple[float, ...] | None = field(
        default=None, metadata={"help": "ring elevations in degrees"}
    )
    resolution: int | None = field(
        default=None, metadata={"help": "image width and height, a power of two"}
    )
    radius: float | None = field(default=None, metadata={"help": "camera distance, scene units"})
    frames: tuple[float, float] | None = field(
        default=None, metadata={"help": "capture time codes A:B (inclusive) as one clip"}
    )
    clips: tuple[str, ...] | None = field(
        default=None, metadata={"help": "capture only these clips of the capture ring"}
    )
    held_out_clips: tuple[str, ...] | None = field(
        default=None,
        metadata={
            "help": "the ring's clips held out of training (None: its heldOutClips; (): none)"
        },
    )
    renderer: str = field(default="auto", metadata={"help": "gl, embree or auto"})
    samples_per_axis: int = field(
        default=2, metadata={"help": "anti-aliasing: s x s samples per pixel"}
    )
    frames_per_item: int = field(
        default=16, metadata={"help": "frames per work item (the unit of sharding and resume)"}
    )
    every: int = field(default=1, metadata={"help": "capture every Nth frame of each clip"})


@dataclass(frozen=True)
class CaptureSettings:
    """Everything that determines a dataset's content (saved as capture.json)."""

    scene: str
    scene_fingerprint: str
    character: str
    skeleton: str
    animation: str
    joints: tuple[str, ...]
    look_at_joint: str
    up_axis: str
    meters_per_unit: float
    clips: tuple[Clip, ...]
    views_per_ring: int
    elevations: tuple[float, ...]
    held_out_views_per_ring: int
    held_out_elevations: tuple[float, ...]
    radius: float
    focal_length: float
    horizontal_aperture: float
    resolution: int
    clipping_range: tuple[float, float]
    renderer: str
    samples_per_axis: int
    frames_per_item: int = 16
    every: int = 1
    """Every Nth frame of each clip is captured (1: all)."""
    blend_shapes: tuple[str, ...] = ()
    """The character's blend shapes (CharacterRig.blend_shapes): the weight vector's order."""
    controls: tuple[Control, ...] = ()
    """The character's named controls (CharacterRig.controls), recorded after the weights."""
    blend_draws: tuple[tuple[str, str, float, float], ...] = ()
    """(clip, shape, low, high): a shape whose weight the clip does not move, drawn per frame
    within the ring's blendShapeRanges (`frame_weights`); for a region, every one of its
    shapes in every clip, whatever the clip does (capture/regions.py)."""
    shape_draws: str = "sparse"
    """How a frame's `blend_draws` are drawn (`frame_weights`): "sparse", each at rest (the
    value of its range nearest 0) or drawn uniformly in its range, the share drawn itself
    drawn per frame, so that the number of shapes at work is uniform from none to all of
    them; "uniform" (captures before 2026-11-28 night), every one drawn in its range, so that
    a frame at rest, the runtime's commonest, was a corner no sample came near."""
    region: str = ""
    """The RigspaceRegionAPI instance this dataset captures ("": the whole character)."""
    region_surface: str = "whole"
    """What of a region's surface each sample keeps: "whole", all of it the view sees, as if
    nothing else of the character were there (its network reads its own joints, not the arm
    that passes before it: the runtime's depth test hides it behind the body's arm);
    "visible" (region captures before 2026-11-29 evening), only where it is the character's
    nearest surface, so that an arm raised beside the head cut a quarter of it from the film
    face's yoga views, a hole its network could not foresee (capture/regions.py)."""
    region_joints: tuple[str, ...] = ()
    """A region's joints: its surface is the points whose largest skinning weight is on one."""
    input_joints: tuple[str, ...] = ()
    """The joints the dataset records as the network's input, in skeleton order (): every
    joint. A region's: its joint's chain from the root and its own joints, so that its network
    reads what moves its surface and not the rest of the body (capture/regions.py)."""
    input_shapes: tuple[str, ...] = ()
    """With `input_joints`, the blend shapes the dataset records (a region's own; () none);
    without, every shape of `blend_shapes`."""
    upright_axis: tuple[float, ...] = ()
    """(): every camera keeps the stage's up axis upright. A region's (x, y, z), RegionAPI
    `upright = "joint"`: the look-at joint's own up, in its local frame (the direction that is
    the stage's up in the skeleton's rest pose), which every camera keeps upright instead, so
    that the images turn with the joint about the line of sight (capture/regions.py)."""

    def camera_up(self, joint_to_world: np.ndarray) -> np.ndarray | None:
        """The world direction the cameras of a frame keep upright, the look-at joint at
        `joint_to_world` (4, 4): its own up (`upright_axis`), or None for the stage's."""
        if not self.upright_axis:
            return None
        return joint_up(joint_to_world, np.asarray(self.upright_axis, np.float64))

    @property
    def dataset_joints(self) -> tuple[str, ...]:
        """The joints of the dataset's `rig` column (and its manifest's `joints`)."""
        return self.input_joints or self.joints

    @property
    def dataset_shapes(self) -> tuple[str, ...]:
        """The blend shapes of the dataset's `blend` column (and its manifest's)."""
        return self.input_shapes if self.input_joints else self.blend_shapes

    @property
    def lens(self) -> Lens:
        return Lens(
            self.resolution,
            self.focal_length,
            self.horizontal_aperture,
            self.clipping_range[0],
            self.clipping_range[1],
        )

    def views(self) -> list[RingView]:
        return ring_views(
            self.views_per_ring,
            self.elevations,
            self.radius,
            self.up_axis,
            self.held_out_views_per_ring,
            self.held_out_elevations,
        )

    def to_json(self) -> dict[str, Any]:
        data = asdict(self)
        data["clips"] = [asdict(c) for c in self.clips]
        if self.every == 1:  # as captures before the option recorded it (resume compares)
            del data["every"]
        if not self.blend_draws:
            del data["shape_draws"]
        if not self.region:
            del data["region_surface"]
        # likewise, for a rig without blend shapes, and for the whole character
        for key in (
            "blend_shapes", "controls", "blend_draws", "region", "region_joints",
            "input_joints", "input_shapes", "upright_axis",
        ):  # fmt: skip
            if not data[key]:
                del data[key]
        return data

    def clip_times(self, clip: Clip, samples: Sequence[float] | np.ndarray = ()) -> np.ndarray:
        """The time codes captured of a clip: every `every`th authored frame, snapped."""
        return clip.times(samples=samples)[:: self.every]

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> CaptureSettings:
        names = {f.name for f in fields(cls)}
        values = {k: v for k, v in data.items() if k in names}
        values["clips"] = tuple(Clip(**c) for c in data["clips"])
        for key in ("joints", "elevations", "held_out_elevations", "clipping_range"):
            values[key] = tuple(values[key])
        values["blend_shapes"] = tuple(values.get("blend_shapes", ()))
        values["controls"] = tuple(
            Control(str(c["name"]), tuple(float(v) for v in c["range"]))
            for c in values.get("controls", ())
        )
        values["blend_draws"] = tuple(tuple(d) for d in values.get("blend_draws", ()))
        # absent: a capture from before sparse draws, which drew every shape uniformly
        _read_choice(values, "shape_draws", "uniform", SHAPE_DRAWS)
        # absent from a region's: a capture from before whole surfaces, which kept the visible
        _read_choice(
            values, "region_surface", "visible" if values.get("region") else "whole",
            REGION_SURFACES,
        )  # fmt: skip
        for key in ("region_joints", "input_joints", "input_shapes"):
            values[key] = tuple(values.get(key, ()))
        values["upright_axis"] = tuple(float(v) for v in values.get("upright_axis", ()))
        return cls(**values)

    def frame_weights(self, rig: CharacterRig, clip: str, time: float) -> np.ndarray:
        """(B + C,) the blend shape weights of a captured frame, then its controls' values as
        the stage gives them: the animation's weights, except the shapes `blend_draws` names
        for this clip, drawn as `shape_draws` says from hashes of (clip, time, shape), so
        every view of the frame, a resumed capture and another worker all draw the same
        weight."""
        weights = rig.scalars(time)
        at_work = _hashed(clip, time, "shapes at work")  # "sparse": the share drawn
        for name, shape, low, high in self.blend_draws:  # a region's: every clip ("*")
            if name not in (clip, "*"):
                continue
            value = low + (high - low) * _hashed(clip, time, shape)
            if self.shape_draws == "sparse" and _hashed(clip, time, shape + "|at work") >= at_work:
                value = min(max(0.0, low), high)  # at rest
            weights[self.blend_shapes.index(shape)] = value
        return weights


def _hashed(clip: str, time: float, what: str) -> float:
    """A number in [0, 1) from (clip, time, what): the same in every view, worker and resume."""
    key = f"{clip}|{time:.6f}|{what}".encode()
    return int.from_bytes(hashlib.sha256(key).digest()[:8], "little") / 2.0**64


def _read_choice(values: dict[str, Any], key: str, absent: str, choices: tuple[str, ...]) -> None:
    """capture.json's `key` in `values` as one of `choices` (`absent` when the file has none:
    what captures before the setting did), or CaptureError naming it."""
    values[key] = str(values.get(key, absent))
    if values[key] not in choices:
        raise CaptureError(
            f"capture.json: {key} is {values[key]!r}, not one of {', '.join(choices)}.",
            "restore the file, or capture into a new folder.",
        )


def scene_fingerprint(stage: Usd.Stage) -> str:
    """sha256 over the bytes of every layer the stage uses (a changed asset changes it)."""
    digest = hashlib.sha256()
    for layer in sorted(stage.GetUsedLayers(), key=lambda layer: layer.identifier):
        if layer.anonymous:
            continue
        path = layer.realPath
        digest.update(Path(layer.identifier).name.encode())
        if path and os.path.isfile(path):
            digest.update(Path(path).read_bytes())
        else:  # a layer inside a package, or generated: its text stands in for its file
            digest.update(layer.ExportToString().encode())
    return digest.hexdigest()


def _character_prim(stage: Usd.Stage, path: str) -> Usd.Prim:
    prim = stage.GetPrimAtPath(path) if path.startswith("/") else Usd.Prim()
    if not prim:
        found = [str(p.GetPath()) for p in schema.neural_characters(stage)]
        raise CaptureError(
            f"There is no prim {path!r} in {stage.GetRootLayer().identifier}.",
            f"pass --character with one of: {', '.join(found) or '(the scene has no neural characters)'}",
        )
    if not schema.is_neural_character(prim):
        raise CaptureError(
            f"{path} is a {prim.GetTypeName() or 'typeless prim'}, not a RigspaceNeuralCharacter.",
            "pass the neural character prim (`rigspace inspect` lists them).",
        )
    return prim


def _resolve_clips(
    ring: schema.CaptureRing | None,
    overrides: CaptureOverrides,
    span: tuple[float, float],
    samples: np.ndarray,
    warn: Warn,
) -> tuple[Clip, ...]:
    """The clips to capture, fitted to the animated range (sdk/timecodes.py).

    An end that rounds into the range is the same frame and is snapped to the authored
    sample; a clip that reaches past the range is clamped with a warning; one wholly
    outside it, or not finite, is refused.
    """
    clips, source = _chosen_clips(ring, overrides, span)
    return tuple(_fit_clip(clip, source, span, samples, warn) for clip in clips)


def _chosen_clips(
    ring: schema.CaptureRing | None, overrides: CaptureOverrides, span: tuple[float, float]
) -> tuple[list[Clip], str]:
    """The clips asked for, as authored, and where they come from: --frames, else the ring's
    clips (those --clips names), else the whole animation. The clips held out of training are
    the ring's heldOutClips, or those --held-out-clips names (none when it names none)."""
    held = set(ring.held_out_clips) if ring else set()
    if overrides.held_out_clips is not None:
        _check_clip_names(
            "--held-out-clips", overrides.held_out_clips, ring.clip_names if ring else ()
        )
        held = set(overrides.held_out_clips)
    if ring and ring.clip_names:
        clips = [
            Clip(n, float(a), float(b), n in held)
            for n, (a, b) in zip(ring.clip_names, ring.clip_ranges, strict=True)
        ]
        source = "rigspace:captureRing:clipRanges"
    else:
        clips = [Clip("all", span[0], span[1])]
        source = "the animation's time samples"
    if overrides.clips is not None:
        _check_clip_names("--clips", overrides.clips, [c.name for c in clips])
        clips = [c for c in clips if c.name in overrides.clips]
    if overrides.frames is not None:
        first, last = overrides.frames
        clips = [Clip("frames", float(first), float(last))]
        source = "--frames"
    return clips, source


def _check_clip_names(flag: str, names: Sequence[str], known: Sequence[str]) -> None:
    """A CaptureError naming those of a flag's clip `names` that are not in `known`."""
    unknown = [n for n in names if n not in known]
    if unknown:
        raise CaptureError(
            f"{flag} names {', '.join(unknown)}, which the capture ring does not define.",
            f"use some of: {', '.join(sorted(known))}"
            if known
            else "name the ring's clips (rigspace:captureRing:clipNames) first",
        )


def _fit_clip(
    clip: Clip, source: str, span: tuple[float, float], samples: np.ndarray, warn: Warn
) -> Clip:
    """`clip` fitted to the animated range `span`, its ends snapped to `samples`."""
    named = (
        f"--frames {clip.first:g}:{clip.last:g}"
        if source == "--frames"
        else (f"Clip {clip.name!r} ({clip.first:g}-{clip.last:g}) of {source}")
    )
    if not (math.isfinite(clip.first) and math.isfinite(clip.last)):
        raise CaptureError(
            f"{named} is not a range of finite time codes.",
            f"use A:B with finite numbers inside {span[0]:g}-{span[1]:g}.",
        )
    if clip.first > clip.last and not timecodes.same_time(clip.first, clip.last):
        raise CaptureError(f"{named} ends before it starts.", "use A:B with A <= B.")
    inside = timecodes.clamp_range(clip.first, clip.last, *span)
    if inside is None:
        raise CaptureError(
            f"{named} lies outside the animation's time samples ({span[0]:g}-{span[1]:g}).",
            "capture frames inside the animated range (--frames or the ring's clipRanges).",
        )
    first, last = (float(t) for t in timecodes.snap(inside, samples))
    if not (timecodes.same_time(first, clip.first) and timecodes.same_time(last, clip.last)):
        warn(
            f"{named} reaches past the animation's time samples ({span[0]:g}-{span[1]:g}); "
            f"capturing {first:g}-{last:g}."
        )
    return Clip(clip.name, first, last, clip.held_out)


def animation_time_samples(rig: CharacterRig) -> np.ndarray:
    """Every authored time code of the character's animation, sorted (what clips snap to):
    its joints', and its point caches' and controls' (the cached frames: CharacterRig.
    time_samples)."""
    return rig.time_samples()


def character_reach(rig: CharacterRig, joint: int, clips: tuple[Clip, ...]) -> float:
    """The farthest any posed vertex gets from the look-at joint over the clips (scene units)."""
    times = np.concatenate([c.times() for c in clips])
    picks = times[np.linspace(0, len(times) - 1, min(BOUNDS_FRAMES, len(times))).astype(int)]
    reach = 0.0
    for t in picks:
        centre = rig.world_transforms(float(t))[joint][:3, 3]
        for mesh in rig.posed_meshes(float(t)):
            reach = max(reach, float(np.linalg.norm(mesh.points - centre, axis=1).max()))
    return reach


def fit_radius(reach: float, focal: float, aperture: float) -> float:
    """The camera distance at which a sphere of radius `reach` fills the frame (with margin)."""
    half_fov = math.atan(aperture / 2 / focal)
    # A sphere of radius `reach` fits a cone of half-angle `half_fov` at distance reach / sin.
    return BOUNDS_MARGIN * reach / math.sin(half_fov)


OFF_CENTRE = 0.35
"""A look-at joint farther than this share of the character's reach from the centre of its
skinned meshes frames the character off-centre (a rig rooted at its feet: its feet)."""


def _warn_off_centre(rig: CharacterRig, joint: int, clips: tuple[Clip, ...], warn: Warn) -> None:
    """Say when the ring would be aimed far from the character's middle, and which joint is
    in the middle (what `rigspace init` picks)."""
    times = np.concatenate([c.times() for c in clips])
    picks = times[np.linspace(0, len(times) - 1, min(4, len(times))).astype(int)]
    found = centre_joint(rig, picks)
    if found is None:
        return
    best, positions, points = found
    reach = max(
        float(np.linalg.norm(p - positions[k, joint], axis=1).max()) for k, p in enumerate(points)
    )
    centre = np.mean([(p.min(axis=0) + p.max(axis=0)) / 2 for p in points], axis=0)
    offset = float(np.linalg.norm(positions[:, joint].mean(axis=0) - centre))
    if best != joint and offset > OFF_CENTRE * reach:
        name = rig.joints[best].rsplit("/", 1)[-1]
        warn(
            f"the look-at joint {rig.joints[joint].rsplit('/', 1)[-1]} is {offset:.3g} units "
            f"from the middle of the character (which reaches {reach:.3g} from it): the ring "
            "aims off-centre and the character fills a corner of every sample (a rig rooted "
            f'at its feet shows its feet). Author rigspace:lookAtJoint = "{name}" (the joint '
            "nearest the middle; rigspace:captureRing:lookAtJoint wins if set)."
        )


def derive_radius(
    rig: CharacterRig, joint: int, clips: tuple[Clip, ...], focal: float, aperture: float
) -> float:
    """A camera distance at which the character's farthest point stays inside the image."""
    return fit_radius(character_reach(rig, joint, clips), focal, aperture)


def _check_resolution(defaults: schema.CaptureRing, overrides: CaptureOverrides) -> int:
    """The image resolution, refused unless a power of two in the allowed range."""
    resolution = defaults.resolution if overrides.resolution is None else overrides.resolution
    if not (MIN_RESOLUTION <= resolution <= MAX_RESOLUTION and resolution & (resolution - 1) == 0):
        raise CaptureError(
            f"Resolution {resolution} is not a power of two from {MIN_RESOLUTION} to {MAX_RESOLUTION}.",
            "use 64, 128, 256, ... (the network doubles its resolution block by block).",
        )
    return resolution


def _check_rings(
    defaults: schema.CaptureRing, overrides: CaptureOverrides
) -> tuple[int, tuple[float, ...]]:
    """The views per ring and the ring elevations, refused when out of range."""
    views = defaults.views_per_ring if overrides.views is None else overrides.views
    elevations = defaults.elevations if overrides.elevations is None else overrides.elevations
    if not 1 <= views <= 360:
        raise CaptureError(f"--views {views} is outside 1 to 360.", "use a count in 1 to 360.")
    if not elevations or any(not abs(e) <= 89 for e in elevations):
        raise CaptureError(
            f"Elevations {list(elevations)} must be in [-89, 89] degrees.", "use such elevations."
        )
    return views, elevations


def _check_clipping_range(defaults: schema.CaptureRing) -> tuple[float, float]:
    """The clipping range (near, far), refused unless 0 < near < far."""
    near, far = defaults.clipping_range
    if not 0 < near < far:
        raise CaptureError(
            f"Clipping range ({near:g}, {far:g}) is not 0 < near < far.",
            "fix rigspace:captureRing:clippingRange.",
        )
    return near, far


def _look_at_joint(
    rig: CharacterRig, ring: schema.CaptureRing | None, info: schema.CharacterAttributes
) -> int:
    """The index of the joint the ring looks at: the ring's, the character's, or the root."""
    look_at = (ring.look_at_joint if ring else "") or info.look_at_joint or rig.joints[0]
    try:
        return schema.find_joint(look_at, rig.joints)
    except schema.JointLookupError as exc:
        raise CaptureError(
            f"Look-at joint: {exc.args[0]}.", "name a joint of the skeleton."
        ) from exc


def _resolve_radius(
    rig: CharacterRig,
    joint: int,
    clips: tuple[Clip, ...],
    defaults: schema.CaptureRing,
    overrides: CaptureOverrides,
    clipping: tuple[float, float],
) -> float:
    """The camera distance, given or fitted to the character, refused outside the clipping."""
    near, far = clipping
    radius = overrides.radius or defaults.radius
    if not radius:
        radius = derive_radius(
            rig, joint, clips, defaults.focal_length, defaults.horizontal_aperture
        )
    if not math.isfinite(radius):
        raise CaptureError(
            f"Camera radius {radius:g} is not a finite distance.",
            "pass --radius with a distance in scene units (or 0 to fit the character).",
        )
    if not radius > near:
        raise CaptureError(
            f"Camera radius {radius:g} is not beyond the near clipping plane {near:g}.",
            "raise the radius or lower the near clipping distance.",
        )
    if not radius < far:
        raise CaptureError(
            f"Camera radius {radius:g} puts the look-at joint beyond the far clipping plane "
            f"{far:g}, so the character would be clipped away.",
            "lower the radius or raise the far clipping distance "
            "(rigspace:captureRing:clippingRange).",
        )
    return radius


def _check_work_options(overrides: CaptureOverrides) -> None:
    """Refuse a frames-per-item count, frame stride or anti-aliasing outside its range."""
    if overrides.frames_per_item < 1:
        raise CaptureError(
            f"--frames-per-item {overrides.frames_per_item} must be at least 1.", "use e.g. 16."
        )
    if overrides.every < 1:
        raise CaptureError(
            f"--every {overrides.every} must be at least 1.", "use 1 (every frame), 2, 10, ..."
        )
    if not 1 <= overrides.samples_per_axis <= MAX_SAMPLES_PER_AXIS:
        raise CaptureError(
            f"--samples {overrides.samples_per_axis} is outside 1 to {MAX_SAMPLES_PER_AXIS}.",
            "use 1, 2, 3 or 4.",
        )


def _warn_all_held_out(clips: tuple[Clip, ...], warn: Warn) -> None:
    """Warn when every clip is held out, so the dataset would have no training samples."""
    if all(clip.held_out for clip in clips):
        names = ", ".join(clip.name for clip in clips)
        warn(
            f"every clip of this capture ({names}) is held out (rigspace:captureRing:"
            "heldOutClips), so the dataset will have 0 training samples and `rigspace train` "
            "cannot use it; capture a training clip too (another --clips or --frames) unless "
            "this dataset is for evaluation only."
        )


_DEFAULT_RING = schema.CaptureRing(
    12, (0.0,), 0.0, 50.0, 20.955, 128, (0.1, 1e4), "", (), (), (), 0, ()
)
"""The capture ring of a character without RigspaceCaptureRingAPI (the schema's fallbacks)."""


def resolve_settings(
    scene: str | Path,
    character: str,
    overrides: CaptureOverrides | None = None,
    *,
    warn: Warn = print_warning,
) -> tuple[CaptureSettings, CharacterRig]:
    """The capture's settings with every bad input reported before any work.

    What is allowed but probably not meant (a clip clamped to the animation, a dataset
    without training samples) goes to `warn`.
    """
    overrides = overrides or CaptureOverrides()
    stage, prim, rig = _open_character(scene, character, warn)
    span = rig.time_range()
    assert span is not None, "require_valid refuses an animation without time samples"
    ring = schema.read_capture_ring(prim) if schema.has_capture_ring(prim) else None
    info = schema.read_neural_character(prim)
    defaults = ring or _DEFAULT_RING
    resolution = _check_resolution(defaults, overrides)
    views, elevations = _check_rings(defaults, overrides)
    near, far = _check_clipping_range(defaults)
    joint = _look_at_joint(rig, ring, info)
    clips = _resolve_clips(ring, overrides, span, animation_time_samples(rig), warn)
    _warn_off_centre(rig, joint, clips, warn)
    radius = _resolve_radius(rig, joint, clips, defaults, overrides, (near, far))
    _check_work_options(overrides)
    _warn_all_held_out(clips, warn)
    draws = _blend_draws(rig, ring, clips, every=overrides.every, warn=warn)
    settings = CaptureSettings(
        scene=str(Path(scene).resolve()),
        scene_fingerprint=scene_fingerprint(stage),
        character=str(prim.GetPath()),
        skeleton=str(rig.skeleton.GetPath()),
        animation=str(rig.animation.GetPath()),
        joints=tuple(rig.joints),
        look_at_joint=rig.joints[joint],
        up_axis=up_axis(stage),
        meters_per_unit=meters_per_unit(stage),
        clips=clips,
        views_per_ring=views,
        elevations=tuple(float(e) for e in elevations),
        held_out_views_per_ring=min(defaults.held_out_views_per_ring, views),
        held_out_elevations=tuple(defaults.held_out_elevations),
        radius=float(radius),
        focal_length=defaults.focal_length,
        horizontal_aperture=defaults.horizontal_aperture,
        resolution=resolution,
        clipping_range=(float(near), float(far)),
        renderer=overrides.renderer,
        samples_per_axis=overrides.samples_per_axis,
        frames_per_item=overrides.frames_per_item,
        every=overrides.every,
        blend_shapes=rig.blend_shapes,
        controls=rig.controls,
        blend_draws=draws,
    )
    return settings, rig


def _open_character(
    scene: str | Path, character: str, warn: Warn
) -> tuple[Usd.Stage, Usd.Prim, CharacterRig]:
    """The scene's stage and the character's prim and rig, refused (CaptureError, SceneError)
    as inspect and posing refuse them."""
    stage = open_stage(scene)
    require_readable(stage, "capture", exception=CaptureError)  # before the character is sought
    prim = _character_prim(stage, character)
    rig = CharacterRig(prim)  # no skeleton, no animation, no skin weights: SceneError
    require_valid(stage, "capture", [prim], exception=CaptureError, warn=warn)  # inspect's checks
    return stage, prim, rig


STILL_WEIGHT = 1e-6
"""A shape whose animated weight varies less than this over a clip's captured frames is one the
clip does not move."""


def _blend_draws(
    rig: CharacterRig,
    ring: schema.CaptureRing | None,
    clips: tuple[Clip, ...],
    every: int = 1,
    warn: Warn = print_warning,
) -> tuple[tuple[str, str, float, float], ...]:
    """(clip, shape, low, high) for each shape with an authored range (blendShapeNames /
    blendShapeRanges, validated by inspect's rules) that the clip leaves still; a range on a
    shape a clip moves is not used in that clip, and `warn` says so (weight and pose stay
    tied there)."""
    if ring is None or not ring.blend_shape_names or not rig.blend_shapes:
        return ()
    samples = animation_time_samples(rig)
    draws = []
    animated: dict[str, list[str]] = {}
    for clip in clips:
        times = clip.times(samples=samples)[::every]
        weights = np.array([rig.blend_weights(float(t)) for t in times])
        still = np.ptp(weights, axis=0) <= STILL_WEIGHT
        for name, (low, high) in zip(ring.blend_shape_names, ring.blend_shape_ranges, strict=True):
            if still[rig.blend_shapes.index(name)]:
                draws.append((clip.name, name, float(low), float(high)))
            else:
                animated.setdefault(name, []).append(clip.name)
    for name, moved in animated.items():
        warn(
            f"blend shape {name} has a capture range (rigspace:captureRing:blendShapeRanges), "
            f"but clip{'s' if len(moved) > 1 else ''} {', '.join(moved)} animate{'' if len(moved) > 1 else 's'} "
            "it: there its captured weight follows the animation, tied to the pose. To draw it "
            "apart from the pose, capture a region that names it (rigspace:region:NAME:"
            "blendShapes), or a clip that leaves it still"
        )
    return tuple(draws)

"""A frame's data: the Frame an Engine returns with its FrameReport, the per-frame context its
stages fill (FrameState), and what it keeps between frames (FrameCaches)."""

from __future__ import annotations

import itertools
import time as clock
from collections.abc import Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from rigspace.runtime.billboard import Billboard
from rigspace.runtime.character import Layer, NeuralCharacter, NeuralPart
from rigspace.runtime.lights import Light
from rigspace.runtime.shadows import PosedCapsules
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import Maps

STAGES = ("scene", "rig", "network", "shadows", "lighting", "composite")
"""The stages whose seconds a report holds (FrameReport.seconds)."""


@dataclass
class FrameReport:
    """What a frame computed and why: every decision and every stage's time. Per character (and
    per region in its entry's "regions") an entry of plain JSON values: path, decision
    ("evaluated", "reused", "skipped", "reference"), reason, and where drawn its level, mode,
    branches, region and colour."""

    time: float
    camera: str
    """The Camera prim's path."""
    lights: int
    """Lights used (those left out not counted)."""
    lighting_on: str
    """What lit the frame (runtime/lighting.py): "numba", "numpy", or the GPU's GL_RENDERER."""
    characters: list[dict[str, Any]] = field(default_factory=list)
    scene_prims: dict[str, Any] = field(default_factory=dict)
    """meshes (drawn), reused (the last frame's G-buffer), lit_reused (the last lighting)."""
    lights_left_out: list[str] | None = None
    """Why each light left out of this frame was (None: none was)."""
    shadows: dict[str, Any] = field(default_factory=dict)
    """maps_drawn, casters (characters casting through their capsules), and once,
    without_capsules (the characters that cast no shadow)."""
    counts: dict[str, int] = field(default_factory=dict)
    """How many characters (and regions) each decision applied to."""
    live: list[dict[str, Any]] | None = None
    """The live bindings' status (None: none is active)."""
    composite_reused: bool = False
    """The last frame's images: nothing it shows changed."""
    background: str | None = None
    """The DomeLight behind everything (None: black)."""
    seconds: dict[str, float] = field(default_factory=dict)
    """Per stage (STAGES) and in total."""
    cpu_seconds: dict[str, float] | None = None
    """Per stage, the process's CPU seconds (Engine.report_cpu; None: not asked)."""
    repeat_of_last_frame: bool = False
    """The same time code as the last frame, the stage unedited: the last frame again."""

    def to_json(self) -> dict[str, Any]:
        """The report as `rigspace render` writes it in report.json: lights_left_out, live and
        cpu_seconds left out where None, repeat_of_last_frame where False. The entries are
        shared, not copied."""
        out: dict[str, Any] = {}
        for name in _JSON_ORDER:
            value = getattr(self, name)
            if name not in _LEFT_OUT_EMPTY or value not in (None, False):
                out[name] = value
        return out

    def repeated(self, start: float) -> FrameReport:
        """This report for the same frame answered again at once (from `start`)."""
        characters = [_repeated(e) for e in self.characters]
        return replace(
            self, characters=characters, counts=counts(characters),
            seconds=_seconds(dict.fromkeys(STAGES, 0.0), start), composite_reused=True,
            repeat_of_last_frame=True,
        )  # fmt: skip


_JSON_ORDER = (
    "time", "camera", "scene_prims", "lights", "lighting_on", "characters", "lights_left_out",
    "shadows", "counts", "live", "composite_reused", "background", "seconds", "cpu_seconds",
    "repeat_of_last_frame",
)  # fmt: skip
"""report.json's keys in the order the engine has always written them."""
_LEFT_OUT_EMPTY = {"lights_left_out", "live", "cpu_seconds", "repeat_of_last_frame"}
"""The keys a frame writes only where they say something."""


@dataclass
class Frame:
    """One rendered frame: premultiplied beauty and the composited maps, plus its report."""

    beauty: np.ndarray
    """(H, W, 3) lit colour, premultiplied by `mask`; over the background where there is one."""
    maps: Maps
    report: FrameReport
    opaque: bool = False
    """A background (a DomeLight) fills the pixels nothing covers: the beauty's alpha is 1."""

    @property
    def alpha(self) -> np.ndarray:
        """(H, W) the beauty's alpha: 1 over a background, else the coverage (maps.mask)."""
        return np.ones_like(self.maps.mask) if self.opaque else self.maps.mask


POSE_TOLERANCE = 1e-5
"""Joint rotations (matrix entries) and translations (in billboard sides) closer than this
to the cached pose count as the same pose: a hold interpolated at fractional times differs
by rounding only (3e-5 measured), far below a pixel at any level (1e-5 of 128 pixels)."""

_serials = itertools.count()


@dataclass
class CachedLayer:
    """A body's or region's evaluated layer, with what it was evaluated and lit for."""

    pose: np.ndarray
    """(J, 4, 4) the model's joints' world transforms the layer was evaluated for."""
    view: bytes
    """The camera and billboard corners it was evaluated for (exact)."""
    layer: Layer
    lit: np.ndarray | None = None
    lit_key: bytes = b""
    """The lights `lit` was shaded with: lights that change re-light a reused layer."""
    serial: int = field(default_factory=lambda: next(_serials))
    """Identifies this evaluation in the frame cache's key."""

    weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    """(B,) the blend shape weights it was evaluated for (model order)."""

    def matches(self, pose: np.ndarray, view: bytes, side: float, weights: np.ndarray) -> bool:
        if view != self.view:
            return False
        if len(weights) and np.abs(weights - self.weights).max() >= POSE_TOLERANCE:
            return False
        rotation = np.abs(pose[:, :3, :3] - self.pose[:, :3, :3]).max()
        translation = np.abs(pose[:, :3, 3] - self.pose[:, :3, 3]).max() / side
        return bool(rotation < POSE_TOLERANCE and translation < POSE_TOLERANCE)


@dataclass
class Candidate:
    """A character whose billboard is in view this frame, before its maps are known; or one
    of its regions that adds detail this frame (in its body's `regions`)."""

    character: NeuralCharacter
    entry: dict[str, Any]
    """Its entry in the report (a region's: in its character's entry's "regions")."""
    billboard: Billboard
    world: np.ndarray
    """(J, 4, 4) joint-to-world transforms."""
    view: bytes
    region: tuple[int, int, int, int]
    """(x0, y0, w, h) of the billboard in the frame."""
    weights: np.ndarray
    """(B,) blend shape weights in the model's order (empty: it reads none)."""
    part: NeuralPart
    """What draws it: the character itself (its body), or one of its regions."""
    key: str
    """Its layer's key in the engine's caches: the character's path, PATH#NAME a region's."""
    source_weights: np.ndarray | None = None
    """The character's blend shape weights from live sources and overrides (its order;
    None: the animation's), from which each region takes its own."""
    rig: np.ndarray | None = None
    """Rig parameters, computed only for the characters evaluated this frame."""
    regions: list[Candidate] = field(default_factory=list)
    """Its regions evaluated (or reused) this frame, merged into its layer."""


@dataclass
class FrameCaches:
    """What an Engine keeps between frames, each reused while what it was made from holds."""

    prims_key: tuple = ()
    """The meshes and camera the G-buffer `prims` was drawn for."""
    prims: Maps | None = None
    lit_prims: tuple[bytes, np.ndarray | None, list[np.ndarray | None] | None] | None = None
    """The lit prims, keyed by lights and shadow maps, with each light's shadow factor."""
    layers: dict[str, CachedLayer] = field(default_factory=dict)
    """Each body's and region's last evaluated layer, by Candidate.key."""
    drawn: dict[str, CachedLayer] = field(default_factory=dict)
    """Each character's layer as the last frame lit and composited it: its body's, or its
    body's with its regions merged in (kept in `merges` while they hold)."""
    merges: dict[str, tuple[tuple[int, ...], CachedLayer]] = field(default_factory=dict)
    """A character's merged layer, keyed by the serials of the layers merged."""
    background: tuple[bytes, np.ndarray] | None = None
    """The DomeLight's background, keyed by camera and dome."""
    frame: tuple[tuple, Frame] | None = None
    """The last frame, keyed by everything it shows."""
    frame_at: float | None = None
    """The time code of the last frame (the frame cache answers it again at once)."""
    still_camera: tuple[Camera, bytes] | None = None
    still_lights: tuple[list[Light], list[str]] | None = None
    camera_varies: bool | None = None
    lights_vary: bool | None = None

    def stage_edited(self) -> None:
        """Nothing read from the stage so far can be trusted to be still."""
        self.still_camera = self.still_lights = None
        self.camera_varies = self.lights_vary = None
        self.frame = None


@dataclass
class FrameState:
    """One frame's context, filled stage by stage (Engine.render)."""

    time: float
    start: float
    """perf_counter() when the frame began (the report's total)."""
    camera: Camera
    camera_key: bytes
    lights: list[Light]
    light_key: bytes
    report: FrameReport
    cpu: bool = False
    """Whether `timed` also adds the process's CPU seconds to `cpu_timings` (report_cpu)."""
    timings: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    cpu_timings: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    casters: list[tuple[str, PosedCapsules]] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)
    pending: list[tuple[list[Candidate], Future]] = field(default_factory=list)
    """The network calls under way: (the characters, the call making their layers)."""

    @contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Add the time the block takes to the report's seconds of `stage`."""
        began = clock.perf_counter()
        cpu = clock.process_time() if self.cpu else 0.0
        try:
            yield
        finally:
            self.timings[stage] += clock.perf_counter() - began
            if self.cpu:
                self.cpu_timings[stage] += clock.process_time() - cpu

    def finish_report(self) -> None:
        """The report's timings: `seconds` per stage and in total, and with `cpu` the stages'
        `cpu_seconds`."""
        self.report.seconds = _seconds(self.timings, self.start)
        if self.cpu:
            self.report.cpu_seconds = {k: round(v, 6) for k, v in self.cpu_timings.items()}


def _seconds(timings: dict[str, float], start: float) -> dict[str, float]:
    """The report's seconds per stage, and the total since `start`."""
    seconds = {k: round(v, 6) for k, v in timings.items()}
    seconds["total"] = round(clock.perf_counter() - start, 6)
    return seconds


REPEATED = "same time code as the last frame, stage unedited"


def _repeated(entry: dict[str, Any]) -> dict[str, Any]:
    """A report entry (a character's, or a region's) of a frame repeated unchanged."""
    if "regions" in entry:
        entry = {**entry, "regions": [_repeated(r) for r in entry["regions"]]}
    if entry["decision"] in ("evaluated", "reused"):
        return {**entry, "decision": "reused", "reason": REPEATED}
    return entry


def counts(entries: list[dict[str, Any]]) -> dict[str, int]:
    """How many characters each decision applied to in a frame (the report's summary), and
    how many of their regions."""
    found = dict.fromkeys(("evaluated", "reused", "skipped", "reference"), 0)
    found |= {"outside the view": 0, "unlit": 0, "below the largest level": 0}
    found |= dict.fromkeys(("regions evaluated", "regions reused", "regions skipped"), 0)
    for e in entries:
        found[e["decision"]] += 1
        if e.get("reason") == "outside the view":
            found["outside the view"] += 1
        if e.get("mode") == "unlit":
            found["unlit"] += 1
        if "level" in e and e["level"] < e["top_level"]:
            found["below the largest level"] += 1
        for region in e.get("regions", ()):
            found[f"regions {region['decision']}"] += 1
    return found

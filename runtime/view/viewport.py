"""The viewport's frames: the Engine's maps as JPEG, cached, previewed small then refined."""

from __future__ import annotations

import threading
import time as clock
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from rigspace.runtime.engine import Engine, EngineSettings, Frame
from rigspace.sdk import schema
from rigspace.sdk.color import linear_to_srgb
from rigspace.sdk.errors import RigspaceError

MAPS = ("beauty", "albedo", "normal", "depth", "mask", "chart", "uv")
"""chart and uv: where a character's texture head says each pixel lands (its texture chart,
one colour each, and the st it read as red and green), black where no texture coloured it."""
VIEWS = ("neural", "reference", "compare", "error")
"""neural: the network's frame; reference: the skinned mesh's (--reference); compare: the two
side by side; error: 4x their absolute difference."""
PREVIEW = {"scale": 2, "prim_samples": 1, "max_level": 64}
"""The scrub preview: half the size, no anti-aliasing, characters at 64 px at most (about
50 ms a frame against 170 ms at full quality for previs at 640x360 on 2 cores)."""
CACHE_FRAMES = 600
"""Encoded frames kept (about 20 KB each at 640x360)."""
JPEG_QUALITY = 88
BACKGROUND = 0.09
"""What shows through where nothing covers a pixel (display value; the page is dark too)."""
_SRGB = (linear_to_srgb(np.linspace(0.0, 1.0, 4096)) * 255 + 0.5).astype(np.uint8)
"""linear -> sRGB bytes as a table: a lookup is ten times faster than the power per pixel."""


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    return _SRGB[(np.clip(linear, 0.0, 1.0) * 4095 + 0.5).astype(np.int16)]


def map_image(frame: Frame, name: str) -> np.ndarray:
    """(H, W, 3) uint8 display RGB of one of a frame's images."""
    maps = frame.maps
    if name == "beauty":
        back = np.float32(BACKGROUND) * (1 - frame.alpha)[..., None]
        return np.clip(to_srgb8(frame.beauty) + (back * 255).astype(np.uint8), 0, 255)
    if name == "albedo":
        return to_srgb8(maps.albedo)
    if name == "normal":
        covered = np.any(maps.normal != 0, axis=-1, keepdims=True)  # zero where empty
        return ((maps.normal * 0.5 + 0.5) * covered * 255 + 0.5).clip(0, 255).astype(np.uint8)
    if name == "depth":
        depth = maps.depth
        finite = np.isfinite(depth)
        if not finite.any():
            return np.zeros((*depth.shape, 3), np.uint8)
        near, far = float(depth[finite].min()), float(depth[finite].max())
        # Near is bright; empty pixels (inf) are black.
        value = np.where(finite, 1.0 - (depth - near) / max(far - near, 1e-6) * 0.85, 0.0)
        return np.repeat((value * 255 + 0.5).astype(np.uint8)[..., None], 3, axis=2)
    if name == "mask":
        return np.repeat((np.clip(maps.mask, 0, 1) * 255 + 0.5).astype(np.uint8)[..., None], 3, 2)
    if name in ("chart", "uv"):
        shape = maps.mask.shape
        if maps.chart is None or maps.uv is None:
            return np.zeros((*shape, 3), np.uint8)
        if name == "chart":
            return _chart_colours(maps.chart)
        st = maps.uv - np.floor(maps.uv)  # the fractional st: a UDIM tile's own coordinates
        rgb = np.concatenate([st, np.zeros((*shape, 1), np.float32)], axis=-1)
        return (np.where(maps.chart[..., None] > 0, rgb, 0.0) * 255 + 0.5).astype(np.uint8)
    raise ValueError(name)


def _chart_colours(chart: np.ndarray) -> np.ndarray:
    """One bright colour per texture chart (golden-angle hues), black for none."""
    hue = (np.arange(int(chart.max(initial=0)) + 1) * 137.508) % 360
    hsv = np.stack([hue / 2, np.full_like(hue, 200), np.full_like(hue, 230)], -1)
    palette = cv2.cvtColor(hsv.astype(np.uint8)[None], cv2.COLOR_HSV2RGB)[0]
    palette[0] = 0
    return palette[chart]


def encode(rgb: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return data.tobytes()


@dataclass
class Engines:
    """The engines of one camera: full quality, the scrub preview, and the reference."""

    full: Engine
    preview: Engine | None
    reference: Engine | None

    def close(self) -> None:
        for engine in (self.full, self.preview, self.reference):
            if engine is not None:
                engine.close()


class FrameService:
    """Renders and encodes the viewport's frames; one thread at a time (the Engine is not
    thread-safe: the server calls it from one worker)."""

    def __init__(
        self,
        scene: str | Path,
        lock: threading.RLock,
        *,
        width: int = 640,
        height: int = 360,
        reference: bool = False,
        sources: dict[str, str] | None = None,
        renderer: str = "auto",
        predictor: str = "auto",
        regions: bool = True,
    ) -> None:
        self.scene = Path(scene)
        self.lock = lock
        """The scene model's lock, held while engines open (they read the shared layers).
        Frames and reloads run on the server's one worker thread, so never at once."""
        self.width, self.height = width, height
        self.with_reference = reference
        self.sources = sources or {}
        self.renderer = renderer
        self.predictor = predictor
        self.regions = regions
        """Draw the characters' regions (False: `rigspace view --no-regions`)."""
        self.camera: str | None = None
        self.engines: Engines | None = None
        self.error: str | None = None
        """Why no frame can be rendered (the scene refused by the Engine), else None."""
        self.live_error: str | None = None
        self.version = 0
        self._cache: OrderedDict[tuple, tuple[dict[str, Any], bytes]] = OrderedDict()
        self._last: tuple[Any, str, str, dict[str, Any], bytes] | None = None
        """The last live-encoded frame: (beauty array, map, view, header, jpeg)."""

    # -- engines ---------------------------------------------------------------------------

    def open(self, camera: str | None = None) -> None:
        """(Re)build the engines for `camera` (None: the current, else the stage's first);
        a scene the Engine refuses leaves `error` set and no engines."""
        with self.lock:
            if self.engines is not None:
                self.engines.close()  # frees the live sources' ports before the new ones bind
                self.engines = None
            self.version += 1
            self._cache.clear()
            self._last = None
            self.error = self.live_error = None
            camera = camera or self.camera
            try:
                full = Engine(self.scene, EngineSettings(
                    camera=camera, width=self.width, height=self.height, renderer=self.renderer,
                    sources=self.sources, predictor=self.predictor, regions=self.regions,
                ))  # fmt: skip
            except RigspaceError as exc:
                self.error = str(exc)
                return
            self.camera = str(full.camera_prim.GetPath())
            preview = None
            if not full.live.active:  # a live pose is drawn at full quality only
                s = PREVIEW["scale"]
                preview = Engine(self.scene, EngineSettings(
                    camera=self.camera, width=max(self.width // s, 1),
                    height=max(self.height // s, 1), renderer=self.renderer, live=False,
                    predictor=self.predictor, regions=self.regions,
                    prim_samples=PREVIEW["prim_samples"], max_level=PREVIEW["max_level"],
                ))  # fmt: skip
            truth = None
            if self.with_reference:
                truth = Engine(self.scene, EngineSettings(
                    camera=self.camera, width=self.width, height=self.height,
                    renderer=self.renderer, reference=True,
                ))  # fmt: skip
            self.engines = Engines(full, preview, truth)
            # The first frame of a fresh engine draws its shadow maps and warms its sessions
            # (seconds): done here, so that the page's first scrub is not the slow one.
            start = full.stage.GetStartTimeCode()
            for engine in (preview, truth) if full.live.active else (preview, full, truth):
                if engine is not None:
                    engine.render(start)
            if full.live.active:
                try:
                    full.open_live()
                except RigspaceError as exc:
                    self.live_error = str(exc)

    def close(self) -> None:
        with self.lock:
            if self.engines is not None:
                self.engines.close()
                self.engines = None

    @property
    def live(self) -> bool:
        return self.engines is not None and self.engines.full.live.active

    def live_status(self) -> list[dict[str, Any]]:
        """Every live binding of the stage's characters: URL, enabled, and while its source
        runs, status and counters (packets, samples, malformed, dropped, latency...)."""
        if self.engines is None:
            return []
        engine = self.engines.full
        running = {(r["character"], r["binding"]): r for r in engine.live.report()}
        out = []
        for character in engine.characters:
            for binding in schema.read_live_bindings(character.prim):
                url = self.sources.get(binding.name, binding.url)
                row = running.get((character.path, binding.name))
                out.append(
                    {"character": character.path, "binding": binding.name, "url": url,
                     "enabled": binding.enabled or binding.name in self.sources,
                     **(row or {"status": "not running"})}
                )  # fmt: skip
        return out

    # -- frames ----------------------------------------------------------------------------

    def frame(
        self,
        time: float,
        map_name: str,
        view: str,
        quality: str,
        weights: dict[str, dict[str, float]] | None = None,
    ) -> tuple[dict[str, Any], bytes]:
        """The header (report, size, timings) and JPEG of one viewport frame; `weights`:
        character path -> blend shape -> weight, the inspector's sliders (every engine draws
        them, the reference's mesh too)."""
        start = clock.perf_counter()
        # No lock: frames and reloads run on the server's one worker thread, one at a time.
        engines = self.engines
        if engines is None:
            return {"error": self.error or "no engine"}, b""
        weights = weights or {}
        try:
            _set_weights(engines, weights)
        except ValueError as exc:
            return {"error": f"blend shape weights: {exc}"}, b""
        shaped = tuple(sorted((p, tuple(sorted(w.items()))) for p, w in weights.items()))
        if view != "neural" and engines.reference is None:
            view = "neural"
        preview = quality == "preview" and view == "neural" and engines.preview is not None
        quality = "preview" if preview else "full"
        live = engines.full.live.active
        key = (self.version, self.camera, time, map_name, view, shaped, quality)
        if not live and (cached := self._cached(key)) is not None:
            header, data = cached
            return {**header, "cached": True, "server_ms": _ms(start)}, data
        engine = engines.preview if preview and engines.preview else engines.full
        frame = engine.render(time)
        if view == "neural":
            if live and (reused := self._reused(frame, map_name, view)) is not None:
                header, data = reused
                return {**header, "server_ms": _ms(start)}, data
            rgb = map_image(frame, map_name)
        else:
            assert engines.reference is not None
            truth = engines.reference.render(time)
            rgb = _reference_view(frame, truth, map_name, view)
        data = encode(rgb)
        header = {
            "time": time,
            "camera": self.camera,
            "map": map_name,
            "view": view,
            "quality": quality,
            "width": engine.settings.width,
            "height": engine.settings.height,
            "image_width": rgb.shape[1],
            "report": frame.report.to_json(),
            "cached": False,
        }
        if live:
            self._last = (frame.beauty, map_name, view, header, data)
        else:
            self._keep(key, header, data)
        return {**header, "server_ms": _ms(start)}, data

    def _reused(
        self, frame: Frame, map_name: str, view: str
    ) -> tuple[dict[str, Any], bytes] | None:
        """The last live frame's header and JPEG again when the engine reused its composite
        (same pose, still camera) and the map and view are the same; else None."""
        last = self._last
        if last is None or last[0] is not frame.beauty or last[1:3] != (map_name, view):
            return None
        # The engine reused its composite (same pose, still camera): so do we.
        return {**last[3], "report": frame.report.to_json(), "reused": True}, last[4]

    def _cached(self, key: tuple) -> tuple[dict[str, Any], bytes] | None:
        """The still frame cached for `key` (its refined one when known: no preview), now the
        most recently used; None when there is none."""
        better = (*key[:-1], "full")
        if better in self._cache:  # the refined frame is known: no preview
            key = better
        if key not in self._cache:
            return None
        self._cache.move_to_end(key)
        return self._cache[key]

    def _keep(self, key: tuple, header: dict[str, Any], data: bytes) -> None:
        """Cache a still frame, forgetting the least recently used beyond CACHE_FRAMES."""
        self._cache[key] = (header, data)
        while len(self._cache) > CACHE_FRAMES:
            self._cache.popitem(last=False)


def _set_weights(engines: Engines, weights: dict[str, dict[str, float]]) -> None:
    """Every engine draws the inspector's blend shape weights; a character no longer in
    `weights` gets its own back (ValueError: a path or weight an engine cannot take)."""
    for each in (engines.full, engines.preview, engines.reference):
        if each is not None:
            for path in {*each.weight_overrides, *weights}:
                each.set_weights(path, weights.get(path, {}))


def _reference_view(frame: Frame, truth: Frame, map_name: str, view: str) -> np.ndarray:
    mine, theirs = map_image(frame, map_name), map_image(truth, map_name)
    if view == "reference":
        return theirs
    if view == "compare":
        return np.concatenate([mine, theirs], axis=1)
    error = np.abs(mine.astype(np.int16) - theirs.astype(np.int16)) * 4
    return np.clip(error, 0, 255).astype(np.uint8)


def _ms(start: float) -> float:
    return round((clock.perf_counter() - start) * 1e3, 2)

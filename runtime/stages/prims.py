"""The scene prims' stages: their G-buffer drawn by the renderer plugin (`draw`, reused while
neither they nor the camera move), then lit and shadowed into the beauty the characters are
composited over (`light`: the shadow maps' and the characters' capsules' shadows)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigspace.runtime.frame import FrameCaches, FrameState
from rigspace.runtime.lighting import Lighting, reshade
from rigspace.runtime.scene import SceneGeometry
from rigspace.runtime.shadows.frame import FrameShadows, casts_shadows
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import DrawMesh, Maps, Renderer, empty_maps


@dataclass
class Prims:
    """The prims of a frame: what the stages after `PrimStages.draw` are handed."""

    maps: Maps
    """Their G-buffer."""
    meshes: list[DrawMesh]
    """The set's meshes (the shadow casters), without the reference mode's characters."""
    reused: bool
    """Whether the G-buffer is the last frame's."""


class PrimStages:
    """Draws the prims' G-buffer and the lights' shadow maps (`draw`); lights them (`light`)."""

    def __init__(
        self, renderer: Renderer, shadows: FrameShadows, lighting: Lighting, caches: FrameCaches
    ) -> None:
        self.renderer, self.shadows, self.lighting, self.caches = (
            renderer,
            shadows,
            lighting,
            caches,
        )

    def draw(self, f: FrameState, scene: SceneGeometry) -> Prims:
        """The prims' meshes at the frame's time, their G-buffer (the last frame's while
        prims and camera hold) and the lights' shadow maps brought up to date."""
        with f.timed("scene"):
            meshes = scene.meshes(f.time)
            maps, reused = self._gbuffer(meshes, f.camera, f.camera_key)
        f.report.scene_prims = {"meshes": len(meshes), "reused": reused}
        with f.timed("shadows"):
            self.shadows.update(meshes, scene.moving, f.lights)
        return Prims(maps, meshes, reused)

    def _gbuffer(self, meshes, camera: Camera, camera_key: bytes) -> tuple[Maps, bool]:
        caches = self.caches
        key = (tuple(id(m) for m in meshes), camera_key)
        if caches.prims is not None and key == caches.prims_key:
            return caches.prims, True
        maps = (
            self.renderer.render(meshes, camera)
            if meshes
            else empty_maps(camera.height, camera.width)
        )
        caches.prims, caches.prims_key = maps, key
        return maps, False

    def light(self, f: FrameState, prims: Prims) -> np.ndarray:
        """The prims lit and shadowed (the maps' and the capsules' shadows): the beauty the
        characters are composited over. Still prims and lights reuse their lighting and only
        find the capsules' shadows again."""
        lit_key = f.light_key + self.shadows.key
        kept = self.caches.lit_prims
        reused = prims.reused and kept is not None and kept[0] == lit_key
        if reused and kept is not None:
            beauty = self._relight(f, prims, lit_key, kept)
        else:
            beauty = self._light_anew(f, prims, lit_key)
        f.report.scene_prims["lit_reused"] = reused
        return beauty

    def _relight(self, f: FrameState, prims: Prims, lit_key: bytes, kept) -> np.ndarray:
        """The last lighting (the maps' shadows in, still), with the pixels the capsules
        shadow now lit again."""
        camera, lights = f.camera, f.lights
        with f.timed("shadows"):
            _, hidden = self.shadows.prims(
                prims.maps, camera, lights, prims.meshes, f.casters, False
            )
        with f.timed("lighting"):
            _, lit, visibility = kept
            if lit is None:  # last shaded with the capsules' shadows in: once without them
                lit = self._shade(prims.maps, camera, lights, visibility)
                self.caches.lit_prims = (lit_key, lit, visibility)
            beauty = lit.copy()  # the characters are composited over this copy
        with f.timed("shadows"):
            dark = [v < 1.0 for v in hidden if v is not None]
            pixels = np.flatnonzero(np.logical_or.reduce(dark)) if dark else np.zeros(0, int)
            if pixels.size:  # lit again with every light's shadows, the maps' and capsules'
                both = [
                    _product(m, c)
                    for m, c in zip(visibility or [None] * len(lights), hidden, strict=True)
                ]
                reshade(self.lighting, beauty, prims.maps, camera, lights, pixels, both)
        return beauty

    def _light_anew(self, f: FrameState, prims: Prims, lit_key: bytes) -> np.ndarray:
        """One pass finds the maps' and the capsules' shadows; one shading applies both."""
        camera, lights = f.camera, f.lights
        with f.timed("shadows"):
            visibility, hidden = None, []
            if casts_shadows(lights):
                visibility, hidden = self.shadows.prims(
                    prims.maps, camera, lights, prims.meshes, f.casters, True
                )
        with f.timed("lighting"):
            both = visibility
            if any(v is not None for v in hidden) and visibility is not None:
                both = [_product(m, c) for m, c in zip(visibility, hidden, strict=True)]
            beauty = self._shade(prims.maps, camera, lights, both)
            # Kept for a still next frame; without the capsules' shadows it is made then.
            lit = beauty.copy() if both is visibility else None
            self.caches.lit_prims = (lit_key, lit, visibility)
        return beauty

    def _shade(self, prims: Maps, camera: Camera, lights, visibility) -> np.ndarray:
        """The prims' G-buffer lit, with per-light shadow factors `visibility`."""
        if not lights:
            return prims.albedo.copy()
        return self.lighting.shade(
            prims.albedo, prims.normal, prims.depth, prims.mask, camera, lights,
            visibility=visibility,
        )  # fmt: skip


def _product(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    """Two shadow factors of a light together (None: unshadowed)."""
    return b if a is None else a if b is None else a * b

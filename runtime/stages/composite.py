"""The composite stage: each character's layer lit and shadowed (kept while its lights and the
other casters hold), composited over the lit prims by depth with its coverage as alpha at its
edges (composite_kernel.py), and a DomeLight behind everything."""

from __future__ import annotations

import numpy as np

from rigspace.runtime.composite_kernel import composite, over_background
from rigspace.runtime.frame import CachedLayer, Frame, FrameCaches, FrameState
from rigspace.runtime.lighting import Lighting
from rigspace.runtime.lights import AMBIENT, Light, background
from rigspace.runtime.shadows.frame import FrameShadows
from rigspace.runtime.stages.prims import Prims
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import Maps


class CompositeStage:
    """Lights the characters' layers and composites them and the background over the prims."""

    def __init__(self, shadows: FrameShadows, lighting: Lighting, caches: FrameCaches) -> None:
        self.shadows, self.lighting, self.caches = shadows, lighting, caches

    def __call__(self, f: FrameState, prims: Prims, beauty: np.ndarray) -> Frame:
        """The frame: the characters' layers (the caches' `drawn`) lit and composited into
        `beauty` (the lit prims, taken over) and into copies of the prims' AOVs."""
        maps = prims.maps
        albedo, normal = maps.albedo.copy(), maps.normal.copy()
        depth, mask = maps.depth.copy(), maps.mask.copy()
        # Texture AOVs (uv, chart) when anything has them: the reference mode's meshes, or a
        # character coloured from its textures.
        drawn = [(c.character.path, self.caches.drawn[c.key]) for c in f.candidates]
        uv = chart = None
        if maps.chart is not None or any(d.layer.chart is not None for _, d in drawn):
            shape = maps.mask.shape
            uv = maps.uv.copy() if maps.uv is not None else np.zeros((*shape, 2), np.float32)
            chart = maps.chart.copy() if maps.chart is not None else np.zeros(shape, np.int32)
        for path, cached in drawn:
            self._light_layer(f, path, cached, prims)
            with f.timed("composite"):
                layer = cached.layer
                composite(layer, cached.lit, beauty, albedo, normal, depth, mask, uv, chart)
        with f.timed("composite"):
            dome = next((light for light in f.lights if light.kind == AMBIENT), None)
            f.report.background = dome.path if dome is not None else None
            if dome is not None:  # behind everything: over it goes the premultiplied frame
                over_background(beauty, mask, self._background(dome, f.camera, f.camera_key))
        for array in (beauty, albedo, normal, depth, mask, uv, chart):
            if array is not None:
                array.flags.writeable = False  # shared with the frame cache
        return Frame(
            beauty, Maps(albedo, normal, depth, mask, uv, chart), f.report, dome is not None
        )

    def _light_layer(self, f: FrameState, path: str, cached: CachedLayer, prims: Prims) -> None:
        """A character's layer lit and shadowed by the prims' maps and the other characters'
        capsules, unless it was with the same lights, maps and other casters."""
        layer, lights = cached.layer, f.lights
        others = [(p, posed) for p, posed in f.casters if p != path]
        key = f.light_key + self.shadows.key + b"".join(posed.key for _, posed in others)
        if cached.lit is not None and cached.lit_key == key:
            return
        cached.lit_key = key
        with f.timed("shadows"):
            visibility = self.shadows.layer(layer, f.camera, lights, others, prims.meshes)
        with f.timed("lighting"):
            if not lights:
                cached.lit = layer.albedo
                return
            cached.lit = self.lighting.shade(
                layer.albedo, layer.normal, layer.depth, layer.mask, f.camera, lights,
                origin=(layer.x0, layer.y0), visibility=visibility,
            )  # fmt: skip

    def _background(self, dome: Light, camera: Camera, camera_key: bytes) -> np.ndarray:
        """What a DomeLight shows behind everything, cached while camera and dome are still."""
        key = camera_key + dome.radiance.tobytes() + dome.orientation.tobytes()
        key += b"" if dome.texture is None else np.int64(id(dome.texture)).tobytes()
        kept = self.caches.background
        if kept is None or kept[0] != key:
            kept = self.caches.background = (key, background(dome, camera))
        return kept[1]

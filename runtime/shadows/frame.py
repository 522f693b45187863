"""FrameShadows: a frame's shadows behind one object, the strategy the Engine calls.

It holds the prims' shadow maps (PrimShadows) and the passes that find the prims' and a
character layer's shadow factors: numpy's (numpy_passes.py, the reference) or the compiled
kernels' (passes.py), as the ShadowBackend says; the compiled passes stand aside where the
capsules' occlusion runs in the fragment shader (they have no call back into it).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import numpy as np

from rigspace.runtime.character import Layer
from rigspace.runtime.lights import DISTANT, POINT, Light
from rigspace.runtime.shadows import PosedCapsules, PrimShadows, ShadowBackend
from rigspace.runtime.shadows import numpy_passes as numpy_pass
from rigspace.runtime.shadows import passes as shadow_pass
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import DrawMesh, Maps, RendererSpec

Casters = Sequence[tuple[str, PosedCapsules]]
"""The characters casting this frame: (path, its posed capsules)."""


def casts_shadows(lights: Sequence[Light]) -> bool:
    """Whether any light casts shadows (the ambient one does not)."""
    return any(light.kind in (DISTANT, POINT) for light in lights)


class FrameShadows:
    """The prims' shadow maps and the passes that shadow the prims and the characters' layers."""

    def __init__(
        self, spec: RendererSpec, backend: ShadowBackend | None = None, shared: object = None
    ) -> None:
        """`shared`: the device resources the maps and the capsule shader draw with
        (RenderSettings.shared: the engine's GL context)."""
        self.maps = PrimShadows(spec, shared=shared)
        """The prims' shadow maps per light (drawn on demand, kept while they hold)."""
        self.record: dict[str, Callable[[], Any]] | None = None
        """None, or a dict that each frame fills with its shadow passes, each a call that runs
        the pass again on the same inputs with the backend in use then: "prims" (the prims'
        shadows from the maps and the capsules) and "layer" (a character layer's, the frame's
        last). The shadow timing tool (apps/shadow_timing.py) repeats them."""
        self._box: tuple[tuple, np.ndarray] | None = None
        self._compiled = False
        self.use(backend or ShadowBackend())

    def use(self, backend: ShadowBackend) -> None:
        """Compute with `backend` from the next call on (the maps drawn so far are kept: the
        shadow bench times both kernels on the same inputs)."""
        self._compiled = backend.kernel == "numba"
        self.maps.use(backend, shadow_pass.COMPILED if self._compiled else None)

    @property
    def key(self) -> bytes:
        """Changes whenever any map's casters or light do (the frame's caches compare it)."""
        return self.maps.key

    @property
    def drawn(self) -> int:
        """Maps drawn since the last update (the report's)."""
        return self.maps.drawn

    @property
    def capsule_backend(self) -> str:
        """What computes the capsules' occlusion, "gl" or "numpy" (decided on first use)."""
        return self.maps.capsule_backend

    def update(self, meshes: Sequence[DrawMesh], moving: set[int], lights: list[Light]) -> None:
        """This frame's lights and prims: still prims in one map per light, each moving one
        (its id in `moving`) in its own. `meshes` are the scene's prims only: a character casts
        through its capsules (in the reference mode too, so that the two modes differ only in
        the character's maps)."""
        if not casts_shadows(lights):
            self.maps.update([], [])
            return
        still = [m for m in meshes if id(m) not in moving]
        each = [(f"moving {m.name}", [m]) for m in meshes if id(m) in moving]
        self.maps.update(lights, [("still", still), *each])

    def prims(
        self, prims: Maps, camera: Camera, lights: list[Light], meshes: Sequence[DrawMesh],
        casters: Casters, maps: bool,
    ) -> tuple[list[np.ndarray | None], list[np.ndarray | None]]:  # fmt: skip
        """Per light, the prims' (H, W) shadow factor from the shadow maps (with `maps`) and
        from the characters' capsules (None: none can fall)."""
        if self.record is not None:
            self.record["prims"] = partial(self.prims, prims, camera, lights, meshes, casters, maps)
        box = self._scene_box(meshes)
        run = shadow_pass.prim_shadows if self._kernels() else numpy_pass.prim_shadows
        return run(self.maps, prims, camera, lights, box, casters, maps)

    def layer(
        self, layer: Layer, camera: Camera, lights: list[Light], others: Casters,
        meshes: Sequence[DrawMesh],
    ) -> list[np.ndarray | None] | None:  # fmt: skip
        """Per light, a character layer's (h, w) shadow factor: the prims' shadow maps and
        the other characters' capsules (`others`); None where nothing can shadow it."""
        if self.record is not None:
            self.record["layer"] = partial(self.layer, layer, camera, lights, others, meshes)
        if not casts_shadows(lights) or layer.depth is None or layer.normal is None:
            return None
        box = self._scene_box(meshes)
        run = shadow_pass.layer_visibility if self._kernels() else numpy_pass.layer_visibility
        return run(self.maps, layer, camera, lights, box, others)

    def _kernels(self) -> bool:
        """Whether the compiled passes run: the backend's kernel is numba and the capsules'
        occlusion is not in the fragment shader."""
        return self._compiled and self.maps.capsule_backend == "numpy"

    def _scene_box(self, meshes: Sequence[DrawMesh]) -> np.ndarray:
        """(2, 3) bounds of the prims (where a capsule shadow can land), cached with them."""
        key = tuple(id(m) for m in meshes)
        if self._box is None or self._box[0] != key:
            if meshes:
                lo = np.min([m.points.min(axis=0) for m in meshes], axis=0)
                hi = np.max([m.points.max(axis=0) for m in meshes], axis=0)
            else:
                lo = hi = np.zeros(3)
            self._box = (key, np.array([lo, hi], dtype=np.float64))
        return self._box[1]

    def close(self) -> None:
        self.maps.close()

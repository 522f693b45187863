"""How an engine lights its G-buffers, chosen once: the Lighting protocol and its three implementations.

All three compute shading.py's Lambert plus Blinn-Phong on a region of the frame: NumpyLighting
(shading.shade, the reference), CompiledLighting (shading_kernel.shade, numba: the CPU's
default) and gl_shading.GLShading (a fragment shader: where the gl renderer runs on a GPU).
`choose_lighting` picks one for an Engine; `reshade` lights scattered pixels again with it (the
prims under the characters' capsule shadows).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from rigspace.runtime import shading, shading_kernel
from rigspace.runtime.gl_shading import open_gl_shading
from rigspace.runtime.lights import Light
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import Maps, RendererSpec
from rigspace.sdk.render.gl import SharedContext


class Lighting(Protocol):
    """Lights a G-buffer region (shading.shade's contract)."""

    @property
    def name(self) -> str:
        """What lights: "numpy", "numba", or the GPU's GL_RENDERER (the report's lighting_on)."""
        ...

    def shade(
        self,
        albedo: np.ndarray,
        normal: np.ndarray,
        depth: np.ndarray,
        mask: np.ndarray,
        camera: Camera,
        lights: Sequence[Light],
        origin: tuple[int, int] = (0, 0),
        visibility: Sequence[np.ndarray | None] | None = None,
    ) -> np.ndarray:
        """Lit, premultiplied colour (H, W, 3) of a region whose top-left pixel is `origin`;
        `visibility` per light None or its (H, W) shadow factor."""
        ...

    def close(self) -> None: ...


class NumpyLighting:
    """shading.shade: the reference the others are tested against."""

    name = "numpy"

    def shade(self, albedo, normal, depth, mask, camera, lights, origin=(0, 0), visibility=None):
        return shading.shade(albedo, normal, depth, mask, camera, lights, origin, visibility)

    def close(self) -> None:
        pass


class CompiledLighting:
    """shading_kernel.shade: the CPU's lighting (within 1e-5 of numpy's brightest pixel)."""

    name = "numba"

    def shade(self, albedo, normal, depth, mask, camera, lights, origin=(0, 0), visibility=None):
        return shading_kernel.shade(albedo, normal, depth, mask, camera, lights, origin, visibility)

    def close(self) -> None:
        pass


def choose_lighting(
    renderer: RendererSpec, gl_lighting: str, kernel: str = "numba", shared: object = None
) -> Lighting:
    """The fragment shader where `gl_lighting` asks for it with this renderer (gl_shading's
    open_gl_shading, in the `shared` GL context where one is given), else the CPU's `kernel`
    ("numba" or "numpy")."""
    context = shared if isinstance(shared, SharedContext) else None
    shader = open_gl_shading(renderer, gl_lighting, context)
    if shader is not None:
        return shader
    return CompiledLighting() if kernel == "numba" else NumpyLighting()


def reshade(
    lighting: Lighting,
    beauty: np.ndarray,
    prims: Maps,
    camera: Camera,
    lights: Sequence[Light],
    pixels: np.ndarray,
    visibility: Sequence[np.ndarray | None],
) -> None:
    """Light the prims' `pixels` (flat indices of the frame) again into `beauty`, with per
    light None or its (H, W) shadow factor: the window holding them is lit with the other
    pixels' coverage zeroed (each pixel is lit alone: the same values as lighting the frame)."""
    rows, cols = np.divmod(pixels, camera.width)
    y0, x0 = int(rows.min()), int(cols.min())
    window = (slice(y0, int(rows.max()) + 1), slice(x0, int(cols.max()) + 1))
    w = window[1].stop - x0
    inside = (rows - y0) * w + (cols - x0)
    mask = np.zeros((window[0].stop - y0, w), np.float32)
    mask.reshape(-1)[inside] = prims.mask.reshape(-1)[pixels]
    lit = lighting.shade(
        prims.albedo[window], prims.normal[window], prims.depth[window], mask, camera, lights,
        (x0, y0), [None if v is None else v[window] for v in visibility],
    )  # fmt: skip
    beauty.reshape(-1, 3)[pixels] = lit.reshape(-1, 3)[inside]

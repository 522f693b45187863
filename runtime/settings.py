"""EngineSettings: what an Engine is asked to render, and how, chosen once (its fields' docstrings
are the documentation).

    engine = Engine("samples/scenes/previs.usda", EngineSettings(width=640, height=360))
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rigspace.runtime.shadows import ShadowBackend
from rigspace.sdk.errors import SceneError

AOVS = ("beauty", "albedo", "normal", "depth", "mask")
"""The images a frame can give (Frame.beauty and Frame.maps)."""
LIGHTING_KERNELS = ("numba", "numpy")


@dataclass(frozen=True)
class EngineSettings:
    """An Engine's settings. A bad viewport or an unknown AOV is a SceneError naming the fix."""

    camera: str | None = None
    """The Camera prim's path (None: the stage's first camera)."""
    width: int = 640
    """Image width in pixels."""
    height: int = 360
    """Image height in pixels."""
    renderer: str = "auto"
    """The renderer plugin that draws the scene prims, the shadow maps and the reference mode's
    meshes: "gl", "embree" or "auto" (rigspace.sdk.render.choose_renderer)."""
    precision: str = "fp32"
    """The networks' graphs: "fp32" or "int8" (where the bundle has them)."""
    reference: bool = False
    """Draw each character's real skinned mesh with the renderer instead of its network (the
    ground truth that `rigspace render --reference` compares with)."""
    aovs: tuple[str, ...] = AOVS
    """The images the caller will read: without "normal" and "depth", a character with no
    lights on it and nothing overlapping its billboard runs its albedo branch only."""
    prim_samples: int = 2
    """Samples per axis that anti-alias the scene prims (2: 2x2 per pixel; 1: none, about twice
    as fast on a software renderer)."""
    max_level: int | None = None
    """Caps the level of detail (the network's output resolution) to trade detail for time."""
    textures: bool = True
    """False colours every character from its albedo branch even where its bundle has a texture
    head (a comparison, or a scene whose textures should not be read)."""
    live: bool = True
    """Enabled RigspaceLiveBindingAPI bindings drive their characters (runtime/live; their
    sources open at the first frame, or `Engine.open_live()`; `close()` or `with` stops them)."""
    sources: dict[str, str] = field(default_factory=dict)
    """Binding names to URLs that replace theirs and enable them."""
    predictor: str = "auto"
    """What runs the networks (rigspace.sdk.predictors; "auto": the fastest that can)."""
    models: dict[str, str] = field(default_factory=dict)
    """Neural character paths ("" for the stage's only one) to model bundles drawn instead of
    their rigspace:model, in the session layer: the scene file is not edited."""
    shadow_backend: ShadowBackend = field(default_factory=ShadowBackend)
    """What computes the shadows (rigspace.runtime.shadows.ShadowBackend: the compiled kernels
    and, on a GPU, the fragment shader by default)."""
    gl_lighting: str = "hardware"
    """Where the lighting runs in a fragment shader (runtime/gl_shading.py): "hardware", the gl
    renderer on a GPU; "always", on Mesa's llvmpipe too; "never"."""
    lighting_kernel: str = "numba"
    """What lights where the fragment shader does not (runtime/lighting.py): "numba", the
    compiled kernel (shading_kernel.py), or "numpy", shading.py (the reference)."""
    regions: bool = True
    """False draws each character's body alone, never its regions (the face, a hand: bundles of
    their own listed in its manifest, docs/regions.md; not loaded)."""

    def __post_init__(self) -> None:
        unknown = sorted(set(self.aovs) - set(AOVS))
        if unknown:
            raise SceneError(
                f"Unknown AOV {', '.join(unknown)}.", f"choose from {', '.join(AOVS)}."
            )
        if self.width <= 0 or self.height <= 0:
            raise SceneError(
                f"The viewport is {self.width}x{self.height}.",
                "render at least 1x1 pixels (--resolution WxH).",
            )
        if self.lighting_kernel not in LIGHTING_KERNELS:
            raise ValueError(
                f"lighting_kernel {self.lighting_kernel!r} is not one of {LIGHTING_KERNELS}"
            )
        object.__setattr__(self, "aovs", tuple(self.aovs))

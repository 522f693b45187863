"""runtime/shading.shade in a fragment shader: a frame's lighting on the GPU that draws it.

At 1920x1080 the numpy shading of the prims' G-buffer is the frame's largest CPU stage after
the scene (120-300 ms on 2 cores); a GPU shades the same pixels in well under a millisecond,
so where the gl renderer runs on one, the engine lights the prims and the characters' layers
here (`open_gl_shading`, Engine's `gl_lighting`). The maths is shading.py's, term for term
and in float32 (the highlight's power by repeated squaring too): tests hold the two equal
within 1e-5 of the brightest pixel on Mesa's llvmpipe. numpy stays the reference and the
path of every machine without a GPU, where the shader is no faster (uploads and read-backs
through a software rasteriser).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from rigspace.runtime.lights import Light
from rigspace.runtime.shading import (
    MIN_DISTANCE,
    SHININESS,
    SPECULAR,
    light_uniforms,
    shadow_layers,
)
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import RendererSpec
from rigspace.sdk.render.gl import FULL_SCREEN_VERTEX_SHADER, SharedContext, share

GL_LIGHTING = ("hardware", "always", "never")
"""Where the engine lights in the fragment shader: "hardware" with the gl renderer on a GPU
(the default), "always" with the gl renderer (Mesa's llvmpipe too: the tests), "never"."""
MAX_LIGHTS = 16
"""Lights per draw; more are shaded in batches whose colours add (shading is linear in them)."""
GROWTH = 1.25
"""The textures grow to this much more than the region that outgrew them."""


_FRAGMENT = """
#version 330 core
#define MAX_LIGHTS %(max_lights)d
#define SQUARINGS %(squarings)d
uniform sampler2D albedo;        // RGB32F, premultiplied by coverage
uniform sampler2D normal;        // RGB32F camera-space unit normals
uniform sampler2D depth;         // R32F distance along -Z, inf where empty
uniform sampler2D mask;          // R32F coverage
uniform sampler2DArray shadow;   // R32F per shadowed light: its visibility
uniform vec2 origin;             // the region's top-left pixel in the camera's image
uniform vec4 lens;               // fx, fy, cx, cy
uniform int count;
uniform int kind[MAX_LIGHTS];    // 0 ambient, 1 distant, 2 point
uniform vec3 radiance[MAX_LIGHTS];
uniform vec3 vector[MAX_LIGHTS]; // camera space: towards a distant light, a point light's position
uniform float area[MAX_LIGHTS];
uniform int layer[MAX_LIGHTS];   // its visibility's layer in `shadow`, -1: unshadowed
out vec4 colour;
const float SPECULAR = %(specular)r;
const float MIN_DISTANCE = %(min_distance)r;

void main() {
    ivec2 pixel = ivec2(gl_FragCoord.xy);  // row y of the region is the arrays' row y
    float coverage = texelFetch(mask, pixel, 0).r;
    if (!(coverage > 0.0)) {
        colour = vec4(0.0);
        return;
    }
    float d = texelFetch(depth, pixel, 0).r;
    d = (isinf(d) || isnan(d)) ? 0.0 : d;
    vec3 p = vec3((float(pixel.x) + (origin.x + 0.5 - lens.z)) / lens.x * d,
                  ((lens.w - origin.y - 0.5) - float(pixel.y)) / lens.y * d,
                  -d);
    vec3 n = texelFetch(normal, pixel, 0).xyz;
    vec3 view = p * (-1.0 / max(sqrt(dot(p, p)), MIN_DISTANCE));
    vec3 diffuse = vec3(0.0), specular = vec3(0.0);
    for (int i = 0; i < count; ++i) {
        if (kind[i] == 0) {
            diffuse += radiance[i];
            continue;
        }
        float strength;
        vec3 half_vector;
        if (kind[i] == 1) {
            strength = max(dot(vector[i], n), 0.0);
            half_vector = view + vector[i];
        } else {
            vec3 to_light = vector[i] - p;
            float distance2 = max(dot(to_light, to_light), MIN_DISTANCE * MIN_DISTANCE);
            to_light *= 1.0 / sqrt(distance2);
            strength = max(dot(n, to_light), 0.0) * (area[i] / distance2);
            half_vector = to_light + view;
        }
        if (layer[i] >= 0)
            strength *= texelFetch(shadow, ivec3(pixel, layer[i]), 0).r;
        diffuse += radiance[i] * strength;
        half_vector *= 1.0 / max(sqrt(dot(half_vector, half_vector)), MIN_DISTANCE);
        float highlight = max(dot(n, half_vector), 0.0);
        for (int k = 0; k < SQUARINGS; ++k)
            highlight *= highlight;
        specular += radiance[i] * (strength * highlight);
    }
    vec3 a = texelFetch(albedo, pixel, 0).rgb;
    colour = vec4(a * diffuse + (SPECULAR * coverage) * specular, 1.0);
}
"""


def _squarings() -> int:
    """How many squarings raise a highlight to SHININESS (a power of two, as shading.py's)."""
    exponent = int(SHININESS)
    if SHININESS != exponent or exponent.bit_count() != 1:
        raise ValueError(f"the shader raises to powers of two only, not SHININESS={SHININESS}")
    return exponent.bit_length() - 1


def open_gl_shading(
    renderer: RendererSpec, where: str, shared: SharedContext | None = None
) -> GLShading | None:
    """The shader an Engine drawing with `renderer` lights with, per `where` (GL_LIGHTING);
    None: numpy (shading.shade). A software rasteriser (`cost_grows_with_triangles`) counts
    as no GPU; no EGL context is made unless the shader will be used. `shared`: the
    context it draws in (the engine's, its renderer's too; None: one of its own)."""
    if where not in GL_LIGHTING:
        raise ValueError(f"gl_lighting {where!r} is not one of {GL_LIGHTING}")
    if where == "never" or renderer.name != "gl" or renderer.unavailable() is not None:
        return None
    if where == "hardware" and renderer.cost_grows_with_triangles():
        return None
    return GLShading(shared)


class GLShading:
    """The shading program in an EGL context (shared with the engine's renderer, or its own),
    and one set of textures grown to the largest region lit so far (a frame's full-screen
    prims, its characters' layers)."""

    def __init__(self, shared: SharedContext | None = None) -> None:
        self._shared = share(shared)
        self._ctx = self._shared.acquire()
        with self._ctx:
            self.renderer = str(self._ctx.info["GL_RENDERER"])
        """What draws: a GPU's name, or Mesa's "llvmpipe (LLVM ...)" on the CPU."""
        self.name = self.renderer
        """What lights (runtime/lighting.py's Lighting): the GL_RENDERER."""
        source = _FRAGMENT % {
            "max_lights": MAX_LIGHTS,
            "squarings": _squarings(),
            "specular": SPECULAR,
            "min_distance": MIN_DISTANCE,
        }
        self._program: Any
        with self._ctx:
            self._program = self._ctx.program(
                vertex_shader=FULL_SCREEN_VERTEX_SHADER, fragment_shader=source
            )
            self._vao = self._ctx.vertex_array(self._program, [])
        self._targets: dict[str, Any] = {}
        self._size = (0, 0, 0)
        """(width, height, shadow layers) the textures hold."""

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
        """shading.shade's lit, premultiplied colour (H, W, 3), computed by the GPU."""
        h, w = mask.shape
        if h == 0 or w == 0 or not lights:
            return np.zeros((h, w, 3), np.float32)
        shadowed, layers = shadow_layers(visibility, len(lights))
        with self._ctx:
            textures = self._textures(w, h, max(len(shadowed), 1))
            corner = (0, 0, w, h)
            for name, array in (("albedo", albedo), ("normal", normal), ("depth", depth),
                                ("mask", mask)):  # fmt: skip
                textures[name].write(np.ascontiguousarray(array, np.float32), viewport=corner)
            if shadowed:
                stacked = np.ascontiguousarray(np.stack(shadowed), np.float32)
                textures["shadow"].write(stacked, viewport=(0, 0, 0, w, h, len(shadowed)))
            uniforms = light_uniforms(lights, camera)
            out = np.zeros((h, w, 3), np.float32)
            for first in range(0, len(lights), MAX_LIGHTS):
                batch = slice(first, first + MAX_LIGHTS)
                out += self._draw(textures, camera, origin, uniforms[batch], layers[batch], w, h)
        return out

    def _draw(self, textures, camera: Camera, origin, uniforms, layers, w: int, h: int):
        program = self._program
        for unit, name in enumerate(("albedo", "normal", "depth", "mask", "shadow")):
            textures[name].use(unit)
            program[name].value = unit
        program["origin"].value = (float(origin[0]), float(origin[1]))
        program["lens"].value = (camera.fx, camera.fy, camera.cx, camera.cy)
        count = len(uniforms)
        program["count"].value = count
        pad = MAX_LIGHTS - count
        kinds = np.array([u[0] for u in uniforms] + [0] * pad, np.int32)
        radiance = np.zeros((MAX_LIGHTS, 3), np.float32)
        vectors = np.zeros((MAX_LIGHTS, 3), np.float32)
        areas = np.zeros(MAX_LIGHTS, np.float32)
        for i, (_, r, v, a) in enumerate(uniforms):
            radiance[i], vectors[i], areas[i] = r, v, a
        program["kind"].write(kinds.tobytes())
        program["radiance"].write(radiance.tobytes())
        program["vector"].write(vectors.tobytes())
        if "area" in program:  # the compiler drops it where no point light could read it
            program["area"].write(areas.tobytes())
        program["layer"].write(np.array(list(layers) + [-1] * pad, np.int32).tobytes())
        fbo = textures["fbo"]
        fbo.use()
        fbo.viewport = (0, 0, w, h)
        self._vao.render(vertices=3)
        data = fbo.read(viewport=(0, 0, w, h), components=3, dtype="f4")
        return np.frombuffer(data, np.float32).reshape(h, w, 3)

    def _textures(self, w: int, h: int, layers: int) -> dict[str, Any]:
        """The textures and target, grown (never shrunk) to hold a w x h region and `layers`
        shadow layers: regions are written into and read from their lower-left w x h corner,
        so a character whose layer changes size every frame allocates nothing."""
        size = self._size
        if w > size[0] or h > size[1] or layers > size[2]:
            # Room for some growth at once: a character walking closer grows a little a frame.
            grown = (max(w, size[0], int(w * GROWTH)), max(h, size[1], int(h * GROWTH)),
                     max(layers, size[2]))  # fmt: skip
            if self._targets:
                _release(self._targets)
            self._targets = self._allocate(*grown)
            self._size = grown
        return self._targets

    def _allocate(self, w: int, h: int, layers: int) -> dict[str, Any]:
        ctx = self._ctx
        target = ctx.texture((w, h), 4, dtype="f4")
        textures: dict[str, Any] = {
            "albedo": ctx.texture((w, h), 3, dtype="f4"),
            "normal": ctx.texture((w, h), 3, dtype="f4"),
            "depth": ctx.texture((w, h), 1, dtype="f4"),
            "mask": ctx.texture((w, h), 1, dtype="f4"),
            "shadow": ctx.texture_array((w, h, layers), 1, dtype="f4"),
            "target": target,
            "fbo": ctx.framebuffer(color_attachments=[target]),
        }
        for name in ("albedo", "normal", "depth", "mask", "shadow"):
            textures[name].filter = (ctx.NEAREST, ctx.NEAREST)  # read by texelFetch only
        return textures

    def close(self) -> None:
        if self._ctx is None:  # closed already
            return
        with self._ctx:
            if self._targets:
                _release(self._targets)
            self._targets = {}
            self._vao.release()
            self._program.release()
        self._shared.release()
        self._ctx = None


def _release(textures: dict[str, Any]) -> None:
    for name in ("fbo", "target", "albedo", "normal", "depth", "mask", "shadow"):
        textures[name].release()

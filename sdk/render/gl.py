"""The gl renderer: moderngl rasterisation on an EGL context (Mesa llvmpipe where there is no GPU)."""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigspace.sdk.camera import Camera
from rigspace.sdk.render import (
    DrawMesh,
    Maps,
    MeshArrays,
    RendererSpec,
    RenderSettings,
    depth_arrays,
    empty_maps,
    maps_from_samples,
    mesh_arrays,
)

GL_VERSION = 330
"""OpenGL 3.3 core: float render targets, multiple draw buffers, float texture filtering."""

VERTEX_SHADER = """
#version 330 core
uniform mat4 world_to_camera;
uniform mat4 projection;
uniform mat3 normal_to_camera;  // inverse-transpose of world_to_camera's 3x3 block
in vec3 in_position;
in vec3 in_normal;
in vec3 in_color;
in vec2 in_uv;
in float in_chart;
out vec3 v_normal;
out vec3 v_color;
out vec2 v_uv;
out float v_depth;
flat out float v_chart;  // one chart per triangle: weld_corners keeps a vertex per chart
void main() {
    vec4 p = world_to_camera * vec4(in_position, 1.0);
    v_depth = -p.z;  // distance along -Z; perspective-correct interpolation keeps it exact
    v_normal = normal_to_camera * in_normal;
    v_color = in_color;
    v_uv = in_uv;
    v_chart = in_chart;
    gl_Position = projection * p;
}
"""

FRAGMENT_SHADER = """
#version 330 core
uniform bool use_texture;
uniform sampler2D albedo_texture;
uniform vec2 uv_scale;   // st * uv_scale + uv_offset reads the texture (a UDIM atlas)
uniform vec2 uv_offset;
uniform ivec2 wrap;      // per axis: 0 repeat, 1 mirror, 2 clamp, 3 black (sdk.geometry)
in vec3 v_normal;
in vec3 v_color;
in vec2 v_uv;
in float v_depth;
flat in float v_chart;
layout(location = 0) out vec4 out_albedo;    // rgb albedo, a = 1: this sample is covered
layout(location = 1) out vec4 out_geometry;  // xyz camera-space normal, w depth along -Z
layout(location = 2) out vec4 out_surface;   // uv (USD st), texture chart (0: none), 1
// The texture's hardware wrap is REPEAT for repeat and CLAMP_TO_EDGE otherwise: mirror folds
// the coordinate into [0, 1] first, black is zero outside [0, 1].
float fold(float x, int mode) {
    if (mode != 1) return x;
    float m = mod(x, 2.0);
    return m > 1.0 ? 2.0 - m : m;
}
vec3 albedo_at(vec2 uv) {
    vec2 st = uv * uv_scale + uv_offset;
    bool outside = (wrap.x == 3 && (st.x < 0.0 || st.x > 1.0))
        || (wrap.y == 3 && (st.y < 0.0 || st.y > 1.0));
    return outside ? vec3(0.0) : texture(albedo_texture, vec2(fold(st.x, wrap.x), fold(st.y, wrap.y))).rgb;
}
void main() {
    out_albedo = vec4(use_texture ? albedo_at(v_uv) : v_color, 1.0);
    float len = length(v_normal);
    out_geometry = vec4(len > 0.0 ? v_normal / len : vec3(0.0), v_depth);
    out_surface = vec4(v_chart > 0.0 ? v_uv : vec2(0.0), v_chart, 1.0);
}
"""

DEPTH_VERTEX_SHADER = """
#version 330 core
uniform mat4 world_to_camera;
uniform mat4 projection;
in vec3 in_position;
out float v_depth;
void main() {
    vec4 p = world_to_camera * vec4(in_position, 1.0);
    v_depth = -p.z;
    gl_Position = projection * p;
}
"""

DEPTH_FRAGMENT_SHADER = """
#version 330 core
in float v_depth;
out float out_depth;  // distance along -Z; the target is cleared to 0 where nothing is
void main() {
    out_depth = v_depth;
}
"""

FULL_SCREEN_VERTEX_SHADER = """
#version 330 core
void main() {  // one triangle over the whole viewport, no vertex buffer
    vec2 corner = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
    gl_Position = vec4(corner, 0.0, 1.0);
}
"""

RESOLVE_FRAGMENT_SHADER = """
#version 330 core
#define S %(samples)d
uniform sampler2D albedo_fine;    // the supersampled targets above
uniform sampler2D geometry_fine;
uniform sampler2D surface_fine;
uniform bool charted;
layout(location = 0) out vec4 out_albedo;    // rgb mean albedo, a coverage
layout(location = 1) out vec4 out_geometry;  // the nearest sample's normal and depth (inf: none)
layout(location = 2) out vec4 out_surface;   // uv mean over the nearest's chart, its chart
// maps_from_samples, per pixel and in its order: sub-sample (a, b) of pixel (i, j) counted
// from the top-left is fine pixel (i*S + a, j*S + b), and GL's rows run bottom-up.
void main() {
    ivec2 pixel = ivec2(gl_FragCoord.xy);
    vec3 albedo = vec3(0.0);
    float hits = 0.0;
    float nearest = uintBitsToFloat(0x7f800000u);  // +inf
    ivec2 at = ivec2(pixel.x * S, pixel.y * S + S - 1);
    for (int a = 0; a < S; ++a) {
        for (int b = 0; b < S; ++b) {
            ivec2 q = ivec2(pixel.x * S + b, pixel.y * S + S - 1 - a);
            vec4 c = texelFetch(albedo_fine, q, 0);
            albedo += c.rgb;
            if (c.a > 0.0) {
                hits += 1.0;
                float d = texelFetch(geometry_fine, q, 0).w;
                if (d < nearest) {  // the first of equal depths, as argmin
                    nearest = d;
                    at = q;
                }
            }
        }
    }
    bool hit = hits > 0.0;
    out_albedo = vec4(albedo / float(S * S), hits / float(S * S));
    out_geometry = vec4(hit ? texelFetch(geometry_fine, at, 0).xyz : vec3(0.0), nearest);
    out_surface = vec4(0.0);
    if (!charted || !hit)
        return;
    float chart = floor(texelFetch(surface_fine, at, 0).z + 0.5);
    vec2 total = vec2(0.0);
    float count = 0.0;
    for (int a = 0; a < S; ++a) {
        for (int b = 0; b < S; ++b) {
            ivec2 q = ivec2(pixel.x * S + b, pixel.y * S + S - 1 - a);
            vec4 surface = texelFetch(surface_fine, q, 0);
            bool same = texelFetch(albedo_fine, q, 0).a > 0.0 && floor(surface.z + 0.5) == chart;
            if (same && chart > 0.0) {
                total += surface.xy;
                count += 1.0;
            }
        }
    }
    out_surface = vec4(total / max(count, 1.0), chart, 0.0);
}
"""

DEPTH_SLOT_IDLE = 16
"""render_depth keeps a mesh's buffers until this many depth calls have not drawn it: the
shadow maps draw one moving prim per call, so each call's meshes differ from the last's."""

INSTALL_HINT = (
    "install Mesa's EGL and software rasteriser (Debian/Ubuntu: apt install libegl1 "
    "libgl1-mesa-dri), or use the embree renderer"
)


def _context() -> Any:
    import moderngl

    # moderngl's stub types `backend` as a dict; its documented use is the string "egl".
    return moderngl.create_standalone_context(backend="egl", require=GL_VERSION)  # type: ignore[arg-type]


class SharedContext:
    """One EGL context for several users: an Engine's renderers (the prims', the shadow maps',
    the reference meshes'), its lighting (runtime/gl_shading.py) and its capsule shadows
    (runtime/shadows/gl.py). Each user `acquire`s it and `release`s it when closed; the last
    release frees it. Each makes it current around its calls (`with ctx:`) and sets the
    state it draws with (program, textures, framebuffer, viewport, depth test) every time:
    what one leaves bound does not change what the next draws."""

    def __init__(self) -> None:
        self._ctx: Any = _context()
        with self._ctx:  # moderngl reads `info` once, from the context current then
            self._ctx.info  # noqa: B018
        self._users = 0

    def acquire(self) -> Any:
        """The moderngl context, counted as used until `release`."""
        if self._ctx is None:
            raise RuntimeError("the shared GL context was released by its last user")
        self._users += 1
        return self._ctx

    def release(self) -> None:
        self._users -= 1
        if self._users == 0:
            self._ctx.release()
            self._ctx = None


def share(settings_shared: Any) -> SharedContext:
    """The SharedContext a GL user draws in: the one given, else one of its own."""
    return settings_shared if isinstance(settings_shared, SharedContext) else SharedContext()


@functools.cache
def unavailable() -> str | None:
    """None when an EGL context can be created here, else why not (probed once per process)."""
    try:
        import moderngl  # noqa: F401
    except ImportError as exc:
        return f"moderngl could not be imported: {exc}; pip install moderngl"
    try:
        ctx = _context()
    except Exception as exc:  # any backend failure means "not here"; keep the original message
        return f"EGL could not create a context: {type(exc).__name__}: {exc}; {INSTALL_HINT}"
    ctx.release()
    return None


SOFTWARE_RASTERISERS = ("llvmpipe", "softpipe", "swrast", "lavapipe")


@functools.cache
def software() -> bool:
    """True when this machine's GL is a CPU rasteriser (Mesa llvmpipe): its cost grows with the
    triangles drawn, ~0.11 us each on one core here, however few pixels they cover."""
    if unavailable() is not None:
        return False
    ctx = _context()
    try:
        name = str(ctx.info.get("GL_RENDERER", "")).lower()
    finally:
        ctx.release()
    return any(s in name for s in SOFTWARE_RASTERISERS)


def _mat(m: np.ndarray) -> bytes:
    """A numpy (column-vector, row-major storage) matrix as GLSL's column-major float32 bytes."""
    return np.ascontiguousarray(m.T, dtype=np.float32).tobytes()


@dataclass
class _Slot:
    """GPU state of one drawn mesh, kept across calls while its topology and look stay the same."""

    remap: np.ndarray | None  # (V,) source vertex of each GPU vertex; None: the same vertices
    buffers: dict[str, Any]  # attribute name -> moderngl Buffer
    vao: Any
    texture: Any  # moderngl Texture or None
    refs: tuple  # the cached source arrays, held so their ids cannot be reused

    def release(self) -> None:
        self.vao.release()
        for b in self.buffers.values():
            b.release()
        if self.texture is not None:
            self.texture.release()


def weld_corners(
    triangles: np.ndarray, corner_uv: np.ndarray, chart: np.ndarray | None = None
) -> tuple[np.ndarray, ...]:
    """GPU vertices for faceVarying uv: one per distinct (vertex, uv, chart), found vectorised.

    Returns remap (V,) source vertex per GPU vertex, uv (V,2), index (T,3) into the GPU
    vertices and the chart (V,) of each GPU vertex (zeros without `chart`, (T,) per triangle).
    Only corners on a uv seam or chart border are duplicated, so an indexed draw shades about
    as few vertices as the mesh has (de-indexing every corner measured ~1 ms slower at 20k
    triangles); every vertex of a triangle has the triangle's chart, so a flat varying is exact.
    """
    corners = triangles.reshape(-1).astype(np.uint64)
    uv = np.ascontiguousarray(corner_uv, dtype=np.float32).reshape(-1, 2)
    uv_bits = uv.view(np.uint64)[:, 0]  # both float32 halves of the uv as one exact key
    charts = (
        np.zeros(len(corners), np.uint64)
        if chart is None
        else np.repeat(np.asarray(chart, np.int64), 3).astype(np.uint64)
    )
    _, first, inverse = np.unique(
        np.stack([corners, uv_bits, charts], axis=1),
        axis=0,
        return_index=True,
        return_inverse=True,
    )
    return (
        corners[first].astype(np.intp),
        uv[first],
        inverse.reshape(-1, 3).astype(np.int32),
        charts[first].astype(np.float32),
    )


def _static_key(mesh: DrawMesh) -> tuple:
    """Identity of what a slot caches (see DrawMesh: these are cached by array identity)."""
    parts = (mesh.triangles, mesh.corner_uv, mesh.texture, mesh.color, mesh.chart)
    look = (tuple(mesh.wrap), tuple(mesh.uv_scale), tuple(mesh.uv_offset))
    shapes = tuple(np.shape(p) if p is not None else None for p in parts)
    return (*(id(p) for p in parts), shapes, look)


RESOLVES = ("auto", "gpu", "numpy")


class GLRenderer:
    """Rasterises meshes with moderngl into supersampled float32 targets, reduced to pixels
    by a fragment shader (maps_from_samples' rules: tested equal to it)."""

    name = "gl"

    def __init__(self, settings: RenderSettings, resolve: str = "auto") -> None:
        """`resolve`: where the supersamples become pixels: "gpu", a pass that reads back a
        quarter of the data at 2x2 (1920x1080 on llvmpipe: 106 ms against numpy's 224 ms),
        or "numpy", maps_from_samples over the samples read back (the reference). "auto":
        the pass, but for one sample per pixel on a software rasteriser, where there is
        nothing to average and the read-back, unpacked in one compiled pass
        (unpack_kernel.py, maps_from_samples' rules), costs less than another draw."""
        import moderngl

        if resolve not in RESOLVES:
            raise ValueError(f"resolve {resolve!r} is not one of {RESOLVES}")
        if resolve == "auto":
            resolve = "numpy" if settings.samples_per_axis == 1 and software() else "gpu"
        self.resolve = resolve
        self.settings = settings
        self._gl = moderngl
        self._shared = share(settings.shared)
        self._ctx = self._shared.acquire()
        with self._ctx:
            self._program = self._ctx.program(
                vertex_shader=VERTEX_SHADER, fragment_shader=FRAGMENT_SHADER
            )
            self._program["albedo_texture"].value = 0
            self._depth_program = self._ctx.program(
                vertex_shader=DEPTH_VERTEX_SHADER, fragment_shader=DEPTH_FRAGMENT_SHADER
            )
        self._resolve_program: Any = None
        self._resolve_vao: Any = None
        self._resolved: Any = None
        """The resolve pass's framebuffer and targets at the frame's size, and its read-back."""
        self._resolved_targets: list[Any] = []
        self._resolved_size: tuple[int, int, int] = (0, 0, 0)
        self._coarse = np.empty((2, 0, 0, 4), np.float32)
        self._slots: dict[tuple, _Slot] = {}
        self._depth_slots: dict[tuple, tuple[Any, Any, Any, tuple, int]] = {}
        """render_depth's: key -> (position buffer, index buffer, vao, source refs, last call)."""
        self._depth_calls = 0
        self._depth_fbo: Any = None
        self._depth_targets: list[Any] = []
        self._depth_size: tuple[int, int] = (0, 0)
        self._fbo: Any = None
        self._targets: list[Any] = []
        self._fine_size: tuple[int, int, int] = (0, 0, 0)
        """(width, height, colour targets) of the framebuffer: 3 with the surface target."""
        self._fine = np.empty((2, 0, 0, 4), np.float32)
        self.last_timings: dict[str, float] = {}
        """Seconds of the last render: draw (upload, rasterise) and readback (read, reduce)."""

    # --- resources ------------------------------------------------------------------------------
    def _framebuffer(self, width: int, height: int, charted: bool) -> Any:
        """The supersampled framebuffer: albedo and geometry targets, and the surface target
        (uv, chart) only while charted meshes are drawn (the runtime's prims never are)."""
        count = 3 if charted else 2
        if self._fine_size != (width, height, count):
            limit = min(
                self._ctx.info["GL_MAX_RENDERBUFFER_SIZE"], self._ctx.info["GL_MAX_TEXTURE_SIZE"]
            )
            if max(width, height) > limit:
                raise ValueError(
                    f"gl renderer: the supersampled image {width}x{height} exceeds this GL's "
                    f"limit {limit}; lower the resolution or samples_per_axis."
                )
            self._release_framebuffer()
            # albedo, geometry, surface (uv and chart: read back only when a mesh has charts),
            # textures that the resolve pass reads
            self._targets = [
                self._ctx.texture((width, height), 4, dtype="f4") for _ in range(count)
            ]
            for target in self._targets:
                target.filter = (self._gl.NEAREST, self._gl.NEAREST)
            depth = self._ctx.depth_renderbuffer((width, height))
            self._fbo = self._ctx.framebuffer(self._targets, depth)
            self._targets.append(depth)
            self._fine_size = (width, height, count)
            # Read-back memory, reused: maps_from_samples copies what it keeps.
            shape = (count, height, width, 4) if self.resolve == "numpy" else (count, 0, 0, 4)
            self._fine = np.empty(shape, np.float32)
        return self._fbo

    def _resolve_framebuffer(self, width: int, height: int, count: int) -> Any:
        """The pixel-sized targets the resolve pass writes, and its program."""
        if self._resolve_program is None:
            source = RESOLVE_FRAGMENT_SHADER % {"samples": self.settings.samples_per_axis}
            self._resolve_program = self._ctx.program(
                vertex_shader=FULL_SCREEN_VERTEX_SHADER, fragment_shader=source
            )
            self._resolve_vao = self._ctx.vertex_array(self._resolve_program, [])
        if self._resolved_size != (width, height, count):
            self._release_resolved()
            self._resolved_targets = [
                self._ctx.renderbuffer((width, height), 4, dtype="f4") for _ in range(count)
            ]
            self._resolved = self._ctx.framebuffer(self._resolved_targets)
            self._resolved_size = (width, height, count)
            self._coarse = np.empty((count, height, width, 4), np.float32)
        return self._resolved

    def _release_resolved(self) -> None:
        if self._resolved is not None:
            self._resolved.release()
            for target in self._resolved_targets:
                target.release()
        self._resolved, self._resolved_targets, self._resolved_size = None, [], (0, 0, 0)

    def _release_framebuffer(self) -> None:
        if self._fbo is not None:
            self._fbo.release()
            for t in self._targets:
                t.release()
        self._fbo, self._targets, self._fine_size = None, [], (0, 0, 0)

    def _slot(self, key: tuple, mesh: DrawMesh, arrays: MeshArrays) -> _Slot:
        slot = self._slots.get(key)
        if slot is not None:
            return slot
        n = len(arrays.points)
        if arrays.corner_uv is None:
            remap, index = None, arrays.triangles
            uv = np.zeros((n, 2), np.float32)
            chart = np.zeros(n, np.float32)
        else:
            remap, uv, index, chart = weld_corners(arrays.triangles, arrays.corner_uv, arrays.chart)
        count = n if remap is None else len(remap)
        if arrays.color.ndim == 1:
            colors = np.broadcast_to(arrays.color, (count, 3))
        else:
            colors = arrays.color if remap is None else arrays.color[remap]
        ctx = self._ctx
        buffers = {
            "in_position": ctx.buffer(reserve=count * 12, dynamic=True),
            "in_normal": ctx.buffer(reserve=count * 12, dynamic=True),
            "in_color": ctx.buffer(np.ascontiguousarray(colors, np.float32).tobytes()),
            "in_uv": ctx.buffer(np.ascontiguousarray(uv, np.float32).tobytes()),
            "in_chart": ctx.buffer(np.ascontiguousarray(chart, np.float32).tobytes()),
            "index": ctx.buffer(np.ascontiguousarray(index, np.int32).tobytes()),
        }
        fmt = {
            "in_position": "3f",
            "in_normal": "3f",
            "in_color": "3f",
            "in_uv": "2f",
            "in_chart": "1f",
        }
        vao = ctx.vertex_array(
            self._program,
            [(buffers[a], fmt[a], a) for a in fmt],
            index_buffer=buffers["index"],
            index_element_size=4,
        )
        texture = None
        if arrays.texture is not None:
            h, w = arrays.texture.shape[:2]
            # USD st has v = 0 at the image's BOTTOM row while GL's t = 0 is the first row
            # uploaded: upload bottom row first so st addresses the texture unchanged.
            data = np.ascontiguousarray(arrays.texture[::-1]).tobytes()
            texture = ctx.texture((w, h), 3, data, dtype="f4", alignment=4)
            texture.repeat_x, texture.repeat_y = arrays.wrap[0] == 0, arrays.wrap[1] == 0
            texture.filter = (self._gl.LINEAR, self._gl.LINEAR)  # bilinear, no mipmaps
        refs = (mesh.triangles, mesh.corner_uv, mesh.texture, mesh.color, mesh.chart)
        slot = _Slot(remap, buffers, vao, texture, refs)
        self._slots[key] = slot
        return slot

    # --- drawing --------------------------------------------------------------------------------
    def render(self, meshes: Sequence[DrawMesh], camera: Camera) -> Maps:
        if self._ctx is None:
            raise RuntimeError("gl renderer: render() after close().")
        started = time.perf_counter()
        s = self.settings.samples_per_axis
        width, height = camera.width * s, camera.height * s
        prepared = [(m, mesh_arrays(m)) for m in meshes]
        prepared = [(m, a) for m, a in prepared if len(a.triangles)]
        if not prepared:
            return empty_maps(camera.height, camera.width)
        charted = any(a.chart is not None for _, a in prepared)
        with self._ctx:
            fbo = self._framebuffer(width, height, charted)
            fbo.use()
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            self._ctx.enable(self._gl.DEPTH_TEST)
            self._ctx.disable(self._gl.CULL_FACE | self._gl.BLEND)
            self._use_camera(camera)
            self._draw(prepared)
            self._ctx.finish()  # GL is asynchronous: wait here so the timings split honestly
            drawn = time.perf_counter()
            if self.resolve == "gpu":
                maps = self._resolve(camera, charted)
                self.last_timings = {
                    "draw": drawn - started,
                    "readback": time.perf_counter() - drawn,
                }
                return maps
            fine = self._fine
            fbo.read_into(fine[0], components=4, attachment=0, dtype="f4")
            fbo.read_into(fine[1], components=4, attachment=1, dtype="f4")
            if charted:
                fbo.read_into(fine[2], components=4, attachment=2, dtype="f4")
        maps = _maps_from_fine(fine, s, charted)
        self.last_timings = {"draw": drawn - started, "readback": time.perf_counter() - drawn}
        return maps

    def _use_camera(self, camera: Camera) -> None:
        """The program's camera uniforms: world to camera, projection, and normals' transform."""
        w2c = camera.world_to_camera
        self._program["world_to_camera"].write(_mat(w2c))
        self._program["projection"].write(_mat(camera.gl_projection))
        normal_to_camera = np.linalg.inv(w2c[:3, :3]).T
        self._program["normal_to_camera"].write(_mat(normal_to_camera))

    def _draw(self, prepared: list[tuple[DrawMesh, MeshArrays]]) -> None:
        """Draw each mesh into the bound framebuffer (inside the context), each from its slot,
        then release the slots this call did not draw."""
        used: set[tuple] = set()
        for mesh, arrays in prepared:
            key = _static_key(mesh)
            while key in used:  # the same topology drawn twice in one call needs two slots
                key = (*key, "again")
            used.add(key)
            slot = self._slot(key, mesh, arrays)
            points, normals = arrays.points, arrays.normals
            if slot.remap is not None:
                points, normals = points[slot.remap], normals[slot.remap]
            slot.buffers["in_position"].write(points)
            slot.buffers["in_normal"].write(normals)
            self._program["use_texture"].value = slot.texture is not None
            if slot.texture is not None:
                slot.texture.use(0)
                self._program["uv_scale"].value = arrays.uv_scale
                self._program["uv_offset"].value = arrays.uv_offset
                self._program["wrap"].value = arrays.wrap
            slot.vao.render(self._gl.TRIANGLES)
        # Slots not drawn this call are released so changing scenes do not grow GPU memory.
        for key in [k for k in self._slots if k not in used]:
            self._slots.pop(key).release()

    def _resolve(self, camera: Camera, charted: bool) -> Maps:
        """The drawn supersamples reduced to pixels by the resolve pass and read back (inside
        the context)."""
        count = 3 if charted else 2
        fbo = self._resolve_framebuffer(camera.width, camera.height, count)
        fbo.use()
        fbo.viewport = (0, 0, camera.width, camera.height)
        program = self._resolve_program
        for unit, name in enumerate(("albedo_fine", "geometry_fine", "surface_fine")[:count]):
            self._targets[unit].use(unit)
            program[name].value = unit
        if "charted" in program:
            program["charted"].value = charted
        if "surface_fine" in program and not charted:
            self._targets[0].use(2)  # bound to something; not read
            program["surface_fine"].value = 2
        self._resolve_vao.render(vertices=3)
        coarse = self._coarse
        for k in range(count):
            fbo.read_into(coarse[k], components=4, attachment=k, dtype="f4")
        # GL's rows run bottom-up: flip so row 0 is the top (copies: Maps own their arrays).
        albedo, geometry = coarse[0, ::-1], coarse[1, ::-1]
        maps = Maps(
            np.ascontiguousarray(albedo[..., :3]),
            np.ascontiguousarray(geometry[..., :3]),
            np.ascontiguousarray(geometry[..., 3]),
            np.ascontiguousarray(albedo[..., 3]),
        )
        if charted:
            surface = coarse[2, ::-1]
            maps.uv = np.ascontiguousarray(surface[..., :2])
            maps.chart = np.rint(surface[..., 2]).astype(np.int32)
        return maps

    def render_depth(self, meshes: Sequence[DrawMesh], camera: Camera) -> np.ndarray:
        """(H, W) float32 depth along -Z, +inf where empty, one sample per pixel centre: the
        depth map of render() at one sample, drawn without colour or normals (shadow maps)."""
        if self._ctx is None:
            raise RuntimeError("gl renderer: render_depth() after close().")
        started = time.perf_counter()
        arrays = [depth_arrays(m) for m in meshes]
        arrays = [(m, p, t) for m, (p, t) in zip(meshes, arrays, strict=True) if len(t)]
        width, height = camera.width, camera.height
        if not arrays:
            return np.full((height, width), np.inf, np.float32)
        self._depth_calls += 1
        with self._ctx:
            if self._depth_size != (width, height):
                self._release_depth_framebuffer()
                self._depth_targets = [
                    self._ctx.renderbuffer((width, height), 1, dtype="f4"),
                    self._ctx.depth_renderbuffer((width, height)),
                ]
                self._depth_fbo = self._ctx.framebuffer(*self._depth_targets)
                self._depth_size = (width, height)
            fbo = self._depth_fbo
            fbo.use()
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            self._ctx.enable(self._gl.DEPTH_TEST)
            self._ctx.disable(self._gl.CULL_FACE | self._gl.BLEND)
            self._depth_program["world_to_camera"].write(_mat(camera.world_to_camera))
            self._depth_program["projection"].write(_mat(camera.gl_projection))
            used: set[tuple] = set()
            for mesh, points, triangles in arrays:
                key: tuple = (id(mesh.triangles), triangles.shape, len(points))
                while key in used:
                    key = (*key, "again")
                used.add(key)
                slot = self._depth_slots.get(key)
                if slot is None:
                    position = self._ctx.buffer(reserve=len(points) * 12, dynamic=True)
                    index = self._ctx.buffer(triangles.tobytes())
                    vao = self._ctx.vertex_array(
                        self._depth_program, [(position, "3f", "in_position")],
                        index_buffer=index, index_element_size=4,
                    )  # fmt: skip
                    slot = (position, index, vao, (mesh.triangles,), 0)
                self._depth_slots[key] = slot = (*slot[:4], self._depth_calls)
                slot[0].write(points)
                slot[2].render(self._gl.TRIANGLES)
            for key, slot in list(self._depth_slots.items()):
                if self._depth_calls - slot[4] >= DEPTH_SLOT_IDLE:
                    for resource in slot[2::-1]:
                        resource.release()
                    del self._depth_slots[key]
            depth = np.empty((height, width), np.float32)
            fbo.read_into(depth, components=1, attachment=0, dtype="f4")
        self.last_timings = {"draw": time.perf_counter() - started, "readback": 0.0}
        # GL's rows run bottom-up; a cleared (0) texel is empty: depths lie beyond near > 0.
        depth = depth[::-1]
        return np.where(depth > 0, depth, np.float32(np.inf))

    def _release_depth_framebuffer(self) -> None:
        if self._depth_fbo is not None:
            self._depth_fbo.release()
            for target in self._depth_targets:
                target.release()
        self._depth_fbo, self._depth_targets, self._depth_size = None, [], (0, 0)

    def close(self) -> None:
        if self._ctx is None:
            return
        with self._ctx:
            for slot in self._slots.values():
                slot.release()
            self._slots.clear()
            for position, index, vao, _, _ in self._depth_slots.values():
                vao.release()
                index.release()
                position.release()
            self._depth_slots.clear()
            self._release_depth_framebuffer()
            self._release_framebuffer()
            self._release_resolved()
            if self._resolve_program is not None:
                self._resolve_vao.release()
                self._resolve_program.release()
            self._depth_program.release()
            self._program.release()
        self._shared.release()
        self._ctx = None

    def __enter__(self) -> GLRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


SPEC = RendererSpec(
    name="gl",
    description="moderngl rasterisation on EGL (GPU, or Mesa llvmpipe on the CPU)",
    create=GLRenderer,
    unavailable=unavailable,
    cost_grows_with_triangles=software,
)


def _maps_from_fine(fine: np.ndarray, s: int, charted: bool) -> Maps:
    """The supersamples read back (numpy resolve), `s` by `s` a pixel, reduced to pixels."""
    if s == 1:
        return _unpack_one_sample(fine, charted)
    # GL's rows run bottom-up: flip (a view) so row 0 is the top.
    albedo, geometry = fine[0, ::-1], fine[1, ::-1]
    surface = fine[2, ::-1] if charted else None
    return maps_from_samples(
        s,
        albedo[..., 3] > 0,
        albedo[..., :3],
        geometry[..., :3],
        geometry[..., 3],
        None if surface is None else surface[..., :2],
        None if surface is None else np.rint(surface[..., 2]).astype(np.int32),
    )


def _unpack_one_sample(fine: np.ndarray, charted: bool) -> Maps:
    """maps_from_samples at one sample per pixel over the read-back attachments (compiled)."""
    from rigspace.sdk.render.unpack_kernel import unpack, unpack_surface

    h, w = fine.shape[1:3]
    maps = Maps(
        np.empty((h, w, 3), np.float32),
        np.empty((h, w, 3), np.float32),
        np.empty((h, w), np.float32),
        np.empty((h, w), np.float32),
    )
    unpack(fine[0], fine[1], maps.albedo, maps.normal, maps.depth, maps.mask)
    if charted:
        maps.uv, maps.chart = np.empty((h, w, 2), np.float32), np.empty((h, w), np.int32)
        unpack_surface(fine[2], fine[0], maps.uv, maps.chart)
    return maps

"""Shadows: scene prims by shadow maps, neural characters by capsules (Unreal's capsule shadows).

- **Prims** cast through a shadow map per light: their depth seen from the light, drawn by
  the renderer plugin. A DistantLight's map is orthographic in effect: its camera sits
  DISTANT_RANGE bounding radii away with a matching telephoto lens (rays within 0.6 degrees
  of parallel, about the sun's own width). A point light's map is a perspective view from
  the light towards the casters, at most MAX_HALF_ANGLE off its axis; what lies outside is
  unshadowed. Prims that never move share one map (SHADOW_MAP_SIZE, drawn once while they
  and the light are still); each prim that moves gets a smaller one fitted to it alone
  (MOVING_MAP_SIZE, drawn when it moves), so a rolling ball does not redraw the set. A
  receiver is moved one texel along its normal and compared with 2x2 bilinear taps (soft
  1-texel edges). Lookups happen only in the screen rectangles where a prim's shadow can
  fall (its bounds swept away from the light to the scene's bounds; the ground, flat on
  the scene's boundary, casts onto nothing).
- **Characters** cast through capsules (sdk/capsules.py) posed by their joints: the
  fraction of the light's disc (its angular radius, at least MIN_SOFTNESS) that each capsule
  hides, seen from the receiver, multiplied over capsules. As in Unreal, the capsule becomes
  the sphere at its segment's point nearest the ray towards the light; the overlap of the
  two cones (light and sphere) is that of two discs, exact for small angles (Unreal's
  smoothstep estimate, ApproximateConeConeIntersection, came out up to 0.16 darker than ray
  casting in the test's penumbra; this is within 0.08, and within 0.013 at the penumbra). Only pixels in
  the screen rectangles of the limbs' shadow volumes are visited, and only the (pixel,
  capsule) pairs that lie close in the light's 2-D view (a capsule's shadow is a 2-D
  capsule there, widened by each pixel's penumbra) are computed. With a GPU behind the gl
  renderer the same maths runs in a fragment shader instead (shadows/gl.py, ShadowBackend).

Shadowing multiplies each light's contribution (diffuse and specular), never the ambient.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from rigspace.runtime.billboard import cross
from rigspace.runtime.lights import DISTANT, POINT, Light
from rigspace.runtime.shadows.gl import GLCapsuleShadows
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import DrawMesh, Renderer, RendererSpec, RenderSettings, render_depth
from rigspace.sdk.render.gl import SharedContext

SHADOW_MAP_SIZE = 512
"""Texels per side of the still prims' map (drawn once; 6 scene units a texel over the
previs scene's 30 m ground)."""
MOVING_MAP_SIZE = 128
"""Texels per side of a moving prim's own map (drawn whenever it moves; under a scene unit
a texel over the previs scene's 60-unit crate)."""
DISTANT_RANGE = 100.0
"""A DistantLight's map camera sits this many bounding radii from the casters."""
MAX_HALF_ANGLE = np.radians(60.0)
"""A point light's map covers at most this angle around its axis (a 120-degree frustum)."""
MIN_SOFTNESS = np.radians(3.0)
"""Capsule shadows see the light at least this wide (angular radius) from the character:
capsules are a coarse stand-in for the body, and a sharp capsule outline would show it;
Unreal softens its capsule shadows the same way. A DistantLight's angle is widened to it
(the sun's 0.27 degrees), a point light's radius to what subtends it at the character (a
lamp 15 units across, 400 away: 2.1 degrees), so it still shrinks with distance beyond."""
NORMAL_OFFSET_TEXELS = 1.0
"""Receivers move this many texels along their normal before the map lookup (acne)."""
DEPTH_BIAS_TEXELS = 1.5
"""And count as lit up to this many texels behind the map's depth."""
MIN_VISIBILITY = 1e-6
"""Capsule occlusions are summed as log(visibility): fully hidden stays finite."""
SPARSE_STEP = 4
"""sparse_visibility evaluates every SPARSE_STEP-th pixel along both axes (a power of two),
blends or evaluates the pixels between."""
BEND_TOLERANCE = 0.1
"""A cell where the shadow factor's second difference at a sample exceeds this (the factor
does not change linearly there: a shadow's edge, its end, a thin shadow) is evaluated, and
so are its neighbours; elsewhere a blend errs by about an eighth of it."""
GL_CAPSULE_CHOICES = ("hardware", "always", "never")
KERNELS = ("numba", "numpy")


@dataclass(frozen=True)
class ShadowBackend:
    """How an Engine computes shadows, chosen once per engine (no module state: a test or the
    shadow bench picks one by argument)."""

    kernel: str = "numba"
    """What computes the shadows where the fragment shader does not: "numba", the compiled
    kernels of shadows/kernels.py (one call per pass, shadows/passes.py), or "numpy", the engine's
    passes over this module's functions (the reference the kernels are tested against)."""
    gl_capsules: str = "hardware"
    """Where capsule occlusion runs in a fragment shader (shadows/gl.py) rather than on the
    CPU: "hardware" with the gl renderer on a GPU, "always" with the gl renderer (Mesa's
    llvmpipe too), "never". On llvmpipe, 2 shared cores, the shader measured no faster than
    numpy per frame (each draw hands its pixels to llvmpipe's threads and waits for them), so
    the CPU keeps it there; the numpy pairs are also the reference and the fallback (embree,
    no EGL)."""

    def __post_init__(self) -> None:
        if self.kernel not in KERNELS:
            raise ValueError(f"shadow kernel {self.kernel!r} is not one of {KERNELS}")
        if self.gl_capsules not in GL_CAPSULE_CHOICES:
            raise ValueError(f"gl_capsules {self.gl_capsules!r} is not one of {GL_CAPSULE_CHOICES}")


@dataclass(frozen=True)
class CompiledPasses:
    """The compiled kernels' entry points a PrimShadows calls instead of numpy (shadows.passes
    gives them: this module does not import it, which imports this one)."""

    points_visibility: Callable[..., np.ndarray]
    shadow_regions: Callable[..., list]


SOFTWARE_GL = ("llvmpipe", "softpipe", "swrast", "software")
"""GL_RENDERER strings (lower case) of a rasteriser on the CPU."""
SURFACE_TOLERANCE = 0.01
"""A pixel whose inverse depth is off its cell's blend by more than this fraction lies on
another surface (a silhouette, a crease) and is evaluated exactly."""


@dataclass
class ShadowMap:
    """The depth of some casters seen from a light."""

    camera: Camera
    depth: np.ndarray
    """(S, S) float32 distance along the map camera's -Z, +inf where no caster is."""

    def __post_init__(self) -> None:
        # A border of +inf: a lookup clamped into it finds no caster (lit), with no test.
        height, width = self.depth.shape
        self._padded = np.full((height + 2, width + 2), np.inf, np.float32)  # np.pad: 4x slower
        self._padded[1:-1, 1:-1] = self.depth
        self._m = self.camera.world_to_camera.astype(np.float32)

    @property
    def padded(self) -> np.ndarray:
        """(S + 2, S + 2) float32 depth with a border of +inf."""
        return self._padded

    def visibility(self, points: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
        """(N,) in [0, 1]: how much of the light reaches world `points` (planar (3, N)
        float32, as `normals`) past these casters."""
        cam, m = self.camera, self._m
        px, py, pz = points
        if normals is not None:  # one texel towards the outside: no self-shadowing acne
            depth0 = -(m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3])
            offset = np.maximum(depth0, 0.0) * np.float32(NORMAL_OFFSET_TEXELS / cam.fx)
            px, py, pz = (
                px + normals[0] * offset,
                py + normals[1] * offset,
                pz + normals[2] * offset,
            )
        d = -(m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3])
        inv = 1.0 / np.maximum(d, np.float32(cam.near))
        x = (m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]) * (np.float32(cam.fx) * inv)
        y = (m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]) * (np.float32(-cam.fy) * inv)
        size_y, size_x = self.depth.shape
        x = np.clip(x + np.float32(cam.cx + 0.5), 0.0, size_x)  # +1 - 0.5: padding, centres
        y = np.clip(y + np.float32(cam.cy + 0.5), 0.0, size_y)
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        width = size_x + 2
        index = y0.astype(np.int32) * width + x0.astype(np.int32)
        flat = self._padded.reshape(-1)
        limit = d - np.float32(DEPTH_BIAS_TEXELS / cam.fx) * d
        top = (flat[index] >= limit) * (1 - fx) + (flat[index + 1] >= limit) * fx
        bottom = (flat[index + width] >= limit) * (1 - fx) + (flat[index + width + 1] >= limit) * fx
        lit = top * (1 - fy) + bottom * fy
        # Behind the map's camera (a point light's back) nothing it drew can shadow.
        return np.where(d > cam.near, lit, np.float32(1.0)).astype(np.float32)


def _box(meshes: Sequence[DrawMesh]) -> np.ndarray:
    """(2, 3) axis-aligned bounds of the meshes' points."""
    lo = np.min([np.min(m.points, axis=0) for m in meshes], axis=0)
    hi = np.max([np.max(m.points, axis=0) for m in meshes], axis=0)
    return np.array([lo, hi], dtype=np.float64)


def _corners(box: np.ndarray) -> np.ndarray:
    """(8, 3) the corners of a (2, 3) box, x slowest."""
    return np.asarray(box)[_CORNER_PICK, np.arange(3)]


def _frame_axes(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors e1, e2 perpendicular to unit `w`, with e1 x e2 = w."""
    helper = np.array([0.0, 1.0, 0.0]) if abs(w[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = cross(helper, w)
    e1 /= np.linalg.norm(e1)
    return e1, cross(w, e1)


def _frame(forward: np.ndarray, position: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world looking along `forward` from `position`, rolled anyhow."""
    z = -forward / np.linalg.norm(forward)
    x, y = _frame_axes(z)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, position
    return m


def light_camera(light: Light, box: np.ndarray, size: int) -> Camera | None:
    """The camera a shadow map of casters within `box` is drawn with (None: none needed)."""
    corners = _corners(box)
    centre = corners.mean(axis=0)
    radius = float(np.linalg.norm(corners - centre, axis=1).max()) * 1.01 + 1e-3
    if light.kind == DISTANT:
        distance = DISTANT_RANGE * radius
        position = centre - light.direction * distance
        # A lens whose field at the centre's distance spans the bounding sphere.
        aperture = 2.0 * radius * distance / (distance - radius)
        return Camera(
            _frame(light.direction, position), size, size, distance, aperture, aperture,
            near=distance - radius, far=distance + radius,
        )  # fmt: skip
    if light.kind != POINT:
        return None
    to_corners = corners - light.position
    lengths = np.linalg.norm(to_corners, axis=1)
    axis = centre - light.position
    if np.linalg.norm(axis) < 1e-6 * radius:
        axis = np.array([0.0, -1.0, 0.0])  # a light at the casters' centre looks down
    axis /= np.linalg.norm(axis)
    cosines = (to_corners @ axis) / np.maximum(lengths, 1e-9)
    half = min(float(np.arccos(np.clip(cosines.min(), -1.0, 1.0))) * 1.01, MAX_HALF_ANGLE)
    # Near: the closest a caster can be along the axis, kept off zero for depth precision.
    far = float(lengths.max()) * 1.01
    inside = np.all(light.position >= box[0]) and np.all(light.position <= box[1])
    near = max(far * 1e-4, 0.0 if inside else float((to_corners @ axis).min()) * 0.99)
    near = min(max(near, far * 1e-4), far * 0.5)
    aperture = 2.0 * np.tan(half)
    return Camera(
        _frame(axis, light.position), size, size, 1.0, aperture, aperture, near=near, far=far
    )


class PrimShadows:
    """Shadow maps of the scene prims per light, drawn when first needed in a frame and
    kept while their casters and light are still."""

    def __init__(
        self,
        spec: RendererSpec,
        backend: ShadowBackend | None = None,
        compiled: CompiledPasses | None = None,
        shared: object = None,
    ) -> None:
        """`compiled`: the kernels' passes (shadow_pass.COMPILED) when `backend.kernel` is
        "numba"; None computes with this module's numpy functions. `shared`: the device
        resources its renderer and capsule shader draw with (RenderSettings.shared: the
        engine's GL context)."""
        self._spec = spec
        self._shared = shared
        self.backend = backend or ShadowBackend()
        self._compiled = compiled
        self._renderer: Renderer | None = None
        """Its own renderer, made on the first map: one sample per texel, and the frame's
        renderer keeps its meshes uploaded (a renderer releases what a call does not draw)."""
        self._maps: dict[tuple[int, str], tuple[bytes, ShadowMap | None]] = {}
        self._groups: dict[int, list[tuple[str, bytes, list[DrawMesh]]]] = {}
        self._lights: list[Light] = []
        self._bounds: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._regions: dict[tuple, list] = {}
        """This frame's regions per light (asked by the prims' and each layer's lighting)."""
        self.key = b""
        """Changes whenever any map's casters or light do (the frame and layer caches
        compare it)."""
        self.drawn = 0
        """Maps drawn since the last update (the report's)."""
        self._gl: GLCapsuleShadows | None = None
        self._gl_tried = False

    def use(self, backend: ShadowBackend, compiled: CompiledPasses | None) -> None:
        """Compute with `backend` (and the kernels' `compiled` passes, or numpy without) from
        now on; where capsule occlusion runs is decided again on its next use."""
        self.backend, self._compiled = backend, compiled
        if self._gl is not None:
            self._gl.close()
            self._gl = None
        self._gl_tried = False

    def update(
        self, lights: Sequence[Light], groups: Sequence[tuple[str, Sequence[DrawMesh]]]
    ) -> None:
        """Take this frame's lights and prims in `groups` (a name, its meshes): "still" for
        the prims that never move, one group per moving prim. Maps are drawn on demand."""
        self.drawn = 0
        self._lights = list(lights)
        self._groups = {}
        self._regions = {}
        keys = []
        mesh_keys = [np.array([id(m) for m in meshes], np.int64).tobytes() for _, meshes in groups]
        for i, light in enumerate(lights):
            if light.kind not in (DISTANT, POINT):
                continue
            light_key = light.direction.tobytes() + light.position.tobytes()
            self._groups[i] = []
            for (name, meshes), mesh_key in zip(groups, mesh_keys, strict=True):
                if meshes:
                    key = light_key + mesh_key
                    self._groups[i].append((name, key, list(meshes)))
                    keys.append(key)
        live = {(i, name) for i, group in self._groups.items() for name, _, _ in group}
        for stale in set(self._maps) - live:
            del self._maps[stale]
        self.key = b"|".join(keys)
        casters = [m for group in self._groups.values() for _, _, ms in group for m in ms]
        self._bounds = {
            id(m): self._bounds.get(id(m)) or (m.points.min(axis=0), m.points.max(axis=0))
            for m in casters
        }

    def _map(self, index: int, name: str, key: bytes, meshes: list[DrawMesh]) -> ShadowMap | None:
        cached = self._maps.get((index, name))
        if cached is None or cached[0] != key:
            size = SHADOW_MAP_SIZE if name == "still" else MOVING_MAP_SIZE
            light = self._lights[index]
            camera = light_camera(light, _box(meshes), size)
            drawn = None if camera is None else ShadowMap(camera, self._render(meshes, camera))
            self._maps[(index, name)] = cached = (key, drawn)
            self.drawn += 1
        return cached[1]

    def _render(self, meshes: list[DrawMesh], camera: Camera) -> np.ndarray:
        if self._renderer is None:
            self._renderer = self._spec.create(RenderSettings(1, shared=self._shared))
        return render_depth(self._renderer, meshes, camera)  # its depth-only pass

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._gl is not None:
            self._gl.close()
            self._gl = None
        self._gl_tried = False

    def capsule_visibility(
        self, points: np.ndarray, capsules: PosedCapsules, light: Light
    ) -> np.ndarray:
        """capsule_visibility, in the fragment shader where the backend's gl_capsules says so,
        else compiled where it has the kernels, else numpy."""
        shader = self._capsule_shader()
        if shader is None and self._compiled is not None:
            return self._compiled.points_visibility(points, None, light, capsules)
        return capsule_visibility(points, capsules, light, shader)

    @property
    def capsule_backend(self) -> str:
        """What computes the capsules' occlusion, "gl" or "numpy" (decided on first use)."""
        return "numpy" if self._capsule_shader() is None else "gl"

    def _capsule_shader(self) -> GLCapsuleShadows | None:
        if not self._gl_tried:
            self._gl_tried = True
            where = self.backend.gl_capsules
            wanted = where != "never" and self._spec.name == "gl"
            if wanted and self._spec.unavailable() is None:
                shared = self._shared if isinstance(self._shared, SharedContext) else None
                self._gl = GLCapsuleShadows(MIN_VISIBILITY, shared)
                software = any(name in self._gl.renderer.lower() for name in SOFTWARE_GL)
                if software and where != "always":
                    self._gl.close()
                    self._gl = None
        return self._gl

    def regions(
        self, index: int, box: np.ndarray, camera: Camera
    ) -> list[tuple[list[Region], tuple]]:
        """Light `index`'s maps (as handles for `lookup`) with the frame regions where their
        casters' shadows can fall; maps whose shadows miss the view are left out (not drawn)."""
        cache_key = (
            index,
            box.tobytes(),
            camera.camera_to_world.tobytes(),
            camera.fx,
            camera.width,
        )
        if cache_key in self._regions:
            return self._regions[cache_key]
        out = []
        groups = self._groups.get(index, [])
        casters = [m for _, _, meshes in groups for m in meshes]
        if casters:  # one call for every map's casters: its cost is mostly per call
            lo = np.array([self._bounds[id(m)][0] for m in casters])
            hi = np.array([self._bounds[id(m)][1] for m in casters])
            find = self._compiled.shadow_regions if self._compiled else shadow_regions
            found = iter(find(lo, hi, self._lights[index], box, camera))
            for name, key, meshes in groups:
                rects = [r for r in (next(found) for _ in meshes) if r]
                if rects:
                    out.append((rects, (index, name, key, meshes)))
        self._regions[cache_key] = out
        return out

    def shadow_regions(
        self, lo: np.ndarray, hi: np.ndarray, light: Light, box: np.ndarray, camera: Camera
    ) -> list[Region | None]:
        """shadow_regions, compiled where the backend has the kernels."""
        find = self._compiled.shadow_regions if self._compiled else shadow_regions
        return find(lo, hi, light, box, camera)

    def lookup(self, handle: tuple, points: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
        """(N,) visibility past one map (a handle from `regions`), drawing it if needed."""
        shadow_map = self._map(*handle)
        if shadow_map is None:
            return np.ones(points.shape[1], np.float32)
        if self._compiled is not None:
            return self._compiled.points_visibility(points, normals, shadow_map=shadow_map)
        return shadow_map.visibility(points, normals)

    def shadow_map(self, handle: tuple) -> ShadowMap | None:
        """The map of a handle from `regions`, drawn if needed (None: the light needs none)."""
        return self._map(*handle)


# -- capsules ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class PosedCapsules:
    """A character's capsules in world space at one pose."""

    a: np.ndarray
    """(K, 3) segment starts."""
    b: np.ndarray
    """(K, 3) segment ends."""
    radius: np.ndarray
    """(K,)"""
    chains: tuple[np.ndarray, ...] = ()
    """Index arrays of capsules along one limb (a leg, an arm, the spine): each is culled
    as one sphere first, much tighter than the whole body's."""

    @property
    def key(self) -> bytes:
        return np.concatenate([self.a.ravel(), self.b.ravel(), self.radius]).round(3).tobytes()

    def bounds(self) -> tuple[np.ndarray, float]:
        """A sphere (centre, radius) holding every capsule (found once: asked per light and
        pass)."""
        found = self.__dict__.get("_bounds")
        if found is None:
            found = self.__dict__["_bounds"] = self._sphere()
        return found

    def _sphere(self) -> tuple[np.ndarray, float]:
        ends = np.concatenate([self.a, self.b])
        lo, hi = ends.min(axis=0), ends.max(axis=0)
        centre = (lo + hi) / 2
        reach = np.linalg.norm(ends - centre, axis=1) + np.concatenate([self.radius] * 2)
        return centre, float(reach.max())

    def parts(self) -> list[PosedCapsules]:
        """The capsules chain by chain (all of them as one part without chains), found once."""
        found = self.__dict__.get("_parts")
        if found is None:
            found = [self]
            if self.chains:
                found = [PosedCapsules(self.a[c], self.b[c], self.radius[c]) for c in self.chains]
            self.__dict__["_parts"] = found
        return found


def chains(joints: Sequence[str]) -> tuple[np.ndarray, ...]:
    """Split capsules, listed in skeleton order, where a joint does not descend from the one
    before (joint paths as UsdSkel writes them, 'pelvis/thigh_l/calf_l')."""
    starts = [0] + [
        i for i in range(1, len(joints)) if not joints[i].startswith(joints[i - 1] + "/")
    ]
    ends = [*starts[1:], len(joints)]
    return tuple(np.arange(s, e) for s, e in zip(starts, ends, strict=True) if e > s)


def pose_capsules(
    a: np.ndarray,
    b: np.ndarray,
    radius: np.ndarray,
    world: np.ndarray,
    groups: tuple[np.ndarray, ...] = (),
) -> PosedCapsules:
    """Capsules given in joint frames (a, b (K, 3), radius (K,)) placed by `world` (K, 4, 4),
    each capsule's own joint-to-world transform."""
    rotation, translation = world[:, :3, :3], world[:, :3, 3]
    scale = np.cbrt(np.abs(np.linalg.det(rotation)))  # the character's own scale, if any
    return PosedCapsules(
        np.einsum("kij,kj->ki", rotation, a) + translation,
        np.einsum("kij,kj->ki", rotation, b) + translation,
        radius * scale,
        groups,
    )


def _soft_radius(light: Light, capsules: PosedCapsules) -> float:
    """A point light's radius for capsule shadows: its own, or what subtends MIN_SOFTNESS at
    the capsules, if more."""
    centre, _ = capsules.bounds()
    return max(light.radius, float(np.linalg.norm(centre - light.position)) * np.tan(MIN_SOFTNESS))


def _towards_light(
    light: Light, points: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (3, N) from planar points towards the light, and its angular radius
    (N,); a point light's `radius` from _soft_radius."""
    n = points.shape[1]
    if light.kind == DISTANT:
        direction = np.repeat(-light.direction.astype(np.float32)[:, None], n, axis=1)
        return direction, np.full(n, max(light.angle, MIN_SOFTNESS), np.float32)
    offset = light.position.astype(np.float32)[:, None] - points
    distance = np.maximum(np.sqrt(_dot(offset, offset)), 1e-6)
    angle = np.arcsin(np.clip(radius / distance, 0.0, 1.0)).astype(np.float32)
    return offset / distance, angle


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products over the first axis of planar (3, ...) vectors."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cone_occlusion(
    light_angle: np.ndarray, sphere_angle: np.ndarray, between: np.ndarray
) -> np.ndarray:
    """Fraction of a light cone (angular radius `light_angle`) hidden by a sphere's cone
    (`sphere_angle`) whose axis is `between` radians away: the overlap of two discs of those
    radii at that distance (the small-angle view of the two cones) over the light's disc."""
    r1, r2, d = light_angle, sphere_angle, between
    d_safe = np.maximum(d, 1e-9)
    c1 = np.clip((d * d + r1 * r1 - r2 * r2) / (2 * d_safe * r1), -1.0, 1.0)
    c2 = np.clip((d * d + r2 * r2 - r1 * r1) / (2 * d_safe * np.maximum(r2, 1e-9)), -1.0, 1.0)
    kite = np.sqrt(np.maximum((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2), 0.0))
    lens = r1 * r1 * np.arccos(c1) + r2 * r2 * np.arccos(c2) - 0.5 * kite
    inner = np.minimum(r1, r2) ** 2  # one disc inside the other
    area = np.where(d >= r1 + r2, 0.0, np.where(d <= np.abs(r1 - r2), np.pi * inner, lens))
    return np.clip(area / (np.pi * r1 * r1), 0.0, 1.0)


def _light_plane(light: Light, capsules: PosedCapsules, points: np.ndarray, soft: float):
    """Receivers and capsules in the light's 2-D view, where a capsule's shadow is a 2-D
    capsule: for a DistantLight the plane across its direction (u, v in scene units), for a
    point light the directions from it (u, v: tangents about the axis towards the capsules).

    Returns the points' u, v (N,), the capsules' ends (K, 2) twice, their radii there (K,),
    each point's penumbra margin (N,: how far beyond a capsule's outline its shadow can
    still reach that point, which grows with the point's distance behind the capsules) and
    the tangent stretch (a function of the margins: for a point light 1 / cos^2 of the
    largest angle off the axis, NaN where that reaches 80 degrees). None when the light is
    among the capsules: every pair is computed then. `soft`: a point light's _soft_radius."""
    centre, reach = capsules.bounds()
    if light.kind == DISTANT:
        w = light.direction
        e1, e2 = _frame_axes(w)
        m = np.stack([e1, e2, w]).astype(np.float32)
        u, v, depth = (
            m[j, 0] * points[0] + m[j, 1] * points[1] + m[j, 2] * points[2] for j in range(3)
        )
        front = float(centre @ w - reach)  # the capsules' nearest depth along the light
        margin = np.maximum(depth - front, 0.0) * np.tan(max(light.angle, MIN_SOFTNESS))
        flat = capsules.a @ m[:2].T, capsules.b @ m[:2].T
        return u, v, flat[0], flat[1], capsules.radius, margin, np.ones_like
    offset = centre - light.position
    distance = float(np.linalg.norm(offset))
    if distance <= reach * 1.05:
        return None
    w = offset / distance
    e1, e2 = _frame_axes(w)
    m = np.stack([e1, e2, w])
    q = points - light.position.astype(np.float32)[:, None]
    mf = m.astype(np.float32)
    x, y, z = (mf[j, 0] * q[0] + mf[j, 1] * q[1] + mf[j, 2] * q[2] for j in range(3))
    ahead = z > 0  # behind the light's view of the capsules: out of their shadow
    inv = 1.0 / np.where(ahead, z, 1.0)
    u, v = np.where(ahead, x * inv, np.inf), np.where(ahead, y * inv, np.inf)
    ends = []
    for e in (capsules.a, capsules.b):
        local = (e - light.position) @ m.T
        ends.append(local[:, :2] / local[:, 2:3])
    closest = np.minimum(
        np.linalg.norm(capsules.a - light.position, axis=1),
        np.linalg.norm(capsules.b - light.position, axis=1),
    )
    angular = np.arcsin(np.clip(capsules.radius / np.maximum(closest, 1e-9), 0.0, 1.0))
    # A receiver at distance D sees the light R / D wide; seen from the light, a caster at
    # distance d shifts the penumbra by that angle times (D - d) / d: at most R / d.
    nearest = max(float(closest.min()), 1e-9)
    far = np.sqrt(x * x + y * y + z * z)
    margin = soft * np.maximum(far - nearest, 0.0) / (np.maximum(far, nearest) * nearest)
    base = float(np.arctan(np.linalg.norm(np.concatenate(ends), axis=1).max()))
    base += float(angular.max())

    def stretch(margin: np.ndarray) -> np.ndarray:
        off_axis = base + margin
        return np.where(off_axis < np.radians(80.0), 1.0 / np.cos(off_axis) ** 2, np.nan)

    # Angles become tangent units (times the stretch) in _candidate_pairs.
    return u, v, ends[0], ends[1], np.tan(angular), margin, stretch


def _near(u, v, a2, b2, radius, margin, stretch) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each receiver's tangent stretch (NaN where it is too far off the light's axis to
    bound), whether that is so, and the receivers within reach of all capsules' 2-D bounds."""
    factor = stretch(margin)
    unbounded = np.isnan(factor) & np.isfinite(u)
    lo, hi = np.minimum(a2, b2).astype(np.float32), np.maximum(a2, b2).astype(np.float32)
    reach = (np.float32(radius.max()) + margin) * factor
    near = np.flatnonzero(
        (u >= lo[:, 0].min() - reach) & (u <= hi[:, 0].max() + reach)
        & (v >= lo[:, 1].min() - reach) & (v <= hi[:, 1].max() + reach)
    )  # fmt: skip
    return factor, unbounded, near


def _candidate_pairs(
    u, v, a2, b2, radius, margin, stretch, parts: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """(receiver, capsule) pairs whose 2-D distance may lie within the capsule's shadow: a
    receiver's reach is the capsule's radius plus its own penumbra margin (times the tangent
    stretch). The 2-D bounds of all capsules cull most receivers with a few operations each;
    the rest are tested against each capsule's 2-D bounds at once (receivers x capsules, a
    block of float32 comparisons), and the pairs left meet the capsule's 2-D segment. (`parts`
    is kept for the callers' signature: one block over every capsule measured faster than a
    loop over the limbs.)"""
    del parts
    factor, unbounded, near = _near(u, v, a2, b2, radius, margin, stretch)
    lo, hi = np.minimum(a2, b2).astype(np.float32), np.maximum(a2, b2).astype(np.float32)
    receivers, capsules = [], []
    if near.size:
        pu, pv, f = u[near, None], v[near, None], factor[near, None]
        limit = (radius.astype(np.float32)[None] + margin[near, None]) * f  # (n, K)
        box = (pu >= lo[None, :, 0] - limit) & (pu <= hi[None, :, 0] + limit)
        box &= (pv >= lo[None, :, 1] - limit) & (pv <= hi[None, :, 1] + limit)
        hit, k = np.nonzero(box)
        seg = (b2 - a2).astype(np.float32)
        length2 = np.maximum(seg[:, 0] * seg[:, 0] + seg[:, 1] * seg[:, 1], 1e-18)
        du = u[near[hit]] - a2[k, 0].astype(np.float32)
        dv = v[near[hit]] - a2[k, 1].astype(np.float32)
        t = np.clip((du * seg[k, 0] + dv * seg[k, 1]) / length2[k], 0.0, 1.0)
        du -= t * seg[k, 0]
        dv -= t * seg[k, 1]
        keep = du * du + dv * dv <= limit[hit, k] ** 2
        receivers.append(near[hit[keep]])
        capsules.append(k[keep])
    if unbounded.any():  # every pair of the receivers seen too far off the light's axis
        members = np.flatnonzero(unbounded)
        receivers.append(np.repeat(members, len(radius)))
        capsules.append(np.tile(np.arange(len(radius)), len(members)))
    if not receivers:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(receivers), np.concatenate(capsules)


def capsule_visibility(
    points: np.ndarray, capsules: PosedCapsules, light: Light, gl: GLCapsuleShadows | None = None
) -> np.ndarray:
    """(N,) how much of `light` reaches world points (planar (3, N)) past the capsules. With
    `gl`, the receivers within reach of all capsules' 2-D bounds go to its fragment shader
    (the same maths, every capsule per receiver, a limb's capsules skipped together where
    its bounding sphere misses the light) instead of pair by pair here."""
    n = points.shape[1]
    out = np.ones(n, np.float32)
    if n == 0 or len(capsules.radius) == 0:
        return out
    p = np.asarray(points, dtype=np.float32)
    soft = _soft_radius(light, capsules) if light.kind == POINT else 0.0
    plane = _light_plane(light, capsules, p, soft)
    if gl is not None:  # receivers near all capsules' 2-D bounds; the shader skips the rest
        if plane is None:
            receivers = np.arange(n)
        else:
            _, unbounded, near = _near(*plane)
            receivers = np.union1d(near, np.flatnonzero(unbounded))
        if receivers.size:
            angle = max(light.angle, MIN_SOFTNESS)
            out[receivers] = gl.visibility(
                p[:, receivers], capsules.a, capsules.b, capsules.radius, capsules.chains,
                light, angle, soft,
            )  # fmt: skip
        return out
    if plane is None:  # no 2-D view to bin in: every pair
        i, k = np.divmod(np.arange(n * len(capsules.radius)), len(capsules.radius))
    else:
        parts = capsules.chains or (np.arange(len(capsules.radius)),)
        u, v, a2, b2, radius, margin, stretch = plane
        i, k = _candidate_pairs(u, v, a2, b2, radius, margin, stretch, parts)
    if i.size == 0:
        return out
    receivers, i = _distinct_receivers(i)
    p = p[:, receivers]
    to_light, light_angle = _towards_light(light, p, soft)
    a = capsules.a.astype(np.float32).T  # planar (3, K)
    u = (capsules.b - capsules.a).astype(np.float32).T
    r = capsules.radius.astype(np.float32)[k]
    # The segment's point closest to the ray p + t L (exact for a segment against a line).
    d = to_light[:, i]
    uk = u[:, k]
    w0 = a[:, k] - p[:, i]
    uu, ud, uw, dw = _dot(u, u)[k], _dot(uk, d), _dot(uk, w0), _dot(d, w0)
    denominator = uu - ud * ud
    s = np.where(denominator > 1e-9, (ud * dw - uw) / np.maximum(denominator, 1e-9), 0.0)
    c = w0 + np.clip(s, 0.0, 1.0) * uk  # from the receiver to the sphere's centre
    distance = np.maximum(np.sqrt(_dot(c, c)), 1e-6)
    sphere_angle = np.arcsin(np.clip(r / distance, 0.0, 1.0))
    between = np.arccos(np.clip(_dot(c, d) / distance, -1.0, 1.0))
    occlusion = cone_occlusion(light_angle[i], sphere_angle, between)
    occlusion = np.where(distance > r, occlusion, 0.0)  # a receiver inside: not its caster
    log_visibility = np.log(np.maximum(1.0 - occlusion, MIN_VISIBILITY))
    out[receivers] = np.exp(np.bincount(i, weights=log_visibility, minlength=receivers.size))
    return out


def _distinct_receivers(i: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct receivers of the pairs' receivers `i` (non-empty), sorted, and each pair's
    index among them (np.unique's inverse)."""
    if np.all(i[1:] >= i[:-1]):  # pairs come receiver by receiver: no sort needed
        first = np.empty(i.size, bool)
        first[0], first[1:] = True, i[1:] != i[:-1]
        return i[first], np.cumsum(first) - 1
    receivers, inverse = np.unique(i, return_inverse=True)
    return receivers, inverse


Region = tuple[int, int, int, int]
"""(x0, y0, x1, y1) pixels of a frame."""


_CORNER_PICK = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
"""Which of (lo, hi) each of a box's 8 corners takes, per axis."""


def shadow_regions(
    lo: np.ndarray, hi: np.ndarray, light: Light, box: np.ndarray, camera: Camera
) -> list[Region | None]:
    """Per caster with bounds lo, hi (M, 3): the frame pixels its shadow can fall on, or
    None. Its box is swept away from `light` until it leaves the scene's bounds `box`,
    widened along the way by the shadow's softness (light_softness). None: it casts onto
    nothing in view (a flat caster on the scene's boundary, the ground, onto nothing).
    The numpy reference; shadow_pass.shadow_regions is its compiled twin (CompiledPasses)."""
    m = len(lo)
    bounds = np.stack([lo, hi], axis=1)  # (M, 2, 3)
    corners = bounds[:, _CORNER_PICK, np.arange(3)]  # (M, 8, 3)
    scene = np.stack([np.minimum(box[0], lo), np.maximum(box[1], hi)], axis=1)
    full: Region = (0, 0, camera.width, camera.height)
    if light.kind == DISTANT:
        directions = np.broadcast_to(light.direction, corners.shape)
        angles = np.full(m, max(light.angle, MIN_SOFTNESS))
        around = np.zeros(m, bool)
    else:
        offsets = corners - light.position
        directions = offsets / np.maximum(np.linalg.norm(offsets, axis=-1, keepdims=True), 1e-12)
        distance = np.linalg.norm((lo + hi) / 2 - light.position, axis=-1)
        angles = np.maximum(np.arcsin(np.clip(light.radius / np.maximum(distance, 1e-9), 0, 1)),
                            MIN_SOFTNESS)  # fmt: skip
        around = np.all((light.position >= lo) & (light.position <= hi), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(directions > 0, scene[:, None, 1] - corners, scene[:, None, 0] - corners)
        t = np.where(directions == 0, np.inf, t / directions)
    lengths = np.maximum(t.min(axis=-1), 0.0)  # (M, 8): to the scene's boundary
    size = np.maximum(np.linalg.norm(hi - lo, axis=-1), 1e-9)
    flat = (lengths.max(axis=1) <= 1e-6 * size) & ((hi - lo).min(axis=-1) <= 1e-6 * size)
    grow = lengths.max(axis=1) * np.tan(angles)
    ends = corners + directions * lengths[..., None]
    far = np.stack([ends.min(axis=1) - grow[:, None], ends.max(axis=1) + grow[:, None]], axis=1)
    points = np.concatenate([corners, far[:, _CORNER_PICK, np.arange(3)]], axis=1)  # (M, 16, 3)
    w2c = camera.world_to_camera
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    depth = -pc[..., 2]
    behind = np.any(depth <= camera.near, axis=1)
    inv = 1.0 / np.where(depth > camera.near, depth, 1.0)
    x = camera.cx + camera.fx * pc[..., 0] * inv
    y = camera.cy - camera.fy * pc[..., 1] * inv
    x0 = np.maximum(np.floor(x.min(axis=1)) - 1, 0).astype(int)
    y0 = np.maximum(np.floor(y.min(axis=1)) - 1, 0).astype(int)
    x1 = np.minimum(np.ceil(x.max(axis=1)) + 1, camera.width).astype(int)
    y1 = np.minimum(np.ceil(y.max(axis=1)) + 1, camera.height).astype(int)
    out: list[Region | None] = []
    for i in range(m):
        if flat[i]:
            out.append(None)
        elif around[i] or behind[i]:  # the light among it, or reaching behind the camera
            out.append(full)
        elif x1[i] <= x0[i] or y1[i] <= y0[i]:
            out.append(None)
        else:
            out.append((int(x0[i]), int(y0[i]), int(x1[i]), int(y1[i])))
    return out


def region_mask(regions: Sequence[Region], camera: Camera, window=None) -> np.ndarray:
    """(H, W) bool: the union of the regions, within `window` (rows, columns slices of the
    frame) when given."""
    rows, cols = window or (slice(0, camera.height), slice(0, camera.width))
    mask = np.zeros((rows.stop - rows.start, cols.stop - cols.start), bool)
    for x0, y0, x1, y1 in regions:
        top, left = max(y0 - rows.start, 0), max(x0 - cols.start, 0)
        mask[top : y1 - rows.start, left : x1 - cols.start] = True
    return mask


def _bend(values: np.ndarray) -> np.ndarray:
    """Per sample of a grid, the largest second difference along either axis around it
    (|a - 2b + c|; at the grid's border, its neighbour's): zero where the values change
    linearly, which a blend reproduces exactly; a shadow's edge between samples shows."""
    out = np.zeros_like(values)
    for axis in (0, 1):
        if values.shape[axis] < 3:
            continue
        v = np.moveaxis(values, axis, 0)
        bend = np.abs(v[:-2] - 2 * v[1:-1] + v[2:])
        mine = np.moveaxis(out, axis, 0)
        np.maximum(mine[1:-1], bend, out=mine[1:-1])
        np.maximum(mine[:1], bend[:1], out=mine[:1])
        np.maximum(mine[-1:], bend[-1:], out=mine[-1:])
    return out


def _around(cells: np.ndarray) -> np.ndarray:
    """Cells and their 8 neighbours (a boolean dilation by one cell)."""
    out = cells.copy()
    out[1:] |= cells[:-1]
    out[:-1] |= cells[1:]
    wide = out.copy()
    wide[:, 1:] |= out[:, :-1]
    wide[:, :-1] |= out[:, 1:]
    return wide


CROP_MARGIN = 6
"""sparse_visibility leaves out what lies this many coarse samples beyond every candidate:
a pixel's blend looks at its cell, the cells around it and their samples' neighbours (3
samples), so past twice that everything is lit and smooth, and the result is the same."""


def _crop(candidates: np.ndarray, step: int) -> tuple[slice, slice] | None:
    """Rows and columns holding every candidate with CROP_MARGIN samples around, starting
    on the sample grid (so the samples stay where they were); None when that saves little."""
    margin = CROP_MARGIN * step
    spans = []
    for axis in (1, 0):
        hit = np.flatnonzero(candidates.any(axis=axis))
        if hit.size == 0:
            return None
        size = candidates.shape[1 - axis]
        start = max((int(hit[0]) - margin) // step * step, 0)
        spans.append(slice(start, min(int(hit[-1]) + 1 + margin, size)))
    rows, cols = spans
    kept = (rows.stop - rows.start) * (cols.stop - cols.start)
    return None if kept > 0.8 * candidates.size else (rows, cols)


def sparse_visibility(
    candidates: np.ndarray, evaluate, depth: np.ndarray | None = None, step: int = SPARSE_STEP
) -> np.ndarray:
    """(H, W) shadow factors of the `candidates` pixels (1 elsewhere), with `evaluate(flat)`
    giving them for flat pixel indices. Shadows here are soft (MIN_SOFTNESS, a shadow map's
    bilinear taps), so most pixels are blended rather than evaluated: every `step`th pixel
    (a power of two) along both axes is evaluated, then each grid of half the spacing is
    filled in from the one above, down to every pixel. A new pixel (the middle of a cell's
    edge or of the cell) is the blend of its cell's samples where that cell and its
    neighbours are smooth (their values change linearly, BEND_TOLERANCE: no shadow edge, no thin
    shadow in between) and where it lies on their surface; every other candidate is
    evaluated exactly. With the pixels' `depth` the surface test is that the inverse depth
    (affine in screen space across a plane) is within SURFACE_TOLERANCE of the samples'
    blend (no silhouette, no crease), and a sample that is no candidate counts as lit (it
    lies where no shadow reaches); without it, all four samples must be candidates."""
    h, w = candidates.shape
    crop = _crop(candidates, step)
    if crop is not None:  # only where candidates are (the sky above the ground is none)
        return _cropped_visibility(candidates, evaluate, depth, step, crop)
    if h < 2 or w < 2:  # no cells to blend in
        return _exact_visibility(candidates, evaluate)
    # Padded to whole cells; the padding is no candidate (its cells are evaluated exactly).
    size_y, size_x = (-(-(n - 1) // step) * step + 1 for n in (h, w))
    wanted = np.zeros((size_y, size_x), bool)
    wanted[:h, :w] = candidates
    out = np.ones((size_y, size_x), np.float32)
    inverse = None
    if depth is not None:  # 1 / depth is affine in screen space across a plane; empty: 0
        inverse = np.zeros((size_y, size_x), np.float32)
        inverse[:h, :w] = 1.0 / np.maximum(depth, 1e-30)
    grid = (slice(None, None, step),) * 2
    _fill(out, _where(grid, wanted[grid], w), evaluate, w)
    spacing = step
    while spacing > 1:
        _fill(out, _refine(out, wanted, inverse, spacing, w), evaluate, w)
        spacing //= 2
    return out[:h, :w]


def _cropped_visibility(
    candidates: np.ndarray,
    evaluate,
    depth: np.ndarray | None,
    step: int,
    crop: tuple[slice, slice],
) -> np.ndarray:
    """sparse_visibility on the `crop` of the frame that holds the candidates; 1 elsewhere."""
    h, w = candidates.shape
    rows, cols = crop
    inner = candidates[rows, cols]
    width = cols.stop - cols.start

    def evaluate_inner(pixels: np.ndarray) -> np.ndarray:
        r, c = np.divmod(pixels, width)
        return evaluate((r + rows.start) * w + c + cols.start)

    out = np.ones((h, w), np.float32)
    out[rows, cols] = sparse_visibility(
        inner, evaluate_inner, None if depth is None else depth[rows, cols], step
    )
    return out


def _exact_visibility(candidates: np.ndarray, evaluate) -> np.ndarray:
    """Every candidate evaluated exactly (1 elsewhere): a frame too thin for cells."""
    h, w = candidates.shape
    out = np.ones(h * w, np.float32)
    exact = np.flatnonzero(candidates)
    if exact.size:
        out[exact] = evaluate(exact)
    return out.reshape(h, w)


def _where(at: tuple[slice, slice], mask: np.ndarray, w: int) -> np.ndarray:
    """Flat frame indices of a strided view's True entries (no index grid to gather)."""
    rows, cols = np.nonzero(mask)
    return (rows * at[0].step + (at[0].start or 0)) * w + cols * at[1].step + (at[1].start or 0)


def _fill(out: np.ndarray, pixels: np.ndarray, evaluate, w: int) -> None:
    """Evaluate `pixels` (flat indices of a frame `w` wide) exactly, into `out`."""
    if pixels.size:
        rows, cols = np.divmod(pixels, w)
        out[rows, cols] = evaluate(pixels)


def _refine(
    out: np.ndarray, wanted: np.ndarray, inverse: np.ndarray | None, spacing: int, w: int
) -> np.ndarray:
    """Fill in, in `out`, the candidates of the grid of half `spacing` that blend from the
    grid of `spacing` (sparse_visibility); the flat indices of those to evaluate instead."""
    half = spacing // 2
    on, mid = slice(None, None, spacing), slice(half, None, spacing)
    c, valid = out[on, on], wanted[on, on]
    corners = (c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:])
    rough = _bend(c) > BEND_TOLERANCE
    rough = rough[:-1, :-1] | rough[:-1, 1:] | rough[1:, :-1] | rough[1:, 1:]
    if inverse is None:  # nothing tells a non-candidate's surface: evaluate beside one
        rough |= ~(valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:])
    smooth = ~_around(rough)
    # The middles of horizontal edges, of vertical edges, and of cells; an edge is
    # smooth where a cell beside it is (the dilation has looked at the other).
    parts = [
        ((on, mid), (c[:, :-1] + c[:, 1:]) * 0.5, np.concatenate([smooth, smooth[-1:]])),
        ((mid, on), (c[:-1] + c[1:]) * 0.5, np.concatenate([smooth, smooth[:, -1:]], 1)),
        ((mid, mid), (corners[0] + corners[1] + corners[2] + corners[3]) * 0.25, smooth),
    ]
    pending: list[np.ndarray] = []
    for at, blended, ok in parts:
        new = wanted[at]
        blend = new & ok
        if inverse is not None:
            i = inverse[on, on]
            if at == (on, mid):
                expected = (i[:, :-1] + i[:, 1:]) * 0.5
            elif at == (mid, on):
                expected = (i[:-1] + i[1:]) * 0.5
            else:
                expected = (i[:-1, :-1] + i[:-1, 1:] + i[1:, :-1] + i[1:, 1:]) * 0.25
            mine = inverse[at]
            blend &= np.abs(expected - mine) <= np.float32(SURFACE_TOLERANCE) * mine
        np.copyto(out[at], blended, where=blend)
        pending.append(_where(at, new & ~blend, w))
    return np.concatenate(pending)

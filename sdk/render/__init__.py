"""The renderer plugin kind: draw meshes for a camera into albedo, normal, depth and mask maps."""

from __future__ import annotations

import sys
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from rigspace.sdk.camera import Camera
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.plugins import Kind, PluginSet, discover

# Map conventions (docs/renderers.md): depth is the camera-space distance along -Z in scene
# units, +inf where empty; normals are camera space, unit length, zero where empty; albedo is
# linear RGB premultiplied by coverage; mask is coverage in [0, 1]. Every pixel is sampled on the
# same s x s stratified grid, at (k + 0.5) / s within the pixel; albedo and mask average the
# samples (an empty sample counts as 0), depth and normal come from the nearest hit sample.
# Meshes with texture charts (DrawMesh.chart) also give the surface's texture coordinates:
# chart from the nearest hit sample, uv the mean of the samples on that same chart (a chart's
# uvs are continuous, so the mean never blends across a seam); 0 where no chart is seen.

DEFAULT_COLOR = (0.18, 0.18, 0.18)
"""Linear mid grey (18% reflectance), the albedo of a mesh with no colour or texture."""


@dataclass
class DrawMesh:
    """One triangle mesh to draw, in world space.

    Renderers re-read `points` and `normals` on every call (they may change every frame, in place
    or not), unless they are frozen (`frozen`: read-only, as `CharacterRig.posed_meshes` returns
    them): then a renderer may keep what it built from them (the checks, gl's upload, embree's
    acceleration structure) while the same array objects come back, so the 32 views of one
    captured pose pay for it once. `triangles`, `corner_uv`, `color` and `texture` are cached by
    array identity: to change them, assign a new array rather than editing the old one in place.
    """

    points: np.ndarray
    """(N,3) float32 world-space positions."""
    triangles: np.ndarray
    """(T,3) int32 vertex indices, counter-clockwise seen from outside."""
    normals: np.ndarray | None = None
    """(N,3) world-space vertex normals; None -> area-weighted normals from the points."""
    corner_uv: np.ndarray | None = None
    """(T,3,2) float32 faceVarying uv, USD st convention (v = 0 is the BOTTOM row of the texture)."""
    texture: np.ndarray | None = None
    """(H,W,3) float32 linear RGB, sampled bilinear (no mipmaps) at st * uv_scale + uv_offset,
    wrapped per axis as `wrap` says."""
    color: Any = DEFAULT_COLOR
    """(3,) constant or (N,3) per-vertex linear RGB, used where there is no texture."""
    name: str = ""
    chart: np.ndarray | None = None
    """(T,) int32 texture chart of each triangle (rigspace.sdk.charts; 0: none), for a textured
    mesh: with it, renderers also give the maps' `uv` and `chart` (capture's texture AOVs)."""
    wrap: tuple[int, int] = (0, 0)
    """The texture's wrap mode along s and t: 0 repeat, 1 mirror, 2 clamp (to the edge texel),
    3 black (rigspace.sdk.geometry.WRAP_MODES)."""
    uv_scale: tuple[float, float] = (1.0, 1.0)
    uv_offset: tuple[float, float] = (0.0, 0.0)
    """The texture is read at st * uv_scale + uv_offset (a UDIM atlas; the uv map keeps st)."""


@dataclass
class MeshArrays:
    """A DrawMesh's arrays checked and converted to the dtypes renderers upload."""

    points: np.ndarray  # (N,3) float32
    triangles: np.ndarray  # (T,3) int32
    normals: np.ndarray  # (N,3) float32
    corner_uv: np.ndarray | None  # (T,3,2) float32, only when there is a texture
    texture: np.ndarray | None  # (H,W,3) float32
    color: np.ndarray  # (3,) or (N,3) float32
    chart: np.ndarray | None = None  # (T,) int32, only for a textured mesh with charts
    wrap: tuple[int, int] = (0, 0)
    uv_scale: tuple[float, float] = (1.0, 1.0)
    uv_offset: tuple[float, float] = (0.0, 0.0)


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(N,3) float32 unit vertex normals, each the area-weighted mean of its faces' normals."""
    p = np.asarray(points, dtype=np.float32)
    t = np.asarray(triangles, dtype=np.intp)
    # The cross product's length is twice the triangle's area: that is the area weighting.
    face = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    corners = t.reshape(-1)
    n = np.stack(
        [np.bincount(corners, np.repeat(face[:, c], 3), minlength=len(p)) for c in range(3)], 1
    )
    length = np.linalg.norm(n, axis=1, keepdims=True)
    # Vertices with no (or only degenerate) faces keep a zero normal instead of NaN.
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0).astype(np.float32)


def freeze(*arrays: np.ndarray | None) -> None:
    """Make arrays read-only, so renderers may keep what they build from them (`frozen`)."""
    for a in arrays:
        if a is not None:
            a.flags.writeable = False


def frozen(a: Any) -> bool:
    """True when nobody can change `a`'s values: it and every array it views are read-only (a
    read-only view of a writeable array is not frozen: its owner can still write)."""
    while isinstance(a, np.ndarray):
        if a.flags.writeable:
            return False
        a = a.base
    return a is None


_CHECKED: weakref.WeakValueDictionary[tuple, np.ndarray] = weakref.WeakValueDictionary()
"""Frozen arrays already checked, by (id, what was checked): the entry dies with the array, so a
later array with the same id is never taken for it."""


def checked_once(a: np.ndarray, what: tuple, check: Callable[[], None]) -> None:
    """Run `check` on `a`, or skip it when `a` is frozen and passed the same check before."""
    key = (id(a), *what)
    if _CHECKED.get(key) is a:
        return
    check()
    if frozen(a):
        _CHECKED[key] = a


def _array(mesh: DrawMesh, field_name: str, value: Any, dtype: type, shape: tuple) -> np.ndarray:
    a: np.ndarray = np.ascontiguousarray(value, dtype=dtype)
    checked_once(a, (field_name, shape), lambda: _check_array(mesh, field_name, a, shape))
    return a


def _check_array(mesh: DrawMesh, field_name: str, a: np.ndarray, shape: tuple) -> None:
    if a.ndim != len(shape) or any(
        s is not None and s != n for s, n in zip(shape, a.shape, strict=True)
    ):
        want = "(" + ",".join("?" if s is None else str(s) for s in shape) + ")"
        raise ValueError(
            f"DrawMesh {mesh.name or '(unnamed)'}: {field_name} must have shape {want}, got {a.shape}."
        )
    if not np.all(np.isfinite(a)):
        raise ValueError(
            f"DrawMesh {mesh.name or '(unnamed)'}: {field_name} has non-finite values."
        )


def mesh_arrays(mesh: DrawMesh) -> MeshArrays:
    """Check a DrawMesh and convert its arrays (ValueError naming the mesh and field)."""
    points = _array(mesh, "points", mesh.points, np.float32, (None, 3))
    tris = _array(mesh, "triangles", mesh.triangles, np.int32, (None, 3))
    n, t = len(points), len(tris)
    _check_indices(mesh, tris, n)
    if mesh.normals is None:
        normals = vertex_normals(points, tris)
    else:
        normals = _array(mesh, "normals", mesh.normals, np.float32, (n, 3))
    uv = texture = None
    if mesh.texture is not None:
        texture = _array(mesh, "texture", mesh.texture, np.float32, (None, None, 3))
        if mesh.corner_uv is None:
            raise ValueError(
                f"DrawMesh {mesh.name or '(unnamed)'} has a texture but no corner_uv to place it."
            )
        uv = _array(mesh, "corner_uv", mesh.corner_uv, np.float32, (t, 3, 2))
    color = np.ascontiguousarray(mesh.color, dtype=np.float32)
    if color.shape != (3,):
        color = _array(mesh, "color", color, np.float32, (n, 3))
    chart = None
    if mesh.chart is not None:
        if texture is None:
            raise ValueError(
                f"DrawMesh {mesh.name or '(unnamed)'} has texture charts but no texture: charts "
                "say where a texture lands."
            )
        chart = _array(mesh, "chart", mesh.chart, np.int32, (t,))
        if t and chart.min() < 0:
            raise ValueError(f"DrawMesh {mesh.name or '(unnamed)'}: chart indices must be >= 0.")
    wrap = (int(mesh.wrap[0]), int(mesh.wrap[1]))
    if not all(0 <= w <= 3 for w in wrap):
        raise ValueError(
            f"DrawMesh {mesh.name or '(unnamed)'}: wrap modes must be 0-3, got {mesh.wrap}."
        )
    scale = (float(mesh.uv_scale[0]), float(mesh.uv_scale[1]))
    offset = (float(mesh.uv_offset[0]), float(mesh.uv_offset[1]))
    return MeshArrays(points, tris, normals, uv, texture, color, chart, wrap, scale, offset)


def depth_arrays(mesh: DrawMesh) -> tuple[np.ndarray, np.ndarray]:
    """A DrawMesh's points (N,3) float32 and triangles (T,3) int32, checked as mesh_arrays
    checks them: all a depth-only pass (render_depth) reads."""
    points = _array(mesh, "points", mesh.points, np.float32, (None, 3))
    tris = _array(mesh, "triangles", mesh.triangles, np.int32, (None, 3))
    _check_indices(mesh, tris, len(points))
    return points, tris


def _check_indices(mesh: DrawMesh, tris: np.ndarray, n: int) -> None:
    """Every triangle index lies in [0, n) (ValueError naming the mesh otherwise)."""

    def check() -> None:
        if len(tris) and (tris.min() < 0 or tris.max() >= n):
            raise ValueError(
                f"DrawMesh {mesh.name or '(unnamed)'}: triangle indices must lie in [0, {n}), "
                f"got [{tris.min()}, {tris.max()}]."
            )

    checked_once(tris, ("indices", n), check)


def render_depth(renderer: Renderer, meshes: Sequence[DrawMesh], camera: Camera) -> np.ndarray:
    """(H, W) float32 depth of `meshes` at one sample per pixel: the renderer's depth-only
    pass (`render_depth`, as gl and embree have) where it has one, else render()'s depth
    (which a renderer made with samples_per_axis 1 samples identically)."""
    own = getattr(renderer, "render_depth", None)
    if own is not None:
        return np.asarray(own(meshes, camera), np.float32)
    return renderer.render(meshes, camera).depth


@dataclass
class Maps:
    """The maps of one rendered frame (conventions at the top of this module)."""

    albedo: np.ndarray
    """(H,W,3) float32 linear RGB, premultiplied by coverage."""
    normal: np.ndarray
    """(H,W,3) float32 camera-space unit normals, zero where empty."""
    depth: np.ndarray
    """(H,W) float32 distance along the camera's -Z in scene units, +inf where empty."""
    mask: np.ndarray
    """(H,W) float32 coverage in [0, 1]."""
    uv: np.ndarray | None = None
    """(H,W,2) float32 USD st of the visible surface on its chart's texture, 0 where no chart;
    None when no mesh drawn had charts."""
    chart: np.ndarray | None = None
    """(H,W) int32 texture chart of the visible surface (rigspace.sdk.charts), 0: none."""

    def as_dict(self) -> dict[str, np.ndarray]:
        maps = {
            "albedo": self.albedo,
            "normal": self.normal,
            "depth": self.depth,
            "mask": self.mask,
        }
        if self.uv is not None and self.chart is not None:
            maps |= {"uv": self.uv, "chart": self.chart}
        return maps


def empty_maps(height: int, width: int) -> Maps:
    """A frame with nothing in it: mask 0, depth +inf."""
    return Maps(
        np.zeros((height, width, 3), np.float32),
        np.zeros((height, width, 3), np.float32),
        np.full((height, width), np.inf, np.float32),
        np.zeros((height, width), np.float32),
    )


def _pixel_samples(fine: np.ndarray, s: int) -> list[np.ndarray]:
    """The s*s sub-sample images (H, W, ...) of a supersampled (H*s, W*s, ...) array, as views.

    Reducing over these strided views is several times faster than numpy's reduce over the
    non-adjacent axes of a (H, s, W, s, ...) reshape (measured: 0.9 ms vs 8 ms at 256^2, s=2).
    """
    return [fine[a::s, b::s] for a in range(s) for b in range(s)]


def maps_from_samples(
    samples_per_axis: int,
    hit: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    depth: np.ndarray,
    uv: np.ndarray | None = None,
    chart: np.ndarray | None = None,
) -> Maps:
    """Reduce a supersampled image, (H*s, W*s, ...) with row 0 at the top, to per-pixel maps.

    `hit` (H*s,W*s) bool; `albedo` (H*s,W*s,3) must be zero where there is no hit; `normal`
    (H*s,W*s,3) and `depth` (H*s,W*s) may hold anything there; `uv` (H*s,W*s,2) and `chart`
    (H*s,W*s) int, when given, only where a charted mesh is hit. Pixel (i, j)'s sub-sample
    (a, b) is fine pixel (i*s + a, j*s + b). Both renderers reduce through here, so identically.
    """
    s = samples_per_axis
    if chart is not None:
        chart = np.where(hit, chart, 0).astype(np.int32)
    if s == 1:
        return _maps_at_one_sample(hit, albedo, normal, depth, uv, chart)
    h, w = hit.shape[0] // s, hit.shape[1] // s
    count = np.float32(s * s)
    mask = np.zeros((h, w), np.float32)
    out_albedo = np.zeros((h, w, 3), np.float32)
    for sample_hit, sample_albedo in zip(
        _pixel_samples(hit, s), _pixel_samples(albedo, s), strict=True
    ):
        mask += sample_hit
        out_albedo += sample_albedo
    mask /= count
    out_albedo /= count
    # Depth and normal from the nearest sample, never blended across a silhouette.
    nearest = np.stack(_pixel_samples(np.where(hit, depth, np.float32(np.inf)), s))
    k = nearest.argmin(axis=0)
    out_depth = np.take_along_axis(nearest, k[None], axis=0)[0].astype(np.float32)
    rows = np.arange(h)[:, None] * s + k // s
    cols = np.arange(w)[None, :] * s + k % s
    out_normal = np.where(np.isfinite(out_depth)[..., None], normal[rows, cols], np.float32(0))
    maps = Maps(out_albedo, out_normal.astype(np.float32), out_depth, mask)
    if uv is not None and chart is not None:
        maps.chart = np.where(np.isfinite(out_depth), chart[rows, cols], 0).astype(np.int32)
        maps.uv = _uv_on_chart(uv, chart, maps.chart, s)
    return maps


def _maps_at_one_sample(
    hit: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    depth: np.ndarray,
    uv: np.ndarray | None,
    chart: np.ndarray | None,
) -> Maps:
    """maps_from_samples at one sample per pixel: nothing to reduce (np.where makes the
    arrays owned); `chart` already zero where there is no hit."""
    depth = np.where(hit, depth, np.float32(np.inf)).astype(np.float32, copy=False)
    normal = np.where(hit[..., None], normal, np.float32(0)).astype(np.float32, copy=False)
    maps = Maps(np.array(albedo, np.float32), normal, depth, hit.astype(np.float32))
    if uv is not None and chart is not None:
        maps.chart = chart
        maps.uv = np.where(chart[..., None] > 0, uv, np.float32(0)).astype(np.float32, copy=False)
    return maps


def _uv_on_chart(uv: np.ndarray, chart: np.ndarray, pixel_chart: np.ndarray, s: int) -> np.ndarray:
    """Each pixel's uv: the mean over its samples on the nearest sample's chart `pixel_chart`
    (a chart's uvs are continuous there, so nothing is blended across a seam or with another
    surface's); 0 where the pixel has no chart."""
    h, w = pixel_chart.shape
    total = np.zeros((h, w, 2), np.float64)
    on_chart = np.zeros((h, w), np.float64)
    for sample_chart, sample_uv in zip(
        _pixel_samples(chart, s), _pixel_samples(uv, s), strict=True
    ):
        same = (sample_chart == pixel_chart) & (pixel_chart > 0)
        total += np.where(same[..., None], sample_uv, 0.0)
        on_chart += same
    return (total / np.maximum(on_chart, 1)[..., None]).astype(np.float32)


@dataclass(frozen=True)
class RenderSettings:
    """How a renderer samples the image."""

    samples_per_axis: int = 2
    """Stratified samples per pixel along each axis (s x s per pixel), at (k + 0.5) / s."""
    shared: Any = field(default=None, compare=False, repr=False)
    """Device resources to draw with instead of the renderer's own: for gl, a
    gl.SharedContext (an Engine shares one EGL context among its renderers, its lighting
    and its capsule shadows); renderers that have none ignore it."""

    def __post_init__(self) -> None:
        s = self.samples_per_axis
        if isinstance(s, bool) or int(s) != s or s < 1:
            raise ValueError(
                f"RenderSettings.samples_per_axis must be a positive integer, got {s!r}."
            )


class Renderer(Protocol):
    """A live renderer; keep it for many frames (it caches GPU state), then close() it.

    A renderer may also keep `last_timings`, a dict of seconds per phase of its last
    render (gl: draw, readback), which benchmarks report, and a depth-only pass
    `render_depth(meshes, camera) -> (H, W) float32` (one sample per pixel centre; shadow
    maps draw through it, see the module function render_depth).
    """

    name: str

    def render(self, meshes: Sequence[DrawMesh], camera: Camera) -> Maps: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class RendererSpec:
    """What a renderer plugin exports (entry-point group `rigspace.renderers`)."""

    name: str
    description: str
    create: Callable[[RenderSettings], Renderer]
    unavailable: Callable[[], str | None] = field(repr=False)
    """None when usable on this machine, else the reason (with the original error)."""
    cost_grows_with_triangles: Callable[[], bool] = field(default=lambda: False, repr=False)
    """True where this renderer's time grows with every triangle drawn however small (gl on a
    software rasteriser): choose_renderer("auto") then puts it after the others for a heavy
    frame (HEAVY_TRIANGLES)."""


RENDERERS: Kind[RendererSpec] = Kind("renderer", "rigspace.renderers", RendererSpec)

AUTO_ORDER = ("gl", "embree")
"""Preference of choose_renderer("auto"): rasterising first, ray casting as the fallback."""


def renderer_plugins() -> PluginSet[RendererSpec]:
    """Every renderer plugin (entry-point group rigspace.renderers; the built-ins included)."""
    return discover(RENDERERS)


HEAVY_TRIANGLES = 250_000
"""Over this many triangles a frame, "auto" prefers embree to a software GL (llvmpipe), whose
cost grows with every triangle however small: capturing the film-weight character (1.5M) at
128x128 measured 4.9 samples/s through gl and 20 through embree, the 23k-triangle sample 89.7
and 38.5 (samples/film_character/README.md). A GPU's GL stays first at any size."""


def choose_renderer(name: str | None = None, triangles: int = 0) -> RendererSpec:
    """The renderer called `name`, or for None / "auto" the first usable one of AUTO_ORDER
    (embree first for a frame of over HEAVY_TRIANGLES `triangles` where GL is software).

    Falling back prints one line to stderr saying why the preferred renderer was skipped. A
    named renderer that cannot run here raises RigspaceError with the reason.
    """
    plugins = renderer_plugins()
    if name is None or name == "auto":
        order = [*AUTO_ORDER, *(n for n in plugins.specs if n not in AUTO_ORDER)]
        skipped: list[str] = []
        if triangles > HEAVY_TRIANGLES:
            slow = [n for n in order if n in plugins.specs and _grows(plugins.specs[n])]
            if slow:
                order = [n for n in order if n not in slow] + slow
                skipped.append(
                    f"{triangles:,} triangles raster slowly on this machine's "
                    f"{' and '.join(slow)} (a software rasteriser; --renderer {slow[0]} to "
                    "use it anyway)"
                )
        for candidate in order:
            if candidate in plugins.specs:
                reason = plugins.specs[candidate].unavailable()
            else:
                reason = plugins.failed.get(candidate, "not installed")
            if reason is None:
                if skipped:
                    print(f"rigspace: {'; '.join(skipped)}; using {candidate}", file=sys.stderr)
                return plugins.specs[candidate]
            skipped.append(f"the {candidate} renderer is unavailable ({reason})")
        raise RigspaceError(
            f"No renderer can run here: {'; '.join(skipped)}.",
            "install EGL (Mesa's libegl1) for gl, or embreex for embree.",
        )
    spec = plugins.get(name)
    reason = spec.unavailable()
    if reason is not None:
        others = [n for n in plugins.specs if n != name]
        raise RigspaceError(
            f"The {name} renderer cannot run here: {reason}.",
            f"fix what the reason names, or choose {' or '.join([*others, 'auto'])} instead.",
        )
    return spec


def _grows(spec: RendererSpec) -> bool:
    """A usable renderer whose cost grows with every triangle (RendererSpec)."""
    return spec.unavailable() is None and spec.cost_grows_with_triangles()


__all__ = [
    "AUTO_ORDER",
    "HEAVY_TRIANGLES",
    "RENDERERS",
    "DrawMesh",
    "Maps",
    "MeshArrays",
    "RenderSettings",
    "Renderer",
    "RendererSpec",
    "choose_renderer",
    "depth_arrays",
    "empty_maps",
    "maps_from_samples",
    "mesh_arrays",
    "render_depth",
    "renderer_plugins",
    "vertex_normals",
]

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
  capsule) pairs that a light-space table (the capsules' 2-D shadows binned in GRID x GRID
  cells) puts near each other are computed.

Shadowing multiplies each light's contribution (diffuse and specular), never the ambient.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rigspace.runtime.lights import DISTANT, POINT, Light
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import DrawMesh

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
"""Capsule shadows see the light at least this wide (angular radius): capsules are a coarse
stand-in for the body, and a sharp capsule outline would show it; Unreal softens its capsule
shadows the same way. The sun (0.27 degrees) is widened to it, a lamp 15 cm across at 4 m
(2.1 degrees) too."""
NORMAL_OFFSET_TEXELS = 1.0
"""Receivers move this many texels along their normal before the map lookup (acne)."""
DEPTH_BIAS_TEXELS = 1.5
"""And count as lit up to this many texels behind the map's depth."""
GRID = 32
"""Cells per side of the light-space table that pairs receivers with nearby capsules."""
MIN_VISIBILITY = 1e-6
"""Capsule occlusions are summed as log(visibility): fully hidden stays finite."""


@dataclass
class ShadowMap:
    """The depth of some casters seen from a light."""

    camera: Camera
    depth: np.ndarray
    """(S, S) float32 distance along the map camera's -Z, +inf where no caster is."""

    def __post_init__(self) -> None:
        # A border of +inf: a lookup clamped into it finds no caster (lit), with no test.
        self._padded = np.pad(self.depth, 1, constant_values=np.inf).astype(np.float32)
        self._m = self.camera.world_to_camera.astype(np.float32)

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
    return np.array(
        [[box[i][0], box[j][1], box[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    )


def _frame(forward: np.ndarray, position: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world looking along `forward` from `position`, rolled anyhow."""
    z = -forward / np.linalg.norm(forward)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, position
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
    """Shadow maps of the scene prims per light, redrawn only when casters or light move."""

    def __init__(self, renderer) -> None:
        self.renderer = renderer
        self._maps: dict[tuple[int, str], tuple[bytes, ShadowMap | None]] = {}
        self._casters: list[DrawMesh] = []
        self._bounds: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.key = b""
        """Changes whenever any map does (the frame and layer caches compare it)."""
        self.drawn = 0
        """Maps drawn by the last update (the report's)."""

    def update(
        self, lights: Sequence[Light], groups: Sequence[tuple[str, Sequence[DrawMesh]]]
    ) -> None:
        """Bring each shadowing light's maps up to date with the prims in `groups` (a name,
        its meshes): "still" for the prims that never move, one group per moving prim."""
        self.drawn = 0
        keys = []
        live = set()
        for i, light in enumerate(lights):
            if light.kind not in (DISTANT, POINT):
                continue
            light_key = light.direction.tobytes() + light.position.tobytes()
            for name, meshes in groups:
                size = SHADOW_MAP_SIZE if name == "still" else MOVING_MAP_SIZE
                key = light_key + b"".join(np.int64(id(m)).tobytes() for m in meshes)
                live.add((i, name))
                cached = self._maps.get((i, name))
                if cached is None or cached[0] != key:
                    self._maps[(i, name)] = (key, self._draw(light, meshes, size))
                    self.drawn += 1
                keys.append(key)
        for stale in set(self._maps) - live:
            del self._maps[stale]
        self.key = b"|".join(keys)
        self._casters = [m for _, meshes in groups for m in meshes] if live else []
        self._bounds = {
            id(m): self._bounds.get(id(m)) or (m.points.min(axis=0), m.points.max(axis=0))
            for m in self._casters
        }

    def _draw(self, light: Light, meshes: Sequence[DrawMesh], size: int) -> ShadowMap | None:
        if not meshes:
            return None
        camera = light_camera(light, _box(meshes), size)
        if camera is None:
            return None
        return ShadowMap(camera, self.renderer.render(meshes, camera).depth)

    def maps(self, index: int) -> list[ShadowMap]:
        """The maps of light `index` (of the lights last updated with)."""
        return [m for (i, _), (_, m) in self._maps.items() if i == index and m is not None]

    def regions(self, light: Light, box: np.ndarray, camera: Camera) -> list[Region]:
        """The frame regions the prims' shadows from `light` can fall on."""
        out = []
        for mesh in self._casters:
            lo, hi = self._bounds[id(mesh)]
            distance = float(np.linalg.norm((lo + hi) / 2 - light.position))
            region = shadow_region(lo, hi, light, box, camera, light_softness(light, distance))
            if region is not None:
                out.append(region)
        return out

    def visibility(self, index: int, points: np.ndarray, normals: np.ndarray | None):
        """(N,) light `index`'s visibility past every prim at planar (3, N) world points, or
        None when nothing shadows it."""
        maps = self.maps(index)
        if not maps:
            return None
        out = maps[0].visibility(points, normals)
        for m in maps[1:]:
            out *= m.visibility(points, normals)
        return out


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
        """A sphere (centre, radius) holding every capsule."""
        ends = np.concatenate([self.a, self.b])
        lo, hi = ends.min(axis=0), ends.max(axis=0)
        centre = (lo + hi) / 2
        reach = np.linalg.norm(ends - centre, axis=1) + np.concatenate([self.radius] * 2)
        return centre, float(reach.max())

    def parts(self) -> list[PosedCapsules]:
        """The capsules chain by chain (all of them as one part without chains)."""
        if not self.chains:
            return [self]
        return [PosedCapsules(self.a[c], self.b[c], self.radius[c]) for c in self.chains]


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


def _towards_light(light: Light, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (3, N) from planar points towards the light, and its angular radius (N,)."""
    n = points.shape[1]
    if light.kind == DISTANT:
        direction = np.repeat(-light.direction.astype(np.float32)[:, None], n, axis=1)
        return direction, np.full(n, max(light.angle, MIN_SOFTNESS), np.float32)
    offset = light.position.astype(np.float32)[:, None] - points
    distance = np.maximum(np.sqrt(_dot(offset, offset)), 1e-6)
    angle = np.arcsin(np.clip(light.radius / distance, 0.0, 1.0))
    return offset / distance, np.maximum(angle, MIN_SOFTNESS).astype(np.float32)


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


def _frame_axes(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to unit `w` and to each other."""
    helper = np.array([0.0, 1.0, 0.0]) if abs(w[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, w)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(w, e1)


def _light_plane(light: Light, capsules: PosedCapsules, points: np.ndarray):
    """Receivers and capsules in the light's 2-D view, where a capsule's shadow is a 2-D
    capsule: for a DistantLight the plane across its direction (u, v in scene units), for a
    point light the directions from it (u, v: tangents about the axis towards the capsules).

    Returns the points' u, v (N,), the capsules' ends (K, 2) twice, their radii there (K,),
    each point's penumbra margin (N,: how far beyond a capsule's outline its shadow can
    still reach that point, which grows with the point's distance behind the capsules) and
    the tangent stretch (a function of the margin: 1 / cos^2 of the largest angle off the
    axis, for a point light; None when that reaches 80 degrees). None when the light is
    among the capsules: every pair is computed then."""
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
        return u, v, flat[0], flat[1], capsules.radius, margin, lambda _: 1.0
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
    # A receiver at distance D sees the light at most `widest` wide; seen from the light, a
    # caster at distance d shifts the penumbra by that angle times (D - d) / d.
    nearest = max(float(closest.min()), 1e-9)
    widest = max(float(np.arcsin(min(light.radius / nearest, 1.0))), MIN_SOFTNESS)
    far = np.sqrt(x * x + y * y + z * z)
    margin = widest * np.maximum(far - nearest, 0.0) / nearest
    base = float(np.arctan(np.linalg.norm(np.concatenate(ends), axis=1).max()))
    base += float(angular.max())

    def stretch(largest_margin: float) -> float | None:
        off_axis = base + largest_margin
        return None if off_axis >= np.radians(80.0) else 1.0 / np.cos(off_axis) ** 2

    # Angles become tangent units (times the stretch) in _candidate_pairs.
    return u, v, ends[0], ends[1], np.tan(angular), margin, stretch


def _candidate_pairs(u, v, a2, b2, radius, margin, stretch) -> tuple[np.ndarray, np.ndarray]:
    """(receiver, capsule) pairs whose 2-D distance may lie within the capsule's shadow.

    Receivers are grouped in slabs of similar penumbra margin (doubling from the smallest
    capsule radius); per slab the capsules' 2-D shadows, widened by the slab's largest
    margin, are binned into a GRID x GRID table of cells, and each receiver reads its cell's
    row: it meets only the capsules near it, with the margin its own distance needs."""
    base = max(float(radius.min()), 1e-12)
    slab = np.ceil(np.log2(margin / base + 1.0)).astype(np.int64)
    receivers, capsules = [], []
    for s in np.unique(slab[np.isfinite(u)]):
        members = np.flatnonzero((slab == s) & np.isfinite(u))
        widest = float(margin[members].max())
        factor = stretch(widest)
        if factor is None:  # too far off the light's axis to bin: every pair of the slab
            receivers.append(np.repeat(members, len(radius)))
            capsules.append(np.tile(np.arange(len(radius)), len(members)))
            continue
        grow = (radius + widest) * factor
        lo = np.minimum(a2, b2).min(axis=0) - grow.max()
        hi = np.maximum(a2, b2).max(axis=0) + grow.max()
        size = np.maximum((hi - lo) / GRID, 1e-12)
        mu, mv = u[members], v[members]
        inside = (mu >= lo[0]) & (mu < hi[0]) & (mv >= lo[1]) & (mv < hi[1])
        members, mu, mv = members[inside], mu[inside], mv[inside]
        if members.size == 0:
            continue
        # Which capsules reach each cell: its centre's distance to the capsule's 2-D segment.
        cells = np.stack(np.divmod(np.arange(GRID * GRID), GRID), -1)[:, ::-1]
        centres = lo + (cells + 0.5) * size
        seg = b2 - a2
        length2 = np.maximum(np.einsum("kc,kc->k", seg, seg), 1e-18)
        t = np.einsum("nkc,kc->nk", centres[:, None, :] - a2[None], seg) / length2
        nearest = a2[None] + np.clip(t, 0.0, 1.0)[..., None] * seg[None]
        gap = np.linalg.norm(centres[:, None, :] - nearest, axis=-1)
        table = gap <= grow[None, :] + 0.5 * float(np.hypot(*size))
        col = np.minimum(((mu - lo[0]) / size[0]).astype(np.int64), GRID - 1)
        row = np.minimum(((mv - lo[1]) / size[1]).astype(np.int64), GRID - 1)
        hit, k = np.nonzero(table[row * GRID + col])
        receivers.append(members[hit])
        capsules.append(k)
    if not receivers:
        empty = np.zeros(0, np.int64)
        return empty, empty
    return np.concatenate(receivers), np.concatenate(capsules)


def capsule_visibility(points: np.ndarray, capsules: PosedCapsules, light: Light) -> np.ndarray:
    """(N,) how much of `light` reaches world points (planar (3, N)) past the capsules."""
    n = points.shape[1]
    out = np.ones(n, np.float32)
    if n == 0 or len(capsules.radius) == 0:
        return out
    p = np.asarray(points, dtype=np.float32)
    plane = _light_plane(light, capsules, p)
    if plane is None:  # no 2-D view to bin in: every pair
        i, k = np.divmod(np.arange(n * len(capsules.radius)), len(capsules.radius))
    else:
        i, k = _candidate_pairs(*plane)
    if i.size == 0:
        return out
    receivers, i = np.unique(i, return_inverse=True)
    p = p[:, receivers]
    to_light, light_angle = _towards_light(light, p)
    a = capsules.a.astype(np.float32).T  # planar (3, K)
    u = (capsules.b - capsules.a).astype(np.float32).T
    r = capsules.radius.astype(np.float32)
    # The segment's point closest to the ray p + t L (exact for a segment against a line).
    d = to_light[:, i]
    uk = u[:, k]
    w0 = a[:, k] - p[:, i]
    uu, ud, uw, dw = _dot(uk, uk), _dot(uk, d), _dot(uk, w0), _dot(d, w0)
    denominator = uu - ud * ud
    s = np.where(denominator > 1e-9, (ud * dw - uw) / np.maximum(denominator, 1e-9), 0.0)
    c = w0 + np.clip(s, 0.0, 1.0) * uk  # from the receiver to the sphere's centre
    distance = np.maximum(np.sqrt(_dot(c, c)), 1e-6)
    sphere_angle = np.arcsin(np.clip(r[k] / distance, 0.0, 1.0))
    between = np.arccos(np.clip(_dot(c, d) / distance, -1.0, 1.0))
    occlusion = cone_occlusion(light_angle[i], sphere_angle, between)
    occlusion = np.where(distance > r[k], occlusion, 0.0)  # a receiver inside: not its caster
    log_visibility = np.log(np.maximum(1.0 - occlusion, MIN_VISIBILITY))
    out[receivers] = np.exp(np.bincount(i, weights=log_visibility, minlength=receivers.size))
    return out


def _exit_distance(origin: np.ndarray, direction: np.ndarray, box: np.ndarray) -> float:
    """How far a ray from inside `box` travels before leaving it."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(direction > 0, (box[1] - origin) / direction, (box[0] - origin) / direction)
    t = np.where(direction == 0, np.inf, t)
    return max(float(t.min()), 0.0)


Region = tuple[int, int, int, int]
"""(x0, y0, x1, y1) pixels of a frame."""


def shadow_region(
    lo: np.ndarray, hi: np.ndarray, light: Light, box: np.ndarray, camera: Camera, angle: float
) -> Region | None:
    """The frame pixels the shadow of a caster within bounds (lo, hi) can fall on: its box
    swept away from `light` until it leaves the scene's bounds `box`, widened by `angle`
    (the shadow's softness) along the way. None: it casts onto nothing in view (a flat
    caster on the scene's boundary, the ground, casts onto nothing at all)."""
    corners = _corners(np.array([lo, hi]))
    box = np.array([np.minimum(box[0], lo), np.maximum(box[1], hi)])
    if light.kind == DISTANT:
        directions = np.repeat(light.direction[None], 8, axis=0)
    else:
        if np.all(light.position >= lo) and np.all(light.position <= hi):
            return 0, 0, camera.width, camera.height  # the light among the caster
        offsets = corners - light.position
        directions = offsets / np.linalg.norm(offsets, axis=1, keepdims=True)
    lengths = np.array(
        [_exit_distance(c, d, box) for c, d in zip(corners, directions, strict=True)]
    )
    size = float(np.linalg.norm(hi - lo))
    if lengths.max() <= 1e-6 * max(size, 1e-9) and np.min(hi - lo) <= 1e-6 * max(size, 1e-9):
        return None  # flat and on the boundary: nothing lies beyond it
    grow = lengths.max() * np.tan(angle)
    ends = corners + directions * lengths[:, None]
    points = np.concatenate([corners, _corners(np.array([ends.min(0) - grow, ends.max(0) + grow]))])
    xy, depth = camera.project(points)
    if np.any(depth <= camera.near):
        return 0, 0, camera.width, camera.height  # reaches behind the camera: all of it
    lo_px = np.floor(xy.min(axis=0)).astype(int) - 1
    hi_px = np.ceil(xy.max(axis=0)).astype(int) + 1
    x0, y0 = max(int(lo_px[0]), 0), max(int(lo_px[1]), 0)
    x1, y1 = min(int(hi_px[0]), camera.width), min(int(hi_px[1]), camera.height)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def light_softness(light: Light, distance: float) -> float:
    """A capsule shadow's angular radius of the light, seen from `distance` (point lights)."""
    if light.kind == DISTANT:
        return max(light.angle, MIN_SOFTNESS)
    return max(float(np.arcsin(min(light.radius / max(distance, 1e-9), 1.0))), MIN_SOFTNESS)


def region_mask(regions: Sequence[Region], height: int, width: int) -> np.ndarray:
    """(H, W) bool: the union of the regions."""
    mask = np.zeros((height, width), bool)
    for x0, y0, x1, y1 in regions:
        mask[y0:y1, x0:x1] = True
    return mask

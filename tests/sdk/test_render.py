"""The gl and embree renderers: agreement with each other, analytic checks, caching and choice."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rigspace.apps.render_timing import textured_sphere
from rigspace.sdk.camera import Camera
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.render import (
    DrawMesh,
    Maps,
    RenderSettings,
    choose_renderer,
    mesh_arrays,
    renderer_plugins,
    vertex_normals,
)
from rigspace.sdk.render import embree as embree_module
from rigspace.sdk.render import gl as gl_module
from rigspace.sdk.render.embree import sample_bilinear
from rigspace.sdk.render.gl import weld_corners

# Agreement between gl and embree on the same frame. Measured here (Mesa llvmpipe, the five
# scenes below; docs/renderers.md): IoU 1, mask MAE 0, depth relative error median <= 8.1e-8 and
# p95 <= 2.8e-7, normal angle median 0 and p95 <= 0.028 deg, albedo MAE <= 7.2e-7. The bounds
# leave room for a GPU driver's rasteriser and texture filtering (8-bit sub-texel weights).
MIN_MASK_IOU = 0.999
"""Pixels covered by one renderer only: only samples within rounding of an edge may differ."""
MAX_MASK_MAE = 1e-3
MAX_DEPTH_REL_MEDIAN = 1e-6
MAX_DEPTH_REL_P95 = 1e-5
"""Relative depth difference where both hit: float32 interpolation vs float32 ray distances."""
MAX_NORMAL_DEG_MEDIAN = 0.01
MAX_NORMAL_DEG_P95 = 0.1
"""Normal angle in degrees where both hit: both interpolate the same vertex normals. (A pixel
whose nearest samples tie in depth across a box edge may pick either face: 90 deg, rare.)"""
MAX_ALBEDO_MAE = 1e-3
"""Mean absolute albedo difference; 8-bit bilinear weights err by up to 1/512 of a texel step."""

FLOAT32_RTOL = 1e-5
"""Relative tolerance for values that are exact up to float32 rounding (~1e-7 per op)."""
UNIT_TOLERANCE = 1e-5
"""How far a float32 unit normal's length may be from 1."""

SIZE = (96, 72)  # width x height: not square, so a swapped axis shows


# --- synthetic meshes -----------------------------------------------------------------------
def icosphere(subdivisions: int, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """Points (N,3) float32 and counter-clockwise triangles (T,3) int32 of a subdivided icosahedron."""
    g = (1 + 5**0.5) / 2
    p = np.array(
        [[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g], [0, -1, -g],
         [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]],
    )  # fmt: skip
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]],
    )  # fmt: skip
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = len(p) + inverse.reshape(3, -1)  # midpoint vertex of edges ab, bc, ca per face
        p = np.concatenate([p, p[unique].mean(axis=1)])
        a, b, c = f.T
        ab, bc, ca = mid
        f = np.concatenate(
            [np.stack(t, 1) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))]
        )
    p = p / np.linalg.norm(p, axis=1, keepdims=True) * radius + center
    return p.astype(np.float32), f.astype(np.int32)


def box(half=(0.5, 0.5, 0.5), center=(0.0, 0.0, 0.0)):
    """24 points (flat faces), 12 counter-clockwise triangles and a colour per point."""
    points, colors = [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.eye(3)[axis] * sign
            u, v = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
            if sign < 0:
                u, v = v, u  # keep u x v = n so the quad winds counter-clockwise from outside
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                points.append((n + du * u + dv * v) * half + center)
            colors += [np.abs(n) * 0.6 + 0.2 + (sign > 0) * 0.1] * 4
    quads = np.arange(24).reshape(6, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return np.array(points, np.float32), tris.astype(np.int32), np.array(colors, np.float32)


def quad(corners, st=((0, 0), (1, 0), (1, 1), (0, 1))):
    """Two triangles over corners given counter-clockwise (bottom-left first), with corner st."""
    tris = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    return np.asarray(corners, np.float32), tris, np.asarray(st, np.float32)[tris]


def quadrant_texture(size: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A texture whose four quadrants have distinct colours; also returns the four colours."""
    colors = np.array(
        [[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [[0.0, 0.0, 1.0], [1.0, 1.0, 0.0]]], np.float32
    )  # [top/bottom][left/right] of the IMAGE (row 0 is the top)
    h = size // 2
    return np.repeat(np.repeat(colors, h, axis=0), h, axis=1), colors


def deformed_sphere(phase: float) -> np.ndarray:
    p, _ = icosphere(3, radius=0.8)
    bump = 1 + 0.15 * np.sin(3 * p[:, 0] + phase) * np.cos(2 * p[:, 1])
    return (p * bump[:, None]).astype(np.float32)


def camera(eye=(0.6, 0.8, 4.0), target=(0.0, 0.0, 0.0), size=SIZE, **kw) -> Camera:
    return Camera.look_at(
        eye,
        target,
        width=size[0],
        height=size[1],
        focal_length=35.0,
        horizontal_aperture=20.955,
        **kw,
    )


def front_camera(size=SIZE) -> Camera:
    """At the origin looking down -Z: world and camera space coincide."""
    return Camera(np.eye(4), size[0], size[1], focal_length=35.0, horizontal_aperture=20.955)


def scenes() -> dict[str, tuple[list[DrawMesh], Camera]]:
    rng = np.random.default_rng(0)
    sphere_p, sphere_t = icosphere(3)
    box_p, box_t, box_c = box((0.6, 0.4, 0.5))
    rot = np.array([[0.8, 0.0, 0.6], [0.0, 1.0, 0.0], [-0.6, 0.0, 0.8]], np.float32)
    texture = rng.random((16, 16, 3)).astype(np.float32)
    quad_p, quad_t, quad_uv = quad([[-1, -1, -0.3], [1, -1, 0.3], [1, 1, 0.3], [-1, 1, -0.3]])
    blob = icosphere(3, radius=0.8)[1]
    box2_p, box2_t, box2_c = box((0.3, 0.3, 0.3), center=(0.5, 0.2, 0.7))
    clipped_p, clipped_t = icosphere(3, radius=1.0, center=(0.2, 0.0, -1.5))
    return {
        # Near and far both cut the sphere: GL clips, embree starts and stops its rays there.
        "clipped": (
            [DrawMesh(clipped_p, clipped_t)],
            Camera(np.eye(4), *SIZE, 35.0, 20.955, near=0.8, far=2.2),
        ),
        "sphere": (
            [DrawMesh(sphere_p, sphere_t, color=rng.random((len(sphere_p), 3)).astype(np.float32))],
            camera(),
        ),
        "box": ([DrawMesh(box_p @ rot.T, box_t, normals=None, color=box_c)], camera()),
        "textured_quad": (
            [DrawMesh(quad_p, quad_t, corner_uv=quad_uv * 2.5 - 0.7, texture=texture)],
            camera(eye=(0.3, -0.2, 3.0)),
        ),
        "deformed_occluded": (
            [
                DrawMesh(deformed_sphere(0.4), blob, color=(0.7, 0.3, 0.2)),
                DrawMesh(box2_p, box2_t, color=box2_c),
            ],
            camera(eye=(1.5, 1.0, 3.5)),
        ),
    }


def agreement(a: Maps, b: Maps) -> dict[str, float]:
    """The agreement measures docs/renderers.md reports."""
    ma, mb = a.mask > 0, b.mask > 0
    both = ma & mb
    rel = np.abs(a.depth[both] - b.depth[both]) / b.depth[both]
    cos = np.clip((a.normal[both] * b.normal[both]).sum(-1), -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    return {
        "mask_iou": float(both.sum() / (ma | mb).sum()),
        "mask_mae": float(np.abs(a.mask - b.mask).mean()),
        "depth_rel_median": float(np.median(rel)),
        "depth_rel_p95": float(np.percentile(rel, 95)),
        "normal_deg_median": float(np.median(angle)),
        "normal_deg_p95": float(np.percentile(angle, 95)),
        "albedo_mae": float(np.abs(a.albedo - b.albedo).mean()),
    }


def check_invariants(maps: Maps) -> None:
    assert maps.mask.dtype == np.float32 and maps.depth.dtype == np.float32
    assert np.all((maps.mask >= 0) & (maps.mask <= 1))
    hit = maps.mask > 0
    assert np.all(np.isfinite(maps.depth) == hit), "depth must be finite exactly where covered"
    assert np.all(maps.depth[hit] > 0)
    length = np.linalg.norm(maps.normal, axis=-1)
    assert np.all(np.abs(length[hit] - 1) < UNIT_TOLERANCE)
    assert np.all(maps.normal[~hit] == 0) and np.all(maps.albedo[~hit] == 0)


# --- fixtures ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def gl_renderer():
    reason = gl_module.unavailable()
    if reason is not None:
        pytest.skip(f"the gl renderer cannot run here: {reason}")
    renderer = gl_module.SPEC.create(RenderSettings())
    yield renderer
    renderer.close()


@pytest.fixture(scope="module")
def embree_renderer():
    renderer = embree_module.SPEC.create(RenderSettings())
    yield renderer
    renderer.close()


@pytest.fixture(params=["gl", "embree"])
def renderer(request):
    return request.getfixturevalue(f"{request.param}_renderer")


# --- agreement ----------------------------------------------------------------------------------
@pytest.mark.parametrize("scene", sorted(scenes()))
def test_gl_and_embree_agree(scene, gl_renderer, embree_renderer):
    meshes, cam = scenes()[scene]
    a, b = gl_renderer.render(meshes, cam), embree_renderer.render(meshes, cam)
    check_invariants(a)
    check_invariants(b)
    assert (a.mask > 0).sum() > 0.1 * a.mask.size, "the scene should fill a good part of the frame"
    m = agreement(a, b)
    assert m["mask_iou"] >= MIN_MASK_IOU, m
    assert m["mask_mae"] <= MAX_MASK_MAE, m
    assert m["depth_rel_median"] <= MAX_DEPTH_REL_MEDIAN, m
    assert m["depth_rel_p95"] <= MAX_DEPTH_REL_P95, m
    assert m["normal_deg_median"] <= MAX_NORMAL_DEG_MEDIAN, m
    assert m["normal_deg_p95"] <= MAX_NORMAL_DEG_P95, m
    assert m["albedo_mae"] <= MAX_ALBEDO_MAE, m


# --- analytic checks --------------------------------------------------------------------------
def test_plane_facing_the_camera(renderer):
    d = 3.0
    p, t, _ = quad([[-5, -5, -d], [5, -5, -d], [5, 5, -d], [-5, 5, -d]])
    maps = renderer.render([DrawMesh(p, t, color=(0.2, 0.4, 0.6))], front_camera())
    check_invariants(maps)
    assert np.all(maps.mask == 1)
    np.testing.assert_allclose(maps.depth, d, rtol=FLOAT32_RTOL)
    np.testing.assert_allclose(
        maps.normal, np.broadcast_to((0, 0, 1), maps.normal.shape), atol=UNIT_TOLERANCE
    )
    np.testing.assert_allclose(
        maps.albedo, np.broadcast_to((0.2, 0.4, 0.6), maps.albedo.shape), rtol=FLOAT32_RTOL
    )


def test_sphere_depth_at_the_centre_pixel(renderer):
    distance, radius, size = 4.0, 1.0, (63, 63)  # odd size: a pixel centre on the optical axis
    p, t = icosphere(3, radius, center=(0.0, 0.0, -distance))
    cam = front_camera(size)
    maps = renderer.render([DrawMesh(p, t)], cam)
    # The facets lie between the circumscribed sphere and the inscribed one (radius r_in).
    face_n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    face_n /= np.linalg.norm(face_n, axis=1, keepdims=True)
    r_in = np.min(np.abs(((p[t[:, 0]] - (0, 0, -distance)) * face_n).sum(1)))
    # The nearest sample is up to s/(2s) * sqrt(2) pixels = 0.35 px off the axis (s=2, offsets 0.25).
    off_axis = distance * 0.25 * np.sqrt(2) / cam.fx
    centre = maps.depth[size[1] // 2, size[0] // 2]
    assert distance - radius <= centre <= distance - np.sqrt(r_in**2 - off_axis**2)
    np.testing.assert_allclose(maps.normal[size[1] // 2, size[0] // 2], (0, 0, 1), atol=0.05)


def test_projected_point_lands_where_it_is_drawn(renderer):
    cam = camera(eye=(2.0, 1.0, 5.0), target=(0.3, 0.2, 0.0))
    center = np.array([0.8, -0.4, 0.5])
    # A small square facing the camera, centred on `center`; its coverage centroid is the
    # projection of the centre (a fronto-parallel square projects to a square).
    r = cam.camera_to_world[:3, :3]
    half = 0.06
    corners = center + np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * half @ r.T
    p, t, _ = quad(corners)
    maps = renderer.render([DrawMesh(p, t)], cam)
    ii, jj = np.mgrid[: cam.height, : cam.width] + 0.5
    w = maps.mask
    centroid = np.array([(jj * w).sum() / w.sum(), (ii * w).sum() / w.sum()])
    xy, depth = cam.project(center[None])
    # Coverage is quantised to 1/s of a pixel per axis, so the centroid is within that.
    np.testing.assert_allclose(centroid, xy[0], atol=1.0 / 2)
    row, col = int(xy[0, 1]), int(xy[0, 0])
    assert maps.mask[row, col] == 1
    np.testing.assert_allclose(maps.depth[row, col], depth[0], rtol=1e-3)


def test_empty_frames(renderer):
    maps = renderer.render([], front_camera())
    check_invariants(maps)
    assert np.all(maps.mask == 0) and np.all(np.isinf(maps.depth))
    p, t = icosphere(1, center=(0.0, 0.0, 5.0))  # behind the camera
    behind = renderer.render([DrawMesh(p, t)], front_camera())
    assert np.all(behind.mask == 0) and np.all(np.isinf(behind.depth))


def test_texture_orientation_and_repeat(renderer):
    texture, colors = quadrant_texture()
    # The quad fills the frame: world lower-left corner gets st (0, 0).
    cam = front_camera((64, 64))
    d = 2.0
    half = d * cam.horizontal_aperture / cam.focal_length / 2  # image half-width at depth d
    p, t, uv = quad([[-half, -half, -d], [half, -half, -d], [half, half, -d], [-half, half, -d]])
    maps = renderer.render([DrawMesh(p, t, corner_uv=uv, texture=texture)], cam)
    assert np.all(maps.mask == 1)
    # Quadrant centres of the image, away from the bilinear blend across quadrant borders.
    np.testing.assert_allclose(maps.albedo[16, 16], colors[0, 0], atol=1e-6)  # top-left texel
    np.testing.assert_allclose(maps.albedo[16, 48], colors[0, 1], atol=1e-6)
    np.testing.assert_allclose(maps.albedo[48, 16], colors[1, 0], atol=1e-6)  # st (0, 0)
    np.testing.assert_allclose(maps.albedo[48, 48], colors[1, 1], atol=1e-6)
    # st over [0, 2] repeats the texture twice each way.
    tiled = renderer.render([DrawMesh(p, t, corner_uv=uv * 2, texture=texture)], cam)
    for row, col in ((8, 8), (8, 40), (40, 8), (40, 40)):
        np.testing.assert_allclose(tiled.albedo[row, col], colors[0, 0], atol=1e-6)


def test_sample_bilinear_matches_texel_centres():
    texture = np.random.default_rng(1).random((3, 5, 3)).astype(np.float32)
    rows, cols = np.mgrid[:3, :5]
    # st's v counts from the bottom row.
    st = np.stack([(cols + 0.5) / 5, (3 - rows - 0.5) / 3], -1).reshape(-1, 2)
    np.testing.assert_allclose(sample_bilinear(texture, st), texture.reshape(-1, 3), atol=1e-6)
    # Half-way between the last and first column wraps around.
    mid = sample_bilinear(texture, np.array([[1.0, (3 - 0.5) / 3]]))
    np.testing.assert_allclose(mid[0], (texture[0, 0] + texture[0, 4]) / 2, atol=1e-6)


def test_welded_uv_vertices_reproduce_every_corner():
    mesh = textured_sphere(rings=6, segments=8)
    remap, uv, index, chart = weld_corners(mesh.triangles, mesh.corner_uv)
    np.testing.assert_array_equal(remap[index], mesh.triangles)
    np.testing.assert_array_equal(uv[index], mesh.corner_uv)
    np.testing.assert_array_equal(chart, 0)
    # Only the seam column (u = 1 next to u = 0) and the poles' per-segment uvs add vertices.
    assert len(mesh.points) < len(remap) < mesh.triangles.size
    # With charts every triangle's three vertices carry its chart (a flat varying is exact),
    # and only corners on a chart border are added.
    charts = (np.arange(len(mesh.triangles)) % 3 + 1).astype(np.int32)
    remap2, uv2, index2, chart2 = weld_corners(mesh.triangles, mesh.corner_uv, charts)
    np.testing.assert_array_equal(remap2[index2], mesh.triangles)
    np.testing.assert_array_equal(uv2[index2], mesh.corner_uv)
    np.testing.assert_array_equal(chart2[index2], np.repeat(charts[:, None], 3, axis=1))
    assert len(remap) < len(remap2) <= mesh.triangles.size


def test_edge_pixels_are_premultiplied(renderer):
    cam = front_camera((32, 24))
    d, color = 2.0, np.array([0.9, 0.5, 0.1], np.float32)
    # A left edge at image x = 10.5 covers one of the two sample columns (10.25, 10.75).
    x_edge = (10.5 - cam.cx) * d / cam.fx
    p, t, _ = quad([[x_edge, -5, -d], [5, -5, -d], [5, 5, -d], [x_edge, 5, -d]])
    maps = renderer.render([DrawMesh(p, t, color=color)], cam)
    edge = maps.mask[:, 10]
    assert np.all(edge == 0.5)
    np.testing.assert_allclose(maps.albedo[:, 10], edge[:, None] * color, rtol=FLOAT32_RTOL)
    # Depth and normal come from the covered sample, not blended with the empty one.
    np.testing.assert_allclose(maps.depth[:, 10], d, rtol=FLOAT32_RTOL)
    assert np.all(maps.mask[:, :10] == 0) and np.all(maps.mask[:, 11:] == 1)


def test_more_samples_per_axis():
    cam = front_camera((32, 24))
    p, t, _ = quad([[-0.1, -0.1, -2], [0.5, -0.1, -2.1], [0.4, 0.5, -2.2], [-0.2, 0.4, -2]])
    maps = {}
    for spec in (gl_module.SPEC, embree_module.SPEC):
        if spec.unavailable():
            continue
        r = spec.create(RenderSettings(samples_per_axis=3))
        maps[spec.name] = r.render([DrawMesh(p, t)], cam)
        r.close()
        levels = maps[spec.name].mask * 9
        np.testing.assert_allclose(levels, np.round(levels), atol=1e-5)
    if len(maps) == 2:
        assert agreement(maps["gl"], maps["embree"])["mask_iou"] >= MIN_MASK_IOU


# --- caching ----------------------------------------------------------------------------------
SPECS = {"gl": gl_module.SPEC, "embree": embree_module.SPEC}


def test_rerender_with_changed_points_is_not_stale(renderer):
    p, t = icosphere(2, radius=0.5)
    cam = camera()
    mesh = DrawMesh(p.copy(), t, color=(0.5, 0.5, 0.5))
    first = renderer.render([mesh], cam)
    mesh.points += np.float32(0.4)  # in place: renderers re-read points every call
    moved = renderer.render([mesh], cam)
    assert not np.array_equal(first.mask, moved.mask)
    fresh = SPECS[renderer.name].create(RenderSettings())
    expected = fresh.render([DrawMesh(p + np.float32(0.4), t, color=(0.5, 0.5, 0.5))], cam)
    fresh.close()
    for name in ("mask", "depth", "normal", "albedo"):
        np.testing.assert_array_equal(getattr(moved, name), getattr(expected, name), err_msg=name)
    # New arrays for topology and colour are picked up; a mesh left out is not drawn.
    mesh.triangles = t[: len(t) // 2].copy()
    half = renderer.render([mesh], cam)
    assert 0 < half.mask.sum() < moved.mask.sum()
    mesh.color = (0.1, 0.9, 0.1)
    recoloured = renderer.render([mesh], cam)
    covered = recoloured.mask == 1
    np.testing.assert_allclose(
        recoloured.albedo[covered], [[0.1, 0.9, 0.1]] * covered.sum(), atol=1e-6
    )
    other = DrawMesh(*icosphere(1, 0.3, center=(-0.8, 0.0, 0.0)))
    both = renderer.render([mesh, other], cam)
    alone = renderer.render([mesh], cam)
    np.testing.assert_array_equal(alone.mask, half.mask)
    assert both.mask.sum() > alone.mask.sum()


def test_frozen_points_are_kept_and_new_or_writeable_ones_are_reread(renderer):
    """DrawMesh: frozen (read-only) arrays may be kept between calls (embree keeps its scene);
    a new frozen array, or a writeable one edited in place, is always drawn as it is now."""
    from rigspace.sdk.render import freeze, frozen

    p, t = icosphere(2, radius=0.5)
    cam = camera()
    points = p.copy()
    freeze(points, t)
    assert frozen(points) and not frozen(p) and not frozen(p[:4].view())
    view = p.view()
    view.flags.writeable = False
    assert not frozen(view)  # its owner can still write
    first = renderer.render([DrawMesh(points, t)], cam)
    np.testing.assert_array_equal(renderer.render([DrawMesh(points, t)], cam).mask, first.mask)
    moved = points + np.float32(0.4)
    freeze(moved)
    shifted = renderer.render([DrawMesh(moved, t)], cam)
    assert not np.array_equal(shifted.mask, first.mask)
    writeable = moved.copy()
    again = renderer.render([DrawMesh(writeable, t)], cam)
    np.testing.assert_array_equal(again.mask, shifted.mask)
    writeable -= np.float32(0.4)  # in place: a writeable array is re-read every call
    np.testing.assert_array_equal(renderer.render([DrawMesh(writeable, t)], cam).mask, first.mask)


def test_embree_builds_a_frozen_scene_once_and_matches_embreex():
    """The ctypes binding (sdk/render/embree_api.py) against embreex's own ray casting, and
    the embree renderer's scene kept for frozen arrays only."""
    reason = embree_module.unavailable()
    if reason is not None:  # embreex is a dependency; a broken install is the only way here
        pytest.skip(f"the embree renderer cannot run here: {reason}")
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    from rigspace.sdk.render import embree_api, freeze

    p, t = icosphere(3, radius=0.5)
    rng = np.random.default_rng(1)
    origins = np.tile(np.float32([0, 0, 3]), (5000, 1))
    directions = np.float32([0, 0, -1]) + rng.normal(0, 0.15, (5000, 3)).astype(np.float32)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    far = np.full(5000, 10, np.float32)
    device = embree_api.Device()
    ours = embree_api.TriangleScene(device, [(p, t)]).intersect(origins, directions, far)
    reference = rtcore_scene.EmbreeScene()
    TriangleMesh(reference, p, t)
    theirs = reference.run(origins, directions, dists=far, output=1)
    np.testing.assert_array_equal(ours["geomID"], theirs["geomID"])
    hit = theirs["geomID"] >= 0
    assert 1000 < hit.sum() < 5000
    np.testing.assert_allclose(ours["tfar"][hit], theirs["tfar"][hit], atol=1e-5)
    device.close()

    renderer = embree_module.EmbreeRenderer(RenderSettings())
    built = []
    real = embree_api.TriangleScene
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(embree_api, "TriangleScene", lambda *a: built.append(1) or real(*a))
        freeze(p, t)
        for _ in range(3):
            renderer.render([DrawMesh(p, t)], camera())
        assert len(built) == 1  # one scene for three views of one frozen pose
        for _ in range(2):
            renderer.render([DrawMesh(p.copy(), t)], camera())
        assert len(built) == 3  # a writeable array is built every call
    renderer.close()


def test_auto_prefers_embree_for_a_heavy_frame_on_a_software_gl(monkeypatch, capsys):
    from rigspace.sdk.render import HEAVY_TRIANGLES

    spec = dataclasses.replace(gl_module.SPEC, cost_grows_with_triangles=lambda: True)
    monkeypatch.setattr(gl_module, "SPEC", spec)
    assert choose_renderer(None, triangles=HEAVY_TRIANGLES + 1).name == "embree"
    assert "raster slowly on this machine's gl (a software rasteriser; --renderer gl" in (
        capsys.readouterr().err
    )
    if gl_module.unavailable() is None:
        assert choose_renderer(None, triangles=HEAVY_TRIANGLES).name == "gl"
        assert choose_renderer("gl", triangles=10 * HEAVY_TRIANGLES).name == "gl"
        gpu = dataclasses.replace(gl_module.SPEC, cost_grows_with_triangles=lambda: False)
        monkeypatch.setattr(gl_module, "SPEC", gpu)  # a GPU's GL
        assert choose_renderer(None, triangles=10 * HEAVY_TRIANGLES).name == "gl"


def test_new_texture_array_is_uploaded(renderer):
    cam = front_camera((16, 16))
    p, t, uv = quad([[-5, -5, -2], [5, -5, -2], [5, 5, -2], [-5, 5, -2]])
    mesh = DrawMesh(p, t, corner_uv=uv, texture=np.full((4, 4, 3), 0.25, np.float32))
    np.testing.assert_allclose(renderer.render([mesh], cam).albedo, 0.25, atol=1e-6)
    mesh.texture = np.full((4, 4, 3), 0.75, np.float32)
    np.testing.assert_allclose(renderer.render([mesh], cam).albedo, 0.75, atol=1e-6)


def test_same_topology_twice_in_one_call(renderer):
    p, t = icosphere(1, radius=0.3)
    cam = camera()
    left, right = p - np.float32([0.6, 0, 0]), p + np.float32([0.6, 0, 0])
    both = renderer.render([DrawMesh(left, t), DrawMesh(right, t)], cam)
    one = renderer.render([DrawMesh(left, t)], cam)
    two = renderer.render([DrawMesh(right, t)], cam)
    np.testing.assert_allclose(both.mask, np.maximum(one.mask, two.mask))


def test_two_gl_renderers_keep_their_own_contexts(gl_renderer):
    p, t = icosphere(2, radius=0.5)
    cam = camera()
    other = gl_module.SPEC.create(RenderSettings(samples_per_axis=1))
    try:
        a1 = gl_renderer.render([DrawMesh(p, t)], cam)
        b1 = other.render([DrawMesh(p + np.float32(0.3), t)], cam)
        a2 = gl_renderer.render([DrawMesh(p, t)], cam)
    finally:
        other.close()
    np.testing.assert_array_equal(a1.depth, a2.depth)
    assert not np.array_equal(a1.mask, b1.mask)


def test_close_is_final_and_idempotent():
    for spec in SPECS.values():
        if spec.unavailable():
            continue
        r = spec.create(RenderSettings())
        r.close()
        r.close()
    if gl_module.unavailable() is None:
        r = gl_module.SPEC.create(RenderSettings())
        r.close()
        with pytest.raises(RuntimeError, match="after close"):
            r.render([], front_camera())


# --- inputs -------------------------------------------------------------------------------------
def test_vertex_normals_point_outward_with_unit_length():
    p, t = icosphere(2)
    n = vertex_normals(p, t)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=UNIT_TOLERANCE)
    assert np.all((n * p).sum(1) > 0.99)
    lonely = vertex_normals(np.concatenate([p, [[9, 9, 9]]]), t)
    assert np.all(lonely[-1] == 0)


def test_mesh_errors_name_the_mesh():
    p, t = icosphere(0)
    with pytest.raises(ValueError, match=r"DrawMesh ball: triangle indices"):
        mesh_arrays(DrawMesh(p, t + 1, name="ball"))
    with pytest.raises(ValueError, match=r"DrawMesh ball: points must have shape \(\?,3\)"):
        mesh_arrays(DrawMesh(p[:, :2], t, name="ball"))
    with pytest.raises(ValueError, match="texture but no corner_uv"):
        mesh_arrays(DrawMesh(p, t, texture=np.zeros((2, 2, 3)), name="ball"))
    with pytest.raises(ValueError, match="color"):
        mesh_arrays(DrawMesh(p, t, color=np.zeros((3, 3)), name="ball"))
    with pytest.raises(ValueError, match="samples_per_axis"):
        RenderSettings(samples_per_axis=0)


# --- choosing a renderer -------------------------------------------------------------------------
def test_both_builtins_are_found():
    plugins = renderer_plugins()
    assert {"gl", "embree"} <= set(plugins.specs), plugins.failed
    assert embree_module.SPEC.unavailable() is None


def test_auto_prefers_gl(capsys):
    if gl_module.unavailable() is not None:
        pytest.skip(f"the gl renderer cannot run here: {gl_module.unavailable()}")
    assert choose_renderer(None).name == "gl"
    assert choose_renderer("auto").name == "gl"
    assert capsys.readouterr().err == ""


def test_auto_falls_back_to_embree_with_one_line(monkeypatch, capsys):
    reason = "EGL could not create a context: test"
    monkeypatch.setattr(
        gl_module, "SPEC", dataclasses.replace(gl_module.SPEC, unavailable=lambda: reason)
    )
    assert choose_renderer(None).name == "embree"
    err = capsys.readouterr().err
    assert err == f"rigspace: the gl renderer is unavailable ({reason}); using embree\n"


def test_an_unavailable_named_renderer_is_an_error(monkeypatch):
    monkeypatch.setattr(
        gl_module, "SPEC", dataclasses.replace(gl_module.SPEC, unavailable=lambda: "no EGL here")
    )
    with pytest.raises(RigspaceError, match="The gl renderer cannot run here: no EGL here") as info:
        choose_renderer("gl")
    assert "embree" in info.value.fix
    assert choose_renderer("embree").name == "embree"
    with pytest.raises(RigspaceError, match="no renderer plugin called 'vulkan'"):
        choose_renderer("vulkan")
    monkeypatch.setattr(
        embree_module,
        "SPEC",
        dataclasses.replace(embree_module.SPEC, unavailable=lambda: "no embreex"),
    )
    with pytest.raises(RigspaceError, match="No renderer can run here"):
        choose_renderer("auto")

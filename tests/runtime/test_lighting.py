"""UsdLux lights at a time code and the deferred shading shared by characters and prims."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdLux

from rigspace.runtime.lighting import CompiledLighting, NumpyLighting, reshade
from rigspace.runtime.lights import AMBIENT, DISTANT, POINT, Light, light_prims, lights_at
from rigspace.runtime.shading import SPECULAR, shade
from rigspace.sdk.camera import Camera
from rigspace.sdk.render import Maps
from tests.conftest import REPO

SHADE_TOLERANCE = 1e-5


def stage(meters_per_unit: float = 1.0) -> Usd.Stage:
    s = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(s, meters_per_unit)
    UsdGeom.SetStageUpAxis(s, "Y")
    return s


def test_distant_light_shines_along_its_minus_z_with_exposure_and_color():
    s = stage()
    sun = UsdLux.DistantLight.Define(s, "/Sun")
    sun.CreateIntensityAttr(2.0)
    sun.CreateExposureAttr(1.0)
    sun.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))
    sun.AddRotateXOp().Set(-90.0)  # -Z turned to point down
    (light,) = lights_at(light_prims(s), 0)
    assert light.kind == DISTANT
    assert np.allclose(light.direction, [0, -1, 0], atol=1e-6)
    assert np.allclose(light.radiance, [4.0, 2.0, 1.0])


def test_lights_follow_time_samples_and_visibility():
    s = stage()
    lamp = UsdLux.SphereLight.Define(s, "/Lamp")
    lamp.CreateRadiusAttr(0.5)
    lamp.CreateIntensityAttr().Set(1.0, 0)
    lamp.GetIntensityAttr().Set(3.0, 10)
    op = lamp.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 0)
    op.Set(Gf.Vec3d(0, 4, 0), 10)
    (at_10,) = lights_at(light_prims(s), 10)
    assert at_10.kind == POINT and np.allclose(at_10.position, [0, 4, 0])
    assert np.allclose(at_10.radiance, 3.0) and at_10.area == pytest.approx(np.pi * 0.25)
    UsdGeom.Imageable(lamp.GetPrim()).MakeInvisible()
    assert lights_at(light_prims(s), 10) == []
    UsdLux.DomeLight.Define(s, "/Sky").CreateIntensityAttr(0.2)
    (sky,) = lights_at(light_prims(s), 0)
    assert sky.kind == AMBIENT and np.allclose(sky.radiance, 0.2)


def test_previs_scene_lights():
    s = Usd.Stage.Open(str(REPO / "samples" / "scenes" / "previs.usda"))
    kinds = sorted(light.kind for light in lights_at(light_prims(s), 0))
    assert kinds in ([DISTANT, POINT], [AMBIENT, DISTANT, POINT])  # a sun, a lamp, a sky


def facing_plane(depth: float = 2.0, size: int = 8):
    """A camera at the origin looking down -Z at a plane facing it."""
    camera = Camera(np.eye(4), size, size, focal_length=50.0, horizontal_aperture=20.0)
    albedo = np.full((size, size, 3), 0.5, np.float32)
    normal = np.zeros((size, size, 3), np.float32)
    normal[..., 2] = 1.0
    return (
        albedo,
        normal,
        np.full((size, size), depth, np.float32),
        np.ones((size, size), np.float32),
        camera,
    )


def test_head_on_distant_light_is_albedo_times_radiance_plus_a_highlight():
    albedo, normal, depth, mask, camera = facing_plane()
    s = stage()
    UsdLux.DistantLight.Define(s, "/Sun").CreateIntensityAttr(2.0)  # shines along -Z: head on
    lit = shade(albedo, normal, depth, mask, camera, lights_at(light_prims(s), 0))
    centre = lit[4, 4]
    # n.l = 1 and n.h ~ 1 near the centre: diffuse 0.5 * 2, specular ~ 0.04 * 2.
    assert np.allclose(centre, 0.5 * 2 + SPECULAR * 2, atol=2e-3)


def test_no_lights_is_black_and_coverage_scales_everything():
    albedo, normal, depth, mask, camera = facing_plane()
    assert np.all(shade(albedo, normal, depth, mask, camera, []) == 0)
    s = stage()
    UsdLux.DomeLight.Define(s, "/Sky").CreateIntensityAttr(1.0)
    half = shade(albedo * 0.5, normal, depth, mask * 0.5, camera, lights_at(light_prims(s), 0))
    assert np.allclose(half, 0.25, atol=SHADE_TOLERANCE)  # premultiplied in, premultiplied out


@pytest.mark.parametrize("meters_per_unit", [1.0, 0.01])
def test_point_light_falls_off_with_the_square_and_ignores_units(meters_per_unit):
    unit = 1.0 / meters_per_unit  # one metre in scene units
    results = []
    for distance_m in (1.0, 2.0):
        albedo, normal, depth, mask, camera = facing_plane(depth=3.0 * unit)
        s = stage(meters_per_unit)
        lamp = UsdLux.SphereLight.Define(s, "/Lamp")
        lamp.CreateRadiusAttr(0.1 * unit)
        lamp.CreateIntensityAttr(100.0)
        lamp.AddTranslateOp().Set(Gf.Vec3d(0, 0, -(3.0 - distance_m) * unit))
        results.append(
            shade(albedo, normal, depth, mask, camera, lights_at(light_prims(s), 0))[4, 4]
        )
    near, far = results
    assert np.allclose(near / far, 4.0, rtol=0.05)
    expected = 0.5 * 100 * np.pi * 0.01 / 1.0  # albedo * radiance * area / d^2, metres
    assert np.allclose(near, expected, rtol=0.06)


def test_shading_only_covered_pixels_equals_shading_every_pixel():
    from rigspace.runtime.shading import pixel_positions, shade_pixels

    rng = np.random.default_rng(0)
    h, w = 12, 16
    camera = Camera.look_at(
        (1, 2, 5), (0, 0, 0), width=w, height=h, focal_length=35, horizontal_aperture=20
    )
    mask = (rng.random((h, w)) > 0.4).astype(np.float32) * rng.uniform(0.2, 1, (h, w)).astype(
        np.float32
    )
    albedo = rng.random((h, w, 3)).astype(np.float32) * mask[..., None]
    normal = rng.normal(size=(h, w, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    depth = np.where(mask > 0, rng.uniform(3, 6, (h, w)), np.inf).astype(np.float32)
    s = stage()
    UsdLux.DistantLight.Define(s, "/Sun").CreateIntensityAttr(2.0)
    lamp = UsdLux.SphereLight.Define(s, "/Lamp")
    lamp.AddTranslateOp().Set(Gf.Vec3d(1, 1, 1))
    UsdLux.DomeLight.Define(s, "/Sky").CreateIntensityAttr(0.1)
    lights = lights_at(light_prims(s), 0)
    fast = shade(albedo, normal, depth, mask, camera, lights)
    rows, cols = np.indices((h, w)).reshape(2, -1)
    points = pixel_positions(depth.reshape(-1), rows, cols, camera).reshape(h, w, 3)
    every = shade_pixels(albedo, normal, points, mask, camera.world_to_camera, lights)
    assert np.allclose(fast, every, atol=SHADE_TOLERANCE)
    assert np.all(fast[mask == 0] == 0)


# -- reshade (runtime/lighting.py): scattered pixels lit again ----------------------------------


def _gbuffer(h: int, w: int) -> tuple[Maps, Camera]:
    rng = np.random.default_rng(5)
    normal = rng.normal(size=(h, w, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    mask = np.where(rng.random((h, w)) < 0.8, 1.0, rng.random((h, w))).astype(np.float32)
    albedo = (rng.random((h, w, 3)) * mask[..., None]).astype(np.float32)
    depth = rng.uniform(50.0, 80.0, (h, w)).astype(np.float32)
    world = np.eye(4)
    world[:3, 3] = (3.0, 40.0, 10.0)
    return Maps(albedo, normal, depth, mask), Camera(world, w, h, 60.0, w / 2, h / 2)


@pytest.mark.parametrize("lighting", [NumpyLighting(), CompiledLighting()], ids=["numpy", "numba"])
def test_reshade_lights_the_pixels_given_as_the_whole_frame_would(lighting):
    h, w = 40, 64
    maps, camera = _gbuffer(h, w)
    lights = [
        Light(AMBIENT, np.array([0.1, 0.12, 0.15])),
        Light(DISTANT, np.ones(3), direction=np.array([0.3, -0.9, -0.3]) / np.sqrt(0.99)),
        Light(
            POINT, np.full(3, 5.0), position=np.array([10.0, 60.0, -30.0]), area=300.0, radius=5.0
        ),
    ]
    rng = np.random.default_rng(6)
    shadow = [None, rng.random((h, w)).astype(np.float32), rng.random((h, w)).astype(np.float32)]
    whole = lighting.shade(
        maps.albedo, maps.normal, maps.depth, maps.mask, camera, lights, visibility=shadow
    )
    beauty = np.full((h, w, 3), -1.0, np.float32)
    pixels = np.flatnonzero((rng.random((h, w)) < 0.05) & (maps.mask > 0))
    pixels = pixels[(pixels % w > 5) & (pixels // w > 3)]  # a window that is not the frame
    reshade(lighting, beauty, maps, camera, lights, pixels, shadow)
    flat, expected = beauty.reshape(-1, 3), whole.reshape(-1, 3)
    assert np.array_equal(flat[pixels], expected[pixels])
    others = np.setdiff1d(np.arange(h * w), pixels)
    assert np.all(flat[others] == -1.0)  # nothing else is written

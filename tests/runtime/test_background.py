"""The background: a DomeLight's colour or latlong texture behind everything, else black."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.runtime.lights import background, light_prims, lights_at
from rigspace.sdk.camera import Camera

WIDTH, HEIGHT = 32, 18


def _stage(tmp_path: Path, build, yaw: float = 0.0) -> Path:
    """A camera at the origin looking along -Z (turned by `yaw` about +Y), a small cube low
    in its view 10 units away, and what `build` adds."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "scene.usda"))
    UsdGeom.SetStageUpAxis(stage, "Y")
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateFocalLengthAttr(35.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.AddRotateYOp().Set(yaw)
    cube = UsdGeom.Cube.Define(stage, "/Cube")
    cube.CreateSizeAttr(1.0)
    ahead = -10 * np.array([np.sin(np.radians(yaw)), 0.2, np.cos(np.radians(yaw))])
    cube.AddTranslateOp().Set(Gf.Vec3d(*ahead))  # 2 units below the horizon
    build(stage)
    stage.Save()
    return tmp_path / "scene.usda"


def _render(scene: Path):
    engine = Engine(scene, EngineSettings(width=WIDTH, height=HEIGHT))
    try:
        return engine.render(0.0)
    finally:
        engine.close()


def test_a_dome_colour_fills_what_nothing_covers(tmp_path):
    def build(stage):
        dome = UsdLux.DomeLight.Define(stage, "/Sky")
        dome.CreateColorAttr(Gf.Vec3f(0.2, 0.4, 0.6))
        dome.CreateIntensityAttr(2.0)
        dome.CreateExposureAttr(1.0)

    frame = _render(_stage(tmp_path, build))
    empty = frame.maps.mask == 0
    assert empty.sum() > 0.8 * WIDTH * HEIGHT and (~empty).any()
    assert np.allclose(frame.beauty[empty], [0.8, 1.6, 2.4], atol=1e-6)
    assert frame.opaque and np.all(frame.alpha == 1.0)
    assert frame.report.background == "/Sky"
    # The cube's fully covered pixels keep their own (ambient-lit) colour.
    solid = frame.maps.mask == 1.0
    assert np.allclose(frame.beauty[solid], frame.maps.albedo[solid] * [0.8, 1.6, 2.4], atol=1e-5)


def test_without_a_dome_the_background_stays_black_and_transparent(tmp_path):
    def build(stage):
        UsdLux.DistantLight.Define(stage, "/Sun")

    frame = _render(_stage(tmp_path, build))
    empty = frame.maps.mask == 0
    assert np.all(frame.beauty[empty] == 0.0)
    assert not frame.opaque and np.array_equal(frame.alpha, frame.maps.mask)
    assert frame.report.background is None


def _latlong(path: Path) -> None:
    """An 8x4 latlong map: each column its own colour (longitude), the top half brighter."""
    image = np.zeros((4, 8, 3), np.uint8)
    image[..., 0] = np.arange(8)[None, :] * 30  # red (RGB) increases with the column
    image[:2, :, 1] = 255  # green above the horizon
    cv2.imwrite(str(path), image[..., ::-1])


@pytest.mark.parametrize(
    ("yaw", "column"),
    [
        (180.0, 4),  # looking along +Z: longitude 0, the map's middle column (OpenEXR)
        (-90.0, 2),  # along +X: longitude pi/2, a quarter of the way across
        (90.0, 6),  # along -X: longitude -pi/2
    ],
)
def test_a_latlong_texture_is_sampled_by_the_camera_rays(tmp_path, yaw, column):
    _latlong(tmp_path / "sky.png")

    def build(stage):
        dome = UsdLux.DomeLight.Define(stage, "/Sky")
        dome.CreateTextureFileAttr(Sdf.AssetPath("sky.png"))
        dome.CreateTextureFormatAttr("latlong")
        dome.CreateIntensityAttr(0.5)

    frame = _render(_stage(tmp_path, build, yaw))
    # Just above the horizon and right of the centre ray: the column's red, the upper
    # half's green.
    row, col = HEIGHT // 2 - 2, WIDTH // 2
    assert frame.maps.mask[row, col] == 0
    red = (column * 30 / 255 + 0.055) / 1.055  # sRGB decoded (8-bit textures are sRGB)
    expected = 0.5 * np.array([red**2.4, 1.0, 0.0])
    assert np.allclose(frame.beauty[row, col], expected, atol=2e-3)
    assert frame.beauty[HEIGHT - 1, col, 1] == 0.0  # below the horizon: no green


def test_the_texture_mean_is_the_ambient_light_and_a_rotated_dome_turns_the_sky(tmp_path):
    _latlong(tmp_path / "sky.png")
    stage = Usd.Stage.CreateNew(str(tmp_path / "dome.usda"))
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateTextureFileAttr(Sdf.AssetPath("sky.png"))
    (light,) = lights_at(light_prims(stage), 0)
    # The upper half is green: the mean over the sphere, rows weighted by solid angle.
    assert light.radiance[1] == pytest.approx(0.5, abs=0.02)
    camera = Camera(np.eye(4), WIDTH, HEIGHT, 35.0, 36.0)  # looks along -Z
    ahead = background(light, camera)[HEIGHT // 2 - 2, WIDTH // 2, 0]
    dome.AddRotateYOp().Set(180.0)  # the dome's +Z (longitude 0) now lies along -Z
    (turned,) = lights_at(light_prims(stage), 0)
    behind = background(turned, camera)[HEIGHT // 2 - 2, WIDTH // 2, 0]
    assert ahead == pytest.approx(((0 * 30 / 255 + 0.055) / 1.055) ** 2.4, abs=1e-3)
    assert behind == pytest.approx(((4 * 30 / 255 + 0.055) / 1.055) ** 2.4, abs=1e-3)


def test_a_dome_map_in_another_layout_is_left_out_with_its_name(tmp_path, capsys):
    _latlong(tmp_path / "sky.png")

    def build(stage):
        dome = UsdLux.DomeLight.Define(stage, "/Sky")
        dome.CreateTextureFileAttr(Sdf.AssetPath("sky.png"))
        dome.CreateTextureFormatAttr("mirroredBall")

    frame = _render(_stage(tmp_path, build))
    err = capsys.readouterr().err
    assert "DomeLight /Sky" in err and "latlong" in err
    assert frame.report.lights_left_out and frame.report.background is None
    assert np.all(frame.beauty[frame.maps.mask == 0] == 0.0)

"""The scene's UsdLux lights at a time code, reduced to what the runtime shades with.

DESIGN.md conventions: radiance = intensity * 2^exposure * color (times the blackbody
colour when enableColorTemperature is on); a DistantLight shines along its -Z axis;
SphereLight, RectLight, DiskLight and CylinderLight act as points at their origin with
inverse-square falloff: irradiance = radiance * area / distance^2, where area is the
light's emitting area (pi r^2 for spheres and disks, width * height for rects, 2 r length
for cylinders) in the same units as the distance, so the scene's metersPerUnit cancels
and a lamp is as bright in a centimetre scene as in a metre one. With inputs:normalize on,
the light's power does not depend on its size: area is one square metre. A DomeLight is
uniform ambient light (its texture's mean times its radiance) and the frame's background
(runtime/background.py). For shadows each light keeps its size: a DistantLight's angular
radius (half of inputs:angle) and a point light's radius (its sphere's or disk's, half the
diagonal of a rect). Invisible and deactivated lights are left out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pxr import Usd, UsdGeom, UsdLux

from rigspace.sdk.camera import Camera, from_gf
from rigspace.sdk.errors import SceneError
from rigspace.sdk.geometry import read_texture

DISTANT = "distant"
POINT = "point"
AMBIENT = "ambient"
FLOAT32_MAX = float(np.finfo(np.float32).max)
"""The largest radiance shading can hold (it is float32); NaN compares false with it too."""
POINT_LIGHT_TYPES = (UsdLux.SphereLight, UsdLux.RectLight, UsdLux.DiskLight, UsdLux.CylinderLight)


@dataclass(frozen=True)
class Light:
    kind: str
    """distant, point or ambient."""
    radiance: np.ndarray
    """(3,) linear RGB: intensity * 2^exposure * color."""
    direction: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """distant: the unit direction the light travels, world space."""
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """point: world position, scene units."""
    area: float = 0.0
    """point: emitting area in scene units squared (irradiance = radiance * area / d^2)."""
    path: str = ""
    angle: float = 0.0
    """distant: angular radius in radians (half of inputs:angle); softens shadows."""
    radius: float = 0.0
    """point: the emitter's radius in scene units (its size, whatever inputs:normalize says)."""
    texture: np.ndarray | None = None
    """ambient: the DomeLight's latlong texture times its colour radiance, linear RGB (H, W, 3)
    (`radiance` is then its mean, the ambient term)."""
    orientation: np.ndarray = field(default_factory=lambda: np.eye(3))
    """ambient: world-to-dome rotation (the dome's transform, and its pole onto +Y)."""


def _radiance(light: UsdLux.LightAPI, time: Usd.TimeCode) -> np.ndarray:
    intensity = float(light.GetIntensityAttr().Get(time) or 0.0)
    exposure = float(light.GetExposureAttr().Get(time) or 0.0)
    color = np.asarray(light.GetColorAttr().Get(time) or (1.0, 1.0, 1.0), dtype=np.float64)
    if light.GetEnableColorTemperatureAttr().Get(time):
        kelvin = float(light.GetColorTemperatureAttr().Get(time) or 6500.0)
        color = color * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(kelvin), dtype=np.float64)
    return intensity * 2.0**exposure * color


def emitting_area(
    prim: Usd.Prim, scale: float, meters_per_unit: float, time: Usd.TimeCode
) -> float:
    """A point-approximated light's emitting area in scene units squared."""
    if UsdLux.LightAPI(prim).GetNormalizeAttr().Get(time):
        return 1.0 / meters_per_unit**2  # one square metre
    if prim.IsA(UsdLux.SphereLight):
        r = UsdLux.SphereLight(prim).GetRadiusAttr().Get(time) * scale
        return float(np.pi * r * r)
    if prim.IsA(UsdLux.DiskLight):
        r = UsdLux.DiskLight(prim).GetRadiusAttr().Get(time) * scale
        return float(np.pi * r * r)
    if prim.IsA(UsdLux.RectLight):
        rect = UsdLux.RectLight(prim)
        return float(rect.GetWidthAttr().Get(time) * rect.GetHeightAttr().Get(time) * scale * scale)
    cylinder = UsdLux.CylinderLight(prim)
    return float(
        2 * cylinder.GetRadiusAttr().Get(time) * cylinder.GetLengthAttr().Get(time) * scale * scale
    )


def emitter_radius(prim: Usd.Prim, scale: float, time: Usd.TimeCode) -> float:
    """A point-approximated light's radius in scene units: how wide it looks to a shadow."""
    if prim.IsA(UsdLux.SphereLight):
        return float(UsdLux.SphereLight(prim).GetRadiusAttr().Get(time)) * scale
    if prim.IsA(UsdLux.DiskLight):
        return float(UsdLux.DiskLight(prim).GetRadiusAttr().Get(time)) * scale
    if prim.IsA(UsdLux.RectLight):
        rect = UsdLux.RectLight(prim)
        diagonal = np.hypot(rect.GetWidthAttr().Get(time), rect.GetHeightAttr().Get(time))
        return float(diagonal) * scale / 2
    return float(UsdLux.CylinderLight(prim).GetRadiusAttr().Get(time)) * scale


def light_prims(stage: Usd.Stage) -> list[Usd.Prim]:
    """Every UsdLux light prim of the stage (found once; evaluate them per time with lights_at)."""
    return [prim for prim in stage.Traverse() if prim.HasAPI(UsdLux.LightAPI)]


def lights_at(
    prims: list[Usd.Prim], time: float, on_problem: Callable[[SceneError], None] | None = None
) -> list[Light]:
    """The visible lights among `prims` at `time`.

    A light with a NaN, Inf or float32-overflowing radiance or transform is a SceneError;
    with `on_problem`, it is passed there and the light is left out instead (the runtime:
    one bad light must not end a sequence, nor turn a frame into NaN)."""
    when = Usd.TimeCode(time)
    cache = UsdGeom.XformCache(when)
    lights: list[Light] = []
    for prim in prims:
        if UsdGeom.Imageable(prim).ComputeVisibility(when) == UsdGeom.Tokens.invisible:
            continue
        meters_per_unit = float(UsdGeom.GetStageMetersPerUnit(prim.GetStage()))
        radiance = _radiance(UsdLux.LightAPI(prim), when)
        xf = from_gf(cache.GetLocalToWorldTransform(prim))
        path = str(prim.GetPath())
        problem = _unusable(path, time, radiance, xf)
        if problem is not None:
            if on_problem is None:
                raise problem
            on_problem(problem)
            continue
        if prim.IsA(UsdLux.DistantLight):
            axis = xf[:3, :3] @ np.array([0.0, 0.0, -1.0])
            angle = float(UsdLux.DistantLight(prim).GetAngleAttr().Get(when) or 0.0)
            lights.append(
                Light(
                    DISTANT,
                    radiance,
                    direction=axis / np.linalg.norm(axis),
                    path=path,
                    angle=float(np.radians(abs(angle)) / 2),
                )
            )
        elif any(prim.IsA(t) for t in POINT_LIGHT_TYPES):
            scale = float(np.cbrt(abs(np.linalg.det(xf[:3, :3]))))  # the xform's uniform scale
            area = emitting_area(prim, scale, meters_per_unit, when)
            radius = emitter_radius(prim, scale, when)
            lights.append(
                Light(
                    POINT,
                    radiance,
                    position=xf[:3, 3].copy(),
                    area=area,
                    path=path,
                    radius=abs(radius),
                )
            )
        elif prim.IsA(UsdLux.DomeLight):
            dome = _dome(prim, radiance, xf, path, when, on_problem)
            if dome is not None:
                lights.append(dome)
    return lights


def _unusable(path: str, time: float, radiance: np.ndarray, xf: np.ndarray) -> SceneError | None:
    """Why a light cannot be shaded (a radiance or transform that is not finite in float32),
    or None when it can."""
    # Shading is float32: a radiance beyond its range is Inf there, and Inf * 0 is NaN.
    if np.all(np.abs(radiance) <= FLOAT32_MAX) and np.all(np.isfinite(xf)):
        return None
    return SceneError(
        f"Light {path} at time {time:g}: intensity * 2^exposure * color is "
        f"{radiance.tolist()} and its transform is "
        f"{'finite' if np.all(np.isfinite(xf)) else 'not finite'}.",
        "give inputs:intensity, inputs:exposure, inputs:color and the xformOps finite "
        "values (radiance below 3e38).",
    )


TEXTURE_FORMATS = ("automatic", "latlong")
"""DomeLight texture parameterisations read here (automatic: taken as latlong)."""
_Z_POLE_TO_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Turns +Z onto +Y: a dome whose pole follows a Z-up stage (poleAxis "scene" or "Z")."""


def _dome(
    prim: Usd.Prim,
    radiance: np.ndarray,
    xf: np.ndarray,
    path: str,
    when: Usd.TimeCode,
    on_problem: Callable[[SceneError], None] | None,
) -> Light | None:
    """A DomeLight: ambient radiance (times its texture's mean) and what its background needs;
    None when its texture cannot be used (passed to `on_problem`, which leaves it out)."""
    rotation = xf[:3, :3] / np.cbrt(abs(np.linalg.det(xf[:3, :3])))
    pole = prim.GetAttribute("poleAxis").Get() if prim.HasAttribute("poleAxis") else "scene"
    z_up = UsdGeom.GetStageUpAxis(prim.GetStage()) == UsdGeom.Tokens.z
    to_dome = rotation.T
    if pole == "Z" or (pole == "scene" and z_up):
        to_dome = _Z_POLE_TO_Y @ to_dome
    dome = UsdLux.DomeLight(prim)
    asset = dome.GetTextureFileAttr().Get(when)
    if not asset or not asset.path:
        return Light(AMBIENT, radiance, path=path, orientation=to_dome)
    layout = str(dome.GetTextureFormatAttr().Get(when) or "automatic")
    try:
        if layout not in TEXTURE_FORMATS:
            raise SceneError(
                f"DomeLight {path}: inputs:texture:format is {layout!r}; rigspace reads "
                "latitude-longitude maps only.",
                'convert the map to latlong and set inputs:texture:format = "latlong".',
            )
        texture = read_texture(asset)
    except SceneError as exc:
        problem = (
            exc
            if exc.what.startswith("DomeLight")
            else SceneError(f"DomeLight {path}: {exc.what}", exc.fix)
        )
        if on_problem is None:
            raise problem from exc
        on_problem(problem)
        return None
    # Ambient light is the sphere's mean radiance: rows weighted by their solid angle.
    rows = texture.shape[0]
    weight = np.cos((np.arange(rows) + 0.5) / rows * np.pi - np.pi / 2)
    mean = np.einsum("hwc,h->c", texture, weight) / (weight.sum() * texture.shape[1])
    tinted = (texture * radiance).astype(np.float32)
    return Light(AMBIENT, radiance * mean, path=path, texture=tinted, orientation=to_dome)


def background(light: Light, camera: Camera) -> np.ndarray:
    """(H, W, 3) what a DomeLight shows behind everything, along each camera ray.

    Its colour (intensity * 2^exposure * color), or its latlong texture times that colour,
    sampled nearest by the ray through each pixel centre (OpenEXR's latlong convention,
    which UsdLux follows: longitude 0 towards +Z, pi/2 towards +X, +Y the top row)."""
    if light.texture is None:
        return np.broadcast_to(light.radiance.astype(np.float32), (camera.height, camera.width, 3))
    rows, cols = light.texture.shape[:2]
    x = (np.arange(camera.width, dtype=np.float32) + 0.5 - camera.cx) / camera.fx
    y = (camera.cy - np.arange(camera.height, dtype=np.float32) - 0.5) / camera.fy
    # Ray directions in the dome's frame: camera space -> world -> dome, one 3x3 matrix.
    m = (light.orientation @ camera.camera_to_world[:3, :3]).astype(np.float32)
    d = [m[k, 0] * x[None, :] + m[k, 1] * y[:, None] - m[k, 2] for k in range(3)]
    length = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    longitude = np.arctan2(d[0], d[2])
    latitude = np.arcsin(np.clip(d[1] / length, -1.0, 1.0))
    u = ((np.pi - longitude) / (2 * np.pi) * cols).astype(np.int32) % cols
    v = np.clip(((np.pi / 2 - latitude) / np.pi * rows).astype(np.int32), 0, rows - 1)
    return light.texture[v, u]

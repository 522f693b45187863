"""The scene's UsdLux lights at a time code, reduced to what the runtime shades with.

DESIGN.md conventions: radiance = intensity * 2^exposure * color (times the blackbody
colour when enableColorTemperature is on); a DistantLight shines along its -Z axis;
SphereLight, RectLight, DiskLight and CylinderLight act as points at their origin with
inverse-square falloff: irradiance = radiance * area / distance^2, where area is the
light's emitting area (pi r^2 for spheres and disks, width * height for rects, 2 r length
for cylinders) in the same units as the distance, so the scene's metersPerUnit cancels
and a lamp is as bright in a centimetre scene as in a metre one. With inputs:normalize on,
the light's power does not depend on its size: area is one square metre. A DomeLight is
uniform ambient light. Invisible and deactivated lights are left out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pxr import Usd, UsdGeom, UsdLux

from rigspace.sdk.camera import from_gf
from rigspace.sdk.errors import SceneError

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
        # Shading is float32: a radiance beyond its range is Inf there, and Inf * 0 is NaN.
        if not (np.all(np.abs(radiance) <= FLOAT32_MAX) and np.all(np.isfinite(xf))):
            problem = SceneError(
                f"Light {path} at time {time:g}: intensity * 2^exposure * color is "
                f"{radiance.tolist()} and its transform is "
                f"{'finite' if np.all(np.isfinite(xf)) else 'not finite'}.",
                "give inputs:intensity, inputs:exposure, inputs:color and the xformOps finite "
                "values (radiance below 3e38).",
            )
            if on_problem is None:
                raise problem
            on_problem(problem)
            continue
        if prim.IsA(UsdLux.DistantLight):
            axis = xf[:3, :3] @ np.array([0.0, 0.0, -1.0])
            lights.append(
                Light(DISTANT, radiance, direction=axis / np.linalg.norm(axis), path=path)
            )
        elif any(prim.IsA(t) for t in POINT_LIGHT_TYPES):
            scale = float(np.cbrt(abs(np.linalg.det(xf[:3, :3]))))  # the xform's uniform scale
            area = emitting_area(prim, scale, meters_per_unit, when)
            lights.append(Light(POINT, radiance, position=xf[:3, 3].copy(), area=area, path=path))
        elif prim.IsA(UsdLux.DomeLight):
            lights.append(Light(AMBIENT, radiance, path=path))
    return lights


def scene_lights(stage: Usd.Stage, time: float) -> list[Light]:
    """Every visible, active UsdLux light of the stage at `time`."""
    return lights_at(light_prims(stage), time)

"""`rigspace inspect`: a scene's metrics, the prims rigspace cares about, and validation.

Like a look through usdview's prim browser from the terminal: stage metadata, skeletons,
animations, skinned meshes, cameras, lights and neural characters (every schema value
and applied API), then the findings of USD's validators and rigspace's. Each rigspace
error names the commands that refuse the scene for it (`blocks`: capture, render; they
run the same rules through `validation.require_valid`); USD's own findings are
compliance and stop no command. Exit code 1 when an error stops a command (capture,
render), else 0 (`--strict`: 1 on any error, USD's included); `--json`
prints one object with keys stage, prims, errors, warnings.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from pxr import Usd, UsdGeom, UsdLux, UsdSkel

from rigspace.sdk import schema, validation
from rigspace.sdk.bindings import bound_animation
from rigspace.sdk.cache_rules import cache_frames, control_spans
from rigspace.sdk.character_rules import point_cached_meshes
from rigspace.sdk.cli import CommandSpec
from rigspace.sdk.controls import STILL_VALUE
from rigspace.sdk.stage import meters_per_unit, open_stage, up_axis


def stage_metrics(stage: Usd.Stage) -> dict[str, Any]:
    default_prim = stage.GetDefaultPrim()
    return {
        "path": stage.GetRootLayer().realPath or stage.GetRootLayer().identifier,
        "upAxis": up_axis(stage),
        "metersPerUnit": meters_per_unit(stage),
        "startTimeCode": stage.GetStartTimeCode(),
        "endTimeCode": stage.GetEndTimeCode(),
        "timeCodesPerSecond": stage.GetTimeCodesPerSecond(),
        "framesPerSecond": stage.GetFramesPerSecond(),
        "defaultPrim": str(default_prim.GetPath()) if default_prim else None,
        "layers": len(stage.GetUsedLayers()),
    }


def _triangles(mesh: UsdGeom.Mesh) -> int:
    counts = mesh.GetFaceVertexCountsAttr().Get()
    return int(sum(max(int(c) - 2, 0) for c in counts)) if counts else 0


def _value(value: Any) -> Any:
    """A JSON-friendly version of a USD attribute value."""
    if isinstance(value, float):
        # Attribute values are mostly float32: print what was authored, not the binary noise.
        return float(f"{value:.7g}")
    if value is None or isinstance(value, bool | int | str):
        return value
    if hasattr(value, "path") and hasattr(value, "resolvedPath"):  # Sdf.AssetPath
        return value.path
    if hasattr(value, "GetReal"):  # Gf quaternions
        return [value.GetReal(), *value.GetImaginary()]
    try:
        return [_value(v) for v in value]
    except TypeError:
        return str(value)


def _schema_values(prim: Usd.Prim) -> dict[str, Any]:
    """Every rigspace property of the prim (authored or fallback), relationships as paths."""
    values: dict[str, Any] = {}
    for prop in prim.GetProperties():
        name = prop.GetName()
        if not name.startswith("rigspace:"):
            continue
        if isinstance(prop, Usd.Relationship):
            values[name] = [str(t) for t in prop.GetTargets()]
        else:
            values[name] = _value(prop.Get())
    return values


def _authored(prim: Usd.Prim) -> list[str]:
    """The rigspace properties with an authored opinion (the others show schema fallbacks)."""
    return [
        p.GetName()
        for p in prim.GetAuthoredProperties()
        if p.GetName().startswith("rigspace:")
        and (isinstance(p, Usd.Relationship) or p.HasAuthoredValue())
    ]


def _light_info(prim: Usd.Prim) -> dict[str, Any]:
    light = UsdLux.LightAPI(prim)
    return {
        "intensity": light.GetIntensityAttr().Get(),
        "exposure": light.GetExposureAttr().Get(),
        "color": _value(light.GetColorAttr().Get()),
        "animated": any(
            a.ValueMightBeTimeVarying()
            for a in (light.GetIntensityAttr(), light.GetColorAttr(), light.GetExposureAttr())
        ),
    }


def _camera_info(prim: Usd.Prim) -> dict[str, Any]:
    cam = UsdGeom.Camera(prim)
    xformable = UsdGeom.Xformable(prim)
    return {
        "focalLength": cam.GetFocalLengthAttr().Get(),
        "horizontalAperture": cam.GetHorizontalApertureAttr().Get(),
        "verticalAperture": cam.GetVerticalApertureAttr().Get(),
        "clippingRange": _value(cam.GetClippingRangeAttr().Get()),
        "animated": xformable.TransformMightBeTimeVarying(),
    }


def _rig_info(prim: Usd.Prim) -> dict[str, Any] | None:
    """A character's rig beyond UsdSkel (docs/point_caches.md): its cached frames (the pose
    space), its point-cached meshes, and which controls vary over those frames and which never
    do (None for a UsdSkel-only character)."""
    controls = schema.read_controls(prim)
    if not schema.has_point_cache(prim) and not controls:
        return None
    frames = cache_frames(prim)
    spans = control_spans(prim, frames)
    return {
        "cachedFrames": len(frames),
        "frameRange": [frames[0], frames[-1]] if frames else None,
        "pointCaches": [str(m.GetPath()) for m in point_cached_meshes(prim)[0]],
        "controls": [{"name": c.name, "range": list(c.range)} for c in controls],
        "controlsVarying": [n for n, s in spans.items() if s > STILL_VALUE],
        "controlsConstant": [n for n, s in spans.items() if s <= STILL_VALUE],
    }


def describe_prim(prim: Usd.Prim) -> dict[str, Any] | None:
    """A summary of a prim rigspace cares about, or None for the others."""
    entry: dict[str, Any] = {"path": str(prim.GetPath()), "type": prim.GetTypeName()}
    if schema.is_neural_character(prim):
        entry["kind"] = "neuralCharacter"
        entry["appliedSchemas"] = list(prim.GetAppliedSchemas())
        entry["values"] = _schema_values(prim)
        entry["authored"] = _authored(prim)
        rig = _rig_info(prim)
        if rig is not None:
            entry["rig"] = rig
    elif prim.IsA(UsdSkel.Root):
        entry["kind"] = "skelRoot"
    elif prim.IsA(UsdSkel.Skeleton):
        entry["kind"] = "skeleton"
        entry["joints"] = len(schema.skeleton_joints(prim))
        source = bound_animation(prim)  # its own binding or the SkelRoot's, as UsdSkel reads it
        entry["animationSource"] = str(source.GetPath()) if source else None
    elif prim.IsA(UsdSkel.Animation):
        entry["kind"] = "skelAnimation"
        entry["joints"] = len(UsdSkel.Animation(prim).GetJointsAttr().Get() or [])
        shapes = UsdSkel.Animation(prim).GetBlendShapesAttr().Get() or []
        if shapes:
            entry["blendShapes"] = [str(s) for s in shapes]
        span = validation.animation_time_range(prim)
        entry["timeRange"] = list(span) if span else None
        clips = prim.GetCustomDataByKey("rigspace:clips")
        if clips:
            entry["clips"] = {k: list(v) for k, v in clips.items()}
    elif prim.IsA(UsdGeom.Mesh):
        mesh = UsdGeom.Mesh(prim)
        binding = UsdSkel.BindingAPI(prim)
        skinned = bool(binding.GetJointIndicesPrimvar().IsDefined())
        entry["kind"] = "skinnedMesh" if skinned else "mesh"
        samples = mesh.GetPointsAttr().GetTimeSamples()
        first = samples[0] if samples else Usd.TimeCode.Default()
        entry["points"] = len(mesh.GetPointsAttr().Get(first) or [])
        entry["triangles"] = _triangles(mesh)
        if len(samples) > 1:
            entry["cachedFrames"] = len(samples)
        if skinned:
            entry["influences"] = binding.GetJointIndicesPrimvar().GetElementSize()
            shapes = binding.GetBlendShapesAttr().Get() or []
            if shapes:
                entry["blendShapes"] = [str(s) for s in shapes]
    elif prim.IsA(UsdGeom.Gprim):
        entry["kind"] = "geometry"
        entry["animated"] = UsdGeom.Xformable(prim).TransformMightBeTimeVarying()
    elif prim.IsA(UsdGeom.Camera):
        entry["kind"] = "camera"
        entry.update(_camera_info(prim))
    elif prim.HasAPI(UsdLux.LightAPI):
        entry["kind"] = "light"
        entry.update(_light_info(prim))
    else:
        return None
    return entry


def inspect_stage(stage: Usd.Stage, include_usd_validators: bool = True) -> dict[str, Any]:
    prims = [
        info
        for prim in stage.Traverse(Usd.TraverseInstanceProxies())
        if (info := describe_prim(prim)) is not None
    ]
    findings = validation.validate(stage, include_usd=include_usd_validators)
    return {
        "stage": stage_metrics(stage),
        "prims": prims,
        "errors": [f.as_dict() for f in findings if f.severity == validation.ERROR],
        "warnings": [f.as_dict() for f in findings if f.severity == validation.WARNING],
    }


def _details(info: dict[str, Any]) -> str:
    kind = info["kind"]
    if kind == "skeleton":
        anim = info["animationSource"] or "no animation"
        return f"{info['joints']} joints, animation {anim}"
    if kind == "skelAnimation":
        span = info["timeRange"]
        text = f"{info['joints']} joints, "
        if info.get("blendShapes"):
            text += f"{len(info['blendShapes'])} blend shape weights, "
        text += f"time {span[0]:g}-{span[1]:g}" if span else "no time samples"
        if "clips" in info:
            text += ", clips " + ", ".join(
                f"{k} {a:g}-{b:g}"
                for k, (a, b) in sorted(info["clips"].items(), key=lambda c: c[1])
            )
        return text
    if kind in ("skinnedMesh", "mesh"):
        text = f"{info['points']} points, {info['triangles']} triangles"
        text += f", {info['influences']} influences" if kind == "skinnedMesh" else ""
        text += f", point cache of {info['cachedFrames']} frames" if "cachedFrames" in info else ""
        shapes = info.get("blendShapes")
        return text + (f", blend shapes {', '.join(shapes)}" if shapes else "")
    if kind == "geometry":
        return info["type"] + (", animated" if info["animated"] else "")
    if kind == "camera":
        near, far = info["clippingRange"]
        moving = ", animated" if info["animated"] else ""
        return (
            f"focal {info['focalLength']:g}, aperture {info['horizontalAperture']:g}"
            f"x{info['verticalAperture']:g}, clip {near:g}-{far:g}{moving}"
        )
    if kind == "light":
        color = ", ".join(f"{c:.3g}" for c in info["color"])
        moving = ", animated" if info["animated"] else ""
        return f"intensity {info['intensity']:g}, exposure {info['exposure']:g}, color ({color}){moving}"
    return ""


def _rig_lines(rig: dict[str, Any]) -> list[str]:
    """The lines a character's point caches and controls add to its entry."""
    span = rig["frameRange"]
    where = f" ({span[0]:g}-{span[1]:g})" if span else ""
    caches = rig["pointCaches"]
    lines = [
        f"      pose space: {rig['cachedFrames']} cached frames{where}"
        + (f", point caches {', '.join(caches)}" if caches else ", no point cache")
    ]
    if rig["controls"]:
        lines.append(
            "      controls: "
            + ", ".join(
                f"{c['name']} ({c['range'][0]:g}..{c['range'][1]:g})" for c in rig["controls"]
            )
        )
        lines.append(f"      varying: {', '.join(rig['controlsVarying']) or 'none'}")
        lines.append(
            f"      never varying (cannot be learned): {', '.join(rig['controlsConstant']) or 'none'}"
        )
    return lines


def _count(items: list, noun: str) -> str:
    return f"{len(items)} {noun}{'' if len(items) == 1 else 's'}"


def format_report(report: dict[str, Any], shown_path: str | None = None) -> str:
    """The report as text; `shown_path` replaces the stage's absolute path in the title."""
    s = report["stage"]
    lines = [
        f"Stage {shown_path or s['path']}",
        f"  upAxis {s['upAxis']}, metersPerUnit {s['metersPerUnit']:g}, "
        f"time {s['startTimeCode']:g}-{s['endTimeCode']:g} at {s['timeCodesPerSecond']:g} "
        f"timecodes/s ({s['framesPerSecond']:g} fps), defaultPrim {s['defaultPrim']}, "
        f"{s['layers']} layers",
        "",
        "Prims",
    ]
    width = max((len(p["path"]) for p in report["prims"]), default=0)
    for p in report["prims"]:
        lines.append(f"  {p['path']:<{width}}  {p['kind']:<15} {_details(p)}".rstrip())
        if p["kind"] == "neuralCharacter":
            if p["appliedSchemas"]:
                lines.append(f"      applied: {', '.join(p['appliedSchemas'])}")
            for name, value in p["values"].items():
                fallback = "" if name in p["authored"] else "  (fallback)"
                lines.append(f"      {name} = {json.dumps(value)}{fallback}")
            if "rig" in p:
                lines += _rig_lines(p["rig"])
    if not report["prims"]:
        lines.append("  (none)")
    errors, warnings = report["errors"], report["warnings"]
    refusals = ", ".join(
        f"{command} refuses {sum(command in e['blocks'] for e in errors)}"
        for command in validation.PURPOSES
    )
    lines += [
        "",
        f"Validation: {_count(errors, 'error')} ({refusals}), {_count(warnings, 'warning')}",
    ]
    for finding in errors + warnings:
        where = finding["prim"] or "stage"
        if finding["severity"] != validation.ERROR:
            stops = ""
        elif finding["blocks"]:
            stops = f"  stops {' and '.join(finding['blocks'])}"
        else:
            stops = "  (USD compliance: no rigspace command refuses it)"
        lines.append(
            f"  {finding['severity']:<7} {where}  [{finding['validator']}.{finding['code']}]{stops}"
        )
        lines.append(f"          {finding['message']}")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", help="a .usda, .usdc, .usd or .usdz file")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead")
    parser.add_argument(
        "--no-usd-validators",
        action="store_true",
        help="run only rigspace's validators, not USD's built-in ones",
    )
    parser.add_argument(
        "--strict",
        action="store_true",
        help="exit 1 on any error, USD's own compliance findings included (by default only "
        "errors that stop a rigspace command do)",
    )


def run(args: argparse.Namespace) -> int:
    stage = open_stage(args.scene)
    report = inspect_stage(stage, include_usd_validators=not args.no_usd_validators)
    if args.json:
        json.dump(report, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_report(report, shown_path=args.scene))
    stopping = [e for e in report["errors"] if e["blocks"]]
    return 1 if stopping or (args.strict and report["errors"]) else 0


COMMAND = CommandSpec(
    name="inspect",
    help="print a scene's metrics, characters, cameras, lights and validation findings",
    description=__doc__ or "",
    add_arguments=add_arguments,
    run=run,
)

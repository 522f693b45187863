"""The inspector's stage: prim tree, properties, composition and findings, reloaded from disk."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Any

from pxr import Sdf, Tf, Usd, UsdGeom

from rigspace.sdk import schema, validation
from rigspace.sdk.stage import open_stage

MAX_ITEMS = 12
"""Array values show this many items and their count: a mesh's points would be megabytes."""
MAX_TEXT = 400


def value_json(value: Any, depth: int = 0) -> Any:
    """A short JSON-friendly form of a USD value (arrays cut to MAX_ITEMS, text to MAX_TEXT)."""
    if isinstance(value, float):
        return float(f"{value:.7g}")
    if value is None or isinstance(value, bool | int):
        return value
    if isinstance(value, str):
        return value if len(value) <= MAX_TEXT else value[:MAX_TEXT] + "…"
    if isinstance(value, Sdf.AssetPath):
        return value.path
    if isinstance(value, Sdf.Path):
        return str(value)
    if hasattr(value, "GetReal"):  # Gf quaternions
        return [value.GetReal(), *value.GetImaginary()]
    if isinstance(value, dict):
        return {str(k): value_json(v, depth + 1) for k, v in list(value.items())[: MAX_ITEMS * 4]}
    if depth < 3 and hasattr(value, "__len__") and hasattr(value, "__getitem__"):
        items = [value_json(value[i], depth + 1) for i in range(min(len(value), MAX_ITEMS))]
        if len(value) > MAX_ITEMS:
            return {"count": len(value), "first": items}
        return items
    text = str(value)
    return text if len(text) <= MAX_TEXT else text[:MAX_TEXT] + "…"


def _layer_name(layer: Sdf.Layer) -> str:
    return layer.realPath or layer.identifier


class SceneModel:
    """One opened scene, read for the panels. `poll()` reloads its layers when their files
    change; a layer that no longer parses becomes a finding and the last good content stays."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.stage: Usd.Stage = open_stage(self.path)
        self.lock = threading.RLock()
        """USD reads and reloads are serialised: the server answers from several threads."""
        self.version = 0
        self.load_errors: list[dict[str, Any]] = []
        """Findings for layers whose last edit failed to parse (cleared once they parse)."""
        self._findings: list[dict[str, Any]] | None = None
        self._mtimes = self._read_mtimes()

    # -- reloading -------------------------------------------------------------------------

    def _files(self) -> list[Sdf.Layer]:
        return [layer for layer in self.stage.GetUsedLayers() if layer.realPath]

    def _read_mtimes(self) -> dict[str, int]:
        times: dict[str, int] = {}
        for layer in self._files():
            try:
                times[layer.realPath] = os.stat(layer.realPath).st_mtime_ns
            except OSError:
                times[layer.realPath] = -1
        return times

    def poll(self) -> bool:
        """Reload the layers whose files changed on disk; True when the stage changed."""
        with self.lock:
            now = self._read_mtimes()
            changed = [p for p, t in now.items() if self._mtimes.get(p) != t]
            if not changed:
                return False
            self._mtimes = now
            errors = []
            for layer in self._files():
                if layer.realPath not in changed:
                    continue
                try:
                    layer.Reload(force=True)
                except Tf.ErrorException as exc:
                    # USD keeps the layer's last good content: the stage stays as it was.
                    errors.append(_parse_finding(layer.realPath, exc))
            self.load_errors = errors
            self._findings = None
            self.version += 1
            self._mtimes = self._read_mtimes()  # a reload can add sublayers
            return True

    # -- panels ----------------------------------------------------------------------------

    def cameras(self) -> list[str]:
        with self.lock:
            return [str(p.GetPath()) for p in self.stage.Traverse() if p.IsA(UsdGeom.Camera)]

    def summary(self) -> dict[str, Any]:
        with self.lock:
            stage = self.stage
            cameras = self.cameras()
            return {
                "scene": self.path.name,
                "version": self.version,
                "start": stage.GetStartTimeCode(),
                "end": stage.GetEndTimeCode(),
                "fps": stage.GetFramesPerSecond() or 24.0,
                "timeCodesPerSecond": stage.GetTimeCodesPerSecond(),
                "upAxis": UsdGeom.GetStageUpAxis(stage),
                "metersPerUnit": UsdGeom.GetStageMetersPerUnit(stage),
                "defaultPrim": str(stage.GetDefaultPrim().GetPath())
                if stage.GetDefaultPrim()
                else None,
                "cameras": cameras,
                "layers": self.layers(),
                "used": sorted(
                    _layer_name(layer) for layer in stage.GetUsedLayers() if not layer.anonymous
                ),
            }

    def layers(self) -> list[dict[str, Any]]:
        """The root layer stack (sublayers), strongest first."""
        stack = self.stage.GetLayerStack(includeSessionLayers=False)
        return [
            {"layer": _layer_name(layer), "name": Path(_layer_name(layer)).name,
             "dirty": layer.dirty}
            for layer in stack
        ]  # fmt: skip

    def tree(self) -> list[dict[str, Any]]:
        """Every prim (inactive ones too), depth-first, with what the tree panel shows."""
        with self.lock:
            out = []
            for prim in Usd.PrimRange(self.stage.GetPseudoRoot(), Usd.PrimAllPrimsPredicate):
                if prim.IsPseudoRoot():
                    continue
                applied = list(prim.GetAppliedSchemas())
                out.append(
                    {
                        "path": str(prim.GetPath()),
                        "name": prim.GetName(),
                        "type": prim.GetTypeName(),
                        "depth": prim.GetPath().pathElementCount - 1,
                        "active": prim.IsActive(),
                        "applied": applied,
                        "rigspace": prim.GetTypeName().startswith("Rigspace")
                        or any(a.startswith("Rigspace") for a in applied),
                        "children": bool(prim.GetAllChildren()),
                    }
                )
            return out

    def prim(self, path: str) -> Usd.Prim | None:
        """The prim at `path`, or None (a malformed path is no prim)."""
        if not Sdf.Path.IsValidPathString(path):
            return None
        sdf = Sdf.Path(path)
        if not sdf.IsAbsolutePath() or not sdf.IsPrimPath():
            return None
        prim = self.stage.GetPrimAtPath(sdf)
        return prim if prim else None

    def properties(self, prim: Usd.Prim, time: float) -> dict[str, Any]:
        """The prim's properties at `time`: value, authored or fallback, time samples, targets."""
        with self.lock:
            rows = []
            code = Usd.TimeCode(time)
            for prop in prim.GetProperties():
                row: dict[str, Any] = {"name": prop.GetName(), "custom": prop.IsCustom()}
                if isinstance(prop, Usd.Relationship):
                    row.update(kind="relationship", targets=[str(t) for t in prop.GetTargets()])
                    row["source"] = "authored" if prop.HasAuthoredTargets() else "fallback"
                else:
                    attr = prop
                    samples = attr.GetNumTimeSamples()
                    row.update(
                        kind="attribute",
                        type=str(attr.GetTypeName()),
                        variability="uniform"
                        if attr.GetVariability() == Sdf.VariabilityUniform
                        else "varying",
                        value=value_json(attr.Get(code)),
                        samples=samples,
                        source=_source(attr),
                    )
                rows.append(row)
            return {
                "path": str(prim.GetPath()),
                "type": prim.GetTypeName(),
                "time": time,
                "active": prim.IsActive(),
                "applied": list(prim.GetAppliedSchemas()),
                "metadata": {k: _metadata(v) for k, v in prim.GetAllAuthoredMetadata().items()},
                "properties": rows,
                "bundle": _bundle(prim),
            }

    def composition(self, prim: Usd.Prim) -> dict[str, Any]:
        """Which layer each opinion of the prim and its properties comes from."""
        with self.lock:
            arcs = []
            query = Usd.PrimCompositionQuery(prim)
            for arc in query.GetCompositionArcs():
                node = arc.GetTargetNode()
                arcs.append(
                    {
                        "arc": str(arc.GetArcType()).rsplit(".", 1)[-1].removeprefix("ArcType"),
                        "layer": _layer_name(arc.GetTargetLayer())
                        if arc.GetTargetLayer()
                        else None,
                        "path": str(node.path),
                        "introducedIn": _layer_name(arc.GetIntroducingLayer())
                        if arc.GetIntroducingLayer()
                        else None,
                        "hasSpecs": arc.HasSpecs(),
                    }
                )
            prim_stack = [
                {"layer": _layer_name(spec.layer), "path": str(spec.path),
                 "specifier": str(spec.specifier).rsplit(".", 1)[-1]}
                for spec in prim.GetPrimStack()
            ]  # fmt: skip
            props = []
            for prop in prim.GetProperties():
                stack = [
                    {"layer": _layer_name(spec.layer), "path": str(spec.path)}
                    for spec in prop.GetPropertyStack(Usd.TimeCode.Default())
                ]
                entry: dict[str, Any] = {"name": prop.GetName(), "stack": stack}
                if isinstance(prop, Usd.Attribute):
                    entry["resolvedFrom"] = _source(prop)
                    node = prop.GetResolveInfo().GetNode()
                    entry["node"] = str(node.path) if node else None
                props.append(entry)
            return {
                "path": str(prim.GetPath()),
                "arcs": arcs,
                "primStack": prim_stack,
                "properties": props,
            }

    def findings(self) -> list[dict[str, Any]]:
        """USD's and rigspace's validation findings (inspect's), then layers that failed to
        parse; each names its prim (the panel links it). Cached until the next reload."""
        with self.lock:
            if self._findings is None:
                found = validation.validate(self.stage)
                self._findings = [{**f.as_dict(), "prim": _prim_of(f.prim)} for f in found]
            return [*self.load_errors, *self._findings]


def _metadata(value: Any) -> Any:
    """A metadata value as usdview shows it: list ops as their items, enums by name."""
    if hasattr(value, "GetAddedOrExplicitItems"):  # SdfTokenListOp, SdfPathListOp, ...
        return [str(item) for item in value.GetAddedOrExplicitItems()]
    if isinstance(value, Sdf.Specifier):
        return str(value).removeprefix("Sdf.Specifier").lower()
    return value_json(value)


def _prim_of(site: str) -> str:
    """A finding's prim path: a property site's prim, a layer site as it is."""
    if site and Sdf.Path.IsValidPathString(site):
        path = Sdf.Path(site)
        if path.IsPropertyPath():
            return str(path.GetPrimPath())
    return site


def _source(attr: Usd.Attribute) -> str:
    """Where the attribute's value comes from: authored, its schema's fallback, or nothing."""
    info = attr.GetResolveInfo()
    kind = info.GetSource()
    if kind == Usd.ResolveInfoSourceTimeSamples:
        return "time samples"
    if kind in (Usd.ResolveInfoSourceDefault, Usd.ResolveInfoSourceValueClips):
        return "authored"
    if kind == Usd.ResolveInfoSourceFallback:
        return "fallback"
    return "none"


def _parse_finding(path: str, exc: Exception) -> dict[str, Any]:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    said = next((line for line in lines if path in line), lines[-1] if lines else str(exc))
    return {
        "severity": validation.ERROR,
        "validator": "rigspace:view",
        "code": "LayerParseError",
        "prim": path,
        "message": f"{Path(path).name} no longer parses ({said.strip(chr(39))}); the viewer "
        "keeps its last good content. Fix the file and save it again.",
        "blocks": [],
    }


def _bundle(prim: Usd.Prim) -> dict[str, Any] | None:
    """A neural character's bundle: its manifest's summary and metrics (None for other prims)."""
    if not schema.is_neural_character(prim):
        return None
    manifest = schema.resolve_model_path(schema.read_neural_character(prim))
    if manifest is None:
        return {"error": "rigspace:model does not resolve to a bundle with a manifest.json"}
    try:
        data = json.loads(manifest.read_text())
    except (OSError, ValueError) as exc:
        return {"manifest": str(manifest), "error": f"manifest.json cannot be read: {exc}"}
    levels = [level.get("resolution") for level in data.get("levels", [])]
    training = data.get("training", {})
    return {
        "manifest": str(manifest),
        "format": f"{data.get('format')} v{data.get('format_version')}",
        "joints": len(data.get("joints", [])),
        "blend_shapes": list(data.get("blend_shapes", [])),
        "controls": [
            {"name": str(c.get("name")), "range": list(c.get("range", [0, 1]))}
            for c in data.get("controls") or []
            if isinstance(c, dict)
        ],
        "levels": levels,
        "maps": data.get("maps"),
        "training": {
            "steps": training.get("steps"),
            "preset": training.get("config", {}).get("preset"),
        },
        "metrics": _metric_rows(data.get("metrics", {})),
    }


def _metric_rows(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """The manifest's evaluation: one row per split, precision and predictor."""
    rows = []
    for split, by_precision in metrics.items():
        for precision, table in by_precision.items():
            for row in table.get("rows", []):
                rows.append(
                    {"split": split, "precision": precision,
                     **{k: value_json(v) for k, v in row.items()}}
                )  # fmt: skip
    return rows

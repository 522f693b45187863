"""Run a model bundle with onnxruntime: the trunk once, then only the branches and level asked for.

Shared by `rigspace eval` and the runtime; imports no torch itself. A predictor
(rigspace.sdk.predictors: onnxruntime on the CPU or GPU, or torch) runs the graphs; the
onnxruntime ones create a session per graph when first needed, so a frame that needs only
albedo at 32x32 never loads the other graphs. Outputs are named by the
graphs themselves: albedo graphs give `albedo` and (bundle format 2) `alpha`, geometry
graphs `depth`, `normal` and `mask`; a bundle with a texture head (manifest `texture`) also
gives `chart` and `uv` from its albedo graphs. A pose-conditioned bundle (manifest `conditioning`)
also reads `joints2d` in every graph; it is computed here from the rig parameters with
rigspace.sdk.conditioning (the function training used), so callers pass the rig alone.
"""

from __future__ import annotations

import functools
import hashlib
import json
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.sdk.bundle import BundleError, GraphFiles, ModelManifest, read_manifest
from rigspace.sdk.charts import parse_charts
from rigspace.sdk.conditioning import Skeleton2D, joints2d
from rigspace.sdk.predictors import AUTO, GraphSet, Runner, open_predictor


class BundleModel:
    """A loaded model bundle: `predict(rig, resolution, branches)` -> named maps (NCHW)."""

    def __init__(
        self,
        path: str | Path,
        precision: str = "fp32",
        threads: int = 0,
        predictor: str = AUTO,
        device: str = AUTO,
    ) -> None:
        """`predictor`: a rigspace.sdk.predictors name, or "auto" (the fastest that can run
        this bundle here); `device`: "auto", "cpu" or "cuda[:N]" (predictors that cannot run
        there are passed over); `threads`: intra-op threads of CPU predictors (0: all)."""
        self.manifest: ModelManifest = read_manifest(path)
        manifest = self.manifest
        if manifest.trunk is None or not manifest.levels:
            raise BundleError(
                f"{self.manifest.path} lists no trunk or levels.",
                "re-export the bundle with `rigspace train` from this rigspace version.",
            )
        if precision not in ("fp32", "int8"):
            raise ValueError(f"precision must be 'fp32' or 'int8', got {precision!r}")
        self.precision = precision
        self.levels: dict[int, dict[str, str]] = {}
        self.int8_fallbacks: dict[str, str] = {}
        """int8 graphs the export's check failed (manifest int8_check) -> fp32 graph run instead."""
        offered = manifest.int8_offered_levels
        self.int8_offered: list[int] | None = None if offered is None else list(offered)
        """Levels where int8 met the accuracy aim and was MIN_SPEEDUP faster at export
        (rigspace.train.int8check): the only ones to run int8 at for speed. None: a check
        older than that judgement (every level whose graphs passed is then offered)."""
        self._trunk_file = self._choose_graphs(manifest.trunk, precision)
        self.runner: Runner = open_predictor(
            predictor, GraphSet(self.manifest, precision, threads, self._graph_table(), device)
        )
        """The predictor running the graphs (runner.description says which, on what)."""
        self.depth_scale = manifest.depth_scale
        self.albedo_has_alpha = self.manifest.format_version >= 2
        """Whether the albedo branch alone gives coverage (lets unlit frames skip geometry)."""
        self.joints = list(self.manifest.joints)
        self.blend_shapes: tuple[str, ...] = manifest.blend_shapes
        """Blend shapes whose weights follow the rotations in the rig input (manifest order)."""
        self.controls: tuple[str, ...] = tuple(c.name for c in manifest.controls)
        """Named controls whose values follow the blend shape weights (manifest order)."""
        self.charts = manifest.texture.charts if manifest.texture else 0
        """K texture charts the texture head predicts (0: no texture head)."""
        self.texture_branch = manifest.texture.branch if manifest.texture else "albedo"
        """The branch whose graphs give the texture head's chart and uv outputs: albedo,
        geometry, or texture (a branch of its own, bundle format 4)."""
        top = self.levels[max(self.levels)]
        self.branch_names: tuple[str, ...] = tuple(
            b for b in ("albedo", "geometry", "texture") if b in top
        )
        """The branches the bundle's graphs give (`predict`'s default: all of them)."""
        self._check_texture_branch()
        self.skeleton = Skeleton2D.of_conditioning(manifest.conditioning)
        """The skeleton a pose-conditioned bundle projects (None: the rig is the only input)."""

    def chart_table(self) -> dict[str, Any] | None:
        """The bundle's texture charts (charts.json, rigspace.sdk.charts), None without a head."""
        texture = self.manifest.texture
        if texture is None:
            return None
        path = self.manifest.folder / texture.file
        try:
            table = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise BundleError(
                f"Model bundle {self.manifest.folder}: its texture charts {path.name} cannot be "
                f"read ({exc}).",
                "re-export the bundle with `rigspace train`, or restore the file.",
            ) from exc
        try:
            charts = parse_charts(table)
        except ValueError as exc:
            raise BundleError(
                f"Model bundle {self.manifest.folder}: its texture charts {path.name} cannot be "
                f"used: {exc}.",
                "re-export the bundle with `rigspace train`, or restore the file.",
            ) from exc
        if len(charts) != self.charts:
            raise BundleError(
                f"Model bundle {self.manifest.folder}: {path.name} lists {len(charts)} texture "
                f"charts; its manifest says {self.charts}.",
                "re-export the bundle with `rigspace train`.",
            )
        return table

    def _choose_graphs(self, trunk_files: GraphFiles, precision: str) -> str:
        """Fill `levels` with each level's graph files at `precision` and return the trunk's:
        an int8 graph whose export check failed gives way to its fp32 graph (with a warning)."""
        for level in self.manifest.levels:
            graphs = level.files.int8 if precision == "int8" else level.files.fp32
            if precision == "int8" and not graphs:
                raise BundleError(
                    f"{self.manifest.path} has no int8 graphs.",
                    "evaluate the fp32 graphs, or export with int8 (drop --no-int8).",
                )
            if precision == "int8":
                graphs = {b: self._checked(g, level.files.fp32[b]) for b, g in graphs.items()}
            self.levels[level.resolution] = graphs
        trunk = (trunk_files.int8 if precision == "int8" else trunk_files.fp32)["trunk"]
        if precision == "int8":
            trunk = self._checked(trunk, trunk_files.fp32["trunk"])
        if self.int8_fallbacks:
            warnings.warn(
                f"Model bundle {self.manifest.folder}: int8 graphs "
                f"{', '.join(sorted(self.int8_fallbacks))} failed the export's check against "
                "fp32 (manifest int8_check); their fp32 graphs run instead.",
                stacklevel=3,  # the caller of BundleModel(), as when this ran in __init__
            )
        return trunk

    def _graph_table(self) -> dict[str, tuple[str, int]]:
        """Every graph file the bundle runs -> (its branch, or "trunk", and its resolution)."""
        graphs = {self._trunk_file: ("trunk", 8)}
        for resolution, files in self.levels.items():
            graphs |= {file: (branch, resolution) for branch, file in files.items()}
        return graphs

    def _check_texture_branch(self) -> None:
        """A texture head's branch has graphs (else BundleError)."""
        if self.manifest.texture and self.texture_branch not in self.branch_names:
            raise BundleError(
                f"{self.manifest.path}: its texture head is on the {self.texture_branch} "
                f"branch, which has no graphs (levels list {', '.join(self.branch_names)}).",
                "re-export the bundle with `rigspace train`.",
            )

    def _checked(self, int8: str, fp32: str) -> str:
        if int8 not in self.manifest.int8_failed:
            return int8
        self.int8_fallbacks[int8] = fp32
        return fp32

    @property
    def resolutions(self) -> list[int]:
        return sorted(self.levels)

    def level_for(self, pixels: float, max_level: int | None = None) -> int:
        """The smallest level whose resolution covers `pixels` (else the largest level), at
        most `max_level` (else the smallest level)."""
        levels = self.resolutions
        if max_level is not None:
            levels = [r for r in levels if r <= max_level] or levels[:1]
        for r in levels:
            if r >= pixels:
                return r
        return levels[-1]

    def check_rig(self, rig: np.ndarray) -> np.ndarray:
        rig = np.ascontiguousarray(rig, dtype=np.float32)
        rotations = len(self.joints) * 6
        scalars = (*self.blend_shapes, *self.controls)
        expected = rotations + len(scalars)
        if rig.ndim != 2 or rig.shape[1] != expected:
            weights = (
                f" + {len(self.blend_shapes)} blend shape weights" if self.blend_shapes else ""
            )
            weights += f" + {len(self.controls)} control values" if self.controls else ""
            raise BundleError(
                f"Rig parameters have shape {rig.shape}; the model reads (N, {expected}) "
                f"({len(self.joints)} joints x 6{weights}).",
                "map the skeleton's joints (and blend shapes and controls) to the manifest's "
                "order first.",
            )
        if not np.all(np.isfinite(rig)):
            bad = np.argwhere(~np.isfinite(rig))[0]
            column = int(bad[1])
            what = (
                f"joint {self.joints[column // 6]}"
                if column < rotations
                else f"blend shape {scalars[column - rotations]}"
                if column < rotations + len(self.blend_shapes)
                else f"control {scalars[column - rotations]}"
            )
            raise BundleError(
                f"Rig parameters hold NaN or Inf (sample {bad[0]}, {what}).",
                "check the animation or live source feeding this character.",
            )
        return rig

    def joints2d(self, rig: np.ndarray) -> np.ndarray | None:
        """The conditioning input (N, joints * 2) for rig parameters; None when unconditioned."""
        return None if self.skeleton is None else self._joints2d(rig)

    def _joints2d(self, rig: np.ndarray) -> np.ndarray:
        assert self.skeleton is not None
        return joints2d(self.check_rig(rig), self.skeleton)

    def features(self, rig: np.ndarray, joints2d: np.ndarray | None = None) -> np.ndarray:
        """The trunk's 8x8 features for rig parameters (N, joints * 6)."""
        feeds = {"rig": self.check_rig(rig)}
        if self.skeleton is not None:
            feeds["joints2d"] = joints2d if joints2d is not None else self._joints2d(rig)
        return self.runner.run(self._trunk_file, feeds)["features"]

    def branch(
        self,
        features: np.ndarray,
        branch: str,
        resolution: int,
        joints2d: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        if resolution not in self.levels:
            raise BundleError(
                f"The model has no level {resolution}; it has {self.resolutions}.",
                "ask for one of those resolutions.",
            )
        graph = self.levels[resolution][branch]
        feeds = {"features": features}
        # The 8x8 level's graphs have no block, so no conditioning input (the export drops it).
        if self.skeleton is not None and "joints2d" in self.runner.inputs(graph):
            if joints2d is None:
                raise BundleError(
                    f"Model bundle {self.manifest.folder} is pose-conditioned: its branch graphs "
                    "read joints2d.",
                    "pass joints2d (BundleModel.joints2d(rig)), or call predict(rig, ...).",
                )
            feeds["joints2d"] = joints2d
        return self.runner.run(graph, feeds)

    def predict(
        self, rig: np.ndarray, resolution: int, branches: tuple[str, ...] | None = None
    ) -> dict[str, np.ndarray]:
        """Maps at `resolution` for (N, joints * 6) rig parameters, only of `branches` (None:
        every branch the bundle has, branch_names)."""
        joints2d = self.joints2d(rig)
        features = self.features(rig, joints2d)
        out: dict[str, np.ndarray] = {}
        for branch in self.branch_names if branches is None else branches:
            out.update(self.branch(features, branch, resolution, joints2d))
        return out

    def preload(self, resolutions: Iterable[int] | None = None) -> None:
        """Load every graph now (or the trunk and the levels at `resolutions`), so a missing or
        damaged file fails before a sequence starts."""
        self.runner.load(self._trunk_file)
        wanted = self.levels if resolutions is None else set(resolutions)
        for resolution, level in self.levels.items():
            if resolution in wanted:
                for name in level.values():
                    self.runner.load(name)

    def footprint_bytes(self) -> int:
        files = {self._trunk_file, *(g for level in self.levels.values() for g in level.values())}
        return sum((self.manifest.folder / f).stat().st_size for f in files)


def graphs_problem(folder: Path) -> str | None:
    """Why a bundle's graphs cannot all run, or None: every graph the manifest lists, at every
    level, including levels a run does not use (cached per folder content). inspect and the
    character validator refuse on it; `rigspace eval`, which loads one level, warns with it."""
    stamp = tuple((p.name, p.stat().st_mtime_ns, p.stat().st_size) for p in folder.glob("*"))
    return _check_graphs(folder.resolve(), stamp)


@functools.lru_cache(maxsize=32)
def _check_graphs(folder: Path, _stamp: tuple) -> str | None:
    """Every graph the manifest lists is there with the size and sha256 it records; the trunk,
    and any graph without a record or that differs from it, loads in onnxruntime (the
    runtime's loader, so its words). Loading every graph would triple inspect's time."""
    try:
        model = BundleModel(folder, predictor="onnxruntime")  # checks the ONNX files
        manifest = model.manifest
        assert manifest.trunk is not None  # BundleModel refuses a manifest without one
        sets = [manifest.trunk, *(level.files for level in manifest.levels)]
        graphs = sorted(  # an fp32-only bundle (--no-int8) records its trunk's int8 as null
            {g for s in sets for names in (s.fp32, s.int8) for g in names.values() if g}
        )
        records = manifest.files
        load = {manifest.trunk.fp32["trunk"]}
        changed = []
        for name in graphs:
            path = folder / name
            if not path.is_file():
                return (
                    f"Model file {path} is missing from the bundle. Fix: re-export the bundle, "
                    "or restore the file."
                )
            record = records.get(name)
            if not record or _differs(path, record):
                load.add(name)
                changed += [name] if record else []
        for name in sorted(load):
            model.runner.load(name)  # the runtime loader: its errors, word for word
    except BundleError as exc:
        return str(exc)
    except (KeyError, TypeError, AttributeError) as exc:  # a manifest that lacks what it lists
        return (
            f"Model bundle {folder}: manifest.json is incomplete ({type(exc).__name__}: {exc}). "
            "Fix: re-export the bundle with `rigspace train`."
        )
    if changed:
        return (
            f"Model bundle {folder}: {', '.join(changed)} differ from the size and sha256 "
            "manifest.json records (changed after export). Fix: re-export the bundle with "
            "`rigspace train`, or restore the files."
        )
    return None


def _differs(path: Path, record: dict) -> bool:
    if path.stat().st_size != record.get("bytes"):
        return True
    return hashlib.sha256(path.read_bytes()).hexdigest() != record.get("sha256")

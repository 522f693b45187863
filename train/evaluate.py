"""Evaluate any predictor of maps against a captured dataset split: metrics, error maps, tables."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np

from rigspace.capture.dataset import PARAMS_FILE, DatasetError, DatasetManifest, read_manifest
from rigspace.capture.ring import SPLITS, TRAIN
from rigspace.sdk.files import write_atomic
from rigspace.sdk.render import Maps
from rigspace.sdk.rotations import rig_inputs
from rigspace.train.data import chart_targets, read_sample, targets_at
from rigspace.train.metrics import (
    MASK_THRESHOLD,
    METRICS,
    TEXTURE_METRICS,
    angle_deg,
    map_metrics,
    psnr,
    texture_metrics,
)
from rigspace.train.stream import ShardSet, is_shards

if TYPE_CHECKING:
    from rigspace.train.regions import Region

HEIGHT_SAMPLES = 16
"""Training samples (evenly spaced) whose masks estimate the character's height."""
PREDICT_BATCH = 32
"""Samples per predict() call: bounds the maps held at once, whatever the split's size."""
FLIP_SAMPLES = 24
"""Samples (evenly spaced among those evaluated) whose albedo FLIP is measured: FLIP takes
about half a second for a 512x512 image on one core, the other metrics milliseconds."""
OPTIONAL_METRICS = ("albedo_flip", *TEXTURE_METRICS)
"""Metrics a report has when some sample has them: FLIP (FLIP_SAMPLES of the samples), and
the texture head's placement (a predictor with `texels_per_st`, maps with charts)."""

# Error-map images: each map becomes a tile at least TILE_MIN pixels wide (nearest upscaling).
TILE_MIN = 128
LABEL_HEIGHT = 18
ROW_LABEL_WIDTH = 44
ALBEDO_ERROR_RANGE = 0.25
"""Albedo |error| (mean over R,G,B) shown full scale: a quarter of the range is a gross error."""
DEPTH_ERROR_PCT_RANGE = 5.0
"""Depth |error| shown full scale, % of the character's height."""
NORMAL_ERROR_RANGE_DEG = 45.0
"""Normal angle error shown full scale."""
DISPLAY_GAMMA = 1 / 2.2
"""Albedo is linear; a display gamma makes dark albedo readable in the PNG (display only)."""


class Predictor(Protocol):
    """Anything that predicts a dataset's maps from its rows (rig parameters, camera).

    `predict` gets row indices into the dataset's params.npz and returns one Maps per row,
    at the dataset's resolution, in the dataset's conventions (sdk/exr.py). A predictor
    may also expose `footprint_bytes: int`, what it keeps in memory to predict (a model:
    the size of its .onnx files; a baseline: its captured maps); tables report it.
    """

    name: str

    def predict(self, indices: np.ndarray) -> list[Maps]: ...


class DatasetTable:
    """A captured dataset's manifest and parameter table, and its maps read on demand.

    Columns of params.npz load on first use (`column`) and stay cached; maps are read from
    their EXRs each time (datasets are far larger than memory at the paper's scale). With
    `resolution` below the captured one, `maps` returns the captured maps box-downsampled
    to it (downsample_maps: the targets training makes, train.data.targets_at), so a model
    whose top level is below the capture's resolution is evaluated the way it was trained.
    """

    def __init__(self, folder: str | Path, resolution: int | None = None) -> None:
        self.folder = Path(folder)
        self.manifest: DatasetManifest = read_manifest(self.folder)
        self._params = np.load(self.folder / PARAMS_FILE, allow_pickle=False)
        self._columns: dict[str, np.ndarray] = {}
        self._shard_sets: dict[int, ShardSet] = {}
        self._rows_of: dict[int, np.ndarray] = {}
        captured = self.captured_resolution
        self.factor = 1 if resolution is None else captured // max(int(resolution), 1)
        if resolution is not None and (
            resolution > captured or self.factor * resolution != captured
        ):
            raise DatasetError(
                f"{self.folder} is captured at {captured}x{captured}; {resolution}x{resolution} "
                "targets cannot be made from it by box downsampling.",
                f"evaluate at {captured} or a resolution that divides it.",
            )

    def column(self, name: str) -> np.ndarray:
        """One params.npz column (docs/capture.md lists them), one row per sample."""
        if name not in self._columns:
            if name not in self._params.files:
                raise DatasetError(
                    f"{self.folder / PARAMS_FILE} has no column {name!r} "
                    f"(it has {', '.join(sorted(self._params.files))}).",
                    "re-capture the dataset with this version of rigspace.",
                )
            self._columns[name] = self._params[name]
        return self._columns[name]

    def rig_inputs(self, indices: np.ndarray) -> np.ndarray:
        """The network's input rows of samples `indices`: rig parameters, then blend shape
        weights and controls' values when the dataset has them
        (rigspace.sdk.rotations.rig_inputs)."""
        blend, controls = (
            self.column(name)[indices] if name in self._params.files else None
            for name in ("blend", "controls")
        )
        return rig_inputs(self.column("rig")[indices], blend, controls)

    def __len__(self) -> int:
        return len(self.column("path"))

    @property
    def captured_resolution(self) -> int:
        return self.manifest.resolution

    @property
    def resolution(self) -> int:
        """The resolution of `maps` (the captured one unless the table downsamples)."""
        return self.captured_resolution // self.factor

    def indices(self, split: str) -> np.ndarray:
        """Row indices of a split ("train", "heldout-views", "heldout-clips"), ascending."""
        if split not in SPLITS:
            raise DatasetError(f"Unknown split {split!r}.", f"choose one of {', '.join(SPLITS)}.")
        rows = np.flatnonzero(self.column("split") == SPLITS.index(split))
        if rows.size == 0:
            counts = ", ".join(f"{s} {self.manifest.counts.get(s, 0)}" for s in SPLITS)
            raise DatasetError(
                f"Split {split!r} of {self.folder} is empty (samples per split: {counts}).",
                "capture with held-out views (the ring's heldOutViewsPerRing or "
                "heldOutElevations) or held-out clips (heldOutClips), or evaluate another split.",
            )
        return rows

    def path(self, index: int) -> Path:
        return self.folder / str(self.column("path")[index])

    def captured_maps(self, index: int) -> Maps:
        """The captured maps of row `index`, at the captured resolution: from its EXR, or in a
        shards folder (rigspace dataset pack) from its shard."""
        if is_shards(self.folder):
            split = int(self.column("split")[index])
            rows = self._split_rows(split)
            k = int(np.searchsorted(rows, index))
            if self._shard_sets.get(split) is None:
                self._shard_sets[split] = ShardSet(self.folder, SPLITS[split])
            return self._shard_sets[split].maps(k)
        return read_sample(self.folder, self.manifest, str(self.column("path")[index]))

    def _split_rows(self, split: int) -> np.ndarray:
        """The rows of a split in params order: a pack keeps that order within a split."""
        if split not in self._rows_of:
            self._rows_of[split] = np.flatnonzero(self.column("split") == split)
        return self._rows_of[split]

    def maps(self, index: int) -> Maps:
        """The maps of row `index` at `resolution` (box-downsampled when below the capture's)."""
        return downsample_maps(self.captured_maps(index), self.factor)

    @cached_property
    def character_height(self) -> float:
        """The character's height in scene units, estimated once from the captured maps.

        The masked pixels of HEIGHT_SAMPLES evenly spaced training samples are unprojected
        with their depth and the intrinsics to camera space (Y = (cy - y) depth / fy); the
        height is the largest vertical extent (max Y - min Y) found. Samples seen from a
        ring at elevation 0 see the character upright, so the maximum is its standing
        height (or its tallest pose's) to within a pixel.
        """
        rows = self.indices(TRAIN)
        rows = rows[np.unique(np.linspace(0, len(rows) - 1, HEIGHT_SAMPLES).round().astype(int))]
        intrinsics = self.column("intrinsics")
        height = 0.0
        for index in rows:
            maps = self.captured_maps(int(index))  # the intrinsics are the capture's
            inside = (maps.mask >= MASK_THRESHOLD) & np.isfinite(maps.depth)
            if not inside.any():
                continue
            _fx, fy, _cx, cy = intrinsics[index]
            y = np.nonzero(inside)[0] + 0.5  # pixel centres, rows counted down from the top
            vertical = (cy - y) * maps.depth[inside] / fy
            height = max(height, float(vertical.max() - vertical.min()))
        if height <= 0.0:
            raise DatasetError(
                f"The character covers no pixel in the training samples of {self.folder}.",
                "check the capture ring's radius and look-at joint (see contact_sheet.png).",
            )
        return height


def downsample_maps(maps: Maps, factor: int) -> Maps:
    """Maps box-downsampled by `factor` exactly as training makes its targets
    (train.data.targets_at): albedo (premultiplied) and coverage averaged over each box,
    depth and normals averaged over its covered part; empty boxes keep +inf depth and zero
    normals (the dataset's conventions)."""
    if factor == 1:
        return maps
    mask = maps.mask[None].astype(np.float32)
    depth = np.where((mask > 0) & np.isfinite(maps.depth[None]), maps.depth[None], 0.0)
    albedo, coverage, normal, depth = targets_at(
        np.moveaxis(maps.albedo, -1, 0),
        mask,
        np.moveaxis(maps.normal, -1, 0),
        depth.astype(np.float32),
        factor,
    )
    covered = coverage[0] > 0
    chart = uv = None
    if maps.chart is not None and maps.uv is not None:
        # Each box's commonest chart and its own mean st (train.data.chart_targets over boxes
        # of centre 0 and half-size 1, so the coordinates stay st): never across a seam.
        k = int(maps.chart.max(initial=0)) + 1
        identity = (np.zeros((k, 2), np.float32), np.ones((k, 2), np.float32))
        small, st = chart_targets(maps.chart.astype(np.int64), maps.uv, identity, factor)
        chart, uv = small.astype(np.int32), np.moveaxis(st, 0, -1).astype(np.float32)
    return Maps(
        albedo=np.moveaxis(albedo, 0, -1).astype(np.float32),
        normal=np.where(covered[..., None], np.moveaxis(normal, 0, -1), 0.0).astype(np.float32),
        depth=np.where(covered, depth[0], np.inf).astype(np.float32),
        mask=coverage[0].astype(np.float32),
        uv=uv,
        chart=chart,
    )


class Downsampled:
    """A predictor whose maps come at the captured resolution (the captured-view baselines),
    box-downsampled to an evaluation's lower one like the targets (downsample_maps)."""

    def __init__(self, predictor: Predictor, factor: int) -> None:
        self.predictor, self.factor = predictor, factor
        self.name = predictor.name
        self.footprint_bytes = getattr(predictor, "footprint_bytes", None)

    def predict(self, indices: np.ndarray) -> list[Maps]:
        return [downsample_maps(m, self.factor) for m in self.predictor.predict(indices)]


def evenly_spaced(indices: np.ndarray, limit: int | None) -> np.ndarray:
    """`limit` of the indices, evenly spaced from the first to the last (all when None)."""
    if limit is None or limit >= len(indices):
        return indices
    if limit < 1:
        raise DatasetError(f"limit must be at least 1, got {limit}.", "pass a positive limit.")
    return indices[np.unique(np.linspace(0, len(indices) - 1, limit).round().astype(int))]


def _summary(values: np.ndarray) -> dict[str, float]:
    """Mean and median over the samples where the metric is defined (not nan)."""
    defined = values[~np.isnan(values)]
    if defined.size == 0:
        return {"mean": math.nan, "median": math.nan, "count": 0}
    # +inf PSNR (an exact match) makes the mean +inf; the median stays informative.
    return {
        "mean": float(defined.mean()),
        "median": float(np.median(defined)),
        "count": int(defined.size),
    }


def _predict(predictor: Predictor, rows: np.ndarray, table: DatasetTable) -> list[Maps]:
    maps = predictor.predict(rows)
    if len(maps) != len(rows):
        raise RuntimeError(
            f"predictor {predictor.name} returned {len(maps)} maps for {len(rows)} indices."
        )
    size = table.resolution
    for m in maps:
        if m.mask.shape != (size, size):
            raise DatasetError(
                f"Predictor {predictor.name} returns {m.mask.shape[1]}x{m.mask.shape[0]} maps; "
                f"the dataset {table.folder} is {size}x{size}.",
                "evaluate against a dataset captured at the model's resolution "
                "(or the model level of detail that matches it).",
            )
    return maps


def _measure(
    predictor: Predictor,
    table: DatasetTable,
    rows: np.ndarray,
    worst: int,
    regions: Sequence[Region],
) -> tuple[list[dict[str, Any]], dict[int, tuple[dict[str, Any], Maps, Maps]], float, int]:
    """Predict `rows` in batches and measure each sample against the truth: the records (one
    per sample), the `worst` samples' record, prediction and truth by index, the seconds the
    predictions took, and how many predicted an empty mask."""
    height = table.character_height
    flip_rows = set(evenly_spaced(rows, FLIP_SAMPLES).tolist())
    texels_per_st = getattr(predictor, "texels_per_st", None)
    per_sample: list[dict[str, Any]] = []
    kept: dict[int, tuple[dict[str, Any], Maps, Maps]] = {}  # worst so far: record, pred, truth
    seconds, empty = 0.0, 0
    for start in range(0, len(rows), PREDICT_BATCH):
        batch = rows[start : start + PREDICT_BATCH]
        begin = time.perf_counter()
        predicted = _predict(predictor, batch, table)
        seconds += time.perf_counter() - begin
        for index, pred in zip(batch, predicted, strict=True):
            record = _sample_info(table, int(index))
            target = table.maps(int(index))
            record.update(map_metrics(pred, target, height))
            record.update(region_metrics(pred, target, regions))
            if int(index) in flip_rows:
                record["albedo_flip"] = albedo_flip(pred, target)
            if texels_per_st is not None:
                record.update(texture_metrics(pred, target, texels_per_st))
            per_sample.append(record)
            kept[int(index)] = (record, pred, target)
            empty += not np.any(pred.mask >= MASK_THRESHOLD)
        # Keep only the worst so far, so memory stays at `worst` samples' maps.
        worst_now = _worst_first([k[0] for k in kept.values()])[:worst]
        kept = {r["index"]: kept[r["index"]] for r in worst_now}
    return per_sample, kept, seconds, empty


def evaluate(
    predictor: Predictor,
    table: DatasetTable,
    split: str,
    limit: int | None = None,
    worst: int = 4,
    out_dir: str | Path | None = None,
    indices: np.ndarray | None = None,
    regions: Sequence[Region] = (),
) -> dict[str, Any]:
    """Metrics of `predictor` on a split: per sample, aggregated, and the worst samples.

    Each of `regions` (train/regions.py: the whole character, its face) adds the albedo PSNR
    over that region's pixels in the ground truth, `albedo_psnr@NAME`, and its pixel count.

    Samples: the split's rows, or `limit` of them evenly spaced (evenly_spaced), or exactly
    `indices` when given. Every metric (metrics.METRICS) gets its mean and median over the
    samples where it is defined. With `out_dir`, the `worst` samples by albedo PSNR get an
    error-map PNG each (error_map_image) and the report is saved as report JSON (to_json).
    Values may be +inf (PSNR of an exact match) or nan (no pixel to measure); json.dumps
    writes them as Infinity/NaN, to_json as null.
    """
    rows = table.indices(split) if indices is None else np.asarray(indices, dtype=np.int64)
    rows = evenly_spaced(rows, limit) if indices is None else rows
    height = table.character_height
    per_sample, kept, seconds, empty = _measure(predictor, table, rows, worst, regions)
    report: dict[str, Any] = {
        "predictor": predictor.name,
        "dataset": str(table.folder),
        "dataset_checksum": table.manifest.checksum or None,
        "split": split,
        "samples": len(per_sample),
        "indices": [int(i) for i in rows],
        "character_height": height,
        "seconds_per_sample": seconds / max(len(per_sample), 1),
        "footprint_bytes": getattr(predictor, "footprint_bytes", None),
        "empty_masks": empty,
        "metrics": {
            key: _summary(np.array([s.get(key, math.nan) for s in per_sample], np.float64))
            for key in (*METRICS, *(k for k in OPTIONAL_METRICS if any(k in s for s in per_sample)))
        },
        "regions": {r.name: _region_summary(r, per_sample) for r in regions},
        "per_sample": per_sample,
        "worst": [
            {"index": s["index"], "path": s["path"], "albedo_psnr": s["albedo_psnr"]}
            for s in _worst_first(per_sample)[:worst]
        ],
    }
    if out_dir is not None:
        _write_worst(report, kept, Path(out_dir), height)
    return report


def draws_nothing(report: dict[str, Any]) -> str | None:
    """The sentence for a predictor whose mask is empty (no pixel at MASK_THRESHOLD) on every
    sample of an evaluate() report, else None: its IoU 0 and SSIM near 0 measure no image."""
    n = report["samples"]
    if not n or report.get("empty_masks", 0) < n:
        return None
    return (
        f"{report['predictor']} draws nothing: its mask is empty on {n} of {n} samples (no "
        f"pixel's coverage reaches {MASK_THRESHOLD:g}), so its metrics measure an empty image "
        "(untrained, or the wrong bundle for this character?)"
    )


def _write_worst(
    report: dict[str, Any],
    kept: dict[int, tuple[dict[str, Any], Maps, Maps]],
    out: Path,
    height: float,
) -> None:
    """The worst samples' error-map PNGs (named in report["worst"]) and the report JSON."""
    out.mkdir(parents=True, exist_ok=True)
    name = report["predictor"]
    prefix = f"{_safe(name)}_{report['split']}"
    for rank, entry in enumerate(report["worst"]):
        _, pred, target = kept[entry["index"]]
        path = out / f"{prefix}_worst{rank}_{entry['index']:06d}_{Path(entry['path']).stem}.png"
        title = f"{name}  {entry['path']}  PSNR {entry['albedo_psnr']:.1f} dB"
        write_png(path, error_map_image(pred, target, height, title))
        entry["image"] = str(path)
    write_atomic(out / f"{prefix}_report.json", to_json(report))


def albedo_flip(pred: Maps, target: Maps) -> float:
    """Mean FLIP (rigspace.sdk.flip) of the albedo, premultiplied over black as stored, over
    the character's box (either mask's pixels): nan when neither covers a pixel."""
    from rigspace.sdk.flip import mean_flip, region_of

    box = region_of(pred.mask, target.mask)
    return math.nan if box is None else mean_flip(pred.albedo[box], target.albedo[box])


def _region_summary(region: Region, per_sample: list[dict[str, Any]]) -> dict[str, Any]:
    """A region's albedo PSNR over the samples, and its mean pixel count a sample."""
    psnrs = np.array([s[f"albedo_psnr@{region.name}"] for s in per_sample], np.float64)
    pixels = [s[f"pixels@{region.name}"] for s in per_sample]
    return {
        "description": region.description,
        "albedo_psnr": _summary(psnrs),
        "pixels_mean": float(np.mean(pixels or [0])),
    }


def region_metrics(pred: Maps, target: Maps, regions: Sequence[Region]) -> dict[str, float]:
    """Albedo PSNR over each region's pixels in `target` (nan where it shows none)."""
    out: dict[str, float] = {}
    for region in regions:
        pixels = region.pixels(target)
        count = 0 if pixels is None else int(pixels.sum())
        out[f"albedo_psnr@{region.name}"] = (
            psnr(pred.albedo, target.albedo, pixels) if count else math.nan
        )
        out[f"pixels@{region.name}"] = count
    return out


def _worst_first(per_sample: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Samples by albedo PSNR, lowest first; ties (and nan, sorted last) by row index."""
    return sorted(
        per_sample, key=lambda s: (np.nan_to_num(s["albedo_psnr"], nan=np.inf), s["index"])
    )


def _sample_info(table: DatasetTable, index: int) -> dict[str, Any]:
    return {
        "index": index,
        "path": str(table.column("path")[index]),
        "clip": int(table.column("clip")[index]),
        "time": float(table.column("time")[index]),
        "view": int(table.column("view")[index]),
        "azimuth": float(table.column("azimuth")[index]),
        "elevation": float(table.column("elevation")[index]),
    }


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def compare(
    predictors: Sequence[Predictor],
    table: DatasetTable,
    split: str,
    limit: int | None = None,
    out_dir: str | Path | None = None,
    worst: int = 4,
    regions: Sequence[Region] = (),
) -> dict[str, Any]:
    """Evaluate several predictors on the SAME samples; one summary row per predictor.

    Rows hold each metric's mean (and normal_median_deg's median), the predict time per
    sample and the footprint; `reports` keeps each predictor's full evaluate() report.
    """
    rows = evenly_spaced(table.indices(split), limit)
    reports = {
        p.name: evaluate(
            p, table, split, worst=worst, out_dir=out_dir, indices=rows, regions=regions
        )
        for p in predictors
    }
    table_rows = []
    for name, report in reports.items():
        row: dict[str, Any] = {"predictor": name}
        row.update({key: report["metrics"][key]["mean"] for key in METRICS})
        row["normal_median_deg"] = report["metrics"]["normal_median_deg"]["median"]
        for key in OPTIONAL_METRICS:
            if key in report["metrics"]:  # a median's and a percentile's: their median
                summary = report["metrics"][key]
                row[key] = summary["median" if key.startswith("uv_texels") else "mean"]
        row["seconds_per_sample"] = report["seconds_per_sample"]
        row["footprint_bytes"] = report["footprint_bytes"]
        for region, summary in report["regions"].items():
            row[f"albedo_psnr@{region}"] = summary["albedo_psnr"]["mean"]
        table_rows.append(row)
    return {
        "dataset": str(table.folder),
        "split": split,
        "samples": len(rows),
        "resolution": table.resolution,
        "targets": targets_note(table),
        "indices": [int(i) for i in rows],
        "rows": table_rows,
        "reports": reports,
    }


def targets_note(table: DatasetTable) -> str:
    """How the evaluation's targets were made: as captured, or box-downsampled."""
    if table.factor == 1:
        return f"as captured, {table.resolution}x{table.resolution}"
    return (
        f"box-downsampled {table.factor}x from the captured {table.captured_resolution}x"
        f"{table.captured_resolution} to {table.resolution}x{table.resolution}, as training does"
    )


COLUMNS = (
    ("predictor", "predictor", "{}"),
    ("albedo_psnr", "albedo PSNR (dB)", "{:.2f}"),
    ("albedo_ssim", "albedo SSIM", "{:.4f}"),
    ("mask_iou", "mask IoU", "{:.4f}"),
    ("depth_mae", "depth MAE", "{:.4f}"),
    ("depth_mae_pct", "depth MAE (% height)", "{:.2f}"),
    ("normal_mean_deg", "normal mean (deg)", "{:.2f}"),
    ("normal_median_deg", "normal median (deg)", "{:.2f}"),
    ("albedo_flip", "albedo FLIP", "{:.4f}"),
    ("chart_accuracy", "chart right", "{:.3f}"),
    ("uv_texels_median", "uv error median (texels)", "{:.2f}"),
    ("uv_texels_p90", "uv error p90 (texels)", "{:.2f}"),
    ("seconds_per_sample", "ms/sample", "ms"),
    ("footprint_bytes", "footprint (MiB)", "MiB"),
)
"""format_table's columns: key, header, format (an optional metric's only when a row has it)."""


def _cell(value: Any, fmt: str) -> str:
    if value is None:
        return "-"
    if fmt == "ms":
        return f"{1000 * value:.2f}"
    if fmt == "MiB":
        return f"{value / 2**20:.2f}"
    if isinstance(value, float) and not math.isfinite(value):
        return "inf" if value > 0 else ("-inf" if value < 0 else "n/a")
    return fmt.format(value)


def format_table(result: dict[str, Any]) -> str:
    """A compare() result as a Markdown table (means over the samples; normal median: median)."""
    columns = [
        c for c in COLUMNS if c[0] not in OPTIONAL_METRICS or any(c[0] in r for r in result["rows"])
    ]
    lines = [
        f"{result['split']}: {result['samples']} samples of {result['dataset']}"
        + (f" (targets {result['targets']})" if result.get("targets") else ""),
        "",
        "| " + " | ".join(header for _, header, _ in columns) + " |",
        "|" + "|".join("---" for _ in columns) + "|",
    ]
    for row in result["rows"]:
        lines.append("| " + " | ".join(_cell(row.get(k), f) for k, _, f in columns) + " |")
    if any("albedo_flip" in r for r in result["rows"]):
        lines.append(
            f"\nalbedo FLIP: mean over the character's box of {min(FLIP_SAMPLES, result['samples'])} "
            "of the samples (evenly spaced); 0 is identical"
        )
    first: dict[str, Any] = next(iter(result.get("reports", {}).values()), {})
    for name, region in first.get("regions", {}).items():
        if region["pixels_mean"] == 0:  # a named reason, never a bare "n/a"
            lines.append(
                f"\nalbedo PSNR over the {name} ({region['description']}): not measured: no "
                f"sample of the {result['samples']} shows a pixel of it (views from behind, or "
                "targets without texture coordinates; evaluate more samples with --limit 0)"
            )
            continue
        values = ", ".join(
            f"{row['predictor']} {_cell(row.get(f'albedo_psnr@{name}'), '{:.2f}')} dB"
            for row in result["rows"]
        )
        lines.append(
            f"\nalbedo PSNR over the {name} ({region['description']}, "
            f"{region['pixels_mean']:.0f} pixels a sample): {values}"
        )
    return "\n".join(lines) + "\n"


def _strict(value: Any) -> Any:
    if isinstance(value, np.generic):  # numpy scalars (float32, int64) -> Python numbers
        value = value.item()
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_strict(v) for v in value]
    return value


def to_json(report: dict[str, Any]) -> str:
    """A report as strict JSON: non-finite numbers (+inf PSNR, nan) become null (never the
    NaN/Infinity tokens json.dumps writes by default, which strict parsers reject)."""
    return json.dumps(_strict(report), indent=2, allow_nan=False) + "\n"


# --- error-map images ---------------------------------------------------------------------------


def heat_tile(values: np.ndarray, full_scale: float, valid: np.ndarray) -> np.ndarray:
    """(H,W) values -> (H,W,3) uint8 BGR inferno colours, 0..full_scale; black where not valid."""
    scaled = np.clip(np.nan_to_num(values / full_scale), 0.0, 1.0)
    image = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    image[~valid] = 0
    return image


def _gray(values: np.ndarray) -> np.ndarray:
    return np.repeat((np.clip(values, 0.0, 1.0) * 255).astype(np.uint8)[..., None], 3, axis=-1)


def rgb_tile(values: np.ndarray) -> np.ndarray:
    """(H,W,3) RGB in [0, 1] -> (H,W,3) uint8 BGR."""
    return np.ascontiguousarray((np.clip(values, 0.0, 1.0) * 255).astype(np.uint8)[..., ::-1])


def normal_tile(normal: np.ndarray) -> np.ndarray:
    """(H,W,3) normals -> (H,W,3) uint8 BGR, n/2 + 1/2; black where a normal is empty."""
    shown = np.where(np.linalg.norm(normal, axis=-1, keepdims=True) > 0, normal * 0.5 + 0.5, 0.0)
    return rgb_tile(shown)


def _map_tiles(maps: Maps, near: float, far: float) -> list[np.ndarray]:
    """Albedo, mask, depth (near white .. far dark, empty black), normals (n/2 + 1/2)."""
    finite = np.isfinite(maps.depth)
    depth = np.where(finite, 1.0 - 0.8 * (maps.depth - near) / max(far - near, 1e-12), 0.0)
    return [
        rgb_tile(np.clip(maps.albedo, 0.0, None) ** DISPLAY_GAMMA),
        _gray(maps.mask),
        _gray(depth),
        normal_tile(maps.normal),
    ]


def _error_tiles(pred: Maps, target: Maps, character_height: float) -> list[np.ndarray]:
    everywhere = np.ones(target.mask.shape, bool)
    albedo = np.abs(pred.albedo - target.albedo).mean(axis=-1)
    xor = (pred.mask >= MASK_THRESHOLD) != (target.mask >= MASK_THRESHOLD)
    both = np.isfinite(pred.depth) & np.isfinite(target.depth)
    depth = np.abs(np.where(both, pred.depth, 0.0) - np.where(both, target.depth, 0.0))
    lp = np.linalg.norm(pred.normal, axis=-1)
    lt = np.linalg.norm(target.normal, axis=-1)
    normals = (lp > 0) & (lt > 0)
    a = pred.normal / np.where(normals, lp, 1.0)[..., None]
    b = target.normal / np.where(normals, lt, 1.0)[..., None]
    angle = angle_deg(a, b)
    return [
        heat_tile(albedo, ALBEDO_ERROR_RANGE, everywhere),
        _gray(xor.astype(np.float32)),
        heat_tile(depth, DEPTH_ERROR_PCT_RANGE / 100.0 * character_height, both),
        heat_tile(angle, NORMAL_ERROR_RANGE_DEG, normals),
    ]


def put_label(image: np.ndarray, text: str, x: int, y: int, scale: float = 0.4) -> None:
    cv2.putText(
        image, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA
    )


def error_map_image(
    pred: Maps, target: Maps, character_height: float, title: str = ""
) -> np.ndarray:
    """(H,W,3) uint8 BGR picture of one sample: rows prediction | ground truth | error.

    Columns: albedo (display gamma), mask, depth, normals. The error row shows the albedo
    |error| (mean over R,G,B; inferno, full scale ALBEDO_ERROR_RANGE), the mask XOR at
    coverage MASK_THRESHOLD (white = disagree), the depth |error| where both are finite
    (full scale DEPTH_ERROR_PCT_RANGE % of the character's height) and the normal angle
    error (full scale NORMAL_ERROR_RANGE_DEG). Small maps are upscaled by nearest neighbour
    to at least TILE_MIN pixels so every pixel stays visible.
    """
    finite = np.concatenate(
        [target.depth[np.isfinite(target.depth)], pred.depth[np.isfinite(pred.depth)]]
    )
    near, far = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    grid = [
        _map_tiles(pred, near, far),
        _map_tiles(target, near, far),
        _error_tiles(pred, target, character_height),
    ]
    h, w = target.mask.shape
    factor = max(1, -(-TILE_MIN // min(h, w)))  # ceil
    th, tw = h * factor, w * factor
    headers = ["albedo", "mask", "depth", "normal"]
    error_headers = [
        f"|albedo| 0-{ALBEDO_ERROR_RANGE:g}",
        "mask xor",
        f"|depth| 0-{DEPTH_ERROR_PCT_RANGE:g}%h",
        f"angle 0-{NORMAL_ERROR_RANGE_DEG:g}deg",
    ]
    row_names = ["pred", "truth", "error"]
    width = ROW_LABEL_WIDTH + 4 * tw
    height = LABEL_HEIGHT + 3 * (LABEL_HEIGHT + th)  # title, then per row: header and tiles
    image = np.zeros((height, width, 3), np.uint8)
    put_label(image, title, 4, LABEL_HEIGHT - 5)
    for r, tiles in enumerate(grid):
        top = LABEL_HEIGHT * 2 + r * (th + LABEL_HEIGHT)
        names = error_headers if r == 2 else headers
        for c, tile in enumerate(tiles):
            left = ROW_LABEL_WIDTH + c * tw
            put_label(image, names[c], left + 2, top - 5)
            image[top : top + th, left : left + tw] = cv2.resize(
                tile, (tw, th), interpolation=cv2.INTER_NEAREST
            )
        put_label(image, row_names[r], 2, top + th // 2)
    return image


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write a BGR uint8 image; an unwritable path is a DatasetError naming it."""
    if not cv2.imwrite(str(path), image):
        raise DatasetError(f"cannot write {path}.", "choose a writable --out folder.")

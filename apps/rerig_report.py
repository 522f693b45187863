"""A point-cached character's network against the LBS re-rig a studio would otherwise build.

    python -m rigspace.apps.rerig_report DATASET --model BUNDLE --rerig LBS_DATASET --out DIR
        [--split heldout-views] [--limit N] [--sheet K]

DATASET is the capture of a character whose meshes are point caches (the truth: what the
production rig evaluated, docs/point_caches.md); BUNDLE the network trained on it; LBS_DATASET
the capture of the **re-rig**: the same skeleton skinning the rest mesh by linear blend
skinning (what moving the character to a game engine's deformers gives), from the same capture
ring over the same clips, so that each sample of DATASET has its twin there (same time code,
view and camera; a sample without one is an error naming it). The re-rig may be captured
`--every N` frames: the samples of DATASET at frames it did not capture are left out.

For each sample of the split (or `--limit` of them, evenly spaced), the pixels where the truth
**departs from LBS** are those where the two masks disagree, or both cover the pixel and the
depths differ by more than DEPART_DEPTH_CM or the normals by more than DEPART_ANGLE_DEG. Over
those pixels, pooled over the samples, for the network and for the re-rig:

- mask IoU (the predictor's coverage against the truth's);
- normal error (mean and median angle) and depth error (mean, cm), over the departing pixels
  that the truth, the network and the re-rig all cover (the same pixels for both);
- albedo PSNR (premultiplied albedo: coverage errors count).

and over the whole character, per sample then averaged: albedo PSNR, mask IoU, normal error
(rigspace.train.metrics.map_metrics, as `rigspace eval`). Writes DIR/rerig_report.json,
DIR/rerig_report.md and DIR/rerig_sheet.png (the `--sheet` samples where the truth departs most:
truth, re-rig and network normals, the departing pixels, each one's normal error there), all
at the end: nothing is written when a sample fails.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from rigspace.sdk.render import Maps
from rigspace.train.evaluate import (
    DatasetTable,
    evenly_spaced,
    heat_tile,
    normal_tile,
    put_label,
)
from rigspace.train.metrics import MASK_THRESHOLD, angle_deg, map_metrics

DEPART_DEPTH_CM = 0.5
"""Depths further apart than this (centimetres) make a pixel depart from LBS."""
DEPART_ANGLE_DEG = 10.0
"""Normals further apart than this make a pixel depart from LBS."""
MATCH_TOLERANCE = 1e-3
"""The largest difference in a camera-to-world entry between a sample and its twin."""
BATCH = 32
TIMING_REPEATS = 15
"""One-sample predictions timed for the network's cost (network_ms), after a warm-up."""
"""Samples the network predicts at a time."""
TILE = 256
"""The side each 128x128 map is enlarged to (nearest neighbour) in the sheet."""
ERROR_RANGE_DEG = 45.0
"""Normal error shown full scale in the sheet."""
LABEL_SCALE = 0.5
"""The sheet's text size (cv2 font scale): its tiles are twice evaluate's."""


@dataclass
class Tally:
    """One predictor's numbers over the departing pixels, summed over samples."""

    hits: int = 0
    unions: int = 0
    angles: list[np.ndarray] = field(default_factory=list)
    depth_err_cm: list[np.ndarray] = field(default_factory=list)
    albedo_se: float = 0.0
    pixels: int = 0
    whole: list[dict[str, float]] = field(default_factory=list)

    def summary(self) -> dict[str, float]:
        angles = np.concatenate(self.angles) if self.angles else np.zeros(0)
        depth = np.concatenate(self.depth_err_cm) if self.depth_err_cm else np.zeros(0)
        mse = self.albedo_se / max(self.pixels * 3, 1)
        whole = {
            f"whole_{key}": _mean_defined([w[key] for w in self.whole])
            for key in ("albedo_psnr", "mask_iou", "normal_mean_deg")
        }
        return {
            "departing_mask_iou": self.hits / max(self.unions, 1),
            "departing_normal_mean_deg": float(angles.mean()) if angles.size else math.nan,
            "departing_normal_median_deg": float(np.median(angles)) if angles.size else math.nan,
            "departing_depth_mean_cm": float(depth.mean()) if depth.size else math.nan,
            "departing_albedo_psnr": 10.0 * math.log10(1.0 / mse) if mse > 0 else math.inf,
            **whole,
        }


def _mean_defined(values: list[float]) -> float:
    """The mean of the values that are not nan (nan when none is)."""
    defined = [v for v in values if not math.isnan(v)]
    return float(np.mean(defined)) if defined else math.nan


def departing(truth: Maps, lbs: Maps, cm_per_unit: float) -> np.ndarray:
    """(H, W) bool: where the truth departs from LBS (the module docstring's rule)."""
    t, r = truth.mask >= MASK_THRESHOLD, lbs.mask >= MASK_THRESHOLD
    both = t & r
    with np.errstate(invalid="ignore"):
        far = np.abs(truth.depth - lbs.depth) * cm_per_unit > DEPART_DEPTH_CM
    turned = angle_deg(truth.normal, lbs.normal) > DEPART_ANGLE_DEG
    return (t ^ r) | (both & (far | turned))


def with_twin_times(table, twin, rows: np.ndarray) -> np.ndarray:
    """`rows` at the time codes the twin captured (a re-rig captured `--every N` frames)."""
    from rigspace.capture.dataset import DatasetError

    times = np.unique(np.round(twin.column("time"), 3))
    kept = rows[np.isin(np.round(table.column("time")[rows], 3), times)]
    if kept.size == 0:
        raise DatasetError(
            f"{twin.folder} has none of the time codes of {table.folder}'s samples.",
            "capture the re-rig's shot over the same clips (samples/point_cache/README.md).",
        )
    return kept


def match_rows(table, twin, rows: np.ndarray) -> np.ndarray:
    """The row of `twin` with the same time code, view and camera as each of `rows`."""
    from rigspace.capture.dataset import DatasetError

    key = {
        (round(float(t), 3), int(v)): k
        for k, (t, v) in enumerate(zip(twin.column("time"), twin.column("view"), strict=True))
    }
    cameras, twin_cameras = table.column("camera_to_world"), twin.column("camera_to_world")
    out = np.empty(len(rows), np.int64)
    for n, row in enumerate(rows):
        time, view = float(table.column("time")[row]), int(table.column("view")[row])
        k = key.get((round(time, 3), view))
        if k is None or np.abs(cameras[row] - twin_cameras[k]).max() > MATCH_TOLERANCE:
            what = "no sample" if k is None else "a sample with another camera"
            raise DatasetError(
                f"{twin.folder} has {what} at time {time:g}, view {view} "
                f"({table.folder}'s {table.column('path')[row]}).",
                "capture the re-rig's shot with the same capture ring and clips as the cached "
                "character's (samples/point_cache/README.md).",
            )
        out[n] = k
    return out


def measure(
    truth: Maps, pred: Maps, lbs: Maps, depart: np.ndarray, tally: Tally, cm_per_unit: float
) -> None:
    """Add one sample's numbers for one predictor (`pred`) to its tally."""
    t, p = truth.mask >= MASK_THRESHOLD, pred.mask >= MASK_THRESHOLD
    tally.hits += int((t & p & depart).sum())
    tally.unions += int(((t | p) & depart).sum())
    common = depart & t & (lbs.mask >= MASK_THRESHOLD) & p
    a, b = (m.normal[common].astype(np.float64) for m in (pred, truth))  # reported: float64
    tally.angles.append(angle_deg(a, b))
    tally.depth_err_cm.append(np.abs(pred.depth[common] - truth.depth[common]) * cm_per_unit)
    tally.albedo_se += float(((pred.albedo[depart] - truth.albedo[depart]) ** 2).sum())
    tally.pixels += int(depart.sum())


def _error_tile(pred: Maps, truth: Maps, depart: np.ndarray) -> np.ndarray:
    """The normal error, full scale where either side is empty; dimmed off the departing
    pixels."""
    valid = (truth.mask >= MASK_THRESHOLD) & (pred.mask >= MASK_THRESHOLD)
    angle = np.where(valid, angle_deg(pred.normal, truth.normal), ERROR_RANGE_DEG)
    heat = heat_tile(angle, ERROR_RANGE_DEG, np.ones(valid.shape, bool))
    heat[~depart] //= 4
    return heat


def _depart_tile(truth: Maps, depart: np.ndarray) -> np.ndarray:
    gray = (np.clip(np.abs(truth.normal[..., 2]), 0, 1) * 160).astype(np.uint8)
    tile = np.repeat(gray[..., None], 3, axis=-1)
    tile[depart] = (40, 40, 255)
    return tile


HEADERS = ("truth", "LBS re-rig", "network", "departs", "re-rig error", "network error")


def sheet(rows: list[tuple[str, Maps, Maps, Maps, np.ndarray]]) -> np.ndarray:
    """The sheet image (BGR): one row per sample, the columns HEADERS."""
    label_h = 22
    image = np.zeros((label_h + len(rows) * (TILE + label_h), len(HEADERS) * TILE, 3), np.uint8)
    for c, name in enumerate(HEADERS):
        put_label(image, name, c * TILE + 4, 16, LABEL_SCALE)
    for r, (title, truth, lbs, pred, depart) in enumerate(rows):
        tiles = (
            normal_tile(truth.normal),
            normal_tile(lbs.normal),
            normal_tile(pred.normal),
            _depart_tile(truth, depart),
            _error_tile(lbs, truth, depart),
            _error_tile(pred, truth, depart),
        )
        top = label_h + r * (TILE + label_h)
        put_label(image, title, 4, top + 16, LABEL_SCALE)
        for c, tile in enumerate(tiles):
            big = cv2.resize(tile, (TILE, TILE), interpolation=cv2.INTER_NEAREST)
            image[top + label_h : top + label_h + TILE, c * TILE : (c + 1) * TILE] = big
    return image


def run(args: argparse.Namespace) -> tuple[dict, np.ndarray]:
    """Measure; returns the report and the sheet image."""
    from tqdm import tqdm

    from rigspace.train.predictor import BundlePredictor

    table, twin = DatasetTable(args.dataset), DatasetTable(args.rerig)
    rows = evenly_spaced(with_twin_times(table, twin, table.indices(args.split)), args.limit)
    twins = match_rows(table, twin, rows)
    network = BundlePredictor(Path(args.model), table)
    cm_per_unit = 100.0 * (table.manifest.meters_per_unit or 0.01)
    height = table.character_height
    tallies = {"network": Tally(), "LBS re-rig": Tally()}
    most: list[tuple[int, str, Maps, Maps, Maps, np.ndarray]] = []
    with tqdm(total=len(rows), unit="sample", desc="samples") as bar:
        for start in range(0, len(rows), BATCH):
            batch = rows[start : start + BATCH]
            pairs = zip(batch, twins[start : start + BATCH], network.predict(batch), strict=True)
            for row, k, pred in pairs:
                truth, lbs = table.maps(int(row)), twin.maps(int(k))
                depart = departing(truth, lbs, cm_per_unit)
                for tally, maps in ((tallies["network"], pred), (tallies["LBS re-rig"], lbs)):
                    measure(truth, maps, lbs, depart, tally, cm_per_unit)
                    tally.whole.append(map_metrics(maps, truth, height))
                title = f"{table.column('path')[row]}: {int(depart.sum())} departing px"
                most = sorted(
                    [*most, (int(depart.sum()), title, truth, lbs, pred, depart)], key=_first
                )
                most = most[-args.sheet :]
                bar.update(1)
    report = {
        "dataset": str(table.folder),
        "rerig": str(twin.folder),
        "model": str(args.model),
        "split": args.split,
        "samples": len(rows),
        "departing_pixels": tallies["network"].pixels,
        "departing_per_sample": tallies["network"].pixels / max(len(rows), 1),
        "rule": {"depth_cm": DEPART_DEPTH_CM, "angle_deg": DEPART_ANGLE_DEG},
        "predictors": {name: t.summary() for name, t in tallies.items()},
        "network_ms_per_sample": network_ms(network, rows),
    }
    return report, sheet([m[1:] for m in reversed(most)])


def network_ms(network, rows) -> float:
    """Median milliseconds of the network's prediction of one sample (batch 1, as a frame's
    one character: every graph at the dataset's resolution and the maps decoded), after a
    warm-up; nan without rows."""
    if len(rows) == 0:
        return math.nan
    times = []
    for i in range(TIMING_REPEATS + 1):
        one = rows[i % len(rows) : i % len(rows) + 1]
        start = time.perf_counter()
        network.predict(one)
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times[1:]))


def _first(item: tuple) -> int:
    return item[0]


def table_md(report: dict) -> str:
    """The report as a markdown table, a row per predictor."""
    keys = list(next(iter(report["predictors"].values())))
    lines = [
        f"{report['samples']} samples of {report['split']} ({report['dataset']}); "
        f"{report['departing_per_sample']:.0f} departing pixels per sample "
        f"(masks differ, depth > {DEPART_DEPTH_CM} cm or normals > {DEPART_ANGLE_DEG:g} deg).",
        "",
        "| predictor | " + " | ".join(keys) + " |",
        "|---" * (len(keys) + 1) + "|",
    ]
    for name, values in report["predictors"].items():
        lines.append(f"| {name} | " + " | ".join(f"{values[k]:.3f}" for k in keys) + " |")
    lines += [
        "",
        f"The network: {report['network_ms_per_sample']:.1f} ms a sample (batch 1, this "
        "machine). The re-rig's cost is a skinned mesh's (docs/bench, \"The premise\").",
    ]
    return "\n".join(lines) + "\n"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.rerig_report", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("dataset", help="the point-cached character's capture (the truth)")
    parser.add_argument("--model", required=True, help="the bundle trained on DATASET")
    parser.add_argument("--rerig", required=True, help="the LBS re-rig's capture, same ring")
    parser.add_argument("--out", required=True, help="folder for the report and the sheet")
    parser.add_argument("--split", default="heldout-views", help="default: heldout-views")
    parser.add_argument("--limit", type=int, default=None, help="samples, evenly spaced")
    parser.add_argument("--sheet", type=int, default=6, help="samples in the sheet (default 6)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from rigspace.sdk.errors import RigspaceError
    from rigspace.sdk.files import write_atomic

    args = parse_args(argv)
    try:
        report, image = run(args)
    except RigspaceError as error:
        print(f"rerig_report: {error}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _ok, png = cv2.imencode(".png", image)
    write_atomic(out / "rerig_sheet.png", png.tobytes())
    write_atomic(out / "rerig_report.json", json.dumps(report, indent=2, allow_nan=True))
    write_atomic(out / "rerig_report.md", table_md(report))
    print(table_md(report), end="")
    print(f"wrote {out / 'rerig_report.md'}, rerig_report.json, rerig_sheet.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Quality against training time: a run's kept checkpoints, each evaluated on held-out samples.

    python -m rigspace.apps.curve MODEL DATASET --checkpoints DIR [--limit 200] \
        [--out docs/images/training_curve.png] [--clock FILE] [--target-psnr 31] \
        [--device auto|cpu|cuda[:N]]

A run keeps one checkpoint (MODEL/training/checkpoint.pt, replaced every
`checkpoint_every` steps); copies of it taken while the run trained (DIR/*.pt, any names)
are the curve's points. Each is evaluated through rigspace.train.evaluate at the run's
final resolution on the same `limit` evenly spaced held-out views and held-out-clip
samples as `rigspace eval`, with torch (no export): the same network the bundle's graphs
compute (tests/train/test_conditioning.py: within 1e-5). Only checkpoints whose final level
has faded in count (a level still fading in is not the trained network).

The x axis is training wall time: the `seconds` the run's log records at the checkpoint's
step (train.loop), or `--clock`, a file of `unix_time step` lines sampled while the run
trained (its first line the run's start, step 0), interpolated: for a log from before that
field, or a run continued by a process that logs it. Writes a PNG (albedo PSNR and mask IoU against minutes, the
aims as lines) and prints a Markdown table and, from the last points' slope against
log(minutes), the minutes the held-out albedo PSNR would need to reach `--target-psnr` at
that rate: an extrapolation, printed as one.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rigspace.apps.ablation import save_figure
from rigspace.capture.dataset import read_manifest
from rigspace.sdk.conditioning import joints2d
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.files import write_atomic
from rigspace.sdk.render import Maps
from rigspace.train.budget import trained_levels
from rigspace.train.conditioning import dataset_skeleton
from rigspace.train.data import depth_scale
from rigspace.train.evaluate import DatasetTable, compare
from rigspace.train.loop import build_model, load_checkpoint, read_run
from rigspace.train.network import Rig2Image, albedo_maps, geometry_maps
from rigspace.train.predictor import to_maps

SPLITS = ("heldout-views", "heldout-clips")
AIMS = {"albedo_psnr": 31.0, "mask_iou": 0.95}
"""Issue 12's held-out-view aims, drawn on the plot."""


class TorchPredictor:
    """A checkpoint's network as an evaluation predictor (rigspace.train.evaluate)."""

    def __init__(
        self,
        model: Rig2Image,
        table: DatasetTable,
        scale: float,
        skeleton,
        device: torch.device | None = None,
    ) -> None:
        self.device = device or torch.device("cpu")
        self.model = model.to(self.device)
        self.table, self.scale, self.skeleton = table, scale, skeleton
        self.name = "model"
        self.footprint_bytes = sum(p.numel() * 4 for p in model.parameters())

    def predict(self, indices: np.ndarray) -> list[Maps]:
        rig = self.table.rig_inputs(indices)
        j2d = None
        if self.skeleton is not None:
            j2d = torch.from_numpy(joints2d(rig, self.skeleton)).to(self.device)
        resolution = self.table.resolution
        with torch.no_grad():
            heads = self.model(torch.from_numpy(rig).to(self.device), resolution, joints2d=j2d)
            depth, normal, mask = geometry_maps(heads["geometry"][-1])
            albedo = albedo_maps(heads["albedo"][-1])
            out = {
                name: value.float().cpu().numpy()
                for name, value in (
                    ("albedo", albedo),
                    ("depth", depth),
                    ("normal", normal),
                    ("mask", mask),
                )
            }
        joint_depth = -self.table.column("joint_camera")[indices][:, 2]
        return to_maps(out, joint_depth, self.scale)


def run_folder(model: Path) -> Path:
    """A model bundle's training folder, or the run folder itself."""
    return model / "training" if (model / "training" / "run.json").is_file() else model


def logged_clock(log: Path) -> dict[int, float]:
    """step -> training seconds, from a log's `seconds` field (empty for older logs)."""
    clock: dict[int, float] = {}
    for line in log.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if "seconds" in record and "step" in record:
            clock[int(record["step"])] = float(record["seconds"])
    return clock


def sampled_clock(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(steps, seconds since the first line) from `unix_time step` lines."""
    pairs = [line.split() for line in path.read_text().splitlines() if len(line.split()) == 2]
    times = np.array([float(t) for t, _ in pairs])
    steps = np.array([float(s) for _, s in pairs])
    order = np.argsort(steps, kind="stable")
    return steps[order], times[order] - times.min()


def minutes_at(step: int, clock: dict[int, float], sampled) -> float:
    """Training minutes at `step`: from the sampled clock when given (it spans every call
    of a run), else from the log."""
    if sampled is None and step in clock:
        return clock[step] / 60
    if sampled is None:
        raise SystemExit(
            f"rigspace curve: the log records no training time at step {step} (a run from "
            "before the log's `seconds` field). Fix: pass --clock, a file of `unix_time step` "
            "lines sampled while it trained."
        )
    steps, seconds = sampled
    return float(np.interp(step, steps, seconds)) / 60


def measure(
    model_dir: Path,
    dataset: Path,
    checkpoints: list[Path],
    limit: int,
    clock_file: Path | None,
    device: str | None = None,
) -> list[dict[str, Any]]:
    """One point per checkpoint past the final level's fade-in: step, minutes, metrics.
    `device`: a --device value (train.distributed.resolve_device; None: the CPU)."""
    from tqdm import tqdm

    from rigspace.train.distributed import resolve_device

    folder = run_folder(model_dir)
    config = read_run(folder).train_config()
    clock = logged_clock(folder / "log.jsonl")
    sampled = sampled_clock(clock_file) if clock_file else None
    table = DatasetTable(dataset, config.resolution)
    manifest = read_manifest(dataset)
    skeleton = dataset_skeleton(dataset, manifest) if config.conditioning != "none" else None
    scale = depth_scale(manifest)
    splits = [s for s in SPLITS if manifest.counts.get(s, 0)]  # a capture may lack clips
    steps = {path: int(load_checkpoint(path)["step"]) for path in checkpoints}
    by_step = {  # copies of one checkpoint: once; the final level faded in (train.budget)
        s: p for p, s in sorted(steps.items()) if config.resolution in trained_levels(config, s)
    }
    kept = sorted(by_step.items())
    points = []
    for step, path in tqdm(kept, unit="checkpoint", file=sys.stderr):
        model, _, _ = build_model(folder, path)
        predictor = TorchPredictor(model, table, scale, skeleton, resolve_device(device))
        point: dict[str, Any] = {"step": step, "minutes": minutes_at(step, clock, sampled)}
        for split in splits:
            (row,) = compare([predictor], table, split, limit=limit)["rows"]
            point[split] = {k: v for k, v in row.items() if isinstance(v, float)}
        points.append(point)
    return points


def extrapolate(points: list[dict[str, Any]], target: float, last: int = 4) -> float | None:
    """Minutes at which held-out-view albedo PSNR reaches `target`, continuing the slope of
    the last `last` points against log(minutes); None when that slope is not rising."""
    tail = points[-last:]
    if len(tail) < 2:
        return None
    x = np.log([p["minutes"] for p in tail])
    y = np.array([p["heldout-views"]["albedo_psnr"] for p in tail])
    slope, intercept = np.polyfit(x, y, 1)
    if slope <= 0:
        return None
    return float(math.exp((target - intercept) / slope))


def markdown(points: list[dict[str, Any]]) -> str:
    lines = [
        "| step | training minutes | views albedo dB | views SSIM | views IoU | views depth %h "
        "| views normal med deg | clip albedo dB | clip IoU |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for p in points:
        v = p["heldout-views"]
        c = p.get("heldout-clips")
        clip = f"{c['albedo_psnr']:.2f} | {c['mask_iou']:.3f}" if c else "- | -"
        lines.append(
            f"| {p['step']} | {p['minutes']:.1f} | {v['albedo_psnr']:.2f} | {v['albedo_ssim']:.3f} "
            f"| {v['mask_iou']:.3f} | {v['depth_mae_pct']:.2f} | {v['normal_median_deg']:.1f} "
            f"| {clip} |"
        )
    return "\n".join(lines) + "\n"


def plot(points: list[dict[str, Any]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    minutes = [p["minutes"] for p in points]
    for ax, key, label in (
        (axes[0], "albedo_psnr", "albedo PSNR (dB)"),
        (axes[1], "mask_iou", "mask IoU"),
    ):
        for split, marker in (("heldout-views", "o"), ("heldout-clips", "s")):
            if split not in points[0]:
                continue
            ax.plot(minutes, [p[split][key] for p in points], marker=marker, label=split)
        ax.axhline(AIMS[key], color="0.5", linestyle="--", linewidth=0.8, label="aim (views)")
        ax.set_xlabel("training wall time (minutes, 2 CPU cores)")
        ax.set_ylabel(f"held-out {label}")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.suptitle(title)
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.curve", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("model", type=Path, help="model bundle (or its training folder)")
    parser.add_argument("dataset", type=Path, help="the run's dataset (rigspace capture)")
    parser.add_argument("--checkpoints", type=Path, required=True, help="folder of kept *.pt")
    parser.add_argument("--limit", type=int, default=200, help="held-out samples per split")
    parser.add_argument("--out", type=Path, default=Path("training_curve.png"))
    parser.add_argument("--clock", type=Path, help="`unix_time step` lines (older logs)")
    parser.add_argument("--target-psnr", type=float, default=AIMS["albedo_psnr"])
    parser.add_argument(
        "--device",
        default="auto",
        help="where the checkpoints run: auto (a CUDA GPU when torch sees one), cpu, cuda[:N]",
    )
    args = parser.parse_args(argv)
    paths = sorted(args.checkpoints.glob("*.pt"))
    if not paths:
        raise SystemExit(f"rigspace curve: no *.pt in {args.checkpoints}.")
    try:
        points = measure(args.model, args.dataset, paths, args.limit, args.clock, args.device)
    except RigspaceError as exc:  # a bad --device, dataset or checkpoint: said, no traceback
        raise SystemExit(f"rigspace curve: {exc}") from None
    if not points:
        raise SystemExit(
            f"rigspace curve: none of the {len(paths)} checkpoints is past the final level's "
            "fade-in."
        )
    resolution = read_run(run_folder(args.model)).train_config().resolution
    plot(
        points,
        args.out,
        f"{args.model.name}: held-out quality at {resolution}x{resolution} against training "
        f"time ({args.limit} samples per split)",
    )
    print(markdown(points))
    reach = extrapolate(points, args.target_psnr)
    if reach is None:
        print(
            f"held-out-view albedo is not rising over the last points: no estimate for "
            f"{args.target_psnr:g} dB"
        )
    else:
        print(
            f"extrapolated: held-out-view albedo reaches {args.target_psnr:g} dB after about "
            f"{reach:.0f} training minutes at the last points' rate (log-linear fit)"
        )
    write_atomic(args.out.with_suffix(".json"), json.dumps(points, indent=2) + "\n")
    print(f"curve: {args.out}, {args.out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

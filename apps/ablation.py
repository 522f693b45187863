"""Ablation: network variants trained with the same steps, measured on the same held-out samples.

    python -m rigspace.apps.ablation DATASET --out DIR [--steps-per-level N] [--resolution R]

Each variant is the small preset with a few options changed (VARIANTS). It trains to
`resolution` with `steps-per-level` steps at every level (the same steps for all: on a shared
CPU, minutes are not a fair budget), is exported (fp32 graphs) and evaluated through
rigspace.train.evaluate on the same evenly spaced held-out views and held-out-clip samples,
against targets box-downsampled to the model's resolution, as training sees them. Results go
to DIR/<variant>/result.json as each variant finishes; a re-run skips finished variants and
resumes an interrupted one. DIR/ablation.md (the table), DIR/ablation_cost.png (quality
against MFLOP) and DIR/ablation_curve.png (held-out
quality against steps) are rewritten after every variant.

With `--display HIRES` (a capture of the same ring at a higher resolution, `rigspace capture
... --resolution 512 --every 30`) each variant is also measured at the size it is seen
(train/display.py): at 2x, 4x, ... its resolution, up to the training dataset's resolution and
HIRES's, the model as the runtime draws it against the truth captured at that size.

    python -m rigspace.apps.ablation DATASET --out DIR --cost 128 --variants ...

prints what each distinct architecture among the variants costs at 128x128 (MFLOP, fp32 and
int8 ms), untrained.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from rigspace.capture.dataset import DatasetManifest
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import Maps
from rigspace.train.config import preset
from rigspace.train.evaluate import OPTIONAL_METRICS, DatasetTable, downsample_maps, evaluate
from rigspace.train.export import export_bundle
from rigspace.train.loop import RUN_FILE, build_model, train
from rigspace.train.network import Rig2Image
from rigspace.train.predictor import BundlePredictor

ADD32_BCE: dict[str, Any] = {
    "conditioning": "bones2d",
    "mask_loss": "bce",
    "conditioning_mode": "add",
    "conditioning_top": 32,
}
"""The sample model's form (bones2d maps up to 32x32, projected and added; cross-entropy
mask): the base of the variants named bones2d-add32+bce..."""

SAMPLE_RECIPE: dict[str, Any] = {**ADD32_BCE, "depth_weight": 2.0, "texture": True}
"""The committed sample model's options (docs/training.md): the base of the capacity variants."""

VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "paper": ("the paper's input (rotations only), small widths, L2/L1 mask loss", {}),
    "joints2d": ("+ per-joint 2D Gaussian maps at every block", {"conditioning": "joints2d"}),
    "bones2d": ("+ per-bone 2D segment maps at every block", {"conditioning": "bones2d"}),
    "width32": ("32 channels at 32x32 and 64x64 (16 in paper)", {"min_width": 32}),
    "latent512": ("fully connected latent 512 (256 in paper)", {"latent": 512}),
    "mask-bce": ("mask and alpha by cross-entropy", {"mask_loss": "bce"}),
    "mask-iou-edge": (
        "mask L2/L1 + soft IoU, silhouette edges weighted x5",
        {"mask_loss": "soft-iou", "edge_weight": 4.0},
    ),
    "bones2d+iou-edge": (
        "bones2d with the soft-IoU, edge-weighted mask loss",
        {"conditioning": "bones2d", "mask_loss": "soft-iou", "edge_weight": 4.0},
    ),
    "bones2d+bce": (
        "bones2d with the cross-entropy mask loss",
        {"conditioning": "bones2d", "mask_loss": "bce"},
    ),
    # Cheaper conditioning: the same maps without widening the 3x3 convolutions.
    "bones2d-add+bce": (
        "bones2d+bce, maps 1x1-projected and added to the features (no extra conv channels)",
        {"conditioning": "bones2d", "mask_loss": "bce", "conditioning_mode": "add"},
    ),
    "bones2d-add32+bce": (
        "bones2d-add+bce, maps computed up to 32x32; 64x64 adds the 32x32 projection upsampled",
        ADD32_BCE,
    ),
    "bones2d-add16+bce": (
        "bones2d-add+bce, maps computed up to 16x16 only, upsampled above",
        {
            "conditioning": "bones2d",
            "mask_loss": "bce",
            "conditioning_mode": "add",
            "conditioning_top": 16,
        },
    ),
    "bones2d-add32+bce+rare": (
        "bones2d-add32+bce, rare poses (the cartwheel) drawn more often: --oversample 1",
        {**ADD32_BCE, "oversample": 1.0},
    ),
    # Width, on the conditioned form: what more (or fewer) FLOPs buy at the same steps.
    "bones2d-add32+bce-base64": (
        "bones2d-add32+bce with half the channels at every level (base width 64)",
        {**ADD32_BCE, "base_width": 64, "min_width": 8},
    ),
    "bones2d-add32+bce-width32": (
        "bones2d-add32+bce with 32 channels at 32x32 and 64x64 (min width 32)",
        {**ADD32_BCE, "min_width": 32},
    ),
    # Depth: the sample model's depth error rose (1.27 -> 1.53 % of height) with the
    # conditioned form; its depth term is the smallest of the loss (0.002 of 0.17).
    "bones2d-add32+bce-depth2": (
        "bones2d-add32+bce with the depth loss weighted x2",
        {**ADD32_BCE, "depth_weight": 2.0},
    ),
    "bones2d-add32+bce-depth2-seed1": (
        "`bones2d-add32+bce-depth2`, seed 1",
        {**ADD32_BCE, "depth_weight": 2.0, "seed": 1},
    ),
    "bones2d-add32+bce-depth4": (
        "bones2d-add32+bce with the depth loss weighted x4",
        {**ADD32_BCE, "depth_weight": 4.0},
    ),
    # The same variants from another seed: how much of a difference is the seed's.
    "paper-seed1": ("`paper`, seed 1", {"seed": 1}),
    "bones2d-seed1": ("`bones2d`, seed 1", {"conditioning": "bones2d", "seed": 1}),
    "bones2d+bce-seed1": (
        "`bones2d+bce`, seed 1",
        {"conditioning": "bones2d", "mask_loss": "bce", "seed": 1},
    ),
    "bones2d-add32+bce-seed1": (
        "`bones2d-add32+bce`, seed 1",
        {**ADD32_BCE, "seed": 1},
    ),
    "bones2d-add32+bce-depth4-seed1": (
        "`bones2d-add32+bce-depth4`, seed 1",
        {**ADD32_BCE, "depth_weight": 4.0, "seed": 1},
    ),
    "bones2d-add32+bce+rare-seed1": (
        "`bones2d-add32+bce+rare`, seed 1",
        {**ADD32_BCE, "oversample": 1.0, "seed": 1},
    ),
    # Texture: colour from the character's own textures where a head says each pixel lands
    # (train/network.py), against the albedo branch alone, on the sample model's form.
    "sample-form": (
        "the sample model's form (bones2d-add32+bce, depth x2), albedo branch only",
        {**ADD32_BCE, "depth_weight": 2.0},
    ),
    "sample-form+texture": (
        "sample-form with the texture head (chart and coordinates, loss weights 1)",
        {**ADD32_BCE, "depth_weight": 2.0, "texture": True, "chart_weight": 1.0, "uv_weight": 1.0},
    ),
    "sample-form+texture-light": (
        "sample-form+texture with the texture terms weighted 0.25",
        {
            **ADD32_BCE,
            "depth_weight": 2.0,
            "texture": True,
            "chart_weight": 0.25,
            "uv_weight": 0.25,
        },
    ),
    "sample-form+texture-uv4": (
        "sample-form+texture with the sample model's weights (chart 0.25, coordinates 4)",
        {**ADD32_BCE, "depth_weight": 2.0, "texture": True},
    ),
    # Capacity (issue 32): the texture head on its own branch, and width at 64 and 128.
    "sample-recipe": (
        "the committed sample model's recipe: sample-form+texture-uv4",
        SAMPLE_RECIPE,
    ),
    "sample-recipe-own": (
        "sample-recipe with the texture head on a branch of its own",
        {**SAMPLE_RECIPE, "texture_branch": "texture"},
    ),
    "sample-recipe-width24": (
        "sample-recipe, 24 channels at 64x64 and 128x128 (1.5x; min width 24)",
        {**SAMPLE_RECIPE, "min_width": 24},
    ),
    "sample-recipe-width32": (
        "sample-recipe, 32 channels at 64x64 and 128x128 (2x; min width 32)",
        {**SAMPLE_RECIPE, "min_width": 32},
    ),
    "sample-recipe-own-width32": (
        "sample-recipe-own, 32 channels at 64x64 and 128x128 (2x; min width 32)",
        {**SAMPLE_RECIPE, "texture_branch": "texture", "min_width": 32},
    ),
}
SPLITS = ("heldout-views", "heldout-clips")
TIMING_REPEATS = 30


class DownsampledTable(DatasetTable):
    """A dataset seen at a lower resolution: maps box-downsampled as training does (train.data)."""

    def __init__(self, folder: str | Path, resolution: int) -> None:
        super().__init__(folder)
        full = self.manifest.resolution
        if full % resolution:
            raise RigspaceError(
                f"Resolution {resolution} does not divide the dataset's {full}.",
                "choose a power of two at or below the dataset's resolution.",
            )
        self._factor, self._resolution = full // resolution, resolution
        self._full = DatasetTable(folder)

    @property
    def resolution(self) -> int:
        return self._resolution

    @cached_property
    def character_height(self) -> float:
        return self._full.character_height  # from the full-resolution maps and intrinsics

    def maps(self, index: int) -> Maps:
        """The captured maps box-downsampled as training does (evaluate.downsample_maps), the
        chart and uv AOVs with them (each box's commonest chart and its own mean st)."""
        return downsample_maps(super().maps(index), self._factor)


def mflop(model: Rig2Image, resolution: int) -> float:
    """Floating-point operations of one evaluation (both branches at `resolution`), in millions:
    2 x multiply-adds of every convolution and linear layer, plus about 10 operations per
    conditioning-map element."""
    total = 0.0

    def count(module: nn.Module, inputs: tuple, output: torch.Tensor) -> None:
        nonlocal total
        if isinstance(module, nn.Conv2d):
            k = module.kernel_size[0] * module.kernel_size[1]
            total += 2.0 * output.numel() * module.in_channels * k
        elif isinstance(module, nn.Linear):
            total += 2.0 * module.in_features * module.out_features * output.shape[0]

    hooks = [m.register_forward_hook(count) for m in model.modules()]
    joints2d = torch.zeros(1, 2 * model.shape.joints) if model.conditioned else None
    with torch.no_grad():
        model(torch.zeros(1, model.shape.inputs), resolution, joints2d=joints2d)
        maps = model.condition_maps(joints2d, resolution)
        unique = {id(m): m for m in (maps or {}).values()}  # levels above conditioning_top share
        total += 10.0 * sum(m.numel() for m in unique.values())
    for hook in hooks:
        hook.remove()
    return total / 1e6


def milliseconds(bundle: Path, rig: np.ndarray, resolution: int) -> float:
    """Best wall time of TIMING_REPEATS evaluations (trunk and both branches, one sample, fp32
    ONNX): the minimum, because the CPU is shared and slower runs measure the others' load."""
    model = BundleModel(bundle, "fp32")
    model.predict(rig, resolution)
    times = []
    for _ in range(TIMING_REPEATS):
        begin = time.perf_counter()
        model.predict(rig, resolution)
        times.append(time.perf_counter() - begin)
    return 1e3 * min(times)


def display_metrics(
    bundle: Path, datasets: list[Path], split: str, limit: int
) -> dict[str, dict[str, Any]]:
    """The variant measured at the sizes it is seen (train/display.py), from every dataset
    above its resolution: per size, albedo PSNR, mask IoU and ms per sample of the runtime's
    drawing, and the same of the truth at its resolution upsampled."""
    from rigspace.train.display import (
        MODES,
        DisplayPredictor,
        UpsampledTruth,
        display_sizes,
        scene_textures,
    )

    model = BundleModel(bundle, "fp32")
    level = max(model.resolutions)
    out: dict[str, dict[str, Any]] = {}
    for folder in datasets:
        full = DatasetTable(folder)
        textures, _ = scene_textures(model, full.manifest)
        for size in display_sizes(level, full.resolution):
            if str(size) in out:
                continue
            table = DatasetTable(folder, size)
            entry = {}
            for predictor in (
                *(DisplayPredictor(model, table, mode, textures) for mode in MODES),
                UpsampledTruth(table, level),
            ):
                report = evaluate(predictor, table, split, limit=limit)
                entry[predictor.name] = {
                    "albedo_psnr": report["metrics"]["albedo_psnr"]["mean"],
                    "albedo_ssim": report["metrics"]["albedo_ssim"]["mean"],
                    "mask_iou": report["metrics"]["mask_iou"]["mean"],
                    "ms": 1e3 * report["seconds_per_sample"],
                    "samples": report["samples"],
                    **{
                        key: summary["median" if key.startswith("uv_texels") else "mean"]
                        for key, summary in report["metrics"].items()
                        if key in OPTIONAL_METRICS
                    },
                }
            out[str(size)] = entry
    return out


def _bundle_metrics(bundle: Path, table: DownsampledTable, limit: int) -> dict[str, Any]:
    """Each split's metrics (means; the uv texel errors' medians) and samples, of the bundle
    as it renders (with its textures where it has charts)."""
    predictor = BundlePredictor(bundle, table)
    if predictor.model.charts:  # where the head lands on the textures, in texels
        from rigspace.train.display import scene_textures

        textures, _ = scene_textures(predictor.model, table.manifest)
        if textures is not None:
            predictor.attach_textures(textures)
    metrics = {}
    for split in SPLITS:
        report = evaluate(predictor, table, split, limit=limit)
        metrics[split] = {
            k: v["median" if k.startswith("uv_texels") else "mean"]
            for k, v in report["metrics"].items()
        }
        metrics[split]["samples"] = report["samples"]
    return metrics


def run_variant(
    dataset: Path,
    out: Path,
    name: str,
    steps_per_level: int,
    resolution: int,
    limit: int,
    display: Path | None = None,
    device: str | None = None,
) -> dict[str, Any]:
    """Train (on `device`, a --device value; None: the CPU), export and evaluate one variant
    (resuming what an earlier call left); with `display`, also measured at the sizes it is
    seen (display_metrics)."""
    description, overrides = VARIANTS[name]
    folder = out / name
    options: dict[str, Any] = {
        "texture": False,  # the variants before the texture head were measured without one
        "resolution": resolution,
        "steps_per_level": steps_per_level,
        "eval_every": max(1, steps_per_level // 3),
        "checkpoint_every": max(1, steps_per_level // 3),
    }
    config = preset("small", **(options | overrides))
    began = time.monotonic()
    resume = (folder / "run" / RUN_FILE).exists()
    result = train(dataset, folder / "run", config, resume=resume, progress=False, device=device)
    if result.stopped != "done":
        raise RigspaceError(f"Variant {name} stopped: {result.stopped}.", "re-run to resume it.")
    train_seconds = time.monotonic() - began
    bundle = folder / "bundle"
    export_bundle(folder / "run", bundle, int8=False)
    model, _, _ = build_model(folder / "run")
    table = DownsampledTable(dataset, resolution)
    metrics = _bundle_metrics(bundle, table, limit)
    rig = table.rig_inputs(table.indices("heldout-views")[:1])
    record = {
        "variant": name,
        "description": description,
        "overrides": overrides,
        "config": config.to_json(),
        "steps": result.step,
        "train_seconds_this_call": train_seconds,
        "parameters": int(sum(p.numel() for p in model.parameters())),
        "mflop": mflop(model, resolution),
        "ms_fp32": milliseconds(bundle, rig, resolution),
        "resolution": resolution,
        "metrics": metrics,
        "curve": curve(folder / "run" / "log.jsonl"),
    }
    if display is not None:
        record["display"] = display_metrics(bundle, [dataset, display], "heldout-views", limit)
    (folder / "result.json").write_text(json.dumps(_finite(record), indent=2) + "\n")
    return record


def _finite(value: Any) -> Any:
    """NaN/Inf (a metric with nothing to measure) as null, so the JSON is strict."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def curve(log: Path) -> list[dict[str, float]]:
    """(step, level, held-out preview PSNR and IoU) from a run's log, one point per evaluation."""
    points: dict[int, dict[str, float]] = {}
    for line in log.read_text().splitlines():
        entry = json.loads(line)
        if "heldout" in entry:  # a resumed run may log a step twice: the last one counts
            points[entry["step"]] = {
                "step": entry["step"],
                "resolution": entry["resolution"],
                "albedo_psnr": entry["heldout"]["albedo_psnr"],
                "mask_iou": entry["heldout"]["mask_iou"],
            }
    return [points[step] for step in sorted(points)]


COLUMNS = (
    ("albedo_psnr", "albedo dB", "{:.2f}"),
    ("albedo_ssim", "SSIM", "{:.3f}"),
    ("mask_iou", "IoU", "{:.3f}"),
    ("depth_mae_pct", "depth %h", "{:.2f}"),
    ("normal_median_deg", "normal med deg", "{:.1f}"),
    ("albedo_flip", "FLIP", "{:.3f}"),
    ("chart_accuracy", "chart right", "{:.3f}"),
    ("uv_texels_median", "uv texels med", "{:.2f}"),
    ("uv_texels_p90", "uv texels p90", "{:.2f}"),
)

CLIP_COLUMNS = ("albedo_psnr", "mask_iou", "depth_mae_pct")
"""Metrics shown for the held-out clip (the table stays readable)."""


def table_markdown(records: list[dict[str, Any]]) -> str:
    """One markdown table: variant, cost, and per-split metrics."""
    head = ["variant", "params", "MFLOP", "ms fp32"]
    head += [f"views {label}" for _, label, _ in COLUMNS]
    head += [f"clip {label}" for key, label, _ in COLUMNS if key in CLIP_COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        cells = [
            f"`{r['variant']}`",
            f"{r['parameters'] / 1e6:.2f} M",
            f"{r['mflop']:.0f}",
            f"{r['ms_fp32']:.2f}",
        ]
        for split in SPLITS:
            m = r["metrics"][split]
            for key, _, fmt in COLUMNS:
                if split == "heldout-views" or key in CLIP_COLUMNS:
                    value = m.get(key)
                    cells.append(
                        "-" if value is None or not math.isfinite(value) else fmt.format(value)
                    )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def display_markdown(records: list[dict[str, Any]]) -> str:
    """The variants measured at the sizes they are seen (display_metrics): per size, albedo
    PSNR and mask IoU of each way of drawing, and ms per sample of the runtime's; empty when
    no variant was."""
    shown = [r for r in records if r.get("display")]
    if not shown:
        return ""
    lines = ["", "At the size the character is seen (held-out views, `--display`):", ""]
    head = (
        "| variant | size | runtime dB | runtime SSIM | runtime IoU | albedo branch dB "
        "| albedo branch SSIM | bilinear dB | truth at R upsampled dB | runtime ms |"
    )
    lines += [head, "|---|---|---|---|---|---|---|---|---|---|"]

    def cell(entry: dict[str, Any], mode: str, key: str, fmt: str) -> str:
        value = entry.get(mode, {}).get(key)
        return "-" if value is None else fmt.format(value)

    for r in shown:
        for size, entry in sorted(r["display"].items(), key=lambda kv: int(kv[0])):
            truth = next((k for k in entry if k.startswith("truth")), "")
            lines.append(
                f"| `{r['variant']}` | {size} | {cell(entry, 'runtime', 'albedo_psnr', '{:.2f}')} "
                f"| {cell(entry, 'runtime', 'albedo_ssim', '{:.3f}')} "
                f"| {cell(entry, 'runtime', 'mask_iou', '{:.3f}')} "
                f"| {cell(entry, 'albedo branch', 'albedo_psnr', '{:.2f}')} "
                f"| {cell(entry, 'albedo branch', 'albedo_ssim', '{:.3f}')} "
                f"| {cell(entry, 'bilinear', 'albedo_psnr', '{:.2f}')} "
                f"| {cell(entry, truth, 'albedo_psnr', '{:.2f}')} "
                f"| {cell(entry, 'runtime', 'ms', '{:.1f}')} |"
            )
    return "\n".join(lines) + "\n"


def save_figure(fig, path: Path) -> None:
    """Lay a matplotlib figure out, write it as a PNG at `path` (folders made), close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_curves(records: list[dict[str, Any]], path: Path) -> None:
    """Held-out preview albedo PSNR and mask IoU against steps, one line per variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    colours = plt.get_cmap("tab20")(np.arange(len(records)) % 20)
    for r, colour in zip(records, colours, strict=True):
        steps = [p["step"] for p in r["curve"]]
        style = {"marker": "o", "label": r["variant"], "color": colour}
        axes[0].plot(steps, [p["albedo_psnr"] for p in r["curve"]], **style)
        axes[1].plot(steps, [p["mask_iou"] for p in r["curve"]], **style)
    config = records[0]["config"]
    levels = preset("small", **{k: v for k, v in config.items() if k != "preset"}).levels()
    for ax in axes:
        for k in range(1, len(levels)):  # where each new level starts fading in
            ax.axvline(k * config["steps_per_level"], color="0.8", linewidth=0.8)
        ax.set_xlabel(f"step (levels {', '.join(map(str, levels))}; grey lines: a new level)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("held-out preview albedo PSNR (dB)")
    axes[1].set_ylabel("held-out preview mask IoU")
    axes[1].legend(fontsize=7)
    size = config["resolution"]
    fig.suptitle(
        f"Ablation at {size}x{size}, same steps per variant (4 held-out views per point, "
        "at the level being trained)"
    )
    save_figure(fig, path)


def retime(out: Path, dataset: Path, rounds: int = 5) -> dict[str, float]:
    """Re-measure ms fp32 of every finished variant in one process, round-robin, so that all
    see the same load (the shared CPU's load changes over the hours the variants train);
    each variant keeps its best round. Updates result.json; returns variant -> ms."""
    records = {
        name: json.loads((out / name / "result.json").read_text())
        for name in VARIANTS
        if (out / name / "result.json").is_file()
    }
    rig = DatasetTable(dataset).rig_inputs(np.arange(1))
    best = dict.fromkeys(records, math.inf)
    for _ in range(rounds):
        for name, record in records.items():
            ms = milliseconds(out / name / "bundle", rig, record["resolution"])
            best[name] = min(best[name], ms)
    for name, record in records.items():
        record["ms_fp32"] = best[name]
        record["timing"] = f"best of {rounds} rounds x {TIMING_REPEATS}, all variants interleaved"
        (out / name / "result.json").write_text(json.dumps(_finite(record), indent=2) + "\n")
    return best


ARCHITECTURE = (
    "conditioning",
    "conditioning_mode",
    "conditioning_top",
    "base_width",
    "min_width",
    "latent",
    "fc_layers",
    "texture",
    "texture_branch",
)
"""The options that change the graphs (and so the cost); losses, sampling and seeds do not."""


def cost(dataset: Path, names: list[str], resolution: int = 128, rounds: int = 8) -> str:
    """MFLOP and ms of one evaluation (trunk and every branch, batch 1, one onnxruntime
    thread) at `resolution`, fp32 and int8, of each distinct architecture among `names`,
    with no training: cost depends on the graphs' shapes, not their weights (seeded random
    weights here). int8 is the export's graph without its accuracy sweep: the trunk whole,
    each branch with its output heads and pose nodes in float (train.quantize), calibrated
    on 64 training rows. Timed round-robin over all architectures, best of `rounds` x 30.
    Returns a markdown table (variant, params, MFLOP, ms fp32, ms int8, ratio)."""
    import tempfile

    from rigspace.train.conditioning import dataset_skeleton

    manifest, rig, shape = _cost_inputs(dataset)
    skeleton = None
    groups, configs = _architectures(names, resolution)
    rows: dict[tuple, dict[str, Any]] = {}
    graphs: dict[tuple, dict[str, tuple[Any, dict[str, np.ndarray]]]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for key, config in configs.items():
            torch.manual_seed(0)
            model = Rig2Image(shape, config).eval()
            if model.conditioned and skeleton is None:
                skeleton = dataset_skeleton(dataset, manifest)
            folder = Path(tmp) / groups[key][0]
            graphs[key] = _export_graphs(model, rig, skeleton, resolution, folder)
            rows[key] = {
                "parameters": int(sum(p.numel() for p in model.parameters())),
                "mflop": mflop(model, resolution),
                "fp32": math.inf,
                "int8": math.inf,
            }
            print(f"ablation: cost: {', '.join(groups[key])} exported", file=sys.stderr, flush=True)
        _time_graphs(graphs, rows, rounds)
    return _cost_table(rows, groups, resolution)


def _cost_inputs(dataset: Path) -> tuple[DatasetManifest, np.ndarray, Any]:
    """(the dataset's manifest, 64 evenly spaced training rig rows, the network's Shape)."""
    from rigspace.capture.dataset import read_manifest
    from rigspace.train.conditioning import parents_of
    from rigspace.train.data import SampleSet, chart_boxes
    from rigspace.train.network import Shape

    manifest = read_manifest(dataset)
    train_rows = SampleSet(dataset, "train")
    picks = np.linspace(0, len(train_rows) - 1, 64).astype(int)
    rig = train_rows.rig[train_rows.rows[picks]].astype(np.float32)
    boxes = chart_boxes(dataset)  # a variant with a texture head costs its K charts' channels
    charts = 0 if boxes is None else len(boxes[0]) - 1
    shape = Shape(len(train_rows.joints), parents=parents_of(train_rows.joints), charts=charts)
    return manifest, rig, shape


def _architectures(
    names: list[str], resolution: int
) -> tuple[dict[tuple, list[str]], dict[tuple, Any]]:
    """The variants grouped by their ARCHITECTURE options: (key -> names, key -> first config)."""
    groups: dict[tuple, list[str]] = {}
    configs: dict[tuple, Any] = {}
    for name in names:
        config = preset("small", resolution=resolution, channels_last=False, **VARIANTS[name][1])
        key = tuple(getattr(config, k) for k in ARCHITECTURE)
        groups.setdefault(key, []).append(name)
        configs.setdefault(key, config)
    return groups, configs


def _export_graphs(
    model: Rig2Image, rig: np.ndarray, skeleton: Any, resolution: int, folder: Path
) -> dict[str, tuple[Any, dict[str, np.ndarray]]]:
    """Export the model's graphs to `folder`, fp32 and int8 (calibrated on `rig`), and open
    them: "branch.precision" -> (onnxruntime session, its feeds for one sample)."""
    from rigspace.train.export import export_graph
    from rigspace.train.int8check import graph_feeds, rig_feeds, session
    from rigspace.train.quantize import head_nodes, quantize

    feeds = rig_feeds(rig, skeleton if model.conditioned else None)
    with torch.no_grad():
        tensors = {k: torch.from_numpy(v) for k, v in feeds.items()}
        feeds["features"] = model.features(tensors["rig"], tensors.get("joints2d")).numpy()
    folder.mkdir()
    graphs: dict[str, tuple[Any, dict[str, np.ndarray]]] = {}
    for branch in ("trunk", *model.branch_names):
        fp32 = folder / f"{branch}.onnx"
        int8 = folder / f"{branch}.int8.onnx"
        with torch.no_grad():
            export_graph(model, branch, resolution, fp32)
        quantize(fp32, int8, feeds, head_nodes(fp32))
        one = {k: v[:1] for k, v in feeds.items()}
        for precision, path in (("fp32", fp32), ("int8", int8)):
            graph = session(path)
            graphs[f"{branch}.{precision}"] = (graph, graph_feeds(graph, one))
    return graphs


def _time_graphs(
    graphs: dict[tuple, dict[str, tuple[Any, dict[str, np.ndarray]]]],
    rows: dict[tuple, dict[str, Any]],
    rounds: int,
) -> None:
    """Time each architecture's evaluation, fp32 and int8, round-robin over all of them;
    each row keeps its best ms per precision."""
    for _ in range(rounds):
        for key in graphs:
            for precision in ("fp32", "int8"):
                evaluation = [v for k, v in graphs[key].items() if k.endswith(f".{precision}")]
                for graph, feed in evaluation:
                    graph.run(None, feed)  # warm
                times = []
                for _ in range(TIMING_REPEATS):
                    begin = time.perf_counter()
                    for graph, feed in evaluation:
                        graph.run(None, feed)
                    times.append(time.perf_counter() - begin)
                rows[key][precision] = min(rows[key][precision], 1e3 * min(times))


def _cost_table(
    rows: dict[tuple, dict[str, Any]], groups: dict[tuple, list[str]], resolution: int
) -> str:
    """The cost rows as a markdown table."""
    lines = [
        f"| variants (same graphs) | params | MFLOP at {resolution} | ms fp32 | ms int8 | int8 speed-up |",
        "|---|---|---|---|---|---|",
    ]
    for key, row in rows.items():
        lines.append(
            f"| {', '.join(f'`{n}`' for n in groups[key])} | {row['parameters'] / 1e6:.2f} M | "
            f"{row['mflop']:.0f} | {row['fp32']:.2f} | {row['int8']:.2f} | "
            f"{row['fp32'] / row['int8']:.2f}x |"
        )
    return "\n".join(lines) + "\n"


GRAPH_COLUMNS = ("trunk", "albedo", "geometry", "predict")


def breakdown(out: Path, dataset: Path, names: list[str], rounds: int = 12) -> str:
    """ms per graph (trunk, each branch at the top level) and per predict of finished variants,
    one onnxruntime thread, best of `rounds` x 20 with the variants interleaved: where a
    variant's time goes, steadier under load than the default-threads `retime`."""
    rig = DatasetTable(dataset).rig_inputs(np.arange(1))
    found = [n for n in names if (out / n / "bundle").is_dir()]
    models = {n: BundleModel(out / n / "bundle", "fp32", threads=1) for n in found}
    best = {n: dict.fromkeys(GRAPH_COLUMNS, math.inf) for n in found}

    def ms(call: Any) -> float:
        call()
        times = []
        for _ in range(20):
            begin = time.perf_counter()
            call()
            times.append(time.perf_counter() - begin)
        return 1e3 * min(times)

    for _ in range(rounds):
        for name, model in models.items():
            top = model.resolutions[-1]
            j2d = model.joints2d(rig)
            features = model.features(rig, j2d)
            calls = {
                "trunk": lambda m=model, j=j2d: m.features(rig, j),
                "albedo": lambda m=model, f=features, j=j2d, r=top: m.branch(f, "albedo", r, j),
                "geometry": lambda m=model, f=features, j=j2d, r=top: m.branch(f, "geometry", r, j),
                "predict": lambda m=model, r=top: m.predict(rig, r),
            }
            for key, call in calls.items():
                best[name][key] = min(best[name][key], ms(call))
    lines = ["| variant | " + " | ".join(f"{c} ms" for c in GRAPH_COLUMNS) + " |"]
    lines.append("|" + "---|" * (len(GRAPH_COLUMNS) + 1))
    for name in found:
        cells = " | ".join(f"{best[name][c]:.2f}" for c in GRAPH_COLUMNS)
        lines.append(f"| `{name}` | {cells} |")
    return "\n".join(lines) + "\n"


def report(out: Path) -> list[dict[str, Any]]:
    """Rewrite DIR/ablation.md and DIR/ablation_curve.png from the finished variants."""
    records = [
        json.loads((out / name / "result.json").read_text())
        for name in VARIANTS
        if (out / name / "result.json").is_file()
    ]
    for record in records:  # the curve as the run's log has it now (resumed runs deduplicated)
        log = out / record["variant"] / "run" / "log.jsonl"
        if log.is_file():
            record["curve"] = curve(log)
    (out / "ablation.md").write_text(table_markdown(records) + display_markdown(records))
    if records:
        plot_curves(records, out / "ablation_curve.png")
        plot_cost(records, out / "ablation_cost.png")
    return records


def plot_cost(records: list[dict[str, Any]], path: Path) -> None:
    """Held-out-view albedo PSNR and mask IoU against MFLOP per evaluation, one labelled
    point per variant: what more (or fewer) FLOPs buy at the same steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, key, label in (
        (axes[0], "albedo_psnr", "held-out-view albedo PSNR (dB)"),
        (axes[1], "mask_iou", "held-out-view mask IoU"),
    ):
        for r in records:
            value = r["metrics"]["heldout-views"].get(key)
            if value is None or not math.isfinite(value):
                continue
            ax.scatter(r["mflop"], value, color="tab:blue" if "bones2d" in r["variant"] else "0.5")
            ax.annotate(
                r["variant"],
                (r["mflop"], value),
                fontsize=6,
                xytext=(3, 2),
                textcoords="offset points",
            )
        ax.set_xlabel("MFLOP per evaluation (both branches, final level)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    size = records[0]["config"]["resolution"]
    fig.suptitle(
        f"Ablation at {size}x{size}: quality against cost, same steps per variant "
        "(blue: pose-conditioned)"
    )
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    unknown = sorted(set(args.variants) - set(VARIANTS))
    try:
        if unknown:
            raise RigspaceError(
                f"Unknown variants {unknown}.", f"choose from {', '.join(VARIANTS)}."
            )
        if args.threads:
            torch.set_num_threads(args.threads)
        args.out.mkdir(parents=True, exist_ok=True)
        if args.cost:
            print(cost(args.dataset, args.variants, args.cost), end="")
            return 0
        if args.breakdown:
            print(breakdown(args.out, args.dataset, args.variants), end="")
            return 0
        if args.redisplay:
            _redisplay(args)
            report(args.out)
            return 0
        if args.retime:
            for name, ms in retime(args.out, args.dataset).items():
                print(f"ablation: {name}: {ms:.2f} ms fp32", file=sys.stderr)
            report(args.out)
            return 0
        _run_variants(args)
        report(args.out)
    except RigspaceError as exc:
        print(f"ablation: {exc}", file=sys.stderr)
        return 2
    return 0


def _parser() -> argparse.ArgumentParser:
    """The command line (the module doc)."""
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.ablation", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "dataset", type=Path, help="a dataset folder written by `rigspace capture` (read only)"
    )
    parser.add_argument(
        "--out", type=Path, required=True, help="folder for the variants' runs and results"
    )
    parser.add_argument(
        "--steps-per-level", type=int, default=150, help="steps at every level, every variant"
    )
    parser.add_argument("--resolution", type=int, default=64, help="final training resolution")
    parser.add_argument(
        "--limit", type=int, default=200, help="held-out samples per split (evenly spaced)"
    )
    parser.add_argument(
        "--variants", nargs="*", default=list(VARIANTS), help=f"of {', '.join(VARIANTS)}"
    )
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument(
        "--device",
        default="cpu",
        help="where the variants train: cpu (default: the same for every variant), auto, cuda "
        "or cuda:N (rigspace train --device)",
    )
    parser.add_argument(
        "--redisplay",
        action="store_true",
        help="only measure the finished --variants at the sizes they are seen again (with "
        "--display) and rewrite the report",
    )
    parser.add_argument(
        "--display",
        type=Path,
        metavar="HIRES",
        help="also measure each variant at the size it is seen, on this capture of the same "
        "ring at a higher resolution (and on DATASET above the variant's resolution)",
    )
    parser.add_argument(
        "--retime",
        action="store_true",
        help="only re-measure ms of the finished variants, interleaved, and rewrite the report",
    )
    parser.add_argument(
        "--breakdown",
        action="store_true",
        help="only print ms per graph of --variants (one onnxruntime thread, interleaved)",
    )
    parser.add_argument(
        "--cost",
        type=int,
        metavar="R",
        help="only print MFLOP and ms fp32/int8 at R x R of --variants' architectures "
        "(untrained: cost does not depend on weights; one onnxruntime thread, interleaved)",
    )
    return parser


def _redisplay(args: argparse.Namespace) -> None:
    """Measure the finished --variants at the sizes they are seen again (display_metrics)."""
    for name in args.variants:
        path = args.out / name / "result.json"
        if not path.is_file():
            continue
        record = json.loads(path.read_text())
        record["display"] = display_metrics(
            args.out / name / "bundle",
            [args.dataset, *([args.display] if args.display else [])],
            "heldout-views",
            args.limit,
        )
        path.write_text(json.dumps(_finite(record), indent=2) + "\n")
        print(f"ablation: {name}: display {record['display']}", file=sys.stderr)


def _run_variants(args: argparse.Namespace) -> None:
    """Train and measure the --variants not measured yet, rewriting the report after each."""
    for name in args.variants:
        if (args.out / name / "result.json").is_file():
            print(f"ablation: {name} already measured", file=sys.stderr)
            continue
        began = time.monotonic()
        record = run_variant(
            args.dataset,
            args.out,
            name,
            args.steps_per_level,
            args.resolution,
            args.limit,
            args.display,
            args.device,
        )
        views = record["metrics"]["heldout-views"]
        print(
            f"ablation: {name}: {time.monotonic() - began:.0f} s, held-out views "
            f"{views['albedo_psnr']:.2f} dB, IoU {views['mask_iou']:.3f}",
            file=sys.stderr,
            flush=True,
        )
        report(args.out)


if __name__ == "__main__":
    sys.exit(main())

"""Run time against error: every model variant, the ground-truth renderers, the baselines.

The truth is the real skinned mesh drawn by `gl` with 4x4 samples per pixel at the ring
cameras (held-out views of training clips; training views of the held-out clip), at the
training resolution. Against it, on the same samples:

- each model variant that exists: every level of detail in fp32 and int8 (the bundle
  holds no bf16 graphs: bf16 is a training option, measured in docs/training.md), its
  maps upsampled to the training resolution (what a viewer sees when a lower level is
  drawn at that size); time = one evaluation (trunk and both branches, batch 1) and one
  full runtime frame with the level capped there (previs scene, 256x256, moving camera,
  prims drawn with 1 sample per pixel);
- the renderers: `gl` with 1x1 and 2x2 samples and `embree` with 1x1 and 2x2, time =
  skinning plus drawing one sample, and one full `--reference` frame of the runtime (the
  mesh and the prims drawn by that renderer with those samples);
- with a captured dataset: the nearest captured view and the linear interpolation of
  captured views (`rigspace eval`'s baselines, on the dataset's own ground truth), with
  their memory footprint.

Metrics per variant and split: albedo PSNR and SSIM, mask IoU, depth MAE (% of height),
normal mean angle; times are medians after a warm-up, with min and max.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from rigspace.bench.frame_stages import frame_reports, total_ms
from rigspace.bench.predictors import for_precision
from rigspace.bench.timing import timed
from rigspace.capture.settings import resolve_settings
from rigspace.sdk import schema
from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import Maps, RenderSettings, choose_renderer
from rigspace.sdk.rotations import rig_parameters
from rigspace.train.metrics import map_metrics, mask_iou
from rigspace.train.predictor import to_maps

ROOT = Path(__file__).resolve().parents[1]
PREVIS = ROOT / "samples" / "scenes" / "previs.usda"
TRUTH_SAMPLES = 4
"""Samples per axis of the ground truth (4x4 per pixel)."""
SPLITS = ("heldout-views", "heldout-clip")
KEYS = ("albedo_psnr", "albedo_ssim", "mask_iou", "depth_mae_pct", "normal_mean_deg")


class Samples:
    """Held-out samples of a scene's character, their rig parameters and their truth."""

    def __init__(self, scene: Path, character: str, per_split: int) -> None:
        self.settings, self.rig = resolve_settings(scene, character)
        stage = self.rig.skeleton.GetPrim().GetStage()
        info = schema.read_neural_character(stage.GetPrimAtPath(character))
        self.bundle = schema.resolve_model_path(info)
        joints = BundleModel(self.bundle).joints
        self.order = [schema.find_joint(j, self.rig.joints) for j in joints]
        self.look_at = schema.find_joint(self.settings.look_at_joint, self.rig.joints)
        views = self.settings.views()
        held_views = [v for v in views if v.held_out]
        train_views = [v for v in views if not v.held_out]
        clips = {
            "heldout-views": [c for c in self.settings.clips if not c.held_out],
            "heldout-clip": [c for c in self.settings.clips if c.held_out],
        }
        self.items: dict[str, list[tuple[float, Any]]] = {}
        for split, chosen in clips.items():
            if not chosen:
                continue
            times = np.concatenate([c.times() for c in chosen])
            picks = times[np.linspace(0, len(times) - 1, per_split).astype(int)]
            pool = held_views if split == "heldout-views" else train_views
            self.items[split] = [(float(t), pool[(7 * k) % len(pool)]) for k, t in enumerate(picks)]
        self.height = 0.0
        self.truth: dict[str, list[Maps]] = {}
        self.rigs: dict[str, np.ndarray] = {}
        self.joint_depth: dict[str, np.ndarray] = {}
        self.cameras: dict[str, list] = {}
        renderer = choose_renderer("gl").create(RenderSettings(TRUTH_SAMPLES))
        try:
            for split, items in self.items.items():
                truth, rigs, depths, cameras = [], [], [], []
                for t, view in items:
                    world = self.rig.world_transforms(t)
                    joint = world[self.look_at][:3, 3]
                    up = self.settings.camera_up(world[self.look_at])
                    camera = view.camera(joint, self.settings.lens, up)
                    meshes = self.rig.posed_meshes(t)
                    if not self.height:
                        points = np.concatenate([m.points for m in meshes])
                        self.height = float(np.ptp(points @ view.up))
                    truth.append(renderer.render(meshes, camera))
                    rigs.append(rig_parameters(world[self.order], camera.camera_to_world))
                    depths.append(-float(camera.to_camera(joint[None])[0, 2]))
                    cameras.append(camera)
                self.truth[split] = truth
                self.rigs[split] = np.stack(rigs).reshape(len(items), -1)
                self.joint_depth[split] = np.array(depths)
                self.cameras[split] = cameras
        finally:
            renderer.close()


def _resize(image: np.ndarray, size: int, interpolation: int) -> np.ndarray:
    if image.shape[0] == size:
        return image
    return np.asarray(cv2.resize(image, (size, size), interpolation=interpolation))


def _upsampled(maps: Maps, size: int) -> Maps:
    """A lower level's maps at the training size: bilinear colour and coverage; depth and
    normals nearest (never blended across the silhouette)."""
    return Maps(
        _resize(maps.albedo, size, cv2.INTER_LINEAR),
        _resize(maps.normal, size, cv2.INTER_NEAREST),
        _resize(maps.depth, size, cv2.INTER_NEAREST),
        _resize(maps.mask, size, cv2.INTER_LINEAR),
    )


def _means(rows: list[dict[str, float]]) -> dict[str, float]:
    return {k: float(np.nanmean([r[k] for r in rows])) for k in KEYS}


def model_rows(
    samples: Samples, repeats: int, frame_size: int, frames: int, predictor: str = "auto"
) -> list[dict]:
    """One row per (level, precision): error per split, ms per evaluation and per frame."""
    rows = []
    size = samples.settings.resolution
    times = np.linspace(100.0, 1500.0, frames + 1)
    for precision in ("fp32", "int8"):
        model = BundleModel(
            samples.bundle, precision, predictor=for_precision(predictor, precision)
        )
        for level in model.resolutions:
            row: dict[str, Any] = {"kind": "model", "variant": f"{precision} level {level}"}
            row |= {"precision": precision, "level": level}
            for split, truth in samples.truth.items():
                out = model.predict(samples.rigs[split], level)
                maps = to_maps(out, samples.joint_depth[split], model.depth_scale)
                errors = [
                    map_metrics(_upsampled(m, size), t, samples.height)
                    for m, t in zip(maps, truth, strict=True)
                ]
                row[split] = _means(errors)
                if "alpha" in out:  # the unlit mode's coverage, from the albedo branch alone
                    row[split]["alpha_iou"] = float(
                        np.mean(
                            [
                                mask_iou(_resize(a[0], size, cv2.INTER_LINEAR), t.mask)
                                for a, t in zip(out["alpha"], truth, strict=True)
                            ]
                        )
                    )
            one = samples.rigs["heldout-views"][:1]
            row["evaluation"] = timed(partial(model.predict, one, level), repeats)
            row["frame"] = _frame_time(
                PREVIS,
                frame_size,
                times,
                precision=precision,
                max_level=level,
                prim_samples=1,
                predictor=for_precision(predictor, precision),
            )
            rows.append(row)
    return rows


def _frame_time(scene: Path, size: int, times: np.ndarray, **options) -> dict[str, float]:
    return total_ms(frame_reports(scene, times, size, **options))


def renderer_rows(samples: Samples, repeats: int, frame_size: int, frames: int) -> list[dict]:
    """The real skinned mesh through each renderer: error against the 4x4 truth, and time."""
    rows = []
    times = np.linspace(100.0, 1500.0, frames + 1)
    for name in ("gl", "embree"):
        for s in (1, 2):
            try:
                renderer = choose_renderer(name).create(RenderSettings(s))
            except Exception as exc:  # a renderer this machine lacks is reported, not fatal
                rows.append({"kind": "renderer", "variant": f"{name} {s}x{s}", "skipped": str(exc)})
                continue
            row: dict[str, Any] = {"kind": "renderer", "variant": f"{name} {s}x{s}"}
            row |= {"renderer": name, "samples_per_axis": s}
            try:
                for split, truth in samples.truth.items():
                    errors = []
                    for (t, _), camera, target in zip(
                        samples.items[split], samples.cameras[split], truth, strict=True
                    ):
                        maps = renderer.render(samples.rig.posed_meshes(t), camera)
                        errors.append(map_metrics(maps, target, samples.height))
                    row[split] = _means(errors)
                t0, _ = samples.items["heldout-views"][0]
                draw = partial(_draw, renderer, samples, t0, samples.cameras["heldout-views"][0])
                row["evaluation"] = timed(draw, repeats)
            finally:
                renderer.close()
            row["frame"] = _frame_time(
                PREVIS, frame_size, times, reference=True, renderer=name, prim_samples=s
            )
            rows.append(row)
    return rows


def _draw(renderer, samples: Samples, t: float, camera) -> Maps:
    """One ground-truth sample: skin the mesh with UsdSkel, draw it."""
    return renderer.render(samples.rig.posed_meshes(t), camera)


def baseline_rows(dataset: Path, limit: int) -> list[dict]:
    """The captured-view baselines on the dataset's own ground truth (held-out views)."""
    from rigspace.train.baselines import BaselinePredictor
    from rigspace.train.evaluate import DatasetTable, compare

    table = DatasetTable(dataset)
    predictors = [BaselinePredictor(table, kind) for kind in ("nearest", "linear")]
    result = compare(predictors, table, "heldout-views", limit=limit)
    rows = []
    for r in result["rows"]:
        ms = 1e3 * r["seconds_per_sample"]
        rows.append(
            {
                "kind": "baseline",
                "variant": r["predictor"],
                "heldout-views": {k: r[k] for k in KEYS},
                "evaluation": {"median_ms": ms, "min_ms": ms, "max_ms": ms},
                "footprint_bytes": r["footprint_bytes"],
                "note": f"on {result['samples']} dataset samples (mean time per sample)",
            }
        )
    return rows


def measure(
    per_split: int = 8,
    repeats: int = 10,
    frame_size: int = 256,
    frames: int = 6,
    dataset: Path | None = None,
    scene: Path = PREVIS,
    character: str = "/World/Hero",
    predictor: str = "auto",
) -> dict[str, Any]:
    samples = Samples(scene, character, per_split)
    rows = model_rows(samples, repeats, frame_size, frames, predictor)
    rows += renderer_rows(samples, repeats, frame_size, frames)
    if dataset is not None:
        rows += baseline_rows(dataset, limit=4 * per_split)
    return {
        "truth": f"gl, {TRUTH_SAMPLES}x{TRUTH_SAMPLES} samples per pixel, {samples.settings.resolution}^2",
        "samples": {split: len(items) for split, items in samples.items.items()},
        "frame_size": frame_size,
        "rows": rows,
    }


def plot(result: dict[str, Any], path: Path) -> None:
    """Time (log x) against error, one panel per measure, Pareto front of the model drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (
        ("albedo_psnr", "albedo PSNR (dB), higher is better", True),
        ("mask_iou", "mask IoU, higher is better", True),
        ("normal_mean_deg", "normal mean angle (deg), lower is better", False),
    )
    style = {"model": ("o", "C0"), "renderer": ("s", "C1"), "baseline": ("^", "C2")}
    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    for ax, (key, label, higher) in zip(axes, panels, strict=True):
        for split in SPLITS:
            filled = split == "heldout-views"
            for kind, (marker, colour) in style.items():
                pts = [
                    (r["evaluation"]["median_ms"], r[split][key], r["variant"])
                    for r in result["rows"]
                    if r["kind"] == kind and split in r and "evaluation" in r
                ]
                if not pts:
                    continue
                xs, ys, _ = zip(*pts, strict=True)
                ax.scatter(
                    xs, ys, marker=marker, label=f"{kind}, {split}",
                    facecolors=colour if filled else "none", edgecolors=colour,
                )  # fmt: skip
                if kind == "model":
                    front = _front(list(zip(xs, ys, strict=True)), higher)
                    ax.plot(*zip(*front, strict=True), ":" if not filled else "--",
                            linewidth=0.8, color="gray")  # fmt: skip
                if filled:
                    for x, y, n in pts:
                        ax.annotate(n.replace("level ", ""), (x, y), fontsize=6)
        ax.set_xscale("log")
        ax.set_xlabel("ms per evaluation (log)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"Run time against error (truth: {result['truth']})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _front(points: list[tuple[float, float]], higher: bool) -> list[tuple[float, float]]:
    """The points no other point beats in both time and error, by time."""
    best = -np.inf if higher else np.inf
    front = []
    for x, y in sorted(points):
        if (y > best) if higher else (y < best):
            front.append((x, y))
            best = y
    return front

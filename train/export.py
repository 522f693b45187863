"""Export a trained run as the model bundle: one ONNX graph per (branch, level), int8 variants.

The bundle is the only artefact the runtime reads (DESIGN.md "Model bundle"):

    MODEL/manifest.json
    MODEL/trunk.onnx                                        rig -> shared 8x8 features
    MODEL/albedo_<R>.onnx, MODEL/geometry_<R>.onnx          features -> maps, R = 8, ..., final
    MODEL/*.int8.onnx                                       static QDQ int8 variants (optional)
    MODEL/capsules.json                                     capsule shadow proxies (when the
                                                            dataset has them)

onnxruntime runs every node of a graph even when one output is requested, so separate
graphs are what lets a frame skip a branch or stop at a small level. The shared trunk
(the fully connected layers and the first block, most of the weights) is its own graph:
stored once rather than in every level's graph (a 5x smaller bundle), and run once per
frame even when both branches are needed. Graph inputs and outputs:

    rig      float32 (N, joints * 6)  per-joint camera-space rotations, 6D, manifest order
    features float32 (N, C, 8, 8)     trunk output, the branch graphs' input
    albedo   float32 (N, 3, R, R)     linear RGB premultiplied by coverage, [0, 1]
    depth   float32 (N, 1, R, R)      (depth - joint depth) / depth_scale, valid where mask > 0.5
    normal  float32 (N, 3, R, R)      camera-space unit normals
    mask    float32 (N, 1, R, R)      coverage, [0, 1]
    alpha   float32 (N, 1, R, R)      coverage from the albedo branch, [0, 1]
    chart   float32 (N, K+1, R, R)    texture chart probabilities (softmax; 0: no chart), from
                                      the branch that carries the texture head (manifest
                                      texture.branch: albedo, geometry, or texture_<R>.onnx,
                                      a branch of its own)
    uv      float32 (N, 2K, R, R)     per chart its (u, v) within its uv box, [-1, 1]
    MODEL/charts.json               the texture charts (rigspace.sdk.charts), with a head

Only the levels the run trained are exported, each int8 graph is checked against its fp32
graph (train.int8check), and the dataset's capsules.json (rigspace.sdk.capsules) is copied.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from rigspace.capture.dataset import CHARTS_FILE, DatasetManifest, read_manifest, training_views
from rigspace.sdk.bundle import (
    CONDITIONED_VERSION,
    FORMAT,
    FORMAT_VERSION,
    TEXTURE_BRANCH_VERSION,
    ModelManifest,
    write_manifest_document,
)
from rigspace.sdk.capsules import FILE_NAME as CAPSULES
from rigspace.sdk.capsules import read_capsules
from rigspace.sdk.conditioning import Skeleton2D
from rigspace.sdk.controls import controls_json
from rigspace.sdk.files import replacing, write_atomic
from rigspace.sdk.predictors import GraphSet, OrtRunner
from rigspace.sdk.view_coverage import VIEWS_FILE, views_bytes
from rigspace.sdk.weights import write_safetensors
from rigspace.train.budget import trained_levels
from rigspace.train.conditioning import dataset_skeleton
from rigspace.train.config import TrainConfig
from rigspace.train.data import SampleSet, depth_scale
from rigspace.train.graphs import INPUTS, BranchAtLevel, Trunk, output_names
from rigspace.train.int8check import TOLERANCES, check_int8, rig_feeds
from rigspace.train.loop import CHECKPOINT, RUN_FILE, RunRecord, TrainingError, build_model
from rigspace.train.network import Rig2Image
from rigspace.train.quantize import int8_name
from rigspace.train.torch_predictor import CHECK_TOLERANCE, WEIGHTS, TorchRunner

OPSET = 17
CALIBRATION_SAMPLES = 128
"""Training samples fed to the int8 calibration (activation ranges)."""


def export_graph(model: Rig2Image, branch: str, resolution: int, path: Path) -> None:
    """Export the trunk (branch "trunk") or one branch at one resolution."""
    # A conditioned network's graphs also read joints2d (rigspace.sdk.conditioning).
    joints2d = torch.zeros(1, 2 * model.shape.joints) if model.conditioned else None
    if branch == "trunk":
        wrapper: nn.Module = Trunk(model).eval()
        example: tuple[torch.Tensor, ...] = (torch.zeros(1, model.shape.inputs),)
    else:
        wrapper = BranchAtLevel(model, branch, resolution).eval()
        example = (model.features(torch.zeros(1, model.shape.inputs), joints2d),)
    inputs = [INPUTS[branch]]
    if joints2d is not None:
        example, inputs = (*example, joints2d), [*inputs, "joints2d"]
    names = output_names(branch, model.charts if branch == model.texture_branch else 0)
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of torch.export; it is the one that
        # needs no onnxscript and gives plain, stable graphs for this small static network.
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.onnx")
        warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX export.*")
        with replacing(path, ".onnx") as tmp:  # a re-export replaces each graph in one step
            _export(wrapper, example, tmp, inputs, names)


def _export(
    wrapper: nn.Module,
    example: tuple[torch.Tensor, ...],
    path: Path,
    inputs: list[str],
    names: list[str],
) -> None:
    torch.onnx.export(
        wrapper,
        example,
        str(path),
        input_names=inputs,
        output_names=names,
        dynamic_axes={name: {0: "n"} for name in [*inputs, *names]},
        opset_version=OPSET,
        dynamo=False,  # the TorchScript exporter: no onnxscript needed, stable graphs
    )
    if "chart" in names:  # the texture head's softmax in the form onnxruntime runs fast
        import onnx

        from rigspace.train.graph_rewrite import fast_channel_softmax

        graph = onnx.load(str(path))
        fast_channel_softmax(graph)
        onnx.save(graph, str(path))


def quantize_int8(
    fp32: Path, int8: Path, input_name: str, calibration: np.ndarray | dict[str, np.ndarray]
) -> None:
    """Static QDQ int8 of one exported graph, calibrated on `calibration` (the graph's input
    for the training rows, or rows by input name): train.quantize. Activation ranges come from the pixels the
    character covers (MinMax, Percentile and Entropy calibration lose 7-10 dB at level 128
    on the sample model: its background activations are 20x its character's); a branch
    keeps its output heads, and the convolutions a per-node sweep finds it must, in float
    (a mixed graph). The trunk is quantised whole: its check (train.int8check) judges it.
    A graph with more inputs (a pose-conditioned one's joints2d) gets `calibration` as a
    dict of rows by input name; each graph reads those it has (int8check.graph_feeds).
    """
    from rigspace.train.quantize import mixed_int8, quantize

    if isinstance(calibration, dict):
        feeds = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in calibration.items()}
    else:
        feeds = {input_name: np.ascontiguousarray(calibration, dtype=np.float32)}
    if input_name == INPUTS["trunk"]:
        quantize(fp32, int8, feeds)
    else:
        mixed_int8(fp32, int8, feeds)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


BUNDLE_GRAPHS = ("trunk*.onnx", "albedo_*.onnx", "geometry_*.onnx", CHARTS_FILE, WEIGHTS)
"""Names of the graphs an export writes: a re-export removes those it no longer writes."""
INT8_CHECK_SAMPLES = 32
"""Held-out rows (training rows when there are none) each int8 graph is checked on."""


def check_rows(dataset: Path) -> tuple[np.ndarray, str]:
    """Rig rows for the int8 check: held-out views, evenly spaced; training rows without them."""
    for split in ("heldout-views", "train"):
        samples = SampleSet(dataset, split)
        if len(samples):
            picks = np.linspace(0, len(samples) - 1, min(INT8_CHECK_SAMPLES, len(samples)))
            return samples.rig[samples.rows[np.unique(picks.astype(int))]], split
    raise TrainingError(f"{dataset} has no samples.", "capture the dataset again.")


def export_bundle(
    run_folder: str | Path,
    out: str | Path,
    *,
    int8: bool = True,
    metrics: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the model bundle of a training run; return its manifest.

    Only the levels the run trained are exported (train.budget.trained_levels: a run
    stopped by a budget before a level faded in has no usable graph there), and the
    manifest says which. Each int8 graph is checked against fp32 (train.int8check) and a
    failed one is marked in `int8_check`. Graphs of an earlier export into `out` that
    this one does not write are removed, after the new manifest is in place.
    """
    run_folder, out = Path(run_folder), Path(out)
    model, run, step = _trained_run(run_folder)
    config = run.train_config()
    resolutions = [r for r in model.albedo.resolutions if r <= trained_levels(config, step)[-1]]
    dataset = Path(run.dataset)
    data_manifest = read_manifest(dataset)
    # Capsules are fitted to the character, not trained: the dataset's copy wins; without
    # one, those already in the bundle (added by `python -m rigspace.apps.capsules`) stay.
    source = dataset / CAPSULES
    capsules = source if source.is_file() else out / CAPSULES
    if capsules.is_file():
        read_capsules(capsules)  # before any graph is written: a CapsuleError naming the file
    skeleton = dataset_skeleton(dataset, data_manifest) if model.conditioned else None
    out.mkdir(parents=True, exist_ok=True)
    calibration = _calibration(model, dataset, skeleton) if int8 else {}
    trunk, levels, written = _write_graphs(model, out, resolutions, calibration if int8 else None)
    manifest = bundle_manifest(model, run, step, data_manifest, trunk, levels, metrics)
    if skeleton is not None:
        manifest["format_version"] = CONDITIONED_VERSION
        manifest["conditioning"] = _conditioning(config, skeleton)
        manifest["inputs"]["joints2d"] = JOINTS2D_INPUT
    if model.texture is not None:  # the texture head's own graphs: readers from version 4
        manifest["format_version"] = TEXTURE_BRANCH_VERSION
    rows, split = check_rows(dataset)  # the int8 graphs' and the weights' check
    if int8:
        manifest["int8_check"] = _int8_check(out, trunk, levels, rows, split, skeleton)
    if source.is_file():
        write_atomic(out / CAPSULES, source.read_bytes())
    if capsules.is_file():
        manifest["capsules"] = CAPSULES
        written.append(CAPSULES)
    if model.charts:
        manifest["texture"] = _write_texture(model, dataset, out)
        written.append(CHARTS_FILE)
    written.append(add_weights(out, manifest, model, step, run.config, rows, split, skeleton))
    views = _write_views(out, dataset, run.joints)
    if views is not None:
        manifest["views"] = views
        written.append(VIEWS_FILE)
    manifest["files"] = {
        name: {"bytes": (out / name).stat().st_size, "sha256": _sha256(out / name)}
        for name in sorted(written)
    }
    write_manifest_document(out, manifest)  # checked as the readers check it, then written
    remove_stale(out, set(written))
    return manifest


def _write_views(out: Path, dataset: Path, joints: Sequence[str]) -> dict[str, Any] | None:
    """The training views of the look-at joint (sdk.view_coverage): `views.npy` and the
    manifest's `views` section; None for a dataset without training rows or look-at joint."""
    views = training_views(dataset, joints)
    if views is None:
        return None
    coverage, every = views
    write_atomic(out / VIEWS_FILE, views_bytes(coverage))
    return coverage.to_json(len(coverage.rotations), every)


def _int8_check(
    out: Path,
    trunk: dict[str, str],
    levels: list[dict[str, Any]],
    rows: np.ndarray,
    split: str,
    skeleton: Skeleton2D | None,
) -> dict[str, Any]:
    """The manifest's int8_check: each int8 graph checked against fp32 on `rows` of `split`."""
    return {
        "split": split,
        "samples": len(rows),
        "tolerances": {k: f"{op} {limit:g}" for k, (op, limit) in TOLERANCES.items()},
        "graphs": check_int8(out, trunk, levels, rows, skeleton=skeleton),
    }


def _write_texture(model: Rig2Image, dataset: Path, out: Path) -> dict[str, Any]:
    """Copy the chart table the texture head numbers from the dataset (capture wrote it) into
    the bundle; the manifest's texture section."""
    write_atomic(out / CHARTS_FILE, (dataset / CHARTS_FILE).read_bytes())
    return {
        "charts": model.charts,
        "file": CHARTS_FILE,
        "branch": model.texture_branch,
        "outputs": ["chart", "uv"],
    }


def _trained_run(run_folder: Path) -> tuple[Rig2Image, RunRecord, int]:
    """The run's network at its checkpoint, its run.json and step; a TrainingError when it
    has trained no level yet."""
    if (run_folder / RUN_FILE).is_file() and not (run_folder / CHECKPOINT).is_file():
        raise TrainingError(
            f"The run in {run_folder} has trained no level yet (no step, no checkpoint).",
            "train longer: continue it with --resume (and a larger --steps or --minutes).",
        )
    model, run, step = build_model(run_folder)
    if not trained_levels(run.train_config(), step):
        raise TrainingError(
            f"The run in {run_folder} has trained no level yet (step {step}).",
            "train longer: continue it with --resume (and a larger --steps or --minutes).",
        )
    return model, run, step


def _calibration(
    model: Rig2Image, dataset: Path, skeleton: Skeleton2D | None
) -> dict[str, np.ndarray]:
    """The int8 calibration's rows by input name: rig, features and (conditioned) joints2d,
    the rows' own by rigspace.sdk.conditioning; each graph is fed the inputs it reads
    (train.quantize)."""
    train = SampleSet(dataset, "train")
    picks = np.linspace(0, len(train) - 1, min(CALIBRATION_SAMPLES, len(train))).astype(int)
    calibration = rig_feeds(train.rig[train.rows[picks]], skeleton)
    with torch.no_grad():
        tensors = {k: torch.from_numpy(v) for k, v in calibration.items()}
        features = model.features(tensors["rig"], tensors.get("joints2d"))
    calibration["features"] = features.numpy()
    return calibration


def _write_graphs(
    model: Rig2Image,
    out: Path,
    resolutions: list[int],
    calibration: dict[str, np.ndarray] | None,
) -> tuple[dict[str, str], list[dict[str, Any]], list[str]]:
    """The trunk's and every level's branch graphs (and int8 variants, given calibration):
    the trunk's names, the manifest's levels and every file written."""
    written: list[str] = []

    def write(branch: str, resolution: int, stem: str) -> dict[str, str]:
        names = {"fp32": f"{stem}.onnx"}
        export_graph(model, branch, resolution, out / names["fp32"])
        if calibration is not None:
            names["int8"] = int8_name(names["fp32"])
            quantize_int8(out / names["fp32"], out / names["int8"], INPUTS[branch], calibration)
        written.extend(names.values())
        return names

    with torch.no_grad():
        trunk = write("trunk", 8, "trunk")
        levels = []
        for resolution in resolutions:
            entry: dict[str, Any] = {"resolution": resolution, "graphs": {}, "int8": {}}
            for branch in model.branch_names:
                names = write(branch, resolution, f"{branch}_{resolution}")
                entry["graphs"][branch] = names["fp32"]
                if "int8" in names:
                    entry["int8"][branch] = names["int8"]
            levels.append(entry)
    return trunk, levels, written


RIG_INPUT = (
    "float32 (N, joints*6 + blend_shapes + controls): per joint the world rotation in the "
    "camera frame, first two matrix columns (r00 r10 r20 r01 r11 r21), then each blend "
    "shape's weight (manifest blend_shapes order, when there are any), then each named "
    "control's value (manifest controls order, when there are any); input of the trunk graph"
)
JOINTS2D_INPUT = (
    "float32 (N, joints*2): per joint (u, v), the joint by forward kinematics from the "
    "rig and conditioning.skeleton, projected by a camera at the training distance "
    "from the look-at joint; [-1, 1] across the image, v down "
    "(rigspace.sdk.conditioning.joints2d); input of the trunk and of every branch "
    "graph above 8x8 (int8 variants included)"
)
OUTPUTS = {
    "albedo": "float32 (N,3,R,R) linear RGB premultiplied by mask, [0,1]",
    "depth": "float32 (N,1,R,R) (camera depth along -Z - joint depth) / depth.scale",
    "normal": "float32 (N,3,R,R) camera-space unit normals",
    "mask": "float32 (N,1,R,R) coverage in [0,1]",
    "alpha": "float32 (N,1,R,R) coverage in [0,1] from the albedo branch (for frames "
    "that run the albedo branch alone)",
}
TEXTURE_OUTPUTS = {
    "chart": "float32 (N,K+1,R,R) texture chart probabilities (softmax over "
    "the charts of texture.file; 0: background or no texture), from the "
    "graphs of the branch texture.branch",
    "uv": "float32 (N,2K,R,R) per chart k (channels 2(k-1), 2(k-1)+1) its "
    "texture coordinates within its uv box (charts.json uv_min..uv_max mapped "
    "to -1..1), from the graphs of the branch texture.branch",
}


def bundle_manifest(
    model: Rig2Image,
    run: RunRecord,
    step: int,
    data_manifest: DatasetManifest,
    trunk: dict[str, str],
    levels: list[dict[str, Any]],
    metrics: dict[str, Any] | None,
) -> dict[str, Any]:
    """The manifest's document for these graphs (export_bundle adds the conditioning, the
    int8 check, capsules, texture and files sections)."""
    ring = data_manifest.ring
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "joints": list(run.joints),
        **({"blend_shapes": list(run.blend_shapes)} if run.blend_shapes else {}),
        **({"controls": controls_json(run.controls)} if run.controls else {}),
        "rotation_encoding": "rot6d",
        "look_at_joint": data_manifest.look_at_joint,
        "maps": ["albedo", "normal", "depth", "mask"],
        "trunk": {"graphs": {"trunk": trunk["fp32"]}, "int8": {"trunk": trunk.get("int8")}},
        "levels": levels,
        "inputs": {
            "rig": RIG_INPUT,
            "features": "float32 (N, C, 8, 8): the trunk's output, input of every branch graph",
        },
        "outputs": {**OUTPUTS, **(TEXTURE_OUTPUTS if model.charts else {})},
        "depth": {
            "encoding": "relative-to-look-at-joint",
            "scale": depth_scale(data_manifest),
            "units": "scene units",
        },
        "training_camera": {
            "distance": ring.radius,
            "focal_length": ring.focal_length,
            "horizontal_aperture": ring.horizontal_aperture,
            "resolution": data_manifest.resolution,
            **(
                {"upright_axis": list(data_manifest.settings["upright_axis"])}
                if data_manifest.settings.get("upright_axis")
                else {}
            ),
        },
        **(
            {"meters_per_unit": data_manifest.meters_per_unit}
            if data_manifest.meters_per_unit is not None
            else {}
        ),
        "dataset": {
            "checksum": data_manifest.checksum,
            "scene_fingerprint": data_manifest.scene_fingerprint,
            "character": data_manifest.character,
            "samples": dict(data_manifest.counts),
        },
        "training": _training_section(model, run, step, levels),
        "metrics": metrics or {},
    }


def _training_section(
    model: Rig2Image, run: RunRecord, step: int, levels: list[dict[str, Any]]
) -> dict[str, Any]:
    """The manifest's training section: the run's config, steps and levels, trained and planned."""
    return {
        "config": run.config,
        "steps": step,
        "planned_steps": run.train_config().total_steps(),
        "trained_levels": [level["resolution"] for level in levels],
        "planned_levels": list(model.albedo.resolutions),
        **({"plan": run.plan} if run.plan else {}),
    }


def _conditioning(config: TrainConfig, skeleton: Skeleton2D) -> dict[str, Any]:
    return {
        "kind": config.conditioning,
        "sigma": config.conditioning_sigma,
        "mode": config.conditioning_mode,
        "top": config.conditioning_top,
        "input": "joints2d",
        "skeleton": skeleton.to_json(),
    }


def add_weights(
    out: Path,
    manifest: dict[str, Any],
    model: Rig2Image,
    step: int,
    config: dict[str, Any],
    rows: np.ndarray,
    split: str,
    skeleton: Skeleton2D | None,
) -> str:
    """Write the network's weights beside the graphs for the torch predictor
    (train.torch_predictor) and its manifest section `torch`, with their check against the
    fp32 graphs; returns the file's name. `manifest` is the bundle's, its graphs written."""
    write_safetensors(
        out / WEIGHTS,
        {k: v.detach().cpu().float().numpy() for k, v in model.state_dict().items()},
        {"format": "rigspace.weights", "step": str(step)},
    )
    manifest["torch"] = {
        "file": WEIGHTS,
        "config": config,
        "joints": model.shape.joints,
        "parents": list(model.shape.parents),
        "charts": model.shape.charts,
        **({"blend_shapes": model.shape.blend_shapes} if model.shape.blend_shapes else {}),
        **({"controls": model.shape.controls} if model.shape.controls else {}),
    }
    manifest["torch"]["check"] = {"split": split, **check_weights(out, manifest, rows, skeleton)}
    return WEIGHTS


def check_weights(
    folder: Path, manifest: dict[str, Any], rows: np.ndarray, skeleton: Skeleton2D | None
) -> dict[str, Any]:
    """The torch predictor (CPU, fp32) against every fp32 graph of a bundle being exported, on
    the rig rows `rows`: the largest |difference| per graph over all its outputs, and
    whether it is within CHECK_TOLERANCE with the same inputs and outputs by name."""
    graphs = {manifest["trunk"]["graphs"]["trunk"]: ("trunk", 8)}
    for level in manifest["levels"]:
        for branch, file in level["graphs"].items():
            graphs[file] = (branch, int(level["resolution"]))
    bundle = ModelManifest.from_json(json.loads(json.dumps(manifest)), folder / "manifest.json")
    request = GraphSet(bundle, "fp32", 1, graphs)
    ours = TorchRunner(request, device="cpu", half=False, cuda_graphs=False)
    onnx = OrtRunner(request, ["CPUExecutionProvider"], "CPU")
    feeds = rig_feeds(rows, skeleton)
    trunk = next(iter(graphs))
    feeds["features"] = onnx.run(trunk, {k: feeds[k] for k in onnx.inputs(trunk)})["features"]
    worst: dict[str, float] = {}
    same = True
    for graph in graphs:
        names = onnx.inputs(graph)
        same &= names == ours.inputs(graph)
        given = {k: feeds[k] for k in names}
        a, b = onnx.run(graph, given), ours.run(graph, given)
        same &= sorted(a) == sorted(b)
        worst[graph] = max(float(np.abs(a[k] - b[k]).max()) for k in a if k in b)
    largest = max(worst.values())
    return {
        "samples": len(rows),
        "max_abs": largest,
        "tolerance": CHECK_TOLERANCE,
        "ok": bool(same and largest <= CHECK_TOLERANCE),
        "graphs": worst,
    }


def remove_stale(out: Path, keep: set[str]) -> list[str]:
    """Delete the graphs in `out` an earlier export wrote and this one did not."""
    stale = {p.name for pattern in BUNDLE_GRAPHS for p in out.glob(pattern)}
    removed = sorted(name for name in stale - keep if (out / name).is_file())
    for name in removed:
        (out / name).unlink()
    return removed

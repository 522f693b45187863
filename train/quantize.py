"""Static int8 graphs that keep accuracy: coverage-aware calibration and a mixed fp32/int8 graph.

Why MinMax, Percentile and Entropy calibration all fail on these networks (measured on the
sample model's albedo_128, 32 held-out rows, int8 against fp32, head left in float: 22.2,
21.9 and 22.2 dB): the branches have no normalisation, and the background, which only has
to drive the output sigmoids to 0, carries activations of up to 4,000 while the character's
pixels stay below 200 (median 1-15). One scale per tensor spends the 256 steps on the
background, and the character's pixels get a handful of them. Calibrating each activation
on the pixels the character covers (its coverage output box-downsampled to the tensor's
size, dilated by one pixel, 99.99th percentile both ways) gives them the steps; background
activations saturate, which the sigmoids do not see. Same graph: 41-42 dB.

The 1x1 output heads stay in float (their logits are what the sigmoids read, and they are
cheap), and a greedy per-node sweep keeps further convolutions in float until the graph
meets SWEEP_TARGET on the calibration rows (onnxruntime's nodes_to_exclude). A
pose-conditioned graph's maps, computed from its joints2d input, stay in float too (pose_nodes).
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.sdk.bundle import read_manifest_document, write_manifest_document
from rigspace.sdk.conditioning import Skeleton2D
from rigspace.sdk.files import replacing
from rigspace.train.int8check import drift, graph_feeds, named_outputs, rig_feeds, session

COVERAGE_OUTPUTS = ("alpha", "mask")
"""A branch graph's outputs whose coverage selects the pixels its activations calibrate on."""
COVERED = 0.01
"""Coverage from which a pixel (or a box of them, at a tensor's lower resolution) counts."""
DILATE = 1
"""Pixels the covered region grows by at each tensor's resolution (the silhouette's edge)."""
RANGE_PERCENTILE = 99.99
"""Each activation's range: this percentile of its values (and 100 minus it) on the region."""
SPATIAL_OPS = ("Conv", "LeakyRelu", "Relu", "Resize", "Add", "Concat", "Mul")
"""Ops whose (N, C, H, W) outputs get a coverage-aware range."""
SWEEP_TARGET = {"albedo_psnr": 40.0, "alpha_iou": 0.98, "mask_iou": 0.98, "normal_mean_deg": 3.0}
"""int8 against fp32 on the calibration rows that a mixed graph must reach (the sweep keeps
more convolutions in float until it does, at most `max_float`): a little above int8check.AIM,
since held-out rows drift slightly more than the calibration rows."""
SWEEP_ROWS = 32
"""Calibration rows the sweep measures on (fewer than calibrate on: it quantises often)."""


def _region(coverage: np.ndarray, size: int) -> np.ndarray:
    """(N, R, R) coverage -> (N, size, size) bool: boxes with any coverage, dilated."""
    factor = coverage.shape[-1] // size
    n = len(coverage)
    region = coverage.reshape(n, size, factor, size, factor).max(axis=(2, 4)) > COVERED
    for _ in range(DILATE):
        p = np.pad(region, ((0, 0), (1, 1), (1, 1)))
        region = (
            p[:, 1:-1, 1:-1] | p[:, :-2, 1:-1] | p[:, 2:, 1:-1] | p[:, 1:-1, :-2] | p[:, 1:-1, 2:]
        )
    return region


def _is_image(value: np.ndarray, coverage: np.ndarray) -> bool:
    """Whether `value` is (N, C, R, R) for the coverage's rows at a resolution that divides
    the coverage's: not a broadcast row or column (a conditioning map's pixel grid)."""
    n, size = len(coverage), coverage.shape[-1]
    return (
        value.ndim == 4
        and value.shape[0] == n
        and value.shape[-2] == value.shape[-1] <= size
        and size % value.shape[-1] == 0
    )


def activation_ranges(fp32: Path, feeds: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """Per intermediate tensor of a graph, the (rmin, rmax) its int8 scale should cover.

    Branch graphs (an alpha or mask output): spatial tensors on the covered region (module
    docstring); the trunk: every value. The range always includes 0 (int8 zero exact).
    """
    import onnx

    model = onnx.load(str(fp32))
    names = [
        n.output[0]
        for n in model.graph.node
        if n.op_type in SPATIAL_OPS or n.op_type in ("Gemm", "MatMul", "Reshape")
    ]
    known = {o.name for o in model.graph.output}
    for name in names:
        if name not in known:
            model.graph.output.append(onnx.helper.make_value_info(name, onnx.TypeProto()))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "probe.onnx"
        onnx.save(model, str(path))
        out = named_outputs(session(path), feeds)
    coverage = next((out[k][:, 0] for k in COVERAGE_OUTPUTS if k in out), None)
    ranges: dict[str, tuple[float, float]] = {}
    for name in names:
        value = out[name]
        if coverage is not None and _is_image(value, coverage):
            region = _region(coverage, value.shape[-1])
            picked = np.moveaxis(value, 1, -1)[region]
            value = picked if picked.size else value
        lo, hi = np.percentile(value, [100 - RANGE_PERCENTILE, RANGE_PERCENTILE])
        ranges[name] = (min(float(lo), 0.0), max(float(hi), 0.0))
    return ranges


class _Calibration:
    """onnxruntime's CalibrationDataReader protocol over a graph's real inputs, in batches."""

    def __init__(self, feeds: dict[str, np.ndarray], batch: int = 16) -> None:
        self._feeds, self._batch, self._at = feeds, batch, 0
        self._n = len(next(iter(feeds.values())))

    def get_next(self):
        if self._at >= self._n:
            return None
        part = {k: v[self._at : self._at + self._batch] for k, v in self._feeds.items()}
        self._at += self._batch
        return part

    def rewind(self) -> None:
        self._at = 0


def head_nodes(fp32: Path) -> list[str]:
    """The convolutions whose outputs reach a graph output with no other Conv or Gemm
    between, and the nodes between (their logits' slices and activations): kept in float."""
    import onnx

    graph = onnx.load(str(fp32)).graph
    producer = {o: n for n in graph.node for o in n.output}
    heads: list[str] = []
    stack = [o.name for o in graph.output]
    seen: set[str] = set()
    while stack:
        tensor = stack.pop()
        node = producer.get(tensor)
        if node is None or node.name in seen:
            continue
        seen.add(node.name)
        heads.append(node.name)
        if node.op_type not in ("Conv", "Gemm"):
            stack.extend(node.input)
    # The trunk's output is the features every branch reads: its last layer is quantised.
    return sorted(heads) if any(o.name != "features" for o in graph.output) else []


def pose_nodes(fp32: Path) -> list[str]:
    """The nodes of a pose-conditioned graph that read joints2d and constants only: the
    conditioning maps' computation (rigspace.train.conditioning.ConditionMaps, and in
    conditioning_mode "add" their 1x1 projection). Kept in float: uint8 steps of the squared
    distances would move a Gaussian's peak by pixels, and they are cheap next to the
    convolutions that read them (quantised at their input). Empty without joints2d."""
    import onnx

    graph = onnx.load(str(fp32)).graph
    pose = {i.name for i in graph.input if i.name == "joints2d"}
    constant = {t.name for t in graph.initializer}
    nodes: list[str] = []
    for node in graph.node:  # ONNX nodes are in topological order
        inputs = [name for name in node.input if name]
        if not inputs:
            constant.update(node.output)
        elif any(i in pose for i in inputs) and all(i in pose or i in constant for i in inputs):
            pose.update(node.output)
            nodes.append(node.name)
    return nodes


def softmax_nodes(fp32: Path) -> list[str]:
    """The nodes of the texture head's softmax (from the chart logits' convolution to the
    `chart` output; in graph_rewrite's fast form its sum is a convolution too), kept in
    float: probabilities in uint8 steps would blur the chart borders the runtime draws at
    display size, and a quantised sum would miss its weights of one. Empty without a
    texture head."""
    import onnx

    graph = onnx.load(str(fp32)).graph
    producer = {out: node for node in graph.node for out in node.output}
    nodes: list[str] = []
    pending = [o.name for o in graph.output if o.name == "chart"]
    while pending:
        node = producer.get(pending.pop())
        if node is None or node.name in nodes:
            continue
        if node.op_type == "Conv" and not node.name.startswith("channel_softmax"):
            continue  # the logits' own convolution
        nodes.append(node.name)
        pending.extend(i for i in node.input if i in producer)
    return nodes


def quantize(
    fp32: Path,
    int8: Path,
    feeds: dict[str, np.ndarray],
    exclude: list[str] | tuple[str, ...] = (),
    ranges: dict[str, tuple[float, float]] | None = None,
) -> None:
    """One static QDQ int8 graph: per-channel int8 weights, uint8 activations whose ranges
    are activation_ranges (computed on `feeds` unless given), `exclude` kept in float.
    `feeds` holds rows by input name; those the graph does not read are left out."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    feeds = graph_feeds(session(fp32), feeds)  # the calibration reader feeds every key
    ranges = activation_ranges(fp32, feeds) if ranges is None else ranges
    overrides = {
        name: [{"rmin": np.float32(lo), "rmax": np.float32(hi)}]
        for name, (lo, hi) in ranges.items()
    }
    # onnxruntime still calibrates the tensors without an override (the graph input):
    # MinMax on the same rows.
    with tempfile.TemporaryDirectory() as tmp:
        prepared = Path(tmp) / "prepared.onnx"
        quant_pre_process(str(fp32), str(prepared), skip_symbolic_shape=True)
        with replacing(int8, ".onnx") as written:  # in place, in one step (requantize_bundle)
            quantize_static(
                str(prepared),
                str(written),
                _Calibration(feeds),
                quant_format=QuantFormat.QDQ,
                activation_type=QuantType.QUInt8,
                weight_type=QuantType.QInt8,
                per_channel=True,
                nodes_to_exclude=[*exclude, *pose_nodes(fp32), *softmax_nodes(fp32)],
                calibrate_method=CalibrationMethod.MinMax,
                extra_options={"TensorQuantOverrides": overrides},
            )


def meets(metrics: dict[str, float | None], target: dict[str, float] | None = None) -> bool:
    """Whether int8-against-fp32 metrics reach the sweep's target (None: not judged)."""
    target = SWEEP_TARGET if target is None else target
    for key, limit in target.items():
        value = metrics.get(key)
        if value is None:
            continue
        if (value > limit) if key.endswith("_deg") else (value < limit):
            return False
    return True


def _score(metrics: dict[str, float | None]) -> float:
    """How far a graph is from the target (0 when it meets it), to rank the sweep's steps."""
    gap = 0.0
    for key, limit in SWEEP_TARGET.items():
        value = metrics.get(key)
        if value is None:
            continue
        if key == "albedo_psnr":
            gap += max(0.0, limit - value) / 10.0
        elif key.endswith("_deg"):
            gap += max(0.0, value - limit) / 10.0
        else:
            gap += max(0.0, limit - value) * 10.0
    return gap


def mixed_int8(
    fp32: Path, int8: Path, feeds: dict[str, np.ndarray], max_float: int = 2
) -> dict[str, Any]:
    """Quantise a graph, keeping its heads and, greedily, up to `max_float` more
    convolutions in float until int8 meets SWEEP_TARGET against fp32 on SWEEP_ROWS of the
    calibration rows. Returns {"float_nodes", "metrics", "meets"}."""
    import onnx

    n = len(next(iter(feeds.values())))
    picks = np.unique(np.linspace(0, n - 1, min(SWEEP_ROWS, n)).astype(int))
    probe = {k: v[picks] for k, v in feeds.items()}
    reference = named_outputs(session(fp32), probe)
    ranges = activation_ranges(fp32, feeds)
    exclude = head_nodes(fp32)

    def attempt(nodes: list[str], path: Path) -> dict[str, float | None]:
        quantize(fp32, path, feeds, nodes, ranges)
        return drift(reference, named_outputs(session(path), probe))

    metrics = attempt(exclude, int8)
    convs = [n.name for n in onnx.load(str(fp32)).graph.node if n.op_type == "Conv"]
    with tempfile.TemporaryDirectory() as tmp:
        trial = Path(tmp) / "trial.onnx"
        while not meets(metrics) and len(exclude) - len(head_nodes(fp32)) < max_float:
            candidates = [c for c in convs if c not in exclude]
            if not candidates:
                break
            # Leave-one-out: the convolution whose float copy brings the graph closest.
            scored = [(_score(attempt([*exclude, c], trial)), c) for c in candidates]
            exclude.append(min(scored)[1])
            metrics = attempt(exclude, int8)
    return {"float_nodes": sorted(exclude), "metrics": metrics, "meets": meets(metrics)}


def requantize_bundle(bundle: Path, dataset: Path, rows: int = 128) -> dict[str, Any]:
    """Re-quantise a bundle's int8 graphs from its fp32 graphs (no checkpoint needed) and
    re-check them; the fp32 graphs are not touched. Calibration: `rows` training rows,
    evenly spaced (real poses), with their joints2d when the bundle is pose-conditioned
    (the manifest's conditioning.skeleton); check: held-out rows (export.check_rows'
    choice). A bundle exported without int8 variants gets them, named as the export names
    them. Writes the int8 graphs, their manifest entries and file records and the
    manifest's int8_check (with offered_levels); returns the new int8_check."""
    from rigspace.train.data import SampleSet

    manifest = read_manifest_document(bundle)
    train = SampleSet(dataset, "train")
    picks = np.unique(np.linspace(0, len(train) - 1, min(rows, len(train))).astype(int))
    inputs = rig_feeds(
        train.rig[train.rows[picks]], Skeleton2D.of_conditioning(manifest.get("conditioning"))
    )
    trunk = manifest["trunk"]["graphs"]["trunk"]
    features = named_outputs(session(bundle / trunk), inputs)["features"]
    int8 = manifest["trunk"].setdefault("int8", {})
    int8["trunk"] = int8.get("trunk") or int8_name(trunk)
    quantize(bundle / trunk, bundle / int8["trunk"], inputs)
    branch_feeds = {**inputs, "features": features}
    for level in manifest["levels"]:
        for branch, fp32 in level["graphs"].items():
            name = level.setdefault("int8", {}).get(branch) or int8_name(fp32)
            mixed_int8(bundle / fp32, bundle / name, branch_feeds)
            level["int8"][branch] = name
    _write_manifest(bundle, manifest)
    return recheck_bundle(bundle, dataset)


def int8_name(fp32: str) -> str:
    """The int8 variant's file name of an fp32 graph (train.export's naming)."""
    return f"{fp32.removesuffix('.onnx')}.int8.onnx"


def _write_manifest(bundle: Path, manifest: dict[str, Any]) -> None:
    """Write a bundle's manifest (sdk.bundle.write_manifest_document: checked, atomic), with
    the size and sha256 of every int8 graph it lists (the export's `files` records, which the
    runtime's rules verify)."""
    import hashlib

    names = [manifest["trunk"]["int8"].get("trunk")]
    names += [name for level in manifest["levels"] for name in level["int8"].values()]
    files = manifest.setdefault("files", {})
    for name in filter(None, names):
        data = (bundle / name).read_bytes()
        files[name] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    manifest["files"] = dict(sorted(files.items()))
    write_manifest_document(bundle, manifest)


def recheck_bundle(bundle: Path, dataset: Path, limit: int = 200) -> dict[str, Any]:
    """Check a bundle's int8 graphs against fp32 (int8check.check_int8, per graph; a
    pose-conditioned bundle's graphs fed joints2d from its skeleton) and, per level,
    against the truth (level_table, `limit` held-out samples); write both into the
    manifest's int8_check, with `offered_levels`: the levels whose int8 graphs all pass
    the check and where int8 is within AIM_TRUTH of fp32 and MIN_SPEEDUP faster."""
    import json

    from rigspace.train.data import SampleSet
    from rigspace.train.evaluate import to_json
    from rigspace.train.int8check import TOLERANCES, check_int8

    manifest = read_manifest_document(bundle)
    trunk = manifest["trunk"]["graphs"]["trunk"]
    trunk_int8 = manifest["trunk"]["int8"]["trunk"]
    split = "heldout-views" if len(SampleSet(dataset, "heldout-views")) else "train"
    held = SampleSet(dataset, split)
    picks = np.unique(np.linspace(0, len(held) - 1, min(32, len(held))).astype(int))
    check_rig = held.rig[held.rows[picks]]
    entry = {"fp32": trunk, "int8": trunk_int8}
    graphs = check_int8(
        bundle,
        entry,
        manifest["levels"],
        check_rig,
        skeleton=Skeleton2D.of_conditioning(manifest.get("conditioning")),
    )
    levels = level_table(bundle, dataset, split, limit)
    ok = all(g["ok"] for g in graphs.values())
    check = {
        "split": split,
        "samples": len(check_rig),
        "calibration": "training rows, coverage-aware ranges, heads in float (train.quantize)",
        "tolerances": {k: f"{op} {v:g}" for k, (op, v) in TOLERANCES.items()},
        "graphs": graphs,
        "levels": {str(r): e for r, e in levels.items()},
        "offered_levels": [r for r, e in levels.items() if e["offered"] and ok],
    }
    manifest["int8_check"] = json.loads(to_json(check))  # strict JSON: nan -> null
    _write_manifest(bundle, manifest)
    return check


AIM_TRUTH = {"albedo_psnr": 0.5, "mask_iou": 0.01, "alpha_iou": 0.01}
"""Against the truth, the most int8 may lose to fp32 at a level (issue 12): dB, IoU."""


def _evaluation_ms(model_fp32, model_int8, rig: np.ndarray, resolution: int) -> dict[str, float]:
    """ms of one evaluation (trunk, both branches; batch 1), fp32 and int8 interleaved,
    the fastest of 30 each."""
    import time

    one = rig[:1]
    runs: dict[str, list[float]] = {"fp32": [], "int8": []}
    for model in (model_fp32, model_int8):
        model.predict(one, resolution)  # sessions loaded, warmed up
    for _ in range(30):
        for key, model in (("fp32", model_fp32), ("int8", model_int8)):
            start = time.perf_counter()
            model.predict(one, resolution)
            runs[key].append(time.perf_counter() - start)
    ms = {k: 1000 * float(np.min(v)) for k, v in runs.items()}  # as int8check's timing
    return {**ms, "speedup": ms["fp32"] / ms["int8"]}


def level_table(bundle: Path, dataset: Path, split: str = "heldout-views", limit: int = 200):
    """Per level, fp32 and int8 against the truth (box-downsampled to the level, as in
    training) on the same `limit` samples: albedo PSNR, mask IoU, alpha IoU, depth % of
    height, normal median; ms per evaluation (one thread, batch 1) and the speed ratio;
    and whether int8 is within AIM_TRUTH of fp32 and MIN_SPEEDUP faster (`offered`)."""
    import warnings

    from rigspace.sdk.model import BundleModel
    from rigspace.train.evaluate import DatasetTable, compare
    from rigspace.train.int8check import MIN_SPEEDUP
    from rigspace.train.metrics import mask_iou
    from rigspace.train.predictor import BundlePredictor

    full = DatasetTable(dataset)
    levels: dict[int, dict[str, Any]] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fp32 in place of failed graphs: recorded below
        fp32_model = BundleModel(bundle, threads=1)
        int8_model = BundleModel(bundle, "int8", threads=1)
    for resolution in fp32_model.resolutions:
        if full.captured_resolution % resolution:
            continue
        table = DatasetTable(dataset, resolution)
        predictors = [BundlePredictor(bundle, table), BundlePredictor(bundle, table, int8=True)]
        result = compare(predictors, table, split, limit=limit)
        rows = result["indices"]
        rig = table.rig_inputs(rows)
        alpha = {}
        for key, model in (("fp32", fp32_model), ("int8", int8_model)):
            out = model.predict(rig, resolution, ("albedo",))["alpha"][:, 0]
            alpha[key] = float(
                np.mean([mask_iou(out[k], table.maps(int(i)).mask) for k, i in enumerate(rows)])
            )
        entry: dict[str, Any] = {}
        for key, row in zip(("fp32", "int8"), result["rows"], strict=True):
            entry[key] = {
                "albedo_psnr": row["albedo_psnr"],
                "mask_iou": row["mask_iou"],
                "alpha_iou": alpha[key],
                "depth_mae_pct": row["depth_mae_pct"],
                "normal_median_deg": row["normal_median_deg"],
            }
        entry["ms"] = _evaluation_ms(fp32_model, int8_model, rig, resolution)
        short = [
            f"{key} loses {entry['fp32'][key] - entry['int8'][key]:.3g}, at most {most:g}"
            for key, most in AIM_TRUTH.items()
            if entry["fp32"][key] - entry["int8"][key] > most
        ]
        if entry["ms"]["speedup"] < MIN_SPEEDUP:
            short.append(f"speedup {entry['ms']['speedup']:.2f}, needs >= {MIN_SPEEDUP:g}")
        entry.update(samples=len(rows), offered=not short, not_offered=short)
        levels[resolution] = entry
    return levels


def format_level_table(levels: dict[int, dict[str, Any]]) -> str:
    """level_table as Markdown: fp32 / int8 per map, ms and the ratio, offered or why not."""
    lines = [
        "| level | albedo PSNR (dB) | mask IoU | alpha IoU | depth % height | normal median (deg) "
        "| ms fp32 / int8 | speed ratio | int8 offered |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for resolution, e in levels.items():
        f, q = e["fp32"], e["int8"]
        lines.append(
            f"| {resolution} | {f['albedo_psnr']:.2f} / {q['albedo_psnr']:.2f} "
            f"| {f['mask_iou']:.3f} / {q['mask_iou']:.3f} | {f['alpha_iou']:.3f} / {q['alpha_iou']:.3f} "
            f"| {f['depth_mae_pct']:.2f} / {q['depth_mae_pct']:.2f} "
            f"| {f['normal_median_deg']:.2f} / {q['normal_median_deg']:.2f} "
            f"| {e['ms']['fp32']:.2f} / {e['ms']['int8']:.2f} | {e['ms']['speedup']:.2f}x "
            f"| {'yes' if e['offered'] else 'no: ' + '; '.join(e['not_offered'])} |"
        )
    return "\n".join(lines) + "\n"

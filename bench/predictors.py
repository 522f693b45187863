"""Predictors side by side: ms per character for every predictor that runs here.

    rigspace bench --only predictors --out /tmp/bench

For the sample bundle, each predictor (rigspace.sdk.predictors) at every level: all maps for
one character, and for eight in one batch (a crowd's frame), with its largest difference
from onnxruntime on the CPU (the reference: the graphs as exported). Imports no USD, so the
GPU check (rigspace.apps.gpu_check) times synthetic bundles through the same function.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.bench.timing import timed
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.model import BundleModel
from rigspace.sdk.predictors import available

BATCHES = (1, 8)
"""Characters per call: one, and a crowd of eight in one batch."""


def for_precision(predictor: str, precision: str) -> str:
    """The predictor a bench part uses for one precision: --predictor for fp32; int8 graphs
    are onnxruntime's, so "auto" (which passes over the torch predictor) for int8."""
    return predictor if precision == "fp32" else "auto"


def sample_rigs(joints: int, n: int, seed: int = 0) -> np.ndarray:
    """(n, joints * 6) rig rows: every joint near the identity rotation, seeded noise."""
    rng = np.random.default_rng(seed)
    rest = np.tile(np.array([1, 0, 0, 0, 1, 0], np.float32), (n, joints))
    return rest + rng.normal(0.0, 0.05, rest.shape).astype(np.float32)


def time_model(
    model: BundleModel, rigs: np.ndarray, levels: list[int], repeats: int
) -> list[dict[str, Any]]:
    """ms per call and per character of `model.predict` (both branches) at each level and
    batch size (BATCHES)."""
    rows = []
    for level in levels:
        for n in BATCHES:
            ms = timed(partial(model.predict, rigs[:n], level), repeats)
            rows.append(
                {
                    "runs_on": model.runner.description,
                    "level": level,
                    "batch": n,
                    "ms": ms,
                    "ms_per_character": ms["median_ms"] / n,
                }
            )
    return rows


def measure(
    bundle: str | Path, repeats: int, levels: tuple[int, ...] | None = None, device: str = "auto"
) -> list[dict[str, Any]]:
    """One row per (predictor, level, batch); a predictor that cannot run says why."""
    reference = BundleModel(bundle, predictor="onnxruntime")
    rigs = sample_rigs(len(reference.joints), max(BATCHES))
    chosen = [r for r in reference.resolutions if levels is None or r in levels]
    rows: list[dict[str, Any]] = []
    for name in available():
        try:
            model = BundleModel(bundle, predictor=name, device=device)
        except RigspaceError as exc:
            rows.append({"predictor": name, "skipped": exc.what})
            continue
        for row in time_model(model, rigs, chosen, repeats):
            ours = model.predict(rigs[: row["batch"]], row["level"])
            truth = reference.predict(rigs[: row["batch"]], row["level"])
            row["max_abs_vs_onnxruntime"] = max(
                float(np.abs(ours[k] - truth[k]).max()) for k in truth
            )
            rows.append({"predictor": name, **row})
    return rows


def table(rows: list[dict[str, Any]]) -> list[str]:
    """The bench README's section."""
    lines = [
        "## Predictors",
        "",
        "All maps of the sample model per call (trunk, albedo and geometry branches): one "
        "character, and eight in one batch. Max |diff|: the largest difference of any output "
        "from onnxruntime on the CPU.",
        "",
        "| predictor | runs on | level | characters | ms (min-max) | ms per character | max abs diff |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if "skipped" in row:
            lines.append(f"| {row['predictor']} | skipped: {row['skipped']} ||||||")
            continue
        ms = row["ms"]
        lines.append(
            f"| {row['predictor']} | {row['runs_on']} | {row['level']} | {row['batch']} | "
            f"{ms['median_ms']:.2f} ({ms['min_ms']:.2f}-{ms['max_ms']:.2f}) | "
            f"{row['ms_per_character']:.2f} | {row['max_abs_vs_onnxruntime']:.1e} |"
        )
    return lines

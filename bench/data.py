"""How fast training items are made: from the EXRs against from the decoded cache.

    rigspace bench --only data --dataset /tmp/sample_ds

One thread (one core), the same random samples of the train split: a sample's maps read
from its EXR against from the dataset's decoded cache (capture.cache; built first if
stale), and whole training items (SampleSet.item: the maps, relative depth, targets at the
dataset's resolution, joints2d and the texture head's targets) both ways. The two ways run
in alternating blocks, so a busy machine slows both alike; medians of the blocks.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

BLOCKS = 8
"""Alternating blocks per way (EXR, cache, EXR, ...)."""


def per_second(work, ks: np.ndarray) -> float:
    start = time.perf_counter()
    for k in ks:
        work(int(k))
    return len(ks) / (time.perf_counter() - start)


def alternating(ways: dict[str, Callable[[int], Any]], ks: np.ndarray) -> dict[str, float]:
    """Median rate of each way over BLOCKS alternating blocks of `ks`."""
    rates: dict[str, list[float]] = {name: [] for name in ways}
    for block in np.array_split(ks, BLOCKS):
        for name, work in ways.items():
            rates[name].append(per_second(work, block))
    return {name: float(np.median(r)) for name, r in rates.items()}


def measure(dataset: Path | None, count: int = 400) -> dict[str, Any]:
    if dataset is None:
        return {"skipped": "needs --dataset (a capture of the sample scene)"}
    from rigspace.capture.dataset import read_manifest, read_sample
    from rigspace.train.conditioning import dataset_skeleton
    from rigspace.train.data import SampleSet, chart_boxes, ensure_cache

    manifest = read_manifest(dataset)
    built = ensure_cache(dataset, manifest, progress=False)
    samples = SampleSet(dataset, "train")
    samples.skeleton = dataset_skeleton(dataset, manifest)
    samples.charts = chart_boxes(dataset)
    ks = np.random.default_rng(0).choice(len(samples), min(count, len(samples)), replace=False)
    cache = samples.cache
    if cache is None:
        return {"skipped": f"no decoded cache ({built})"}

    def exr_maps(k: int) -> None:
        read_sample(dataset, manifest, str(samples.paths[samples.rows[k]]))

    def exr_item(k: int) -> None:
        samples.cache = None
        samples.item(k)
        samples.cache = cache

    rates = alternating(
        {
            "exr_maps": exr_maps,
            "cache_maps": lambda k: cache.maps(int(samples.rows[k])),
            "exr_items": exr_item,
            "cache_items": samples.item,
        },
        ks,
    )
    return {
        "dataset": str(dataset),
        "resolution": samples.resolution,
        "samples": len(ks),
        "cache": built,
        **{f"{name}_per_s": rate for name, rate in rates.items()},
        **batches(samples),
    }


def batches(samples: Any, kept: int = 2048, batch: int = 256, repeats: int = 3) -> dict[str, Any]:
    """A step's batch as the prefetcher makes it (decoded from the cache) against gathered
    from items kept in memory (train.resident, on the CPU here: on a GPU the gather is a
    copy in its memory), over the first `kept` train samples; and how fast they were kept."""
    try:
        import torch

        from rigspace.train.data import Prefetcher
        from rigspace.train.resident import ResidentBatches
    except ImportError:
        return {"batches": {"skipped": "needs torch (the train extra)"}}
    samples = copy.copy(samples)  # the caller's split keeps its rows
    samples.rows = samples.rows[:kept]
    start = time.perf_counter()
    resident = ResidentBatches(samples, batch, seed=0, device=torch.device("cpu"),
                               channels_last=True, progress=False)  # fmt: skip
    decoding = time.perf_counter() - start
    plain = Prefetcher(samples, batch, seed=0)
    ms: dict[str, list[float]] = {"decoded": [], "gathered": []}
    for step in range(repeats):  # alternating, as above
        for name, get in (("decoded", lambda s: samples.batch(plain.indices(s))),
                          ("gathered", resident.get)):  # fmt: skip
            began = time.perf_counter()
            get(step)
            ms[name].append(1e3 * (time.perf_counter() - began))
    plain.close()
    resident.close()
    return {
        "batches": {
            "batch": batch,
            "kept": len(samples),
            "kept_seconds": decoding,
            "mib_per_item": resident.bytes / len(samples) / 2**20,
            **{f"{name}_ms": float(np.median(v)) for name, v in ms.items()},
        }
    }


def table(r: dict[str, Any]) -> list[str]:
    lines = ["## Training data", ""]
    if "skipped" in r:
        return [*lines, f"skipped: {r['skipped']}"]
    return [
        *lines,
        f"Per second on one core, {r['samples']} random train samples at "
        f"{r['resolution']}x{r['resolution']} ({r['cache']}); a training item adds relative "
        "depth, joints2d and the texture head's targets to the maps:",
        "",
        "| read from | sample maps/s | training items/s |",
        "|---|---|---|",
        f"| the EXRs | {r['exr_maps_per_s']:.0f} | {r['exr_items_per_s']:.0f} |",
        f"| the decoded cache | {r['cache_maps_per_s']:.0f} | {r['cache_items_per_s']:.0f} |",
        "",
        *_batch_lines(r.get("batches")),
    ]


def _batch_lines(b: dict[str, Any] | None) -> list[str]:
    if not b:
        return []
    if "skipped" in b:
        return [f"A step's batch: skipped: {b['skipped']}."]
    return [
        f"A step's batch of {b['batch']}: decoded by the prefetcher {b['decoded_ms']:.0f} ms; "
        f"gathered from the items kept in memory (`rigspace train --resident`) "
        f"{b['gathered_ms']:.0f} ms, after {b['kept']} items ({b['mib_per_item']:.2f} MiB "
        f"each) were kept in {b['kept_seconds']:.1f} s by every core."
    ]

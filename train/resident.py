"""A split's training items decoded once and kept in the memory of the device that trains.

    rigspace train DATASET --out MODEL --resident auto|on|off

A step's batch is then an index gather on the device: no decoding, no host-to-device copy
per step. On a GPU that is what keeps it fed: a 128x128 item of the sample recipe is 11
float32 maps plus its rig (about 0.75 MB), so the sample dataset's 33,120 training items
take 24 GiB, decoded once by every core (the dataset's cache makes that a read), and one
batch of 256 is a gather of 190 MB on the GPU instead of 256 items decoded on the CPU and
copied over. `auto` keeps the items on a CUDA device when they fit in half of its free
memory (else it says so and reads batches as before); on the CPU the dataset's memory-mapped
cache already serves them from RAM, so `auto` leaves them there. `on` forces it (the tests,
a CPU run that fits). Batches are exactly the prefetcher's: the same indices per step
(Prefetcher.indices), the same values, so a run trains identically either way (tested).
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from rigspace.train.data import Prefetcher, SampleSet

RESIDENT_MODES = ("auto", "on", "off")
FREE_FRACTION = 0.5
"""`auto` keeps the items on a GPU when they take at most this share of its free memory
(the rest is for the network, its activations and the optimiser)."""
CHUNK = 64
"""Items decoded per task of the decoding pool."""

_decoding: SampleSet | None = None
"""The split the forked decoding workers read (set before the pool forks)."""


def item_bytes(samples: SampleSet) -> int:
    """The bytes one training item of `samples` takes (every item has the same shapes)."""
    return sum(v.nbytes for v in samples.item(0).values())


def _decode(ks: np.ndarray) -> tuple[int, dict[str, np.ndarray]]:
    assert _decoding is not None
    return int(ks[0]), _decoding.batch(ks)


def decode_all(
    samples: SampleSet, device: torch.device, workers: int | None = None, progress: bool = True
) -> dict[str, torch.Tensor]:
    """Every item of the split, stacked per key into one tensor on `device`, decoded by
    `workers` forked processes (default: every core; 1: in this process)."""
    global _decoding
    n = len(samples)
    first = samples.item(0)
    out = {
        k: torch.empty((n, *v.shape), dtype=torch.from_numpy(v).dtype, device=device)
        for k, v in first.items()
    }
    chunks = [c for c in np.array_split(np.arange(n), max(1, -(-n // CHUNK))) if len(c)]
    workers = workers or len(os.sched_getaffinity(0))
    bar = tqdm(total=n, unit="item", desc="rigspace train: items into memory",
               disable=not progress, file=sys.stderr, dynamic_ncols=True)  # fmt: skip
    _decoding = samples  # read by _decode here, or inherited by the forked workers (no pickle)
    try:
        with bar:
            if workers <= 1:
                _fill(out, map(_decode, chunks), bar)
            else:
                context = multiprocessing.get_context("fork")
                with ProcessPoolExecutor(workers, mp_context=context) as pool:
                    _fill(out, pool.map(_decode, chunks), bar)
    finally:
        _decoding = None
    return out


def _fill(out: dict[str, torch.Tensor], results, bar) -> None:
    for start, batch in results:
        count = len(next(iter(batch.values())))
        for k, v in batch.items():
            out[k][start : start + count].copy_(torch.from_numpy(v))
        bar.update(count)


class ResidentBatches(Prefetcher):
    """The prefetcher's batches (same indices per step) gathered from items decoded once
    into `device` memory; `get` returns tensors on the device, in channels_last when asked."""

    def __init__(
        self,
        samples: SampleSet,
        batch: int,
        seed: int,
        rank: int = 0,
        world: int = 1,
        oversample: float = 0.0,
        *,
        device: torch.device,
        channels_last: bool = False,
        workers: int | None = None,
        progress: bool = True,
    ) -> None:
        super().__init__(samples, batch, seed, rank, world, oversample)
        self.device, self.channels_last = device, channels_last
        self.items = decode_all(samples, device, workers, progress)
        self.bytes = sum(t.numel() * t.element_size() for t in self.items.values())

    def get(self, step: int) -> dict[str, torch.Tensor]:
        index = torch.from_numpy(self.indices(step)).to(self.device)
        batch = {k: v.index_select(0, index) for k, v in self.items.items()}
        if self.channels_last:
            batch = {
                k: v.contiguous(memory_format=torch.channels_last) if v.ndim == 4 else v
                for k, v in batch.items()
            }
        return batch


def resident_or_not(samples: Any, device: torch.device, mode: str) -> tuple[bool, str | None]:
    """Whether to keep `samples`' items in `device` memory under `mode` (RESIDENT_MODES),
    and the line that says why not where the user would expect it (None: nothing to say)."""
    if mode not in RESIDENT_MODES:
        raise ValueError(f"resident {mode!r} is not one of {RESIDENT_MODES}")
    if mode == "off" or not isinstance(samples, SampleSet):
        return False, None  # shards are a stream by design: read in bounded memory
    if mode == "on":
        return True, None
    if device.type != "cuda":
        return False, None  # the memory-mapped cache serves them from RAM already
    need = len(samples) * item_bytes(samples)
    free, _ = torch.cuda.mem_get_info(device)
    if need > FREE_FRACTION * free:
        return False, (
            f"the {len(samples)} training items take {need / 2**30:.1f} GiB, more than half of "
            f"{device}'s free {free / 2**30:.1f} GiB: batches are decoded per step instead"
        )
    return True, None

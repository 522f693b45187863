"""Timing the bench's way: warm-up calls first, then repeated calls, each one timed."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any


def repeat(fn: Callable[[], Any], repeats: int, warmup: int = 2) -> list[float]:
    """Seconds of each of `repeats` calls of `fn`, after `warmup` untimed calls."""
    for _ in range(warmup):
        fn()
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        seconds.append(time.perf_counter() - start)
    return seconds


def summary(ms: list[float]) -> dict[str, float]:
    """Median, min and max of milliseconds."""
    return {"median_ms": statistics.median(ms), "min_ms": min(ms), "max_ms": max(ms)}


def timed(fn: Callable[[], Any], repeats: int, warmup: int = 2) -> dict[str, float]:
    """Median, min and max milliseconds of `fn` (see `repeat`)."""
    return summary([1e3 * s for s in repeat(fn, repeats, warmup)])

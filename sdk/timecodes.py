"""Stage time codes compared with one documented tolerance (exporters leave float drift on samples).

A real exporter wrote a 3,023-frame animation's samples at 1.0000000521, 2.0000001043,
..., 3023.0001577 (each frame off by 5.2e-8 of its value, float32 rounding); comparing
those with `<` refuses `--frames 1:120`, and posing at 2.0 instead of 2.0000001043 reads
an interpolated (or, with held interpolation, the previous) pose. Every comparison of
time codes goes through `same_time`, every requested time is snapped to the authored
samples with `snap`, every requested range is fitted to the animated one with
`clamp_range`, and a time code written for people (init's scene range) is made `whole`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

TOLERANCE = 1e-6
"""Relative tolerance of two time codes: equal when |a - b| <= TOLERANCE * max(1, |a|, |b|).

float32 keeps 24 bits, so a time code that went through float32 is off by up to 6e-8 of
its value (half an ulp), and the drift seen on real assets is 5.2e-8; 1e-6 (about 8
float32 ulps) covers that with room for accumulated rounding, yet stays far below a
frame: 0.003 of a frame at time code 3,000 and 0.1 at 100,000 (an hour at 30 fps). Below
magnitude 1 it acts as an absolute 1e-6."""


def tolerance(t: ArrayLike) -> np.ndarray:
    """The largest difference still counted as the same time code, at `t`."""
    return TOLERANCE * np.maximum(1.0, np.abs(np.asarray(t, dtype=np.float64)))


def same_time(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Whether time codes `a` and `b` are the same within TOLERANCE (elementwise)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.abs(a - b) <= TOLERANCE * np.maximum(1.0, np.maximum(np.abs(a), np.abs(b)))


def snap(times: ArrayLike, samples: ArrayLike) -> np.ndarray:
    """`times` with each value replaced by the nearest authored sample within TOLERANCE.

    Times between samples (sub-frame steps, sparse animations) are returned unchanged.
    """
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    s = np.unique(np.asarray(samples, dtype=np.float64))
    if s.size == 0:
        return t.copy()
    right = np.clip(np.searchsorted(s, t), 0, s.size - 1)
    left = np.clip(right - 1, 0, s.size - 1)
    nearest = np.where(np.abs(s[left] - t) <= np.abs(s[right] - t), s[left], s[right])
    return np.where(same_time(t, nearest), nearest, t)


def whole(t: float) -> float:
    """`t` as the nearest whole number when within TOLERANCE of it (an exporter's drift:
    1.0000000521 is frame 1), else unchanged: what a time code written for people reads as."""
    nearest = float(round(t)) if np.isfinite(t) else t
    return nearest if bool(same_time(t, nearest)) else float(t)


def clamp_range(first: float, last: float, lo: float, hi: float) -> tuple[float, float] | None:
    """The part of [first, last] inside the animated range [lo, hi], or None if none is.

    An end within TOLERANCE of either end of the range becomes that end exactly (it is the same
    frame); an end beyond it is clamped (the caller says so, comparing with `same_time`).
    A NaN or infinite end is a caller's error (ValueError): check user input first.
    """
    if not np.all(np.isfinite([first, last, lo, hi])):
        raise ValueError(f"clamp_range needs finite time codes, got {first}, {last}, {lo}, {hi}")
    first, last = (float(snap(end, (lo, hi))[0]) for end in (first, last))
    first, last = max(first, lo), min(last, hi)
    if first > last and not same_time(first, last):
        return None
    return float(first), float(max(first, last))

"""A rig's named float controls (RigspaceControlAPI): rig parameters after the blend shape weights.

A production rig that no game engine runs is delivered as point caches with the animators'
controls beside them (docs/point_caches.md): each control is a name, a range and a value per
time code. The rig vector the network reads is the joints' rotations, then the blend shape
weights, then the controls, in the order the character applies them; the dataset manifest
and the bundle manifest list them as `controls: [{"name": ..., "range": [low, high]}]`.
This module needs no pxr: the bundle reader and the runtime's live code use it too.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

DEFAULT_RANGE = (0.0, 1.0)
"""The schema's fallback range (RigspaceControlAPI `range`)."""
STILL_VALUE = 1e-6
"""A control whose value varies less than this (peak to peak) over the cached frames never
moves: the network cannot learn what it does (validation warns, inspect says so)."""


@dataclass(frozen=True)
class Control:
    """One named float control: its name (the API instance's) and its inclusive range."""

    name: str
    range: tuple[float, ...]
    """(low, high), in the control's own units (the schema's fallback: DEFAULT_RANGE)."""

    @property
    def low(self) -> float:
        return float(self.range[0])

    @property
    def high(self) -> float:
        return float(self.range[1])

    def problem(self) -> str:
        """Why its range is unusable ("" when it is finite with low < high)."""
        if len(self.range) != 2 or not all(math.isfinite(float(v)) for v in self.range):
            return f"its range {list(self.range)} is not two finite numbers"
        if not self.low < self.high:
            return f"its range ({self.low:g}, {self.high:g}) does not have low < high"
        return ""

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "range": [float(v) for v in self.range]}


def controls_json(controls: Iterable[Control]) -> list[dict[str, Any]] | None:
    """The manifests' `controls` list, None for a rig without controls (the key is left out,
    so a manifest of such a rig is the one it always was)."""
    out = [c.to_json() for c in controls]
    return out or None


def controls_from_json(entries: Any) -> tuple[Control, ...]:
    """A manifest's `controls` (already checked against its spec: each a name and a range)."""
    return tuple(
        Control(str(e["name"]), tuple(float(v) for v in e["range"])) for e in entries or ()
    )


def ranges(controls: Sequence[Control]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) per control, float32 arrays (what live values are clamped into)."""
    low = np.array([c.low for c in controls], dtype=np.float32)
    high = np.array([c.high for c in controls], dtype=np.float32)
    return low, high

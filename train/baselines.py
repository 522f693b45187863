"""The paper's baselines from the captured views: the nearest view, and two views interpolated."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from rigspace.capture.ring import TRAIN
from rigspace.sdk.exr import FORMATS
from rigspace.sdk.render import Maps
from rigspace.train.evaluate import DatasetError, DatasetTable

NEAREST = "nearest"
LINEAR = "linear"
KINDS = (NEAREST, LINEAR)

ANGLE_DECIMALS = 9
"""Angles (radians) are rounded to 1e-9 before ranking: a held-out view halfway between two
training views is equally far from both up to float noise, and rounding lets such ties break
on the lower row index on every machine instead of on the last bit of a matrix product."""
TIME_DECIMALS = 6
"""Time codes equal to 1e-6 are the same frame (float rounding of clip ranges)."""


def view_directions(camera_to_world: np.ndarray) -> np.ndarray:
    """(N,3) unit vectors from the look-at point towards each camera: its +Z axis.

    Ring cameras look at the joint down their -Z, so +Z is the viewing direction reversed;
    the angle between two of them is the angle between the two views.
    """
    back = np.asarray(camera_to_world, dtype=np.float64)[..., :3, 2]
    return back / np.linalg.norm(back, axis=-1, keepdims=True)


def angles_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in radians between unit vectors a (3,) and b (N,3), exact near 0 (atan2)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), b @ a)


def rotate_normals(
    normals: np.ndarray, source_to_world: np.ndarray, target_to_world: np.ndarray
) -> np.ndarray:
    """Camera-space normals of the source camera expressed in the target camera's frame.

    n_target = R_target^T R_source n_source, with R the rotation blocks of the cameras'
    camera_to_world (column-vector convention). Zero normals ("empty") stay zero.
    """
    r_source = np.asarray(source_to_world, dtype=np.float64)[:3, :3]
    r_target = np.asarray(target_to_world, dtype=np.float64)[:3, :3]
    rotation = r_target.T @ r_source
    # Row vectors n (..., 3): (R n)^T = n^T R^T.
    return (np.asarray(normals, dtype=np.float64) @ rotation.T).astype(np.float32)


def blend(maps: list[Maps], weights: np.ndarray) -> Maps:
    """A weighted blend of maps already in the target camera's frame (weights sum to 1).

    Albedo and mask blend linearly. Depth blends over the maps where it is finite, with the
    weights renormalised over those maps (one finite depth is taken as is), +inf where none
    is. Normals blend and are renormalised; where they cancel or all are empty, zero.
    """
    w = np.asarray(weights, dtype=np.float64)
    albedo = sum(wi * m.albedo.astype(np.float64) for wi, m in zip(w, maps, strict=True))
    mask = sum(wi * m.mask.astype(np.float64) for wi, m in zip(w, maps, strict=True))
    depths = np.stack([m.depth for m in maps]).astype(np.float64)
    finite = np.isfinite(depths)
    dw = np.where(finite, w[:, None, None], 0.0)
    total = dw.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(
            total > 0, (dw * np.where(finite, depths, 0.0)).sum(axis=0) / total, np.inf
        )
    normal = sum(wi * m.normal.astype(np.float64) for wi, m in zip(w, maps, strict=True))
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    return Maps(
        np.asarray(albedo, np.float32),
        normal.astype(np.float32),
        depth.astype(np.float32),
        np.asarray(mask, np.float32),
    )


def bytes_per_pixel() -> int:
    """Bytes one pixel of a sample takes at its stored precision (sdk/exr.py FORMATS)."""
    return int(sum(oiio.TypeDesc(f).size() for f in FORMATS))


class BaselinePredictor:
    """A baseline that predicts a sample from the training views of the same frame.

    kind "nearest": the training sample of the same clip and time code whose camera
    direction is closest in angle, its maps used as they are. The ring's cameras all look
    at the same joint from the same distance (the billboard assumption), so images of
    neighbouring views are directly comparable; nothing is warped.

    kind "linear": the two closest training views of the frame, blended (`blend`) with
    weights inversely proportional to their angular distance (w_i = (1/d_i) / sum 1/d_j;
    an exact match gets all the weight). Each neighbour's normals are first rotated into
    the predicted camera's frame (rotate_normals), since camera-space normals of different
    cameras do not compare. The paper's "linear interpolation of the captured views".

    Only the training split is used as the captured views, so a held-out clip (a frame
    never captured from the training views) has nothing to predict from: DatasetError.
    `footprint_bytes` is what a baseline must keep to predict anything: every training
    sample's maps at stored precision, uncompressed (`footprint()` also gives the EXR bytes
    on disk, compressed).
    """

    def __init__(self, dataset: str | Path | DatasetTable, kind: str = NEAREST) -> None:
        if kind not in KINDS:
            raise DatasetError(f"Unknown baseline {kind!r}.", f"choose one of {', '.join(KINDS)}.")
        self.table = dataset if isinstance(dataset, DatasetTable) else DatasetTable(dataset)
        self.kind = kind
        self.name = kind
        self.train = self.table.indices(TRAIN)
        self.camera_to_world = self.table.column("camera_to_world")
        self.directions = view_directions(self.camera_to_world)
        frames: dict[tuple[int, float], list[int]] = {}
        for row in self.train:
            frames.setdefault(self._frame(int(row)), []).append(int(row))
        self.frames = {key: np.array(rows) for key, rows in frames.items()}

    def _frame(self, index: int) -> tuple[int, float]:
        return (
            int(self.table.column("clip")[index]),
            round(float(self.table.column("time")[index]), TIME_DECIMALS),
        )

    def neighbours(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(training rows, their angles in degrees, weights) this baseline uses for `index`."""
        candidates = self.frames.get(self._frame(index))
        if candidates is None:
            raise DatasetError(
                f"Sample {self.table.column('path')[index]} has no training view of its frame "
                f"in {self.table.folder} (a held-out clip is never captured from training views).",
                f"evaluate the {self.kind} baseline on the heldout-views split.",
            )
        # A training sample is not its own neighbour (on the train split the nearest view of
        # its frame would be itself: a baseline at inf dB, measuring nothing).
        candidates = candidates[candidates != index]
        if len(candidates) == 0:
            raise DatasetError(
                f"Sample {self.table.column('path')[index]} is the only training view of its "
                f"frame in {self.table.folder}: the {self.kind} baseline has nothing else to use.",
                "capture more views per ring, or evaluate with --no-baselines.",
            )
        angles = np.round(
            angles_between(self.directions[index], self.directions[candidates]), ANGLE_DECIMALS
        )
        order = np.lexsort((candidates, angles))  # by angle, ties by row index
        count = 1 if self.kind == NEAREST else min(2, len(candidates))
        rows, d = candidates[order[:count]], angles[order[:count]]
        if d[0] == 0.0 or count == 1:
            weights = np.eye(count)[0]
        else:
            inverse = 1.0 / d
            weights = inverse / inverse.sum()
        return rows, np.degrees(d), weights

    def predict_one(self, index: int) -> Maps:
        rows, _, weights = self.neighbours(index)
        if self.kind == NEAREST:
            return self.table.maps(int(rows[0]))
        maps = []
        for row in rows:
            m = self.table.maps(int(row))
            m.normal = rotate_normals(
                m.normal, self.camera_to_world[row], self.camera_to_world[index]
            )
            maps.append(m)
        return blend(maps, weights)

    def predict(self, indices: np.ndarray) -> list[Maps]:
        return [self.predict_one(int(i)) for i in np.asarray(indices).reshape(-1)]

    def footprint(self) -> dict[str, int]:
        """Training samples kept, their bytes at stored precision, and their EXR bytes on disk."""
        return {
            "samples": len(self.train),
            "bytes": self.footprint_bytes,
            "disk_bytes": int(sum(self.table.path(int(i)).stat().st_size for i in self.train)),
        }

    @property
    def footprint_bytes(self) -> int:
        """Every training sample's maps at stored precision, uncompressed."""
        return len(self.train) * self.table.resolution**2 * bytes_per_pixel()

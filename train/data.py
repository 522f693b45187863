"""Read a capture dataset for training: rig parameters in, target maps out, streamed from disk.

Samples are read from their EXRs when needed (a background thread reads the next batch
while the current one trains), so a dataset of any size trains in bounded memory.
Targets: premultiplied albedo, mask, camera-space normals, and depth relative to the
look-at joint in units of the dataset's `depth_scale` (below), 0 where empty.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from rigspace.capture.dataset import DatasetError, read_manifest
from rigspace.sdk.conditioning import Skeleton2D, joints2d
from rigspace.sdk.exr import read_exr
from rigspace.sdk.render import Maps

SPLITS = ("train", "heldout-views", "heldout-clips")


def depth_scale(manifest: dict[str, Any]) -> float:
    """Depth unit for training: half the visible extent at the joint's distance, scene units.

    S = radius * tan(half field of view) = radius * (aperture / 2) / focal length. Relative
    depth (depth - joint depth) / S is then about [-1, 1] across the character whatever
    the scene's units, as the paper's 1/s depth scaling at run time expects.
    """
    ring = manifest["ring"]
    return float(ring["radius"] * (ring["horizontal_aperture"] / 2.0) / ring["focal_length"])


def read_sample(folder: Path, manifest: dict[str, Any], relative: str) -> Maps:
    """A dataset sample's maps; a missing or damaged EXR is a DatasetError naming the file
    and the capture command that re-renders it (training and evaluation read through here)."""
    path = folder / relative
    try:
        return read_exr(path)
    except OSError as exc:  # sdk.exr.ExrError is an OSError, as is a file that went away
        state = "missing" if not path.is_file() else "damaged"
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        scene = manifest.get("scene", "SCENE")
        raise DatasetError(
            f"Sample {path} of the dataset is {state} ({reason}).",
            f"re-render it: repeat the capture with --resume (`rigspace capture {scene} --out "
            f"{folder} --resume`, with the original capture's other flags), which re-renders "
            "missing and damaged samples.",
        ) from exc


def area_downsample(x: np.ndarray, factor: int) -> np.ndarray:
    """(..., H, W) -> (..., H/f, W/f) by box averaging."""
    if factor == 1:
        return x
    *lead, h, w = x.shape
    return x.reshape(*lead, h // factor, factor, w // factor, factor).mean(axis=(-3, -1))


def targets_at(
    albedo: np.ndarray, mask: np.ndarray, normal: np.ndarray, depth: np.ndarray, factor: int
) -> tuple[np.ndarray, ...]:
    """Channel-first targets box-downsampled by `factor`.

    Albedo (premultiplied) and mask average over the box; depth and normals average over
    the covered part of the box only (mask-weighted), so empty pixels never leak in.
    """
    if factor == 1:
        return albedo, mask, normal, depth
    m = area_downsample(mask, factor)
    weight = np.maximum(m, 1e-6)
    depth_d = area_downsample(depth * mask, factor) / weight
    normal_d = area_downsample(normal * mask, factor) / weight
    length = np.linalg.norm(normal_d, axis=0, keepdims=True)
    normal_d = np.where(length > 0, normal_d / np.maximum(length, 1e-6), 0.0)
    return (
        area_downsample(albedo, factor),
        m,
        normal_d.astype(np.float32),
        depth_d.astype(np.float32),
    )


ITEM_COLUMNS = ["rig", "joint_camera"]
"""The params.npz columns a training item is made from (a shard sample's .npz holds them all)."""


class SplitInfo:
    """What turning one sample's files into a training item needs of its dataset split.

    SampleSet (a dataset folder) and train.stream (tar shards) both make their items with
    `make_item`, so the two readers yield exactly the same keys and values.
    """

    def __init__(self, manifest: dict[str, Any], split: str, resolution: int | None) -> None:
        if split not in SPLITS:
            raise DatasetError(f"Unknown split {split!r}.", f"use one of {', '.join(SPLITS)}.")
        self.manifest = manifest
        self.split = split
        self.dataset_resolution = int(self.manifest["resolution"])
        self.resolution = resolution or self.dataset_resolution
        if self.resolution > self.dataset_resolution or self.dataset_resolution % self.resolution:
            raise DatasetError(
                f"Training resolution {self.resolution} does not divide the dataset's "
                f"{self.dataset_resolution}.",
                f"use --resolution {self.dataset_resolution} or a power of two below it.",
            )
        self.depth_scale = depth_scale(self.manifest)
        self.joints = list(self.manifest["joints"])
        self.skeleton: Skeleton2D | None = None
        """Set (train.conditioning.dataset_skeleton) to add each item's `joints2d`."""

    def make_item(self, maps: Maps, row: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """A sample's item from its maps and its params row (ITEM_COLUMNS): rig (J*6,),
        albedo (3,R,R), mask (1,R,R), normal (3,R,R), depth (1,R,R)."""
        joint_depth = -np.float32(row["joint_camera"][2])
        mask = maps.mask[None]
        hit = mask > 0
        depth = np.where(hit, (maps.depth[None] - joint_depth) / self.depth_scale, 0.0)
        albedo, mask, normal, depth = targets_at(
            np.moveaxis(maps.albedo, -1, 0),
            mask,
            np.moveaxis(maps.normal, -1, 0),
            depth.astype(np.float32),
            self.dataset_resolution // self.resolution,
        )
        item = {
            "rig": np.asarray(row["rig"]).reshape(-1).astype(np.float32),
            "albedo": albedo.astype(np.float32),
            "mask": mask.astype(np.float32),
            "normal": normal.astype(np.float32),
            "depth": depth.astype(np.float32),
        }
        if self.skeleton is not None:  # pose conditioning: the runtime's function, same input
            item["joints2d"] = joints2d(item["rig"][None], self.skeleton)[0]
        return item

    def batch_of(self, items: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        return {key: np.stack([it[key] for it in items]) for key in items[0]}


class SampleSet(SplitInfo):
    """One split of a dataset folder at a training resolution."""

    def __init__(self, folder: str | Path, split: str, resolution: int | None = None) -> None:
        self.folder = Path(folder)
        if split not in SPLITS:
            raise DatasetError(f"Unknown split {split!r}.", f"use one of {', '.join(SPLITS)}.")
        manifest = read_manifest(self.folder)
        with np.load(self.folder / "params.npz", allow_pickle=False) as table:
            self.rows = np.flatnonzero(table["split"] == SPLITS.index(split))
            self.rig = table["rig"].reshape(len(table["rig"]), -1).astype(np.float32)
            self.paths = table["path"]
            self.joint_depth = -table["joint_camera"][:, 2].astype(np.float32)
            self.columns = {c: table[c] for c in ITEM_COLUMNS}
        super().__init__(manifest, split, resolution)

    def __len__(self) -> int:
        return len(self.rows)

    def item(self, k: int) -> dict[str, np.ndarray]:
        """Sample k of the split (SplitInfo.make_item)."""
        row = int(self.rows[k])
        maps = read_sample(self.folder, self.manifest, str(self.paths[row]))
        return self.make_item(maps, {c: v[row] for c, v in self.columns.items()})

    def batch(self, ks: np.ndarray) -> dict[str, np.ndarray]:
        return self.batch_of([self.item(int(k)) for k in ks])


def batch_indices(n: int, batch: int, step: int, seed: int) -> np.ndarray:
    """The sample indices of a step: epochs of seeded permutations, a pure function of step.

    Resuming at step s therefore continues exactly where an uninterrupted run would be.
    """
    start = step * batch
    out = np.empty(batch, dtype=np.int64)
    filled = 0
    while filled < batch:
        epoch, offset = divmod(start + filled, n)
        perm = np.random.default_rng([seed, epoch]).permutation(n)
        take = min(batch - filled, n - offset)
        out[filled : filled + take] = perm[offset : offset + take]
        filled += take
    return out


class Prefetcher:
    """Reads the batch of step s + 1 on a background thread while step s trains."""

    def __init__(
        self, samples: SampleSet, batch: int, seed: int, rank: int = 0, world: int = 1
    ) -> None:
        self.samples, self.batch, self.seed = samples, batch, seed
        # Under torch.distributed `batch` is the global batch and each rank reads its slice:
        # the global batch of a step is the same whatever the world size (exact resume).
        self.rank, self.world = rank, world
        self._pool = ThreadPoolExecutor(max_workers=1)
        self._pending: dict[int, Future] = {}

    def _submit(self, step: int) -> None:
        if step not in self._pending:
            ks = batch_indices(len(self.samples), self.batch, step, self.seed)
            ks = np.array_split(ks, self.world)[self.rank]
            self._pending[step] = self._pool.submit(self.samples.batch, ks)

    def get(self, step: int) -> dict[str, np.ndarray]:
        for other in [s for s in self._pending if s != step]:  # a skipped step's read
            self._pending.pop(other).cancel()
        self._submit(step)
        result = self._pending.pop(step).result()
        self._submit(step + 1)
        return result

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

"""Read a capture dataset for training: rig parameters in, target maps out, streamed from disk.

Samples are read from their EXRs when needed (a background thread reads the next batch
while the current one trains), so a dataset of any size trains in bounded memory.
Targets: premultiplied albedo, mask, camera-space normals, and depth relative to the
look-at joint in units of the dataset's `depth_scale` (below), 0 where empty. Batches are
drawn uniformly (the paper) or, with --oversample, rare poses more often (`pose_rarity`).
"""

from __future__ import annotations

import sys
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from rigspace.capture.cache import FOLDER as CACHE_FOLDER
from rigspace.capture.cache import build_cache, open_cache, stale_reason
from rigspace.capture.dataset import (
    DatasetError,
    DatasetManifest,
    read_charts,
    read_manifest,
    read_sample,
)
from rigspace.capture.ring import stage_axes
from rigspace.sdk.conditioning import Skeleton2D, joints2d
from rigspace.sdk.render import Maps
from rigspace.sdk.rotations import matrix_from_rot6d, rig_inputs, rot6d_from_matrix
from rigspace.train.config import check_oversample

if TYPE_CHECKING:
    from rigspace.train.regions import ShapeMobility

SPLITS = ("train", "heldout-views", "heldout-clips")


def depth_scale(manifest: DatasetManifest) -> float:
    """Depth unit for training: half the visible extent at the joint's distance, scene units.

    S = radius * tan(half field of view) = radius * (aperture / 2) / focal length. Relative
    depth (depth - joint depth) / S is then about [-1, 1] across the character whatever
    the scene's units, as the paper's 1/s depth scaling at run time expects.
    """
    ring = manifest.ring
    return float(ring.radius * (ring.horizontal_aperture / 2.0) / ring.focal_length)


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


def chart_boxes(folder: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(K+1, 2) centres and half sizes of a dataset's texture charts' uv boxes (row 0, no
    chart: centre 0, half 1), from its charts.json; None when it has no texture charts."""
    table = read_charts(folder)
    if table is None or not table.get("charts"):
        return None
    charts = table["charts"]
    center = np.zeros((len(charts) + 1, 2), np.float32)
    half = np.ones((len(charts) + 1, 2), np.float32)
    for chart in charts:
        lo, hi = np.asarray(chart["uv_min"], np.float64), np.asarray(chart["uv_max"], np.float64)
        center[int(chart["index"])] = (lo + hi) / 2
        half[int(chart["index"])] = np.maximum((hi - lo) / 2, 1e-6)
    return center, half


def texels_per_coordinate(folder: str | Path, manifest: DatasetManifest) -> np.ndarray | None:
    """(K+1, 2) texels of each chart's texture per unit of the texture head's coordinates
    ([-1, 1] over the chart's uv box): how far a coordinate error lands on the texture. From
    the textures of the dataset's character (its scene opened read-only); nan for charts
    without a texture; None when the dataset has no charts or its scene's textures cannot be
    read (the training log then leaves the texel error out)."""
    from rigspace.sdk.errors import RigspaceError
    from rigspace.sdk.posing import CharacterRig
    from rigspace.sdk.stage import open_stage
    from rigspace.sdk.texturing import ChartTextures, TextureMismatch

    table = read_charts(folder)
    if not table or not table.get("charts"):
        return None
    try:
        stage = open_stage(manifest.scene)
        rig = CharacterRig(stage.GetPrimAtPath(manifest.character))
        textures = ChartTextures.build(table, {rig.mesh_name(m): m for m in rig.mesh_sources()})
    except (RigspaceError, TextureMismatch, OSError):
        return None
    return textures.texels_per_st() * textures.half.astype(np.float64)


def chart_targets(
    chart: np.ndarray, uv: np.ndarray, boxes: tuple[np.ndarray, np.ndarray], factor: int
) -> tuple[np.ndarray, np.ndarray]:
    """(R, R) chart and (2, R, R) chart coordinates in [-1, 1] over the chart's uv box, from
    a sample's (H, W) chart and (H, W, 2) uv, downsampled by `factor`.

    A box of factor x factor pixels takes its commonest chart (ties: a chart before none,
    then the lower number) and
    the mean uv of its pixels on that chart: coordinates are never averaged across charts,
    so never across a seam. Coordinates are 0 where the chart is 0.
    """
    h, w = chart.shape
    r, c = h // factor, w // factor
    blocks = chart.reshape(r, factor, c, factor).transpose(0, 2, 1, 3).reshape(r, c, -1)
    if factor == 1:
        mode = chart.astype(np.int64)
        uv_mode = uv.astype(np.float64)
    else:
        charts = np.arange(int(chart.max(initial=0)) + 1)
        counts = (blocks[..., None] == charts).sum(axis=2).astype(np.float64)
        counts[..., 0] -= 0.5  # a tie between a chart and none goes to the chart
        mode = counts.argmax(axis=-1)
        same = blocks == mode[..., None]
        uv_blocks = (
            uv.reshape(r, factor, c, factor, 2).transpose(0, 2, 1, 3, 4).reshape(r, c, -1, 2)
        )
        uv_mode = (uv_blocks * same[..., None]).sum(axis=2) / same.sum(axis=2)[..., None]
    center, half = boxes
    if mode.max(initial=0) >= len(center):
        raise DatasetError(
            f"A sample names texture chart {int(mode.max())}; the dataset's charts.json has "
            f"{len(center) - 1}.",
            "capture the dataset again (charts.json and the samples disagree).",
        )
    local = (uv_mode - center[mode]) / half[mode]
    local = np.where(mode[..., None] > 0, local, 0.0)
    return mode.astype(np.int64), np.moveaxis(local, -1, 0).astype(np.float32)


ITEM_COLUMNS = ["rig", "joint_camera"]
"""The params.npz columns a training item is made from (a shard sample's .npz holds them all)."""
BLEND_COLUMN = "blend"
"""The blend shape weights of a character that has blend shapes (absent otherwise): they
follow the rig parameters in the network's input (rigspace.sdk.rotations.rig_inputs)."""
CONTROL_COLUMN = "controls"
"""The named controls' values of a character that has controls (absent otherwise): they
follow the blend shape weights in the network's input (docs/point_caches.md)."""
POSE_COLUMNS = ("clip", "time", "camera_to_world")
"""The params.npz columns pose rarity needs besides the rig: which frame a row shows (its
views share one pose) and the camera, to take the rig out of the camera's frame."""

RARITY_NEIGHBOURS = 8
"""k: a pose's rarity is its distance to the k-th nearest other frame. Larger than the few
frames a slow clip lingers on, small next to a clip (300 frames): local density."""
RARITY_RANGE = 10.0
"""Rarity is clipped to [median / 10, median * 10]: a held pose (distance 0, the yoga hold)
is still drawn, and no glitch frame takes a large share of the batches."""
RARITY_REFERENCE = 4096
"""Poses above this many are measured against a seeded subsample of this many (distances
n x 4096, in blocks): the sample dataset's 1380 frames are measured exactly, in well under
a second."""
RARITY_DECIMALS = 4
"""Rarity is rounded (to 1e-4 of the median) so that its value, and with it the batches of a
resumed run, do not depend on how BLAS ordered a matrix product's sums."""


def mobility_target(mobility: ShapeMobility, maps: Maps, factor: int) -> np.ndarray:
    """(1, R/factor, R/factor) float32 how much the blend shapes move what each pixel of a
    sample's maps shows (--shape-weight), from its chart and uv maps: the mobility of the
    surface there, the most within one pixel (what a moving part uncovers or covers: the eyes
    under a blink's lids, the silhouette's edge by an opening jaw), box-downsampled."""
    assert maps.chart is not None and maps.uv is not None
    seen = mobility.pixels(np.where(maps.mask > 0, maps.chart, 0), maps.uv)
    seen = cv2.dilate(seen, np.ones((3, 3), np.uint8))  # a 3x3 maximum
    return area_downsample(seen[None], factor).astype(np.float32)


class SplitInfo:
    """What turning one sample's files into a training item needs of its dataset split.

    SampleSet (a dataset folder) and train.stream (tar shards) both make their items with
    `make_item`, so the two readers yield exactly the same keys and values.
    """

    def __init__(self, manifest: DatasetManifest, split: str, resolution: int | None) -> None:
        if split not in SPLITS:
            raise DatasetError(f"Unknown split {split!r}.", f"use one of {', '.join(SPLITS)}.")
        self.manifest = manifest
        self.split = split
        self.dataset_resolution = self.manifest.resolution
        self.resolution = resolution or self.dataset_resolution
        if self.resolution > self.dataset_resolution or self.dataset_resolution % self.resolution:
            raise DatasetError(
                f"Training resolution {self.resolution} does not divide the dataset's "
                f"{self.dataset_resolution}.",
                f"use --resolution {self.dataset_resolution} or a power of two below it.",
            )
        self.depth_scale = depth_scale(self.manifest)
        self.joints = list(self.manifest.joints)
        self.skeleton: Skeleton2D | None = None
        """Set (train.conditioning.dataset_skeleton) to add each item's `joints2d`."""
        self.charts: tuple[np.ndarray, np.ndarray] | None = None
        """Set (chart_boxes) to add each item's `chart` and `uv` (the texture head's targets)."""
        self.mobility: ShapeMobility | None = None
        """Set (train.regions.shape_mobility) to add each item's `mobility` (1, R, R): how much
        the blend shapes move the surface each pixel shows (--shape-weight)."""

    def make_item(self, maps: Maps, row: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """A sample's item from its maps and its params row (ITEM_COLUMNS, and BLEND_COLUMN
        and CONTROL_COLUMN when there are): rig (J*6 + B + C,), albedo (3,R,R), mask (1,R,R),
        normal (3,R,R), depth (1,R,R)."""
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
            "rig": rig_inputs(
                np.asarray(row["rig"])[None], row.get(BLEND_COLUMN), row.get(CONTROL_COLUMN)
            )[0],
            "albedo": albedo.astype(np.float32),
            "mask": mask.astype(np.float32),
            "normal": normal.astype(np.float32),
            "depth": depth.astype(np.float32),
        }
        if self.skeleton is not None:  # pose conditioning: the runtime's function, same input
            item["joints2d"] = joints2d(item["rig"][None], self.skeleton)[0]
        if self.charts is not None:  # the texture head's targets
            if maps.chart is None or maps.uv is None:
                raise DatasetError(
                    "A sample of this dataset has no texture AOVs (uv, chart), though its "
                    "charts.json says the character is textured.",
                    "capture the dataset again with this rigspace.",
                )
            chart, uv = chart_targets(
                np.where(maps.mask > 0, maps.chart, 0),
                maps.uv,
                self.charts,
                self.dataset_resolution // self.resolution,
            )
            item["chart"], item["uv"] = chart[None], uv
        if self.mobility is not None:  # --shape-weight: where the blend shapes move it
            if maps.chart is None or maps.uv is None:
                raise DatasetError(
                    "A sample of this dataset has no texture AOVs (uv, chart), which "
                    "--shape-weight reads to find where the blend shapes move the surface.",
                    "capture the dataset again with this rigspace, or train without "
                    "--shape-weight.",
                )
            factor = self.dataset_resolution // self.resolution
            item["mobility"] = mobility_target(self.mobility, maps, factor)
        return item

    def batch_of(self, items: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        return {key: np.stack([it[key] for it in items]) for key in items[0]}


def ensure_cache(folder: str | Path, manifest: DatasetManifest, progress: bool = True) -> str:
    """Build the dataset's decoded cache (capture.cache) unless a fresh one is there; returns
    one line saying what happened. A cache that cannot be written (a read-only folder, a
    full disk) is reported and training reads the EXRs instead."""
    folder = Path(folder)
    why = stale_reason(folder, manifest)
    if why is None:
        return f"decoded cache {folder / CACHE_FOLDER} is up to date"
    with np.load(folder / "params.npz", allow_pickle=False) as table:
        paths = [str(p) for p in table["path"]]
    print(
        f"rigspace train: decoding {len(paths)} samples once into {folder / CACHE_FOLDER} ({why})",
        file=sys.stderr,
    )
    try:
        cache = build_cache(folder, manifest, paths, progress=progress)
    except OSError as exc:
        return f"no decoded cache ({exc}): the samples are read from their EXRs"
    return f"decoded cache {cache.root}: {cache.info['bytes'] / 2**30:.2f} GiB"


class SampleSet(SplitInfo):
    """One split of a dataset folder at a training resolution. Samples come from the
    dataset's decoded cache (capture.cache) when a fresh one is there, else from their EXRs."""

    def __init__(self, folder: str | Path, split: str, resolution: int | None = None) -> None:
        self.folder = Path(folder)
        if split not in SPLITS:
            raise DatasetError(f"Unknown split {split!r}.", f"use one of {', '.join(SPLITS)}.")
        manifest = read_manifest(self.folder)
        with np.load(self.folder / "params.npz", allow_pickle=False) as table:
            self.rows = np.flatnonzero(table["split"] == SPLITS.index(split))
            blend = table[BLEND_COLUMN] if BLEND_COLUMN in table.files else None
            controls = table[CONTROL_COLUMN] if CONTROL_COLUMN in table.files else None
            self.rig = rig_inputs(table["rig"], blend, controls)
            """The network's input rows (rig parameters, then blend shape weights, then the
            controls' values)."""
            self.paths = table["path"]
            self.joint_depth = -table["joint_camera"][:, 2].astype(np.float32)
            self.columns = {c: table[c] for c in ITEM_COLUMNS}
            if blend is not None:
                self.columns[BLEND_COLUMN] = blend
            if controls is not None:
                self.columns[CONTROL_COLUMN] = controls
        super().__init__(manifest, split, resolution)
        self.cache = open_cache(self.folder, manifest)
        self._rarity: np.ndarray | None = None
        self._weights: dict[float, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.rows)

    def item(self, k: int) -> dict[str, np.ndarray]:
        """Sample k of the split (SplitInfo.make_item)."""
        row = int(self.rows[k])
        if self.cache is not None:
            maps = self.cache.maps(row)
        else:
            maps = read_sample(self.folder, self.manifest, str(self.paths[row]))
        return self.make_item(maps, {c: v[row] for c, v in self.columns.items()})

    def batch(self, ks: np.ndarray) -> dict[str, np.ndarray]:
        return self.batch_of([self.item(int(k)) for k in ks])

    def rarity(self) -> np.ndarray:
        """Each sample's pose rarity (`pose_rarity` of its frame), computed once."""
        if self._rarity is None:
            with np.load(self.folder / "params.npz", allow_pickle=False) as table:
                missing = [c for c in POSE_COLUMNS if c not in table.files]
                columns = {c: table[c][self.rows] for c in POSE_COLUMNS if c in table.files}
            if missing:
                raise DatasetError(
                    f"{self.folder / 'params.npz'} has no {', '.join(missing)} column, which "
                    "--oversample needs to tell a sample's frame and camera.",
                    f"re-capture the dataset with this rigspace (`rigspace capture "
                    f"{self.manifest.scene or 'SCENE'} --out NEW_DIR`), or train with "
                    "--oversample 0.",
                )
            keys = np.stack([columns["clip"].astype(np.float64), columns["time"]], axis=1)
            _, first, frame_of = np.unique(keys, axis=0, return_index=True, return_inverse=True)
            up = stage_axes(self.manifest.up_axis)[0]
            rows = self.rows[first]
            rotations = self.rig[rows][:, : 6 * len(self.joints)]
            features = pose_features(rotations, columns["camera_to_world"][first], up)
            # An expression is part of the pose: a rare one is drawn more often too.
            features = np.concatenate([features, self.rig[rows][:, 6 * len(self.joints) :]], 1)
            self._rarity = pose_rarity(features)[frame_of.reshape(-1)]
        return self._rarity

    def sampling_weights(self, oversample: float, announce: bool = False) -> np.ndarray:
        """Probabilities of drawing each sample, proportional to rarity ** oversample.

        `announce` prints, the first time, one line saying how much the rarest tenth of the
        poses is drawn more often than under uniform sampling (rank 0 of a run).
        """
        check_oversample(oversample)
        if oversample not in self._weights:
            rarity = self.rarity()
            weights = rarity**oversample
            weights = weights / weights.sum()
            self._weights[oversample] = weights
            if announce:
                print(
                    f"rigspace train: {upweighting(rarity, weights, oversample)}", file=sys.stderr
                )
        return self._weights[oversample]


def pose_features(rig: np.ndarray, camera_to_world: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(n, J*6) rig rows -> (n, (J-1)*6 + 3): the pose, independent of camera and heading.

    A rig row holds each joint's world rotation in its camera's frame, so one frame's views
    differ, and a walk that turns round (the sample's does) would look like new poses at
    every heading. The feature keeps what the images depend on beyond the ring's azimuth:
    every joint's rotation relative to the root (joint 0, first in skeleton order), in 6D,
    and the stage's up axis in the root's frame (its tilt: upside down in a cartwheel). Both
    are unchanged by any rotation about the up axis, the camera's included.
    """
    rotation = matrix_from_rot6d(rig.reshape(len(rig), -1, 6))  # (n, J, 3, 3) camera frame
    root_t = np.swapaxes(rotation[:, :1], -1, -2)  # (n, 1, 3, 3): camera -> root frame
    posture = rot6d_from_matrix(root_t @ rotation[:, 1:]).reshape(len(rig), -1)
    up_camera = np.swapaxes(camera_to_world[:, :3, :3], -1, -2) @ up  # (n, 3)
    tilt = (root_t[:, 0] @ up_camera[..., None])[..., 0]
    return np.concatenate([posture, tilt], axis=1)


def pose_rarity(
    features: np.ndarray,
    neighbours: int = RARITY_NEIGHBOURS,
    reference: int = RARITY_REFERENCE,
) -> np.ndarray:
    """Each pose's distance to its k-th nearest other pose, over the median, clipped.

    The k-nearest-neighbour distance is the simplest density estimate that needs no choice
    of clusters or bandwidth and is deterministic: a clip is a curve in pose space, so a
    pose's distance to its k-th neighbour grows as 1 / (frames per unit of pose change).
    A walk cycle repeated ten times or a held yoga pose is dense; a cartwheel, passed once
    and fast, is sparse. Rarity ** 1 is then about even sampling along the curves. Over
    `reference` poses, distances go to a seeded subsample of that many (a coarser scale,
    the same ranking). Returns values in [1 / RARITY_RANGE, RARITY_RANGE], median 1.
    """
    x = np.asarray(features, dtype=np.float64)
    n = len(x)
    chosen = np.arange(n)
    if n > reference:
        chosen = np.sort(np.random.default_rng(0).choice(n, reference, replace=False))
    k = min(neighbours, len(chosen) - 1)
    if k < 1:
        return np.ones(n)
    ref = x[chosen]
    ref_sq = np.einsum("ij,ij->i", ref, ref)
    position = np.full(n, -1)
    position[chosen] = np.arange(len(chosen))
    distance = np.empty(n)
    for start in range(0, n, 256):  # blocks of 256 x reference distances: bounded memory
        block = x[start : start + 256]
        d2 = np.einsum("ij,ij->i", block, block)[:, None] + ref_sq[None] - 2 * block @ ref.T
        own = position[start : start + 256]
        mine = np.flatnonzero(own >= 0)
        d2[mine, own[mine]] = np.inf  # not a neighbour of itself
        kth = np.partition(d2, k - 1, axis=1)[:, k - 1]
        distance[start : start + 256] = np.sqrt(np.maximum(kth, 0.0))
    scale = np.median(distance)
    if not scale > 0:  # most poses held still: measure against the mean instead
        scale = distance.mean()
    if not scale > 0:  # one pose throughout: nothing is rarer than anything else
        return np.ones(n)
    rarity = np.clip(distance / scale, 1 / RARITY_RANGE, RARITY_RANGE)
    return np.round(rarity, RARITY_DECIMALS)


def upweighting(rarity: np.ndarray, weights: np.ndarray, oversample: float) -> str:
    """One line: how much more often the rarest tenth of the samples is drawn than uniformly."""
    order = np.argsort(rarity, kind="stable")
    tenth = max(1, len(order) // 10)
    rare = float(weights[order[-tenth:]].mean() * len(weights))
    common = float(weights[order[:tenth]].mean() * len(weights))
    return (
        f"--oversample {oversample:g}: the rarest tenth of the poses is drawn {rare:.2f}x as "
        f"often as under uniform sampling, the commonest tenth {common:.2f}x"
    )


def epoch_order(n: int, epoch: int, seed: int, weights: np.ndarray | None = None) -> np.ndarray:
    """The n sample indices of an epoch, a pure function of (seed, epoch, weights).

    Uniform (no weights): a permutation, every sample once. Weighted: systematic resampling
    in a shuffled order, so each sample is drawn floor or ceil of n * weight times (its
    expectation, with the least variance) and no sample's turn depends on its neighbours in
    dataset order; then shuffled.
    """
    rng = np.random.default_rng([seed, epoch])
    if weights is None:
        return rng.permutation(n)
    shuffled = rng.permutation(n)
    edges = np.cumsum(weights[shuffled]) * (n / weights.sum())
    picks = np.searchsorted(edges, rng.random() + np.arange(n), side="right")
    return rng.permutation(shuffled[np.minimum(picks, n - 1)])


def batch_indices(
    n: int, batch: int, step: int, seed: int, weights: np.ndarray | None = None
) -> np.ndarray:
    """The sample indices of a step: epochs of `epoch_order`, a pure function of step.

    Resuming at step s therefore continues exactly where an uninterrupted run would be.
    """
    start = step * batch
    out = np.empty(batch, dtype=np.int64)
    filled = 0
    while filled < batch:
        epoch, offset = divmod(start + filled, n)
        perm = epoch_order(n, epoch, seed, weights)
        take = min(batch - filled, n - offset)
        out[filled : filled + take] = perm[offset : offset + take]
        filled += take
    return out


class Prefetcher:
    """Reads the batch of step s + 1 on a background thread while step s trains.

    `oversample` > 0 draws rare poses more often (SampleSet.sampling_weights); 0 is the
    paper's uniform sampling.
    """

    def __init__(
        self,
        samples: SampleSet,
        batch: int,
        seed: int,
        rank: int = 0,
        world: int = 1,
        oversample: float = 0.0,
    ) -> None:
        self.samples, self.batch, self.seed = samples, batch, seed
        # Under torch.distributed `batch` is the global batch and each rank reads its slice:
        # the global batch of a step is the same whatever the world size (exact resume).
        self.rank, self.world = rank, world
        check_oversample(oversample)
        # oversample 0 keeps the uniform permutations exactly (runs from before resume as
        # they were); every rank computes the same weights, so the global batch is shared.
        self.weights = samples.sampling_weights(oversample, rank == 0) if oversample else None
        self._pool = ThreadPoolExecutor(max_workers=1)
        self._pending: dict[int, Future] = {}

    def indices(self, step: int) -> np.ndarray:
        """This rank's sample indices of step `step` (its slice of the global batch)."""
        ks = batch_indices(len(self.samples), self.batch, step, self.seed, self.weights)
        return np.array_split(ks, self.world)[self.rank]

    def _submit(self, step: int) -> None:
        if step not in self._pending:
            self._pending[step] = self._pool.submit(self.samples.batch, self.indices(step))

    def get(self, step: int) -> dict[str, np.ndarray]:
        for other in [s for s in self._pending if s != step]:  # a skipped step's read
            self._pending.pop(other).cancel()
        self._submit(step)
        result = self._pending.pop(step).result()
        self._submit(step + 1)
        return result

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

"""The shape response: what a blend shape's weight changes in the network's image against what
it changes in the mesh's, with the pose and the camera held (issue 33).

For each of a dataset's samples (evenly spaced over a split) and each shape, the shape's
weight is set to 0 and then to 1 and everything else is kept: the network draws the sample's
rig input with those two weights, and the mesh is posed at the sample's time with the same two
weights and rendered from the sample's camera (the dataset's renderer; for a region's dataset
its surface alone, where it is the nearest, as its capture drew it). A change map is the
absolute difference of the two albedos (premultiplied, mean over RGB) per pixel. Over the
pixels either mesh image covers:

- `mesh_change` and `network_change`: the mean change, per sample, then over the samples;
- `ratio`: network_change / mesh_change (1: the network moves the face as much as the mesh);
- `correlation`: Pearson's r of the two change maps over those pixels of every sample (1:
  the network moves the same pixels; near 0: it moves others, or none).

A network that ignores a shape scores a ratio near 0; one that moves the wrong pixels (body
stripes instead of the jaw) a ratio that may look fine and a correlation near 0.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.render import Maps


@dataclass(frozen=True)
class ShapeResponse:
    """One shape's response over the samples (module doc)."""

    shape: str
    samples: int
    mesh_change: float
    network_change: float
    ratio: float
    correlation: float


def change(a: Maps, b: Maps) -> np.ndarray:
    """(H, W) the absolute albedo change from `a` to `b`, mean over RGB."""
    return np.abs(b.albedo.astype(np.float64) - a.albedo.astype(np.float64)).mean(axis=-1)


def summarise(shape: str, pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> ShapeResponse:
    """A shape's response from (mesh change, network change, pixels) per sample."""
    mesh = [float(m[p].mean()) for m, _, p in pairs if p.any()]
    network = [float(n[p].mean()) for _, n, p in pairs if p.any()]
    if not mesh:
        nan = math.nan
        return ShapeResponse(shape, len(pairs), nan, nan, nan, nan)
    all_mesh = np.concatenate([m[p] for m, _, p in pairs])
    all_network = np.concatenate([n[p] for _, n, p in pairs])
    spread = all_mesh.std() > 0 and all_network.std() > 0
    r = float(np.corrcoef(all_mesh, all_network)[0, 1]) if spread else math.nan
    mesh_change, network_change = float(np.mean(mesh)), float(np.mean(network))
    ratio = network_change / mesh_change if mesh_change > 0 else math.nan
    return ShapeResponse(shape, len(pairs), mesh_change, network_change, ratio, r)


class MeshTruth:
    """The dataset's character posed at a sample's time with chosen shape weights, rendered
    from the sample's camera as its capture rendered it (the same renderer and settings)."""

    def __init__(self, dataset: Path) -> None:
        from rigspace.capture.pipeline import ItemWorker
        from rigspace.capture.settings import CaptureSettings

        settings = CaptureSettings.from_json(json.loads((dataset / "capture.json").read_text()))
        self.settings = settings
        self.worker = ItemWorker(settings, dataset)

    def render(
        self, time: float, clip: int, camera_to_world: np.ndarray, weights: dict[str, float]
    ) -> Maps:
        """The maps at `time` of clip number `clip` (the dataset's clip column) from the camera
        at `camera_to_world`, with `weights` (shape -> weight) over the frame's own."""
        from rigspace.sdk.camera import Camera

        worker, lens = self.worker, self.settings.lens
        frame = worker.pose(self.settings.clips[clip].name, time, weights)
        camera = Camera(
            np.asarray(camera_to_world, np.float64), lens.resolution, lens.resolution,
            lens.focal_length, lens.horizontal_aperture, near=lens.near, far=lens.far,
        )  # fmt: skip
        return worker.render(frame, camera)

    def close(self) -> None:
        self.worker.close()


def _shapes_both_have(
    model: Path, read: list[str], recorded: list[str], shapes: list[str] | None
) -> list[str]:
    """`shapes` (default: every shape the model reads), each read by the model and recorded
    by the dataset; a RigspaceError naming what each has otherwise."""
    shapes = read if shapes is None else shapes
    if not read:
        raise RigspaceError(
            f"The model {model} reads no blend shapes, so no shape moves what it draws.",
            "train it on a capture of a character with blend shapes (skel:blendShapes).",
        )
    unknown = [s for s in shapes if s not in read or s not in recorded]
    if unknown:
        raise RigspaceError(
            f"--shapes {', '.join(unknown)}: the model reads {', '.join(read)} and the dataset "
            f"records {', '.join(recorded) or 'none'}.",
            "name shapes both have.",
        )
    return shapes


def _downsampling(level: int, resolution: int) -> int:
    """The factor from the dataset's resolution down to the model's top level (a
    RigspaceError when it is not a whole one)."""
    factor = resolution // level if resolution % level == 0 else 0
    if factor < 1:
        raise RigspaceError(
            f"The model's top level {level} does not divide the dataset's {resolution}.",
            "measure on a dataset captured at the model's resolution or a multiple of it.",
        )
    return factor


def shape_response(
    model: Path,
    dataset: Path,
    shapes: list[str] | None = None,
    split: str = "heldout-views",
    limit: int = 8,
    predictor: str = "auto",
    device: str = "auto",
) -> list[ShapeResponse]:
    """Each of `shapes` (default: every shape the model reads) on `limit` samples of `split`
    (module doc). RigspaceError when the model reads no shapes or names one the dataset lacks."""
    from rigspace.sdk.model import BundleModel
    from rigspace.train.evaluate import DatasetTable, downsample_maps
    from rigspace.train.predictor import to_maps

    table = DatasetTable(dataset)
    network = BundleModel(model, predictor=predictor, device=device)
    recorded = list(table.manifest.blend_shapes)
    shapes = _shapes_both_have(model, list(network.manifest.blend_shapes), recorded, shapes)
    level = max(network.resolutions)
    factor = _downsampling(level, table.resolution)
    indices = table.indices(split)
    indices = indices[np.linspace(0, len(indices) - 1, min(limit, len(indices))).astype(int)]
    truth = MeshTruth(dataset)
    rig_columns = int(np.prod(table.column("rig").shape[1:]))  # joints x 6
    joint_depth = -table.column("joint_camera")[:, 2]
    clips, times = table.column("clip"), table.column("time")
    poses = table.column("camera_to_world")
    pairs: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {s: [] for s in shapes}
    try:
        for index in indices:
            base = table.rig_inputs(np.array([index]))
            for shape in shapes:
                rows = np.repeat(base, 2, axis=0)
                rows[:, rig_columns + recorded.index(shape)] = (0.0, 1.0)
                out = network.predict(rows, level)
                drawn = to_maps(out, np.repeat(joint_depth[index], 2), network.depth_scale)
                mesh = [
                    downsample_maps(
                        truth.render(float(times[index]), int(clips[index]), poses[index],
                                     {shape: w}),
                        factor,
                    )
                    for w in (0.0, 1.0)
                ]  # fmt: skip
                pixels = (mesh[0].mask >= 0.5) | (mesh[1].mask >= 0.5)
                pairs[shape].append((change(*mesh), change(*drawn), pixels))
    finally:
        truth.close()
    return [summarise(shape, pairs[shape]) for shape in shapes]


def format_responses(rows: list[ShapeResponse], what: str) -> str:
    """The responses as a markdown table."""
    lines = [
        f"shape response of {what} (pose and camera held, weight 0 -> 1, albedo change over the "
        "mesh's pixels):",
        "",
        "| shape | samples | mesh change | network change | ratio | correlation |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.shape} | {r.samples} | {r.mesh_change:.4f} | {r.network_change:.4f} | "
            f"{r.ratio:.3f} | {r.correlation:.3f} |"
        )
    return "\n".join(lines) + "\n"

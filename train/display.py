"""Measure a model at the size it is seen: its maps upsampled onto a higher-resolution capture.

The network draws a character at R x R; on screen it is often larger (the previs shot's is
about 324 pixels tall at 640x360). `rigspace eval MODEL DATASET --display` evaluates on a
dataset captured at a multiple of R (a small one: `rigspace capture ... --resolution 512
--every 10`) at every power of two from 2R up to the dataset's resolution (targets box-
downsampled to it), with these predictors of the same held-out rows:

- `runtime`: what `rigspace render` draws: the character's own textures where the texture
  head says (rigspace.sdk.texturing), the albedo branch elsewhere, coverage upsampled and
  sharpened to a one-pixel edge;
- `albedo branch`: the same without the textures (a bundle without a texture head);
- `bilinear`: every map bilinearly upsampled, as the runtime drew before;
- `truth at R, upsampled`: the captured maps box-downsampled to R and upsampled bilinearly:
  the best any R x R image-space predictor can do at this size;
- `textures at the true R coordinates`: the runtime's sampler fed the captured chart and
  coordinates at R (made as training makes its targets) instead of the network's: the best
  the texture path can do at this size, when the head is exact (bundles with a texture head,
  datasets with the texture AOVs).

No torch: it runs the bundle through onnxruntime as the runtime does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rigspace.capture.dataset import DatasetManifest
from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import Maps
from rigspace.sdk.texturing import ChartTextures, TextureMismatch, display_colour, region_warper
from rigspace.train.data import chart_targets
from rigspace.train.evaluate import DatasetTable, downsample_maps
from rigspace.train.predictor import MASK_VALID

MODES = ("runtime", "albedo branch", "bilinear")


def scene_textures(
    model: BundleModel, manifest: DatasetManifest
) -> tuple[ChartTextures | None, str]:
    """The textures of the dataset's character by the bundle's charts (its scene opened
    read-only), and why there are none ("" when there are)."""
    if not model.charts:
        return None, "the bundle has no texture head"
    from rigspace.sdk.posing import CharacterRig
    from rigspace.sdk.stage import open_stage

    stage = open_stage(manifest.scene)
    rig = CharacterRig(stage.GetPrimAtPath(manifest.character))
    table = model.chart_table()
    assert table is not None
    try:
        textures = ChartTextures.build(table, {rig.mesh_name(m): m for m in rig.mesh_sources()})
    except TextureMismatch as exc:
        return None, f"{exc} (the dataset's character is not the one the bundle was trained on)"
    return (textures, "") if textures.any_texture else (None, "the character has no texture")


class DisplayPredictor:
    """A bundle's top level drawn at a table's (higher) resolution (module doc's modes)."""

    def __init__(
        self, model: Path | BundleModel, table: DatasetTable, mode: str = "runtime",
        textures: ChartTextures | None = None,
    ) -> None:  # fmt: skip
        self.model = model if isinstance(model, BundleModel) else BundleModel(model)
        self.table = table
        self.mode = mode
        self.level = max(self.model.resolutions)
        self.textures = textures if mode == "runtime" else None
        self.texels_per_st = None if self.textures is None else self.textures.texels_per_st()
        """Where the runtime read the textures is measured against the captured uv AOV."""
        self.name = mode
        self.footprint_bytes = self.model.footprint_bytes() + (
            self.textures.texture_bytes() if self.textures is not None else 0
        )

    def predict(self, indices: np.ndarray) -> list[Maps]:
        rig = self.table.rig_inputs(indices)
        joint_depth = -self.table.column("joint_camera")[indices][:, 2].astype(np.float32)
        out = self.model.predict(rig, self.level)
        size = self.table.resolution
        scale = size / self.level
        homography = np.diag([scale, scale, 1.0])
        region = (0, 0, size, size)
        warp = region_warper(homography, region)
        maps = []
        for k in range(len(indices)):
            one = {name: value[k] for name, value in out.items()}
            uv = chart = None
            coverage = np.clip(warp(one["mask"])[..., 0], 0.0, 1.0)
            if self.mode == "bilinear":
                albedo = np.clip(warp(one["albedo"]), 0.0, 1.0)
                mask = coverage
            else:
                albedo, mask, info = display_colour(
                    one, homography, region, coverage, self.textures
                )
                sample = info.get("sample")
                if sample is not None:  # where the runtime read the textures: its uv AOV
                    uv, chart = sample.st, sample.chart
            weight = np.maximum(coverage, 1e-6)[..., None]
            normal = warp(one["normal"] * one["mask"]) / weight
            length = np.linalg.norm(normal, axis=-1, keepdims=True)
            normal = np.where(length > 0, normal / np.maximum(length, 1e-12), 0.0)
            offset = warp(one["depth"] * one["mask"])[..., 0] / weight[..., 0]
            valid = coverage >= MASK_VALID
            depth = np.where(valid, joint_depth[k] + self.model.depth_scale * offset, np.inf)
            maps.append(
                Maps(
                    albedo=albedo.astype(np.float32),
                    normal=np.where(valid[..., None], normal, 0.0).astype(np.float32),
                    depth=depth.astype(np.float32),
                    mask=mask.astype(np.float32),
                    uv=uv,
                    chart=chart,
                )
            )
        return maps


class UpsampledTruth:
    """The captured maps box-downsampled to R, upsampled bilinearly back to the table's size:
    the ceiling of any R x R image-space predictor at that size."""

    def __init__(self, table: DatasetTable, resolution: int) -> None:
        self.table = table
        self.factor = table.resolution // resolution
        self.name = f"truth at {resolution}, upsampled"

    def _warp(self):
        size = self.table.resolution
        homography = np.diag([float(self.factor), float(self.factor), 1.0])
        return homography, (0, 0, size, size), region_warper(homography, (0, 0, size, size))

    def predict(self, indices: np.ndarray) -> list[Maps]:
        _, _, warp = self._warp()
        return [
            self._upsampled(downsample_maps(self.table.maps(int(index)), self.factor), warp)
            for index in indices
        ]

    @staticmethod
    def _upsampled(small: Maps, warp) -> Maps:
        """Maps at R (`small`) bilinearly upsampled by `warp`; normals and depth divided by
        the upsampled coverage."""
        mask = small.mask[None]
        depth = np.where(np.isfinite(small.depth), small.depth, 0.0)[None] * mask
        coverage = warp(mask)[..., 0]
        weight = np.maximum(coverage, 1e-6)
        normal = warp(np.moveaxis(small.normal, -1, 0) * mask)
        length = np.linalg.norm(normal, axis=-1, keepdims=True)
        valid = coverage >= MASK_VALID
        return Maps(
            albedo=warp(np.moveaxis(small.albedo, -1, 0)),
            normal=np.where(valid[..., None], normal / np.maximum(length, 1e-12), 0.0).astype(
                np.float32
            ),
            depth=np.where(valid, warp(depth)[..., 0] / weight, np.inf).astype(np.float32),
            mask=coverage.astype(np.float32),
        )


def display_sizes(model_level: int, dataset_resolution: int) -> list[int]:
    """2R, 4R, ... up to the dataset's resolution (each must divide it)."""
    sizes, size = [], 2 * model_level
    while size <= dataset_resolution:
        if dataset_resolution % size == 0:
            sizes.append(size)
        size *= 2
    return sizes


class TrueCoordinates(UpsampledTruth):
    """The texture path's ceiling (module doc): truth at R, upsampled, for the geometry; the
    colour and coverage the runtime would draw from a texture head that predicted the
    captured charts (one-hot) and coordinates exactly, over the captured albedo and coverage
    at R (the albedo branch's part: where no texture colours a pixel)."""

    def __init__(
        self, table: DatasetTable, resolution: int, textures: ChartTextures,
        boxes: tuple[np.ndarray, np.ndarray],
    ) -> None:  # fmt: skip
        super().__init__(table, resolution)
        self.resolution, self.textures, self.boxes = resolution, textures, boxes
        self.name = f"textures at the true {resolution} coordinates"

    def predict(self, indices: np.ndarray) -> list[Maps]:
        homography, region, warp = self._warp()
        below = self.table.captured_resolution // self.resolution
        k = self.textures.charts
        maps = []
        for index in indices:
            full = self.table.captured_maps(int(index))  # one read: the geometry and the colour
            if full.chart is None or full.uv is None:
                raise TextureMismatch(
                    f"{self.table.path(int(index))} has no texture AOVs (uv, chart)"
                )
            shown = downsample_maps(full, self.table.factor)  # as table.maps(index)
            truth = self._upsampled(downsample_maps(shown, self.factor), warp)
            small = downsample_maps(full, below)
            chart, coords = chart_targets(full.chart.astype(np.int64), full.uv, self.boxes, below)
            r = chart.shape[0]
            probabilities = np.zeros((k + 1, r, r), np.float32)
            np.put_along_axis(probabilities, chart[None].astype(np.int64), 1.0, axis=0)
            coordinates = np.zeros((2 * k, r, r), np.float32)
            rows, cols = np.nonzero(chart > 0)
            on = chart[rows, cols]
            coordinates[2 * on - 2, rows, cols] = coords[0, rows, cols]
            coordinates[2 * on - 1, rows, cols] = coords[1, rows, cols]
            out = {
                "albedo": np.moveaxis(small.albedo, -1, 0),
                "alpha": small.mask[None],
                "chart": probabilities,
                "uv": coordinates,
            }
            coverage = np.clip(warp(small.mask[None])[..., 0], 0.0, 1.0)
            albedo, mask, _ = display_colour(out, homography, region, coverage, self.textures)
            maps.append(Maps(albedo, truth.normal, truth.depth, mask.astype(np.float32)))
        return maps

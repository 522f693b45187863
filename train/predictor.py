"""The model as an evaluation predictor: a bundle's maps in the dataset's conventions (no torch)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import Maps
from rigspace.sdk.texturing import ChartTextures
from rigspace.train.evaluate import DatasetTable

MASK_VALID = 0.5
"""Predicted depth and normals count where the predicted coverage is at least this."""


def to_maps(out: dict[str, np.ndarray], joint_depth: np.ndarray, depth_scale: float) -> list[Maps]:
    """Bundle outputs (NCHW, relative depth) -> Maps (HWC, camera depth, +inf where empty)."""
    maps = []
    for k in range(len(joint_depth)):
        mask = out["mask"][k, 0]
        valid = mask >= MASK_VALID
        depth = np.where(valid, joint_depth[k] + depth_scale * out["depth"][k, 0], np.inf)
        maps.append(
            Maps(
                albedo=np.moveaxis(out["albedo"][k], 0, -1).astype(np.float32),
                normal=np.where(valid[..., None], np.moveaxis(out["normal"][k], 0, -1), 0.0).astype(
                    np.float32
                ),
                depth=depth.astype(np.float32),
                mask=mask.astype(np.float32),
            )
        )
    return maps


class BundlePredictor:
    """Predicts a dataset's rows with a model bundle at the dataset's resolution."""

    def __init__(
        self,
        model: Path,
        table: DatasetTable,
        int8: bool = False,
        predictor: str = "auto",
        device: str = "auto",
    ) -> None:
        self.model = BundleModel(
            model, "int8" if int8 else "fp32", predictor=predictor, device=device
        )
        self.table = table
        check_inputs(model, self.model, table)
        self.name = "model (int8)" if int8 else "model"
        self.footprint_bytes = self.model.footprint_bytes()
        if table.resolution not in self.model.levels:
            from rigspace.sdk.bundle import BundleError

            training = self.model.manifest.training
            if table.resolution in training.get("planned_levels", ()):
                raise BundleError(
                    f"The model {model} has levels {self.model.resolutions}: its run stopped at "
                    f"step {training.get('steps')} of {training.get('planned_steps')}, before "
                    f"level {table.resolution} (the dataset's resolution) was trained.",
                    f"continue training: `rigspace train {table.folder} --out {model} --resume` "
                    "(with the original options).",
                )
            raise BundleError(
                f"The model has levels {self.model.resolutions}, the dataset is {table.resolution}x"
                f"{table.resolution}.",
                "evaluate on a dataset captured at one of the model's resolutions.",
            )

    texels_per_st: np.ndarray | None = None
    """Set by attach_textures: the texel scale evaluate() measures the head's placement in."""
    textures: ChartTextures | None = None

    def attach_textures(self, textures: ChartTextures) -> None:
        """Give the maps the texture head's chart and st (where it says the pixel lands on the
        character's textures), so an evaluation measures them (metrics.texture_metrics)."""
        self.textures, self.texels_per_st = textures, textures.texels_per_st()

    def predict(self, indices: np.ndarray) -> list[Maps]:
        rig = self.table.rig_inputs(indices)
        joint_depth = -self.table.column("joint_camera")[indices][:, 2]
        out = self.model.predict(rig, self.table.resolution)
        maps = to_maps(out, joint_depth, self.model.depth_scale)
        if self.textures is None or "chart" not in out:
            return maps
        return [
            replace(m, **dict(zip(("chart", "uv"), head_st(out, k, self.textures), strict=True)))
            for k, m in enumerate(maps)
        ]


def check_inputs(folder: Path, model: BundleModel, table: DatasetTable) -> None:
    """A BundleError when the dataset records other inputs than the model reads: another
    character's, or a region's own joints and shapes (capture/regions.py) under a body."""
    from rigspace.sdk.bundle import BundleError

    manifest = table.manifest
    recorded = (tuple(manifest.joints), tuple(manifest.blend_shapes))
    read = (tuple(model.joints), tuple(model.manifest.blend_shapes))
    if recorded == read:
        return
    region = manifest.settings.get("region")
    fix = (
        f"it is region {region}'s dataset: evaluate the body's dataset, which measures each "
        f"region on DATASET/regions/NAME, or the region's bundle (MODEL/regions/{region}) here"
        if region
        else "evaluate the model on a capture of the character it was trained on"
    )
    raise BundleError(
        f"The model {folder} reads {len(read[0])} joints and {len(read[1])} blend shapes; the "
        f"dataset {table.folder} records {len(recorded[0])} joints and {len(recorded[1])} "
        f"blend shapes{' (other ones)' if len(read[0]) == len(recorded[0]) else ''}.",
        f"{fix}.",
    )


def head_st(
    out: dict[str, np.ndarray], k: int, textures: ChartTextures
) -> tuple[np.ndarray, np.ndarray]:
    """Sample k's most likely chart (H, W) and its predicted st (H, W, 2) from a texture head's
    outputs (0 and 0 where no chart is the most likely)."""
    chart = out["chart"][k].argmax(axis=0)
    pair = np.maximum(chart - 1, 0)[None]
    coords = np.stack([np.take_along_axis(out["uv"][k][c::2], pair, 0)[0] for c in (0, 1)], axis=-1)
    st = textures.center[chart] + coords * textures.half[chart]
    return chart.astype(np.int32), np.where(chart[..., None] > 0, st, 0.0).astype(np.float32)

"""The model as an evaluation predictor: a bundle's maps in the dataset's conventions (no torch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rigspace.sdk.model import BundleModel
from rigspace.sdk.render import Maps
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

    def predict(self, indices: np.ndarray) -> list[Maps]:
        rig = self.table.rig_inputs(indices)
        joint_depth = -self.table.column("joint_camera")[indices][:, 2]
        out = self.model.predict(rig, self.table.resolution)
        return to_maps(out, joint_depth, self.model.depth_scale)

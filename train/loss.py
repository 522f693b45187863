"""The paper's loss, L = (1 - a) L2 + a L1 with a = 0.1, per map and per level of detail.

Coverage (the geometry mask and the albedo alpha) can instead use cross-entropy or add a
soft IoU term (config.mask_loss), and weigh silhouette-edge pixels more (config.edge_weight):
the ablation's mask-loss variants (docs/training.md).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from rigspace.train.config import TrainConfig
from rigspace.train.network import albedo_maps, fade, geometry_maps


def mixed(pred: torch.Tensor, target: torch.Tensor, a: float, weight: torch.Tensor | None = None):
    """(1 - a) * L2 + a * L1, averaged over elements (weighted by `weight` when given)."""
    err = pred - target
    per = (1.0 - a) * err.square() + a * err.abs()
    if weight is None:
        return per.mean()
    weight = weight.expand_as(per)
    return (per * weight).sum() / weight.sum().clamp_min(1.0)


def edge_weights(mask: torch.Tensor, extra: float) -> torch.Tensor | None:
    """1 + extra * (max - min of the target mask over each 3x3 neighbourhood): pixels on or
    beside the silhouette weigh up to 1 + extra; None when extra is 0 (plain mean)."""
    if extra <= 0:
        return None
    spread = F.max_pool2d(mask, 3, 1, 1) + F.max_pool2d(-mask, 3, 1, 1)
    return 1.0 + extra * spread


def coverage_loss(
    logits: torch.Tensor, target: torch.Tensor, config: TrainConfig, weight: torch.Tensor | None
) -> torch.Tensor:
    """The loss of one coverage map (pre-sigmoid `logits`) against its target in [0, 1]."""
    if config.mask_loss == "bce":
        per = F.binary_cross_entropy_with_logits(logits.float(), target.float(), reduction="none")
        if weight is None:
            return per.mean()
        return (per * weight).sum() / weight.sum()
    pred = torch.sigmoid(logits)
    loss = mixed(pred, target, config.l1_weight, weight)
    if config.mask_loss == "soft-iou":
        inter = (pred * target).flatten(1).sum(1)
        union = (pred + target - pred * target).flatten(1).sum(1)
        loss = loss + (1.0 - (inter + 1.0) / (union + 1.0)).mean()
    return loss


def downsample(x: torch.Tensor, size: int) -> torch.Tensor:
    factor = x.shape[-1] // size
    return x if factor == 1 else F.avg_pool2d(x, factor)


def targets_for(batch: dict[str, torch.Tensor], size: int) -> dict[str, torch.Tensor]:
    """Targets at a lower level: box averages; depth and normals weighted by coverage."""
    mask = downsample(batch["mask"], size)
    weight = mask.clamp_min(1e-6)
    normal = F.normalize(
        downsample(batch["normal"] * batch["mask"], size) / weight, dim=1, eps=1e-6
    )
    return {
        "albedo": downsample(batch["albedo"], size),
        "mask": mask,
        "normal": normal,
        "depth": downsample(batch["depth"] * batch["mask"], size) / weight,
    }


def level_loss(
    albedo_head: torch.Tensor, geometry_head: torch.Tensor, target: dict, config: TrainConfig
) -> dict[str, torch.Tensor]:
    """The loss terms of one level's head outputs against targets of the same size."""
    a = config.l1_weight
    depth, normal, _ = geometry_maps(geometry_head)
    inside = (target["mask"] > 0.5).float()  # depth and normals where the target has surface
    edges = edge_weights(target["mask"], config.edge_weight)
    return {
        "albedo": mixed(albedo_maps(albedo_head), target["albedo"], a),
        "mask": config.mask_weight
        * coverage_loss(geometry_head[:, 4:5], target["mask"], config, edges),
        "alpha": config.mask_weight
        * coverage_loss(albedo_head[:, 3:4], target["mask"], config, edges),
        "depth": config.depth_weight * mixed(depth, target["depth"], a, inside),
        "normal": config.normal_weight * mixed(normal, target["normal"], a, inside),
    }


def total_loss(
    heads: dict[str, list[torch.Tensor]],
    batch: dict[str, torch.Tensor],
    alpha: float,
    config: TrainConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of the newest level (faded in by alpha) plus the lower heads at lower_level_weight.

    Keeping every lower head trained against downsampled targets is what makes each level
    a usable output for the runtime's level of detail.
    """
    albedo_levels, geometry_levels = heads["albedo"], heads["geometry"]
    top = fade(albedo_levels, alpha), fade(geometry_levels, alpha)
    terms = level_loss(*top, targets_for(batch, top[0].shape[-1]), config)
    loss = torch.stack(list(terms.values())).sum()
    for albedo_head, geometry_head in zip(albedo_levels[:-1], geometry_levels[:-1], strict=True):
        lower = level_loss(
            albedo_head, geometry_head, targets_for(batch, albedo_head.shape[-1]), config
        )
        loss = loss + config.lower_level_weight * torch.stack(list(lower.values())).sum()
    return loss, {k: float(v.detach()) for k, v in terms.items()}

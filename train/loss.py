"""The paper's loss, L = (1 - a) L2 + a L1 with a = 0.1, per map and per level of detail."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from rigspace.train.config import TrainConfig
from rigspace.train.network import albedo_alpha, albedo_maps, fade, geometry_maps


def mixed(pred: torch.Tensor, target: torch.Tensor, a: float, weight: torch.Tensor | None = None):
    """(1 - a) * L2 + a * L1, averaged over elements (weighted by `weight` when given)."""
    err = pred - target
    per = (1.0 - a) * err.square() + a * err.abs()
    if weight is None:
        return per.mean()
    weight = weight.expand_as(per)
    return (per * weight).sum() / weight.sum().clamp_min(1.0)


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
    depth, normal, mask = geometry_maps(geometry_head)
    inside = (target["mask"] > 0.5).float()  # depth and normals where the target has surface
    return {
        "albedo": mixed(albedo_maps(albedo_head), target["albedo"], a),
        "mask": config.mask_weight * mixed(mask, target["mask"], a),
        "alpha": config.mask_weight * mixed(albedo_alpha(albedo_head), target["mask"], a),
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

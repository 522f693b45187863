"""The paper's loss, L = (1 - a) L2 + a L1 with a = 0.1, per map and per level of detail.

Coverage (the geometry mask and the albedo alpha) can instead use cross-entropy or add a
soft IoU term (config.mask_loss), and weigh silhouette-edge pixels more (config.edge_weight):
the ablation's mask-loss variants (docs/training.md).

The texture head (config.texture, train/network.py) adds two terms: the chart, a
cross-entropy over the K + 1 charts weighted by the target's coverage (and by half on the
empty pixels just outside the silhouette, so that "no chart" is learned there), and the chart
coordinates, the same (1 - a) L2 + a L1 on only the target chart's (u, v) pair where the
target has a chart and at least half covers the pixel: coordinates are never compared
across a seam, and a chart's field is free wherever its chart is not seen.

Where the blend shapes move the surface (config.shape_weight, the batch's `mobility`: train.
regions.ShapeMobility), the albedo, normal, depth, chart and coordinate terms weigh a pixel
1 + shape_weight x its mobility (a weighted mean): a blink's few eyelid pixels are otherwise
a small share of a face's loss.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from rigspace.train.config import TrainConfig
from rigspace.train.network import BRANCH_CHANNELS, albedo_maps, fade, geometry_maps


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


def chart_downsample(
    chart: torch.Tensor, uv: torch.Tensor, size: int, charts: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 1, R, R) charts and (N, 2, R, R) coordinates at `size`: each box's commonest chart
    (ties: a chart before none, then the lower number) and the mean coordinates of its pixels
    on that chart, as train.data.chart_targets makes the training resolution's. `charts` is
    K (the classes are 0..K: given, so nothing waits on the device to count them)."""
    factor = chart.shape[-1] // size
    if factor == 1:
        return chart, uv
    labels = chart[:, 0].long()
    counts = F.avg_pool2d(F.one_hot(labels, charts + 1).permute(0, 3, 1, 2).float(), factor)
    counts[:, 0] -= 0.5 / factor**2  # a tie between a chart and none goes to the chart
    mode = counts.argmax(dim=1, keepdim=True)  # argmax takes the first of equal counts
    same = labels[:, None] == F.interpolate(mode.float(), scale_factor=float(factor)).long()
    same = same.to(uv.dtype)
    mean = F.avg_pool2d(uv * same, factor) / F.avg_pool2d(same, factor).clamp_min(1e-6)
    return mode, mean


def targets_for(
    batch: dict[str, torch.Tensor], size: int, charts: int = 0
) -> dict[str, torch.Tensor]:
    """Targets at a lower level: box averages; depth and normals weighted by coverage; for a
    texture head of `charts` charts, its chart and coordinates by chart_downsample."""
    mask = downsample(batch["mask"], size)
    weight = mask.clamp_min(1e-6)
    normal = F.normalize(
        downsample(batch["normal"] * batch["mask"], size) / weight, dim=1, eps=1e-6
    )
    targets = {
        "albedo": downsample(batch["albedo"], size),
        "mask": mask,
        "normal": normal,
        "depth": downsample(batch["depth"] * batch["mask"], size) / weight,
    }
    if charts and "chart" in batch:
        targets["chart"], targets["uv"] = chart_downsample(
            batch["chart"], batch["uv"], size, charts
        )
    if "mobility" in batch:
        targets["mobility"] = downsample(batch["mobility"], size)
    return targets


def shape_weights(target: dict[str, torch.Tensor], config: TrainConfig) -> torch.Tensor | None:
    """1 + config.shape_weight x the targets' mobility (where the blend shapes move the
    surface, train.regions.ShapeMobility); None when off or the batch has no mobility."""
    if config.shape_weight <= 0 or "mobility" not in target:
        return None
    return 1.0 + config.shape_weight * target["mobility"].float()


def head_charts(head: torch.Tensor, branch: str = "albedo") -> int:
    """K, the texture charts a branch's head predicts (0: no texture head)."""
    extra = head.shape[1] - BRANCH_CHANNELS[branch]
    return (extra - 1) // 3 if extra > 0 else 0


BORDER_CHART_WEIGHT = 0.5
"""The chart loss's weight on empty pixels within 2 of the silhouette (chart 0 is learned
there; farther out the runtime never reads a chart)."""


def texture_loss(
    logits: torch.Tensor,
    coords: torch.Tensor,
    target: dict[str, torch.Tensor],
    config: TrainConfig,
    shapes: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The chart and chart-coordinate terms of one level from the texture head's chart logits
    (N, K+1, R, R) and coordinates (N, 2K, R, R) (see the module doc); `shapes` (N, 1, R, R),
    shape_weights, multiplies both terms' weights."""
    n, channels, h, w = coords.shape
    chart = target["chart"][:, 0].long()
    coverage = target["mask"][:, 0].float()
    ce = F.cross_entropy(logits.float(), chart, reduction="none")
    # Weighted by coverage, and by half over the empty pixels beside the silhouette, so that
    # "no chart" is learned where the runtime reads charts at an edge (2 pixels around).
    border = F.max_pool2d((coverage > 0).float()[:, None], 5, 1, 2)[:, 0]
    weight = torch.maximum(coverage, BORDER_CHART_WEIGHT * border)
    if shapes is not None:
        weight = weight * shapes[:, 0]
    chart_term = (ce * weight).sum() / weight.sum().clamp_min(1.0)
    # The target chart's own (u, v) pair per pixel, in one gather (chart 0 reads pair 0 but
    # has no weight). Gathering, not slicing: a slice's backward zero-fills a gradient the
    # size of the whole head, which measured 0.3 s of a 0.9 s step at 128x128.
    pair = (chart - 1).clamp_min(0)[:, None, None].expand(n, 1, 2, h, w)
    uv = coords.reshape(n, channels // 2, 2, h, w).gather(1, pair)[:, 0]
    valid = ((chart > 0) & (coverage > 0.5)).to(coords.dtype)[:, None]
    if shapes is not None:
        valid = valid * shapes.to(coords.dtype)
    uv_term = mixed(uv.float(), target["uv"].float(), config.l1_weight, valid)
    return {"chart": config.chart_weight * chart_term, "uv": config.uv_weight * uv_term}


def level_loss(
    albedo_head: torch.Tensor,
    geometry_head: torch.Tensor,
    target: dict,
    config: TrainConfig,
    texture_head: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The loss terms of one level's head outputs against targets of the same size
    (`texture_head`: the texture branch's, when the texture head has a branch of its own)."""
    a = config.l1_weight
    texture = None
    branch = config.texture_branch
    heads = {"albedo": albedo_head, "geometry": geometry_head, "texture": texture_head}
    head = heads[branch]
    charts = 0 if head is None else head_charts(head, branch)
    if charts:  # split the texture head off once (see texture_loss on slicing)
        assert head is not None
        own, logits, coords = torch.split(
            head, [BRANCH_CHANNELS[branch], charts + 1, 2 * charts], dim=1
        )
        texture = (logits, coords)
        if branch == "albedo":
            albedo_head = own
        elif branch == "geometry":
            geometry_head = own
    depth, normal, _ = geometry_maps(geometry_head)
    inside = (target["mask"] > 0.5).float()  # depth and normals where the target has surface
    edges = edge_weights(target["mask"], config.edge_weight)
    shapes = shape_weights(target, config)  # where the blend shapes move (--shape-weight)
    if shapes is not None:
        inside = inside * shapes
    terms = {
        "albedo": mixed(albedo_maps(albedo_head), target["albedo"], a, shapes),
        "mask": config.mask_weight
        * coverage_loss(geometry_head[:, 4:5], target["mask"], config, edges),
        "alpha": config.mask_weight
        * coverage_loss(albedo_head[:, 3:4], target["mask"], config, edges),
        "depth": config.depth_weight * mixed(depth, target["depth"], a, inside),
        "normal": config.normal_weight * mixed(normal, target["normal"], a, inside),
    }
    if texture is not None:
        terms |= texture_loss(*texture, target, config, shapes)
    return terms


def total_loss(
    heads: dict[str, list[torch.Tensor]],
    batch: dict[str, torch.Tensor],
    alpha: float,
    config: TrainConfig,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Loss of the newest level (faded in by alpha) plus the lower heads at lower_level_weight.

    Keeping every lower head trained against downsampled targets is what makes each level
    a usable output for the runtime's level of detail.
    """
    albedo_levels, geometry_levels = heads["albedo"], heads["geometry"]
    texture_levels = heads.get("texture")
    textured = heads.get(config.texture_branch) or albedo_levels
    charts = (
        head_charts(textured[-1], config.texture_branch) if config.texture_branch in heads else 0
    )
    top = fade(albedo_levels, alpha), fade(geometry_levels, alpha)
    top_texture = None if texture_levels is None else fade(texture_levels, alpha)
    terms = level_loss(*top, targets_for(batch, top[0].shape[-1], charts), config, top_texture)
    loss = torch.stack(list(terms.values())).sum()
    for k, (albedo_head, geometry_head) in enumerate(
        zip(albedo_levels[:-1], geometry_levels[:-1], strict=True)
    ):
        target = targets_for(batch, albedo_head.shape[-1], charts)
        texture_head = None if texture_levels is None else texture_levels[k]
        lower = level_loss(albedo_head, geometry_head, target, config, texture_head)
        loss = loss + config.lower_level_weight * torch.stack(list(lower.values())).sum()
    # The terms stay tensors (the caller reads them all at once: one device sync a step).
    return loss, {k: v.detach() for k, v in terms.items()}

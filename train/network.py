"""Rig2Image (Borer et al. 2021, section 4): camera-space joint rotations -> character image maps.

q~ (per-joint 6D rotations) -> fully connected layers -> a 4x4 grid -> a shared trunk
block to 8x8 -> two branches, albedo and geometry, of blocks that each double the
resolution (upsample x2, 3x3 conv, activation, 3x3 conv, activation; no transposed
convolutions). Both branches keep 1x1 output heads at every resolution from 8x8 up
(toRGB plus coverage; toDepth, toNormals, toMask), so every level is a usable output: the
runtime's level of detail, and the progressive schedule's fade-in. The albedo branch
predicts coverage too (its alpha), so a frame that needs no lighting and no depth test
runs the albedo branch alone (the runtime's unlit mode).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from rigspace.train.config import TrainConfig

GRID = 4
"""The fully connected layers end in a GRID x GRID feature map."""
TRUNK = 8
"""The branches split at 8x8 (the paper's shared trunk)."""
LEAK = 0.2


@dataclass(frozen=True)
class Shape:
    joints: int
    encoding: int = 6

    @property
    def inputs(self) -> int:
        return self.joints * self.encoding


def width(config: TrainConfig, resolution: int) -> int:
    """Conv channels at a resolution: base_width at 4 and 8, halved per doubling after."""
    halvings = max(0, (resolution // TRUNK).bit_length() - 1)
    return max(config.min_width, config.base_width >> halvings)


class UpBlock(nn.Module):
    """Upsample x2, then (3x3 conv, leaky ReLU) twice."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, padding=1)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(x, scale_factor=2.0, mode="nearest")
        x = F.leaky_relu(self.conv1(x), LEAK)
        return F.leaky_relu(self.conv2(x), LEAK)


class Branch(nn.Module):
    """Blocks from 8x8 to the final resolution, with a 1x1 head at every resolution."""

    def __init__(self, config: TrainConfig, head_channels: int) -> None:
        super().__init__()
        self.resolutions = [TRUNK]
        while self.resolutions[-1] < config.resolution:
            self.resolutions.append(self.resolutions[-1] * 2)
        self.blocks = nn.ModuleList(
            UpBlock(width(config, r // 2), width(config, r)) for r in self.resolutions[1:]
        )
        self.heads = nn.ModuleList(
            nn.Conv2d(width(config, r), head_channels, 1) for r in self.resolutions
        )

    def features_at(self, x: torch.Tensor, resolution: int) -> torch.Tensor:
        """The blocks' features at `resolution` (the input of that level's head)."""
        for r, block in zip(self.resolutions[1:], self.blocks, strict=True):
            if r > resolution:
                break
            x = block(x)
        return x

    def forward(self, x: torch.Tensor, resolution: int) -> list[torch.Tensor]:
        """Head outputs (pre-activation) at every resolution from 8x8 up to `resolution`."""
        outs = [self.heads[0](x)]
        for r, block, head in zip(self.resolutions[1:], self.blocks, self.heads[1:], strict=True):
            if r > resolution:
                break
            x = block(x)
            outs.append(head(x))
        return outs


ALBEDO_CHANNELS = 4  # premultiplied RGB 3, coverage (alpha) 1
GEOMETRY_CHANNELS = 5  # depth 1, normal 3, mask 1


class Rig2Image(nn.Module):
    """The whole network; `forward` returns each head's maps at every level up to `resolution`."""

    def __init__(self, shape: Shape, config: TrainConfig) -> None:
        super().__init__()
        self.shape = shape
        self.config = config
        layers: list[nn.Module] = []
        c = shape.inputs
        for _ in range(config.fc_layers):
            layers += [nn.Linear(c, config.latent), nn.LeakyReLU(LEAK)]
            c = config.latent
        self.mapping = nn.Sequential(*layers)
        self.to_grid = nn.Linear(config.latent, width(config, GRID) * GRID * GRID)
        self.trunk = UpBlock(width(config, GRID), width(config, TRUNK))
        self.albedo = Branch(config, ALBEDO_CHANNELS)
        self.geometry = Branch(config, GEOMETRY_CHANNELS)

    def features(self, rig: torch.Tensor) -> torch.Tensor:
        """q~ (N, joints * 6) -> the shared 8x8 trunk features."""
        x = self.to_grid(self.mapping(rig))
        x = F.leaky_relu(x, LEAK).view(-1, width(self.config, GRID), GRID, GRID)
        return self.trunk(x)

    def forward(
        self, rig: torch.Tensor, resolution: int, branches: tuple[str, ...] = ("albedo", "geometry")
    ) -> dict[str, list[torch.Tensor]]:
        """Pre-activation head outputs per branch, one per level from 8x8 to `resolution`."""
        x = self.features(rig)
        return {name: getattr(self, name)(x, resolution) for name in branches}


def fade(levels: list[torch.Tensor], alpha: float) -> torch.Tensor:
    """The output at the newest level while it fades in (ProGAN-style, on head outputs):
    alpha * new + (1 - alpha) * upsample(previous)."""
    new = levels[-1]
    if alpha >= 1.0 or len(levels) < 2:
        return new
    old = F.interpolate(levels[-2], scale_factor=2.0, mode="nearest")
    return alpha * new + (1.0 - alpha) * old


def albedo_maps(head: torch.Tensor) -> torch.Tensor:
    """Premultiplied linear albedo in [0, 1]."""
    return torch.sigmoid(head[:, 0:3])


def albedo_alpha(head: torch.Tensor) -> torch.Tensor:
    """The albedo branch's coverage in [0, 1] (trained against the same target as the mask)."""
    return torch.sigmoid(head[:, 3:4])


def geometry_maps(head: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(relative depth, unit camera-space normals, mask in [0, 1]) from the geometry head."""
    depth = head[:, 0:1]
    normal = F.normalize(head[:, 1:4], dim=1, eps=1e-6)
    mask = torch.sigmoid(head[:, 4:5])
    return depth, normal, mask

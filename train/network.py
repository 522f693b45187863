"""Rig2Image (Borer et al. 2021, section 4): camera-space joint rotations -> character image maps.

q~ (per-joint 6D rotations) -> fully connected layers -> a 4x4 grid -> a shared trunk
block to 8x8 -> two branches, albedo and geometry, of blocks that each double the
resolution (upsample x2, 3x3 conv, activation, 3x3 conv, activation; no transposed
convolutions). Both branches keep 1x1 output heads at every resolution from 8x8 up
(toRGB plus coverage; toDepth, toNormals, toMask), so every level is a usable output: the
runtime's level of detail, and the progressive schedule's fade-in. The albedo branch
predicts coverage too (its alpha), so a frame that needs no lighting and no depth test
runs the albedo branch alone (the runtime's unlit mode).

Pose-guided conditioning (config.conditioning, not in the paper): every block (the trunk's
and each branch's) also reads Gaussian maps of the rig's projected joints or bones at its
output resolution, after the upsampling (train.conditioning): concatenated as extra input
channels of the block's first convolution (config.conditioning_mode "concat"), or projected
by a 1x1 convolution to the block's width and added to its features ("add", which keeps the
3x3 convolutions at the paper's channel counts). With config.conditioning_top the maps are
computed at levels up to that resolution only; blocks above it read them upsampled. The maps
are computed from a small `joints2d` input (rigspace.sdk.conditioning), so with "none" the
network, its parameters and its checkpoints are the paper's.

Texture head (config.texture, not in the paper; after Textured Neural Avatars, Shysheya et
al. 2019): for a character with K texture charts (rigspace.sdk.charts) heads predict, per
pixel, the chart (K + 1 logits, 0: no chart) and, for every chart, the texture coordinates
within it (2K channels, the chart's uv box mapped to [-1, 1]). config.texture_branch says
whose heads: the albedo branch's (the default), the geometry branch's, or a third branch of
their own from the trunk ("texture"), so that neither map pays for the head's channels. Each
chart's coordinate field is continuous wherever that chart is seen, so no output ever has
to jump at a seam: the loss reads only the target chart's pair (train/loss.py) and the
runtime samples the material's own texture where the classifier picks a chart
(rigspace.sdk.texturing); the albedo head stays, as the fallback and for comparison.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from rigspace.train.conditioning import ConditionMaps, channels
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
    parents: tuple[int, ...] = ()
    """Each joint's parent index (-1 for a root); needed by bones2d conditioning only."""
    charts: int = 0
    """Texture charts K of the character (rigspace.sdk.charts); 0: no texture head."""
    blend_shapes: int = 0
    """Blend shape weights B that follow the joints' rotations in the input (0: none)."""
    controls: int = 0
    """Named controls' values C that follow the blend shape weights in the input (0: none)."""

    @property
    def inputs(self) -> int:
        return self.joints * self.encoding + self.blend_shapes + self.controls


def width(config: TrainConfig, resolution: int) -> int:
    """Conv channels at a resolution: base_width at 4 and 8, halved per doubling after."""
    halvings = max(0, (resolution // TRUNK).bit_length() - 1)
    return max(config.min_width, config.base_width >> halvings)


def maps_scale(config: TrainConfig, resolution: int) -> int:
    """How much a level's block upsamples its conditioning maps (1: computed at its level)."""
    top = config.conditioning_top
    return resolution // top if top and resolution > top else 1


class UpBlock(nn.Module):
    """Upsample x2, (read `extra` conditioning maps: concatenated, or 1x1-projected and added),
    then (3x3 conv, leaky ReLU) twice."""

    def __init__(
        self, c_in: int, c_out: int, extra: int = 0, mode: str = "concat", maps_scale: int = 1
    ) -> None:
        super().__init__()
        self.maps_scale = maps_scale
        """Output resolution / the maps' resolution (> 1 above config.conditioning_top)."""
        self.add = bool(extra) and mode == "add"
        self.conv1 = nn.Conv2d(c_in + (0 if self.add else extra), c_out, 3, padding=1)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1)
        self.project = nn.Conv2d(extra, c_in, 1) if self.add else None

    def forward(self, x: torch.Tensor, maps: torch.Tensor | None = None) -> torch.Tensor:
        x = F.interpolate(x, scale_factor=2.0, mode="nearest")
        if maps is not None:
            maps = maps.to(x.dtype)
            if self.project is not None:
                maps = self.project(maps)  # at the maps' resolution: cheaper below the top
            if self.maps_scale > 1:  # maps from conditioning_top, below this level
                maps = F.interpolate(maps, scale_factor=float(self.maps_scale), mode="nearest")
            x = x + maps if self.project is not None else torch.cat([x, maps], dim=1)
        x = F.leaky_relu(self.conv1(x), LEAK)
        return F.leaky_relu(self.conv2(x), LEAK)


class Branch(nn.Module):
    """Blocks from 8x8 to the final resolution, with a 1x1 head at every resolution."""

    def __init__(self, config: TrainConfig, head_channels: int, extra: int = 0) -> None:
        super().__init__()
        self.resolutions = [TRUNK]
        while self.resolutions[-1] < config.resolution:
            self.resolutions.append(self.resolutions[-1] * 2)
        self.blocks = nn.ModuleList(
            UpBlock(
                width(config, r // 2),
                width(config, r),
                extra,
                config.conditioning_mode,
                maps_scale(config, r),
            )
            for r in self.resolutions[1:]
        )
        self.heads = nn.ModuleList(
            nn.Conv2d(width(config, r), head_channels, 1) for r in self.resolutions
        )

    def features_at(
        self, x: torch.Tensor, resolution: int, maps: dict[int, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """The blocks' features at `resolution` (the input of that level's head)."""
        for r, block in zip(self.resolutions[1:], self.blocks, strict=True):
            if r > resolution:
                break
            x = block(x, None if maps is None else maps[r])
        return x

    def forward(
        self, x: torch.Tensor, resolution: int, maps: dict[int, torch.Tensor] | None = None
    ) -> list[torch.Tensor]:
        """Head outputs (pre-activation) at every resolution from 8x8 up to `resolution`."""
        outs = [self.heads[0](x)]
        for r, block, head in zip(self.resolutions[1:], self.blocks, self.heads[1:], strict=True):
            if r > resolution:
                break
            x = block(x, None if maps is None else maps[r])
            outs.append(head(x))
        return outs


BOTH = ("albedo", "geometry")
"""The two map branches every network has."""
ALBEDO_CHANNELS = 4  # premultiplied RGB 3, coverage (alpha) 1
GEOMETRY_CHANNELS = 5  # depth 1, normal 3, mask 1


BRANCH_CHANNELS = {"albedo": ALBEDO_CHANNELS, "geometry": GEOMETRY_CHANNELS, "texture": 0}
"""Each branch's own head channels, before a texture head's (the texture branch has none)."""
TEXTURE_BRANCHES = ("albedo", "geometry", "texture")
"""Where a texture head can be (config.texture_branch): on one of the two map branches, or a
branch of its own."""


def texture_channels(charts: int) -> int:
    """Texture head channels for K charts: K + 1 chart logits, then a (u, v) pair per chart."""
    return 0 if charts <= 0 else (charts + 1) + 2 * charts


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
        extra = channels(config.conditioning, shape.joints)
        self.condition = (
            ConditionMaps(config.conditioning, np.asarray(shape.parents), config.conditioning_sigma)
            if extra
            else None
        )
        if extra and config.conditioning == "bones2d" and len(shape.parents) != shape.joints:
            raise ValueError("bones2d conditioning needs the joints' parents (Shape.parents)")
        self.trunk = UpBlock(
            width(config, GRID), width(config, TRUNK), extra, config.conditioning_mode
        )
        self.charts = shape.charts if config.texture else 0
        """K texture charts the texture head predicts (0: no texture head)."""
        self.texture_branch = config.texture_branch
        """The branch whose heads carry the texture head (config.texture_branch)."""
        if self.texture_branch not in TEXTURE_BRANCHES:
            raise ValueError(
                f"texture_branch must be one of {', '.join(TEXTURE_BRANCHES)}, "
                f"got {self.texture_branch!r}"
            )
        texture = texture_channels(self.charts)

        def head(branch: str) -> int:
            return BRANCH_CHANNELS[branch] + (texture if branch == self.texture_branch else 0)

        self.albedo = Branch(config, head("albedo"), extra)
        self.geometry = Branch(config, head("geometry"), extra)
        self.texture = (
            Branch(config, texture, extra) if self.texture_branch == "texture" and texture else None
        )
        """The texture head's own branch (config.texture_branch "texture"), else None."""

    @property
    def branch_names(self) -> tuple[str, ...]:
        """The branches this network has: albedo, geometry, and texture when it has its own."""
        return ("albedo", "geometry", "texture") if self.texture is not None else BOTH

    @property
    def conditioned(self) -> bool:
        """Whether the network reads joints2d (config.conditioning is not "none")."""
        return self.condition is not None

    def condition_maps(
        self, joints2d: torch.Tensor | None, resolution: int
    ) -> dict[int, torch.Tensor] | None:
        """The conditioning maps for 8x8 and every level up to `resolution` (None: unconditioned);
        above config.conditioning_top a level gets the top level's maps (its block upsamples)."""
        if self.condition is None:
            return None
        if joints2d is None:
            raise ValueError(
                f"this network is conditioned ({self.config.conditioning}): pass joints2d"
            )
        top = self.config.conditioning_top or max(resolution, TRUNK)
        out: dict[int, torch.Tensor] = {}
        r = TRUNK
        while r <= max(resolution, TRUNK):
            out[r] = out[r // 2] if r > top else self.condition(joints2d, r)
            r *= 2
        return out

    def features(self, rig: torch.Tensor, joints2d: torch.Tensor | None = None) -> torch.Tensor:
        """q~ (N, joints * 6) (and joints2d (N, joints * 2) when conditioned) -> the 8x8 features."""
        return self._trunk(rig, self.condition_maps(joints2d, TRUNK))

    def _trunk(self, rig: torch.Tensor, maps: dict[int, torch.Tensor] | None) -> torch.Tensor:
        x = self.to_grid(self.mapping(rig))
        x = F.leaky_relu(x, LEAK).view(-1, width(self.config, GRID), GRID, GRID)
        return self.trunk(x, None if maps is None else maps[TRUNK])

    def forward(
        self,
        rig: torch.Tensor,
        resolution: int,
        branches: tuple[str, ...] | None = None,
        joints2d: torch.Tensor | None = None,
    ) -> dict[str, list[torch.Tensor]]:
        """Pre-activation head outputs per branch (default: every branch it has), one per
        level from 8x8 to `resolution`."""
        maps = self.condition_maps(joints2d, resolution)
        x = self._trunk(rig, maps)
        names = self.branch_names if branches is None else branches
        return {name: getattr(self, name)(x, resolution, maps) for name in names}


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


def texture_maps(
    head: torch.Tensor, charts: int, branch: str = "albedo"
) -> tuple[torch.Tensor, torch.Tensor]:
    """(chart logits (N, K+1, R, R), chart coordinates (N, 2K, R, R)) from the head of the
    branch that carries the texture head: chart k's (u, v) within its uv box, in [-1, 1], are
    channels 2(k-1) and 2(k-1) + 1 of the coordinates."""
    start = BRANCH_CHANNELS[branch]
    return head[:, start : start + charts + 1], head[:, start + charts + 1 : start + 3 * charts + 1]


def geometry_maps(head: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(relative depth, unit camera-space normals, mask in [0, 1]) from the geometry head."""
    depth = head[:, 0:1]
    normal = F.normalize(head[:, 1:4], dim=1, eps=1e-6)
    mask = torch.sigmoid(head[:, 4:5])
    return depth, normal, mask

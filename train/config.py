"""Training configuration: one dataclass, three presets, every field on the CLI, saved as JSON."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from rigspace.sdk.errors import RigspaceError


class ConfigError(RigspaceError, ValueError):
    """A training option with a value it cannot take."""


def check_oversample(oversample: float) -> None:
    """A ConfigError naming --oversample unless it is a finite number >= 0 (NaN is not)."""
    if not (math.isfinite(oversample) and oversample >= 0):
        raise ConfigError(
            f"Training option --oversample is {oversample!r}.",
            "choose a finite number >= 0 (0: uniform sampling, the paper's; 1: rare poses "
            "about as often as common ones).",
        )


def check_anneal(share: float) -> None:
    """A ConfigError naming --anneal unless it is a share from 0 to 1 (NaN is not)."""
    if not (math.isfinite(share) and 0.0 <= share <= 1.0):
        raise ConfigError(
            f"Training option --anneal is {share!r}.",
            "give the share of the run at whose end the learning rate falls, from 0 (off) to 1 "
            "(the whole run), such as 0.3.",
        )


@dataclass(frozen=True)
class TrainConfig:
    """Everything that determines a training run (saved as run.json beside the checkpoints)."""

    preset: str = field(default="small", metadata={"help": "the preset these values started from"})
    resolution: int = field(
        default=128, metadata={"help": "final output resolution (a power of two <= the dataset's)"}
    )
    latent: int = field(default=256, metadata={"help": "width of the fully connected latent"})
    fc_layers: int = field(
        default=3, metadata={"help": "fully connected layers before the 4x4 grid"}
    )
    base_width: int = field(
        default=128, metadata={"help": "conv channels at 4x4 and 8x8; halved per doubling"}
    )
    min_width: int = field(default=16, metadata={"help": "fewest conv channels at any resolution"})
    start_resolution: int = field(
        default=16, metadata={"help": "resolution trained first (the paper: 16x16)"}
    )
    batch: int = field(default=16, metadata={"help": "samples per step"})
    oversample: float = field(
        default=0.0,
        metadata={
            "help": "draw samples with probability proportional to their pose's "
            "rarity^OVERSAMPLE (rarity: distance to the 8th nearest other frame, camera and "
            "heading aside, 0.1-10x the median): 0 uniform (the paper's), 1 about even along "
            "each clip's path through pose space; dataset folders only, not shards"
        },
    )
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate"})
    adam_beta1: float = field(
        default=0.9,
        metadata={"help": "Adam beta1 (ProGAN's 0 made the depth head diverge here, measured)"},
    )
    adam_beta2: float = field(default=0.99, metadata={"help": "Adam beta2"})
    grad_clip: float = field(
        default=1.0, metadata={"help": "clip the global gradient norm to this (0: off)"}
    )
    steps_per_level: int = field(
        default=1000, metadata={"help": "steps at each resolution level (fade-in included)"}
    )
    fade_fraction: float = field(
        default=0.5, metadata={"help": "share of a level's steps spent fading the new block in"}
    )
    l1_weight: float = field(
        default=0.1, metadata={"help": "a in L = (1 - a) L2 + a L1 (the paper's 0.1)"}
    )
    lower_level_weight: float = field(
        default=0.25,
        metadata={"help": "loss weight of each lower-resolution head (level of detail)"},
    )
    depth_weight: float = field(default=1.0, metadata={"help": "weight of the depth loss"})
    normal_weight: float = field(default=1.0, metadata={"help": "weight of the normal loss"})
    mask_weight: float = field(default=1.0, metadata={"help": "weight of the mask loss"})
    mask_loss: str = field(
        default="mixed",
        metadata={
            "help": "mask and alpha loss: mixed (the paper's L2/L1), bce (cross-entropy on the "
            "logits), soft-iou (mixed plus 1 - soft IoU per sample)"
        },
    )
    edge_weight: float = field(
        default=0.0,
        metadata={"help": "extra mask/alpha loss weight on silhouette-edge pixels (0: off)"},
    )
    shape_weight: float = field(
        default=0.0,
        metadata={
            "help": "extra loss weight where the blend shapes move the surface: albedo, normals, "
            "depth and texture terms weigh 1 + this x the pixel's mobility (0..1, its most "
            "moving shape's displacement there over that shape's largest; 0: off)"
        },
    )
    conditioning: str = field(
        default="none",
        metadata={
            "help": "pose-guided conditioning maps fed to every block: none (the paper's "
            "rotations only), joints2d (a Gaussian per projected joint), bones2d (per bone)"
        },
    )
    conditioning_sigma: float = field(
        default=0.05,
        metadata={"help": "width of the conditioning Gaussians, image half-widths (>= 1 pixel)"},
    )
    conditioning_mode: str = field(
        default="concat",
        metadata={
            "help": "how a block reads the maps: concat (extra input channels of its first 3x3 "
            "conv), add (a 1x1 conv projects them to the block's width, added to the features)"
        },
    )
    conditioning_top: int = field(
        default=0,
        metadata={
            "help": "highest resolution the maps are computed at (0: every level); blocks above "
            "it read the top maps upsampled (add: their 1x1 projection, upsampled)"
        },
    )
    texture: bool = field(
        default=False,
        metadata={
            "help": "a texture head on the albedo branch: per pixel the texture chart and the "
            "coordinates within it, so the runtime samples the character's own textures at the "
            "size on screen (datasets with texture charts; the small and paper presets turn it on)"
        },
    )
    texture_branch: str = field(
        default="albedo",
        metadata={
            "help": "the branch whose heads carry the texture head: albedo (an unlit frame runs "
            "the albedo branch alone and is still textured), geometry (the branch that knows "
            "where the surface is) or texture (a branch of its own, so neither map pays for it; "
            "a frame runs it beside the albedo branch)"
        },
    )
    chart_weight: float = field(
        default=0.25,
        metadata={
            "help": "weight of the chart classification loss (cross-entropy; at 1 the other "
            "maps lose more, docs/texture.md)"
        },
    )
    uv_weight: float = field(
        default=4.0,
        metadata={
            "help": "weight of the chart coordinates loss (at 1 the coordinates are 40%% less "
            "precise than at 10; at 10 depth is 37%% worse; docs/texture.md)"
        },
    )
    seed: int = field(default=0, metadata={"help": "seed for weights, sampling and shuffling"})
    bf16: bool = field(
        default=False,
        metadata={
            "help": "bf16 autocast (measured on 2 CPU cores: faster up to 64x64, slower at 128x128)"
        },
    )
    channels_last: bool = field(default=True, metadata={"help": "channels_last memory format"})
    threads: int = field(default=0, metadata={"help": "torch threads (0: one per core)"})
    eval_every: int = field(default=500, metadata={"help": "steps between held-out evaluations"})
    eval_samples: int = field(default=64, metadata={"help": "held-out samples per evaluation"})
    checkpoint_every: int = field(default=500, metadata={"help": "steps between checkpoints"})

    def levels(self) -> list[int]:
        """Resolutions trained in order: start_resolution, then doubling up to resolution."""
        out, r = [], self.start_resolution
        while r <= self.resolution:
            out.append(r)
            r *= 2
        return out

    def total_steps(self) -> int:
        return self.steps_per_level * len(self.levels())

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> TrainConfig:
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown training options {unknown}")
        config = cls(**data)
        config.check()
        return config

    def check(self) -> None:
        """A ConfigError naming an option whose value is not one of its choices."""
        choices = {
            "mask_loss": MASK_LOSSES,
            "conditioning": ("none", "joints2d", "bones2d"),
            "conditioning_mode": CONDITIONING_MODES,
            "texture_branch": ("albedo", "geometry", "texture"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ConfigError(
                    f"Training option --{name.replace('_', '-')} is {getattr(self, name)!r}.",
                    f"choose one of {', '.join(allowed)}.",
                )
        check_oversample(self.oversample)
        if not (math.isfinite(self.shape_weight) and self.shape_weight >= 0):
            raise ConfigError(
                f"Training option --shape-weight is {self.shape_weight}.",
                "give 0 (off) or a positive weight, such as 4.",
            )
        top = self.conditioning_top
        if top and (top < 8 or top & (top - 1)):
            raise ConfigError(
                f"Training option --conditioning-top is {top}.",
                "choose 0 (maps at every level) or a power of two from 8 up.",
            )


MASK_LOSSES = ("mixed", "bce", "soft-iou")
CONDITIONING_MODES = ("concat", "add")


PRESETS: dict[str, TrainConfig] = {
    # Seconds on a laptop CPU: CI smoke runs and tests.
    "tiny": TrainConfig(
        preset="tiny",
        resolution=32,
        latent=32,
        fc_layers=2,
        base_width=16,
        min_width=8,
        start_resolution=16,
        batch=4,
        lr=3e-3,
        steps_per_level=20,
        eval_every=20,
        eval_samples=8,
        checkpoint_every=20,
    ),
    # The committed sample model: about an hour on 2 CPU cores at 128x128.
    "small": TrainConfig(preset="small", steps_per_level=4000, texture=True),
    # The paper's widths (512-channel latent and trunk), for a GPU.
    "paper": TrainConfig(
        preset="paper",
        resolution=256,
        latent=512,
        fc_layers=4,
        base_width=512,
        min_width=32,
        batch=32,
        lr=1e-3,
        texture=True,
        steps_per_level=20000,
        eval_every=2000,
        eval_samples=256,
        checkpoint_every=2000,
    ),
}


def preset(name: str, **overrides: Any) -> TrainConfig:
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    config = replace(PRESETS[name], **{k: v for k, v in overrides.items() if v is not None})
    config.check()
    return config

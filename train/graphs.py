"""The model bundle's graphs as torch modules: the trunk, and one branch at one level.

`rigspace.train.export` traces these to ONNX and the torch predictor
(rigspace.train.torch_predictor) runs the same modules, so both compute one function.
Imports no capture, dataset or training code: only the network.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from rigspace.train.network import BRANCH_CHANNELS, TRUNK, Rig2Image


class Trunk(nn.Module):
    """rig -> the shared 8x8 features."""

    def __init__(self, model: Rig2Image) -> None:
        super().__init__()
        self.model = model

    def forward(self, rig: torch.Tensor, joints2d: torch.Tensor | None = None) -> torch.Tensor:
        return self.model.features(rig, joints2d)


HEAD_GROUPS: dict[str, tuple[tuple[int, int], ...]] = {
    "albedo": ((0, 3), (3, 4)),
    "geometry": ((0, 1), (1, 4), (4, 5)),
    "texture": (),
}
"""Channels of each branch's 1x1 head that make one output: albedo, alpha; depth, normal,
mask (network.ALBEDO_CHANNELS, GEOMETRY_CHANNELS); the texture branch has only the texture
head's (head_groups)."""


class BranchAtLevel(nn.Module):
    """features -> one branch's activated maps at one resolution.

    Each output gets its own 1x1 convolution (the head's rows for its channels) and its own
    activation, the same as network.albedo_maps, albedo_alpha and geometry_maps: the fp32
    graph computes exactly what the one head does, but static int8 now gives each output
    its own activation scale. With one shared scale a confident mask (logits spanning
    hundreds) rounded every normal to zero (train.int8check; measured in docs/training.md).
    """

    def __init__(self, model: Rig2Image, branch: str, resolution: int) -> None:
        super().__init__()
        self.model, self.branch = model, getattr(model, branch)
        self.name, self.resolution = branch, resolution
        self.head = self.branch.heads[self.branch.resolutions.index(resolution)]
        self.groups = head_groups(branch, model.charts if branch == model.texture_branch else 0)

    def forward(self, features: torch.Tensor, joints2d: torch.Tensor | None = None):
        # In the graph (conditioned); the 8x8 level has no block, so reads no maps.
        maps = (
            None
            if self.resolution <= TRUNK
            else self.model.condition_maps(joints2d, self.resolution)
        )
        x = self.branch.features_at(features, self.resolution, maps)
        w, b = self.head.weight, self.head.bias
        parts = [F.conv2d(x, w[i:j], b[i:j]) for i, j in self.groups]
        own = len(HEAD_GROUPS[self.name])
        if self.name == "albedo":
            outputs: tuple = (torch.sigmoid(parts[0]), torch.sigmoid(parts[1]))
        elif self.name == "texture":
            outputs = ()
        else:
            outputs = (parts[0], F.normalize(parts[1], dim=1, eps=1e-6), torch.sigmoid(parts[2]))
        if len(parts) > own:  # the texture head: chart probabilities and coordinates
            outputs = (*outputs, channel_softmax(parts[own]), parts[own + 1])
        return outputs


def channel_softmax(x: torch.Tensor) -> torch.Tensor:
    """Softmax over dim 1 of (N, C, H, W), written out (max, exp, sum, divide). The export
    brings it to the form onnxruntime's CPU runs fast (graph_rewrite.fast_channel_softmax:
    its Softmax node over the channel axis of NCHW took 6.2 of the 128x128 albedo graph's
    10.3 ms, this form 1.1 of 7.0 on one thread); `python -m rigspace.apps.graph_rewrite
    BUNDLE` does the same to older bundles."""
    shifted = x - x.amax(dim=1, keepdim=True)
    e = torch.exp(shifted)
    return e / e.sum(dim=1, keepdim=True)


def head_groups(branch: str, charts: int) -> tuple[tuple[int, int], ...]:
    """A branch's head channels by output (HEAD_GROUPS), with the texture head's chart and
    uv groups after the branch's own when it carries a texture head of `charts` charts."""
    groups = HEAD_GROUPS[branch]
    if charts:
        start = BRANCH_CHANNELS[branch]
        groups = (
            *groups,
            (start, start + charts + 1),
            (start + charts + 1, start + 3 * charts + 1),
        )
    return groups


def output_names(branch: str, charts: int) -> list[str]:
    """The outputs of a branch's graph (the trunk's: features); "chart" and "uv" too when it
    carries the texture head (`charts` > 0)."""
    names = OUTPUTS[branch]
    return [*names, "chart", "uv"] if charts else names


OUTPUTS = {
    "trunk": ["features"],
    "albedo": ["albedo", "alpha"],
    "geometry": ["depth", "normal", "mask"],
    "texture": [],
}
INPUTS = {"trunk": "rig", "albedo": "features", "geometry": "features", "texture": "features"}

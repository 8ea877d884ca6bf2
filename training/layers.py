"""Building blocks both LoGDesc networks share (the paper's, training/paper_model.py, and v3's,
training/invariant_model.py): the per-edge 1x1 convolutions and the head reshapes."""

from __future__ import annotations

import torch
from torch import nn

from .config import ModelConfig


def edge_convolutions(config: ModelConfig) -> nn.Sequential:
    """(B, C, N, k) edges -> (B, W, N, k): 1x1 convolutions over ``config.descriptor_channels``,
    each followed by GroupNorm and ReLU (paper section 3.3, "Local-to-global feature
    aggregation"; a max over k follows in the descriptor)."""
    layers: list[nn.Module] = []
    channels_in = config.edge_channels
    for channels_out in config.descriptor_channels:
        # No conv bias: GroupNorm re-centres every group and adds its own learned shift.
        layers += [
            nn.Conv2d(channels_in, channels_out, kernel_size=1, bias=False),
            nn.GroupNorm(config.group_norm_groups, channels_out),
            nn.ReLU(),
        ]
        channels_in = channels_out
    return nn.Sequential(*layers)


def split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """(B, N, C) -> (B, H, N, C / H)."""
    return x.reshape(x.shape[0], x.shape[1], heads, -1).transpose(1, 2)


def merge_heads(x: torch.Tensor) -> torch.Tensor:
    """(B, H, N, C / H) -> (B, N, C)."""
    return x.transpose(1, 2).reshape(x.shape[0], x.shape[2], -1)

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


def folded_edge_convolutions(local: nn.Sequential, edges: torch.Tensor) -> torch.Tensor:
    """``local`` (from :func:`edge_convolutions`) then the max over the neighbours, with each
    GroupNorm folded into its convolution: (B, N, k, C) edges -> (B, N, W) max-pooled features.

    A convolution y = W x followed by GroupNorm is y -> a y + b with per-sample, per-channel
    a, b, and the group statistics of y follow from the input's first and second moments (mean
    w_c . m, second moment w_c^T M w_c). Each layer's input carries a column of ones, so one
    product x^T x gives both moments and one product with [a W^T; b] applies the convolution,
    the normalisation and its shift; its extra output column (weights 0, shift 1, so ReLU(1) = 1)
    is the next layer's column of ones. This avoids the normalisation's passes over the
    (B, W, N, k) tensor: in onnxruntime at 1024 points the normalisation, its scale and shift and
    the layout reorders took ~14 of the local part's ~30 ms per cloud.

    The algebra is exact; in float32 the variance E[y^2] - E[y]^2 loses ~1e-7 E[y]^2 / var(y),
    held within the export tolerance by tests/test_model.py. Export uses it; training keeps the
    layers as written, whose backward is torch's fused GroupNorm.
    """
    batch, count, neighbours, channels = edges.shape
    positions = count * neighbours
    flat = edges.reshape(batch, positions, channels)
    x = torch.cat((flat, torch.ones_like(flat[..., :1])), dim=-1)  # (B, P, C + 1)
    modules = list(local)
    pairs = list(zip(modules[0::3], modules[1::3]))
    for layer, (conv, norm) in enumerate(pairs):
        weight = conv.weight[:, :, 0, 0]  # (C_out, C_in)
        width = weight.shape[0]
        weight = torch.cat((weight, torch.zeros_like(weight[:, :1])), dim=1)  # (C_out, C_in + 1)
        moments = x.transpose(1, 2) @ x / positions  # (B, C_in + 1, C_in + 1); last row: the means
        mean_out = moments[:, -1, :] @ weight.T  # (B, C_out)
        second_out = ((weight @ moments) * weight).sum(dim=-1)  # (B, C_out): w_c^T M w_c
        groups = norm.num_groups
        group_mean = mean_out.reshape(batch, groups, -1).mean(dim=-1, keepdim=True)
        group_second = second_out.reshape(batch, groups, -1).mean(dim=-1, keepdim=True)
        group_var = (group_second - group_mean * group_mean).clamp_min(0.0)
        inverse_std = torch.rsqrt(group_var + norm.eps).expand(-1, -1, width // groups).reshape(batch, width)
        scale = inverse_std * norm.weight  # (B, C_out)
        shift = norm.bias - scale * group_mean.expand(-1, -1, width // groups).reshape(batch, width)
        applied = weight[:, :-1].T.unsqueeze(0) * scale.unsqueeze(1)  # (B, C_in, C_out)
        applied = torch.cat((applied, shift.unsqueeze(1)), dim=1)  # (B, C_in + 1, C_out)
        ones_column = torch.zeros_like(applied[..., :1])
        ones_column[:, -1] = 1.0
        x = x @ torch.cat((applied, ones_column), dim=2)  # (B, P, C_out + 1)
        if layer < len(pairs) - 1:
            x = torch.relu(x)
    # ReLU is monotone, so the last one commutes with the max over k and runs on N rows, not N k.
    pooled = torch.relu(x.reshape(batch, count, neighbours, -1).amax(dim=2))
    return pooled[..., :-1]


def heads_last(x: torch.Tensor, heads: int) -> torch.Tensor:
    """(B, N, C) -> (B, N, H, C / H): head h holds channels [h C / H, (h + 1) C / H)."""
    return x.reshape(x.shape[0], x.shape[1], heads, -1)


def split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """(B, N, C) -> (B, H, N, C / H)."""
    return heads_last(x, heads).transpose(1, 2)


def merge_heads(x: torch.Tensor) -> torch.Tensor:
    """(B, H, N, C / H) -> (B, N, C)."""
    return x.transpose(1, 2).reshape(x.shape[0], x.shape[2], -1)

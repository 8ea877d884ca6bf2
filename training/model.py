"""The matcher network in PyTorch: descriptor, transformer, matching scores and Sinkhorn with a
learned dustbin, whichever architecture the config names, and the two views export writes.

``config.architecture`` picks the networks: "invariant" (v3 / v4, :mod:`training.invariant_model`,
the bundled model's) or "logdesc" (the paper's, kept as a reference in
:mod:`training.paper_model`). Shapes are batch-first, float32: B pairs, N source points,
M target points, k neighbours, C edge channels (the geometry's layout).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .config import ModelConfig
from .invariant_model import InvariantDescriptor, InvariantTransformer
from .paper_model import LoGDescDescriptor, NormalEncoderTransformer
from .sinkhorn import log_optimal_transport

__all__ = ["DescribeModule", "LoGDescMatcher", "MatchScoresModule"]


class LoGDescMatcher(nn.Module):
    """Descriptor + normal-encoder transformer + scores + Sinkhorn with a learned dustbin.

    ``config.architecture`` picks the descriptor and transformer: the paper's
    (:class:`LoGDescDescriptor`, :class:`NormalEncoderTransformer`) or v3's invariant ones
    (:mod:`training.invariant_model`). Both take the same inputs; each ignores what it does
    not use (the paper's descriptor reads no normals, its transformer no positions).
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        if config.architecture == "invariant":
            self.descriptor = InvariantDescriptor(config)
            self.transformer = InvariantTransformer(config)
        else:
            self.descriptor = LoGDescDescriptor(config)
            self.transformer = NormalEncoderTransformer(config)
        self.dustbin_score = nn.Parameter(torch.tensor(float(config.dustbin_init)))

    @property
    def describe_inputs(self) -> tuple[str, ...]:
        """Names of the inputs :meth:`describe` reads (the exported graph's inputs)."""
        return ("edges", "points", "normals") if self.config.architecture == "invariant" else ("edges", "points")

    @property
    def match_inputs(self) -> tuple[str, ...]:
        """Names of the inputs :meth:`match_scores` reads (the exported graph's inputs)."""
        names = ("descriptors_source", "descriptors_target", "normals_source", "normals_target")
        if self.config.architecture == "invariant":
            names += ("points_source", "points_target")
        return names

    def describe(self, edges: torch.Tensor, points: torch.Tensor, normals: torch.Tensor | None = None) -> torch.Tensor:
        """(B, N, k, C) edges, (B, N, 3) positions, (B, N, 3) unit normals -> (B, N, d)
        unit-norm descriptors. The paper's descriptor needs no normals."""
        if self.config.architecture == "invariant":
            if normals is None:
                raise ValueError("the invariant descriptor needs the normals")
            return self.descriptor(edges, points, normals)
        return self.descriptor(edges, points)

    def match_scores(
        self,
        desc_src: torch.Tensor,
        desc_tgt: torch.Tensor,
        normals_src: torch.Tensor,
        normals_tgt: torch.Tensor,
        points_src: torch.Tensor | None = None,
        points_tgt: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Scores S_ij = <f_i, h_j> / sqrt(d) of the transformer outputs.

        Args:
            desc_src: (B, N, d) descriptors (from :meth:`describe`).
            desc_tgt: (B, M, d).
            normals_src: (B, N, 3) unit normals.
            normals_tgt: (B, M, 3).
            points_src, points_tgt: (B, N, 3) / (B, M, 3) positions, network units (read by
                the invariant transformer's distance terms only).

        Returns:
            (B, N, M) scores.
        """
        if self.config.architecture == "invariant":
            if points_src is None or points_tgt is None:
                raise ValueError("the invariant transformer needs the positions")
            final_src, final_tgt = self.transformer(
                desc_src, desc_tgt, normals_src, normals_tgt, points_src, points_tgt
            )
        else:
            final_src, final_tgt = self.transformer(desc_src, desc_tgt, normals_src, normals_tgt)
        return final_src @ final_tgt.transpose(1, 2) / math.sqrt(self.config.descriptor_dim)

    def forward(
        self,
        src_edges: torch.Tensor,
        src_points: torch.Tensor,
        src_normals: torch.Tensor,
        tgt_edges: torch.Tensor,
        tgt_points: torch.Tensor,
        tgt_normals: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """Match a batch of pairs.

        Args:
            src_edges: (B, N, k, C); src_points: (B, N, 3); src_normals: (B, N, 3).
            tgt_edges: (B, M, k, C); tgt_points: (B, M, 3); tgt_normals: (B, M, 3).

        Returns:
            dict with ``scores`` (B, N, M), ``log_assignment`` (B, N + 1, M + 1) (Sinkhorn,
            :func:`training.sinkhorn.log_optimal_transport`; last row / column = dustbin),
            ``descriptors_src`` (B, N, d) and ``descriptors_tgt`` (B, M, d): the unit-norm
            LoGDesc descriptors before the transformer (for an auxiliary loss).
        """
        desc_src = self.describe(src_edges, src_points, src_normals)
        desc_tgt = self.describe(tgt_edges, tgt_points, tgt_normals)
        scores = self.match_scores(desc_src, desc_tgt, src_normals, tgt_normals, src_points, tgt_points)
        log_assignment = log_optimal_transport(
            scores, self.dustbin_score, self.config.sinkhorn_iterations
        )
        return {
            "scores": scores,
            "log_assignment": log_assignment,
            "descriptors_src": desc_src,
            "descriptors_tgt": desc_tgt,
        }


class DescribeModule(nn.Module):
    """Export view of :meth:`LoGDescMatcher.describe`: forward(*inputs) -> descriptors, the
    inputs named by ``matcher.describe_inputs``."""

    def __init__(self, matcher: LoGDescMatcher) -> None:
        super().__init__()
        self.matcher = matcher

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.matcher.describe(*inputs)


class MatchScoresModule(nn.Module):
    """Export view of :meth:`LoGDescMatcher.match_scores` (Sinkhorn runs in the runtime), the
    inputs named by ``matcher.match_inputs``."""

    def __init__(self, matcher: LoGDescMatcher) -> None:
        super().__init__()
        self.matcher = matcher

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.matcher.match_scores(*inputs)

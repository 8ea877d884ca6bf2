"""The v3 network: LoGDesc made invariant to rigid motion by construction, in matmul form.

The paper's network sees absolute coordinates twice: in the edge features and in the rotary
position encoding of the descriptor's attention. Its outputs therefore change when a cloud
turns, and training on rotated pairs only teaches it to tolerate that approximately. Here the
inputs are the invariant edges of :mod:`logdesc_rt.geometry.invariant_features`, and every
attention layer meets geometry only through quantities that do not change under rotation and
translation, evaluated as extra query / key channels, so that they are part of the one
Q K^T product (no N x N x d tensor, no N x N gather or integer index in the exported graph):

- **distance bias** (:func:`distance_channels`): per head, -w_h |x_i - x_j|^2 with a learned
  w_h > 0. With q = [-|x_i|^2, -1, 2 x_i] and k = [1, |x_j|^2, x_j] (5 channels),
  q . k = -|x_i - x_j|^2 exactly; each head learns its own locality (ALiBi-like, in 3D).
- **normal term** (:func:`normal_channels`): a query-dependent even polynomial
  a2_h(i) (n_i . n_j)^2 + a4_h(i) (n_i . n_j)^4. (n_i . n_j)^p is the inner product of the
  degree-p monomial vectors of n_i and n_j (weighted by the square roots of the multinomial
  coefficients): 6 + 15 channels. Even powers make the term independent of the normals'
  signs, which no local rule can fix reliably. This replaces RoCNet's sinusoidal
  angle embedding (the paper's normal-encoder term), which needed an N x N angle lookup.
- **cross attention with one logit matrix** (:class:`BidirectionalCrossLayer`): source and
  target share the query / key projection, so the source -> target logits are the transpose of
  the target -> source ones and are computed once (LightGlue's bidirectional cross-attention).

Shapes are batch-first float32: B pairs, N / M points, k neighbours, C edge channels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .config import ModelConfig
from .layers import edge_convolutions, folded_edge_convolutions, heads_last, merge_heads, split_heads
from .losses import INFONCE_TEMPERATURE


def _monomials(power: int) -> tuple[list[tuple[int, int, int]], torch.Tensor]:
    """Exponents alpha with |alpha| = ``power`` and the square roots of their multinomial
    coefficients p! / alpha!, so that sum_alpha (w_alpha n^alpha)(w_alpha m^alpha) = (n . m)^p."""
    exponents = [(a, b, power - a - b) for a in range(power + 1) for b in range(power + 1 - a)]
    weights = [math.sqrt(math.factorial(power) / math.prod(math.factorial(e) for e in alpha)) for alpha in exponents]
    return exponents, torch.tensor(weights)


# Built once at import: the normal channels of every layer and call read these constants.
_MONOMIALS_2 = _monomials(2)  # 6 channels
_MONOMIALS_4 = _monomials(4)  # 15 channels


def distance_channels(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Query and key channels whose inner product is minus the squared distance.

    Args:
        points: (B, N, 3) positions, network units (centred, so |x| ~ 1 and the expansion
            loses nothing in float32).

    Returns:
        query_part, key_part: each (B, N, 5), with query_part[i] . key_part[j] =
        -|x_i - x_j|^2.
    """
    squared = (points * points).sum(dim=-1, keepdim=True)
    ones = torch.ones_like(squared)
    query_part = torch.cat((-squared, -ones, 2.0 * points), dim=-1)
    key_part = torch.cat((ones, squared, points), dim=-1)
    return query_part, key_part


def normal_channels(normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted monomials of the normals: (n_i . n_j)^p as an inner product, p = 2 and 4.

    Args:
        normals: (B, N, 3) unit normals (any signs).

    Returns:
        degree2: (B, N, 6) with degree2[i] . degree2[j] = (n_i . n_j)^2.
        degree4: (B, N, 15) with degree4[i] . degree4[j] = (n_i . n_j)^4.
    """

    def monomials(exponents: list[tuple[int, int, int]], weights: torch.Tensor) -> torch.Tensor:
        columns = [
            normals[..., 0] ** a * normals[..., 1] ** b * normals[..., 2] ** c for a, b, c in exponents
        ]
        return torch.stack(columns, dim=-1) * weights.to(normals)

    return monomials(*_MONOMIALS_2), monomials(*_MONOMIALS_4)


class _ExportedAttention(torch.autograd.Function):
    """softmax(Q K^T) V per head, exported as onnxruntime's fused CPU kernel.

    In torch it is plain scaled-dot-product attention (scale 1: queries come pre-scaled). In
    an ONNX export it becomes one ``com.microsoft.MultiHeadAttention`` node, which computes
    head by head without the several (B, H, N, M) logit / probability tensors that separate
    MatMul and Softmax nodes leave alive at once (at 4096 points that is the difference
    between ~1.4 GB and a few hundred MB). Queries and keys may be wider than values.
    """

    @staticmethod
    def forward(ctx, query, key, value, heads: int):  # noqa: ARG004 (ctx: export-only, no backward)
        """query (B, N, H dq), key (B, M, H dq), value (B, M, H dv) -> (B, N, H dv)."""
        attended = F.scaled_dot_product_attention(
            split_heads(query, heads), split_heads(key, heads), split_heads(value, heads), scale=1.0
        )
        return merge_heads(attended)

    @staticmethod
    def symbolic(graph, query, key, value, heads: int):
        return graph.op("com.microsoft::MultiHeadAttention", query, key, value, num_heads_i=heads, scale_f=1.0)


def attend(query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, heads: int) -> torch.Tensor:
    """softmax_j(q_i . k_j) v_j per head, queries pre-scaled, heads-last:
    (B, N, H, dq), (B, M, H, dq), (B, M, H, dv) -> (B, N, H dv); ``heads`` = H as a Python int
    (an exported graph's shapes are traced tensors).

    Heads-last is the fused kernel's own layout (:class:`_ExportedAttention`, whose inputs are
    the heads side by side), so the exported graphs reshape into it without transposing; torch's
    kernel reads the same tensors as (B, H, N, d) views."""
    if torch.onnx.is_in_onnx_export():
        return _ExportedAttention.apply(query.flatten(2), key.flatten(2), value.flatten(2), heads)
    query, key, value = query.transpose(1, 2), key.transpose(1, 2), value.transpose(1, 2)
    value_width, query_width = value.shape[-1], query.shape[-1]
    if value_width < query_width:
        # torch's fused (flash) kernels need one head width for q, k and v; without it SDPA falls
        # back to the math path, which holds the (B, H, N, M) probabilities for backward. Zero
        # columns of v change nothing but cost far less: one training step on the CPU went from
        # ~0.7 s to ~0.4 s per attention pass (8 x 768 points, 4 heads of 50 / 24 channels).
        value = F.pad(value, (0, query_width - value_width))
        attended = F.scaled_dot_product_attention(query, key, value, scale=1.0)[..., :value_width]
    else:
        attended = F.scaled_dot_product_attention(query, key, value, scale=1.0)
    return merge_heads(attended)


class _Update(nn.Module):
    """LoGDesc's residual update: x <- x + LayerNorm(MLP([x, LayerNorm(merge(message))]))."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.merge = nn.Linear(width, width, bias=False)
        self.message_norm = nn.LayerNorm(width)
        self.mlp = nn.Sequential(nn.Linear(2 * width, 2 * width), nn.ReLU(), nn.Linear(2 * width, width))
        self.update_norm = nn.LayerNorm(width)

    def forward(self, x: torch.Tensor, attended: torch.Tensor) -> torch.Tensor:
        """x: (B, N, w); attended: (B, N, w), the heads side by side -> (B, N, w)."""
        message = self.message_norm(self.merge(attended))
        return x + self.update_norm(self.mlp(torch.cat((x, message), dim=-1)))


class GeometricSelfLayer(nn.Module):
    """Self-attention whose logits add an invariant distance bias and normal term.

        logit_ij^h = q_i^h . k_j^h / sqrt(d_h) - w_h |x_i - x_j|^2
                     + a2_h(i) (n_i . n_j)^2 + a4_h(i) (n_i . n_j)^4

    all as one product of (d_h + 5 + 21)-channel queries and keys per head.

    Args:
        width: feature width w.
        heads: attention heads H (w % H == 0).
        locality_range: the heads' initial w_h are spread log-uniformly so that
            1 / sqrt(w_h) (the distance at which the bias reaches -1) spans this range, in
            network units; training moves them.
    """

    def __init__(self, width: int, heads: int, locality_range: tuple[float, float] = (0.05, 1.0)) -> None:
        super().__init__()
        if width % heads:
            raise ValueError(f"width {width} not divisible by heads {heads}")
        self.heads, self.head_dim = heads, width // heads
        self.query = nn.Linear(width, width, bias=False)
        self.key = nn.Linear(width, width, bias=False)
        self.value = nn.Linear(width, width, bias=False)
        reach = torch.logspace(math.log10(locality_range[0]), math.log10(locality_range[1]), heads)
        self.log_locality = nn.Parameter(-2.0 * torch.log(reach))  # w_h = exp(.) = 1 / reach^2
        self.normal_coefficients = nn.Linear(width, 2 * heads)  # a2_h(i), a4_h(i)
        nn.init.zeros_(self.normal_coefficients.weight)
        nn.init.zeros_(self.normal_coefficients.bias)
        self.update = _Update(width)

    def forward(
        self,
        x: torch.Tensor,
        distance_parts: tuple[torch.Tensor, torch.Tensor],
        normal_parts: tuple[torch.Tensor, torch.Tensor],
    ) -> torch.Tensor:
        """Update ``x`` (B, N, w) by attending to itself.

        Args:
            distance_parts: from :func:`distance_channels`, each (B, N, 5).
            normal_parts: from :func:`normal_channels`, (B, N, 6) and (B, N, 15).
        """
        batch, count, heads = x.shape[0], x.shape[1], self.heads
        query = heads_last(self.query(x), heads) * (1.0 / math.sqrt(self.head_dim))  # (B, N, H, d)
        key = heads_last(self.key(x), heads)
        value = heads_last(self.value(x), heads)

        distance_query, distance_key = distance_parts  # (B, N, 5)
        locality = torch.exp(self.log_locality).reshape(1, 1, heads, 1)
        degree2, degree4 = normal_parts
        coefficients = self.normal_coefficients(x).reshape(batch, count, heads, 2)
        query = torch.cat(
            (
                query,
                locality * distance_query.unsqueeze(2),
                coefficients[..., 0:1] * degree2.unsqueeze(2),
                coefficients[..., 1:2] * degree4.unsqueeze(2),
            ),
            dim=-1,
        )
        geometry_key = torch.cat((distance_key, degree2, degree4), dim=-1).unsqueeze(2)
        key = torch.cat((key, geometry_key.expand(batch, count, heads, -1)), dim=-1)
        return self.update(x, attend(query, key, value, heads))


class BidirectionalCrossLayer(nn.Module):
    """Cross-attention both ways from one logit matrix (shared query / key projection).

        S = (P x_src)(P x_tgt)^T / sqrt(d_h) per head, (B, H, N, M)
        src <- src + update(softmax_rows(S) V x_tgt),  tgt <- tgt + update(softmax_cols(S)^T V x_src)

    One update module serves both clouds, as the paper shares a layer's weights between them.
    """

    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        if width % heads:
            raise ValueError(f"width {width} not divisible by heads {heads}")
        self.heads, self.head_dim = heads, width // heads
        self.query_key = nn.Linear(width, width, bias=False)
        self.value = nn.Linear(width, width, bias=False)
        self.update = _Update(width)

    def forward(self, source: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, N, w), (B, M, w) -> updated (B, N, w), (B, M, w)."""
        source_qk, source_value = self._projections(source)
        target_qk, target_value = self._projections(target)
        # The fused kernel once per direction (softmax_cols(S)^T is the row softmax of S^T): twice
        # the Q K^T work of one shared S, but no (B, H, N, M) tensor outlives its kernel, which
        # made it 2.4x faster than the shared-S form in training on the CPU (forward + backward).
        source_message = self._message(source_qk, target_qk, target_value)
        target_message = self._message(target_qk, source_qk, source_value)
        return self.update(source, source_message), self.update(target, target_message)

    def stacked(self, both: torch.Tensor, batch: int) -> torch.Tensor:
        """:meth:`forward` of two clouds of one size stacked in one batch: (2B, N, w) -> (2B, N, w),
        the sources first (``batch`` = B), each attending to its partner B rows away."""
        qk, value = self._projections(both)
        partner = lambda tensor: torch.cat((tensor[batch:], tensor[:batch]))  # noqa: E731
        return self.update(both, self._message(qk, partner(qk), partner(value)))

    def _projections(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, N, w) -> the shared query / key and the values, each (B, N, H, w / H)."""
        return heads_last(self.query_key(x), self.heads), heads_last(self.value(x), self.heads)

    def _message(self, qk: torch.Tensor, other_qk: torch.Tensor, other_value: torch.Tensor) -> torch.Tensor:
        """What each point of one cloud gathers from the other: (B, N, w), the heads side by side."""
        return attend(qk * (1.0 / math.sqrt(self.head_dim)), other_qk, other_value, self.heads)


class InvariantDescriptor(nn.Module):
    """(B, N, k, C) invariant edges -> 1x1 convolutions + GroupNorm + ReLU -> max over k
    -> geometric self-attention layers -> projection -> L2 normalisation, (B, N, d)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.local = edge_convolutions(config)
        width = config.attention_width
        self.layers = nn.ModuleList(
            GeometricSelfLayer(width, config.descriptor_heads, locality_range=(0.05, 0.5))
            for _ in range(config.descriptor_attention_layers)
        )
        self.projection = nn.Linear(width, config.descriptor_dim)

    def forward(self, edges: torch.Tensor, points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """edges (B, N, k, C), points (B, N, 3), normals (B, N, 3) -> (B, N, d) unit-norm descriptors."""
        if torch.onnx.is_in_onnx_export():
            # The same function with the GroupNorms folded into the convolutions: fewer passes
            # over the (B, N, k, W) tensor in onnxruntime (training.layers.folded_edge_convolutions).
            features = folded_edge_convolutions(self.local, edges)  # (B, N, W)
        else:
            features = self.local(edges.permute(0, 3, 1, 2)).amax(dim=3).transpose(1, 2)  # (B, N, W)
        distance_parts, normal_parts = geometric_parts(points, normals)
        for layer in self.layers:
            features = layer(features, distance_parts, normal_parts)
        return F.normalize(self.projection(features), dim=-1)


DESCRIPTOR_ONLY_TEMPERATURE = INFONCE_TEMPERATURE
"""Score per unit of descriptor cosine, inverted, at the start of a descriptor-only model
(``transformer_layers == 0``): the auxiliary InfoNCE's default temperature."""


class InvariantTransformer(nn.Module):
    """``transformer_layers`` pairs of (geometric self, bidirectional cross) layers at width d,
    then a final linear d -> d (the normal-encoder transformer's role, made invariant).

    With no layers the network matches by its descriptors alone: the final linear map is then
    all that stands between the descriptors and the scores."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        dim, heads = config.descriptor_dim, config.transformer_heads
        self.self_layers = nn.ModuleList(
            GeometricSelfLayer(dim, heads, locality_range=(0.1, 2.0)) for _ in range(config.transformer_layers)
        )
        self.cross_layers = nn.ModuleList(
            BidirectionalCrossLayer(dim, heads) for _ in range(config.transformer_layers)
        )
        self.projection = nn.Linear(dim, dim)
        if config.transformer_layers == 0:
            # Descriptor-only matching (the scores are a learned bilinear form of the unit
            # descriptors): start at s I with s^2 / sqrt(d) = 1 / DESCRIPTOR_ONLY_TEMPERATURE, so
            # that the first scores are the cosines over the auxiliary InfoNCE's temperature. A
            # random d x d start gives scores ~0.1 that Sinkhorn spreads flat over all points.
            scale = math.sqrt(math.sqrt(dim) / DESCRIPTOR_ONLY_TEMPERATURE)
            with torch.no_grad():
                self.projection.weight.copy_(scale * torch.eye(dim))
                self.projection.bias.zero_()

    def forward(
        self,
        desc_src: torch.Tensor,
        desc_tgt: torch.Tensor,
        normals_src: torch.Tensor,
        normals_tgt: torch.Tensor,
        points_src: torch.Tensor,
        points_tgt: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, N, d), (B, M, d) descriptors with their normals and positions -> (B, N, d), (B, M, d).

        An ONNX export traced with clouds of one size (N = M) records :meth:`stacked_forward`
        instead (``matcher_same_size.onnx``); torch itself runs the clouds one at a time, which
        trains ~5 % faster on the CPU.
        """
        if torch.onnx.is_in_onnx_export() and desc_src.shape[1] == desc_tgt.shape[1]:
            return self.stacked_forward(desc_src, desc_tgt, normals_src, normals_tgt, points_src, points_tgt)
        parts_src = geometric_parts(points_src, normals_src)
        parts_tgt = geometric_parts(points_tgt, normals_tgt)
        src, tgt = desc_src, desc_tgt
        for self_layer, cross_layer in zip(self.self_layers, self.cross_layers):
            src = self_layer(src, *parts_src)
            tgt = self_layer(tgt, *parts_tgt)
            src, tgt = cross_layer(src, tgt)
        return self.projection(src), self.projection(tgt)

    def stacked_forward(
        self,
        desc_src: torch.Tensor,
        desc_tgt: torch.Tensor,
        normals_src: torch.Tensor,
        normals_tgt: torch.Tensor,
        points_src: torch.Tensor,
        points_tgt: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` of two clouds of one size (N = M), stacked in one batch of 2B through
        every layer: the same function in half the operator calls, which runs ~8 % faster in
        onnxruntime at 384 points than the two clouds one after the other."""
        batch = desc_src.shape[0]
        parts = geometric_parts(torch.cat((points_src, points_tgt)), torch.cat((normals_src, normals_tgt)))
        both = torch.cat((desc_src, desc_tgt))
        for self_layer, cross_layer in zip(self.self_layers, self.cross_layers):
            both = cross_layer.stacked(self_layer(both, *parts), batch)
        both = self.projection(both)
        return both[:batch], both[batch:]


def geometric_parts(points: torch.Tensor, normals: torch.Tensor):
    """The distance and normal channels of one cloud, computed once for all its layers.

    Inputs are geometry, not learned: no gradient flows into them, and they stay float32 under
    autocast (the distance expansion cancels large terms).
    """
    with torch.autocast(device_type=points.device.type, enabled=False):
        points, normals = points.detach().float(), normals.detach().float()
        return distance_channels(points), normal_channels(normals)

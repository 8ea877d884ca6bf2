"""Reference only: the paper's LoGDesc architecture in PyTorch (the descriptor with a 3D rotary
encoding of absolute positions, RoCNet's normal-angle transformer).

No bundled model uses it: it is kept to load and evaluate checkpoints of the paper's
architecture (presets ``small`` and ``paper``) and for the contrast tests that show what the
invariant network's invariance by construction changes (``tests/test_invariance.py``:
these networks' outputs change when a cloud turns). New work goes to
:mod:`training.invariant_model`. :class:`training.model.LoGDescMatcher` builds these networks
for ``config.architecture == "logdesc"``.

Shapes are batch-first, float32: B pairs, N source points, M target points, k neighbours.
Inputs come from :func:`logdesc_rt.geometry.compute_geometry` with the paper geometry
(:data:`logdesc_rt.config.PAPER_GEOMETRY`): the (N, k, 15) edge features, the (N, 3)
positions and the (N, 3) unit normals.

Everything here exports with ``torch.onnx.export``: no Python control flow on tensor values,
no in-place updates of tensors that need gradients, and no N x N x d tensor anywhere (the
normal-angle attention term, which the official code builds as an N x N x d embedding, is
evaluated through a per-head angle table; see :class:`NormalAngleBias`). The largest tensors
are (B, H, N, M) attention logits.

Note on batching: GroupNorm in the descriptor normalises over all points and neighbours of a
cloud, so a batch must hold real clouds, not zero-padded ones (pad by resampling points).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .config import ModelConfig
from .layers import edge_convolutions, merge_heads, split_heads

__all__ = [
    "AttentionalLayer",
    "LoGDescDescriptor",
    "NormalAngleBias",
    "NormalEncoderTransformer",
    "RotaryEncoding3D",
    "normal_angle_embedding",
    "normal_angle_frequencies",
    "normal_angle_lookup",
    "normal_angle_term_direct",
    "normal_angle_table",
    "normal_angles",
]


# --------------------------------------------------------------------------------------------
# 3D rotary position encoding
# --------------------------------------------------------------------------------------------


class RotaryEncoding3D(nn.Module):
    """The block-diagonal rotation R(x) of the paper's equation 9 (Lepard / RoFormer, in 3D).

    Channels are taken in pairs; pair p = 3 (j - 1) + a (a = 0, 1, 2 for the x, y, z axis,
    j = 1 .. W / 6) is rotated by the angle ``position[a] * scale * theta_j`` with
    ``theta_j = 1 / base^(6 (j - 1) / W)``. So each consecutive block of 6 channels is the 6 x 6
    block R^j of the paper. For two points, (R(x_i) q) . (R(x_j) k) = q . R(x_j - x_i) k: the
    encoding makes query-key products depend on relative positions only.
    """

    def __init__(self, width: int, base: float, position_scale: float) -> None:
        super().__init__()
        if width % 6:
            raise ValueError(f"rotary width must be divisible by 6, got {width}")
        pairs = width // 2
        block = torch.arange(pairs) // 3  # j - 1
        axis = torch.arange(pairs) % 3
        theta = base ** (-6.0 * block.double() / width)
        # angles = positions @ frequency: one non-zero per column, so the product is exact.
        frequency = torch.zeros(3, pairs, dtype=torch.float64)
        frequency[axis, torch.arange(pairs)] = theta * position_scale
        self.register_buffer("frequency", frequency.float(), persistent=False)
        self.width = width

    def angles(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, N, 3) positions -> (cos, sin), each (B, N, W / 2)."""
        # float32 even under autocast: angles reach ~10 rad, far beyond bf16's resolution.
        with torch.autocast(device_type=points.device.type, enabled=False):
            angle = points.float() @ self.frequency
            return torch.cos(angle), torch.sin(angle)

    @staticmethod
    def rotate(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        """Rotate the channel pairs of ``x`` (B, N, W) by the angles of ``cos``/``sin`` (B, N, W/2)."""
        pairs = x.reshape(x.shape[0], x.shape[1], -1, 2)
        even, odd = pairs[..., 0], pairs[..., 1]
        rotated = torch.stack((even * cos - odd * sin, even * sin + odd * cos), dim=-1)
        return rotated.reshape(x.shape)


# --------------------------------------------------------------------------------------------
# Attention layer shared by the descriptor and the transformer
# --------------------------------------------------------------------------------------------


class AttentionalLayer(nn.Module):
    """One attention layer with the LoGDesc residual structure.

        message = LayerNorm(merge(MultiHeadAttention(q = W_q x, k = W_k s, v = W_v s)))
        x <- x + LayerNorm(MLP([x, message])),   MLP: 2w -> 2w -> w (ReLU)

    with bias-free q/k/v/merge projections; ``s`` is ``x`` itself (self-attention) or the
    other cloud (cross-attention). The layer returns the update ``x_new`` (residual included).
    Optional extras: a rotary encoding of q/k/v (descriptor, ``rotary_mode="per_layer"``) and an
    additive per-head logit term computed from the queries (the normal-angle term).
    """

    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        if width % heads:
            raise ValueError(f"width {width} not divisible by heads {heads}")
        self.width = width
        self.heads = heads
        self.head_dim = width // heads
        self.query = nn.Linear(width, width, bias=False)
        self.key = nn.Linear(width, width, bias=False)
        self.value = nn.Linear(width, width, bias=False)
        self.merge = nn.Linear(width, width, bias=False)
        self.message_norm = nn.LayerNorm(width)
        self.mlp = nn.Sequential(
            nn.Linear(2 * width, 2 * width), nn.ReLU(), nn.Linear(2 * width, width)
        )
        self.update_norm = nn.LayerNorm(width)

    def forward(
        self,
        x: torch.Tensor,
        source: torch.Tensor,
        rotary: tuple[torch.Tensor, torch.Tensor] | None = None,
        logit_term: "NormalAngleBias | None" = None,
        lookup: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Update ``x`` by attending to ``source``.

        Args:
            x: (B, N, w) features being updated (queries).
            source: (B, M, w) features attended to (keys, values); ``x`` for self-attention.
            rotary: (cos, sin), each (B, N, w / 2): rotate q, k and v by R(position). Only for
                self-attention (N == M, same positions).
            logit_term: a :class:`NormalAngleBias` adding (q_i . p_ij) to the logits; needs
                ``lookup`` from :func:`normal_angle_lookup`. Only for self-attention.
            lookup: (lower bin (B, H, N, N), fraction (B, 1, N, N)) from
                :func:`normal_angle_lookup`.

        Returns:
            (B, N, w) updated features.
        """
        query, key, value = self.query(x), self.key(source), self.value(source)
        if rotary is not None:
            cos, sin = rotary
            query = RotaryEncoding3D.rotate(query, cos, sin)
            key = RotaryEncoding3D.rotate(key, cos, sin)
            value = RotaryEncoding3D.rotate(value, cos, sin)
        query = split_heads(query, self.heads)
        key = split_heads(key, self.heads)
        value = split_heads(value, self.heads)
        if logit_term is None:
            attended = F.scaled_dot_product_attention(query, key, value)
        else:
            if lookup is None:
                raise ValueError("logit_term needs the normal-angle lookup")
            attended = self._attend_with_term(query, key, value, logit_term, lookup)
        message = self.message_norm(self.merge(merge_heads(attended)))
        return x + self.update_norm(self.mlp(torch.cat((x, message), dim=-1)))


    def _attend_with_term(
        self,
        query: torch.Tensor,
        key: torch.Tensor,
        value: torch.Tensor,
        logit_term: "NormalAngleBias",
        lookup: tuple[torch.Tensor, torch.Tensor],
    ) -> torch.Tensor:
        """softmax_j((q_i . k_j + q_i . p_ij) / sqrt(d_head)) v_j, all (B, H, N, d_head).

        Written out rather than through SDPA with a float mask: the term is added inside one
        fused ``baddbmm`` and the softmax needs no masked-row handling, which is measurably
        cheaper on the CPU for (B, H, N, N) logits that require gradients.
        """
        batch, heads, count = query.shape[0], query.shape[1], query.shape[2]
        head_dim = self.head_dim  # a Python int: a constant in an exported graph
        scale = 1.0 / math.sqrt(head_dim)
        term = logit_term(query, lookup, scale=scale)  # (B, H, N, N), already scaled
        logits = torch.baddbmm(
            term.reshape(batch * heads, count, -1),
            query.reshape(batch * heads, count, head_dim),
            key.reshape(batch * heads, -1, head_dim).transpose(1, 2),
            alpha=scale,
        )
        weights = torch.softmax(logits, dim=-1)
        attended = weights @ value.reshape(batch * heads, -1, head_dim)
        return attended.reshape(batch, heads, count, head_dim)


# --------------------------------------------------------------------------------------------
# Descriptor
# --------------------------------------------------------------------------------------------


class LoGDescDescriptor(nn.Module):
    """The LoGDesc descriptor (paper section 3.3, "Local-to-global feature aggregation").

    (B, N, k, 15) edges -> 1x1 convolutions, each + GroupNorm + ReLU -> max over k -> (B, N, W)
    -> ``descriptor_attention_layers`` self-attention layers with the 3D rotary encoding of the
    positions -> 1x1 projection W -> d -> L2 normalisation.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.local = edge_convolutions(config)
        width = config.attention_width
        self.rotary = RotaryEncoding3D(width, config.rotary_base, config.rotary_position_scale)
        self.layers = nn.ModuleList(
            AttentionalLayer(width, config.descriptor_heads)
            for _ in range(config.descriptor_attention_layers)
        )
        self.projection = nn.Linear(width, config.descriptor_dim)

    def forward(self, edges: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Describe every point of a batch of clouds.

        Args:
            edges: (B, N, k, 15) edge features (:mod:`logdesc_rt.geometry.edge_features`).
            points: (B, N, 3) positions, network units (for the rotary encoding).

        Returns:
            (B, N, d) unit-norm descriptors.
        """
        x = self.local(edges.permute(0, 3, 1, 2))  # (B, C, N, k)
        features = x.amax(dim=3).transpose(1, 2)  # (B, N, W)
        cos, sin = self.rotary.angles(points)
        if self.config.rotary_mode == "once":
            features = RotaryEncoding3D.rotate(features, cos, sin)
            rotary = None
        else:
            rotary = (cos, sin)
        for layer in self.layers:
            features = layer(features, features, rotary=rotary)
        return F.normalize(self.projection(features), dim=-1)


# --------------------------------------------------------------------------------------------
# Normal-angle attention term
# --------------------------------------------------------------------------------------------


def normal_angle_frequencies(dim: int, sigma: float, base: float) -> torch.Tensor:
    """(dim / 2,) float64 angular frequencies 1 / (sigma u^(2p / dim)), p = 0 .. dim/2 - 1."""
    p = torch.arange(dim // 2, dtype=torch.float64)
    return 1.0 / (sigma * base ** (2.0 * p / dim))


def normal_angle_embedding(angle: torch.Tensor, dim: int, sigma: float, base: float) -> torch.Tensor:
    """RoCNet's sinusoidal embedding r of angles: (...,) -> (..., dim).

    r^(2p) = sin(angle / (sigma u^(2p/dim))), r^(2p+1) = cos(...), interleaved.
    """
    frequency = normal_angle_frequencies(dim, sigma, base).to(angle)
    phase = angle.unsqueeze(-1) * frequency
    return torch.stack((torch.sin(phase), torch.cos(phase)), dim=-1).flatten(-2)


def normal_angle_table(dim: int, sigma: float, base: float, bins: int) -> torch.Tensor:
    """(dim, bins) float32: r(theta_b) for theta_b = pi b / (bins - 1), b = 0 .. bins - 1."""
    angles = torch.linspace(0.0, math.pi, bins, dtype=torch.float64)
    return normal_angle_embedding(angles, dim, sigma, base).T.float().contiguous()


def normal_angles(normals: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) unit normals -> (B, N, N) angles in [0, pi] between every pair.

    Normals are inputs (no gradient is wanted through them; arccos has an infinite slope at 0).
    """
    # float32 even under autocast: a bf16 cosine near 1 would put the angle off by ~0.1 rad.
    with torch.autocast(device_type=normals.device.type, enabled=False):
        normals = normals.detach().float()
        cosine = torch.clamp(normals @ normals.transpose(1, 2), -1.0, 1.0)
        return torch.acos(cosine)


def normal_angle_lookup(
    normals: torch.Tensor, bins: int, heads: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each pair's angle falls in the ``bins``-entry table over [0, pi].

    Args:
        normals: (B, N, 3) unit normals.
        bins: table size.
        heads: attention heads that share the lookup.

    Returns:
        lower: (B, H, N, N) int64, the lower bin, in [0, bins - 2]: a stride-0 view over
            heads in torch; built once per cloud so that ONNX materialises it once, not per layer.
        fraction: (B, 1, N, N) float, the position between ``lower`` and ``lower + 1``, in [0, 1].
    """
    position = normal_angles(normals) * ((bins - 1) / math.pi)
    lower = torch.clamp(torch.floor(position), 0.0, float(bins - 2))
    fraction = (position - lower).unsqueeze(1)
    batch, count = lower.shape[0], lower.shape[1]
    return lower.long().unsqueeze(1).expand(batch, heads, count, count), fraction


class NormalAngleBias(nn.Module):
    """The normal-angle term q_i . p_ij of a self layer, without any N x N x d tensor.

    RoCNet / LoGDesc: p_ij = W r_ij + b (W: d x d, b: d), r_ij the sinusoidal embedding of the
    angle theta_ij between n_i and n_j, split per head as p_ij^h = W_h r_ij + b_h (W_h the head's
    d/H rows of W). The term is linear in r_ij:

        q_i^h . p_ij^h = (W_h^T q_i^h) . r(theta_ij) + q_i^h . b_h
                       = q_i^h . [W_h r(theta_ij) + b_h],

    and r depends on theta_ij in [0, pi] only. So the (d/H, bins) per-head table
    T_h = W_h R + b_h 1^T (R: the (d, bins) sinusoid table) is built once per call, one matmul
    gives a_i^h(theta_b) = q_i^h . T_h[:, b] for every bin, (B, H, N, bins), and the term at
    theta_ij is the linear interpolation of that row between the two nearest bins: value and
    slope gathered at the lower bin, with one index shared by all heads and layers (see
    :func:`normal_angle_lookup`).
    Interpolating b_h's contribution is exact (it is constant over the bins); the sinusoids'
    interpolation error is at most |a| (omega h)^2 / 8 with omega = 1/sigma the fastest
    frequency and h = pi / (bins - 1): ~2e-5 of the term's scale for 1024 bins, ~3e-4 for 256.
    Cost per self layer: B N d bins multiply-adds and O(B H N^2) memory traffic, versus
    B N^2 d^2 multiply-adds and a B N^2 d tensor for the direct form.
    """

    def __init__(self, dim: int, heads: int, sigma: float, base: float, bins: int) -> None:
        super().__init__()
        self.dim, self.heads, self.bins = dim, heads, bins
        self.sigma, self.base = sigma, base
        self.linear = nn.Linear(dim, dim)  # p = W r + b, per layer
        self.register_buffer("table", normal_angle_table(dim, sigma, base, bins), persistent=False)

    def head_tables(self) -> torch.Tensor:
        """(H, d/H, bins): T_h = W_h R + b_h."""
        weight = self.linear.weight.reshape(self.heads, -1, self.dim)  # (H, d/H, d)
        bias = self.linear.bias.reshape(self.heads, -1, 1)
        return weight @ self.table + bias

    def forward(
        self,
        query: torch.Tensor,
        lookup: tuple[torch.Tensor, torch.Tensor],
        scale: float = 1.0,
    ) -> torch.Tensor:
        """The term ``scale * q_i^h . p_ij^h``.

        Args:
            query: (B, H, N, d/H) per-head queries.
            lookup: (lower, fraction) from :func:`normal_angle_lookup`.
            scale: folded into the small table rather than applied to the (B, H, N, N) result
                (the attention passes 1 / sqrt(d/H)).

        Returns:
            (B, H, N, N).
        """
        lower, fraction = lookup
        per_bin = query @ (self.head_tables() * scale)  # (B, H, N, bins)
        slope = per_bin[..., 1:] - per_bin[..., :-1]  # (B, H, N, bins - 1)
        # value + fraction * slope: plain arithmetic rather than torch.lerp, whose ONNX export
        # is a full-size Where over (B, H, N, N) (half of the CPU matcher's time).
        at_lower = torch.gather(per_bin, 3, lower)
        return at_lower + fraction.to(at_lower.dtype) * torch.gather(slope, 3, lower)


def normal_angle_term_direct(
    query: torch.Tensor, normals: torch.Tensor, bias_module: NormalAngleBias
) -> torch.Tensor:
    """Reference for tests only: the same term with the full (B, N, N, d) embedding.

    Args:
        query: (B, H, N, d/H).
        normals: (B, N, 3) unit normals.
        bias_module: supplies W, b and the sinusoid constants.

    Returns:
        (B, H, N, N) q_i^h . (W r_ij + b)^h, the way the official code computes it.
    """
    angles = normal_angles(normals)
    embedding = normal_angle_embedding(angles, bias_module.dim, bias_module.sigma, bias_module.base)
    projected = bias_module.linear(embedding)  # (B, N, N, d)
    b, n = projected.shape[:2]
    projected = projected.reshape(b, n, n, bias_module.heads, -1)  # (B, N, N, H, d/H)
    return torch.einsum("bhic,bijhc->bhij", query, projected)


# --------------------------------------------------------------------------------------------
# Normal-encoder transformer
# --------------------------------------------------------------------------------------------


class NormalEncoderTransformer(nn.Module):
    """RoCNet's normal-encoder transformer (paper section 3.2.2) and the final projection.

    ``transformer_layers`` pairs of (self, cross) :class:`AttentionalLayer`s at width d. Self
    layers add the normal-angle term of :class:`NormalAngleBias` to their logits; cross layers
    are plain attention and update both clouds from the same pre-layer features (SuperGlue).
    A layer's weights are shared between the source and the target. Then a final linear d -> d.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        dim, heads = config.descriptor_dim, config.transformer_heads
        sigma = math.radians(config.normal_angle_sigma_deg)
        self.self_layers = nn.ModuleList(
            AttentionalLayer(dim, heads) for _ in range(config.transformer_layers)
        )
        self.normal_terms = nn.ModuleList(
            NormalAngleBias(dim, heads, sigma, config.normal_angle_base, config.normal_angle_bins)
            for _ in range(config.transformer_layers)
        )
        self.cross_layers = nn.ModuleList(
            AttentionalLayer(dim, heads) for _ in range(config.transformer_layers)
        )
        self.projection = nn.Linear(dim, dim)

    def forward(
        self,
        desc_src: torch.Tensor,
        desc_tgt: torch.Tensor,
        normals_src: torch.Tensor,
        normals_tgt: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, N, d), (B, M, d) descriptors and (B, N, 3), (B, M, 3) normals -> (B, N, d), (B, M, d)."""
        bins = self.config.normal_angle_bins
        # The angle bins depend only on the normals: one lookup per cloud serves every layer.
        heads = self.config.transformer_heads
        lookup_src = normal_angle_lookup(normals_src, bins, heads)
        lookup_tgt = normal_angle_lookup(normals_tgt, bins, heads)
        src, tgt = desc_src, desc_tgt
        for self_layer, term, cross_layer in zip(self.self_layers, self.normal_terms, self.cross_layers):
            src = self_layer(src, src, logit_term=term, lookup=lookup_src)
            tgt = self_layer(tgt, tgt, logit_term=term, lookup=lookup_tgt)
            src, tgt = cross_layer(src, tgt), cross_layer(tgt, src)
        return self.projection(src), self.projection(tgt)


# --------------------------------------------------------------------------------------------
# Whole matcher
# --------------------------------------------------------------------------------------------

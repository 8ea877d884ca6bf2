"""Every size of the LoGDesc network in one frozen dataclass, plus named presets.

The numbers of the ``"paper"`` preset are the paper's and the official code's (see
``/work/shared/reference/METHOD_NOTES.md``, "Network"). ``"small"`` is a CPU-friendly model about
5x cheaper per pair; ``"tiny"`` exists for unit tests only.

The config travels with every checkpoint and every exported model (``to_dict`` / ``from_dict``,
the same :class:`logdesc_rt.config._DictMixin` convention as the runtime's configs), so a
checkpoint can always rebuild its own network.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from logdesc_rt.config import EDGE_CHANNELS, PAPER_GEOMETRY, GeometryConfig, _DictMixin
from logdesc_rt.geometry.edge_features import EDGE_FEATURE_CHANNELS

ROTARY_MODES = ("per_layer", "once")
# "logdesc": the paper's network (absolute positions, rotary encoding, RoCNet's normal-angle
# term; training/paper_model.py). "invariant": v3, invariant to rigid motion by construction
# (training/invariant_model.py); it reads the "invariant" edge layout and PCA normals.
ARCHITECTURES = ("logdesc", "invariant")


@dataclass(frozen=True)
class ModelConfig(_DictMixin):
    """Sizes and constants of the descriptor, the normal-encoder transformer and the matcher.

    Descriptor (paper section 3.3, "Local-to-global feature aggregation"):
        edge_channels: channels of the edge-feature tensor (15 for the paper's layout, see
            :mod:`logdesc_rt.geometry.edge_features`; 11 or 13 for the invariant network, which
            then reads the "invariant" or the "chiral" layout of
            :mod:`logdesc_rt.geometry.invariant_features`).
        descriptor_channels: output channels of the 1x1 convolutions on the (N, k, 15) edge
            tensor, each followed by GroupNorm and ReLU, then a max over the k neighbours. The
            descriptor attention runs at the last width ``W = descriptor_channels[-1]``.
        group_norm_groups: GroupNorm groups; must divide every entry of ``descriptor_channels``.
        descriptor_attention_layers: self-attention layers with the 3D rotary encoding
            (4 in the paper's experiments, 3 in its method section).
        descriptor_heads: heads of those layers; ``W / heads`` must be even so that no rotary
            pair straddles two heads.
        rotary_mode: where the 3D rotary position encoding is applied.
            ``"per_layer"``: inside every descriptor attention layer the queries, keys and
            values are rotated by R(x) (the paper's equations 10-11; the aggregated values are
            not rotated back, as in equation 10). Queries and keys then carry the *relative*
            position, q_i . k_j depending on x_j - x_i only.
            ``"once"``: the max-pooled features are rotated once by R(x) before the first layer
            and the layers are plain attention (the official code, Lepard's "entangled" mode).
        rotary_base: the 10000 of theta_j = 1 / base^(6 (j - 1) / W), j = 1 .. W / 6.
        rotary_position_scale: positions (network units) are multiplied by this before the
            rotary angles. The official code divides positions by a voxel size of 0.08, i.e. a
            scale of 12.5, which is the default: on clouds scaled into the unit sphere the
            fastest frequency then turns by about one radian per 0.08 of distance (about the
            spacing of 768 points on an object), the slowest hardly at all, so the encoding
            resolves both neighbour-scale and object-scale offsets.
        descriptor_dim: d, the width after the final 1x1 projection of the descriptor and the
            width of the whole transformer (132 in the paper).

    Normal-encoder transformer (paper section 3.2.2, RoCNet):
        transformer_layers: number of (self, cross) layer pairs (6).
        transformer_heads: heads of every transformer layer; must divide ``descriptor_dim``.
        normal_angle_sigma_deg: sigma of the normal-angle sinusoids, degrees (15).
        normal_angle_base: u of the sinusoids (10000).
        normal_angle_bins: size of the angle table over [0, pi] that the factorised
            normal-angle attention term is interpolated from (see
            :class:`training.paper_model.NormalAngleBias`); linear interpolation on 1024 bins is
            accurate to ~1e-5 of the term's scale.

    Matching:
        sinkhorn_iterations: log-domain Sinkhorn iterations (50 in the official code).
        dustbin_init: initial value of the learned dustbin score (1.0).

    Geometry read by the invariant network:
        edge_neighbours: k, each point's nearest neighbours in its (N, k, C) edge tensor (the
            geometry's ``umbrella_neighbours``; 30 for v3 and v4, 20 for v13). The edge convolutions' cost
            grows with it, and their weights do not depend on it.

    Architecture:
        architecture: ``"logdesc"`` (the paper's network) or ``"invariant"`` (v3: invariant
            edges, distance and normal terms as query / key channels, one logit matrix per
            cross layer; :mod:`training.invariant_model`). The rotary and normal-angle fields
            above apply to ``"logdesc"`` only.
    """

    edge_channels: int = EDGE_FEATURE_CHANNELS
    descriptor_channels: tuple[int, ...] = (132, 132, 264)
    group_norm_groups: int = 6
    descriptor_attention_layers: int = 4
    descriptor_heads: int = 4
    rotary_mode: str = "per_layer"
    rotary_base: float = 10000.0
    rotary_position_scale: float = 12.5
    descriptor_dim: int = 132
    transformer_layers: int = 6
    transformer_heads: int = 4
    normal_angle_sigma_deg: float = 15.0
    normal_angle_base: float = 10000.0
    normal_angle_bins: int = 1024
    sinkhorn_iterations: int = 50
    dustbin_init: float = 1.0
    architecture: str = "logdesc"
    edge_neighbours: int = PAPER_GEOMETRY.umbrella_neighbours

    def __post_init__(self) -> None:
        # JSON turns tuples into lists; a frozen dataclass must hold a hashable tuple.
        object.__setattr__(
            self, "descriptor_channels", tuple(int(c) for c in self.descriptor_channels)
        )
        name = type(self).__name__
        if self.edge_neighbours < 3:
            raise ValueError(f"{name}.edge_neighbours must be >= 3, got {self.edge_neighbours}")
        if self.architecture != "invariant" and self.edge_neighbours != PAPER_GEOMETRY.umbrella_neighbours:
            raise ValueError(f"{name}.edge_neighbours: the paper's network reads the paper's geometry (k = 30)")
        if self.edge_channels < 1:
            raise ValueError(f"{name}.edge_channels must be >= 1, got {self.edge_channels}")
        if not self.descriptor_channels or min(self.descriptor_channels) < 1:
            raise ValueError(
                f"{name}.descriptor_channels must be a non-empty tuple of positive ints, "
                f"got {self.descriptor_channels}"
            )
        if self.group_norm_groups < 1 or any(
            c % self.group_norm_groups for c in self.descriptor_channels
        ):
            raise ValueError(
                f"{name}.group_norm_groups={self.group_norm_groups} must divide every entry of "
                f"descriptor_channels={self.descriptor_channels}"
            )
        if self.architecture not in ARCHITECTURES:
            raise ValueError(f"{name}.architecture must be one of {ARCHITECTURES}, got {self.architecture!r}")
        if self.edge_channels != self.geometry().edge_channels:
            raise ValueError(
                f"{name}.edge_channels={self.edge_channels}, but the {self.architecture!r} network reads "
                f"the {self.geometry().edge_layout!r} edge layout of {self.geometry().edge_channels} channels"
            )
        width = self.attention_width
        if self.architecture == "logdesc" and width % 6:
            raise ValueError(
                f"{name}: the descriptor attention width descriptor_channels[-1]={width} must be "
                "divisible by 6 (3D rotary encoding: one pair of channels per axis per frequency)"
            )
        if self.descriptor_heads < 1 or width % self.descriptor_heads:
            raise ValueError(
                f"{name}.descriptor_heads={self.descriptor_heads} must divide the attention "
                f"width {width}"
            )
        if self.architecture == "logdesc" and (width // self.descriptor_heads) % 2:
            raise ValueError(
                f"{name}: descriptor head width {width // self.descriptor_heads} must be even "
                "(a rotary channel pair must not straddle two heads)"
            )
        if self.descriptor_attention_layers < 0:
            raise ValueError(f"{name}.descriptor_attention_layers must be >= 0")
        if self.rotary_mode not in ROTARY_MODES:
            raise ValueError(f"{name}.rotary_mode must be one of {ROTARY_MODES}, got {self.rotary_mode!r}")
        if not self.rotary_base > 1.0:
            raise ValueError(f"{name}.rotary_base must be > 1, got {self.rotary_base}")
        if not self.rotary_position_scale > 0.0:
            raise ValueError(f"{name}.rotary_position_scale must be > 0")
        if self.descriptor_dim < 2 or self.descriptor_dim % 2:
            raise ValueError(
                f"{name}.descriptor_dim must be even and >= 2 (sin/cos pairs), got {self.descriptor_dim}"
            )
        if self.transformer_layers < 0:
            raise ValueError(f"{name}.transformer_layers must be >= 0")
        if self.transformer_heads < 1 or self.descriptor_dim % self.transformer_heads:
            raise ValueError(
                f"{name}.transformer_heads={self.transformer_heads} must divide "
                f"descriptor_dim={self.descriptor_dim}"
            )
        if not self.normal_angle_sigma_deg > 0.0:
            raise ValueError(f"{name}.normal_angle_sigma_deg must be > 0")
        if not self.normal_angle_base > 1.0:
            raise ValueError(f"{name}.normal_angle_base must be > 1")
        if self.normal_angle_bins < 2:
            raise ValueError(f"{name}.normal_angle_bins must be >= 2")
        if self.sinkhorn_iterations < 1:
            raise ValueError(f"{name}.sinkhorn_iterations must be >= 1")

    @property
    def attention_width(self) -> int:
        """W, the width the descriptor attention runs at (``descriptor_channels[-1]``)."""
        return self.descriptor_channels[-1]

    def geometry(self) -> GeometryConfig:
        """The per-point geometry this network reads (training builds its pairs with it and
        stores it in the checkpoint; export copies it into the model's manifest)."""
        if self.architecture == "invariant":
            # v3 reads the 11 invariant channels; v4 the 13 of the chiral layout.
            layout = "chiral" if self.edge_channels == EDGE_CHANNELS["chiral"] else "invariant"
            return GeometryConfig(edge_layout=layout, normals="pca", umbrella_neighbours=self.edge_neighbours)
        return PAPER_GEOMETRY

    def to_dict(self) -> dict[str, Any]:
        values = dataclasses.asdict(self)
        values["descriptor_channels"] = list(self.descriptor_channels)  # JSON-native
        return values

    def replace(self, **changes: Any) -> "ModelConfig":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def preset(cls, name: str) -> "ModelConfig":
        """The named preset: ``"paper"``, ``"small"`` or ``"tiny"``."""
        try:
            return PRESETS[name]
        except KeyError:
            raise ValueError(f"unknown model preset {name!r}; known: {sorted(PRESETS)}") from None

    @classmethod
    def paper(cls) -> "ModelConfig":
        return PRESETS["paper"]

    @classmethod
    def small(cls) -> "ModelConfig":
        return PRESETS["small"]

    @classmethod
    def tiny(cls) -> "ModelConfig":
        return PRESETS["tiny"]


PRESETS: dict[str, ModelConfig] = {
    # The paper / official sizes.
    "paper": ModelConfig(),
    # About 5x fewer multiply-adds per pair than "paper" at 768 points (1x1 convolutions
    # 15->48->96->96, 2 descriptor attention layers at width 96, 3 transformer pairs at d = 96).
    # 256 angle bins: interpolation error ~3e-4 of the normal-angle term's scale (far below the
    # normals' own noise) and a 4x smaller (B, H, N, bins) table, which matters on the CPU.
    # Wall time is only ~2.5x lower than "paper": the (B, H, N, N) attention work and the
    # Sinkhorn iterations do not shrink with the widths.
    "small": ModelConfig(
        descriptor_channels=(48, 96, 96),
        descriptor_attention_layers=2,
        descriptor_heads=4,
        descriptor_dim=96,
        transformer_layers=3,
        transformer_heads=4,
        normal_angle_bins=256,
    ),
    # v3: invariant by construction (training/invariant_model.py), sized for the CPU runtime.
    "v3": ModelConfig(
        architecture="invariant",
        edge_channels=EDGE_CHANNELS["invariant"],
        descriptor_channels=(32, 64, 96),
        group_norm_groups=4,
        descriptor_attention_layers=2,
        descriptor_heads=4,
        descriptor_dim=96,
        transformer_layers=3,
        transformer_heads=4,
    ),
    # Unit tests only: the invariant network's every code path.
    "tiny_v3": ModelConfig(
        architecture="invariant",
        edge_channels=EDGE_CHANNELS["invariant"],
        descriptor_channels=(16, 24, 24),
        group_norm_groups=4,
        descriptor_attention_layers=1,
        descriptor_heads=2,
        descriptor_dim=24,
        transformer_layers=1,
        transformer_heads=2,
        sinkhorn_iterations=20,
    ),
    # Unit tests only: every code path, a few thousand parameters.
    "tiny": ModelConfig(
        descriptor_channels=(24, 24, 24),
        descriptor_attention_layers=1,
        descriptor_heads=2,
        descriptor_dim=24,
        transformer_layers=1,
        transformer_heads=2,
        normal_angle_bins=256,
        sinkhorn_iterations=20,
    ),
}
# v4: v3's sizes reading the chiral edge layout (13 channels: v3's 11 and two that change sign
# under a reflection), so that v3's weights warm-start it (training.train --init-from).
PRESETS["v4"] = PRESETS["v3"].replace(edge_channels=EDGE_CHANNELS["chiral"])
# v4 without the transformer: the matcher network is the final d -> d map alone, so the scores
# are a learned bilinear form of the descriptors (issue #23: does the matcher earn its cost on
# scans?). Its descriptor is v4's, so v4's weights warm-start it (--init-from, --init-skip).
PRESETS["v4_descriptor"] = PRESETS["v4"].replace(transformer_layers=0)
# v4 with one (geometric self + bidirectional cross) pair instead of three: a third of the
# matcher's attention passes (issue #23: the descriptor alone lost the shape protocols, so the
# next question is how little matcher keeps them). v4's first pair and final map warm-start it.
PRESETS["v4_one_pair"] = PRESETS["v4"].replace(transformer_layers=1)
# v6: v4's network with one descriptor attention layer instead of two and two transformer pairs
# instead of three (2.9 instead of 4.2 GFLOP per 512-point pair), for the latency goal of issue
# #40. It reads v4's geometry, so v5 can teach it (training.train --distill-from) and warm-start
# it (--init-from: every weight it has is shaped as v5's; the first layers are copied).
# Trained and not shipped (docs: decisions, v6).
PRESETS["v6"] = PRESETS["v4"].replace(descriptor_attention_layers=1, transformer_layers=2)
# v13: v7's network with 20 edge neighbours instead of 30 (the geometry's neighbourhoods and the
# descriptor's edge convolutions), its three transformer pairs kept; every weight is v7's shape,
# so v7 warm-starts it whole. The bundled model (v19) is this preset: three cycles at 384 points
# from v7 (v15), then four at 320 points.
PRESETS["v13"] = PRESETS["v4"].replace(edge_neighbours=20)

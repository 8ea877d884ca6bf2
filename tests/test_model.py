"""The PyTorch model (training/): shapes, the factorised normal-angle term, Sinkhorn, losses,
equivariance, memory (no N x N x d tensor), a few optimiser steps and ONNX export.

Runs on the CPU in seconds with the "tiny" preset; skipped where torch is not installed.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
import torch.nn.functional as F  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402

from logdesc_rt.config import GeometryConfig  # noqa: E402
from logdesc_rt.geometry import compute_geometry  # noqa: E402
from training.config import PRESETS, ModelConfig  # noqa: E402
from training.losses import (  # noqa: E402
    assignment_nll,
    descriptor_infonce,
    invert_matches,
)
from training.model import DescribeModule, LoGDescMatcher, MatchScoresModule  # noqa: E402
from training.paper_model import (  # noqa: E402
    NormalAngleBias,
    NormalEncoderTransformer,
    RotaryEncoding3D,
    normal_angle_lookup,
    normal_angle_term_direct,
)
from training.sinkhorn import (  # noqa: E402
    log_domain_optimal_transport,
    log_optimal_transport,
    scaling_optimal_transport,
)

from .shapes import fibonacci_sphere  # noqa: E402

TINY = PRESETS["tiny"]
K = 8
# the tiny preset is the paper net
GEOMETRY = GeometryConfig(edge_layout="paper", normals="umbrella", umbrella_neighbours=K, pca_max_neighbours=32)


def _random_inputs(generator: torch.Generator, batch: int, count: int, k: int = K, channels: int = 15):
    edges = torch.randn(batch, count, k, channels, generator=generator)
    points = torch.randn(batch, count, 3, generator=generator)
    normals = F.normalize(torch.randn(batch, count, 3, generator=generator), dim=-1)
    return edges, points, normals


def _geometry_tensors(points: np.ndarray):
    geometry = compute_geometry(points, GEOMETRY)
    return (
        torch.from_numpy(geometry.edges).float()[None],
        torch.from_numpy(geometry.points).float()[None],
        torch.from_numpy(geometry.normals).float()[None],
    )


@pytest.fixture
def pair():
    """A real geometry pair: 64 source points, 64 target points sharing 56 of them, shuffled."""
    rng = np.random.default_rng(0)
    cloud = fibonacci_sphere(72) * rng.uniform(0.8, 1.0, size=(72, 1))
    source_index = np.arange(64)  # points 0..63
    target_index = rng.permutation(np.arange(8, 72))  # points 8..71, shuffled
    src = _geometry_tensors(cloud[source_index])
    tgt = _geometry_tensors(cloud[target_index])
    position = {int(p): j for j, p in enumerate(target_index)}
    gt_src = torch.tensor([[position.get(int(p), -1) for p in source_index]])
    gt_tgt = invert_matches(gt_src, len(target_index))
    return src, tgt, gt_src, gt_tgt


# ------------------------------------------------------------------------------------ config


def test_config_round_trip_through_json():
    for config in PRESETS.values():
        restored = ModelConfig.from_dict(json.loads(json.dumps(config.to_dict())))
        assert restored == config
        assert isinstance(restored.descriptor_channels, tuple)
    assert ModelConfig.preset("small") == ModelConfig.small()


@pytest.mark.parametrize(
    "changes",
    [
        {"descriptor_channels": (24, 24, 28)},  # width not divisible by 6
        {"descriptor_channels": (24, 24, 30), "descriptor_heads": 4},  # heads do not divide W
        {"descriptor_channels": (18, 18, 18), "descriptor_heads": 2},  # odd head width (rotary)
        {"descriptor_dim": 25},
        {"descriptor_dim": 24, "transformer_heads": 5},
        {"rotary_mode": "sometimes"},
        {"group_norm_groups": 5},
        {"normal_angle_bins": 1},
    ],
)
def test_config_rejects_bad_sizes(changes):
    with pytest.raises(ValueError):
        TINY.replace(**changes)


def test_config_rejects_unknown_keys():
    with pytest.raises(ValueError):
        ModelConfig.from_dict({**TINY.to_dict(), "dropout": 0.1})


# ------------------------------------------------------------------------------------ model


@pytest.mark.parametrize("rotary_mode", ["per_layer", "once"])
def test_forward_shapes_and_unit_descriptors(pair, rotary_mode):
    torch.manual_seed(0)
    model = LoGDescMatcher(TINY.replace(rotary_mode=rotary_mode))
    (src, tgt, _, _) = pair
    out = model(*src, *tgt)
    n, m, d = src[0].shape[1], tgt[0].shape[1], TINY.descriptor_dim
    assert out["scores"].shape == (1, n, m)
    assert out["log_assignment"].shape == (1, n + 1, m + 1)
    assert out["descriptors_src"].shape == (1, n, d)
    assert out["descriptors_tgt"].shape == (1, m, d)
    for key in ("descriptors_src", "descriptors_tgt"):
        norms = out[key].norm(dim=-1)
        torch.testing.assert_close(norms, torch.ones_like(norms), atol=1e-5, rtol=0)
    assert all(torch.isfinite(value).all() for value in out.values())


@pytest.mark.parametrize("preset", ["tiny", "tiny_v3"])
def test_a_batch_computes_what_each_pair_computes_alone(preset):
    """Batching never mixes pairs (GroupNorm, attention and Sinkhorn are per pair)."""
    generator = torch.Generator().manual_seed(1)
    config = PRESETS[preset]
    model = LoGDescMatcher(config).eval()
    source = _random_inputs(generator, 3, 40, channels=config.edge_channels)
    target = _random_inputs(generator, 3, 33, channels=config.edge_channels)
    with torch.no_grad():
        batched = model(*source, *target)
        assert batched["scores"].shape == (3, 40, 33)
        assert batched["log_assignment"].shape == (3, 41, 34)
        for row in range(3):
            alone = model(*(t[row : row + 1] for t in source), *(t[row : row + 1] for t in target))
            for key in ("scores", "log_assignment", "descriptors_src"):
                torch.testing.assert_close(batched[key][row], alone[key][0], atol=2e-5, rtol=1e-5)


def test_rotary_encoding_is_relative_and_norm_preserving():
    generator = torch.Generator().manual_seed(2)
    rotary = RotaryEncoding3D(24, base=10000.0, position_scale=12.5)
    q, k = torch.randn(2, 1, 5, 24, generator=generator)
    x, y = torch.randn(2, 1, 5, 3, generator=generator)
    shift = torch.randn(1, 1, 3, generator=generator)

    def products(a, b):
        qa = RotaryEncoding3D.rotate(q, *rotary.angles(a))
        kb = RotaryEncoding3D.rotate(k, *rotary.angles(b))
        return (qa * kb).sum(-1), qa.norm(dim=-1)

    dot, norm = products(x, y)
    dot_shifted, _ = products(x + shift, y + shift)
    torch.testing.assert_close(dot, dot_shifted, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(norm, q.norm(dim=-1), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("bins", [256, 1024])
def test_factorised_normal_angle_term_equals_direct(bins):
    """Interpolated table term == the full N x N x d embedding, values and gradients.

    Tolerance: max |difference| < 1e-3 x max |term| (linear interpolation error bound is
    (pi / (bins - 1) / sigma)^2 / 8 ~ 3e-4 of the term's scale at 256 bins, 2e-5 at 1024).
    """
    generator = torch.Generator().manual_seed(3)
    batch, heads, count, dim = 2, 2, 50, 24
    module = NormalAngleBias(dim, heads, math.radians(15.0), 10000.0, bins)
    with torch.no_grad():  # make the bias non-trivial too
        module.linear.bias.normal_(generator=generator)
    query = torch.randn(batch, heads, count, dim // heads, generator=generator, requires_grad=True)
    normals = F.normalize(torch.randn(batch, count, 3, generator=generator), dim=-1)

    factorised = module(query, normal_angle_lookup(normals, bins, heads))
    direct = normal_angle_term_direct(query, normals, module)
    assert factorised.shape == direct.shape == (batch, heads, count, count)
    scale = direct.abs().max()
    assert (factorised - direct).abs().max() < 1e-3 * scale

    weights = torch.randn(direct.shape, generator=generator)
    grads_factorised = torch.autograd.grad(
        (factorised * weights).sum(), (query, module.linear.weight, module.linear.bias)
    )
    grads_direct = torch.autograd.grad(
        (direct * weights).sum(), (query, module.linear.weight, module.linear.bias)
    )
    for a, b in zip(grads_factorised, grads_direct):
        assert a.abs().max() > 0
        assert (a - b).abs().max() < 1e-3 * b.abs().max()


def test_permuting_the_source_permutes_score_rows():
    generator = torch.Generator().manual_seed(4)
    model = LoGDescMatcher(TINY).eval()
    src = _random_inputs(generator, 2, 48)
    tgt = _random_inputs(generator, 2, 40)
    perm = torch.randperm(48, generator=generator)
    with torch.no_grad():
        scores = model(*src, *tgt)["scores"]
        permuted = model(*(x[:, perm] for x in src), *tgt)["scores"]
    torch.testing.assert_close(permuted, scores[:, perm], atol=1e-5, rtol=1e-4)


def test_bf16_autocast_runs_and_keeps_angles_in_float32():
    """train.py runs the network under bf16 autocast; positions and normal angles stay fp32."""
    generator = torch.Generator().manual_seed(12)
    model = LoGDescMatcher(TINY)
    src, tgt = _random_inputs(generator, 2, 40), _random_inputs(generator, 2, 36)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        desc_src = model.describe(src[0], src[1])
        desc_tgt = model.describe(tgt[0], tgt[1])
        scores = model.match_scores(desc_src, desc_tgt, src[2], tgt[2])
        lower, fraction = normal_angle_lookup(src[2], TINY.normal_angle_bins, TINY.transformer_heads)
        cos, _ = model.descriptor.rotary.angles(src[1])
    assert fraction.dtype == cos.dtype == torch.float32
    exact_lower, _ = normal_angle_lookup(src[2], TINY.normal_angle_bins, TINY.transformer_heads)
    assert torch.equal(lower, exact_lower)
    scores.float().sum().backward()
    assert torch.isfinite(scores.float()).all()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())


# ---------------------------------------------------------------------------------- memory


class _LargestTensor(TorchDispatchMode):
    """Records the largest tensor any ATen op produces (forward and backward)."""

    def __init__(self) -> None:
        super().__init__()
        self.largest = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for value in out if isinstance(out, (tuple, list)) else (out,):
            if isinstance(value, torch.Tensor):
                self.largest = max(self.largest, value.numel())
        return out


def test_no_tensor_of_n_by_n_by_d_elements():
    generator = torch.Generator().manual_seed(5)
    count = 128
    model = LoGDescMatcher(TINY)
    inputs = _random_inputs(generator, 1, count) + _random_inputs(generator, 1, count)
    limit = count * count * TINY.descriptor_dim

    with _LargestTensor() as monitor:
        out = model(*inputs)
        (out["log_assignment"].sum() + out["descriptors_src"].sum()).backward()
    assert monitor.largest < limit / 4, (monitor.largest, limit)

    # The monitor does see an N x N x d tensor when there is one (the direct reference).
    query = torch.randn(1, TINY.transformer_heads, count, TINY.descriptor_dim // TINY.transformer_heads)
    with _LargestTensor() as monitor:
        normal_angle_term_direct(query, inputs[2], model.transformer.normal_terms[0])
    assert monitor.largest >= limit


def test_v3_holds_no_tensor_of_n_by_n_by_d_elements():
    generator = torch.Generator().manual_seed(5)
    count, config = 128, PRESETS["tiny_v3"]
    model = LoGDescMatcher(config)
    inputs = _random_inputs(generator, 1, count, channels=config.edge_channels)
    inputs += _random_inputs(generator, 1, count, channels=config.edge_channels)
    with _LargestTensor() as monitor:
        out = model(*inputs)
        (out["log_assignment"].sum() + out["descriptors_src"].sum()).backward()
    assert monitor.largest < count * count * config.descriptor_dim / 4, monitor.largest


def test_v3_attention_fast_paths_equal_the_explicit_softmax_with_gradients():
    """attend() (heads-last) pads narrow values for torch's fused kernel, and the cross layer runs
    it once per direction; both must equal softmax(S) V written out, values and gradients."""
    from training.invariant_model import BidirectionalCrossLayer, attend
    from training.layers import merge_heads, split_heads

    generator = torch.Generator().manual_seed(8)
    query = torch.randn(2, 3, 40, 11, generator=generator, requires_grad=True)  # (B, H, N, d)
    key = torch.randn(2, 3, 50, 11, generator=generator, requires_grad=True)
    value = torch.randn(2, 3, 50, 4, generator=generator, requires_grad=True)
    fast = attend(query.transpose(1, 2), key.transpose(1, 2), value.transpose(1, 2), heads=3)
    explicit = merge_heads(torch.softmax(query @ key.transpose(2, 3), dim=3) @ value)
    assert fast.shape == explicit.shape == (2, 40, 12)
    torch.testing.assert_close(fast, explicit, rtol=1e-5, atol=1e-6)
    weights = torch.randn(fast.shape, generator=generator)
    fast_grads = torch.autograd.grad((fast * weights).sum(), (query, key, value))
    explicit_grads = torch.autograd.grad((explicit * weights).sum(), (query, key, value))
    for fast_grad, explicit_grad in zip(fast_grads, explicit_grads):
        torch.testing.assert_close(fast_grad, explicit_grad, rtol=1e-4, atol=1e-5)

    layer = BidirectionalCrossLayer(width=12, heads=3)
    source = torch.randn(2, 40, 12, generator=generator)
    target = torch.randn(2, 50, 12, generator=generator)
    new_source, new_target = layer(source, target)
    def split(x):
        return split_heads(x, 3)

    logits = split(layer.query_key(source)) @ split(layer.query_key(target)).transpose(2, 3) / 2.0
    source_message = merge_heads(torch.softmax(logits, dim=3) @ split(layer.value(target)))
    target_message = merge_heads(torch.softmax(logits, dim=2).transpose(2, 3) @ split(layer.value(source)))
    torch.testing.assert_close(new_source, layer.update(source, source_message), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(new_target, layer.update(target, target_message), rtol=1e-5, atol=1e-5)


def test_folded_edge_convolutions_equal_the_layers_as_trained():
    """The export's edge convolutions with GroupNorm folded in (moments of the input, one
    product per layer) compute what Conv -> GroupNorm -> ReLU -> max over k computes, for each
    pair of a batch with its own statistics and with learned (non-unit) norm parameters."""
    from training.layers import edge_convolutions, folded_edge_convolutions

    torch.manual_seed(3)
    config = PRESETS["v4"]
    local = edge_convolutions(config).eval()
    with torch.no_grad():
        for module in local:
            if isinstance(module, torch.nn.GroupNorm):
                module.weight.uniform_(-2.0, 2.0)  # a negative scale: max over k does not commute
                module.bias.uniform_(-1.0, 1.0)
    generator = torch.Generator().manual_seed(4)
    edges = torch.randn(2, 200, 30, config.edge_channels, generator=generator)
    edges[1] = 3.0 * edges[1] + 2.0  # the second pair's own mean and spread
    with torch.no_grad():
        expected = local(edges.permute(0, 3, 1, 2)).amax(dim=3).transpose(1, 2)
        folded = folded_edge_convolutions(local, edges)
    assert folded.shape == expected.shape == (2, 200, config.attention_width)
    torch.testing.assert_close(folded, expected, rtol=1e-4, atol=1e-4)
    # Pair by pair: the statistics are each pair's own, not the batch's.
    with torch.no_grad():
        alone = folded_edge_convolutions(local, edges[1:])
    torch.testing.assert_close(alone, folded[1:], rtol=1e-5, atol=1e-5)


def test_clouds_of_one_size_stacked_in_one_batch_get_what_each_gets_alone():
    """The invariant transformer's stacked form (two clouds of one size in one batch, what
    matcher_same_size.onnx exports): each cross layer's stacked form gives each cloud what the
    two-cloud form gives it, for a batch of several pairs (each attending to its own partner),
    and so does stacked_forward against forward, which runs the clouds one at a time."""
    torch.manual_seed(5)
    model = LoGDescMatcher(PRESETS["v4"]).eval()
    transformer = model.transformer
    generator = torch.Generator().manual_seed(6)
    batch, count, width = 3, 150, PRESETS["v4"].descriptor_dim
    source, target = (F.normalize(torch.randn(batch, count, width, generator=generator), dim=-1) for _ in range(2))
    normals = [F.normalize(torch.randn(batch, count, 3, generator=generator), dim=-1) for _ in range(2)]
    points = [torch.randn(batch, count, 3, generator=generator) for _ in range(2)]
    with torch.no_grad():
        layer = transformer.cross_layers[0]
        stacked = layer.stacked(torch.cat((source, target)), batch)
        apart = torch.cat(layer(source, target))
        torch.testing.assert_close(stacked, apart, rtol=1e-5, atol=1e-5)
        together = transformer.stacked_forward(source, target, *normals, *points)
        one_at_a_time = transformer(source, target, *normals, *points)
    for stacked_final, final in zip(together, one_at_a_time, strict=True):
        torch.testing.assert_close(stacked_final, final, rtol=1e-5, atol=1e-5)


def test_descriptor_only_preset_starts_with_cosine_scores_over_the_temperature():
    """v4_descriptor has no transformer layers, and its first scores are the descriptors'
    cosines over DESCRIPTOR_ONLY_TEMPERATURE (a random d x d map would give scores ~0.1)."""
    from training.invariant_model import DESCRIPTOR_ONLY_TEMPERATURE

    config = PRESETS["v4_descriptor"]
    assert config.transformer_layers == 0 and config.descriptor_dim == PRESETS["v4"].descriptor_dim
    model = LoGDescMatcher(config).eval()
    generator = torch.Generator().manual_seed(5)
    src = F.normalize(torch.randn(1, 40, config.descriptor_dim, generator=generator), dim=-1)
    tgt = F.normalize(torch.randn(1, 30, config.descriptor_dim, generator=generator), dim=-1)
    normals_src, normals_tgt = F.normalize(torch.randn(1, 40, 3), dim=-1), F.normalize(torch.randn(1, 30, 3), dim=-1)
    with torch.no_grad():
        scores = model.match_scores(src, tgt, normals_src, normals_tgt, torch.randn(1, 40, 3), torch.randn(1, 30, 3))
    torch.testing.assert_close(scores, src @ tgt.transpose(1, 2) / DESCRIPTOR_ONLY_TEMPERATURE, rtol=1e-5, atol=1e-5)


def test_transformer_runs_on_2048_points():
    """2048 points per cloud, twice the working size (its speed: benchmarks/latency.py)."""
    generator = torch.Generator().manual_seed(6)
    count = 2048
    transformer = NormalEncoderTransformer(TINY).eval()
    desc = F.normalize(torch.randn(2, 1, count, TINY.descriptor_dim, generator=generator), dim=-1)
    normals = F.normalize(torch.randn(2, 1, count, 3, generator=generator), dim=-1)
    with torch.no_grad():
        out_src, out_tgt = transformer(desc[0], desc[1], normals[0], normals[1])
    assert out_src.shape == out_tgt.shape == (1, count, TINY.descriptor_dim)
    assert torch.isfinite(out_src).all() and torch.isfinite(out_tgt).all()


# --------------------------------------------------------------------------------- sinkhorn


def _sinkhorn_reference(scores: np.ndarray, alpha: float, iterations: int) -> np.ndarray:
    """Plain probability-domain Sinkhorn in float64 with the same marginals and update order."""
    n, m = scores.shape
    couplings = np.full((n + 1, m + 1), alpha)
    couplings[:n, :m] = scores
    kernel = np.exp(couplings)
    mu = np.r_[np.ones(n), m] / (n + m)
    nu = np.r_[np.ones(m), n] / (n + m)
    u, v = np.ones(n + 1), np.ones(m + 1)
    for _ in range(iterations):
        u = mu / (kernel @ v)
        v = nu / (kernel.T @ u)
    return np.log(u[:, None] * kernel * v[None, :] * (n + m))


def test_log_optimal_transport_marginals_and_reference():
    generator = torch.Generator().manual_seed(7)
    n, m = 30, 25
    scores = torch.randn(2, n, m, generator=generator)
    alpha = torch.tensor(1.0)
    log_assignment = log_optimal_transport(scores, alpha, iterations=100)
    assert log_assignment.shape == (2, n + 1, m + 1)
    probabilities = log_assignment.exp()
    rows, cols = probabilities.sum(dim=2), probabilities.sum(dim=1)
    torch.testing.assert_close(rows[:, :n], torch.ones(2, n), atol=1e-4, rtol=0)
    torch.testing.assert_close(cols[:, :m], torch.ones(2, m), atol=1e-5, rtol=0)
    torch.testing.assert_close(rows[:, n], torch.full((2,), float(m)), atol=1e-3, rtol=0)
    torch.testing.assert_close(cols[:, m], torch.full((2,), float(n)), atol=1e-3, rtol=0)

    for iterations in (1, 50):
        ours = log_optimal_transport(scores.double(), alpha.double(), iterations)[0].numpy()
        reference = _sinkhorn_reference(scores[0].double().numpy(), 1.0, iterations)
        np.testing.assert_allclose(ours, reference, atol=1e-10)


def _sinkhorn_values_and_gradients(sinkhorn, scores: torch.Tensor, weights: torch.Tensor):
    """(plan, d loss / d scores, d loss / d dustbin score) of ``sinkhorn`` for the loss
    sum(plan * weights), dustbin score 0.7, 50 iterations (float64)."""
    leaf = scores.clone().requires_grad_()
    alpha = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
    out = sinkhorn(leaf, alpha, 50)
    (out * weights).sum().backward()
    return out.detach(), leaf.grad, alpha.grad


@pytest.mark.parametrize("strength", [1.0, 20.0, 120.0])
def test_scaling_sinkhorn_equals_the_log_domain_one_with_its_gradients(strength):
    """Training's scaling-form Sinkhorn gives the log-domain iteration's values and gradients
    (float64), from mild scores to the sharp ones of a trained network."""
    generator = torch.Generator().manual_seed(int(strength))
    n, m = 40, 33
    scores = torch.randn(2, n, m, generator=generator, dtype=torch.float64) * 0.2 * strength
    scores[:, torch.arange(25), torch.randperm(m, generator=generator)[:25]] += strength
    weights = torch.randn(2, n + 1, m + 1, generator=generator, dtype=torch.float64)
    results = [_sinkhorn_values_and_gradients(sinkhorn, scores, weights)
               for sinkhorn in (log_optimal_transport, log_domain_optimal_transport)]
    for ours, reference in zip(results[0], results[1]):
        torch.testing.assert_close(ours, reference, atol=1e-8 * max(1.0, strength), rtol=1e-7)


def test_cpu_sinkhorn_pair_by_pair_equals_the_whole_batch_with_gradients():
    """On the CPU the Sinkhorn runs one pair at a time (cache-sized kernels); the batch's
    values and gradients, the shared dustbin score's included, are those of the whole batch
    at once (what a GPU runs)."""
    generator = torch.Generator().manual_seed(3)
    n, m = 40, 33
    strengths = torch.tensor([1.0, 20.0, 120.0], dtype=torch.float64)
    scores = torch.randn(3, n, m, generator=generator, dtype=torch.float64) * 0.2 * strengths[:, None, None]
    scores[:, torch.arange(25), torch.randperm(m, generator=generator)[:25]] += strengths[:, None]
    weights = torch.randn(3, n + 1, m + 1, generator=generator, dtype=torch.float64)
    results = [_sinkhorn_values_and_gradients(sinkhorn, scores, weights)
               for sinkhorn in (log_optimal_transport, scaling_optimal_transport)]
    for pair_by_pair, whole_batch in zip(*results):
        torch.testing.assert_close(pair_by_pair, whole_batch, atol=1e-9, rtol=1e-9)


def test_log_optimal_transport_gradient_reaches_dustbin():
    scores = torch.randn(1, 6, 5, requires_grad=True)
    alpha = torch.tensor(0.5, requires_grad=True)
    log_optimal_transport(scores, alpha, 10)[0, :-1, -1].sum().backward()
    assert alpha.grad is not None and alpha.grad.abs() > 0
    assert scores.grad is not None and torch.isfinite(scores.grad).all()


# ----------------------------------------------------------------------------------- losses


def test_invert_matches():
    gt_src = torch.tensor([[2, -1, 0, -1]])
    assert invert_matches(gt_src, 3).tolist() == [[2, -1, 0]]


def test_assignment_nll_matches_its_definition():
    generator = torch.Generator().manual_seed(8)
    log_assignment = torch.randn(2, 5, 4, generator=generator)  # N = 4, M = 3
    gt_src = torch.tensor([[0, 2, -1, -1], [1, -1, 0, 2]])
    gt_tgt = invert_matches(gt_src, 3)
    expected = []
    for b in range(2):
        terms = [log_assignment[b, i, int(j) if j >= 0 else 3] for i, j in enumerate(gt_src[b])]
        terms += [log_assignment[b, 4, j] for j in range(3) if gt_tgt[b, j] < 0]
        expected.append(-torch.stack(terms).mean())
    torch.testing.assert_close(assignment_nll(log_assignment, gt_src, gt_tgt), torch.stack(expected).mean())


def test_ignored_points_add_no_term_to_any_loss():
    """An unlabelled point (IGNORED, resampled pairs) has no term of its own in any loss."""
    from logdesc_rt.metrics import IGNORED

    generator = torch.Generator().manual_seed(10)
    gt_src = torch.tensor([[0, IGNORED, -1, 2, IGNORED]])  # N = 5
    gt_tgt = torch.tensor([[0, IGNORED, 3, -1]])  # M = 4
    # NLL: the ignored rows and the ignored column are never read.
    log_assignment = torch.randn(1, 6, 5, generator=generator)
    changed = log_assignment.clone()
    changed[0, [1, 4], :] = torch.randn(2, 5, generator=generator)
    changed[0, :, 1] = torch.randn(6, generator=generator)
    torch.testing.assert_close(assignment_nll(changed, gt_src, gt_tgt), assignment_nll(log_assignment, gt_src, gt_tgt))
    terms = [log_assignment[0, 0, 0], log_assignment[0, 2, 4], log_assignment[0, 3, 2], log_assignment[0, 5, 3]]
    torch.testing.assert_close(assignment_nll(log_assignment, gt_src, gt_tgt), -torch.stack(terms).mean())
    as_unmatched = torch.where(gt_src == IGNORED, torch.full_like(gt_src, -1), gt_src)
    # InfoNCE counts matches only: ignored and unmatched are the same to it.
    descriptors = F.normalize(torch.randn(1, 5, 8, generator=generator), dim=-1)
    other = F.normalize(torch.randn(1, 4, 8, generator=generator), dim=-1)
    torch.testing.assert_close(descriptor_infonce(descriptors, other, gt_src),
                               descriptor_infonce(descriptors, other, as_unmatched))


def test_descriptor_infonce_prefers_matching_descriptors():
    generator = torch.Generator().manual_seed(9)
    desc = F.normalize(torch.randn(1, 20, 24, generator=generator), dim=-1)
    gt_src = torch.arange(20)[None]
    aligned = descriptor_infonce(desc, desc, gt_src)
    shuffled = descriptor_infonce(desc, desc[:, torch.randperm(20, generator=generator)], gt_src)
    assert aligned < shuffled
    empty = descriptor_infonce(desc, desc, torch.full((1, 20), -1))
    assert empty.item() == 0.0


# --------------------------------------------------------------------------------- training


def test_a_few_adam_steps_lower_the_assignment_loss(pair):
    torch.manual_seed(10)
    src, tgt, gt_src, gt_tgt = pair
    model = LoGDescMatcher(TINY)
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)
    losses = []
    for _ in range(20):
        out = model(*src, *tgt)
        loss = assignment_nll(out["log_assignment"], gt_src, gt_tgt)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    with torch.no_grad():
        out = model(*src, *tgt)
        final = assignment_nll(out["log_assignment"], gt_src, gt_tgt).item()
    assert final < 0.9 * losses[0], losses + [final]


# ------------------------------------------------------------------------------------- ONNX


def test_onnx_export_with_dynamic_point_counts(tmp_path):
    pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    generator = torch.Generator().manual_seed(11)
    model = LoGDescMatcher(TINY).eval()
    edges, points, normals = _random_inputs(generator, 1, 40)

    describe_path = tmp_path / "describe.onnx"
    scores_path = tmp_path / "scores.onnx"
    desc = model.describe(edges, points).detach()
    # The TorchScript exporter (dynamo=False): the dynamo exporter needs onnxscript.
    torch.onnx.export(
        DescribeModule(model),
        (edges, points),
        str(describe_path),
        input_names=["edges", "points"],
        output_names=["descriptors"],
        dynamic_axes={"edges": {0: "batch", 1: "n"}, "points": {0: "batch", 1: "n"},
                      "descriptors": {0: "batch", 1: "n"}},
        opset_version=17,
        dynamo=False,
    )
    torch.onnx.export(
        MatchScoresModule(model),
        (desc, desc[:, :30], normals, normals[:, :30]),
        str(scores_path),
        input_names=["desc_src", "desc_tgt", "normals_src", "normals_tgt"],
        output_names=["scores"],
        dynamic_axes={"desc_src": {0: "batch", 1: "n"}, "desc_tgt": {0: "batch", 1: "m"},
                      "normals_src": {0: "batch", 1: "n"}, "normals_tgt": {0: "batch", 1: "m"},
                      "scores": {0: "batch", 1: "n", 2: "m"}},
        opset_version=17,
        dynamo=False,
    )

    # Run both graphs at point counts other than the traced ones and compare with PyTorch.
    src = _random_inputs(generator, 2, 57)
    tgt = _random_inputs(generator, 2, 71)
    describe = ort.InferenceSession(str(describe_path), providers=["CPUExecutionProvider"])
    scores = ort.InferenceSession(str(scores_path), providers=["CPUExecutionProvider"])
    desc_src = describe.run(None, {"edges": src[0].numpy(), "points": src[1].numpy()})[0]
    desc_tgt = describe.run(None, {"edges": tgt[0].numpy(), "points": tgt[1].numpy()})[0]
    onnx_scores = scores.run(
        None,
        {"desc_src": desc_src, "desc_tgt": desc_tgt, "normals_src": src[2].numpy(),
         "normals_tgt": tgt[2].numpy()},
    )[0]
    with torch.no_grad():
        expected_src = model.describe(src[0], src[1])
        expected_tgt = model.describe(tgt[0], tgt[1])
        expected_scores = model.match_scores(expected_src, expected_tgt, src[2], tgt[2])
    np.testing.assert_allclose(desc_src, expected_src.numpy(), atol=1e-5)
    np.testing.assert_allclose(onnx_scores, expected_scores.numpy(), atol=1e-4)


def test_edge_neighbours_is_the_geometrys_k():
    """ModelConfig.edge_neighbours is the geometry's k: v4 with k = 16 reads (N, 16, 13) edges
    and v4 (N, 30, 13); the paper's network refuses another k."""
    import numpy as np
    import pytest

    from logdesc_rt.geometry import compute_geometry
    from training.config import PRESETS, ModelConfig

    points = np.random.default_rng(0).uniform(-1, 1, size=(200, 3))
    for config, k in ((PRESETS["v4"].replace(edge_neighbours=16), 16), (PRESETS["v4"], 30)):
        assert config.geometry().umbrella_neighbours == k
        assert compute_geometry(points, config.geometry()).edges.shape == (200, k, config.edge_channels)
    with pytest.raises(ValueError, match="edge_neighbours"):
        ModelConfig(edge_neighbours=16)


def test_assignment_distillation_is_zero_on_the_teachers_plan_and_pulls_towards_it():
    """The distillation KL is ~0 when the student's Sinkhorn plan is the teacher's, positive
    otherwise, and a gradient step on the student's scores lowers it."""
    import torch

    from training.losses import assignment_distillation
    from training.sinkhorn import log_optimal_transport

    generator = torch.Generator().manual_seed(0)
    dustbin = torch.tensor(1.0)
    teacher = log_optimal_transport(torch.randn(2, 7, 9, generator=generator) * 3, dustbin, 50)
    assert float(assignment_distillation(teacher, teacher)) == pytest.approx(0.0, abs=1e-5)

    scores = (torch.randn(2, 7, 9, generator=generator) * 3).requires_grad_(True)
    loss = assignment_distillation(log_optimal_transport(scores, dustbin, 50), teacher)
    assert loss.item() > 0.1
    loss.backward()
    with torch.no_grad():
        stepped = scores - 0.5 * scores.grad
    assert float(assignment_distillation(log_optimal_transport(stepped, dustbin, 50), teacher)) < loss.item()
    with pytest.raises(ValueError, match="differ"):
        assignment_distillation(teacher[:, :5], teacher)


def test_soft_correspondence_distance_measures_the_plans_miss_in_network_units():
    """Zero when each matched source point's plan row sits on its true partner; the mass put on
    a wrong target costs that target's distance from the truth (so a far confusion costs more
    than a near one); unmatched and ignored sources add nothing; a step on the scores lowers it."""
    import torch

    from training.losses import soft_correspondence_distance
    from training.sinkhorn import log_optimal_transport

    generator = torch.Generator().manual_seed(0)
    source = torch.randn(1, 6, 3, generator=generator)
    pose = torch.eye(4)[None].clone()
    pose[0, :3, 3] = torch.tensor([0.5, -0.2, 0.1])
    target = source + pose[0, :3, 3]  # target j is source j moved
    gt = torch.tensor([[0, 1, 2, 3, -1, -2]])  # 4 counterparts, one unmatched, one ignored

    def plan_log(rows: list[list[float]]) -> torch.Tensor:
        """A (1, 7, 7) log-plan whose real block is ``rows`` (the dustbins get the remaining mass)."""
        plan = torch.full((1, 7, 7), 1e-9)
        plan[0, :6, :6] = torch.tensor(rows) + 1e-9
        return plan.log()

    exact = torch.eye(6).tolist()
    def distance(log_plan: torch.Tensor) -> float:
        return float(soft_correspondence_distance(log_plan, source, target, pose, gt))

    assert distance(plan_log(exact)) == pytest.approx(0, abs=1e-6)
    # Sources 4 (unmatched) and 5 (ignored) may point anywhere without cost.
    scattered = [row[:] for row in exact]
    scattered[4], scattered[5] = [1.0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 1.0]
    assert distance(plan_log(scattered)) == pytest.approx(0, abs=1e-6)
    # Half of source 0's mass on target 1: a quarter (1 of 4 matched points) of half that distance.
    split = [row[:] for row in exact]
    split[0] = [0.5, 0.5, 0, 0, 0, 0]
    expected = 0.5 * float((target[0, 1] - target[0, 0]).norm()) / 4
    assert distance(plan_log(split)) == pytest.approx(expected, rel=1e-4)

    scores = torch.randn(1, 6, 6, generator=generator).requires_grad_(True)
    dustbin = torch.tensor(1.0)
    loss = soft_correspondence_distance(log_optimal_transport(scores, dustbin, 50), source, target, pose, gt)
    assert loss.item() > 0.05
    loss.backward()
    with torch.no_grad():
        stepped = scores - 2.0 * scores.grad
    assert distance(log_optimal_transport(stepped, dustbin, 50)) < loss.item()

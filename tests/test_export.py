"""ONNX export and parity, onnxruntime against torch (runs wherever torch is installed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from logdesc_rt import Registrar  # noqa: E402
from logdesc_rt.config import PAPER_GEOMETRY, MatchingConfig, NormalizationConfig  # noqa: E402
from logdesc_rt.demo import make_demo_pair  # noqa: E402
from logdesc_rt.matching import sinkhorn_matches  # noqa: E402
from logdesc_rt.network import OnnxNetwork, bundled_model_dir  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def test_bundled_model_matches_its_torch_checkpoint():
    """The shipped ONNX files compute what the committed checkpoint computes in torch.

    Same comparison and tolerances as ``export/to_onnx.py`` (descriptors 1e-4 absolute,
    scores 1e-4 relative to the largest |score|), on random clouds and a real shape.
    """
    from export.to_onnx import compare_with_torch
    from training.checkpoint import load_model

    network = OnnxNetwork()
    shipped_checkpoint = ROOT / network.manifest.provenance["checkpoint_file"]  # written by the export
    model, info = load_model(shipped_checkpoint)
    assert network.manifest.geometry == info.geometry
    assert network.manifest.dustbin_score == pytest.approx(float(model.dustbin_score))
    assert compare_with_torch(model, info, bundled_model_dir())


def test_export_script_writes_a_loadable_checked_model(tmp_path):
    from export.to_onnx import main as export_main
    from training.config import ModelConfig
    from training.model import LoGDescMatcher

    torch.manual_seed(0)
    config = ModelConfig.tiny()
    checkpoint = tmp_path / "tiny.pt"
    torch.save(
        {
            "model": LoGDescMatcher(config).state_dict(),
            "model_config": config.to_dict(),
            "geometry_config": PAPER_GEOMETRY.to_dict(),
            "normalization_config": NormalizationConfig().to_dict(),
            "matching_config": MatchingConfig().to_dict(),
            "train_args": {"points_per_cloud": 1024},
            "step": 0,
        },
        checkpoint,
    )
    out = tmp_path / "model"
    assert export_main([str(checkpoint), "--out", str(out)]) == 0
    registrar = Registrar(out)
    assert registrar.manifest.descriptor_dim == config.descriptor_dim
    assert registrar.manifest.provenance["checkpoint_file"] == str(checkpoint)  # outside the repository: as given
    # The runtime on the exported files computes what torch computes on the same inputs, and
    # its matches are the Sinkhorn reading of those scores with the exported dustbin.
    pair = make_demo_pair()
    matched = registrar.match(pair.source, pair.target)
    prepared = registrar.prepare(pair.source, pair.target)
    model = LoGDescMatcher(config)
    model.load_state_dict(torch.load(checkpoint)["model"])
    model.eval()
    as_tensor = lambda array: torch.from_numpy(np.asarray(array, dtype=np.float32))[None]  # noqa: E731
    with torch.no_grad():
        descriptors = [
            model.describe(as_tensor(geometry.edges), as_tensor(points))
            for geometry, points in ((prepared.source_geometry, prepared.source_network),
                                     (prepared.target_geometry, prepared.target_network))
        ]
        scores = model.match_scores(
            *descriptors, as_tensor(prepared.source_geometry.normals), as_tensor(prepared.target_geometry.normals)
        )[0].numpy()
    np.testing.assert_allclose(matched.source_descriptors, descriptors[0][0].numpy(), atol=1e-4)
    np.testing.assert_allclose(matched.scores, scores, atol=1e-4 * max(1.0, np.abs(scores).max()))
    assert registrar.manifest.dustbin_score == pytest.approx(float(model.dustbin_score))
    expected = sinkhorn_matches(matched.scores, registrar.manifest.dustbin_score, config.sinkhorn_iterations)
    np.testing.assert_array_equal(matched.matches.source_index, expected.source_index)
    np.testing.assert_array_equal(matched.matches.target_index, expected.target_index)


def test_the_bundled_graphs_feed_the_fused_attention_without_transposes():
    """Queries, keys and values are built heads-last, the fused kernel's own layout: no Transpose
    among the three nodes before any attention input or right after its output. With heads
    split to (B, H, N, d) and merged back around the kernel, the matcher had 67 Transposes."""
    import onnx

    for name in ("descriptor.onnx", "matcher.onnx", "matcher_same_size.onnx"):
        graph = onnx.load(str(bundled_model_dir() / name)).graph
        producer = {output: node for node in graph.node for output in node.output}
        consumers: dict[str, list] = {}
        for node in graph.node:
            for tensor in node.input:
                consumers.setdefault(tensor, []).append(node)
        attention = [node for node in graph.node if node.op_type == "MultiHeadAttention"]
        assert attention, name
        for node in attention:
            for tensor in node.input[:3]:
                chain = []
                while tensor in producer and len(chain) < 3:
                    chain.append(producer[tensor].op_type)
                    tensor = producer[tensor].input[0]
                assert "Transpose" not in chain, (name, node.name, chain)
            assert all(after.op_type != "Transpose" for after in consumers.get(node.output[0], [])), (name, node.name)

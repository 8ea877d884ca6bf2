"""ONNX export and parity, onnxruntime against torch (runs wherever torch is installed)."""

from __future__ import annotations

from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from logdesc_rt import Registrar  # noqa: E402
from logdesc_rt.config import GeometryConfig, MatchingConfig, NormalizationConfig  # noqa: E402
from logdesc_rt.demo import make_demo_pair  # noqa: E402
from logdesc_rt.errors import RegistrationError  # noqa: E402
from logdesc_rt.network import OnnxNetwork, bundled_model_dir  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHIPPED_CHECKPOINT = ROOT / "training" / "checkpoints" / "small_h100_v2.pt"


def test_bundled_model_matches_its_torch_checkpoint():
    """The shipped ONNX files compute what the committed checkpoint computes in torch.

    Same comparison and tolerances as ``export/to_onnx.py`` (descriptors 1e-4 absolute,
    scores 1e-4 relative to the largest |score|), on random clouds and a real shape.
    """
    from export.to_onnx import compare_with_torch
    from training.checkpoint import load_model

    model, info = load_model(SHIPPED_CHECKPOINT)
    network = OnnxNetwork()
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
            "geometry_config": GeometryConfig().to_dict(),
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
    pair = make_demo_pair()
    # Untrained weights: the pipeline runs end to end; with too few matches it says so.
    try:
        result = registrar.register(pair.source, pair.target)
    except RegistrationError as error:
        assert "mutual matches" in str(error)
    else:
        assert result.transformation.shape == (4, 4)

"""training/geometry_torch.py is held to the NumPy reference (logdesc_rt.geometry) on the same points."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from logdesc_rt.config import PAPER_GEOMETRY, GeometryConfig  # noqa: E402
from logdesc_rt.geometry import compute_geometry  # noqa: E402
from logdesc_rt.synthetic import make_pair  # noqa: E402
from training.geometry_torch import invariant_geometry  # noqa: E402

from .shapes import fibonacci_sphere  # noqa: E402

V3 = GeometryConfig(edge_layout="invariant", normals="pca")
V4 = GeometryConfig(edge_layout="chiral", normals="pca")


def _clouds() -> list[np.ndarray]:
    """Two clouds of one size: a bumpy sphere and a noisy ellipsoid."""
    rng = np.random.default_rng(0)
    sphere = fibonacci_sphere(600)
    clouds = [
        sphere * (1.0 + 0.2 * np.sin(4 * sphere[:, :1]) * np.cos(3 * sphere[:, 1:2])),
        sphere * [1.0, 0.6, 0.3] + rng.normal(scale=0.01, size=sphere.shape),
    ]
    return clouds


@pytest.mark.parametrize(
    "config",
    [V3, V4, GeometryConfig(edge_layout="chiral", normals="pca", pca_radius=0.15, umbrella_neighbours=16)],
)
def test_torch_geometry_equals_the_numpy_reference(config):
    clouds = _clouds()
    edges, normals = invariant_geometry(torch.from_numpy(np.stack(clouds)), config)
    for row, cloud in enumerate(clouds):
        reference = compute_geometry(cloud, config)
        np.testing.assert_allclose(edges[row].numpy(), reference.edges, atol=2e-5)
        # Normals agree up to sign (the reference orients them; nothing downstream reads the sign).
        cosine = np.abs(np.einsum("nc,nc->n", normals[row].double().numpy(), reference.normals))
        assert cosine.min() > 1 - 1e-6


def test_torch_geometry_on_a_real_partial_pair(shared_data):
    h5py = pytest.importorskip("h5py")
    with h5py.File(shared_data / "modelnet10_hdf5_1024" / "ply_data_train0.h5", "r") as handle:
        shape = handle["data"][7].astype(np.float64)
    pair = make_pair(shape, "partial", np.random.default_rng(3))
    for cloud in (pair.source_network, pair.target_network):
        for config in (V3, V4):
            edges, _ = invariant_geometry(torch.from_numpy(cloud)[None], config)
            np.testing.assert_allclose(edges[0].numpy(), compute_geometry(cloud, config).edges, atol=2e-5)


def test_torch_geometry_refuses_the_paper_layout_and_tiny_clouds():
    with pytest.raises(ValueError, match="invariant and chiral layouts"):
        invariant_geometry(torch.zeros(1, 40, 3), PAPER_GEOMETRY)
    with pytest.raises(ValueError, match="neighbours need at least"):
        invariant_geometry(torch.zeros(1, 20, 3, dtype=torch.float64), V3)

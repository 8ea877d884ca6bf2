"""Per-point geometry of one cloud: neighbours, PCA features, LRFs, umbrella normals, edges.

:func:`compute_geometry` is the single entry point used by the runtime and by training.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import GeometryConfig
from ..validation import as_points, check_not_degenerate
from .edge_features import EDGE_FEATURE_CHANNELS, edge_features
from .invariant_features import (
    CHIRAL_EDGE_CHANNELS,
    INVARIANT_EDGE_CHANNELS,
    chiral_edge_channels,
    invariant_edge_features,
    invariant_edge_tensor,
)
from .kernels import neighbourhoods
from .neighbours import drop_self, knn_excluding_self, nearest_neighbours
from .normals import umbrella_normals
from .pca import PcaFeatures, pca_features, pca_from_covariance

__all__ = [
    "EDGE_FEATURE_CHANNELS",
    "CHIRAL_EDGE_CHANNELS",
    "INVARIANT_EDGE_CHANNELS",
    "GeometryConfig",
    "PcaFeatures",
    "PointGeometry",
    "compute_geometry",
    "chiral_edge_channels",
    "edge_features",
    "invariant_edge_features",
    "knn_excluding_self",
    "drop_self",
    "nearest_neighbours",
    "pca_features",
    "umbrella_normals",
]


@dataclass(frozen=True)
class PointGeometry:
    """Everything the network needs about one cloud of N points (network units).

    Attributes:
        points: (N, 3) float64 positions.
        neighbour_index: (N, k) int64, k = config.umbrella_neighbours nearest other points.
        pca: :class:`PcaFeatures` (anisotropy, planarity, omnivariance, LRF).
        normals: (N, 3) float64 unit normals handed to the network (``config.normals``:
            umbrella normals, or the LRF's normal axis), oriented by the LRF sign rule.
        edges: (N, k, C) float32 edge features, C = config.edge_channels (layout in
            :mod:`.edge_features` or :mod:`.invariant_features`, per ``config.edge_layout``).
    """

    points: np.ndarray
    neighbour_index: np.ndarray
    pca: PcaFeatures
    normals: np.ndarray
    edges: np.ndarray


def compute_geometry(points, config: GeometryConfig = GeometryConfig()) -> PointGeometry:
    """Compute the per-point geometry of a cloud, in the units of ``config`` (network units).

    Args:
        points: (N, 3) array-like, N >= config.umbrella_neighbours + 1.
        config: radii and neighbour counts.

    Raises:
        PointCloudShapeError, NonFinitePointsError, TooFewPointsError: bad array.
        DegenerateGeometryError: all points coincide or are collinear (no surface).
    """
    points = as_points(points, min_points=config.min_points)
    check_not_degenerate(points)
    count, mean, covariance, neighbour_index = neighbourhoods(
        points,
        config.pca_radius,
        config.pca_max_neighbours,
        config.pca_min_neighbours,
        config.umbrella_neighbours,
    )
    pca = pca_from_covariance(points, count, mean, covariance)
    if config.normals == "pca":
        normals = pca.lrf[:, :, 2].copy()
    else:
        normals = umbrella_normals(points, neighbour_index, pca.lrf, config.umbrella_area_temperature)
    shape_features = np.stack([pca.anisotropy, pca.planarity, pca.omnivariance], axis=1)
    if config.edge_layout in ("invariant", "chiral"):
        chiral = config.edge_layout == "chiral"
        edges = invariant_edge_tensor(
            points,
            shape_features,
            normals,
            pca.lrf if chiral else None,
            (pca.anisotropy - pca.planarity) * pca.planarity if chiral else None,
            neighbour_index,
            config.pca_radius,
        )
    else:
        edges = edge_features(points, shape_features, pca.lrf, normals, neighbour_index)
    return PointGeometry(
        points=points, neighbour_index=neighbour_index, pca=pca, normals=normals, edges=edges
    )

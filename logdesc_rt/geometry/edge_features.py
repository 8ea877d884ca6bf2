"""The N x k x 15 edge-feature tensor the descriptor network consumes (paper eqs. 4-8).

Channel layout of ``edges[i, j]`` for point i and its j-th neighbour m = neighbour_index[i, j]:

    0:3    x_i                      (position, network units)
    3:6    A_i, P_i, O_i            (anisotropy, planarity, omnivariance of the point)
    6:9    x_m - x_i                (the paper's f0_j - f0_i, position part)
    9:12   A_m - A_i, P_m - P_i, O_m - O_i
    12:15  LRF_i^T n_m              (the neighbour's normal in the point's LRF coordinates)

The paper writes R_lrf . n_j with the eigenvectors as the columns of R_lrf; the coordinates of
n_j in that frame are R_lrf^T n_j, which is what is computed here.
"""

from __future__ import annotations

import numpy as np

from ..config import EDGE_CHANNELS

EDGE_FEATURE_CHANNELS = EDGE_CHANNELS["paper"]  # the layout above; one number for all


def edge_features(
    points: np.ndarray,
    shape_features: np.ndarray,
    lrf: np.ndarray,
    normals: np.ndarray,
    neighbour_index: np.ndarray,
) -> np.ndarray:
    """Build the edge-feature tensor.

    Args:
        points: (N, 3) positions.
        shape_features: (N, 3) anisotropy, planarity, omnivariance.
        lrf: (N, 3, 3) local reference frames (columns u, v, w).
        normals: (N, 3) unit normals.
        neighbour_index: (N, k) neighbour indices.

    Returns:
        (N, k, 15) float32, channels as in the module docstring.
    """
    count, k = neighbour_index.shape
    point_features = np.concatenate([points, shape_features], axis=1)  # f0, (N, 6)
    edges = np.empty((count, k, EDGE_FEATURE_CHANNELS), dtype=np.float32)
    edges[:, :, 0:6] = point_features[:, None, :]
    edges[:, :, 6:12] = point_features[neighbour_index] - point_features[:, None, :]
    edges[:, :, 12:15] = normals[neighbour_index] @ lrf  # row n_m^T R_i = (R_i^T n_m)^T
    return edges

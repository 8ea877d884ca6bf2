"""Edge features that no rigid motion and no normal sign can change (the ``"invariant"`` layout).

The paper's edges (:mod:`.edge_features`) hold the absolute position x_i and the offset
x_m - x_i in the global frame, so its descriptors change when a cloud turns. Here every channel
is a function of distances, of angles between unit vectors that move with the surface, and of
the PCA shape: turning or shifting the cloud leaves the tensor unchanged up to float round-off.

A normal's sign cannot be read from a neighbourhood reliably (two noisy or partial views of
one surface disagree on it at a quarter of the points with the paper's centroid rule, see
``benchmarks/geometry_agreement.py``), so no channel depends on it: with n_i, n_m the unit
normals of point i and of its neighbour m, d = x_m - x_i, r = |d| and e = d / r, each channel
is even in n_i and in n_m separately.

Channel layout of ``edges[i, j]`` for point i and its j-th neighbour m = neighbour_index[i, j]
(R = the geometry's PCA radius, which makes every channel dimensionless):

    0      r / R                          (distance)
    1      |n_i . e|                      (how far the neighbour sits off i's tangent plane)
    2      |n_m . e|
    3      |n_i . n_m|                    (normal deviation: curvature across the edge)
    4      (n_i . e)(n_m . e)(n_i . n_m)  (sign of the bend, independent of normal signs)
    5:8    A_i, P_i, O_i / R^2            (anisotropy, planarity, omnivariance of the point)
    8:11   A_m - A_i, P_m - P_i, (O_m - O_i) / R^2
"""

from __future__ import annotations

import numpy as np

from ..config import EDGE_CHANNELS

INVARIANT_EDGE_CHANNELS = EDGE_CHANNELS["invariant"]  # the layout below; one number for all


def invariant_edge_features(
    points: np.ndarray,
    shape_features: np.ndarray,
    normals: np.ndarray,
    neighbour_index: np.ndarray,
    length_scale: float,
) -> np.ndarray:
    """Build the invariant edge-feature tensor.

    Args:
        points: (N, 3) positions, network units.
        shape_features: (N, 3) anisotropy, planarity, omnivariance (network units squared).
        normals: (N, 3) unit normals; their signs do not matter.
        neighbour_index: (N, k) neighbour indices.
        length_scale: R above (network units), > 0.

    Returns:
        (N, k, 11) float32, channels as in the module docstring.
    """
    count, k = neighbour_index.shape
    offsets = points[neighbour_index] - points[:, None, :]  # (N, k, 3)
    distance = np.linalg.norm(offsets, axis=2)  # (N, k)
    # Exact duplicates (r = 0) get e = 0: no direction, every angle channel reads 0.
    direction = offsets / np.where(distance > 0.0, distance, 1.0)[..., None]
    neighbour_normals = normals[neighbour_index]  # (N, k, 3)
    normal_i_offset = np.einsum("nkc,nc->nk", direction, normals)
    normal_m_offset = np.einsum("nkc,nkc->nk", direction, neighbour_normals)
    normal_i_normal_m = np.einsum("nkc,nc->nk", neighbour_normals, normals)

    scaled_shape = shape_features * np.array([1.0, 1.0, 1.0 / length_scale**2])
    edges = np.empty((count, k, INVARIANT_EDGE_CHANNELS), dtype=np.float32)
    edges[:, :, 0] = distance / length_scale
    edges[:, :, 1] = np.abs(normal_i_offset)
    edges[:, :, 2] = np.abs(normal_m_offset)
    edges[:, :, 3] = np.abs(normal_i_normal_m)
    edges[:, :, 4] = normal_i_offset * normal_m_offset * normal_i_normal_m
    edges[:, :, 5:8] = scaled_shape[:, None, :]
    edges[:, :, 8:11] = scaled_shape[neighbour_index] - scaled_shape[:, None, :]
    return edges

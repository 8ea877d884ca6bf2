"""k-nearest-neighbour queries of a cloud on itself (pykdtree).

General-purpose helpers; :func:`~logdesc_rt.geometry.compute_geometry` finds its
neighbourhoods with :func:`~logdesc_rt.geometry.kernels.neighbourhoods` instead.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from ..errors import TooFewPointsError


def nearest_neighbours(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest points of every point, the point itself included.

    Args:
        points: (N, 3) float64, validated.
        k: neighbours per point; clipped to N.

    Returns:
        distance: (N, K) float64, increasing along each row, K = min(k, N).
        index: (N, K) int64.
    """
    k = min(k, len(points))
    distance, index = KDTree(points).query(points, k=k)
    if k == 1:  # pykdtree drops the neighbour axis for k = 1
        distance, index = distance[:, None], index[:, None]
    return distance, index.astype(np.int64, copy=False)


def drop_self(index: np.ndarray, k: int) -> np.ndarray:
    """The k nearest *other* points, from a self-inclusive neighbour list.

    Args:
        index: (N, K) int64 from :func:`nearest_neighbours`, K >= k + 1.
        k: neighbours to keep.

    Returns:
        (N, k) int64. The query point is removed even when an exact duplicate of it ties at
        distance 0 and is listed first.
    """
    count = len(index)
    if index.shape[1] < k + 1:
        raise TooFewPointsError(f"points: {count} points, but {k} neighbours need at least {k + 1}")
    candidates = index[:, : k + 1]
    is_self = candidates == np.arange(count)[:, None]
    # Rows where self fell outside the k+1 (more than k exact duplicates): drop the farthest.
    is_self[~is_self.any(axis=1), -1] = True
    return candidates[~is_self].reshape(count, k)


def knn_excluding_self(points: np.ndarray, k: int) -> np.ndarray:
    """Indices (N, k) int64 of the k nearest other points of every point, nearest first."""
    if len(points) < k + 1:
        raise TooFewPointsError(
            f"points: {len(points)} points, but {k} neighbours need at least {k + 1}"
        )
    return drop_self(nearest_neighbours(points, k + 1)[1], k)

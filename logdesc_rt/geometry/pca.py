"""Covariance (PCA) features per point: anisotropy, planarity, omnivariance and the LRF.

Paper section 3.3, eq. (2): with eigenvalues l1 >= l2 >= l3 of the neighbourhood covariance,
A = (l1 - l3) / l1, P = (l2 - l3) / l1, O = (l1 l2 l3)^(1/3); the eigenvectors (u, v, w) of
l1, l2, l3 are the columns of the local reference frame (LRF).

Sign rule (the official code flips signs at random; this is deterministic and moves with the
cloud under any rigid motion):
- w, the normal axis, points away from the cloud's centroid: (x_i - centroid) . w >= 0.
  This is "outward" on closed objects, including flat faces, where a local rule (e.g. toward the
  neighbourhood's mass) has no preference.
- u points toward the neighbourhood's centroid: (mean_j x_j - x_i) . u >= 0.
- v = w x u, so that [u, v, w] is a proper rotation (det = +1).
Ties (a dot product of exactly 0) keep the sign the eigen-solver gave.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .kernels import neighbourhoods

# Neighbourhoods whose largest eigenvalue is below this (squared network units) carry no shape:
# a point alone within the radius, or only exact duplicates around it.
_MIN_EIGENVALUE = 1e-18


@dataclass(frozen=True)
class PcaFeatures:
    """Per-point covariance features of a cloud of N points.

    Attributes:
        anisotropy: (N,) in [0, 1]; 1 for a line.
        planarity: (N,) in [0, 1]; 1 for a plane.
        omnivariance: (N,) >= 0, squared length units.
        lrf: (N, 3, 3) rotation matrices, columns (u, v, w) = largest, middle, smallest
            variance direction; w is the PCA normal.
        neighbour_count: (N,) points used (the point included).
    """

    anisotropy: np.ndarray
    planarity: np.ndarray
    omnivariance: np.ndarray
    lrf: np.ndarray
    neighbour_count: np.ndarray


def pca_features(
    points: np.ndarray,
    radius: float,
    max_neighbours: int,
    min_neighbours: int = 8,
) -> PcaFeatures:
    """Covariance features of every point from its neighbours within ``radius``.

    Args:
        points: (N, 3) float64, validated.
        radius: neighbourhood radius, same units as ``points`` (strictly closer points count).
        max_neighbours: at most this many nearest neighbours (the point included).
        min_neighbours: the nearest this-many points are used even beyond the radius.

    Returns:
        :class:`PcaFeatures`. Points whose neighbourhood has no extent (only duplicates) get
        A = P = O = 0 and the identity LRF; all other values follow the formulas above.
    """
    return pca_from_covariance(points, *neighbourhoods(points, radius, max_neighbours, min_neighbours, 0)[:3])


def pca_from_covariance(
    points: np.ndarray, count: np.ndarray, mean: np.ndarray, covariance: np.ndarray
) -> PcaFeatures:
    """:class:`PcaFeatures` of (N, 3) points from their neighbourhoods' (N,) sizes, (N, 3)
    means and (N, 3, 3) covariances (:func:`~logdesc_rt.geometry.kernels.neighbourhoods`)."""
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)  # ascending
    eigenvalues = np.clip(eigenvalues, 0.0, None)
    l3, l2, l1 = eigenvalues[:, 0], eigenvalues[:, 1], eigenvalues[:, 2]
    has_shape = l1 > _MIN_EIGENVALUE
    safe_l1 = np.where(has_shape, l1, 1.0)
    anisotropy = np.where(has_shape, (l1 - l3) / safe_l1, 0.0)
    planarity = np.where(has_shape, (l2 - l3) / safe_l1, 0.0)
    omnivariance = np.cbrt(l1 * l2 * l3)

    u = eigenvectors[:, :, 2]
    w = eigenvectors[:, :, 0]
    centroid = points.mean(axis=0)
    w = w * _sign_not_negative(np.einsum("nc,nc->n", points - centroid, w))[:, None]
    u = u * _sign_not_negative(np.einsum("nc,nc->n", mean - points, u))[:, None]
    v = np.cross(w, u)
    lrf = np.stack([u, v, w], axis=2)
    lrf[~has_shape] = np.eye(3)

    return PcaFeatures(
        anisotropy=anisotropy,
        planarity=planarity,
        omnivariance=omnivariance,
        lrf=lrf,
        neighbour_count=count,
    )


def _sign_not_negative(values: np.ndarray) -> np.ndarray:
    """+1 where ``values`` >= 0, else -1 (so a tie keeps the current orientation)."""
    return np.where(values < 0.0, -1.0, 1.0)

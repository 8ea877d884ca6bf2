"""Edge features that no rigid motion and no normal sign can change (the ``"invariant"`` layout).

The paper's edges (:mod:`.edge_features`) hold the absolute position x_i and the offset
x_m - x_i in the global frame, so its descriptors change when a cloud turns. Here every channel
is a function of distances, of angles between unit vectors that move with the surface, and of
the PCA shape: turning or shifting the cloud leaves the tensor unchanged up to float round-off.

A normal's sign cannot be read from a neighbourhood reliably (two noisy or partial views of
one surface disagree on it at a quarter of the points with the paper's centroid rule:
``docs/decisions.md``), so no channel depends on it: with n_i, n_m the unit
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

The ``"chiral"`` layout (v4) appends two channels that change sign under a reflection, so that a
point can be told from its mirror twin (every channel above is unchanged by a reflection), while
staying even in every axis sign, hence invariant to rotations, translations and normal signs.
With u_i the LRF's major axis, w_i its normal axis (:mod:`.pca`) and l1 >= l2 >= l3 its eigenvalues:

    11     cbrt(((n_i x n_m) . e)(n_i . e)(n_m . e))                     (twist across the edge)
    12     cbrt(g_i ((u_i x w_i) . e)(u_i . e)(w_i . e)),  g_i = (l1 - l2)(l2 - l3) / l1^2
                                                                          (the edge's octant in i's frame)

A triple product is a pseudo-scalar (odd under a reflection); each dot product that repeats an
axis cancels that axis's sign. The gate g_i = (A_i - P_i) P_i vanishes where u or w is undefined
(two equal eigenvalues), so channel 12 is continuous where the frame flips. On a plane, where
every point is its own mirror image, both read 0. The cube root keeps the small products of
smooth surfaces (third order in the bend) in a range the first layer can use.
"""

from __future__ import annotations

import numpy as np

from ..config import EDGE_CHANNELS
from .kernels import edge_channels

INVARIANT_EDGE_CHANNELS = EDGE_CHANNELS["invariant"]  # the layout below; one number for all
CHIRAL_EDGE_CHANNELS = EDGE_CHANNELS["chiral"]


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
    return invariant_edge_tensor(points, shape_features, normals, None, None, neighbour_index, length_scale)


def chiral_edge_channels(
    points: np.ndarray,
    normals: np.ndarray,
    lrf: np.ndarray,
    eigen_gate: np.ndarray,
    neighbour_index: np.ndarray,
) -> np.ndarray:
    """The two reflection-odd channels 11 and 12 of the ``"chiral"`` layout (module docstring).

    Args:
        points: (N, 3) positions, network units.
        normals: (N, 3) unit normals; their signs do not matter.
        lrf: (N, 3, 3) local frames, columns (u, v, w); the signs of u and w do not matter.
        eigen_gate: (N,) g_i = (A_i - P_i) P_i, in [0, 1].
        neighbour_index: (N, k) neighbour indices.

    Returns:
        (N, k, 2) float32.
    """
    return invariant_edge_tensor(points, None, normals, lrf, eigen_gate, neighbour_index, 1.0)


def invariant_edge_tensor(
    points: np.ndarray,
    shape_features: np.ndarray | None,
    normals: np.ndarray,
    lrf: np.ndarray | None,
    eigen_gate: np.ndarray | None,
    neighbour_index: np.ndarray,
    length_scale: float,
) -> np.ndarray:
    """Channels 0-10 (given ``shape_features``) then 11-12 (given ``lrf`` and ``eigen_gate``)
    of the module docstring's layout, in one pass: (N, k, 11, 13 or 2) float32. Arguments as in
    :func:`invariant_edge_features` and :func:`chiral_edge_channels`."""
    invariant = shape_features is not None
    chiral = lrf is not None
    count = len(points)
    return edge_channels(
        _float64(points, (count, 3)),
        _float64(shape_features, (count, 3)),
        _float64(normals, (count, 3)),
        _float64(lrf, (count, 3, 3)),
        _float64(eigen_gate, (count,)),
        np.ascontiguousarray(neighbour_index, dtype=np.int64),
        float(length_scale),
        invariant,
        chiral,
    )


def _float64(values: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """``values`` as a contiguous float64 array; zeros of ``shape`` (unread) for None."""
    return np.zeros(shape) if values is None else np.ascontiguousarray(values, dtype=np.float64)

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

from dataclasses import dataclass

import numpy as np

from ..config import EDGE_CHANNELS

INVARIANT_EDGE_CHANNELS = EDGE_CHANNELS["invariant"]  # the layout below; one number for all
CHIRAL_EDGE_CHANNELS = EDGE_CHANNELS["chiral"]


@dataclass(frozen=True)
class EdgeVectors:
    """What both edge layouts read about each edge (i, m = neighbour_index[i, j]), computed once.

    Attributes:
        distance: (N, k) r = |x_m - x_i|.
        direction: (N, k, 3) e = (x_m - x_i) / r (0 for exact duplicates: no direction).
        neighbour_normals: (N, k, 3) n_m.
        normal_i_offset: (N, k) n_i . e.
        normal_m_offset: (N, k) n_m . e.
    """

    distance: np.ndarray
    direction: np.ndarray
    neighbour_normals: np.ndarray
    normal_i_offset: np.ndarray
    normal_m_offset: np.ndarray


def edge_vectors(points: np.ndarray, normals: np.ndarray, neighbour_index: np.ndarray) -> EdgeVectors:
    """:class:`EdgeVectors` of (N, 3) points with (N, 3) unit normals and (N, k) neighbours."""
    offsets = np.take(points, neighbour_index, axis=0) - points[:, None, :]  # (N, k, 3); take: ~5x faster than [ ]
    distance = np.sqrt(_dot_last(offsets, offsets))
    direction = offsets / np.where(distance > 0.0, distance, 1.0)[..., None]
    neighbour_normals = np.take(normals, neighbour_index, axis=0)
    return EdgeVectors(
        distance=distance,
        direction=direction,
        neighbour_normals=neighbour_normals,
        normal_i_offset=_dot_each(direction, normals),
        normal_m_offset=_dot_last(direction, neighbour_normals),
    )


def _dot_last(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(N, k) dot products of (N, k, 3) vectors, row by row (a batched matmul: several times
    faster than einsum at these shapes)."""
    return (first[..., None, :] @ second[..., :, None])[..., 0, 0]


def _dot_each(vectors: np.ndarray, per_point: np.ndarray) -> np.ndarray:
    """(N, k) dot products of (N, k, 3) vectors with one (N, 3) vector per point."""
    return (vectors @ per_point[:, :, None])[..., 0]


def invariant_edge_features(
    points: np.ndarray,
    shape_features: np.ndarray,
    normals: np.ndarray,
    neighbour_index: np.ndarray,
    length_scale: float,
    vectors: EdgeVectors | None = None,
) -> np.ndarray:
    """Build the invariant edge-feature tensor.

    Args:
        points: (N, 3) positions, network units.
        shape_features: (N, 3) anisotropy, planarity, omnivariance (network units squared).
        normals: (N, 3) unit normals; their signs do not matter.
        neighbour_index: (N, k) neighbour indices.
        length_scale: R above (network units), > 0.
        vectors: :func:`edge_vectors` of the same arguments, when the caller has them.

    Returns:
        (N, k, 11) float32, channels as in the module docstring.
    """
    count, k = neighbour_index.shape
    edge = vectors if vectors is not None else edge_vectors(points, normals, neighbour_index)
    normal_i_normal_m = _dot_each(edge.neighbour_normals, normals)

    scaled_shape = shape_features * np.array([1.0, 1.0, 1.0 / length_scale**2])
    edges = np.empty((count, k, INVARIANT_EDGE_CHANNELS), dtype=np.float32)
    edges[:, :, 0] = edge.distance / length_scale
    edges[:, :, 1] = np.abs(edge.normal_i_offset)
    edges[:, :, 2] = np.abs(edge.normal_m_offset)
    edges[:, :, 3] = np.abs(normal_i_normal_m)
    edges[:, :, 4] = edge.normal_i_offset * edge.normal_m_offset * normal_i_normal_m
    edges[:, :, 5:8] = scaled_shape[:, None, :]
    edges[:, :, 8:11] = np.take(scaled_shape, neighbour_index, axis=0) - scaled_shape[:, None, :]
    return edges


def chiral_edge_channels(
    points: np.ndarray,
    normals: np.ndarray,
    lrf: np.ndarray,
    eigen_gate: np.ndarray,
    neighbour_index: np.ndarray,
    vectors: EdgeVectors | None = None,
) -> np.ndarray:
    """The two reflection-odd channels 11 and 12 of the ``"chiral"`` layout (module docstring).

    Args:
        points: (N, 3) positions, network units.
        normals: (N, 3) unit normals; their signs do not matter.
        lrf: (N, 3, 3) local frames, columns (u, v, w); the signs of u and w do not matter.
        eigen_gate: (N,) g_i = (A_i - P_i) P_i, in [0, 1].
        neighbour_index: (N, k) neighbour indices.
        vectors: :func:`edge_vectors` of the same points, normals and neighbours, when the
            caller has them.

    Returns:
        (N, k, 2) float32.
    """
    edge = vectors if vectors is not None else edge_vectors(points, normals, neighbour_index)
    twist = _dot_last(np.cross(normals[:, None, :], edge.neighbour_normals), edge.direction)
    major, normal_axis = lrf[:, :, 0], lrf[:, :, 2]
    # The edge's coordinates along the frame axes (u x w, u, w): one product for all three.
    axes = np.stack([np.cross(major, normal_axis), major, normal_axis], axis=2)  # (N, 3, 3)
    along = edge.direction @ axes  # (N, k, 3)
    octant = along[..., 0] * along[..., 1] * along[..., 2]
    channels = np.empty(neighbour_index.shape + (2,), dtype=np.float32)
    channels[:, :, 0] = np.cbrt(twist * edge.normal_i_offset * edge.normal_m_offset)
    channels[:, :, 1] = np.cbrt(eigen_gate[:, None] * octant)
    return channels

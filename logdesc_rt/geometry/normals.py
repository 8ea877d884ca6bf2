"""Umbrella (triangle-fan) normals, paper section 3.3 eq. (3).

The k nearest neighbours of a point, sorted by azimuth around the point's LRF normal axis w,
form k - 1 triangles (point, neighbour j, neighbour j+1). Each triangle's unit normal is
weighted by a softmax over triangle areas (divided by a temperature; the official 1e-4 in unit
sphere units makes the largest triangles dominate, as they are the least sensitive to noise).
Sorting counter-clockwise about w makes the fan's normals agree with w, and the result is
finally flipped to agree with w, so normals inherit the LRF's deterministic sign rule
(outward from the cloud's centroid, see :mod:`.pca`).
"""

from __future__ import annotations

import numpy as np
from scipy.special import softmax

# Triangles thinner than this (squared units) have no reliable normal and get weight 0.
_MIN_DOUBLE_AREA = 1e-24


def umbrella_normals(
    points: np.ndarray, neighbour_index: np.ndarray, lrf: np.ndarray, area_temperature: float
) -> np.ndarray:
    """Unit normal of every point from its triangle umbrella.

    Args:
        points: (N, 3) float64.
        neighbour_index: (N, k) int64, the point's k nearest other points.
        lrf: (N, 3, 3) local reference frames, columns (u, v, w); w orients the result.
        area_temperature: softmax temperature on triangle areas, squared length units.

    Returns:
        (N, 3) float64 unit normals with n . w >= 0. Where every triangle is degenerate
        (collinear or duplicate neighbours) the normal falls back to w.
    """
    offsets = np.take(points, neighbour_index, axis=0) - points[:, None, :]  # (N, k, 3); take: ~5x faster than [ ]
    # Azimuth of each neighbour in the tangent plane (u, v) of the LRF.
    in_plane = offsets @ lrf[:, :, :2]  # (N, k, 2) coordinates along u and v
    order = np.argsort(np.arctan2(in_plane[..., 1], in_plane[..., 0]), axis=1, kind="stable")
    fan = np.take_along_axis(offsets, order[..., None], axis=1)

    cross = np.cross(fan[:, :-1], fan[:, 1:])  # (N, k-1, 3), norm = 2 * area
    double_area = np.linalg.norm(cross, axis=2)
    usable = double_area > _MIN_DOUBLE_AREA
    unit_normals = cross / np.where(usable, double_area, 1.0)[..., None]

    logits = np.where(usable, 0.5 * double_area / area_temperature, -np.inf)
    any_usable = usable.any(axis=1)
    logits[~any_usable] = 0.0  # keep softmax finite; these rows fall back to w below
    weights = softmax(logits, axis=1)

    normals = (weights[:, None, :] @ unit_normals)[:, 0]
    length = np.linalg.norm(normals, axis=1)
    w_axis = lrf[:, :, 2]
    fallback = ~any_usable | (length < 1e-12)
    normals = np.where(fallback[:, None], w_axis, normals / np.where(fallback, 1.0, length)[:, None])
    flip = np.einsum("nc,nc->n", normals, w_axis) < 0.0
    normals[flip] *= -1.0
    return normals

"""Checks at the door: every public function validates its point arrays here, once.

Internal helpers may then assume finite float64 arrays of shape (N, 3).
"""

from __future__ import annotations

import numpy as np

from .errors import (
    DegenerateGeometryError,
    NonFinitePointsError,
    PointCloudShapeError,
    TooFewPointsError,
)

# Relative size of the second principal extent below which a cloud counts as a line.
COLLINEAR_RELATIVE_TOLERANCE = 1e-6
# Larger coordinates overflow the float32 features once squared (omnivariance is in units^2),
# and are certainly a unit or parsing mistake (1e15 nm is 1000 km).
MAX_ABS_COORDINATE = 1e15


def as_points(points, *, name: str = "points", min_points: int = 1) -> np.ndarray:
    """Return ``points`` as a C-contiguous float64 array of shape (N, 3), or raise.

    Args:
        points: array-like of shape (N, 3), real numbers (float or integer dtype).
        name: argument name used in error messages.
        min_points: the least N the caller can work with.

    Raises:
        PointCloudShapeError: not a 2-D array with 3 columns, or not a real numeric dtype.
        NonFinitePointsError: NaN or inf coordinates, or any beyond +-MAX_ABS_COORDINATE.
        TooFewPointsError: fewer than ``min_points`` rows.
    """
    try:
        array = np.asarray(points)
    except (TypeError, ValueError) as error:  # ragged nested lists and the like
        raise PointCloudShapeError(f"{name}: cannot be read as an (N, 3) array ({error})") from error
    if array.dtype == bool or not (
        np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)
    ):
        raise PointCloudShapeError(
            f"{name}: dtype {array.dtype} is not a real number type; expected float or int coordinates"
        )
    if array.ndim != 2 or array.shape[1] != 3:
        raise PointCloudShapeError(f"{name}: shape {array.shape} is not (N, 3)")
    if array.shape[0] < min_points:
        raise TooFewPointsError(
            f"{name}: {array.shape[0]} points, but at least {min_points} are needed"
        )
    array = np.ascontiguousarray(array, dtype=np.float64)
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise NonFinitePointsError(
            f"{name}: {bad.size} point(s) have NaN or inf coordinates (first at row {bad[0]})"
        )
    largest = np.abs(array).max(initial=0.0)
    if largest > MAX_ABS_COORDINATE:
        raise NonFinitePointsError(
            f"{name}: coordinate magnitude {largest:.3g} exceeds {MAX_ABS_COORDINATE:.0e}; "
            "check the file's units and format"
        )
    return array


def check_not_degenerate(points: np.ndarray, *, name: str = "points") -> None:
    """Raise if the cloud has no extent in two directions (all duplicates, or collinear).

    Args:
        points: (N, 3) float64, already validated by :func:`as_points`.
    """
    centred = points - points.mean(axis=0)
    # The singular values of the centred cloud, from its 3 x 3 scatter matrix: one pass over
    # the points instead of an (N, 3) SVD (a ratio of 1e-6 between them is 1e-12 between the
    # eigenvalues, far above float64's rounding).
    eigenvalues = np.linalg.eigvalsh(centred.T @ centred)[::-1]
    singular_values = np.sqrt(np.clip(eigenvalues, 0.0, None))
    if singular_values[0] <= np.finfo(np.float64).eps * max(1.0, np.abs(points).max()) * len(points):
        raise DegenerateGeometryError(f"{name}: all {len(points)} points coincide")
    if singular_values[1] <= COLLINEAR_RELATIVE_TOLERANCE * singular_values[0]:
        raise DegenerateGeometryError(
            f"{name}: all points lie on one line; surfaces, normals and rotations about that line are undefined"
        )


def check_distinct_points(points: np.ndarray, *, needed: int, name: str = "points") -> None:
    """Raise unless the cloud has at least ``needed`` distinct points."""
    distinct = np.unique(points, axis=0).shape[0]
    if distinct < needed:
        raise TooFewPointsError(
            f"{name}: only {distinct} distinct points (of {len(points)}), but at least {needed} are needed"
        )

"""How well a transformation aligns two clouds, like Open3D's ``evaluate_registration``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from ..validation import as_points

# How far from orthonormal (max |R^T R - I| entry) and from det = +1 a rotation may be.
ROTATION_TOLERANCE = 1e-6


@dataclass(frozen=True)
class RegistrationEvaluation:
    """Quality of ``transformation`` for a source / target pair.

    Attributes:
        fitness: inlier correspondences / number of source points, in [0, 1].
        inlier_rmse: sqrt(mean squared distance of the inlier correspondences), in the
            clouds' unit; NaN when there are none (0 would read as a perfect fit).
        correspondence_set: (K, 2) int64 rows ``[source_index, target_index]``: each
            transformed source point and its nearest target point, when closer than the
            maximum correspondence distance.
        transformation: (4, 4) float64, the transformation evaluated.
    """

    fitness: float
    inlier_rmse: float
    correspondence_set: np.ndarray
    transformation: np.ndarray


def check_rigid_transformation(transformation, *, name: str = "transformation") -> np.ndarray:
    """Return ``transformation`` as a (4, 4) float64 array, or raise ValueError.

    Requires finite entries, a last row of [0, 0, 0, 1], and a rotation block R with
    ``R^T R = I`` and ``det R = +1`` within :data:`ROTATION_TOLERANCE`.
    """
    try:
        matrix = np.array(transformation, dtype=np.float64)  # a copy: callers keep theirs
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name}: cannot be read as a (4, 4) float array ({error})") from error
    if matrix.shape != (4, 4):
        raise ValueError(f"{name}: shape {matrix.shape} is not (4, 4)")
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{name}: contains NaN or inf")
    if np.max(np.abs(matrix[3] - [0.0, 0.0, 0.0, 1.0])) > ROTATION_TOLERANCE:
        raise ValueError(f"{name}: last row {matrix[3].tolist()} is not [0, 0, 0, 1]")
    rotation = matrix[:3, :3]
    orthonormality_error = np.max(np.abs(rotation.T @ rotation - np.eye(3)))
    if orthonormality_error > ROTATION_TOLERANCE:
        raise ValueError(
            f"{name}: the 3x3 block is not a rotation (max |R^T R - I| = {orthonormality_error:.3g}, "
            f"tolerance {ROTATION_TOLERANCE:g}); scaling and shear are not rigid"
        )
    if np.linalg.det(rotation) < 0:
        raise ValueError(f"{name}: the 3x3 block has det -1, a reflection, not a rotation")
    return matrix


def evaluate_registration(
    source,
    target,
    max_correspondence_distance: float,
    transformation=np.eye(4),
) -> RegistrationEvaluation:
    """Fitness and inlier RMSE of ``transformation`` (Open3D's ``evaluate_registration``).

    Every source point is moved by ``transformation`` and paired with its nearest target
    point (k-d tree); the pair is an inlier when their distance is below
    ``max_correspondence_distance``.

    Args:
        source: (N, 3) points, N >= 1.
        target: (M, 3) points, M >= 1, same unit.
        max_correspondence_distance: > 0, same unit (``inf`` makes every pair an inlier).
        transformation: (4, 4) rigid transform, source -> target. Default identity.

    Returns:
        :class:`RegistrationEvaluation`.

    Raises:
        PointCloudShapeError, NonFinitePointsError, TooFewPointsError: bad clouds.
        ValueError: ``max_correspondence_distance`` not > 0, or ``transformation`` not a
            finite (4, 4) rigid transform.
    """
    source = as_points(source, name="source", min_points=1)
    target = as_points(target, name="target", min_points=1)
    max_correspondence_distance = float(max_correspondence_distance)
    if not max_correspondence_distance > 0:  # also rejects NaN
        raise ValueError(
            "evaluate_registration: max_correspondence_distance must be > 0, "
            f"got {max_correspondence_distance}"
        )
    matrix = check_rigid_transformation(transformation)
    with np.errstate(over="ignore", invalid="ignore"):
        moved = np.ascontiguousarray(source @ matrix[:3, :3].T + matrix[:3, 3])
    # Points pushed to inf by overflow can have no neighbour; keep them out of the tree query.
    reachable = np.flatnonzero(np.isfinite(moved).all(axis=1))
    if reachable.size:
        distances, nearest = KDTree(target).query(moved[reachable], k=1)
    else:
        distances, nearest = np.empty(0), np.empty(0, dtype=np.int64)
    distances = np.asarray(distances, dtype=np.float64).reshape(-1)
    nearest = np.asarray(nearest, dtype=np.int64).reshape(-1)
    inlier = distances < max_correspondence_distance
    correspondence_set = np.stack([reachable[inlier], nearest[inlier]], axis=1).astype(np.int64)
    inlier_count = int(np.count_nonzero(inlier))
    with np.errstate(over="ignore"):
        inlier_rmse = float(np.sqrt(np.mean(distances[inlier] ** 2))) if inlier_count else float("nan")
    return RegistrationEvaluation(
        fitness=inlier_count / len(source),
        inlier_rmse=inlier_rmse,
        correspondence_set=correspondence_set.reshape(-1, 2),
        transformation=matrix,
    )

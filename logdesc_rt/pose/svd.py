"""Closed-form rigid transform from correspondences (Kabsch / Umeyama without scale).

Also holds what the robust estimators (:mod:`.fsr`, :mod:`.ransac`) share: the batched
solver, the inlier test and the :class:`PoseEstimate` result type.

Convention everywhere in :mod:`logdesc_rt.pose`: a (4, 4) transformation ``T`` with rotation
``R = T[:3, :3]`` and translation ``t = T[:3, 3]`` maps a source point ``x`` into the target
frame, ``y ~ R @ x + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import (
    DegenerateGeometryError,
    InvalidPointCloudError,
    NonFinitePointsError,
    PointCloudShapeError,
    TooFewPointsError,
)
from ..validation import COLLINEAR_RELATIVE_TOLERANCE, as_points

# Spread (RMS distance to the weighted centroid) below this fraction of the largest
# |coordinate| counts as "all points coincide": it is float rounding, not geometry.
COINCIDENT_RELATIVE_TOLERANCE = 64 * np.finfo(np.float64).eps

# The cross-covariance must have rank 2 for the rotation to be unique. Its singular values
# scale like squared spreads, hence the squared collinearity tolerance.
CROSS_COVARIANCE_RANK_TOLERANCE = COLLINEAR_RELATIVE_TOLERANCE**2


@dataclass(frozen=True)
class PoseEstimate:
    """Result of a robust pose estimator.

    Attributes:
        transformation: (4, 4) float64 rigid transform, source -> target (rotation det = +1).
        inlier_mask: (M,) bool, True where a correspondence lies within the estimator's
            inlier threshold after ``transformation``.
        inlier_count: number of True entries of ``inlier_mask``.
        iterations_run: sampling rounds (FSR) or hypotheses drawn (RANSAC); 0 when FSR took
            its few-matches path (one SVD, no sampling).
    """

    transformation: np.ndarray
    inlier_mask: np.ndarray
    inlier_count: int
    iterations_run: int


def _power_of_two_scales(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(B,) powers of two at or below each problem's largest |coordinate| (1 if all zero).

    Dividing by a power of two is exact; it keeps the covariance sums from overflowing for
    coordinates near 1e308 and makes the degeneracy tolerances relative to the data.
    """
    magnitude = np.maximum(np.abs(source).max(axis=(1, 2)), np.abs(target).max(axis=(1, 2)))
    exponents = np.frexp(magnitude)[1] - 1
    return np.where(magnitude > 0, np.ldexp(1.0, exponents), 1.0)


def solve_rigid_batch(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None, check_degenerate: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve B weighted rigid-alignment problems at once (no input validation).

    Minimises sum_k w_k ||R x_k + t - y_k||^2 over rotations R (det +1) and translations t,
    for each of the B problems, with one batched ``np.linalg.svd``.

    Args:
        source: (B, K, 3) finite float64 source points x.
        target: (B, K, 3) finite float64 target points y.
        weights: (B, K) finite, non-negative, each row with a positive sum; None for equal
            weights.
        check_degenerate: False skips the degeneracy test (two more SVDs of the centred
            points), for callers that take every step as it comes (an ICP screen).

    Returns:
        rotations (B, 3, 3), translations (B, 3), degenerate (B,) bool. A degenerate problem
        (corresponded points all coincide or lie on a line in either cloud, or a
        cross-covariance of rank < 2) has no unique rotation; its R and t are still finite
        but meaningless. All False when ``check_degenerate`` is False.
    """
    batch, count = source.shape[:2]
    scales = _power_of_two_scales(source, target)
    source = source / scales[:, None, None]
    target = target / scales[:, None, None]
    if weights is None:
        weights = np.full((batch, count), 1.0 / count)
    else:
        # Divide by the maximum first so that a sum of huge weights cannot overflow.
        weights = weights / weights.max(axis=1, keepdims=True)
        weights = weights / weights.sum(axis=1, keepdims=True)

    # Batched matrix products rather than einsum: the same sums; for the verification screen's
    # few-hundred-point problems: about 12 ms a pair against einsum's 21.
    source_centroid = (weights[:, None, :] @ source)[:, 0]
    target_centroid = (weights[:, None, :] @ target)[:, 0]
    source_centred = source - source_centroid[:, None, :]
    target_centred = target - target_centroid[:, None, :]
    cross_covariance = (source_centred * weights[:, :, None]).transpose(0, 2, 1) @ target_centred
    left, singular_values, right_transposed = np.linalg.svd(cross_covariance)

    # R = V diag(1, 1, d) U^T with d = det(V U^T) = +-1: the last axis is flipped when the
    # unconstrained optimum would be a reflection.
    reflection_sign = np.sign(np.linalg.det(left) * np.linalg.det(right_transposed))
    correction = np.ones((batch, 3))
    correction[:, 2] = reflection_sign
    rotations = (right_transposed.transpose(0, 2, 1) * correction[:, None, :]) @ left.transpose(0, 2, 1)
    translations = scales[:, None] * (target_centroid - (rotations @ source_centroid[:, :, None])[:, :, 0])

    degenerate = np.zeros(batch, dtype=bool)
    if not check_degenerate:
        return rotations, translations, degenerate
    root_weights = np.sqrt(weights)[:, :, None]
    spread_source = np.linalg.svd(root_weights * source_centred, compute_uv=False)
    spread_target = np.linalg.svd(root_weights * target_centred, compute_uv=False)
    for spread in (spread_source, spread_target):
        degenerate |= spread[:, 0] <= COINCIDENT_RELATIVE_TOLERANCE
        degenerate |= spread[:, 1] <= COLLINEAR_RELATIVE_TOLERANCE * spread[:, 0]
    degenerate |= singular_values[:, 1] <= CROSS_COVARIANCE_RANK_TOLERANCE * singular_values[:, 0]
    return rotations, translations, degenerate


def to_homogeneous(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) float64 transformation from a (3, 3) rotation and a (3,) translation."""
    transformation = np.eye(4)
    transformation[:3, :3] = rotation
    transformation[:3, 3] = translation
    return transformation


def correspondence_residuals_squared(
    rotations: np.ndarray, translations: np.ndarray, source: np.ndarray, target: np.ndarray
) -> np.ndarray:
    """(B, M) squared distances ||R_b x_m + t_b - y_m||^2 for B hypotheses and M pairs.

    Overflow (coordinates near 1e308) yields inf or nan, which no inlier test accepts.
    """
    batch, count = len(rotations), len(source)
    with np.errstate(over="ignore", invalid="ignore"):
        # All B rotations in one (M, 3) x (3, 3B) product, axis-major so that the sum over the
        # three axes adds contiguous planes (an einsum here cost RANSAC ~20 of its 28 ms).
        rotated = (source @ rotations.transpose(2, 1, 0).reshape(3, 3 * batch)).reshape(count, 3, batch)
        offset = rotated + (translations.T[None, :, :] - target[:, :, None])
        np.square(offset, out=offset)
        return offset.sum(axis=1).T


def refine_on_inliers(
    transformation: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray | None,
    inlier_threshold: float,
    rounds: int,
) -> np.ndarray:
    """Local optimisation: re-solve the SVD on the current inliers until they stop changing.

    A refit is kept when it does not raise the truncated least-squares cost
    ``sum_i w_i min(r_i^2, tau^2)`` (MSAC's score). The (weighted) SVD on the inliers can only
    lower that cost, so refits are normally all kept, even one that drops a stray outlier
    that the loose threshold had let in; counting inliers instead would reject exactly
    those refits.

    Args:
        transformation: (4, 4) starting hypothesis.
        source, target: (M, 3) float64 corresponded points.
        weights: (M,) non-negative confidences, or None for equal weights.
        inlier_threshold: tau, same unit as the points.
        rounds: at most this many re-solves.

    Returns:
        (4, 4) refined transformation; the input itself when no refit is possible (fewer
        than 3 inliers with positive weight, or a degenerate inlier set).
    """
    threshold_squared = inlier_threshold**2

    def score(candidate: np.ndarray) -> tuple[float, np.ndarray]:
        residuals = correspondence_residuals_squared(
            candidate[None, :3, :3], candidate[None, :3, 3], source, target
        )[0]
        inliers = residuals < threshold_squared
        truncated = np.where(inliers, residuals, threshold_squared)
        cost = float(np.sum(truncated if weights is None else weights * truncated))
        return cost, inliers

    best = transformation
    best_cost, best_inliers = score(best)
    for _ in range(rounds):
        inlier_weights = None if weights is None else weights[best_inliers]
        usable = best_inliers if weights is None else best_inliers & (weights > 0)
        if np.count_nonzero(usable) < 3:
            break
        rotations, translations, degenerate = solve_rigid_batch(
            source[best_inliers][None],
            target[best_inliers][None],
            None if inlier_weights is None else inlier_weights[None],
        )
        if degenerate[0] or not np.all(np.isfinite(translations)):
            break
        candidate = to_homogeneous(rotations[0], translations[0])
        candidate_cost, candidate_inliers = score(candidate)
        if not candidate_cost <= best_cost:
            break
        converged = np.array_equal(candidate_inliers, best_inliers)
        best, best_cost, best_inliers = candidate, candidate_cost, candidate_inliers
        if converged:
            break  # the next solve would use the same inliers
    return best


def transformation_inliers(
    transformation: np.ndarray, source: np.ndarray, target: np.ndarray, threshold_squared: float
) -> np.ndarray:
    """(M,) bool: ||R x + t - y||^2 < tau^2 for each pair."""
    residuals = correspondence_residuals_squared(
        transformation[None, :3, :3], transformation[None, :3, 3], source, target
    )[0]
    return residuals < threshold_squared


def validate_correspondences(
    source, target, *, source_name: str, target_name: str, caller: str
) -> tuple[np.ndarray, np.ndarray]:
    """Check two corresponded clouds: (M, 3) each, finite, equal M >= 3.

    Returns both as C-contiguous float64 arrays.

    Raises:
        PointCloudShapeError: not (M, 3), or different lengths.
        NonFinitePointsError: NaN or inf coordinates.
        TooFewPointsError: M < 3.
    """
    source = as_points(source, name=source_name, min_points=0)
    target = as_points(target, name=target_name, min_points=0)
    if len(source) != len(target):
        raise PointCloudShapeError(
            f"{caller}: {source_name} has {len(source)} points but {target_name} has "
            f"{len(target)}; correspondences must pair row i with row i"
        )
    if len(source) < 3:
        raise TooFewPointsError(
            f"{caller}: {len(source)} correspondences, but a rigid transform needs at least 3"
        )
    return source, target


def validate_weights(weights, count: int, *, name: str, caller: str) -> np.ndarray:
    """Return ``weights`` as (count,) float64 after checking shape, finiteness and sign.

    Raises:
        PointCloudShapeError: not a real 1-D array of length ``count``.
        NonFinitePointsError: NaN or inf entries.
        InvalidPointCloudError: a negative entry.
    """
    try:
        array = np.asarray(weights)
    except (TypeError, ValueError) as error:
        raise PointCloudShapeError(f"{caller}: {name} cannot be read as an array ({error})") from error
    if array.dtype == bool or not (
        np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)
    ):
        raise PointCloudShapeError(f"{caller}: {name} has dtype {array.dtype}; expected real numbers")
    if array.shape != (count,):
        raise PointCloudShapeError(
            f"{caller}: {name} has shape {array.shape}; expected ({count},), one per correspondence"
        )
    array = np.asarray(array, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise NonFinitePointsError(f"{caller}: {name} contains NaN or inf")
    if np.any(array < 0):
        raise InvalidPointCloudError(f"{caller}: {name} contains negative values; weights must be >= 0")
    return array


def rigid_transform_svd(source, target, weights=None) -> np.ndarray:
    """Least-squares rigid transform mapping ``source`` onto ``target`` (Kabsch / Umeyama).

    Minimises ``sum_i w_i ||R @ source[i] + t - target[i]||^2`` over proper rotations R
    (det = +1: a reflection is never returned, even for a mirrored target) and translations
    t. Exact (to rounding) for noise-free correspondences; zero-weight pairs have no
    influence at all.

    Args:
        source: (M, 3) points, M >= 3, any unit.
        target: (M, 3) points corresponding row by row to ``source``, same unit.
        weights: optional (M,) finite, non-negative weights with at least 3 positive
            entries; None weighs every pair equally.

    Returns:
        (4, 4) float64 transformation T with ``target ~ T[:3, :3] @ source + T[:3, 3]``.

    Raises:
        PointCloudShapeError: a cloud is not (M, 3), the lengths differ, or the weights are
            not (M,).
        NonFinitePointsError: NaN or inf coordinates or weights.
        TooFewPointsError: fewer than 3 correspondences (with positive weight).
        InvalidPointCloudError: negative weights, or coordinates so large that the
            translation overflows float64.
        DegenerateGeometryError: the (positively weighted) points all coincide or lie on one
            line in either cloud, so the rotation is not unique.
    """
    caller = "rigid_transform_svd"
    source, target = validate_correspondences(
        source, target, source_name="source", target_name="target", caller=caller
    )
    if weights is not None:
        weights = validate_weights(weights, len(source), name="weights", caller=caller)
        positive = weights > 0
        if np.count_nonzero(positive) < 3:
            raise TooFewPointsError(
                f"{caller}: only {np.count_nonzero(positive)} correspondences have a positive "
                "weight, but a rigid transform needs at least 3"
            )
        # Zero-weight pairs are dropped outright, so they cannot leak in through rounding.
        source, target, weights = source[positive], target[positive], weights[positive][None]
    rotations, translations, degenerate = solve_rigid_batch(source[None], target[None], weights)
    if degenerate[0]:
        raise DegenerateGeometryError(
            f"{caller}: the corresponded points all coincide or lie on one line (in source or "
            "target); the rotation about that line is undefined"
        )
    if not np.all(np.isfinite(translations)):
        raise InvalidPointCloudError(
            f"{caller}: coordinates are too large; the translation overflows float64"
        )
    return to_homogeneous(rotations[0], translations[0])

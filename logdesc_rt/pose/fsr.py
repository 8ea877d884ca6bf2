"""Farthest-sampling-guided registration (FSR): the paper's pose estimator (Algorithm 1).

FSR (from RoCNet++) takes the matched pairs that the matching module returns. Each round
farthest-point-samples k of the matched source points, solves the rigid transform by SVD on
those k pairs, and counts the pairs that lie within tau after the transform; the transform
with the most inliers wins. Sampling spread-out points makes each round's SVD well
conditioned, and the few rounds make it cheap. It is meant for mostly correct matches (the
Sinkhorn output); every round fits all k sampled pairs, outliers included, so with many
outliers and few matches (e.g. half wrong among 200) it can fail where :func:`ransac` holds.

Differences from the official implementation, all deliberate:

- Each round's farthest-point sampling starts at a point drawn from a seeded
  ``np.random.default_rng(seed)``: rounds differ, yet the result is reproducible.
- The SVD never returns a reflection (det = +1), and fewer than 3 matches raise
  :class:`~logdesc_rt.errors.TooFewPointsError` instead of returning nothing defined.
- Inliers are the matched pairs within tau, as in the paper's Algorithm 1 (the official code
  counts, for each transformed matched source point, its nearest neighbour in the whole
  target cloud).
- ``refit_on_inliers`` (on by default) refines the winner by re-solving on its inliers; see
  :class:`FsrConfig`.
"""

from __future__ import annotations

import numpy as np

from ..config import FsrConfig
from ..errors import DegenerateGeometryError, TooFewPointsError
from ..sampling import _farthest_point_indices_from, _power_of_two_scale
from .svd import (
    PoseEstimate,
    correspondence_residuals_squared,
    refine_on_inliers,
    rigid_transform_svd,
    solve_rigid_batch,
    to_homogeneous,
    transformation_inliers,
    validate_correspondences,
    validate_weights,
)


def fsr(
    source_matched,
    target_matched,
    confidences=None,
    config: FsrConfig = FsrConfig(),
) -> PoseEstimate:
    """Estimate the rigid transform from matched pairs with FSR (paper Algorithm 1).

    Args:
        source_matched: (M, 3) matched source points, network units.
        target_matched: (M, 3) their matched target points, row i paired with row i.
        confidences: optional (M,) non-negative match confidences (e.g. Sinkhorn assignment
            probabilities). They rank the matches for the few-matches path and weight the
            refit; the sampling rounds themselves are unweighted, as in the paper.
        config: see :class:`FsrConfig`.

    Returns:
        :class:`~logdesc_rt.pose.svd.PoseEstimate`; ``inlier_mask`` marks pairs within
        ``config.inlier_threshold`` after the returned transformation. Same inputs and seed
        give the identical result.

    Raises:
        PointCloudShapeError: arrays are not (M, 3) / (M,), or their lengths differ.
        NonFinitePointsError: NaN or inf coordinates or confidences.
        TooFewPointsError: fewer than 3 matches (no rigid transform is defined), or fewer
            than 3 with positive confidence on the few-matches path.
        InvalidPointCloudError: negative confidences; coordinates so large the transform
            overflows.
        DegenerateGeometryError: the matched points all coincide or lie on one line, so no
            sampled subset determines a rotation.
    """
    caller = "fsr"
    source, target = validate_correspondences(
        source_matched,
        target_matched,
        source_name="source_matched",
        target_name="target_matched",
        caller=caller,
    )
    match_count = len(source)
    weights = None
    if confidences is not None:
        weights = validate_weights(confidences, match_count, name="confidences", caller=caller)

    if match_count < config.min_matches_for_sampling:
        # Few matches: one confidence-weighted SVD on the most confident ones (official).
        if weights is None:
            chosen = np.arange(min(match_count, config.fallback_matches))
        else:
            chosen = np.argsort(-weights, kind="stable")[: config.fallback_matches]
        try:
            transformation = rigid_transform_svd(
                source[chosen], target[chosen], None if weights is None else weights[chosen]
            )
        except (DegenerateGeometryError, TooFewPointsError) as error:
            raise type(error)(
                f"fsr: {match_count} matches (< min_matches_for_sampling = "
                f"{config.min_matches_for_sampling}), and the SVD on the {len(chosen)} most "
                f"confident failed: {error}"
            ) from error
        rounds_run = 0
    else:
        transformation = _best_sampled_hypothesis(source, target, config)
        rounds_run = config.iterations

    if config.refit_on_inliers:
        transformation = refine_on_inliers(
            transformation, source, target, weights, config.inlier_threshold, config.refit_rounds
        )
    final_inliers = transformation_inliers(transformation, source, target, config.inlier_threshold**2)
    return PoseEstimate(
        transformation=transformation,
        inlier_mask=final_inliers,
        inlier_count=int(np.count_nonzero(final_inliers)),
        iterations_run=rounds_run,
    )


def _best_sampled_hypothesis(source: np.ndarray, target: np.ndarray, config: FsrConfig) -> np.ndarray:
    """The paper's rounds: FPS subset -> SVD -> inlier count; returns the best (4, 4).

    All rounds' SVDs and inlier counts run as one batch. Ties go to the earliest round, as
    in Algorithm 1 (``if n_i > best``). Rounds whose subset is degenerate are skipped; when
    all are, one SVD on every match decides (and raises if that is degenerate too).
    """
    match_count = len(source)
    sample_size = config.resolved_sample_size(match_count)
    generator = np.random.default_rng(config.seed)
    # Distinct starting points while there are enough matches, so that rounds differ.
    start_order = generator.permutation(match_count)
    scaled_source = source / _power_of_two_scale(source)
    starts = start_order[np.arange(config.iterations) % match_count]
    subsets = _farthest_point_indices_from(scaled_source, sample_size, starts)
    rotations, translations, degenerate = solve_rigid_batch(source[subsets], target[subsets])
    residuals = correspondence_residuals_squared(rotations, translations, source, target)
    inlier_counts = np.count_nonzero(residuals < config.inlier_threshold**2, axis=1)
    inlier_counts[degenerate | ~np.all(np.isfinite(translations), axis=1)] = -1
    best_round = int(np.argmax(inlier_counts))
    if inlier_counts[best_round] < 0:
        try:
            return rigid_transform_svd(source, target)
        except DegenerateGeometryError as error:
            raise DegenerateGeometryError(
                f"fsr: every sampled subset of the {match_count} matches is degenerate, and so are "
                f"all matches together ({error})"
            ) from error
    return to_homogeneous(rotations[best_round], translations[best_round])


"""3-point RANSAC on putative correspondences (the paper's alternative pose estimator).

Hypotheses are drawn and solved in batches: one batched ``np.linalg.svd`` solves hundreds of
3-point Kabsch problems at once, and one einsum counts all their inliers. Cheap checks
reject a sample before it is solved, as Open3D's ``CorrespondenceCheckerBasedOnEdgeLength``
does: a rigid motion preserves lengths, so the three source edges must match the three
target edges to within the similarity ratio; collinear samples are rejected too.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import RansacConfig
from ..errors import DegenerateGeometryError
from ..validation import COLLINEAR_RELATIVE_TOLERANCE
from .svd import (
    PoseEstimate,
    correspondence_residuals_squared,
    refine_on_inliers,
    solve_rigid_batch,
    to_homogeneous,
    transformation_inliers,
    validate_correspondences,
)

# At most this many (hypothesis, correspondence) residuals are held at once (~50 MB).
MAX_RESIDUALS_PER_CHUNK = 2_000_000


def _draw_triplets(generator: np.random.Generator, count: int, population: int) -> np.ndarray:
    """(count, 3) int64: each row three distinct indices, uniform over unordered triplets.

    Draws the second index from the population minus the first, and the third from the
    population minus both, by shifting past the excluded indices; no rejection loop.
    """
    first = generator.integers(0, population, size=count)
    second = generator.integers(0, population - 1, size=count)
    second += second >= first
    third = generator.integers(0, population - 2, size=count)
    lower, upper = np.minimum(first, second), np.maximum(first, second)
    third += third >= lower
    third += third >= upper
    return np.stack([first, second, third], axis=1)


def _plausible_samples(
    source_triangles: np.ndarray, target_triangles: np.ndarray, similarity: float
) -> np.ndarray:
    """(B,) bool for (B, 3, 3) triangles: edge lengths agree and neither triangle is a line."""
    edge_pairs = ([1, 2, 0], [0, 1, 2])  # edges 0-1, 1-2, 2-0

    def edge_lengths(triangles: np.ndarray) -> np.ndarray:
        with np.errstate(over="ignore", invalid="ignore"):
            return np.linalg.norm(triangles[:, edge_pairs[0]] - triangles[:, edge_pairs[1]], axis=2)

    def not_collinear(triangles: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        # |cross| / longest edge^2 ~ (second / first principal extent): the same relative
        # test as validation.check_not_degenerate, on a triangle. Scaled by the longest edge
        # first so huge coordinates cannot overflow.
        longest = lengths.max(axis=1)
        safe = np.where(longest > 0, longest, 1.0)[:, None, None]
        with np.errstate(over="ignore", invalid="ignore"):
            edges = (triangles[:, [1, 2]] - triangles[:, [0, 0]]) / safe
        area_ratio = np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1)
        return (longest > 0) & (area_ratio > COLLINEAR_RELATIVE_TOLERANCE)

    source_lengths = edge_lengths(source_triangles)
    target_lengths = edge_lengths(target_triangles)
    with np.errstate(over="ignore", invalid="ignore"):
        consistent = np.all(
            (source_lengths >= similarity * target_lengths) & (target_lengths >= similarity * source_lengths),
            axis=1,
        )
    return (
        consistent
        & not_collinear(source_triangles, source_lengths)
        & not_collinear(target_triangles, target_lengths)
    )


def _required_draws(inlier_ratio: float, confidence: float) -> float:
    """Draws needed to pick one all-inlier 3-sample with probability ``confidence``."""
    if confidence >= 1.0 or inlier_ratio <= 0.0:
        return math.inf
    all_inlier_probability = inlier_ratio**3
    if all_inlier_probability >= 1.0:
        return 1.0
    return math.log(1.0 - confidence) / math.log1p(-all_inlier_probability)


def ransac(source_matched, target_matched, config: RansacConfig = RansacConfig()) -> PoseEstimate:
    """Estimate the rigid transform from putative correspondences by 3-point RANSAC.

    Args:
        source_matched: (M, 3) source points, M >= 3.
        target_matched: (M, 3) target points, row i the putative partner of source row i.
        config: see :class:`RansacConfig`.

    Returns:
        :class:`~logdesc_rt.pose.svd.PoseEstimate` with the best hypothesis (most inliers,
        earliest on ties), refined on its inliers when ``config.refit_on_inliers``;
        ``iterations_run`` counts the hypotheses drawn. Deterministic for a given seed.

    Raises:
        PointCloudShapeError, NonFinitePointsError: bad arrays or lengths that differ.
        TooFewPointsError: fewer than 3 correspondences.
        DegenerateGeometryError: no drawn sample passed the edge-length and collinearity
            checks (e.g. all points on a line, or no two consistent triangles).
    """
    source, target = validate_correspondences(
        source_matched,
        target_matched,
        source_name="source_matched",
        target_name="target_matched",
        caller="ransac",
    )
    match_count = len(source)
    threshold_squared = config.inlier_threshold**2
    generator = np.random.default_rng(config.seed)
    hypotheses_per_chunk = max(1, MAX_RESIDUALS_PER_CHUNK // match_count)

    best_count = -1
    best_rotation = best_translation = None
    drawn = 0
    draw_limit: float = config.max_iterations
    while drawn < min(draw_limit, config.max_iterations):
        batch = int(min(config.batch_size, config.max_iterations - drawn))
        triplets = _draw_triplets(generator, batch, match_count)
        drawn += batch
        source_triangles, target_triangles = source[triplets], target[triplets]
        plausible = _plausible_samples(source_triangles, target_triangles, config.edge_length_similarity)
        if not plausible.any():
            continue
        rotations, translations, degenerate = solve_rigid_batch(
            source_triangles[plausible], target_triangles[plausible]
        )
        usable = ~degenerate & np.all(np.isfinite(translations), axis=1)
        rotations, translations = rotations[usable], translations[usable]
        for start in range(0, len(rotations), hypotheses_per_chunk):
            chunk = slice(start, start + hypotheses_per_chunk)
            residuals = correspondence_residuals_squared(
                rotations[chunk], translations[chunk], source, target
            )
            counts = np.count_nonzero(residuals < threshold_squared, axis=1)
            winner = int(np.argmax(counts))
            if counts[winner] > best_count:
                best_count = int(counts[winner])
                best_rotation, best_translation = rotations[chunk][winner], translations[chunk][winner]
        if best_count > 0:
            draw_limit = _required_draws(best_count / match_count, config.confidence)

    if best_rotation is None:
        raise DegenerateGeometryError(
            f"ransac: none of the {drawn} drawn 3-point samples passed the edge-length "
            f"(similarity {config.edge_length_similarity}) and non-collinearity checks; the "
            "correspondences are degenerate or wholly inconsistent"
        )
    transformation = to_homogeneous(best_rotation, best_translation)
    if config.refit_on_inliers:
        transformation = refine_on_inliers(
            transformation, source, target, None, config.inlier_threshold, config.refit_rounds
        )
    final_inliers = transformation_inliers(transformation, source, target, threshold_squared)
    return PoseEstimate(
        transformation=transformation,
        inlier_mask=final_inliers,
        inlier_count=int(np.count_nonzero(final_inliers)),
        iterations_run=drawn,
    )

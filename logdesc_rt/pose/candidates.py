"""Candidate poses from learned matches: one function per estimator name.

The candidate estimators (network units, from the mutual matches and their Sinkhorn
confidences):

- ``fsr``: the paper's estimator (:func:`~logdesc_rt.pose.fsr`);
- ``ransac``: 3-point RANSAC (:func:`~logdesc_rt.pose.ransac`);
- ``svd``: confidence-weighted SVD on every match (outliers included);
- ``top_k``: SVD on the most confident ``top_k_fraction`` of the matches, then re-solved on
  its inliers;
- ``core``: the maximum consistent core of the matches (:mod:`~logdesc_rt.pose.consistency`:
  the largest set whose pairwise distances agree in both clouds), SVD on it, re-solved on its
  inliers; it holds up to about 90 % wrong matches, where FSR breaks at about half.

Beside the matcher's matches, the same estimators can read the descriptors' own mutual nearest
neighbours (:func:`descriptor_candidate_poses`, ``VerificationConfig.descriptor_consensus``):
candidates named ``descriptor_<estimator>``.

Verification (:mod:`logdesc_rt.verification`) scores what these propose; which of them run
is the model's choice (``VerificationConfig.candidates``).
"""

from __future__ import annotations

import numpy as np

from ..config import CANDIDATE_ESTIMATORS, VerificationConfig
from ..errors import DegenerateGeometryError, TooFewPointsError
from ..matching import Matches
from .consistency import consistency_pose
from .fsr import FsrConfig, fsr
from .ransac import RansacConfig, ransac
from .svd import refine_on_inliers, rigid_transform_svd


def estimate_pose(
    estimator: str,
    source_matched: np.ndarray,
    target_matched: np.ndarray,
    confidences: np.ndarray,
    fsr_config: FsrConfig = FsrConfig(),
    ransac_config: RansacConfig = RansacConfig(),
    top_k_fraction: float = VerificationConfig.top_k_fraction,
) -> np.ndarray:
    """(4, 4) network-frame pose of one candidate estimator from matched points.

    Args:
        estimator: one of CANDIDATE_ESTIMATORS (module docstring).
        source_matched, target_matched: (K, 3) float64 matched points, K >= 3, network units.
        confidences: (K,) float64 match probabilities.
        fsr_config, ransac_config: the two robust estimators' parameters (and seeds).
        top_k_fraction: share of the most confident matches the "top_k" candidate fits.

    Raises:
        ValueError: unknown estimator.
        DegenerateGeometryError, TooFewPointsError: the matches do not determine a pose.
    """
    if estimator == "fsr":
        return fsr(source_matched, target_matched, confidences, fsr_config).transformation
    if estimator == "ransac":
        return ransac(source_matched, target_matched, ransac_config).transformation
    if estimator == "svd":
        return rigid_transform_svd(source_matched, target_matched, confidences)
    if estimator == "core":
        return consistency_pose(
            source_matched, target_matched, confidences, fsr_config.inlier_threshold, fsr_config.refit_rounds
        )
    if estimator == "top_k":
        count = max(3, int(round(top_k_fraction * len(confidences))))
        chosen = np.argsort(-confidences, kind="stable")[:count]
        pose = rigid_transform_svd(source_matched[chosen], target_matched[chosen], confidences[chosen])
        return refine_on_inliers(
            pose, source_matched, target_matched, confidences, fsr_config.inlier_threshold, fsr_config.refit_rounds
        )
    raise ValueError(f"estimator {estimator!r}: expected one of {CANDIDATE_ESTIMATORS}")


def candidate_poses(
    source_matched: np.ndarray,
    target_matched: np.ndarray,
    confidences: np.ndarray,
    fsr_config: FsrConfig = FsrConfig(),
    ransac_config: RansacConfig = RansacConfig(),
    top_k_fraction: float = VerificationConfig.top_k_fraction,
    estimators: tuple[str, ...] = VerificationConfig.candidates,
) -> list[tuple[str, np.ndarray]]:
    """The poses of ``estimators`` (:func:`estimate_pose`), network units.

    Returns:
        [(estimator name, (4, 4) network-frame pose)], in ``estimators`` order, leaving out an
        estimator whose points are degenerate (all on a line, say).
    """
    candidates: list[tuple[str, np.ndarray]] = []
    for name in estimators:
        try:
            pose = estimate_pose(
                name, source_matched, target_matched, confidences, fsr_config, ransac_config, top_k_fraction
            )
        except (DegenerateGeometryError, TooFewPointsError):
            continue
        candidates.append((name, pose))
    return candidates


def unexplained_candidate_poses(
    source_matched: np.ndarray,
    target_matched: np.ndarray,
    confidences: np.ndarray,
    pose: np.ndarray,
    tolerance: float,
    fsr_config: FsrConfig = FsrConfig(),
    ransac_config: RansacConfig = RansacConfig(),
    top_k_fraction: float = VerificationConfig.top_k_fraction,
    estimators: tuple[str, ...] = VerificationConfig.candidates,
) -> list[tuple[str, np.ndarray]]:
    """A second consensus: the candidates of the matches that ``pose`` leaves unexplained.

    On an object that looks the same turned over (a wing, a tub), a point and its mirrored twin
    get alike descriptors, and the twin matches can outvote the true ones: every estimator then
    finds the flip. Without the matches the flip explains, the true ones are the largest
    consistent set left.

    Args:
        source_matched, target_matched, confidences: the matches as for :func:`candidate_poses`
            (network units).
        pose: (4, 4) network-frame pose whose explained matches are left out.
        tolerance: a match is explained when ``pose`` maps its source point within this of its
            target point (network units).
        fsr_config, ransac_config, top_k_fraction, estimators: as for :func:`candidate_poses`.

    Returns:
        [(estimator name, (4, 4) network-frame pose)] of the unexplained matches; empty when
        fewer than three are left.
    """
    residual = np.linalg.norm(source_matched @ pose[:3, :3].T + pose[:3, 3] - target_matched, axis=1)
    rest = residual >= tolerance
    if np.count_nonzero(rest) < 3:
        return []
    return candidate_poses(
        source_matched[rest], target_matched[rest], confidences[rest], fsr_config, ransac_config, top_k_fraction,
        estimators,
    )


DESCRIPTOR_PREFIX = "descriptor_"  # + estimator: the candidates of the descriptors' own matches


def descriptor_candidate_poses(
    source_network: np.ndarray,
    target_network: np.ndarray,
    descriptor_matches: Matches,
    fsr_config: FsrConfig = FsrConfig(),
    ransac_config: RansacConfig = RansacConfig(),
    top_k_fraction: float = VerificationConfig.top_k_fraction,
    estimators: tuple[str, ...] = ("ransac",),
) -> list[tuple[str, np.ndarray]]:
    """Candidates of the descriptors' mutual nearest neighbours
    (:func:`~logdesc_rt.matching.mutual_nearest_descriptors`), named ``descriptor_<estimator>``.

    The matcher's transformer reads both clouds at once; where it settles on a wrong reading
    (a scan's one-sided surfaces, a part of the shape the other cloud lacks), the descriptors'
    own matches can still hold the true pose (``docs/decisions.md``).

    Args:
        source_network, target_network: (N, 3) / (M, 3) float64 working subsets, network units.
        descriptor_matches: matches indexing them.
        fsr_config, ransac_config, top_k_fraction, estimators: as for :func:`candidate_poses`.

    Returns:
        [(name, (4, 4) network-frame pose)]; empty when fewer than three matches.
    """
    if len(descriptor_matches) < 3:
        return []
    poses = candidate_poses(
        source_network[descriptor_matches.source_index], target_network[descriptor_matches.target_index],
        descriptor_matches.confidence, fsr_config, ransac_config, top_k_fraction, estimators,
    )
    return [(DESCRIPTOR_PREFIX + name, pose) for name, pose in poses]

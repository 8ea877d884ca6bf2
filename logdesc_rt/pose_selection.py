"""From a matched pair to the returned result: the one path from learned matches to a verified
pose. The runtime (:meth:`Registrar.register`), training's validation and
``training/evaluate.py`` all read their poses here.

    mutual matches -> the fast exit (the exit estimator's pose alone, refined and scored; kept
    when the calibration's exit model is sure) -> else candidate poses
    (:mod:`logdesc_rt.pose.candidates`, network units, mapped back to the user frame) ->
    verification on the full clouds (:class:`PoseVerifier`: the best
    few get a short ICP, the leading one's second look adds turn-overs and a second consensus,
    each is scored, a calibrated confidence) -> the chosen pose (without ICP: its matches
    re-fitted, point-to-point then point-to-plane, :func:`coarse_pose`; where that strays from
    the verified pose, the verified pose if the clouds coincide there, :func:`pose_without_icp`)
    -> optional ICP ->
    fitness / inlier RMSE against the full target (a bounded seeded source subset) -> the success flag.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from pykdtree.kdtree import KDTree

from .config import RuntimeConfig, VerificationConfig
from .normalization import PairNormalization
from .pair import MIN_MATCHES, PairMatches
from .pose import evaluate_registration
from .pose.candidates import unexplained_candidate_poses
from .pose.svd import refine_on_inliers, solve_rigid_batch, to_homogeneous, transformation_inliers
from .refinement import IcpResult, estimate_normals, plane_fit_step, refine_pose
from .results import RegistrationResult
from .sampling import seeded_subset
from .threads import one_thread_per_caller
from .timing import timed
from .verification import UNEXPLAINED_PREFIX, Hypothesis, PoseVerifier, VerificationResult

COARSE_REFIT_ROUNDS = 10  # MSAC re-solves of coarse_pose's fit (the inliers settle in a few)
MIN_PLANE_FIT_MATCHES = 6  # fewer inlier matches: coarse_pose keeps the SVD fit (a 6-dof step)


def register_matched(
    pair: PairMatches,
    config: RuntimeConfig,
    initial: np.ndarray | None = None,
    report: Callable[[str], None] | None = None,
) -> RegistrationResult:
    """The result of a matched pair: candidate poses from its matches (and ``initial``),
    verified on the full clouds, the best (or the configured estimator's) kept, refined if
    the config asks, judged. With ``estimator="auto"``, no ``initial`` and an exit model in the
    calibration, the exit estimator's pose is verified alone first and kept when the exit
    model is sure (:meth:`~logdesc_rt.verification.PoseVerifier.fast_exit`).

    Args:
        pair: the matches and the clouds (:meth:`Registrar.match`, or :func:`pair_from_scores`).
        config: a resolved runtime configuration (estimator, verification, refinement).
        initial: optional (4, 4) user-frame guess, verified like the candidates.
        report: optional callable given a short message as each stage starts.

    Returns:
        :class:`RegistrationResult`; a pair with too few matches or no candidate pose is a
        result with ``success=False``, the identity and a ``reason``.
    """
    report = report if report is not None else (lambda message: None)
    timings = dict(pair.timings)
    verifier, fast = None, None
    fast_exit_applies = config.estimator == "auto" and initial is None and config.verification.fast_exit
    if fast_exit_applies and len(pair.matches) >= MIN_MATCHES:
        # The fast exit (logdesc_rt.verification): one estimator's pose, refined and scored alone.
        exit_estimator = config.verification.exit_estimator
        with timed(timings, "pose"), one_thread_per_caller():
            exit_pose = dict(pair.candidates(config, estimators=(exit_estimator,))).get(exit_estimator)
        if exit_pose is not None:
            report("verifying the leading pose on the full clouds")
            with timed(timings, "verification"), one_thread_per_caller():
                verifier = pose_verifier(pair, config)
                fast = verifier.fast_exit(exit_estimator, exit_pose)
    if fast is not None:
        return _verified_result(pair, config, timings, verifier, fast, report)
    with timed(timings, "pose"), one_thread_per_caller():
        candidates = pair.candidates(config) if len(pair.matches) >= MIN_MATCHES else []
        if initial is not None:
            candidates.append(("init", initial))
    if len(pair.matches) < MIN_MATCHES and initial is None:
        return unregistered_result(
            pair, config, timings,
            f"too few matches: the network found {len(pair.matches)} mutual matches, a pose needs at least "
            f"{MIN_MATCHES} (the clouds may not overlap, or differ too much from the model's training data)",
        )
    if config.estimator != "auto" and config.estimator not in dict(candidates):
        return unregistered_result(
            pair, config, timings,
            f"no candidate pose: estimator {config.estimator!r} found none "
            "(its matches are degenerate: all on one line)",
        )
    if not candidates:
        return unregistered_result(
            pair, config, timings, "no candidate pose: the matches are degenerate (all on one line)"
        )

    report(
        f"verifying {len(candidates)} candidate poses on the full clouds "
        f"({len(pair.source_points)} x {len(pair.target_points)} points)"
    )
    with timed(timings, "verification"), one_thread_per_caller():
        verifier = verifier if verifier is not None else pose_verifier(pair, config)
        verification = verify_candidates(
            verifier, candidates, pair.normalization, *pair.matched_network_points(), config
        )
    return _verified_result(pair, config, timings, verifier, verification, report, candidates)


def pose_verifier(pair: PairMatches, config: RuntimeConfig) -> PoseVerifier:
    """The :class:`PoseVerifier` of a matched pair: its full clouds and matches, user frame."""
    correspondences = pair.correspondences
    return PoseVerifier(
        pair.source_points,
        pair.target_points,
        pair.source_points[correspondences[:, 0]],
        pair.target_points[correspondences[:, 1]],
        pair.matches.confidence,
        pair.normalization.scale,
        config.verification,
    )


def _verified_result(
    pair: PairMatches,
    config: RuntimeConfig,
    timings: dict[str, float],
    verifier: PoseVerifier,
    verification: VerificationResult,
    report: Callable[[str], None],
    candidates: list[tuple[str, np.ndarray]] | None = None,
) -> RegistrationResult:
    """The result of a verified pair: the chosen hypothesis' pose (re-fitted on its matches,
    or the configured estimator's), refined if the config asks, and the flag."""
    refinement = config.refinement
    distance = correspondence_distance(pair, config)
    correspondences = pair.correspondences
    threshold = config.verification.exit_threshold if verification.fast_exit else config.verification.success_threshold
    if config.estimator == "auto":
        chosen = verification.best
        chosen_estimator = chosen.estimators[0]
        source_matched, target_matched = (
            pair.source_points[correspondences[:, 0]],
            pair.target_points[correspondences[:, 1]],
        )
        with timed(timings, "pose"), one_thread_per_caller():  # the returned pose is estimated here too
            pose = coarse_pose(
                chosen, source_matched, target_matched, pair.matches.confidence,
                pair.target_points[pair.target_index], config.verification,
            )
    else:
        chosen = next(h for h in verification.hypotheses if config.estimator in h.estimators)
        chosen_estimator = config.estimator
        pose = dict(candidates or [])[chosen_estimator]

    refined, icp_result, claimable = pose, None, True
    if refinement.method is not None:
        report(f"refining: {refinement.method} ICP on the full clouds")
        with timed(timings, "refinement"):
            icp_result = refine_pose(
                pair.source_points, pair.target_points, chosen.verified_transformation, distance, refinement
            )
        refined = icp_result.transformation
        with timed(timings, "verification"):
            confidence = verifier.confidence_at(refined, chosen, fast_exit=verification.fast_exit)
    elif config.estimator == "auto":
        pose, claimable = pose_without_icp(
            chosen, pose, verifier.pose_within_verified(pose, chosen), config.verification
        )
        refined = pose
        confidence = chosen.confidence if claimable else 0.0
    else:
        # The configured estimator's pose, as it is: right only if it is close to the
        # alignment verification found.
        claimable = verifier.pose_within_verified(pose, chosen)
        confidence = chosen.confidence if claimable else 0.0
    success = bool(confidence >= threshold)
    if success:
        reason = None
    elif not claimable:
        reason = (
            f"not verified: the pose from the matches lies more than {config.verification.same_pose_deg:g} degrees "
            f"(or {config.verification.distance_fraction:.0%} of the pair's scale) from the alignment verification "
            "found (confidence 0)"
        )
    else:
        reason = f"not verified: confidence {confidence:.3f} is below the success threshold {threshold:.3f}"
    return _judged_result(
        pair, config, timings, distance, refined,
        icp_evaluation=icp_result if refinement.max_source_points == refinement.evaluation_points else None,
        pose_estimator=chosen_estimator,
        refinement=refinement.method,
        transformation_before_refinement=pose,
        icp=icp_result,
        success=success,
        confidence=float(confidence),
        verification=verification,
        reason=reason,
    )


def pose_without_icp(
    hypothesis: Hypothesis, refit: np.ndarray, within_verified: bool, verification: VerificationConfig
) -> tuple[np.ndarray, bool]:
    """The pose ``register()`` returns without ICP for the chosen hypothesis, and whether the
    success flag may claim it (the runtime and the flag's calibration both read it here).

    The matches' re-fit (:func:`coarse_pose`) where it lies within ``same_pose_deg`` of the
    hypothesis' verified pose. Where it strays, the verified pose itself if the clouds
    coincide closely there (its ``rmse_ratio`` below ``verification.verified_fallback_rmse``:
    dense clouds, where the short ICP's optimum is the better pose); else the re-fit, which
    the flag may not claim (sparse clouds of separate samples, where the ICP's optimum is
    biased and the matches are the better evidence).

    Args:
        hypothesis: the chosen hypothesis (its verified pose and features).
        refit: (4, 4) :func:`coarse_pose` of it, user frame.
        within_verified: whether ``refit`` lies within ``same_pose_deg`` of the verified pose
            (:meth:`~logdesc_rt.verification.PoseVerifier.pose_within_verified`).
        verification: ``verified_fallback_rmse``.

    Returns:
        ((4, 4) pose, claimable).
    """
    if within_verified:
        return refit, True
    if hypothesis.features["rmse_ratio"] < verification.verified_fallback_rmse:
        return hypothesis.verified_transformation, True
    return refit, False


def coarse_pose(
    hypothesis: Hypothesis,
    source_matched: np.ndarray,
    target_matched: np.ndarray,
    confidences: np.ndarray,
    target_working: np.ndarray,
    verification: VerificationConfig,
) -> np.ndarray:
    """The pose ``register()`` returns without ICP for a verified hypothesis, user frame.

    The confidence-weighted least-squares pose of the learned matches that the hypothesis'
    verified pose explains within ``verification.refit_spacings`` target spacings, iterated
    MSAC-style (:func:`~logdesc_rt.pose.svd.refine_on_inliers`). It is a pose from matches,
    like the estimators': verification's short ICP only chose which matches are inliers
    (measured against the estimator's own pose: ``docs/decisions.md``).

    Then ``verification.refit_plane_steps`` Gauss-Newton steps of the same matches' point-to-
    plane fit (target normals from a PCA of the working subset; a point-to-point term of
    weight ``refit_point_weight``). Two scans sample a surface independently, so a learned
    match pairs a point with a neighbour of its twin: the error along the surface is sampling,
    the error across it is the pose's. The matches stay the learned ones (no nearest-neighbour
    search, unlike ICP): the pose is still one the network's matches give.

    Args:
        hypothesis: the chosen hypothesis (its estimator's and its verified pose).
        source_matched, target_matched: (K, 3) float64 matched points, user frame; the
            target's are points of ``target_working``.
        confidences: (K,) float64 their match probabilities.
        target_working: (Mt, 3) the target's working subset, where the matches live: its
            median nearest-neighbour distance is the spacing.
        verification: ``refit_spacings`` (the inlier distance in those spacings; 0: no
            refit), ``refit_plane_steps`` and ``refit_point_weight``.

    Returns:
        (4, 4) float64 pose; the estimator's own (``hypothesis.transformation``) when there is
        no refit, or fewer than 3 weighted inliers, or a degenerate inlier set.
    """
    if verification.refit_spacings <= 0.0 or len(target_working) < 2:
        return hypothesis.transformation
    tree = KDTree(target_working)
    distances, _ = tree.query(target_working, k=2)
    threshold = verification.refit_spacings * float(np.median(distances[:, 1]))
    inliers = transformation_inliers(hypothesis.verified_transformation, source_matched, target_matched, threshold**2)
    inliers &= confidences > 0
    if np.count_nonzero(inliers) < 3:
        return hypothesis.transformation
    rotations, translations, degenerate = solve_rigid_batch(
        source_matched[inliers][None], target_matched[inliers][None], confidences[inliers][None]
    )
    if degenerate[0]:
        return hypothesis.transformation
    fitted = to_homogeneous(rotations[0], translations[0])
    fitted = refine_on_inliers(fitted, source_matched, target_matched, confidences, threshold, COARSE_REFIT_ROUNDS)
    if verification.refit_plane_steps == 0 or np.count_nonzero(inliers) < MIN_PLANE_FIT_MATCHES:
        return fitted
    source, target, weights = source_matched[inliers], target_matched[inliers], confidences[inliers]
    _, working_index = tree.query(target, k=1)  # the matched target points are working points
    normals = estimate_normals(target_working, tree=tree, index=working_index.astype(np.int64))
    for _ in range(verification.refit_plane_steps):
        moved = source @ fitted[:3, :3].T + fitted[:3, 3]
        step = plane_fit_step(moved, target, normals, weights, verification.refit_point_weight)
        if not np.all(np.isfinite(step)):
            break
        fitted = step @ fitted
    return fitted


def verify_candidates(
    verifier: PoseVerifier,
    candidates: list[tuple[str, np.ndarray]],
    normalization: PairNormalization,
    source_matched: np.ndarray,
    target_matched: np.ndarray,
    confidences: np.ndarray,
    config: RuntimeConfig,
) -> VerificationResult:
    """``verifier.verify(candidates)`` with the second look's second consensus, which needs the
    matches in network units: the one call, shared by the runtime and the flag's calibration
    (``benchmarks/calibrate_success.py``), so that the calibration sees what the runtime scores.

    Args:
        verifier: built on the pair's full clouds with ``config.verification``.
        candidates: [(estimator name, (4, 4) user-frame pose)], at least one.
        normalization: the pair's map between network units and the user frame.
        source_matched, target_matched: (K, 3) float64 matched points, network units.
        confidences: (K,) float64 their match probabilities.
        config: a resolved runtime configuration (FSR, RANSAC, verification).
    """
    verification = config.verification

    def second_consensus(leading: np.ndarray) -> list[tuple[str, np.ndarray]]:
        poses = unexplained_candidate_poses(
            source_matched, target_matched, confidences, normalization.pose_to_network_frame(leading),
            verification.match_tolerance, config.fsr, config.ransac, verification.top_k_fraction,
            verification.second_consensus,
        )
        return [(UNEXPLAINED_PREFIX + name, normalization.pose_to_user_frame(pose)) for name, pose in poses]

    return verifier.verify(candidates, second_consensus if verification.second_consensus else None)


def _judged_result(
    pair: PairMatches, config: RuntimeConfig, timings: dict[str, float], distance: float,
    transformation: np.ndarray, icp_evaluation: IcpResult | None = None, **outcome,
) -> RegistrationResult:
    """The result of ``pair`` with its returned ``transformation``: fitness and inlier RMSE on
    the full target at ``distance`` (over at most ``evaluation_points`` seeded source points),
    the total time, and what every result says of the pair;
    ``outcome`` holds the rest (estimator, refinement, the flag and its reason).

    ``icp_evaluation``: the ICP that returned ``transformation``, run at ``distance`` on the same
    seeded source subset (``max_source_points == evaluation_points``, one seed): its final
    fitness and RMSE are this evaluation already (the same query, in ICP's frame), so the
    target's k-d tree is not built twice."""
    refinement = config.refinement
    # One thread: a bounded query, which OpenMP's start-up and spin-waits on a small machine slow.
    with timed(timings, "evaluation"), one_thread_per_caller():
        if icp_evaluation is not None:
            fitness, inlier_rmse = icp_evaluation.fitness, icp_evaluation.inlier_rmse
            fitness_points = min(len(pair.source_points), refinement.evaluation_points or len(pair.source_points))
        else:
            scored = seeded_subset(
                len(pair.source_points), refinement.evaluation_points, np.random.default_rng(refinement.seed)
            )
            evaluation = evaluate_registration(pair.source_points[scored], pair.target_points, distance, transformation)
            fitness, inlier_rmse, fitness_points = evaluation.fitness, evaluation.inlier_rmse, len(scored)
    timings["total"] = sum(timings.values())
    return RegistrationResult(
        transformation=transformation,
        correspondences=pair.correspondences,
        confidences=pair.matches.confidence,
        fitness=fitness,
        inlier_rmse=inlier_rmse,
        max_correspondence_distance=distance,
        fitness_points=fitness_points,
        subsampled=pair.subsampled,
        source_points_used=len(pair.source_index),
        target_points_used=len(pair.target_index),
        timings=timings,
        config=config,
        **outcome,
    )


def correspondence_distance(pair: PairMatches, config: RuntimeConfig) -> float:
    """The distance for fitness, inlier RMSE and ICP, user units: the caller's, or
    ``distance_fraction`` x the pair's scale (the larger cloud's radius)."""
    refinement = config.refinement
    return refinement.max_correspondence_distance or refinement.distance_fraction * pair.normalization.scale


def unregistered_result(
    pair: PairMatches, config: RuntimeConfig, timings: dict[str, float], reason: str
) -> RegistrationResult:
    """The result of a valid pair no pose could be estimated for: the identity, judged a failure."""
    identity = np.eye(4)
    return _judged_result(
        pair, config, timings, correspondence_distance(pair, config), identity,
        pose_estimator="none",
        refinement=None,
        transformation_before_refinement=identity,
        success=False,
        confidence=0.0,
        reason=reason,
    )

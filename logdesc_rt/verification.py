"""Verified hypotheses and the success flag.

The learned matches yield several candidate poses; each is scored on the full clouds (or
seeded subsets of them, for speed), the best few get a short ICP, and a logistic model turns
the best one's scores into a confidence that the pose is right. ``success`` is that
confidence reaching a threshold. The model's coefficients and the threshold were fitted on
validation pairs only (``benchmarks/calibrate_success.py``; what and how in
``benchmarks/results/success_calibration.md``).

The candidates come from :mod:`logdesc_rt.pose.candidates`; which of them run is the
model's choice (``VerificationConfig.candidates``), since a calibration is fitted with one set.

Candidates closer than ``same_pose_deg`` (and the inlier distance) are one hypothesis; how
many estimators agree on it is a feature.

Features of a pose T (all lengths relative to the pair's scale s, the larger cloud's radius;
``d = distance_fraction * s``), in the order of
:data:`~logdesc_rt.config.VERIFICATION_FEATURES`:

- ``fitness``: share of the scored source points with a target point within d after T;
- ``sharpness``: share of those inliers closer than ``sharp_factor`` times the target's point
  spacing (median nearest-neighbour distance within the scored target points): after ICP a
  right pose lines the overlap up to the scan's noise, a wrong one leaves residuals spread
  over [0, d], whatever the overlap (on partial scans a wrong pose can have the higher fitness);
- ``rmse_ratio``: RMS distance of the fitness inliers / d (1 when there are none);
- ``reverse_fitness``: share of the scored target points with a moved source point within d;
- ``normal_agreement``: mean |n_source . n_target| over the inlier pairs (normals from a
  10-neighbour PCA of each subset), 0 without inliers: wrong poses cross surfaces;
- ``match_inlier_ratio``: confidence-weighted share of the learned matches that T maps within
  ``match_tolerance * s`` of their partner;
- ``log_matches``: log(1 + number of mutual matches) / log(1 + 1024) (a fixed scale);
- ``agreement``: share of the candidate estimators (``VerificationConfig.candidates``; a user's
  initial guess does not count) whose pose is this hypothesis;
- ``margin``: fitness of this hypothesis minus that of the best other distinct hypothesis,
  both after the short ICP (0 when there is no other): an ambiguous pair has rivals;
- ``symmetry``: the best fitness of the pose composed with a half-turn of the source about
  one of its principal axes (through its centroid), divided by the pose's own fitness
  (at most 1.5): near 1 for an object that looks the same turned over, where geometry alone
  cannot tell the right pose from its flip.

**The second look.** The estimators all read the same matches, so when the matches of a
symmetric object's mirrored twins outvote the true ones (a point on a wing's top and its twin
below get alike descriptors) every candidate is the flip, and verification has nothing better
to choose. After the first candidates are refined, the leading one (the highest fitness + match
agreement: a score free of the calibration, so that the calibration can be fitted on what this
stage produces) proposes alternatives, refined and scored with the rest:

- ``turned_over``: its source turned over by a half-turn about each of ``turn_over_axes`` axes,
  evenly spread in the plane of the source's two largest principal axes, through its centroid;
  a few batched point-to-point ICP iterations on a few source points screen them, and the one
  that fits best is refined (the ICP finds the turn about the plate's normal). The
  hypothesis' own pose is its refined one (a raw half-turn is no estimate);
- ``spun`` (``turn_over_spin``): its source spun by a half-turn about its least principal
  axis, the normal of that plane (a table, a tub or a bed that looks the same from either
  end), screened the same way, alone, and refined;
- ``unexplained_<estimator>``: the ``second_consensus`` estimators on the matches the leading
  pose leaves unexplained (:func:`~logdesc_rt.pose.candidates.unexplained_candidate_poses`, by
  the caller, who holds the matches in network units).

``VerificationConfig.turn_over_axes`` and ``.second_consensus`` set how much of it runs.

**The fast exit.** A calibration may carry a second logistic model, the exit model, over the
features of one hypothesis alone (``EXIT_FEATURES``: no agreement, no margin). Before any other
candidate is estimated, the exit estimator's pose (``VerificationConfig.exit_estimator``) is
refined and scored; when the exit model's confidence reaches ``exit_threshold`` (set on
validation pairs where such exits were right at least 99 % of the time), that hypothesis is
kept with the exit model's confidence, and the other candidates, the second look and the
rival scoring do not run (:meth:`PoseVerifier.fast_exit`). Otherwise every candidate is
verified as above, and the flag is the full model's. ``VerificationResult.fast_exit`` says
which path a pair took.

The features of the chosen hypothesis are taken *after* its short ICP, which measures whether
the pose sits in the basin of a good alignment. When the caller does not refine, the
unrefined pose is returned, and it counts as a success only if it also lies within
``same_pose_deg`` (and d) of that verified alignment.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from pykdtree.kdtree import KDTree

from .config import EXIT_FEATURES, VERIFICATION_FEATURES, VerificationConfig
from .metrics import rotation_error_deg
from .refinement import LazyNormals, estimate_normals, icp, point_to_point_icp_batch
from .sampling import seeded_subset
from .threads import per_cloud

# The log_matches feature's fixed scale (every stored calibration was fitted with it; it is
# not the working size, which may change without refitting).
LOG_MATCH_SCALE = math.log1p(1024)
TURNED_OVER = "turned_over"  # the second look's half-turned hypothesis (module docstring)
SPUN = "spun"  # the second look's half-turn about the source's least principal axis
# The turn-overs are screened by this short ICP on this many source points before one is refined.
TURN_OVER_SCREEN_POINTS = 256
TURN_OVER_SCREEN_ITERATIONS = 10
UNEXPLAINED_PREFIX = "unexplained_"  # + estimator: the second consensus's hypotheses
# The scoring queries look no farther than the inlier distance d (a point beyond it only counts
# as not an inlier), which prunes most of the search for a wrong or half-turned pose. The bound
# sits a hair above d: the k-d tree tests squared distances, and no point that the features'
# own test (distance < d) counts may be dropped by a rounding of d squared.
QUERY_BOUND_MARGIN = 1.0 + 1e-9


@dataclass(frozen=True)
class Hypothesis:
    """One distinct candidate pose and how it scored.

    Attributes:
        estimators: the candidate estimators that proposed it (first: the one kept).
        transformation: (4, 4) float64 user-frame pose as the estimator gave it.
        verified_transformation: (4, 4) after the short ICP (the same pose if not refined).
        features: feature name -> value, at ``verified_transformation`` (or at
            ``transformation`` for hypotheses that were not refined).
        confidence: the calibrated probability that the verified pose is right, in [0, 1].
        refined: whether the short ICP ran on it.
    """

    estimators: tuple[str, ...]
    transformation: np.ndarray
    verified_transformation: np.ndarray
    features: dict[str, float]
    confidence: float
    refined: bool

    @property
    def shift_deg(self) -> float:
        """Rotation between the estimator's pose and the verified pose, degrees."""
        return float(rotation_error_deg(self.transformation[:3, :3], self.verified_transformation[:3, :3]))


@dataclass(frozen=True)
class VerificationResult:
    """What verification chose and how sure it is.

    Attributes:
        best: the chosen hypothesis (highest confidence).
        hypotheses: every distinct hypothesis, best first.
        candidate_count: candidate poses scored, the estimators' and the second look's (before
            merging equal ones).
        fast_exit: True when the exit estimator's hypothesis alone was scored and kept (its
            ``confidence`` is then the exit model's, :meth:`PoseVerifier.fast_exit`).
    """

    best: Hypothesis
    hypotheses: tuple[Hypothesis, ...] = field(default_factory=tuple)
    candidate_count: int = 0
    fast_exit: bool = False


def _same_pose(first: np.ndarray, second: np.ndarray, degrees: float, distance: float, centre: np.ndarray) -> bool:
    """Whether two poses agree: rotation within ``degrees`` and ``centre`` moved within ``distance``."""
    if rotation_error_deg(first[:3, :3], second[:3, :3]) > degrees:
        return False
    moved = first[:3, :3] @ centre + first[:3, 3] - (second[:3, :3] @ centre + second[:3, 3])
    return bool(np.linalg.norm(moved) <= distance)


def _half_turn(axis: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(4, 4) rotation by pi about the line through ``centre`` (3,) along unit ``axis`` (3,)."""
    pose = np.eye(4)
    pose[:3, :3] = 2.0 * np.outer(axis, axis) - np.eye(3)
    pose[:3, 3] = centre - pose[:3, :3] @ centre
    return pose


def _apply(function: Callable, points: np.ndarray):
    """``function(points)``: lets :func:`per_cloud` run a different set-up for each cloud."""
    return function(points)


def _source_normals(points: np.ndarray) -> np.ndarray:
    """(N, 3) normals of every scored source point (:func:`estimate_normals`): the features
    read those of nearly all of them."""
    return estimate_normals(points, tree=KDTree(points))


def _target_tree_spacing_normals(points: np.ndarray, source_count: int) -> tuple[KDTree, float, LazyNormals]:
    """A k-d tree of the scored target (M, 3), its median nearest-neighbour distance, and its
    normals (:class:`LazyNormals`). The short ICP and the features read the normals of target
    points paired with the ``source_count`` scored source points only, at most one each: where
    the target is more than twice that size, each normal is computed when a pose first meets
    it (a 40k-point scan's 8,000 scored target points: ~2,000 met); else all of them here, beside
    the source's normals."""
    tree = KDTree(points)
    spacing, _ = tree.query(points, k=2)
    normals = LazyNormals(points, tree)
    if len(points) <= 2 * source_count:
        normals.at(np.arange(len(points)))
    return tree, float(np.median(spacing[:, 1])), normals


def logistic_confidence(features: np.ndarray, config: VerificationConfig) -> float:
    """Calibrated probability, in [0, 1], from a (F,) feature vector."""
    z = config.bias + float(np.dot(config.weights, features))
    return float(1.0 / (1.0 + math.exp(-z))) if z > -700 else 0.0


_EXIT_COLUMNS = [VERIFICATION_FEATURES.index(name) for name in EXIT_FEATURES]


def exit_confidence(features: np.ndarray, config: VerificationConfig) -> float:
    """The exit model's calibrated probability, in [0, 1], from a (F,) feature vector in
    VERIFICATION_FEATURES order (it reads the EXIT_FEATURES among them); 0 without an exit model."""
    if not config.fast_exit:
        return 0.0
    z = config.exit_bias + float(np.dot(config.exit_weights, np.asarray(features)[_EXIT_COLUMNS]))
    return float(1.0 / (1.0 + math.exp(-z))) if z > -700 else 0.0


class PoseVerifier:
    """Scores poses of one pair on seeded subsets of the full clouds.

    Args:
        source, target: (N, 3) / (M, 3) float64 full clouds, user frame.
        source_matched, target_matched: (K, 3) float64 matched points, user frame.
        confidences: (K,) float64 their match probabilities.
        scale: the pair's scale s (user units per network unit: the larger radius).
        config: see :class:`~logdesc_rt.config.VerificationConfig`.
    """

    def __init__(
        self,
        source: np.ndarray,
        target: np.ndarray,
        source_matched: np.ndarray,
        target_matched: np.ndarray,
        confidences: np.ndarray,
        scale: float,
        config: VerificationConfig = VerificationConfig(),
    ):
        generator = np.random.default_rng(config.seed)
        self.config = config
        self.source = source[seeded_subset(len(source), config.source_points, generator)]
        self.target = target[seeded_subset(len(target), config.target_points, generator)]
        self.source_matched = source_matched
        self.target_matched = target_matched
        self.confidences = confidences
        self.distance = config.distance_fraction * scale
        self.query_bound = self.distance * QUERY_BOUND_MARGIN
        # One tree of the scored target serves the spacing, every pose's query and its normals;
        # the target's set-up runs beside the source's normals (most of this set-up's time).
        target_setup = functools.partial(_target_tree_spacing_normals, source_count=len(self.source))
        target_job, self.source_normals = per_cloud(_apply, (target_setup, self.target), (_source_normals, self.source))
        self.target_tree, self.target_spacing, self.target_normals = target_job
        self.sharp_distance = config.sharp_factor * self.target_spacing
        self.match_tolerance = config.match_tolerance * scale
        self.centre = self.source.mean(axis=0)
        # Half-turns about the source's principal axes, through its centroid: (3, 4, 4).
        _, axes = np.linalg.eigh(np.cov((self.source - self.centre).T))
        self.half_turns = np.stack([_half_turn(axes[:, i], self.centre) for i in range(3)])
        # The second look's turn-overs: axes in the plane of the two largest principal axes
        # (eigh sorts them last), which turn a plate over, whichever way it lies.
        angles = np.pi * np.arange(config.turn_over_axes) / max(1, config.turn_over_axes)
        self.turn_overs = [_half_turn(np.cos(a) * axes[:, 2] + np.sin(a) * axes[:, 1], self.centre) for a in angles]
        # ... and the spin in that plane (about the least axis), which no turn-over or ICP reaches.
        self.spin = self.half_turns[0] if config.turn_over_spin else None
        self.screen_source = self.source[seeded_subset(len(self.source), TURN_OVER_SCREEN_POINTS, generator)]
        self._refined: dict[bytes, np.ndarray] = {}

    def fast_exit(self, estimator: str, pose: np.ndarray) -> VerificationResult | None:
        """The fast exit: ``pose`` (the exit estimator's, user frame) refined and scored alone.

        Returns the one-hypothesis result when the exit model's confidence on its features
        (EXIT_FEATURES: those of this hypothesis alone) reaches ``exit_threshold``, else None
        (the caller then verifies every candidate, :meth:`verify`; the refinement done here is
        reused). None as well without an exit model.
        """
        if not self.config.fast_exit:
            return None
        refined = self.refine(pose)
        features = self.features(refined)
        confidence = exit_confidence(features, self.config)
        if confidence < self.config.exit_threshold:
            return None
        hypothesis = Hypothesis(
            estimators=(estimator,),
            transformation=pose,
            verified_transformation=refined,
            features=dict(zip(VERIFICATION_FEATURES, features.tolist(), strict=True)),
            confidence=confidence,
            refined=True,
        )
        return VerificationResult(best=hypothesis, hypotheses=(hypothesis,), candidate_count=1, fast_exit=True)

    def features(self, pose: np.ndarray, agreement: float = 0.0, margin: float = 0.0) -> np.ndarray:
        """(F,) float64 features of ``pose`` (module docstring), in VERIFICATION_FEATURES order."""
        rotation, translation = pose[:3, :3], pose[:3, 3]
        moved = self.source @ rotation.T + translation
        distance, index = self.target_tree.query(moved, k=1, distance_upper_bound=self.query_bound)
        inlier = distance < self.distance
        fitness = float(np.mean(inlier))
        sharp = float(np.mean(distance[inlier] < self.sharp_distance)) if inlier.any() else 0.0
        rmse = float(np.sqrt(np.mean(distance[inlier] ** 2)) / self.distance) if inlier.any() else 1.0
        reverse_distance, _ = KDTree(moved).query(self.target, k=1, distance_upper_bound=self.query_bound)
        reverse = float(np.mean(reverse_distance < self.distance))
        if inlier.any():
            moved_normals = self.source_normals[inlier] @ rotation.T
            agreement_of_normals = float(
                np.mean(np.abs(np.sum(moved_normals * self.target_normals.at(index[inlier]), axis=1)))
            )
        else:
            agreement_of_normals = 0.0
        residual = np.linalg.norm(self.source_matched @ rotation.T + translation - self.target_matched, axis=1)
        total = float(np.sum(self.confidences))
        match_ratio = float(np.sum(self.confidences[residual < self.match_tolerance]) / total) if total > 0 else 0.0
        flipped_fitness = 0.0
        for turn in self.half_turns:
            flipped = pose @ turn
            flipped_fitness = max(flipped_fitness, self.fitness(flipped))
        symmetry = min(1.5, flipped_fitness / fitness) if fitness > 0 else 0.0
        values = {
            "fitness": fitness,
            "sharpness": sharp,
            "rmse_ratio": rmse,
            "reverse_fitness": reverse,
            "normal_agreement": agreement_of_normals,
            "match_inlier_ratio": match_ratio,
            "log_matches": math.log1p(len(self.confidences)) / LOG_MATCH_SCALE,
            "agreement": agreement,
            "margin": margin,
            "symmetry": symmetry,
        }
        return np.array([values[name] for name in VERIFICATION_FEATURES])

    def fitness(self, pose: np.ndarray) -> float:
        """The ``fitness`` feature of ``pose`` alone (one k-d tree query)."""
        moved = self.source @ pose[:3, :3].T + pose[:3, 3]
        distance, _ = self.target_tree.query(moved, k=1, distance_upper_bound=self.query_bound)
        return float(np.mean(distance < self.distance))

    def quick_score(self, pose: np.ndarray) -> float:
        """fitness + match_inlier_ratio of ``pose`` (the two features :meth:`verify` ranks its
        candidates by before refining), at a fraction of :meth:`features`' cost."""
        rotation, translation = pose[:3, :3], pose[:3, 3]
        fitness = self.fitness(pose)
        residual = np.linalg.norm(self.source_matched @ rotation.T + translation - self.target_matched, axis=1)
        total = float(np.sum(self.confidences))
        match_ratio = float(np.sum(self.confidences[residual < self.match_tolerance]) / total) if total > 0 else 0.0
        return fitness + match_ratio

    def refine(self, pose: np.ndarray) -> np.ndarray:
        """(4, 4) ``pose`` after a short point-to-plane ICP on the subsets (adaptive distance);
        a pose refined before is not refined again (the same result: ICP is deterministic)."""
        key = np.ascontiguousarray(pose, dtype=np.float64).tobytes()
        if key not in self._refined:
            self._refined[key] = self._short_icp(pose)
        return self._refined[key]

    def _short_icp(self, pose: np.ndarray) -> np.ndarray:
        return icp(
            self.source,
            self.target,
            pose,
            self.distance,
            "point_to_plane",
            max_iterations=self.config.icp_iterations,
            adaptive=True,
            target_normals=self.target_normals,
            target_spacing=self.target_spacing,
        ).transformation

    def verify(
        self,
        candidates: list[tuple[str, np.ndarray]],
        second_consensus: Callable[[np.ndarray], list[tuple[str, np.ndarray]]] | None = None,
    ) -> VerificationResult:
        """Merge equal candidates, refine the best few, take the second look, score, and rank.

        Args:
            candidates: [(estimator name, (4, 4) user-frame pose)], at least one; names outside
                the config's candidates (e.g. "init") are scored but do not count as agreement.
            second_consensus: the leading refined pose (4, 4, user frame) -> the second look's
                ``unexplained_*`` candidates (user frame); None: none (the turn-overs still run
                when ``turn_over_axes`` > 0).

        Returns:
            :class:`VerificationResult`, hypotheses ranked by confidence (ties: the order of
            ``candidates``, then of the second look's).
        """
        if not candidates:
            raise ValueError("verify: no candidate poses")
        config = self.config
        groups: list[tuple[list[str], np.ndarray]] = []
        self._merge(groups, candidates)
        # Rank by fitness and match agreement first, then refine the best few.
        quick = [self.quick_score(pose) for _, pose in groups]
        order = sorted(range(len(groups)), key=lambda i: -quick[i])
        verified = {i: self.refine(groups[i][1]) for i in order[: config.refine_candidates]}
        first_groups = len(groups)
        alternatives = self._second_look(verified, second_consensus)
        self._merge(groups, alternatives)
        for i in range(first_groups, len(groups)):
            verified[i] = self.refine(groups[i][1])
        poses = [verified.get(i, pose) for i, (_, pose) in enumerate(groups)]
        fitness = [self.fitness(pose) for pose in poses]  # the margins compare these
        estimators = set(config.candidates)
        estimator_count = max(1, sum(name in estimators for name, _ in candidates))
        hypotheses = []
        for i, (names, pose) in enumerate(groups):
            rivals = [fitness[j] for j in range(len(groups)) if j != i]
            margin = fitness[i] - max(rivals) if rivals else 0.0
            agreement = sum(name in estimators for name in names) / estimator_count
            features = self.features(poses[i], agreement=agreement, margin=margin)
            hypotheses.append(
                Hypothesis(
                    estimators=tuple(names),
                    # A turn-over's raw half-turn is no estimate: its pose is the refined one.
                    transformation=poses[i] if names[0] in (TURNED_OVER, SPUN) else pose,
                    verified_transformation=poses[i],
                    features=dict(zip(VERIFICATION_FEATURES, features.tolist(), strict=True)),
                    confidence=logistic_confidence(features, config),
                    refined=i in verified,
                )
            )
        ranked = sorted(range(len(hypotheses)), key=lambda i: (-hypotheses[i].confidence, i))
        ordered = tuple(hypotheses[i] for i in ranked)
        return VerificationResult(
            best=ordered[0], hypotheses=ordered, candidate_count=len(candidates) + len(alternatives)
        )

    def _merge(self, groups: list[tuple[list[str], np.ndarray]], candidates: list[tuple[str, np.ndarray]]) -> None:
        """Add each candidate to the first group with the same pose (its name), or as a new group."""
        for name, pose in candidates:
            for names, kept in groups:
                if _same_pose(pose, kept, self.config.same_pose_deg, self.distance, self.centre):
                    names.append(name)
                    break
            else:
                groups.append(([name], pose))

    def _second_look(
        self,
        verified: dict[int, np.ndarray],
        second_consensus: Callable[[np.ndarray], list[tuple[str, np.ndarray]]] | None,
    ) -> list[tuple[str, np.ndarray]]:
        """The second look's candidates (module docstring), from the refined pose with the best
        :meth:`quick_score` (the lowest group index among ties)."""
        if not self.turn_overs and self.spin is None and second_consensus is None:
            return []
        leading = verified[max(sorted(verified), key=lambda i: self.quick_score(verified[i]))]
        alternatives = []
        if self.turn_overs:
            # Screened by a short batched point-to-point ICP on a few source points: refining
            # every turn would cost more than the rest of verification.
            poses, fitness = point_to_point_icp_batch(
                self.screen_source, self.target_tree, self.target, leading @ np.stack(self.turn_overs), self.distance,
                TURN_OVER_SCREEN_ITERATIONS,
            )
            alternatives.append((TURNED_OVER, poses[int(np.argmax(fitness))]))  # the first among ties
        if self.spin is not None:
            # Screened alone, not against the turn-overs: a spin that fits less well than the
            # best turn-over still gets its refined score.
            poses, _ = point_to_point_icp_batch(
                self.screen_source, self.target_tree, self.target, (leading @ self.spin)[None], self.distance,
                TURN_OVER_SCREEN_ITERATIONS,
            )
            alternatives.append((SPUN, poses[0]))
        if second_consensus is not None:
            alternatives += second_consensus(leading)
        return alternatives

    def pose_within_verified(self, pose: np.ndarray, hypothesis: Hypothesis) -> bool:
        """Whether ``pose`` lies within ``same_pose_deg`` (and d) of the hypothesis' verified pose."""
        return _same_pose(
            pose, hypothesis.verified_transformation, self.config.same_pose_deg, self.distance, self.centre
        )

    def confidence_at(self, pose: np.ndarray, hypothesis: Hypothesis, fast_exit: bool = False) -> float:
        """Calibrated confidence of ``pose`` (e.g. the hypothesis after the full ICP), with the
        hypothesis' agreement and margin; the exit model's for a hypothesis of the fast exit."""
        features = self.features(pose, hypothesis.features["agreement"], hypothesis.features["margin"])
        return exit_confidence(features, self.config) if fast_exit else logistic_confidence(features, self.config)

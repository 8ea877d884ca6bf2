"""Typed configuration of every stage, the one source of truth for their parameters.

Training, export and the runtime all read these classes. The exported model stores the
geometry and normalisation configs in its metadata (``to_dict``), and the runtime rebuilds
them with ``from_dict``, so the three can never disagree on a radius or a neighbour count.
Lengths are in *network units*: the frame :mod:`logdesc_rt.normalization` maps clouds into,
where a training object fits the unit sphere.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

_Config = TypeVar("_Config")

# Edge-feature layouts and their channel counts (see GeometryConfig.edge_layout).
EDGE_CHANNELS = {"paper": 15, "invariant": 11, "chiral": 13}
EDGE_LAYOUTS = tuple(EDGE_CHANNELS)
NORMAL_SOURCES = ("umbrella", "pca")


class _DictMixin:
    """Round-trip a flat dataclass through a JSON-friendly dict, rejecting unknown keys."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls: type[_Config], values: dict[str, Any]) -> _Config:
        known = {field.name for field in dataclasses.fields(cls)}  # type: ignore[arg-type]
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown keys {sorted(unknown)}")
        return cls(**values)


@dataclass(frozen=True)
class GeometryConfig(_DictMixin):
    """Per-point geometry (paper section 3.3; METHOD_NOTES "Geometry").

    Attributes:
        pca_radius: neighbours farther than this are left out of the covariance (network units).
        pca_max_neighbours: at most this many nearest neighbours (the point itself included).
        pca_min_neighbours: the nearest this-many points are always used, even beyond the
            radius, so that isolated points (outliers, sparse scans) still get a shape and an LRF
            that moves with the cloud. The paper's radius-only rule leaves them undefined.
        umbrella_neighbours: k of the umbrella normals and of the edge features (point excluded).
        umbrella_area_temperature: triangle areas are divided by this before the softmax that
            weights the triangle normals (network units squared); the official 1e-4 makes the
            largest triangle dominate.
        edge_layout: which edge features the descriptor network reads.
            ``"paper"``: the paper's 15 channels (absolute position, offsets in the global
            frame, the neighbour's normal in the signed LRF; :mod:`.geometry.edge_features`).
            ``"invariant"``: point-pair features that are unchanged by any rigid motion and by
            the sign of every normal (:mod:`.geometry.invariant_features`).
            ``"chiral"``: those 11 and two that change sign under a reflection (still
            invariant to rigid motions and normal signs), so mirror images differ (v4).
        normals: which unit normal per point is handed to the network.
            ``"umbrella"``: the paper's triangle-umbrella normal.
            ``"pca"``: the LRF's normal axis w (PCA over the ``pca_radius`` neighbourhood), the
            one that agrees best between two noisy or partial views of a surface
            (``docs/decisions.md``); its sign carries no information for the
            invariant layout, which reads only sign-free functions of it.
    """

    pca_radius: float = 0.3
    pca_max_neighbours: int = 128
    pca_min_neighbours: int = 8
    # The defaults are the bundled model's: 20 umbrella / edge neighbours (the paper's 30
    # cost the descriptor about a quarter more time), chiral edges (v3's invariant ones and two
    # that change sign under a reflection) on PCA normals.
    umbrella_neighbours: int = 20
    umbrella_area_temperature: float = 1e-4
    edge_layout: str = "chiral"
    normals: str = "pca"

    def __post_init__(self) -> None:
        if self.edge_layout not in EDGE_LAYOUTS:
            raise ValueError(f"GeometryConfig.edge_layout must be one of {EDGE_LAYOUTS}, got {self.edge_layout!r}")
        if self.normals not in NORMAL_SOURCES:
            raise ValueError(f"GeometryConfig.normals must be one of {NORMAL_SOURCES}, got {self.normals!r}")
        if not self.pca_radius > 0:
            raise ValueError(f"GeometryConfig.pca_radius must be > 0, got {self.pca_radius}")
        if self.pca_max_neighbours < 3:
            raise ValueError(
                f"GeometryConfig.pca_max_neighbours must be >= 3, got {self.pca_max_neighbours}"
            )
        if not 3 <= self.pca_min_neighbours <= self.pca_max_neighbours:
            raise ValueError(
                "GeometryConfig.pca_min_neighbours must be in [3, pca_max_neighbours], "
                f"got {self.pca_min_neighbours}"
            )
        if self.umbrella_neighbours < 3:
            raise ValueError(
                f"GeometryConfig.umbrella_neighbours must be >= 3, got {self.umbrella_neighbours}"
            )
        if not self.umbrella_area_temperature > 0:
            raise ValueError("GeometryConfig.umbrella_area_temperature must be > 0")

    @property
    def min_points(self) -> int:
        """The fewest points a cloud needs: k neighbours plus the point itself."""
        return self.umbrella_neighbours + 1

    @property
    def edge_channels(self) -> int:
        """Channels of the (N, k, C) edge-feature tensor this layout produces."""
        return EDGE_CHANNELS[self.edge_layout]

    @classmethod
    def from_stored(cls, values: dict[str, Any]) -> "GeometryConfig":
        """A geometry as a checkpoint or a manifest stored it. Files without an
        ``edge_layout`` key (the paper architecture) hold the paper's geometry, not the
        defaults."""
        if "edge_layout" not in values:
            values = {**PAPER_GEOMETRY.to_dict(), **values}
        return cls.from_dict(values)


PAPER_GEOMETRY = GeometryConfig(edge_layout="paper", normals="umbrella", umbrella_neighbours=30)
"""The paper's geometry: its 15 edge channels on triangle-umbrella normals over 30 neighbours
(the small-h100 models)."""


@dataclass(frozen=True)
class NormalizationConfig(_DictMixin):
    """How a pair of user clouds is mapped into network units (see :mod:`.normalization`).

    Attributes:
        target_radius: after normalisation the larger of the two clouds' radii (largest
            distance of a non-stray point from the centroid of its cloud's non-stray points)
            equals this.
        stray_neighbours: k of the stray-point test (:mod:`.outliers`): a point is stray when
            its k-th nearest neighbour is far; clumps of fewer than k points count as stray.
        stray_ratio: ... farther than this many times the cloud's median k-th neighbour
            distance. 0 turns the test off (every point counts).
    """

    target_radius: float = 1.0
    stray_neighbours: int = 6
    stray_ratio: float = 3.0

    def __post_init__(self) -> None:
        if not self.target_radius > 0:
            raise ValueError(f"NormalizationConfig.target_radius must be > 0, got {self.target_radius}")
        if self.stray_neighbours < 1:
            raise ValueError(f"NormalizationConfig.stray_neighbours must be >= 1, got {self.stray_neighbours}")
        if not (self.stray_ratio == 0 or self.stray_ratio > 1):
            raise ValueError(f"NormalizationConfig.stray_ratio must be 0 (off) or > 1, got {self.stray_ratio}")


@dataclass(frozen=True)
class MatchingConfig(_DictMixin):
    """Sinkhorn matching (SuperGlue marginals, learned dustbin).

    Attributes:
        sinkhorn_iterations: 50 in the official code.
        match_threshold: a mutual best match is kept if its assignment probability exceeds this.
        dustbin_in_mutual_test: False (default): each point's best real partner, kept
            when it is mutual, however much mass the dustbin holds (the dustbin still shapes the
            plan); on scan pairs, where a trained matcher sends most points to the dustbin, this
            keeps about ten times the matches at a similar inlier share, for the robust
            estimators and verification to sort.
            True (the paper's reading; models stored without the key):
            a point whose largest entry is its dustbin is unmatched. The success flag is
            calibrated for the model's own setting: a model switched by hand keeps a
            calibration fitted on other match counts.
    """

    sinkhorn_iterations: int = 50
    match_threshold: float = 0.0
    dustbin_in_mutual_test: bool = False

    def __post_init__(self) -> None:
        if self.sinkhorn_iterations < 1:
            raise ValueError("MatchingConfig.sinkhorn_iterations must be >= 1")
        if not 0.0 <= self.match_threshold < 1.0:
            raise ValueError("MatchingConfig.match_threshold must be in [0, 1)")

    @classmethod
    def from_stored(cls, values: dict[str, Any]) -> "MatchingConfig":
        """A matching as a manifest or checkpoint stored it. Files without the
        ``dustbin_in_mutual_test`` key match with the paper's reading."""
        return cls.from_dict({"dustbin_in_mutual_test": True, **values})


# ----------------------------------------------------------------------------- runtime stages
# The configs below set what the runtime does with a pair after (or around) the networks.
# Unlike the three above they are not fixed by the trained model; they have defaults that
# work with the bundled model, and every one can be overridden per Registrar or per call.

# Verification features, in the order of VerificationConfig.weights (logdesc_rt/verification.py
# computes them; its module docstring defines each).
# Estimators of candidate poses (logdesc_rt.pose.candidates): the paper's FSR, 3-point RANSAC,
# confidence-weighted SVD on every match, SVD on the most confident share, and the maximum
# consistent core of the matches (logdesc_rt/pose/consistency.py).
CANDIDATE_ESTIMATORS = ("fsr", "ransac", "svd", "top_k", "core")
POSE_ESTIMATORS = ("auto", "fsr", "svd", "ransac", "core")

VERIFICATION_FEATURES = (
    "fitness",
    "sharpness",
    "rmse_ratio",
    "reverse_fitness",
    "normal_agreement",
    "match_inlier_ratio",
    "log_matches",
    "agreement",
    "margin",
    "symmetry",
)
EXIT_FEATURES = tuple(name for name in VERIFICATION_FEATURES if name not in ("agreement", "margin"))
"""The features the fast exit reads: those of one hypothesis alone (no rival, no other estimator)."""


@dataclass(frozen=True)
class VerificationConfig(_DictMixin):
    """Verified hypotheses and the success flag (:mod:`logdesc_rt.verification`).

    Lengths are fractions of the pair's scale (the larger cloud's radius), so the same values
    serve a unit-sphere object and a scan in millimetres.

    Attributes:
        top_k_fraction: the "top-k" hypothesis fits the most confident this share of matches.
        source_points: source points (at most) the poses are scored on; a seeded uniform
            subset of the full cloud.
        target_points: target points (at most) they are scored against.
        distance_fraction: a scored point is an inlier within this x scale (5 %, like
            fitness); independent of the user's max_correspondence_distance, so that the
            calibration holds whatever distance the user reports fitness at.
        sharp_factor: the ``sharpness`` feature counts inliers closer than this many times the
            target's point spacing (median nearest-neighbour distance of the scored subset).
        match_tolerance: a learned match agrees with a pose within this, x scale (FSR's tau).
        refine_candidates: this many best-scoring distinct candidates get a short ICP (all of
            them by default: there are at most five).
        icp_iterations: iterations of that ICP (point-to-plane, on the subsets).
        same_pose_deg: two candidates closer than this (and than ``distance_fraction`` in
            translation) are one hypothesis; it also bounds how far the returned unrefined
            pose may sit from its verified (refined) pose for a success.
        turn_over_axes: the second look (:mod:`logdesc_rt.verification`) turns the leading
            pose's source over by a half-turn about this many axes, evenly spread in the plane
            of the source's two largest principal axes; a short ICP on a few source points
            screens them, and the best is refined; 0: none.
        turn_over_spin: the second look also proposes the leading pose with its source spun
            half a turn about its least principal axis (the normal of that plane), screened
            alone and refined: a flip in the plane, which neither the turn-overs nor an ICP
            reaches. Off by default (``docs/decisions.md``).
        second_consensus: the estimators (of CANDIDATE_ESTIMATORS) the second look runs on the
            matches the leading pose leaves unexplained (the true pose of a symmetric object
            whose mirrored twin matches outvoted it); empty: none.
        descriptor_consensus: the estimators (of CANDIDATE_ESTIMATORS) also run on the
            descriptors' own mutual nearest neighbours (before the matcher's transformer; a
            pair matched outside the runtime, without descriptors, has none); their
            candidates are named ``descriptor_<estimator>``; empty: none.
        refit_spacings: the pose ``register()`` returns without ICP
            (:func:`logdesc_rt.pose_selection.coarse_pose`) is the least-squares fit of the
            learned matches the chosen hypothesis' verified pose explains within this many of
            the target's working-subset point spacings: a pose from matches, whose inliers the
            verified pose chose; 0: the estimator's own pose.
        refit_plane_steps: then this many Gauss-Newton steps of the same matches' point-to-
            plane fit (independent samples of a surface pair a point with a neighbour of its
            twin: the error along the surface is sampling); 0: none.
        refit_point_weight: the point-to-point term's weight in those steps, relative to the
            point-to-plane term (it holds the directions a flat patch leaves free).
        verified_fallback_rmse: where that re-fit lands farther than ``same_pose_deg`` from the
            chosen hypothesis' verified pose, the verified pose is returned instead (with the
            hypothesis' confidence) when the clouds coincide closely at it: its ``rmse_ratio``
            feature (inlier RMSE over the inlier distance) below this. Dense clouds that
            coincide make the short ICP's pose the better one; on sparse clouds of separate
            samples its optimum is biased and the re-fit is kept, unclaimed. 0: never
            (``benchmarks/results/verified_fallback_rmse/``).
        weights: logistic coefficients, one per feature of VERIFICATION_FEATURES.
        bias: the logistic intercept: confidence = 1 / (1 + exp(-(bias + weights . features))).
        success_threshold: success when confidence >= this.
        seed: seeds the scoring subsets.
        candidates: the estimators whose poses are verified (a calibration is fitted with
            one set: its ``agreement`` feature counts among them). The default is the set the
            shipped model's calibration was fitted with.
        exit_estimator: the fast exit's estimator (of CANDIDATE_ESTIMATORS). Before anything
            else, its pose alone is refined and scored; when the exit model's confidence
            reaches ``exit_threshold``, that hypothesis is kept and the other candidates, the
            second look and the rest of verification do not run (:mod:`logdesc_rt.verification`).
        exit_weights: the exit model's logistic coefficients, one per feature of
            EXIT_FEATURES (the hypothesis' own features, without agreement and margin); empty:
            no fast exit (every pair is verified in full).
        exit_bias: its intercept.
        exit_threshold: a pair exits when the exit model's confidence is at least this; the
            calibration sets it where the exits were right at least 99 % of the time.
    """

    top_k_fraction: float = 0.25
    source_points: int = 2000
    target_points: int = 8000
    distance_fraction: float = 0.05
    sharp_factor: float = 1.0
    match_tolerance: float = 0.08
    refine_candidates: int = 5
    icp_iterations: int = 20
    same_pose_deg: float = 4.0
    turn_over_axes: int = 6
    turn_over_spin: bool = False
    second_consensus: tuple[str, ...] = ("ransac",)
    descriptor_consensus: tuple[str, ...] = ("ransac",)
    refit_spacings: float = 2.0
    refit_plane_steps: int = 3
    refit_point_weight: float = 0.1
    verified_fallback_rmse: float = 0.5
    # A calibration belongs to a model: the one in effect is the model manifest's
    # ("runtime" -> "verification"). These defaults are the bundled model's (held equal to
    # its manifest by tests/test_verification.py), the fit of benchmarks/calibrate_success.py
    # on validation pairs (benchmarks/results/success_calibration.{md,json} say on what and how
    # well); a model exported without a calibration gets them.
    weights: tuple[float, ...] = (
        0.29030458126252257,
        2.0759511475710997,
        -7.72893913351615,
        0.7789847902886062,
        2.338426508563753,
        4.421035133029792,
        -1.4109939471758348,
        1.0979349467725652,
        2.2577199393805687,
        -1.1777597470622283,
    )
    bias: float = -0.006777752737214371
    success_threshold: float = 0.6374
    seed: int = 0
    candidates: tuple[str, ...] = ("fsr", "ransac", "svd", "top_k", "core")
    exit_estimator: str = "fsr"
    exit_weights: tuple[float, ...] = (
        0.41448248662254983,
        2.8427933193113333,
        -7.806858068770783,
        0.720086674214041,
        3.1607671869316425,
        4.850229111661629,
        -0.20085398826203418,
        -1.5024416162771945,
    )
    exit_bias: float = -1.3384458192176059
    exit_threshold: float = 0.7913

    @property
    def fast_exit(self) -> bool:
        """Whether this calibration has a fast exit."""
        return len(self.exit_weights) > 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", tuple(float(w) for w in self.weights))
        object.__setattr__(self, "exit_weights", tuple(float(w) for w in self.exit_weights))
        if self.exit_weights and len(self.exit_weights) != len(EXIT_FEATURES):
            raise ValueError(
                f"VerificationConfig.exit_weights: {len(self.exit_weights)} values, expected none or one per "
                f"feature {EXIT_FEATURES}"
            )
        if self.exit_estimator not in CANDIDATE_ESTIMATORS:
            raise ValueError(
                f"VerificationConfig.exit_estimator: {self.exit_estimator!r} is not one of {CANDIDATE_ESTIMATORS}"
            )
        if not 0.0 <= self.exit_threshold <= 1.0:
            raise ValueError(f"VerificationConfig.exit_threshold must be in [0, 1], got {self.exit_threshold}")
        object.__setattr__(self, "candidates", tuple(str(name) for name in self.candidates))
        unknown = set(self.candidates) - set(CANDIDATE_ESTIMATORS)
        if unknown or not self.candidates:
            raise ValueError(
                f"VerificationConfig.candidates: {list(self.candidates)} must be a non-empty subset of "
                f"{CANDIDATE_ESTIMATORS}"
            )
        for name in ("second_consensus", "descriptor_consensus"):
            estimators = getattr(self, name)
            if not isinstance(estimators, (tuple, list)):
                raise ValueError(f"VerificationConfig.{name} must be a list of estimators, got {estimators!r}")
            object.__setattr__(self, name, tuple(str(estimator) for estimator in estimators))
            if set(getattr(self, name)) - set(CANDIDATE_ESTIMATORS):
                raise ValueError(
                    f"VerificationConfig.{name}: {list(getattr(self, name))} must be a subset of "
                    f"{CANDIDATE_ESTIMATORS}"
                )
        if len(self.weights) != len(VERIFICATION_FEATURES):
            raise ValueError(
                f"VerificationConfig.weights: {len(self.weights)} values, expected one per feature "
                f"{VERIFICATION_FEATURES}"
            )
        if not 0.0 < self.top_k_fraction <= 1.0:
            raise ValueError(f"VerificationConfig.top_k_fraction must be in (0, 1], got {self.top_k_fraction}")
        for name in ("source_points", "target_points"):
            if getattr(self, name) < 10:
                raise ValueError(f"VerificationConfig.{name} must be >= 10, got {getattr(self, name)}")
        for name in ("distance_fraction", "sharp_factor", "match_tolerance", "same_pose_deg"):
            value = getattr(self, name)
            if not 0.0 < value < float("inf"):  # also rejects NaN
                raise ValueError(f"VerificationConfig.{name} must be finite and > 0, got {value}")
        if not 0.0 <= self.refit_spacings < float("inf"):  # also rejects NaN
            raise ValueError(f"VerificationConfig.refit_spacings must be finite and >= 0, got {self.refit_spacings}")
        steps = self.refit_plane_steps
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise ValueError(f"VerificationConfig.refit_plane_steps must be an integer >= 0, got {steps!r}")
        if not 0.0 <= self.refit_point_weight < float("inf"):  # also rejects NaN
            raise ValueError(
                f"VerificationConfig.refit_point_weight must be finite and >= 0, got {self.refit_point_weight}"
            )
        if not 0.0 <= self.verified_fallback_rmse < float("inf"):  # also rejects NaN
            raise ValueError(
                f"VerificationConfig.verified_fallback_rmse must be finite and >= 0, got {self.verified_fallback_rmse}"
            )
        if self.refine_candidates < 1:
            raise ValueError(f"VerificationConfig.refine_candidates must be >= 1, got {self.refine_candidates}")
        if self.icp_iterations < 1:
            raise ValueError(f"VerificationConfig.icp_iterations must be >= 1, got {self.icp_iterations}")
        if isinstance(self.turn_over_axes, bool) or not isinstance(self.turn_over_axes, int) or self.turn_over_axes < 0:
            raise ValueError(f"VerificationConfig.turn_over_axes must be an integer >= 0, got {self.turn_over_axes!r}")
        if not isinstance(self.turn_over_spin, bool):
            raise ValueError(f"VerificationConfig.turn_over_spin must be true or false, got {self.turn_over_spin!r}")
        if not 0.0 <= self.success_threshold <= 1.0:
            raise ValueError(f"VerificationConfig.success_threshold must be in [0, 1], got {self.success_threshold}")
        if self.seed < 0:
            raise ValueError(f"VerificationConfig.seed must be >= 0, got {self.seed}")


@dataclass(frozen=True)
class FsrConfig(_DictMixin):
    """Parameters of :func:`~logdesc_rt.pose.fsr` (paper Algorithm 1; official defaults).

    Attributes:
        iterations: N, the number of sampling rounds (official: 7).
        sample_size: k, matched points farthest-point-sampled per round. 0 (default) means
            the official rule ``max(3, n_matches // iterations)``; any explicit k >= 3 is
            used as is (capped at the number of matches).
        inlier_threshold: tau, a pair counts as inlier when ``||R x + t - y|| < tau``
            (network units; official 0.08, where a training object fits the unit sphere).
        seed: seeds ``np.random.default_rng``, which picks each round's first FPS point.
        min_matches_for_sampling: with fewer matches than this, no rounds are run: one
            SVD, weighted by the confidences, on the ``fallback_matches`` most confident
            matches (official: 100).
        fallback_matches: how many of the most confident matches that single SVD uses
            (official: 128).
        refit_on_inliers: an improvement over the paper, on by default. The winning
            transform (or the few-matches SVD) is refined by local optimisation: re-solve
            the SVD on its inliers (weighted by the confidences when given), recount, and
            repeat until the inlier set stops changing, at most ``refit_rounds`` times
            (see :func:`~logdesc_rt.pose.svd.refine_on_inliers`). The paper keeps the best
            round's transform, fitted to only k pairs, some of them outliers: with 50 %
            outliers among 500 matches that transform is typically 5-20 degrees off, the
            refined one within 0.1 degree.
        refit_rounds: the most re-solves ``refit_on_inliers`` performs (>= 1).
    """

    iterations: int = 7
    sample_size: int = 0
    inlier_threshold: float = 0.08
    seed: int = 0
    min_matches_for_sampling: int = 100
    fallback_matches: int = 128
    refit_on_inliers: bool = True
    refit_rounds: int = 5

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ValueError(f"FsrConfig.iterations must be >= 1, got {self.iterations}")
        if self.sample_size != 0 and self.sample_size < 3:
            raise ValueError(
                f"FsrConfig.sample_size must be 0 (automatic) or >= 3, got {self.sample_size}"
            )
        if not 0.0 < self.inlier_threshold < float("inf"):  # also rejects NaN
            raise ValueError(
                f"FsrConfig.inlier_threshold must be finite and > 0, got {self.inlier_threshold}"
            )
        if self.seed < 0:
            raise ValueError(f"FsrConfig.seed must be >= 0, got {self.seed}")
        if self.min_matches_for_sampling < 0:
            raise ValueError("FsrConfig.min_matches_for_sampling must be >= 0")
        if self.fallback_matches < 3:
            raise ValueError(f"FsrConfig.fallback_matches must be >= 3, got {self.fallback_matches}")
        if self.refit_rounds < 1:
            raise ValueError(f"FsrConfig.refit_rounds must be >= 1, got {self.refit_rounds}")

    def resolved_sample_size(self, match_count: int) -> int:
        """k for ``match_count`` matches: the explicit value, or ``max(3, n // N)``; <= n."""
        size = self.sample_size if self.sample_size else max(3, match_count // self.iterations)
        return min(size, match_count)


@dataclass(frozen=True)
class RansacConfig(_DictMixin):
    """Parameters of :func:`~logdesc_rt.pose.ransac`.

    Attributes:
        inlier_threshold: a correspondence is an inlier when ``||R x + t - y|| < this``
            (network units, same default as FSR's tau).
        max_iterations: the most 3-point hypotheses drawn (Open3D's ``max_iteration``).
        confidence: stop early once this probability of having drawn an all-inlier sample
            is reached, estimated from the best inlier ratio w: after
            ``log(1 - confidence) / log(1 - w**3)`` draws. 1.0 disables the early stop.
        edge_length_similarity: reject a sample unless each of its 3 source edges and the
            matching target edge satisfy ``shorter >= similarity * longer`` (Open3D's
            checker, 0.9). 0 disables the check.
        batch_size: hypotheses drawn and solved together. It changes speed and, through
            the early stop (checked after each batch), which hypotheses are drawn; results
            stay reproducible for a given config.
        seed: seeds ``np.random.default_rng`` for the samples.
        refit_on_inliers: refine the best hypothesis by re-solving the SVD on its inliers,
            repeated until they stop changing, at most ``refit_rounds`` times (see
            :func:`~logdesc_rt.pose.svd.refine_on_inliers`).
        refit_rounds: the most re-solves of that refinement (>= 1).
    """

    inlier_threshold: float = 0.08
    max_iterations: int = 10000
    confidence: float = 0.999
    edge_length_similarity: float = 0.9
    batch_size: int = 256
    seed: int = 0
    refit_on_inliers: bool = True
    refit_rounds: int = 5

    def __post_init__(self) -> None:
        if not 0.0 < self.inlier_threshold < float("inf"):  # also rejects NaN
            raise ValueError(
                f"RansacConfig.inlier_threshold must be finite and > 0, got {self.inlier_threshold}"
            )
        if self.max_iterations < 1:
            raise ValueError(f"RansacConfig.max_iterations must be >= 1, got {self.max_iterations}")
        if not 0.0 < self.confidence <= 1.0:
            raise ValueError(f"RansacConfig.confidence must be in (0, 1], got {self.confidence}")
        if not 0.0 <= self.edge_length_similarity < 1.0:
            raise ValueError(
                f"RansacConfig.edge_length_similarity must be in [0, 1), got {self.edge_length_similarity}"
            )
        if self.batch_size < 1:
            raise ValueError(f"RansacConfig.batch_size must be >= 1, got {self.batch_size}")
        if self.seed < 0:
            raise ValueError(f"RansacConfig.seed must be >= 0, got {self.seed}")
        if self.refit_rounds < 1:
            raise ValueError(f"RansacConfig.refit_rounds must be >= 1, got {self.refit_rounds}")


SUBSAMPLING_METHODS = ("fps", "voxel")
DEFAULT_WORKING_SIZE = 320
"""The bundled model's working size (points per cloud its networks see), for code that has no
model at hand (the CLI reads its inputs before loading one; a checkpoint without the value);
tests hold it equal to the bundled manifest's."""
REFINEMENT_METHODS = ("point_to_point", "point_to_plane")


@dataclass(frozen=True)
class SubsamplingConfig(_DictMixin):
    """How a cloud larger than the working size is reduced for the network.

    Attributes:
        max_points: working size per cloud; 0 leaves it to the model: its manifest's
            ``runtime.subsampling.max_points``, else the size it was exported at (for the
            bundled model ``DEFAULT_WORKING_SIZE``). Larger clouds are subsampled to it; memory
            grows with its square.
        method: "fps" (farthest-point sampling) or "voxel" (a grid sized to keep about
            ``max_points``, then farthest-point sampling to the exact count).
        second_draw: off by default. When on and the success flag does not claim the result,
            the pair is matched again on working subsets of the same size drawn by the other
            method ("voxel" for "fps" and back), registered the same way, and the more
            confident of the two results returned (ties: the first). Claimed pairs pay
            nothing; pairs whose clouds give the same subsets both ways (no larger than the
            working size) are not matched again. On 1,440 validation pairs it registered 2.3
            points more, at up to twice the time of the pairs the flag does not claim, and the
            flag's precision fell 0.5 points (``benchmarks/results/second_draw/``).
    """

    max_points: int = 0
    method: str = "fps"
    second_draw: bool = False

    def __post_init__(self) -> None:
        if self.max_points < 0:
            raise ValueError(f"SubsamplingConfig.max_points must be >= 0 (0: the model's), got {self.max_points}")
        if self.method not in SUBSAMPLING_METHODS:
            raise ValueError(f"SubsamplingConfig.method must be one of {SUBSAMPLING_METHODS}, got {self.method!r}")


@dataclass(frozen=True)
class RefinementConfig(_DictMixin):
    """ICP on the full clouds after the learned pose (:mod:`logdesc_rt.refinement`).

    Attributes:
        method: None (no refinement), "point_to_point" or "point_to_plane".
        max_correspondence_distance: for ICP, fitness and inlier RMSE, in the clouds' unit;
            None means ``distance_fraction`` x the pair's scale (the larger cloud's radius).
        distance_fraction: see above (5 %).
        max_iterations: ICP's iteration limit.
        tolerance: ICP stops when an update's rotation (radians) plus translation (as a
            fraction of the correspondence distance) is below this.
        adaptive: once ICP converges, halve the distance and run again while enough inliers
            stay (:mod:`logdesc_rt.refinement`): on real scans with partial overlap a distance
            of 5 % of the radius lets points beside the overlap pull the pose.
        max_source_points: ICP iterates on a seeded uniform subset of at most this many source
            points (None: all of them), against the whole target; the returned fitness and
            inlier RMSE are those of :attr:`evaluation_points`. 20,000 residuals determine six
            pose parameters as well as 200,000 do, at a tenth of the cost per iteration.
        coarse_source_points: the adaptive stages iterate on a seeded subset of at most this
            many of those points, then one stage at the last distance polishes the pose on all
            of them (None: every stage on all). The stages only bring the pose near where the
            last distance's ICP settles, which 5,000 residuals do as well as 20,000; clouds of
            at most this many source points refine exactly as without it.
        evaluation_points: the result's fitness and inlier RMSE are computed over a seeded
            uniform subset of at most this many source points (None: all of them), each
            against the whole target; the result's ``fitness_points`` says how many. The
            work then stays bounded on large clouds: one k-d tree of the target and one
            bounded query (a share of 20,000 samples has a standard error below 0.004). After
            ICP, when this equals ``max_source_points``, ICP's last query on the same subset
            is that evaluation: no second tree.
        seed: seeds those subsets.
    """

    method: str | None = None
    max_correspondence_distance: float | None = None
    distance_fraction: float = 0.05
    max_iterations: int = 30
    tolerance: float = 1e-7
    adaptive: bool = True
    max_source_points: int | None = 20_000
    coarse_source_points: int | None = 5_000
    evaluation_points: int | None = 20_000
    seed: int = 0

    def __post_init__(self) -> None:
        if self.evaluation_points is not None and self.evaluation_points < 1:
            raise ValueError(f"RefinementConfig.evaluation_points must be None or >= 1, got {self.evaluation_points}")
        if self.method is not None and self.method not in REFINEMENT_METHODS:
            raise ValueError(
                f"RefinementConfig.method must be None or one of {REFINEMENT_METHODS}, got {self.method!r}"
            )
        distance = self.max_correspondence_distance
        if distance is not None and not 0.0 < distance < float("inf"):
            raise ValueError(f"RefinementConfig.max_correspondence_distance must be None or > 0, got {distance}")
        if not 0.0 < self.distance_fraction < float("inf"):
            raise ValueError(f"RefinementConfig.distance_fraction must be > 0, got {self.distance_fraction}")
        if self.max_iterations < 1:
            raise ValueError(f"RefinementConfig.max_iterations must be >= 1, got {self.max_iterations}")
        if not self.tolerance >= 0:
            raise ValueError(f"RefinementConfig.tolerance must be >= 0, got {self.tolerance}")
        for name in ("max_source_points", "coarse_source_points"):
            count = getattr(self, name)
            if count is not None and count < 6:
                raise ValueError(f"RefinementConfig.{name} must be None or >= 6, got {count}")
        if self.seed < 0:
            raise ValueError(f"RefinementConfig.seed must be >= 0, got {self.seed}")


_RUNTIME_SECTIONS = {
    "subsampling": SubsamplingConfig,
    "matching": MatchingConfig,
    "fsr": FsrConfig,
    "ransac": RansacConfig,
    "verification": VerificationConfig,
    "refinement": RefinementConfig,
}


# Sections a trained model supplies when a RuntimeConfig leaves them None.
_MODEL_SECTIONS = ("matching", "verification")


@dataclass(frozen=True)
class RuntimeConfig:
    """Every runtime stage's parameters in one place: what ``Registrar`` does with a pair.

    The geometry and normalisation are fixed by the trained model (its manifest) and are not
    here. A model's manifest stores its runtime defaults ("runtime": a partial dict of this
    class, e.g. the success-flag calibration fitted for that model); ``Registrar.config`` is
    them, resolved. Printed by ``logdesc-rt register --json`` under "config"; ``--config FILE``
    and ``Registrar(config={...})`` take a partial dict applied over the model's defaults.

    Attributes:
        subsampling: working size and method (:class:`SubsamplingConfig`).
        matching: Sinkhorn iterations and match threshold; None uses the model's own.
        estimator: "auto" (every candidate estimator, verified; the best kept, default),
            or one of "fsr", "svd", "ransac", "core" (that estimator's pose, still verified).
        fsr, ransac: the two robust estimators (network units; also the "auto" candidates).
        verification: hypotheses, scoring and the success flag; None uses the model's own
            (its calibration).
        refinement: ICP and the correspondence distance for fitness / inlier RMSE.
    """

    subsampling: SubsamplingConfig = SubsamplingConfig()
    matching: MatchingConfig | None = None
    estimator: str = "auto"
    fsr: FsrConfig = FsrConfig()
    ransac: RansacConfig = RansacConfig()
    verification: VerificationConfig | None = None
    refinement: RefinementConfig = RefinementConfig()

    def __post_init__(self) -> None:
        if self.estimator not in POSE_ESTIMATORS:
            raise ValueError(f"RuntimeConfig.estimator must be one of {POSE_ESTIMATORS}, got {self.estimator!r}")
        for name, kind in _RUNTIME_SECTIONS.items():
            value = getattr(self, name)
            if not (isinstance(value, kind) or (name in _MODEL_SECTIONS and value is None)):
                raise TypeError(f"RuntimeConfig.{name} must be a {kind.__name__}, got {type(value).__name__}")

    def to_dict(self) -> dict[str, Any]:
        """Nested JSON-friendly dict (``matching`` / ``verification`` None: the model's)."""
        values: dict[str, Any] = {"estimator": self.estimator}
        for name in _RUNTIME_SECTIONS:
            section = getattr(self, name)
            values[name] = None if section is None else section.to_dict()
        return values

    @classmethod
    def from_dict(cls, values: dict[str, Any], base: "RuntimeConfig | None" = None) -> "RuntimeConfig":
        """``base`` (default: the defaults) with the given values; sections may be partial.

        Raises:
            ValueError: an unknown section or key, or an invalid value.
        """
        base = cls() if base is None else base
        if not isinstance(values, dict):
            raise ValueError(f"RuntimeConfig: expected a JSON object, got {type(values).__name__}")
        unknown = set(values) - set(_RUNTIME_SECTIONS) - {"estimator"}
        if unknown:
            raise ValueError(f"RuntimeConfig: unknown keys {sorted(unknown)}; expected estimator or "
                             f"{sorted(_RUNTIME_SECTIONS)}")
        changes: dict[str, Any] = {}
        if "estimator" in values:
            changes["estimator"] = values["estimator"]
        for name, kind in _RUNTIME_SECTIONS.items():
            if name not in values:
                continue
            given = values[name]
            if given is None:
                if name not in _MODEL_SECTIONS:
                    raise ValueError(f"RuntimeConfig.{name}: null is allowed only for {' and '.join(_MODEL_SECTIONS)}")
                changes[name] = None
                continue
            if not isinstance(given, dict):
                raise ValueError(f"RuntimeConfig.{name}: expected an object, got {type(given).__name__}")
            current = getattr(base, name)
            merged = {**(current.to_dict() if current is not None else {}), **given}
            changes[name] = kind.from_dict(merged)
        return dataclasses.replace(base, **changes)

    def with_seed(self, seed: int) -> "RuntimeConfig":
        """The same config with every random choice (FSR, RANSAC, verification, ICP's subset)
        seeded by ``seed``.

        Raises:
            ValueError: ``verification`` is None (the model's): resolve it first
                (``Registrar.call_config`` does).
        """
        if self.verification is None:
            raise ValueError("RuntimeConfig.with_seed: verification is None (the model's); resolve it first")
        return dataclasses.replace(
            self,
            fsr=dataclasses.replace(self.fsr, seed=seed),
            ransac=dataclasses.replace(self.ransac, seed=seed),
            verification=dataclasses.replace(self.verification, seed=seed),
            refinement=dataclasses.replace(self.refinement, seed=seed),
        )

"""A pair in flight between the stages: :class:`PreparedPair` (loaded, subsampled, normalised,
with its geometry) and :class:`PairMatches` (after the networks and Sinkhorn).

:func:`pair_from_scores` builds a :class:`PairMatches` from matching scores computed elsewhere
(training's torch network), so that training and evaluation read poses through the runtime's
own path (:func:`logdesc_rt.pose_selection.register_matched`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .config import CANDIDATE_ESTIMATORS, MatchingConfig, RuntimeConfig
from .config_resolution import seeded
from .errors import RegistrationError
from .geometry import PointGeometry
from .matching import Matches, mutual_nearest_descriptors, sinkhorn_matches
from .normalization import PairNormalization
from .pose.candidates import candidate_poses, descriptor_candidate_poses, estimate_pose

MIN_MATCHES = 3  # a rigid transform needs three non-collinear pairs


@dataclass(frozen=True)
class PreparedPair:
    """One pair made ready for the networks (:meth:`Registrar.prepare`): loaded, checked,
    subsampled to the working size, mapped into network units, with its geometry.

    Attributes:
        source_points, target_points: (N, 3) / (M, 3) float64 clouds as given (user frame).
        source_index, target_index: (Ns,) / (Mt,) int64, the working subsets' indices.
        normalization: maps the working subsets to network units and poses back.
        source_network, target_network: (Ns, 3) / (Mt, 3) float64 working subsets, network units.
        source_geometry, target_geometry: their kNN, PCA features, normals and (N, k, C) edges;
            None for a pair scored outside the runtime (:func:`pair_from_scores`).
        timings: stage name -> seconds: load, subsample (the working subsets and the
            normalisation), geometry.
    """

    source_points: np.ndarray
    target_points: np.ndarray
    source_index: np.ndarray
    target_index: np.ndarray
    normalization: PairNormalization
    source_network: np.ndarray
    target_network: np.ndarray
    source_geometry: PointGeometry | None
    target_geometry: PointGeometry | None
    timings: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class PairMatches:
    """One pair taken through the learned pipeline up to the matches (:meth:`Registrar.match`).

    Attributes:
        prepared: the pair before the networks (clouds, working subsets, normalisation,
            geometry); its fields are also readable here (``source_points``, ``source_index``,
            ``normalization``, ``source_network`` and their target twins).
        config: the runtime configuration it was matched with (resolved); :meth:`pose` and
            :meth:`candidates` use it by default.
        source_descriptors, target_descriptors: (Ns, d) / (Mt, d) float32 learned descriptors
            (before the matcher's transformer), unit norm; None for a pair scored outside the
            runtime (:func:`pair_from_scores`).
        scores: (Ns, Mt) float32 matching scores <f_i, h_j> / sqrt(d) from the matcher network
            (Sinkhorn with the model's dustbin turns them into the matches).
        matches: mutual matches; indices into the working subsets.
        timings: stage name -> seconds: the preparation's (load, subsample, geometry), then
            descriptors (descriptor network, both clouds), matcher (transformer + scores),
            matching (Sinkhorn + mutual).
    """

    prepared: PreparedPair
    config: RuntimeConfig
    source_descriptors: np.ndarray | None
    target_descriptors: np.ndarray | None
    scores: np.ndarray
    matches: Matches
    timings: dict[str, float] = field(default_factory=dict)

    # The prepared pair's fields, read through (one copy of each array).
    source_points = property(lambda self: self.prepared.source_points)
    target_points = property(lambda self: self.prepared.target_points)
    source_index = property(lambda self: self.prepared.source_index)
    target_index = property(lambda self: self.prepared.target_index)
    normalization = property(lambda self: self.prepared.normalization)
    source_network = property(lambda self: self.prepared.source_network)
    target_network = property(lambda self: self.prepared.target_network)

    @property
    def correspondences(self) -> np.ndarray:
        """(K, 2) int64 rows [source_index, target_index] into the clouds as given."""
        return np.stack(
            [self.source_index[self.matches.source_index], self.target_index[self.matches.target_index]],
            axis=1,
        ).astype(np.int64)

    @property
    def subsampled(self) -> bool:
        """True if the working subset of either cloud leaves points out (a cloud larger than the
        working size, or stray points set aside)."""
        return len(self.source_index) < len(self.source_points) or len(self.target_index) < len(
            self.target_points
        )

    def pose(self, estimator: str = "fsr", seed: int | None = None, config: RuntimeConfig | None = None) -> np.ndarray:
        """(4, 4) user-frame pose source -> target from the matches, one estimator, unverified.

        Args:
            estimator: "fsr", "svd" (confidence-weighted, every match), "ransac" or "top_k"
                (see :mod:`logdesc_rt.pose.candidates`). "auto" needs :meth:`Registrar.register`.
            seed: seeds FSR / RANSAC sampling; None: the config's seeds (0 by default).
            config: FSR / RANSAC / top-k parameters; None: the one it was matched with.

        Raises:
            RegistrationError: fewer than 3 mutual matches.
        """
        if estimator not in CANDIDATE_ESTIMATORS:
            raise ValueError(
                f"estimator {estimator!r}: expected one of {CANDIDATE_ESTIMATORS} (\"auto\" verifies "
                "every candidate: use Registrar.register)"
            )
        config = seeded(self.config if config is None else config, seed)
        self._require_matches()
        network_pose = estimate_pose(
            estimator, *self.matched_network_points(), config.fsr, config.ransac, config.verification.top_k_fraction
        )
        return self.normalization.pose_to_user_frame(network_pose)

    @cached_property
    def descriptor_matches(self) -> Matches | None:
        """The descriptors' own mutual nearest neighbours (before the matcher), indices into the
        working subsets; None for a pair without descriptors (:func:`pair_from_scores`)."""
        if self.source_descriptors is None or self.target_descriptors is None:
            return None
        return mutual_nearest_descriptors(self.source_descriptors, self.target_descriptors)

    def candidates(
        self, config: RuntimeConfig | None = None, estimators: tuple[str, ...] | None = None
    ) -> list[tuple[str, np.ndarray]]:
        """[(estimator, (4, 4) user-frame pose)] of every candidate estimator (unverified), then
        those of ``config.verification.descriptor_consensus`` on :attr:`descriptor_matches`;
        with ``estimators``, those estimators' poses on the matches alone (a degenerate one is
        left out).

        Raises:
            RegistrationError: fewer than 3 mutual matches.
        """
        config = self.config if config is None else config
        self._require_matches()
        all_candidates = estimators is None
        if all_candidates:
            estimators = config.verification.candidates
            if config.estimator not in ("auto", *estimators):  # a user's choice outside the model's set
                estimators = (*estimators, config.estimator)
        poses = candidate_poses(
            *self.matched_network_points(), config.fsr, config.ransac, config.verification.top_k_fraction,
            tuple(estimators),
        )
        if all_candidates and config.verification.descriptor_consensus and self.descriptor_matches is not None:
            poses += descriptor_candidate_poses(
                self.source_network, self.target_network, self.descriptor_matches, config.fsr, config.ransac,
                config.verification.top_k_fraction, config.verification.descriptor_consensus,
            )
        return [(name, self.normalization.pose_to_user_frame(pose)) for name, pose in poses]

    def matched_network_points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(K, 3) source and target points of the matches in network units, and their (K,) confidences."""
        return (
            self.source_network[self.matches.source_index],
            self.target_network[self.matches.target_index],
            self.matches.confidence,
        )

    def _require_matches(self) -> None:
        if len(self.matches) < MIN_MATCHES:
            raise RegistrationError(
                f"the network found {len(self.matches)} mutual matches, a pose needs at least "
                f"{MIN_MATCHES}: the clouds may not overlap, or differ too much from the model's "
                "training data"
            )


def pair_from_scores(
    source_points: np.ndarray,
    target_points: np.ndarray,
    normalization: PairNormalization,
    scores: np.ndarray,
    dustbin_score: float,
    config: RuntimeConfig,
) -> PairMatches:
    """A :class:`PairMatches` from matching scores computed elsewhere: training's torch network
    on clouds already at the working size, read with the runtime's Sinkhorn and mutual test.

    Args:
        source_points, target_points: (N, 3) / (M, 3) float64 clouds in the user frame, each
            its own working subset (every point seen by the network, in the network's order).
        normalization: maps them to the network frame (the one the scores were computed in).
        scores: (N, M) matching scores of the matcher network.
        dustbin_score: the model's learned dustbin score.
        config: a resolved runtime configuration (its ``matching`` set).

    Returns:
        The pair as :meth:`Registrar.match` would return it, without geometry or descriptors.
    """
    matching = config.matching if config.matching is not None else MatchingConfig()
    source_points = np.asarray(source_points, dtype=np.float64)
    target_points = np.asarray(target_points, dtype=np.float64)
    scores = np.asarray(scores, dtype=np.float32)
    if scores.shape != (len(source_points), len(target_points)):
        raise ValueError(f"scores {scores.shape} do not match the clouds ({len(source_points)}, {len(target_points)})")
    matches = sinkhorn_matches(
        scores, dustbin_score, matching.sinkhorn_iterations, matching.match_threshold, matching.dustbin_in_mutual_test
    )
    prepared = PreparedPair(
        source_points=source_points,
        target_points=target_points,
        source_index=np.arange(len(source_points), dtype=np.int64),
        target_index=np.arange(len(target_points), dtype=np.int64),
        normalization=normalization,
        source_network=normalization.source_to_network(source_points),
        target_network=normalization.target_to_network(target_points),
        source_geometry=None,
        target_geometry=None,
    )
    return PairMatches(
        prepared=prepared, config=config, source_descriptors=None, target_descriptors=None, scores=scores,
        matches=matches,
    )

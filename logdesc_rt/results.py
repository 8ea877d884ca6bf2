"""What registration returns: :class:`RegistrationResult` (a pair) and :class:`Descriptors`
(one cloud's learned descriptors)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .config import DEFAULT_WORKING_SIZE, RuntimeConfig
from .io import input_points
from .refinement import IcpResult
from .verification import VerificationResult


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of :func:`register`, in Open3D's vocabulary where it fits.

    Attributes:
        transformation: (4, 4) float64, maps source points into the target frame.
        success: whether verification judges the pose right, i.e. confidence >= the
            calibrated threshold (``benchmarks/results/success_calibration.md``: aimed at a
            rotation error below 5 degrees at least 95 % of the time when True).
        confidence: calibrated probability, in [0, 1], that the returned pose is right
            (rotation error < 5 degrees, translation error < 5 % of the larger radius).
        correspondences: (K, 2) int64 rows [source_index, target_index], indices into the
            clouds as given (before any subsampling): the network's mutual matches.
        confidences: (K,) float64 match probabilities from Sinkhorn, in (0, 1].
        fitness: share of source points with a target point within
            ``max_correspondence_distance`` after the transform, over ``fitness_points``
            source points (all of them up to ``RefinementConfig.evaluation_points``, else a
            seeded uniform subset of that many), each against the whole target.
        inlier_rmse: RMS distance of those point pairs, user units; NaN when there are none
            (``None`` in :meth:`to_dict`).
        fitness_points: how many source points ``fitness`` and ``inlier_rmse`` were computed on.
        max_correspondence_distance: the distance used for fitness and ICP, user units.
        pose_estimator: the estimator whose hypothesis was kept (with ``estimator="auto"``,
            its pose is returned re-fitted on the matches it explains,
            :func:`logdesc_rt.pose_selection.coarse_pose`): "fsr", "ransac", "svd", "top_k",
            "core" (see :mod:`logdesc_rt.pose.candidates`), "descriptor_<estimator>" (that
            estimator on the descriptors' own mutual nearest neighbours), "init" (the caller's initial guess),
            verification's second look: "turned_over" (the leading pose turned over, refined)
            or "unexplained_<estimator>" (that estimator on the matches the leading pose left
            unexplained; :mod:`logdesc_rt.verification`), or "none" (no pose could be
            estimated: the identity, see ``reason``).
        refinement: None, "point_to_point" or "point_to_plane".
        transformation_before_refinement: (4, 4), the learned pipeline's pose before ICP.
        icp: how ICP ended (iterations, converged, stop reason, its fitness / RMSE), or None
            without refinement.
        verification: every distinct hypothesis with its features and confidence (best first).
        config: the runtime configuration used, defaults resolved (working size, matching).
        subsampled: True if the network saw fewer points than given of either cloud (larger
            than the working size, or stray points set aside).
        source_points_used, target_points_used: points the network saw per cloud.
        timings: stage name -> seconds: those of :class:`PairMatches`, then pose,
            refinement (if any), evaluation, second_draw (if it ran: its whole time) and
            total (their sum).
        draws: 1, or 2 when the flag did not claim the first result and the pair was matched
            again on working subsets of the other subsampling method
            (``SubsamplingConfig.second_draw``); ``config.subsampling.method`` is the kept one's.
        reason: None for a success; otherwise why not, in words (too few matches, no
            candidate pose, or a confidence below the threshold). A pair that could not be
            registered at all returns the identity (``pose_estimator`` "none") with fitness
            and RMSE evaluated at it.
    """

    transformation: np.ndarray
    correspondences: np.ndarray
    confidences: np.ndarray
    fitness: float
    inlier_rmse: float
    max_correspondence_distance: float
    pose_estimator: str
    refinement: str | None
    transformation_before_refinement: np.ndarray
    subsampled: bool
    source_points_used: int
    target_points_used: int
    timings: dict[str, float] = field(default_factory=dict)
    icp: IcpResult | None = None
    success: bool = False
    confidence: float = 0.0
    verification: VerificationResult | None = None
    config: RuntimeConfig | None = None
    reason: str | None = None
    fitness_points: int = 0
    draws: int = 1

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rotation block of the transformation."""
        return self.transformation[:3, :3].copy()

    @property
    def translation(self) -> np.ndarray:
        """(3,) translation, user units."""
        return self.transformation[:3, 3].copy()

    def view(self, path, source, target, *, true_transformation=None, max_points: int | None = None,
             seed: int = 0) -> Path:
        """Write an interactive 3D view of this registration: one self-contained HTML file that
        opens offline in any browser (:mod:`logdesc_rt.tools.viewer`; needs plotly, the ``plot`` extra).

        Args:
            path: the .html file to write.
            source, target: the clouds as registered (arrays, or the same paths / meshes as
                given to ``register``: a mesh gives the same seeded surface samples again).
            true_transformation: optional (4, 4) ground truth, for the title's errors.
            max_points: per cloud, at most this many points on the page (default 20,000).
            seed: seeds the thinning.

        Returns:
            The path written.
        """
        from .tools.viewer import DEFAULT_MAX_POINTS, write_registration_view

        working_size = (self.config.subsampling.max_points if self.config is not None else 0) or DEFAULT_WORKING_SIZE
        source, target = (np.asarray(input_points(cloud, working_size=working_size, notify=lambda message: None),
                                     dtype=np.float64) for cloud in (source, target))
        return write_registration_view(
            path, source, target, self, true_transformation=true_transformation,
            max_points=DEFAULT_MAX_POINTS if max_points is None else max_points, seed=seed,
        )

    def to_dict(self) -> dict:
        """JSON-friendly summary (nested lists), as printed by ``logdesc-rt register --json``."""
        return {
            "transformation": self.transformation.tolist(),
            "success": self.success,
            "confidence": self.confidence,
            "reason": self.reason,
            "fitness": self.fitness,
            "fitness_points": self.fitness_points,
            "inlier_rmse": _finite_or_none(self.inlier_rmse),
            "max_correspondence_distance": self.max_correspondence_distance,
            "correspondence_count": int(len(self.correspondences)),
            "correspondences": self.correspondences.tolist(),
            "confidences": self.confidences.tolist(),
            "pose_estimator": self.pose_estimator,
            "refinement": self.refinement,
            "icp": None if self.icp is None else self.icp.to_dict(),
            "hypotheses": []
            if self.verification is None
            else [
                {"estimators": list(h.estimators), "confidence": h.confidence, "features": h.features}
                for h in self.verification.hypotheses
            ],
            "transformation_before_refinement": self.transformation_before_refinement.tolist(),
            "subsampled": self.subsampled,
            "source_points_used": self.source_points_used,
            "target_points_used": self.target_points_used,
            "timings_s": self.timings,
            "draws": self.draws,
            "config": None if self.config is None else self.config.to_dict(),
        }


@dataclass(frozen=True)
class Descriptors:
    """Learned per-point descriptors of one cloud.

    Attributes:
        indices: (K,) int64, the points described (all N unless subsampled).
        descriptors: (K, d) float32, unit norm.
        normals: (K, 3) float64 unit normals (user frame orientation).
    """

    indices: np.ndarray
    descriptors: np.ndarray
    normals: np.ndarray


def _finite_or_none(value: float) -> float | None:
    """``value``, or None for NaN / inf (JSON has no NaN)."""
    return float(value) if np.isfinite(value) else None

"""The public registration pipeline: clouds in, rigid transform out.

    source, target (user units, anywhere)
      -> subsample to the working size (farthest-point or voxel), if larger
      -> PairNormalization: both clouds into network units (shared scale)
      -> compute_geometry on each cloud (NumPy)
      -> descriptor network on each cloud, matcher network on the pair (onnxruntime)
      -> log-Sinkhorn with the learned dustbin, mutual best matches
      -> candidate poses from the matches: FSR, RANSAC, SVD, top-k (network units), mapped
         back exactly to the user frame (plus the user's initial guess, if any)
      -> verification on the full clouds: the best few candidates get a short ICP, each is
         scored, the best kept; a calibrated confidence and the success flag
      -> optional ICP refinement on the full clouds; fitness / inlier RMSE on the full clouds

Every parameter of these stages is in one :class:`~logdesc_rt.config.RuntimeConfig`.

Every stage's wall time is reported in ``RegistrationResult.timings``.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .errors import RegistrationError
from .geometry import PointGeometry, compute_geometry
from .io import DEFAULT_WORKING_SIZE, input_points
from .matching import Matches, sinkhorn_matches
from .network import OnnxNetwork
from .normalization import PairNormalization
from .config import (
    CANDIDATE_ESTIMATORS,
    POSE_ESTIMATORS,
    REFINEMENT_METHODS,
    RefinementConfig,
    RuntimeConfig,
    SubsamplingConfig,
    VerificationConfig,
)
from .pose import evaluate_registration
from .pose.evaluation import check_rigid_transformation
from .refinement import IcpResult, icp
from .verification import PoseVerifier, VerificationResult, candidate_poses, estimate_pose
from .sampling import working_subset
from .validation import as_points, check_not_degenerate

MIN_MATCHES = 3  # a rigid transform needs three non-collinear pairs
ICP_METHODS = REFINEMENT_METHODS
# Default correspondence distance for fitness / ICP, as a fraction of the pair's scale (the
# larger cloud's radius): 5 %, i.e. 0.05 network units, ~3 noise sigmas of the training data.
# RefinementConfig holds it; named here for the benchmarks.
DEFAULT_DISTANCE_FRACTION = RefinementConfig.distance_fraction
_UNSET = object()  # "not given": refine=None means no refinement, so None cannot mean "unset"


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
            ``max_correspondence_distance`` after the transform (full clouds).
        inlier_rmse: RMS distance of those point pairs, user units; NaN when there are none
            (``None`` in :meth:`to_dict`).
        max_correspondence_distance: the distance used for fitness and ICP, user units.
        pose_estimator: the estimator whose pose was kept: "fsr", "ransac", "svd", "top_k",
            "core" (see :mod:`logdesc_rt.verification`), "init" (the caller's initial guess), or "none" (no pose could be estimated: the
            identity, see ``reason``).
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
            refinement (if any), evaluation, and total (their sum).
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


@dataclass(frozen=True)
class PreparedPair:
    """One pair made ready for the networks (:meth:`Registrar.prepare`): loaded, checked,
    subsampled to the working size, mapped into network units, with its geometry.

    Attributes:
        source_points, target_points: (N, 3) / (M, 3) float64 clouds as given (user frame).
        source_index, target_index: (Ns,) / (Mt,) int64, the working subsets' indices.
        normalization: maps the working subsets to network units and poses back.
        source_network, target_network: (Ns, 3) / (Mt, 3) float64 working subsets, network units.
        source_geometry, target_geometry: their kNN, PCA features, normals and (N, k, C) edges.
        timings: stage name -> seconds: load, subsample, geometry.
    """

    source_points: np.ndarray
    target_points: np.ndarray
    source_index: np.ndarray
    target_index: np.ndarray
    normalization: PairNormalization
    source_network: np.ndarray
    target_network: np.ndarray
    source_geometry: PointGeometry
    target_geometry: PointGeometry
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
            (before the matcher's transformer), unit norm.
        scores: (Ns, Mt) float32 matching scores <f_i, h_j> / sqrt(d) from the matcher network
            (Sinkhorn with the model's dustbin turns them into the matches).
        matches: mutual matches; indices into the working subsets.
        timings: stage name -> seconds: the preparation's (load, subsample, geometry), then
            descriptors (descriptor network, both clouds), matcher (transformer + scores),
            matching (Sinkhorn + mutual).
    """

    prepared: PreparedPair
    config: RuntimeConfig
    source_descriptors: np.ndarray
    target_descriptors: np.ndarray
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
                (see :mod:`logdesc_rt.verification`). "auto" needs :meth:`Registrar.register`.
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
        config = _seeded(self.config if config is None else config, seed)
        self._require_matches()
        network_pose = estimate_pose(
            estimator,
            self.source_network[self.matches.source_index],
            self.target_network[self.matches.target_index],
            self.matches.confidence,
            config.fsr,
            config.ransac,
            config.verification.top_k_fraction,
        )
        return self.normalization.pose_to_user_frame(network_pose)

    def candidates(self, config: RuntimeConfig | None = None) -> list[tuple[str, np.ndarray]]:
        """[(estimator, (4, 4) user-frame pose)] of every candidate estimator (unverified).

        Raises:
            RegistrationError: fewer than 3 mutual matches.
        """
        config = self.config if config is None else config
        self._require_matches()
        estimators = config.verification.candidates
        if config.estimator not in ("auto", *estimators):  # a user's choice outside the model's set
            estimators = (*estimators, config.estimator)
        poses = candidate_poses(
            self.source_network[self.matches.source_index],
            self.target_network[self.matches.target_index],
            self.matches.confidence,
            config.fsr,
            config.ransac,
            config.verification.top_k_fraction,
            estimators,
        )
        return [(name, self.normalization.pose_to_user_frame(pose)) for name, pose in poses]

    def _require_matches(self) -> None:
        if len(self.matches) < MIN_MATCHES:
            raise RegistrationError(
                f"the network found {len(self.matches)} mutual matches, a pose needs at least "
                f"{MIN_MATCHES}: the clouds may not overlap, or differ too much from the model's "
                "training data"
            )


class Registrar:
    """Loads the network once and registers any number of pairs.

    Args:
        model_dir: directory written by ``export/to_onnx.py``; None = the bundled model.
        threads: onnxruntime threads (None: all cores).
        max_points: working size per cloud; larger clouds are subsampled to it. None = the
            config's (default: the cloud size used in training, from the model manifest).
        subsampling: "fps" (farthest-point) or "voxel" (grid sized to keep roughly
            ``max_points``, then farthest-point to the exact count); None = the config's ("fps").
        config: every runtime stage's parameters. None: the model's defaults (its manifest's
            "runtime", e.g. its success-flag calibration); a dict: a partial
            :class:`~logdesc_rt.config.RuntimeConfig` dict over the model's defaults; a
            ``RuntimeConfig``: taken as it is, its None sections (matching, verification)
            the model's. ``max_points`` and ``subsampling`` override its subsampling.

    Attributes:
        config: the configuration in use, resolved (working size, the model's matching and
            verification filled in).
    """

    def __init__(
        self,
        model_dir: str | Path | None = None,
        threads: int | None = None,
        max_points: int | None = None,
        subsampling: str | None = None,
        config: RuntimeConfig | dict | None = None,
    ):
        self.network = OnnxNetwork(model_dir, threads=threads)
        self.manifest = self.network.manifest
        model_defaults = self.manifest.runtime_config()
        # The model's calibration (code defaults for a model without one), parsed once: every
        # resolved config with verification None takes it.
        self._model_verification = model_defaults.verification or VerificationConfig()
        self.config = self._resolved(model_defaults)  # the model's defaults first
        config = self._given_config(config)
        if max_points is not None or subsampling is not None:
            config = dataclasses.replace(
                config,
                subsampling=SubsamplingConfig(
                    max_points=config.subsampling.max_points if max_points is None else int(max_points),
                    method=config.subsampling.method if subsampling is None else subsampling,
                ),
            )
        self.config = self._resolved(config)
        self.max_points = self.config.subsampling.max_points
        self.subsampling = self.config.subsampling.method

    # -- public API -------------------------------------------------------------------------

    def register(
        self,
        source,
        target,
        *,
        estimator: str | None = None,
        refine=_UNSET,
        max_correspondence_distance: float | None = None,
        seed: int | None = None,
        init=None,
        config: RuntimeConfig | None = None,
        progress: Callable[[str], None] | None = None,
    ) -> RegistrationResult:
        """Estimate the rigid transform that maps ``source`` onto ``target``, and judge it.

        Args:
            source, target: (N, 3) / (M, 3) arrays, Open3D PointClouds (legacy or tensor), or
                point-cloud file paths (PLY, PCD, XYZ/TXT/CSV, NPY, OFF; LAS/LAZ, E57 with the
                extras), any unit, any placement; or meshes (a mesh file: OBJ, STL, GLB / glTF,
                a PLY / OFF with faces; a :class:`~logdesc_rt.io.Mesh` or ``trimesh.Trimesh``;
                the ``mesh`` extra), registered as seeded points on their surface
                (:mod:`logdesc_rt.io.mesh`; ``logdesc_rt.io.sample_surface`` picks the count).
            estimator: "auto" (default: every candidate estimator's pose is verified on the
                full clouds and the best kept), or "fsr" (the paper's), "svd"
                (confidence-weighted, all matches) or "ransac": that estimator's pose, still
                verified for the success flag.
            refine: None (default), "point_to_point" or "point_to_plane" ICP on the full clouds.
            max_correspondence_distance: for fitness, inlier RMSE and ICP, user units;
                default 5 % of the larger cloud's radius.
            seed: seeds every random choice (FSR, RANSAC, verification subsets); same input
                and seed, same output. Default: the config's (0).
            init: optional (4, 4) initial guess, source -> target (user frame). It joins the
                candidates and is verified like them; with "auto" it is kept if it scores best.
            config: this call's configuration (default: the Registrar's), as the
                Registrar's ``config`` argument takes it (a dict applies over the Registrar's);
                the keyword arguments above override it.
            progress: optional callable, called with a short message as each stage starts
                (the command line prints them on stderr).

        Returns:
            :class:`RegistrationResult`; check ``success`` (or ``confidence``) before using it.

        Raises:
            InvalidPointCloudError (and subclasses), PointCloudFileError: bad clouds.
            ValueError: bad options, or ``init`` not a rigid (4, 4) transform.

        A valid pair that cannot be registered (fewer than 3 mutual matches: no overlap, or far
        out of the training distribution; degenerate matches) is not an exception: the result
        has ``success=False``, confidence 0, the identity and a ``reason``.
        """
        config = self.call_config(
            config,
            estimator=estimator,
            refine=refine,
            max_correspondence_distance=max_correspondence_distance,
            seed=seed,
        )
        initial = None if init is None else check_rigid_transformation(init, name="init")
        report = progress if progress is not None else (lambda message: None)
        report("matching: geometry, networks and Sinkhorn on the working subsets")
        pair = self._with_config(config).match(source, target)
        return self._register_matched(pair, config, initial, report)

    def register_matches(
        self,
        pair: PairMatches,
        *,
        estimator: str | None = None,
        refine=_UNSET,
        max_correspondence_distance: float | None = None,
        seed: int | None = None,
        init=None,
        progress: Callable[[str], None] | None = None,
    ) -> RegistrationResult:
        """:meth:`register` from a pair already matched (:meth:`match`), without running the
        networks again: candidate poses, verification, the success flag, optional ICP.

        The keyword arguments are :meth:`register`'s and apply over the configuration the
        pair was matched with (``pair.config``). ``register(s, t, **kw)`` equals
        ``register_matches(match(s, t), **kw)``.
        """
        config = self.call_config(
            pair.config,
            estimator=estimator,
            refine=refine,
            max_correspondence_distance=max_correspondence_distance,
            seed=seed,
        )
        initial = None if init is None else check_rigid_transformation(init, name="init")
        return self._register_matched(pair, config, initial, progress or (lambda message: None))

    def _register_matched(
        self, pair: PairMatches, config: RuntimeConfig, initial: np.ndarray | None, report: Callable[[str], None]
    ) -> RegistrationResult:
        """Candidates from the matches (and ``initial``), verified; the best kept, refined."""
        timings = dict(pair.timings)
        with _timed(timings, "pose"):
            candidates = pair.candidates(config) if len(pair.matches) >= MIN_MATCHES else []
            if initial is not None:
                candidates.append(("init", initial))
        if len(pair.matches) < MIN_MATCHES and initial is None:
            return self._unregistered(
                pair, config, timings,
                f"too few matches: the network found {len(pair.matches)} mutual matches, a pose needs at least "
                f"{MIN_MATCHES} (the clouds may not overlap, or differ too much from the model's training data)",
            )
        if config.estimator != "auto" and config.estimator not in dict(candidates):
            return self._unregistered(
                pair, config, timings,
                f"no candidate pose: estimator {config.estimator!r} found none (its matches are degenerate: all on one line)",
            )
        if not candidates:
            return self._unregistered(pair, config, timings, "no candidate pose: the matches are degenerate (all on one line)")

        scale = pair.normalization.scale
        refinement = config.refinement
        distance = refinement.max_correspondence_distance or refinement.distance_fraction * scale
        report(
            f"verifying {len(candidates)} candidate poses on the full clouds "
            f"({len(pair.source_points)} x {len(pair.target_points)} points)"
        )
        with _timed(timings, "verification"):
            correspondences = pair.correspondences
            verifier = PoseVerifier(
                pair.source_points,
                pair.target_points,
                pair.source_points[correspondences[:, 0]],
                pair.target_points[correspondences[:, 1]],
                pair.matches.confidence,
                scale,
                config.verification,
            )
            verification = verifier.verify(candidates)
        if config.estimator == "auto":
            chosen = verification.best
            chosen_estimator = chosen.estimators[0]
        else:
            chosen = next(h for h in verification.hypotheses if config.estimator in h.estimators)
            chosen_estimator = config.estimator
        pose = dict(candidates)[chosen_estimator]

        refined, icp_result = pose, None
        if refinement.method is not None:
            report(f"refining: {refinement.method} ICP on the full clouds")
            with _timed(timings, "refinement"):
                icp_result = icp(
                    pair.source_points,
                    pair.target_points,
                    chosen.verified_transformation,
                    distance,
                    method=refinement.method,
                    max_iterations=refinement.max_iterations,
                    tolerance=refinement.tolerance,
                    adaptive=refinement.adaptive,
                )
            refined = icp_result.transformation
            with _timed(timings, "verification"):
                confidence = verifier.confidence_at(refined, chosen)
        else:
            # The returned pose is the estimator's own: right only if it is close to the
            # alignment verification found from it.
            confidence = chosen.confidence if verifier.pose_within_verified(pose, chosen) else 0.0
        with _timed(timings, "evaluation"):
            evaluation = evaluate_registration(pair.source_points, pair.target_points, distance, refined)
        timings["total"] = sum(timings.values())
        success = bool(confidence >= config.verification.success_threshold)

        return RegistrationResult(
            transformation=refined,
            correspondences=correspondences,
            confidences=pair.matches.confidence,
            fitness=evaluation.fitness,
            inlier_rmse=evaluation.inlier_rmse,
            max_correspondence_distance=distance,
            pose_estimator=chosen_estimator,
            refinement=refinement.method,
            transformation_before_refinement=pose,
            subsampled=pair.subsampled,
            source_points_used=len(pair.source_index),
            target_points_used=len(pair.target_index),
            timings=timings,
            icp=icp_result,
            success=success,
            confidence=float(confidence),
            verification=verification,
            config=config,
            reason=None if success else (
                f"not verified: confidence {confidence:.3f} is below the success threshold "
                f"{config.verification.success_threshold:.3f}"
            ),
        )

    def _unregistered(
        self, pair: PairMatches, config: RuntimeConfig, timings: dict[str, float], reason: str
    ) -> RegistrationResult:
        """The result of a valid pair no pose could be estimated for: the identity, judged a failure."""
        refinement = config.refinement
        distance = refinement.max_correspondence_distance or refinement.distance_fraction * pair.normalization.scale
        identity = np.eye(4)
        with _timed(timings, "evaluation"):
            evaluation = evaluate_registration(pair.source_points, pair.target_points, distance, identity)
        timings["total"] = sum(timings.values())
        return RegistrationResult(
            transformation=identity,
            correspondences=pair.correspondences,
            confidences=pair.matches.confidence,
            fitness=evaluation.fitness,
            inlier_rmse=evaluation.inlier_rmse,
            max_correspondence_distance=distance,
            pose_estimator="none",
            refinement=None,
            transformation_before_refinement=identity,
            subsampled=pair.subsampled,
            source_points_used=len(pair.source_index),
            target_points_used=len(pair.target_index),
            timings=timings,
            success=False,
            confidence=0.0,
            config=config,
            reason=reason,
        )

    def call_config(
        self,
        config: RuntimeConfig | dict | None = None,
        *,
        estimator: str | None = None,
        refine=_UNSET,
        max_correspondence_distance: float | None = None,
        seed: int | None = None,
    ) -> RuntimeConfig:
        """The configuration one :meth:`register` call runs with: ``config`` (default: the
        Registrar's; a dict applies over it) with the keyword overrides applied, resolved.

        Raises:
            ValueError: an invalid override (unknown estimator or refinement, distance <= 0).
        """
        config = self._resolved(self._given_config(config))
        if estimator is not None:
            if estimator not in POSE_ESTIMATORS:
                raise ValueError(f"estimator {estimator!r}: expected one of {POSE_ESTIMATORS}")
            config = dataclasses.replace(config, estimator=estimator)
        refinement = config.refinement
        if refine is not _UNSET:
            if refine is not None and refine not in REFINEMENT_METHODS:
                raise ValueError(f"refine {refine!r}: expected None or one of {REFINEMENT_METHODS}")
            refinement = dataclasses.replace(refinement, method=refine)
        if max_correspondence_distance is not None:
            distance = float(max_correspondence_distance)
            if not 0.0 < distance < float("inf"):
                raise ValueError(f"max_correspondence_distance: {distance} must be > 0")
            refinement = dataclasses.replace(refinement, max_correspondence_distance=distance)
        return _seeded(dataclasses.replace(config, refinement=refinement), seed)

    def match(self, source, target) -> PairMatches:
        """The learned pipeline up to the matches: what :meth:`register` builds its pose from.

        Useful to try several pose estimators on one pair, or to feed the descriptors to
        another estimator (``benchmarks/`` does both). Takes the same clouds as
        :meth:`register`; never raises for too few matches (check ``len(result.matches)``).
        """
        prepared = self.prepare(source, target)
        timings = dict(prepared.timings)
        network_source, network_target = prepared.source_network, prepared.target_network
        with _timed(timings, "descriptors"):
            source_descriptors = self.network.describe(
                prepared.source_geometry.edges, network_source, prepared.source_geometry.normals
            )
            target_descriptors = self.network.describe(
                prepared.target_geometry.edges, network_target, prepared.target_geometry.normals
            )
        with _timed(timings, "matcher"):
            scores = self.network.match_scores(
                source_descriptors,
                target_descriptors,
                prepared.source_geometry.normals,
                prepared.target_geometry.normals,
                network_source,
                network_target,
            )
        with _timed(timings, "matching"):
            matches = sinkhorn_matches(
                scores,
                self.manifest.dustbin_score,
                self.config.matching.sinkhorn_iterations,
                self.config.matching.match_threshold,
                self.config.matching.dustbin_in_mutual_test,
            )
        return PairMatches(
            prepared=prepared,
            config=self.config,
            source_descriptors=source_descriptors,
            target_descriptors=target_descriptors,
            scores=scores,
            matches=matches,
            timings=timings,
        )

    def prepare(self, source, target) -> PreparedPair:
        """Everything before the networks: load and check both clouds, subsample each to the
        working size, map both into network units (one shared scale), compute the geometry.

        :meth:`match` starts from this; ``benchmarks/latency.py`` feeds its output to torch and
        onnxruntime alike. Takes the same clouds as :meth:`register`.
        """
        timings: dict[str, float] = {}
        with _timed(timings, "load"):
            source_points = self._load(source, "source")
            target_points = self._load(target, "target")
        with _timed(timings, "subsample"):
            source_index = self._working_subset(source_points)
            target_index = self._working_subset(target_points)
        normalization = PairNormalization.fit(
            source_points[source_index], target_points[target_index], self.manifest.normalization
        )
        network_source = normalization.source_to_network(source_points[source_index])
        network_target = normalization.target_to_network(target_points[target_index])
        with _timed(timings, "geometry"):
            # The two clouds concurrently: kNN, eigen-solver and matrix products release the GIL.
            with ThreadPoolExecutor(max_workers=2) as pool:
                source_job = pool.submit(compute_geometry, network_source, self.manifest.geometry)
                target_geometry = compute_geometry(network_target, self.manifest.geometry)
                source_geometry = source_job.result()
        return PreparedPair(
            source_points=source_points,
            target_points=target_points,
            source_index=source_index,
            target_index=target_index,
            normalization=normalization,
            source_network=network_source,
            target_network=network_target,
            source_geometry=source_geometry,
            target_geometry=target_geometry,
            timings=timings,
        )

    def describe(self, points) -> Descriptors:
        """Learned descriptors of one cloud (subsampled to the working size if larger).

        The cloud is normalised alone (centred, its radius scaled to the network's), so the
        descriptors of two clouds are comparable when the clouds have similar extents.
        """
        cloud = self._load(points, "points")
        index = self._working_subset(cloud)
        normalization = PairNormalization.fit(cloud[index], cloud[index], self.manifest.normalization)
        network_points = normalization.source_to_network(cloud[index])
        geometry = compute_geometry(network_points, self.manifest.geometry)
        descriptors = self.network.describe(geometry.edges, network_points, geometry.normals)
        return Descriptors(indices=index, descriptors=descriptors, normals=geometry.normals)

    # -- helpers ----------------------------------------------------------------------------

    def _given_config(self, config: RuntimeConfig | dict | None) -> RuntimeConfig:
        """A user's ``config`` argument as a RuntimeConfig: None is this Registrar's, a dict
        applies over it, a RuntimeConfig is taken as it is."""
        if config is None:
            return self.config
        if isinstance(config, dict):
            return RuntimeConfig.from_dict(config, base=self.config)
        if not isinstance(config, RuntimeConfig):
            raise TypeError(f"config: expected a RuntimeConfig or a dict, got {type(config).__name__}")
        return config

    def _resolved(self, config: RuntimeConfig) -> RuntimeConfig:
        """``config`` with the model's values filled in (working size, matching,
        verification), checked."""
        max_points = config.subsampling.max_points or self.manifest.points_per_cloud
        min_points = self.manifest.geometry.min_points
        if max_points < min_points:
            raise ValueError(f"max_points {max_points} < {min_points}, the geometry's minimum")
        return dataclasses.replace(
            config,
            subsampling=dataclasses.replace(config.subsampling, max_points=int(max_points)),
            matching=self.manifest.matching if config.matching is None else config.matching,
            verification=self._model_verification if config.verification is None else config.verification,
        )

    def _with_config(self, config: RuntimeConfig) -> "Registrar":
        """This Registrar, or a shallow copy sharing its network when ``config`` changes the
        subsampling or the matching (the stages before the pose read them from ``self``)."""
        if config.subsampling == self.config.subsampling and config.matching == self.config.matching:
            return self
        other = copy.copy(self)
        other.config = config
        other.max_points = config.subsampling.max_points
        other.subsampling = config.subsampling.method
        return other

    def _load(self, cloud, name: str) -> np.ndarray:
        # Files, meshes and Open3D clouds become (N, 3) points; arrays pass as they are.
        cloud = input_points(cloud, working_size=self.max_points)
        points = as_points(cloud, name=name, min_points=self.manifest.geometry.min_points)
        check_not_degenerate(points, name=name)
        return points

    def _working_subset(self, points: np.ndarray) -> np.ndarray:
        """(K,) int64 indices of the points the network sees, K <= min(N, max_points)."""
        return working_subset(
            points,
            self.max_points,
            self.subsampling,
            self.manifest.normalization,
            min_points=self.manifest.geometry.min_points,
        )


def _seeded(config: RuntimeConfig, seed: int | None) -> RuntimeConfig:
    """``config`` with every random choice seeded by ``seed`` (unchanged for None)."""
    if seed is None:
        return config
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: {seed!r} must be an integer >= 0")
    return config.with_seed(int(seed))


def _finite_or_none(value: float) -> float | None:
    """``value``, or None for NaN / inf (JSON has no NaN)."""
    return float(value) if np.isfinite(value) else None


@contextmanager
def _timed(timings: dict[str, float], stage: str) -> Iterator[None]:
    start = time.perf_counter()
    try:
        yield
    finally:
        timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - start


_DEFAULT_REGISTRAR: Registrar | None = None


def _default_registrar() -> Registrar:
    global _DEFAULT_REGISTRAR
    if _DEFAULT_REGISTRAR is None:
        _DEFAULT_REGISTRAR = Registrar()
    return _DEFAULT_REGISTRAR


def register(source, target, **options) -> RegistrationResult:
    """Register two clouds with the bundled model (loaded once, reused).

    ``options`` are those of :meth:`Registrar.register` (estimator, refine,
    max_correspondence_distance, seed, init, config, progress); ``config`` may set every
    runtime stage, the working size and matching included. For another model or thread count,
    build a :class:`Registrar`. Check ``result.success`` before using the pose.
    """
    return _default_registrar().register(source, target, **options)


def describe(points) -> Descriptors:
    """Per-point learned descriptors of one cloud with the bundled model."""
    return _default_registrar().describe(points)

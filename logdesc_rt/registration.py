"""The public registration pipeline: clouds in, rigid transform out.

    source, target (user units, anywhere)
      -> subsample to the working size (farthest-point or voxel), if larger
      -> PairNormalization: both clouds into network units (shared scale)
      -> compute_geometry on each cloud (NumPy)
      -> descriptor network on each cloud, matcher network on the pair (onnxruntime)
      -> log-Sinkhorn with the learned dustbin, mutual best matches
      -> pose from the matches: FSR (default), SVD or RANSAC (network units)
      -> pose mapped back exactly to the user frame
      -> optional ICP refinement on the full clouds; fitness / inlier RMSE on the full clouds

Every stage's wall time is reported in ``RegistrationResult.timings``.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import RegistrationError
from .geometry import PointGeometry, compute_geometry
from .io import read_point_cloud
from .matching import Matches, log_optimal_transport, mutual_matches
from .network import OnnxNetwork
from .normalization import PairNormalization
from .pose import FsrConfig, RansacConfig, evaluate_registration, fsr, ransac, rigid_transform_svd
from .refinement import ICP_METHODS, IcpResult, icp
from .sampling import farthest_point_sampling, voxel_downsample
from .validation import as_points, check_not_degenerate

POSE_ESTIMATORS = ("fsr", "svd", "ransac")
MIN_MATCHES = 3  # a rigid transform needs three non-collinear pairs
SUBSAMPLING_METHODS = ("fps", "voxel")
# Default correspondence distance for fitness / ICP, as a fraction of the pair's scale (the
# larger cloud's radius): 5 %, i.e. 0.05 network units, ~3 noise sigmas of the training data.
DEFAULT_DISTANCE_FRACTION = 0.05


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of :func:`register`, in Open3D's vocabulary where it fits.

    Attributes:
        transformation: (4, 4) float64, maps source points into the target frame.
        correspondences: (K, 2) int64 rows [source_index, target_index], indices into the
            clouds as given (before any subsampling): the network's mutual matches.
        confidences: (K,) float64 match probabilities from Sinkhorn, in (0, 1].
        fitness: share of source points with a target point within
            ``max_correspondence_distance`` after the transform (full clouds).
        inlier_rmse: RMS distance of those point pairs, user units; NaN when there are none
            (``None`` in :meth:`to_dict`).
        max_correspondence_distance: the distance used for fitness and ICP, user units.
        pose_estimator: "fsr", "svd" or "ransac".
        refinement: None, "point_to_point" or "point_to_plane".
        transformation_before_refinement: (4, 4), the learned pipeline's pose before ICP.
        icp: how ICP ended (iterations, converged, stop reason, its fitness / RMSE), or None
            without refinement.
        subsampled: True if either cloud was larger than the working size.
        source_points_used, target_points_used: points the network saw per cloud.
        timings: stage name -> seconds: those of :class:`PairMatches`, then pose,
            refinement (if any), evaluation, and total (their sum).
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

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rotation block of the transformation."""
        return self.transformation[:3, :3].copy()

    @property
    def translation(self) -> np.ndarray:
        """(3,) translation, user units."""
        return self.transformation[:3, 3].copy()

    def to_dict(self) -> dict:
        """JSON-friendly summary (nested lists), as printed by ``logdesc-rt register --json``."""
        return {
            "transformation": self.transformation.tolist(),
            "fitness": self.fitness,
            "inlier_rmse": _finite_or_none(self.inlier_rmse),
            "max_correspondence_distance": self.max_correspondence_distance,
            "correspondence_count": int(len(self.correspondences)),
            "correspondences": self.correspondences.tolist(),
            "confidences": self.confidences.tolist(),
            "pose_estimator": self.pose_estimator,
            "refinement": self.refinement,
            "icp": None if self.icp is None else self.icp.to_dict(),
            "transformation_before_refinement": self.transformation_before_refinement.tolist(),
            "subsampled": self.subsampled,
            "source_points_used": self.source_points_used,
            "target_points_used": self.target_points_used,
            "timings_s": self.timings,
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
        source_geometry, target_geometry: their kNN, PCA features, normals and (N, k, 15) edges.
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
        source_points, target_points: (N, 3) / (M, 3) float64 clouds as given (user frame).
        source_index, target_index: (Ns,) / (Mt,) int64, the points the network saw (all of
            them unless subsampled to the working size).
        normalization: maps the working subsets to network units and poses back.
        source_network, target_network: (Ns, 3) / (Mt, 3) float64 working subsets, network units.
        source_descriptors, target_descriptors: (Ns, d) / (Mt, d) float32 learned descriptors
            (before the matcher's transformer), unit norm.
        log_assignment: (Ns+1, Mt+1) float64 log-Sinkhorn output, dustbin last.
        matches: mutual matches; indices into the working subsets.
        timings: stage name -> seconds: load, subsample, geometry, descriptors (descriptor
            network, both clouds), matcher (transformer + scores), matching (Sinkhorn + mutual).
    """

    source_points: np.ndarray
    target_points: np.ndarray
    source_index: np.ndarray
    target_index: np.ndarray
    normalization: PairNormalization
    source_network: np.ndarray
    target_network: np.ndarray
    source_descriptors: np.ndarray
    target_descriptors: np.ndarray
    log_assignment: np.ndarray
    matches: Matches
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def correspondences(self) -> np.ndarray:
        """(K, 2) int64 rows [source_index, target_index] into the clouds as given."""
        return np.stack(
            [self.source_index[self.matches.source_index], self.target_index[self.matches.target_index]],
            axis=1,
        ).astype(np.int64)

    @property
    def subsampled(self) -> bool:
        """True if either cloud was larger than the working size."""
        return len(self.source_index) < len(self.source_points) or len(self.target_index) < len(
            self.target_points
        )

    def pose(self, estimator: str = "fsr", seed: int = 0) -> np.ndarray:
        """(4, 4) user-frame pose source -> target from the matches.

        Args:
            estimator: "fsr", "svd" (confidence-weighted) or "ransac".
            seed: seeds FSR / RANSAC sampling.

        Raises:
            RegistrationError: fewer than 3 mutual matches.
        """
        if estimator not in POSE_ESTIMATORS:
            raise ValueError(f"estimator {estimator!r}: expected one of {POSE_ESTIMATORS}")
        if len(self.matches) < MIN_MATCHES:
            raise RegistrationError(
                f"the network found {len(self.matches)} mutual matches, a pose needs at least "
                f"{MIN_MATCHES}: the clouds may not overlap, or differ too much from the model's "
                "training data"
            )
        network_pose = _estimate_pose(
            self.source_network[self.matches.source_index],
            self.target_network[self.matches.target_index],
            self.matches.confidence,
            estimator,
            seed,
        )
        return self.normalization.pose_to_user_frame(network_pose)


class Registrar:
    """Loads the network once and registers any number of pairs.

    Args:
        model_dir: directory written by ``export/to_onnx.py``; None = the bundled model.
        threads: onnxruntime threads (None: all cores).
        max_points: working size per cloud; larger clouds are subsampled to it. None = the
            cloud size used in training (from the model manifest).
        subsampling: "fps" (farthest-point, default) or "voxel" (grid sized to keep roughly
            ``max_points``, then farthest-point to the exact count).
    """

    def __init__(
        self,
        model_dir: str | Path | None = None,
        threads: int | None = None,
        max_points: int | None = None,
        subsampling: str = "fps",
    ):
        if subsampling not in SUBSAMPLING_METHODS:
            raise ValueError(f"subsampling {subsampling!r}: expected one of {SUBSAMPLING_METHODS}")
        self.network = OnnxNetwork(model_dir, threads=threads)
        self.manifest = self.network.manifest
        self.max_points = int(max_points or self.manifest.points_per_cloud)
        min_points = self.manifest.geometry.min_points
        if self.max_points < min_points:
            raise ValueError(f"max_points {self.max_points} < {min_points}, the geometry's minimum")
        self.subsampling = subsampling

    # -- public API -------------------------------------------------------------------------

    def register(
        self,
        source,
        target,
        *,
        estimator: str = "fsr",
        refine: str | None = None,
        max_correspondence_distance: float | None = None,
        seed: int = 0,
    ) -> RegistrationResult:
        """Estimate the rigid transform that maps ``source`` onto ``target``.

        Args:
            source, target: (N, 3) / (M, 3) arrays or point-cloud file paths (PLY, PCD,
                XYZ/TXT/CSV, NPY, OFF), any unit, any placement.
            estimator: "fsr" (the paper's), "svd" (confidence-weighted, all matches) or "ransac".
            refine: None, "point_to_point" or "point_to_plane" ICP on the full clouds.
            max_correspondence_distance: for fitness, inlier RMSE and ICP, user units;
                default 5 % of the larger cloud's radius.
            seed: seeds FSR / RANSAC sampling (same input and seed, same output).

        Raises:
            InvalidPointCloudError (and subclasses), PointCloudFileError: bad clouds.
            RegistrationError: fewer than 3 mutual matches (no overlap, or far out of the
                training distribution).
        """
        if estimator not in POSE_ESTIMATORS:
            raise ValueError(f"estimator {estimator!r}: expected one of {POSE_ESTIMATORS}")
        if refine is not None and refine not in ICP_METHODS:
            raise ValueError(f"refine {refine!r}: expected None or one of {ICP_METHODS}")
        pair = self.match(source, target)
        timings = dict(pair.timings)
        with _timed(timings, "pose"):
            pose = pair.pose(estimator, seed)

        distance = (
            float(max_correspondence_distance)
            if max_correspondence_distance is not None
            else DEFAULT_DISTANCE_FRACTION * pair.normalization.scale
        )
        if not distance > 0:
            raise ValueError(f"max_correspondence_distance: {distance} must be > 0")
        refined, icp_result = pose, None
        if refine is not None:
            with _timed(timings, "refinement"):
                icp_result = icp(pair.source_points, pair.target_points, pose, distance, method=refine)
            refined = icp_result.transformation
        with _timed(timings, "evaluation"):
            evaluation = evaluate_registration(pair.source_points, pair.target_points, distance, refined)
        timings["total"] = sum(timings.values())

        return RegistrationResult(
            transformation=refined,
            correspondences=pair.correspondences,
            confidences=pair.matches.confidence,
            fitness=evaluation.fitness,
            inlier_rmse=evaluation.inlier_rmse,
            max_correspondence_distance=distance,
            pose_estimator=estimator,
            refinement=refine,
            transformation_before_refinement=pose,
            subsampled=pair.subsampled,
            source_points_used=len(pair.source_index),
            target_points_used=len(pair.target_index),
            timings=timings,
            icp=icp_result,
        )

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
            source_descriptors = self.network.describe(prepared.source_geometry.edges, network_source)
            target_descriptors = self.network.describe(prepared.target_geometry.edges, network_target)
        with _timed(timings, "matcher"):
            scores = self.network.match_scores(
                source_descriptors,
                target_descriptors,
                prepared.source_geometry.normals,
                prepared.target_geometry.normals,
            )
        with _timed(timings, "matching"):
            log_assignment = log_optimal_transport(
                scores, self.manifest.dustbin_score, self.manifest.matching.sinkhorn_iterations
            )
            matches = mutual_matches(log_assignment, self.manifest.matching.match_threshold)
        return PairMatches(
            source_points=prepared.source_points,
            target_points=prepared.target_points,
            source_index=prepared.source_index,
            target_index=prepared.target_index,
            normalization=prepared.normalization,
            source_network=network_source,
            target_network=network_target,
            source_descriptors=source_descriptors,
            target_descriptors=target_descriptors,
            log_assignment=log_assignment,
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
            source_geometry = compute_geometry(network_source, self.manifest.geometry)
            target_geometry = compute_geometry(network_target, self.manifest.geometry)
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
        descriptors = self.network.describe(geometry.edges, network_points)
        return Descriptors(indices=index, descriptors=descriptors, normals=geometry.normals)

    # -- helpers ----------------------------------------------------------------------------

    def _load(self, cloud, name: str) -> np.ndarray:
        if isinstance(cloud, (str, Path)):
            cloud = read_point_cloud(cloud)
        points = as_points(cloud, name=name, min_points=self.manifest.geometry.min_points)
        check_not_degenerate(points, name=name)
        return points

    def _working_subset(self, points: np.ndarray) -> np.ndarray:
        """(K,) int64 indices of the points the network sees, K = min(N, max_points)."""
        if len(points) <= self.max_points:
            return np.arange(len(points))
        if self.subsampling == "voxel":
            # A scan is a surface: with its two largest extents a x b, cells of side
            # sqrt(a b / (2 max_points)) leave about 2 * max_points occupied, then FPS trims.
            largest_two = np.sort(np.ptp(points, axis=0))[1:]
            voxel = float(np.sqrt(np.prod(largest_two) / (2 * self.max_points)))
            kept = voxel_downsample(points, max(voxel, 1e-12))
            if len(kept) > self.max_points:
                kept = kept[np.sort(farthest_point_sampling(points[kept], self.max_points))]
            return kept
        return np.sort(farthest_point_sampling(points, self.max_points))


def _estimate_pose(
    source: np.ndarray, target: np.ndarray, confidence: np.ndarray, estimator: str, seed: int
) -> np.ndarray:
    """(4, 4) network-frame pose from matched points (network units).

    FSR's and RANSAC's default inlier thresholds (0.08) are in network units already.
    """
    if estimator == "svd":
        return rigid_transform_svd(source, target, confidence)
    if estimator == "ransac":
        return ransac(source, target, RansacConfig(seed=seed)).transformation
    return fsr(source, target, confidence, FsrConfig(seed=seed)).transformation


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
    max_correspondence_distance, seed). For another model, threads or working size, build a
    :class:`Registrar`.
    """
    return _default_registrar().register(source, target, **options)


def describe(points) -> Descriptors:
    """Per-point learned descriptors of one cloud with the bundled model."""
    return _default_registrar().describe(points)

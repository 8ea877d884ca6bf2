"""The registration methods the benchmarks compare, behind one interface.

Each method takes a pair of user-frame clouds and returns a :class:`MethodResult` (a pose and
its wall time). The methods that share work run together on a pair, so that, e.g., the three
pose estimators on logdesc-rt's matches see the same matches:

- ``logdesc_fsr``, ``logdesc_svd``, ``logdesc_ransac``: the shipped pipeline
  (:meth:`logdesc_rt.Registrar.match`), then FSR (the default), confidence-weighted SVD or our
  RANSAC on its mutual matches;
- ``logdesc_auto``, ``logdesc_auto_icp``: what ``register()`` returns by default, from the
  same matches (:meth:`logdesc_rt.Registrar.register_matches`): the fast exit, or every
  candidate pose verified on the full clouds, the best kept, and the success flag; without and
  with point-to-plane ICP; ``logdesc_thorough``: ``register(..., thorough=True)``, every
  candidate verified on every pair; ``logdesc_second_draw``: ``register()`` with the second
  draw (``SubsamplingConfig.second_draw``); ``logdesc_refit_only``: ``register()`` without the
  verified-pose fallback (``VerificationConfig.verified_fallback_rmse = 0``). Their records carry the flag
  (``flagged_success``, ``confidence``);
- ``logdesc_desc_ransac``, ``logdesc_desc_fgr``: only the learned *descriptors* (no matcher
  transformer, no Sinkhorn), fed to Open3D's feature-matching RANSAC and FGR, as the paper's
  MVP-RG table does;
- ``fpfh_ransac``, ``fpfh_fgr``: Open3D FPFH with the same two Open3D estimators;
- ``kiss_matcher``: KISS-Matcher (pip ``kiss-matcher``, MIT; voxel thinning, its faster FPFH,
  max-k-core pruning, a GNC-TLS solve) with its voxel size set to the tuned Open3D voxel, in the
  network frame like FPFH;
- ``icp_point_to_plane``: Open3D point-to-plane ICP from the identity (user frame);
- ``logdesc_fsr_icp``, ``fpfh_fgr_icp``, ``fpfh_ransac_icp``: learned and classical coarse poses,
  each refined by the *same* ICP (``register(..., refine="point_to_plane")``'s: the package's
  point-to-plane ICP with its adaptive stages and source subset, correspondences within 5 % of
  the radius), so the pair differs only in where ICP starts.

Frames and units. Every descriptor-based method works in the runtime's network frame
(:class:`logdesc_rt.normalization.PairNormalization`: each cloud centred, one shared scale that
puts the larger radius at 1), and its pose is mapped back to the user frame exactly. So the
Open3D parameters below are fractions of the object's radius, which transfers them from
ModelNet (unit sphere) to the Bunny scans (metres) unchanged. ICP alone runs in the user frame
from the identity, as a user would run it; its distance threshold is a fraction of the pair's
radius too.

Open3D parameters (``FpfhParameters``) were chosen on *validation* pairs (held-out training
shapes, never the test split) by ``benchmarks/tune_open3d.py``; the chosen values and the
sweep are in ``benchmarks/results/open3d_tuning.md``; the range-scan benchmarks use the same sweep
run on simulated scan pairs of validation shapes (``SCAN_TUNING_FILE``).

Timing: ``seconds`` is the method's own wall time on the pair, network included; the logdesc
estimators each report the shared matching time plus their own pose time, and the
descriptor-only methods the geometry + descriptor network time plus the Open3D estimator.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import asdict, dataclass
from hashlib import sha256
from pathlib import Path

import numpy as np

from logdesc_rt import Registrar
from logdesc_rt.config import RefinementConfig
from logdesc_rt.errors import InvalidPointCloudError, RegistrationError
from logdesc_rt.matching import correspondences_as_array
from logdesc_rt.normalization import PairNormalization
from logdesc_rt.refinement import refine_pose as runtime_refine_pose

LOGDESC_ESTIMATORS = ("fsr", "svd", "ransac")
LOGDESC_METHODS = tuple(f"logdesc_{name}" for name in LOGDESC_ESTIMATORS)
# method -> register()'s (refine, thorough, settings applied over the configuration's)
VERIFIED_METHODS = {
    "logdesc_auto": (None, False, {}),
    "logdesc_auto_icp": ("point_to_plane", False, {}),
    "logdesc_thorough": (None, True, {}),
    "logdesc_second_draw": (None, False, {"subsampling": {"second_draw": True}}),
    "logdesc_refit_only": (None, False, {"verification": {"verified_fallback_rmse": 0.0}}),
}
DESCRIPTOR_METHODS = ("logdesc_desc_ransac", "logdesc_desc_fgr")
FPFH_METHODS = ("fpfh_ransac", "fpfh_fgr")
KISS_METHODS = ("kiss_matcher",)
ICP_METHODS = ("icp_point_to_plane",)
# Refined method -> the coarse method whose pose ICP starts from.
REFINED_FROM = {"logdesc_fsr_icp": "logdesc_fsr", "fpfh_fgr_icp": "fpfh_fgr", "fpfh_ransac_icp": "fpfh_ransac"}
REFINED_METHODS = tuple(REFINED_FROM)
ALL_METHODS = (
    LOGDESC_METHODS + tuple(VERIFIED_METHODS) + DESCRIPTOR_METHODS + FPFH_METHODS + KISS_METHODS + ICP_METHODS
    + REFINED_METHODS
)
OPEN3D_METHODS = DESCRIPTOR_METHODS + FPFH_METHODS + ICP_METHODS + ("fpfh_fgr_icp", "fpfh_ransac_icp")

TUNING_FILE = Path(__file__).resolve().parent / "results" / "open3d_tuning.json"
# The same sweep on raw simulated range-scan pairs of validation shapes (``tune_open3d.py
# --protocols scan``): what the range-scan benchmarks (simulated and real) give Open3D.
SCAN_TUNING_FILE = Path(__file__).resolve().parent / "results" / "open3d_tuning_scans" / "open3d_tuning.json"


@dataclass(frozen=True)
class FpfhParameters:
    """Open3D feature / estimator parameters, in network units (the larger cloud's radius = 1).

    Open3D's tutorial ties everything to one voxel size v: normals within 2 v, FPFH within 5 v,
    RANSAC inliers within 1.5 v, FGR's correspondence distance 0.5 v. We keep those ratios and
    tune only ``voxel`` (no downsampling: every method sees the same points).

    Attributes:
        voxel: v, network units.
        ransac_iterations, ransac_confidence: Open3D's RANSACConvergenceCriteria (its
            tutorial's 100000 / 0.999).
        icp_distance: ICP correspondence distance, network units (scaled back to user units).
    """

    voxel: float = 0.05
    ransac_iterations: int = 100_000
    ransac_confidence: float = 0.999
    icp_distance: float = 0.1

    @property
    def normal_radius(self) -> float:
        return 2.0 * self.voxel

    @property
    def feature_radius(self) -> float:
        return 5.0 * self.voxel

    @property
    def ransac_distance(self) -> float:
        return 1.5 * self.voxel

    @property
    def fgr_distance(self) -> float:
        return 0.5 * self.voxel

    def fingerprint(self) -> str:
        """A short digest of these parameters: result caches stamp the classical methods'
        records with it, so that records computed with other parameters are re-run."""
        return sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:12]

    @classmethod
    def tuned(cls, tuning_file: Path = TUNING_FILE) -> FpfhParameters:
        """The parameters ``tune_open3d.py`` chose on validation pairs (defaults if absent).

        ``tuning_file``: another sweep's ``open3d_tuning.json`` (e.g. one run on the resampled
        protocols, whose sparser clouds want larger radii).
        """
        if Path(tuning_file).exists():
            chosen = json.loads(Path(tuning_file).read_text())["chosen"]
            return cls(**chosen)
        return cls()


@dataclass
class MethodResult:
    """One method on one pair.

    Attributes:
        transformation: (4, 4) float64 predicted pose source -> target, user frame; the
            identity when the method failed.
        seconds: wall time of the method on this pair.
        failed: True when the method produced no pose (too few matches, Open3D error).
        pred_match: (N,) int64 predicted target index per source point (-1 unmatched), for
            methods whose matches are meaningful (logdesc's Sinkhorn matches, mutual
            nearest neighbours in descriptor space); None otherwise.
        flagged_success, confidence: the runtime's success flag and confidence (the
            verified methods); None for the others.
        fast_exit: whether the runtime took the fast exit (the verified methods); None for
            the others.
    """

    transformation: np.ndarray
    seconds: float
    failed: bool = False
    pred_match: np.ndarray | None = None
    flagged_success: bool | None = None
    confidence: float | None = None
    fast_exit: bool | None = None


def failed_result(seconds: float) -> MethodResult:
    return MethodResult(np.eye(4), seconds, failed=True)


# ----------------------------------------------------------------------------- Open3D helpers
def _open3d():
    """Import Open3D lazily: it is a benchmark-only dependency (``pip install open3d``)."""
    import open3d

    open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)
    return open3d


def open3d_available() -> bool:
    try:
        _open3d()
    except ImportError:
        return False
    return True


def runnable_methods(methods: list[str]) -> list[str]:
    """``methods`` less those that need Open3D when it is not installed (said on stderr, so
    that a report written without the baselines' rows does not go unnoticed)."""
    if open3d_available():
        return list(methods)
    skipped = [m for m in methods if m in OPEN3D_METHODS]
    print(f"open3d is not installed (pip install open3d): skipping {skipped}", file=sys.stderr)
    return [m for m in methods if m not in OPEN3D_METHODS]


def _cloud(points: np.ndarray, normal_radius: float | None = None):
    o3d = _open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normal_radius is not None:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
    return cloud


def _feature(descriptors: np.ndarray):
    """An Open3D Feature from (N, d) descriptors (Open3D stores them d x N)."""
    feature = _open3d().pipelines.registration.Feature()
    feature.data = np.ascontiguousarray(np.asarray(descriptors, dtype=np.float64).T)
    return feature


def fpfh_descriptors(cloud, parameters: FpfhParameters) -> np.ndarray:
    """(N, 33) FPFH of an Open3D cloud that has normals."""
    o3d = _open3d()
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=parameters.feature_radius, max_nn=100)
    return np.asarray(o3d.pipelines.registration.compute_fpfh_feature(cloud, search).data).T.copy()


def feature_ransac(source, target, source_features, target_features, parameters: FpfhParameters, seed: int):
    """Open3D RANSAC on feature matches (its tutorial's checkers), network units -> (4, 4).

    Seeded, but repeatable only on one Open3D thread (``open3d.utility.set_max_threads(1)``):
    with several, the threads race to the early stop (3 of 20 repeats of one pair differed on
    2 threads). The recorded runs used all cores, so their ``fpfh_ransac`` rows reproduce
    statistically, not bit for bit.
    """
    o3d = _open3d()
    registration = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed))
    distance = parameters.ransac_distance
    result = registration.registration_ransac_based_on_feature_matching(
        source,
        target,
        _feature(source_features),
        _feature(target_features),
        False,  # mutual_filter: off, as in Open3D's tutorial
        distance,
        registration.TransformationEstimationPointToPoint(False),
        3,
        [
            registration.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            registration.CorrespondenceCheckerBasedOnDistance(distance),
        ],
        registration.RANSACConvergenceCriteria(parameters.ransac_iterations, parameters.ransac_confidence),
    )
    return np.asarray(result.transformation)


def feature_fgr(source, target, source_features, target_features, parameters: FpfhParameters, seed: int):
    """Open3D Fast Global Registration on feature matches, network units -> (4, 4).

    FGR samples tuples at random from Open3D's global generator: without a seed the same
    pair gives different poses from run to run (seen: 171, 114, 56 and 166 degrees).
    """
    o3d = _open3d()
    registration = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed))
    option = registration.FastGlobalRegistrationOption(maximum_correspondence_distance=parameters.fgr_distance)
    result = registration.registration_fgr_based_on_feature_matching(
        source, target, _feature(source_features), _feature(target_features), option
    )
    return np.asarray(result.transformation)


def mutual_nearest_descriptors(source_features: np.ndarray, target_features: np.ndarray) -> np.ndarray:
    """(N,) int64 target index of each source point's mutual nearest neighbour in feature
    space (Euclidean), -1 where the nearest neighbour is not mutual."""
    source_features = np.asarray(source_features, dtype=np.float64)
    target_features = np.asarray(target_features, dtype=np.float64)
    # ||a - b||^2 up to the per-row constant ||a||^2, which does not change the argmin over b.
    distances = np.sum(target_features**2, axis=1)[None, :] - 2.0 * source_features @ target_features.T
    best_target = distances.argmin(axis=1)
    full = distances + np.sum(source_features**2, axis=1)[:, None]
    best_source = full.argmin(axis=0)
    mutual = best_source[best_target] == np.arange(len(source_features))
    return np.where(mutual, best_target, -1).astype(np.int64)


# ----------------------------------------------------------------------------- the runner
class MethodRunner:
    """Runs the selected methods on pairs; loads the network once.

    Args:
        methods: names from :data:`ALL_METHODS`.
        parameters: Open3D parameters (default: the tuned ones).
        threads: onnxruntime threads (None: all cores).
        registrar: an existing :class:`Registrar` to reuse.
        model_dir: the exported model the learned methods run (None: the bundled one).
    """

    def __init__(
        self,
        methods=ALL_METHODS,
        parameters: FpfhParameters | None = None,
        threads: int | None = None,
        registrar: Registrar | None = None,
        model_dir: Path | None = None,
    ) -> None:
        unknown = set(methods) - set(ALL_METHODS)
        if unknown:
            raise ValueError(f"unknown methods {sorted(unknown)}; expected some of {ALL_METHODS}")
        self.methods = tuple(methods)
        self.parameters = parameters or FpfhParameters.tuned()
        needs_network = any(m.startswith("logdesc") for m in self.methods)
        self.registrar = registrar or (Registrar(model_dir, threads=threads) if needs_network else None)
        self._subsets: dict[tuple[str, ...], MethodRunner] = {}

    def run(
        self, source: np.ndarray, target: np.ndarray, seed: int = 0, methods=None
    ) -> dict[str, MethodResult]:
        """The selected methods (or the subset ``methods`` of them) on one pair of user-frame
        clouds (N, 3) / (M, 3). A subset runs only what it needs: e.g. the learned methods
        alone, when a cache already holds the classical ones."""
        if methods is not None and tuple(methods) != self.methods:
            return self._subset(tuple(methods)).run(source, target, seed)
        results: dict[str, MethodResult] = {}
        if any(m.startswith("logdesc") for m in self.methods):
            results.update(self._logdesc(source, target, seed))
        classical = [m for m in self.methods if m.startswith("fpfh") or m == "icp_point_to_plane"]
        # The runtime's pair normalisation, fitted once: FPFH's frame, and the scale ICP's radii use.
        normalization = PairNormalization.fit(source, target) if classical else None
        if any(m.startswith("fpfh") for m in classical):
            results.update(self._fpfh(source, target, normalization, seed))
            for refined in ("fpfh_fgr_icp", "fpfh_ransac_icp"):
                if refined in self.methods:
                    coarse = results[REFINED_FROM[refined]]
                    results[refined] = self._refined(source, target, coarse, normalization.scale)
        if "icp_point_to_plane" in classical:
            results["icp_point_to_plane"] = self._icp(source, target, normalization.scale)
        if "kiss_matcher" in self.methods:
            results["kiss_matcher"] = self._kiss_matcher(source, target)
        return {name: results[name] for name in self.methods}

    def with_parameters(self, parameters: FpfhParameters) -> MethodRunner:
        """A runner of the same methods with other Open3D parameters, sharing this one's network
        (a benchmark whose parts are of different kinds: ModelNet pairs and range scans)."""
        return MethodRunner(self.methods, parameters, registrar=self.registrar)

    def _subset(self, methods: tuple[str, ...]) -> MethodRunner:
        """A runner of some of this one's methods, sharing its network and parameters."""
        unknown = set(methods) - set(self.methods)
        if unknown:
            raise ValueError(f"methods {sorted(unknown)} are not among this runner's {self.methods}")
        if methods not in self._subsets:
            self._subsets[methods] = MethodRunner(methods, self.parameters, registrar=self.registrar)
        return self._subsets[methods]

    def _logdesc(self, source, target, seed) -> dict[str, MethodResult]:
        start = time.perf_counter()
        pair = self.registrar.match(source, target)
        match_seconds = time.perf_counter() - start
        results = {}
        # The matches as a target index per source point of the clouds as given (the working
        # subsets may leave points out: larger clouds, stray points).
        pred_match = correspondences_as_array(pair.correspondences, len(source))
        wanted = set(self.methods)
        if "logdesc_fsr_icp" in wanted:
            wanted.add("logdesc_fsr")
        for estimator in LOGDESC_ESTIMATORS:
            name = f"logdesc_{estimator}"
            if name not in wanted:
                continue
            start = time.perf_counter()
            try:
                pose = pair.pose(estimator, seed=seed)
                results[name] = MethodResult(pose, match_seconds + time.perf_counter() - start, False, pred_match)
            except (RegistrationError, InvalidPointCloudError):
                results[name] = MethodResult(np.eye(4), match_seconds, True, pred_match)
        if "logdesc_fsr_icp" in self.methods:
            results["logdesc_fsr_icp"] = self._refined(source, target, results["logdesc_fsr"], pair.normalization.scale)
        for name, (refine, thorough, settings) in VERIFIED_METHODS.items():
            if name in self.methods:
                results[name] = self._verified(pair, refine, thorough, settings, seed, match_seconds, pred_match)
        if any(m in self.methods for m in DESCRIPTOR_METHODS):
            describe_seconds = sum(pair.timings[stage] for stage in ("load", "subsample", "geometry", "descriptors"))
            results.update(
                self._descriptor_estimators(
                    pair.source_network,
                    pair.target_network,
                    pair.source_descriptors,
                    pair.target_descriptors,
                    pair.normalization,
                    describe_seconds,
                    seed,
                    prefix="logdesc_desc",
                    working_subsets=(pair.source_index, pair.target_index, len(pair.source_points)),
                )
            )
        return results

    def _verified(self, pair, refine, thorough, settings, seed, match_seconds, pred_match) -> MethodResult:
        """register()'s pipeline from the matches: verified candidates, the flag (``thorough``:
        every candidate verified, no fast exit; ``settings``: a configuration dict applied over
        the pair's, e.g. the second draw or the verified-pose fallback)."""
        if settings:
            # register_matches() runs with the configuration the pair was matched with.
            pair = dataclasses.replace(pair, config=self.registrar.resolver.given(settings, pair.config))
        start = time.perf_counter()
        # A failure is a result.
        result = self.registrar.register_matches(pair, refine=refine, seed=seed, thorough=thorough)
        seconds = match_seconds + time.perf_counter() - start
        failed = result.pose_estimator == "none"  # no pose could be estimated (too few matches)
        fast_exit = bool(result.verification is not None and result.verification.fast_exit)
        return MethodResult(
            result.transformation, seconds, failed, pred_match, result.success, result.confidence, fast_exit
        )

    def _fpfh(self, source, target, normalization: PairNormalization, seed) -> dict[str, MethodResult]:
        start = time.perf_counter()
        source_cloud = _cloud(normalization.source_to_network(source), self.parameters.normal_radius)
        target_cloud = _cloud(normalization.target_to_network(target), self.parameters.normal_radius)
        source_features = fpfh_descriptors(source_cloud, self.parameters)
        target_features = fpfh_descriptors(target_cloud, self.parameters)
        feature_seconds = time.perf_counter() - start
        return self._descriptor_estimators(
            source_cloud,
            target_cloud,
            source_features,
            target_features,
            normalization,
            feature_seconds,
            seed,
            prefix="fpfh",
        )

    def _descriptor_estimators(
        self, source, target, source_features, target_features, normalization, feature_seconds, seed, prefix,
        working_subsets=None,
    ) -> dict[str, MethodResult]:
        """RANSAC and FGR (Open3D) on feature matches; clouds in network units.

        ``working_subsets``: (source indices, target indices, source size) when the features
        describe working subsets (stray points set aside), so that the matches are reported
        as indices into the clouds as given."""
        if not hasattr(source, "points"):
            source, target = _cloud(source), _cloud(target)
        pred_match = mutual_nearest_descriptors(source_features, target_features)
        if working_subsets is not None:
            source_index, target_index, source_count = working_subsets
            full = np.full(source_count, -1, dtype=np.int64)
            full[source_index] = np.where(pred_match >= 0, target_index[np.maximum(pred_match, 0)], -1)
            pred_match = full
        results = {}
        wanted = set(self.methods) | {REFINED_FROM[m] for m in self.methods if m in REFINED_FROM}
        for name, estimate in (
            (f"{prefix}_ransac",
             lambda: feature_ransac(source, target, source_features, target_features, self.parameters, seed)),
            (f"{prefix}_fgr",
             lambda: feature_fgr(source, target, source_features, target_features, self.parameters, seed)),
        ):
            if name not in wanted:
                continue
            start = time.perf_counter()
            pose = normalization.pose_to_user_frame(estimate())
            results[name] = MethodResult(pose, feature_seconds + time.perf_counter() - start, False, pred_match)
        return results

    @staticmethod
    def _refined(source, target, coarse: MethodResult, scale: float) -> MethodResult:
        """The package's point-to-plane ICP from a coarse pose (full clouds, user frame)."""
        refined, seconds = refine_pose(source, target, coarse.transformation, scale)
        return MethodResult(refined, coarse.seconds + seconds, coarse.failed, coarse.pred_match)

    def _kiss_matcher(self, source, target) -> MethodResult:
        """KISS-Matcher on the pair in network units (its voxel: the tuned Open3D voxel); its time
        includes the normalisation and the conversion to float32."""
        import kiss_matcher  # the bench extra

        start = time.perf_counter()
        normalization = PairNormalization.fit(source, target)
        matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel_size=self.parameters.voxel))
        solution = matcher.estimate(
            normalization.source_to_network(source).astype(np.float32),
            normalization.target_to_network(target).astype(np.float32),
        )
        pose = np.eye(4)
        pose[:3, :3] = np.asarray(solution.rotation, dtype=np.float64)
        pose[:3, 3] = np.asarray(solution.translation, dtype=np.float64).reshape(3)
        seconds = time.perf_counter() - start
        if not solution.valid:
            return MethodResult(np.eye(4), seconds, True)
        return MethodResult(normalization.pose_to_user_frame(pose), seconds)

    def _icp(self, source, target, scale: float) -> MethodResult:
        """Open3D point-to-plane ICP from the identity, in the user frame (``scale``: the pair's radius)."""
        registration = _open3d().pipelines.registration
        start = time.perf_counter()
        source_cloud = _cloud(source)
        target_cloud = _cloud(target, self.parameters.normal_radius * scale)
        result = registration.registration_icp(
            source_cloud,
            target_cloud,
            self.parameters.icp_distance * scale,
            np.eye(4),
            registration.TransformationEstimationPointToPlane(),
            registration.ICPConvergenceCriteria(max_iteration=50),
        )
        return MethodResult(np.asarray(result.transformation).copy(), time.perf_counter() - start)


BENCHMARK_REFINEMENT = RefinementConfig(method="point_to_plane")
"""The ICP of every refined row: ``register(..., refine="point_to_plane")``'s configuration."""
REFINEMENT_ID = sha256(json.dumps(BENCHMARK_REFINEMENT.to_dict(), sort_keys=True).encode()).hexdigest()[:12]
"""Stamps the refined classical rows in the per-pair caches (benchmarks/common.ResultCache):
records refined by another ICP are re-run from their cached coarse poses."""


def refine_pose(source: np.ndarray, target: np.ndarray, coarse: np.ndarray, scale: float) -> tuple[np.ndarray, float]:
    """(refined (4, 4) pose, seconds): ``register(..., refine="point_to_plane")``'s ICP from
    ``coarse`` (:func:`logdesc_rt.refinement.refine_pose`, :data:`BENCHMARK_REFINEMENT`), with
    correspondences within 5 % of ``scale`` (the pair's radius, user units) and its adaptive
    stages."""
    start = time.perf_counter()
    distance = BENCHMARK_REFINEMENT.distance_fraction * scale
    refined = runtime_refine_pose(source, target, coarse, distance, BENCHMARK_REFINEMENT).transformation
    return refined, time.perf_counter() - start


def parameters_dict(parameters: FpfhParameters) -> dict:
    """The parameters with their derived radii, for result files."""
    values = asdict(parameters)
    values.update(
        normal_radius=parameters.normal_radius,
        feature_radius=parameters.feature_radius,
        ransac_distance=parameters.ransac_distance,
        fgr_distance=parameters.fgr_distance,
    )
    return values

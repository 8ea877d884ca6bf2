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
      -> optional ICP refinement on the full clouds; fitness / inlier RMSE against the full
         target, over a bounded seeded subset of the source
      -> optionally, if the success flag does not claim the result: the same again on working
         subsets drawn by the other subsampling method (the second draw), the more confident
         result kept

Every parameter of these stages is in one :class:`~logdesc_rt.config.RuntimeConfig`.

Where each stage lives: loading (:func:`logdesc_rt.io.input_points`), the working subset
(:mod:`logdesc_rt.sampling`), normalisation (:mod:`logdesc_rt.normalization`), geometry
(:mod:`logdesc_rt.geometry`), the networks (:mod:`logdesc_rt.network`), Sinkhorn
(:mod:`logdesc_rt.matching`), the pair between stages (:mod:`logdesc_rt.pair`), candidates
(:mod:`logdesc_rt.pose.candidates`), verification (:mod:`logdesc_rt.verification`), the path
from matches to the result (:mod:`logdesc_rt.pose_selection`), the result types
(:mod:`logdesc_rt.results`), configuration resolution (:mod:`logdesc_rt.config_resolution`).
This module holds :class:`Registrar`, which runs them in order.

Every stage's wall time is reported in ``RegistrationResult.timings``.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .config import REFINEMENT_METHODS, SUBSAMPLING_METHODS, RefinementConfig, RuntimeConfig, SubsamplingConfig
from .config_resolution import UNSET, ConfigResolver
from .geometry import compute_geometry
from .io import input_points
from .matching import sinkhorn_matches
from .network import OnnxNetwork
from .normalization import PairNormalization, centre_and_radius
from .pair import MIN_MATCHES, PairMatches, PreparedPair, pair_from_scores  # noqa: F401 (re-exported)
from .pose.evaluation import check_rigid_transformation
from .pose_selection import register_matched
from .results import Descriptors, RegistrationResult  # noqa: F401 (re-exported)
from .sampling import working_subset
from .threads import one_thread_per_caller, per_cloud
from .timing import timed
from .validation import as_points, check_not_degenerate

ICP_METHODS = REFINEMENT_METHODS
# Default correspondence distance for fitness / ICP, as a fraction of the pair's scale (the
# larger cloud's radius): 5 %, i.e. 0.05 network units, ~3 noise sigmas of the training data.
# RefinementConfig holds it; named here for the benchmarks.
DEFAULT_DISTANCE_FRACTION = RefinementConfig.distance_fraction


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
        self.resolver = ConfigResolver(self.manifest)
        config = self.resolver.given(config, self.resolver.model_defaults)
        if max_points is not None or subsampling is not None:
            config = dataclasses.replace(
                config,
                subsampling=SubsamplingConfig(
                    max_points=config.subsampling.max_points if max_points is None else int(max_points),
                    method=config.subsampling.method if subsampling is None else subsampling,
                ),
            )
        self.config = self.resolver.resolved(config)
        self.max_points = self.config.subsampling.max_points
        self.subsampling = self.config.subsampling.method
        # Clouds larger than the working size reach the networks at exactly that size.
        self.network.fixed_points = self.max_points

    # -- public API -------------------------------------------------------------------------

    def register(
        self,
        source,
        target,
        *,
        estimator: str | None = None,
        refine=UNSET,
        max_correspondence_distance: float | None = None,
        seed: int | None = None,
        init=None,
        config: RuntimeConfig | None = None,
        progress: Callable[[str], None] | None = None,
        thorough: bool | None = None,
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
                full clouds and the best kept, then re-fitted on the matches its verified pose
                explains, ``VerificationConfig.refit_spacings``), or "fsr" (the paper's), "svd"
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
            thorough: True verifies every candidate pose, also when the fast exit is sure of
                the first one (:mod:`logdesc_rt.verification`): slower, for a second opinion.

        With ``config={"subsampling": {"second_draw": True}}``, a result the success flag does
        not claim is followed by a second draw: the pair matched and registered again on working
        subsets of the other subsampling method, the more confident result returned
        (:class:`~logdesc_rt.config.SubsamplingConfig`; its time is ``timings["second_draw"]``,
        and ``result.draws`` says how many draws ran).

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
            thorough=thorough,
        )
        initial = None if init is None else check_rigid_transformation(init, name="init")
        report = progress if progress is not None else (lambda message: None)
        report("matching: geometry, networks and Sinkhorn on the working subsets")
        registrar = self._with_config(config)
        return registrar._registered(registrar.match(source, target), config, initial, report)

    def register_matches(
        self,
        pair: PairMatches,
        *,
        estimator: str | None = None,
        refine=UNSET,
        max_correspondence_distance: float | None = None,
        seed: int | None = None,
        init=None,
        progress: Callable[[str], None] | None = None,
        thorough: bool | None = None,
    ) -> RegistrationResult:
        """:meth:`register` from a pair already matched (:meth:`match`), without running the
        networks on its working subsets again: candidate poses, verification, the success
        flag, optional ICP, and the second draw if the configuration asks for it.

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
            thorough=thorough,
        )
        initial = None if init is None else check_rigid_transformation(init, name="init")
        report = progress if progress is not None else (lambda message: None)
        return self._with_config(config)._registered(pair, config, initial, report)

    def call_config(
        self,
        config: RuntimeConfig | dict | None = None,
        *,
        estimator: str | None = None,
        refine=UNSET,
        max_correspondence_distance: float | None = None,
        seed: int | None = None,
        thorough: bool | None = None,
    ) -> RuntimeConfig:
        """The configuration one :meth:`register` call runs with: ``config`` (default: the
        Registrar's; a dict applies over it) with the keyword overrides applied, resolved.

        Raises:
            ValueError: an invalid override (unknown estimator or refinement, distance <= 0).
        """
        return self.resolver.for_call(
            config, self.config, estimator=estimator, refine=refine,
            max_correspondence_distance=max_correspondence_distance, seed=seed, thorough=thorough,
        )

    def match(self, source, target) -> PairMatches:
        """The learned pipeline up to the matches: what :meth:`register` builds its pose from.

        Useful to try several pose estimators on one pair, or to feed the descriptors to
        another estimator (``benchmarks/`` does both). Takes the same clouds as
        :meth:`register`; never raises for too few matches (check ``len(result.matches)``).
        """
        return self._match_prepared(self.prepare(source, target))

    def _match_prepared(self, prepared: PreparedPair) -> PairMatches:
        """:meth:`match` from the prepared pair: the networks and Sinkhorn."""
        timings = dict(prepared.timings)
        network_source, network_target = prepared.source_network, prepared.target_network
        with timed(timings, "descriptors"):
            source_descriptors, target_descriptors = self.network.describe_pair(
                {
                    "edges": prepared.source_geometry.edges,
                    "points": network_source,
                    "normals": prepared.source_geometry.normals,
                },
                {
                    "edges": prepared.target_geometry.edges,
                    "points": network_target,
                    "normals": prepared.target_geometry.normals,
                },
            )
        with timed(timings, "matcher"):
            scores = self.network.match_scores(
                source_descriptors,
                target_descriptors,
                prepared.source_geometry.normals,
                prepared.target_geometry.normals,
                network_source,
                network_target,
            )
        with timed(timings, "matching"), one_thread_per_caller():
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
        with timed(timings, "load"):
            source_points = self._load(source, "source")
            target_points = self._load(target, "target")
        with one_thread_per_caller():  # the stray test's and the sampling's kNN too (threads.py)
            return self._prepare_loaded(source_points, target_points, timings)

    def _prepare_loaded(self, source_points: np.ndarray, target_points: np.ndarray, timings: dict) -> PreparedPair:
        subsets = self._working_subsets(source_points, target_points, timings)
        return self._prepared(source_points, target_points, subsets, timings)

    def _working_subsets(
        self, source_points: np.ndarray, target_points: np.ndarray, timings: dict
    ) -> tuple[np.ndarray, np.ndarray, PairNormalization]:
        """Each cloud's working subset (indices) and the pair's map to network units."""
        with timed(timings, "subsample"):
            (source_index, *source_extent), (target_index, *target_extent) = per_cloud(
                self._working_subset_and_extent, (source_points,), (target_points,)
            )
            normalization = PairNormalization.from_extents(*source_extent, *target_extent, self.manifest.normalization)
        return source_index, target_index, normalization

    def _prepared(
        self,
        source_points: np.ndarray,
        target_points: np.ndarray,
        subsets: tuple[np.ndarray, np.ndarray, PairNormalization],
        timings: dict,
    ) -> PreparedPair:
        """The prepared pair of given working subsets: their network-unit points and geometry."""
        source_index, target_index, normalization = subsets
        network_source = normalization.source_to_network(source_points[source_index])
        network_target = normalization.target_to_network(target_points[target_index])
        with timed(timings, "geometry"):
            geometry = self.manifest.geometry
            source_geometry, target_geometry = per_cloud(
                compute_geometry, (network_source, geometry), (network_target, geometry)
            )
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

    def _registered(
        self, pair: PairMatches, config: RuntimeConfig, initial: np.ndarray | None, report: Callable[[str], None]
    ) -> RegistrationResult:
        """The result of a matched pair (:func:`register_matched`), and, when the flag does not
        claim it, the second draw (:attr:`SubsamplingConfig.second_draw`): the same pipeline on
        working subsets of the other subsampling method, the more confident result kept.

        The returned timings are the first draw's stages plus ``second_draw``, the second
        draw's whole time (its subsets, geometry, networks, poses and verification)."""
        first = register_matched(pair, config, initial, report)
        if first.success or not config.subsampling.second_draw:
            return first
        started = time.perf_counter()
        other_method = next(method for method in SUBSAMPLING_METHODS if method != config.subsampling.method)
        second_config = dataclasses.replace(
            config, subsampling=dataclasses.replace(config.subsampling, method=other_method)
        )
        other = self._with_config(second_config)
        timings: dict[str, float] = {}
        with one_thread_per_caller():
            subsets = other._working_subsets(pair.source_points, pair.target_points, timings)
        if np.array_equal(subsets[0], pair.source_index) and np.array_equal(subsets[1], pair.target_index):
            return first  # both clouds are their whole working subsets: a second draw would repeat the first
        report(f"matching again on {other_method} working subsets: the flag did not claim the first result")
        with one_thread_per_caller():
            prepared = other._prepared(pair.source_points, pair.target_points, subsets, timings)
        second = register_matched(other._match_prepared(prepared), second_config, initial, report)
        kept = second if second.confidence > first.confidence else first
        stages = {stage: seconds for stage, seconds in first.timings.items() if stage != "total"}
        stages["second_draw"] = time.perf_counter() - started
        stages["total"] = sum(stages.values())
        return dataclasses.replace(kept, timings=stages, draws=2)

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

    def _working_subset_and_extent(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """The working subset's indices, and its centre and radius (:func:`centre_and_radius`)."""
        index = self._working_subset(points)
        return (index, *centre_and_radius(points[index], self.manifest.normalization))

    def _working_subset(self, points: np.ndarray) -> np.ndarray:
        """(K,) int64 indices of the points the network sees, K <= min(N, max_points)."""
        return working_subset(
            points,
            self.max_points,
            self.subsampling,
            self.manifest.normalization,
            min_points=self.manifest.geometry.min_points,
        )


_DEFAULT_REGISTRAR: Registrar | None = None


def _default_registrar() -> Registrar:
    global _DEFAULT_REGISTRAR
    if _DEFAULT_REGISTRAR is None:
        _DEFAULT_REGISTRAR = Registrar()
    return _DEFAULT_REGISTRAR


def register(source, target, **options) -> RegistrationResult:
    """Register two clouds with the bundled model (loaded once, reused).

    ``options`` are those of :meth:`Registrar.register` (estimator, refine,
    max_correspondence_distance, seed, init, config, progress, thorough); ``config`` may set every
    runtime stage, the working size and matching included. For another model or thread count,
    build a :class:`Registrar`. Check ``result.success`` before using the pose.
    """
    return _default_registrar().register(source, target, **options)


def describe(points) -> Descriptors:
    """Per-point learned descriptors of one cloud with the bundled model."""
    return _default_registrar().describe(points)

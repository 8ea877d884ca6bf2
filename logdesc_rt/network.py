"""The learned network at run time: two ONNX graphs run by onnxruntime, and their metadata.

A model directory holds

    manifest.json           file names, SHA-256 checksums, configs, provenance
    descriptor.onnx         edges (1, N, k, C), points (1, N, 3) [, normals (1, N, 3)]
                            -> descriptors (1, N, d)
    matcher.onnx            descriptors and normals [and positions] of both clouds
                            -> scores (1, N, M)
    matcher_same_size.onnx  (optional) the same for N = M, both clouds in one batch of two:
                            half the operator calls, ~8 % less time at the working size

Which optional inputs a graph takes depends on the model's architecture (the paper's network,
or the invariant one); the runtime feeds each graph by input name.

``export/to_onnx.py`` writes it. The manifest (mirrored in each ONNX file's metadata) carries
everything the runtime must reproduce from training: the geometry, normalisation and matching
configs, the learned dustbin score and the working size (points per cloud seen in training).
Checksums are verified when the model is loaded, so a truncated or altered file fails loudly.
"""

from __future__ import annotations

import hashlib
import json
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from .config import GeometryConfig, MatchingConfig, NormalizationConfig, RuntimeConfig
from .errors import ModelFileError
from .threads import ResidentThread

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = 1
DESCRIPTOR_FILE = "descriptor.onnx"
MATCHER_FILE = "matcher.onnx"
# The matcher for two clouds of one size, both in one batch (optional: the invariant network's).
SAME_SIZE_MATCHER_FILE = "matcher_same_size.onnx"
POINT_AXES = ("n", "m")  # the graphs' point-count axes (export/to_onnx.py): source, target


def bundled_model_dir() -> Path:
    """The directory of the model shipped inside the package."""
    return Path(str(resources.files("logdesc_rt") / "models"))


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class ModelManifest:
    """What ``manifest.json`` says about a model directory.

    Attributes:
        geometry: geometry parameters the network was trained with.
        normalization: how pairs were mapped into network units in training.
        matching: Sinkhorn iterations and match threshold.
        dustbin_score: learned dustbin score alpha.
        points_per_cloud: cloud size in training; larger inputs are subsampled to this.
        descriptor_dim: d, the width of the descriptors.
        checksums: file name -> SHA-256 hex digest.
        model_config: the training model config (informative at run time).
        provenance: data, steps, wall time, hardware, commit, validation metrics.
        runtime: the model's runtime defaults, a partial :class:`~logdesc_rt.config.RuntimeConfig`
            dict (e.g. "verification": the success flag calibrated for this model);
            ``Registrar`` starts from it.
    """

    geometry: GeometryConfig
    normalization: NormalizationConfig
    matching: MatchingConfig
    dustbin_score: float
    points_per_cloud: int
    descriptor_dim: int
    checksums: dict[str, str]
    model_config: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    runtime: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": MANIFEST_FORMAT,
            "geometry": self.geometry.to_dict(),
            "normalization": self.normalization.to_dict(),
            "matching": self.matching.to_dict(),
            "dustbin_score": self.dustbin_score,
            "points_per_cloud": self.points_per_cloud,
            "descriptor_dim": self.descriptor_dim,
            "checksums": self.checksums,
            "model_config": self.model_config,
            "provenance": self.provenance,
            "runtime": self.runtime,
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ModelManifest:
        if values.get("format") != MANIFEST_FORMAT:
            raise ValueError(f"manifest format {values.get('format')!r}, expected {MANIFEST_FORMAT}")
        return cls(
            geometry=GeometryConfig.from_stored(values["geometry"]),
            normalization=NormalizationConfig.from_dict(values["normalization"]),
            matching=MatchingConfig.from_stored(values["matching"]),
            dustbin_score=float(values["dustbin_score"]),
            points_per_cloud=int(values["points_per_cloud"]),
            descriptor_dim=int(values["descriptor_dim"]),
            checksums=dict(values["checksums"]),
            model_config=dict(values.get("model_config", {})),
            provenance=dict(values.get("provenance", {})),
            runtime=dict(values.get("runtime", {})),
        )

    def __post_init__(self) -> None:
        self.runtime_config()  # a bad "runtime" section fails when the model is read

    def runtime_config(self) -> RuntimeConfig:
        """The model's runtime defaults: ``runtime`` over the code's defaults (not yet
        resolved: ``Registrar`` fills in the working size and the model's matching).

        A calibration stored without its candidate set was fitted with the four estimators of
        ``LEGACY_CANDIDATES``, and keeps them: its ``agreement`` feature counts among them.
        One stored without the second look's settings was fitted without it, and runs
        without it: its ``margin`` feature never met a turn-over as a rival. One
        stored without ``descriptor_consensus`` runs without the descriptors' candidates, and
        one without ``refit_spacings`` returns the estimator's own pose without ICP, one
        without ``refit_plane_steps`` returns the re-fit without its point-to-plane steps, and
        one without ``verified_fallback_rmse`` never returns the verified pose in its place."""
        runtime = dict(self.runtime)
        verification = runtime.get("verification")
        if isinstance(verification, dict):
            legacy = {"candidates": list(LEGACY_CANDIDATES)}
            if "weights" in verification:  # a stored calibration
                legacy.update(LEGACY_VERIFICATION_OFF)
            runtime["verification"] = {**legacy, **verification}
        return RuntimeConfig.from_dict(runtime)


LEGACY_CANDIDATES = ("fsr", "ransac", "svd", "top_k")
"""The candidate estimators of calibrations stored without a candidate set (no "core")."""
LEGACY_VERIFICATION_OFF = {
    "turn_over_axes": 0, "second_consensus": [], "descriptor_consensus": [], "refit_spacings": 0.0,
    "refit_plane_steps": 0, "turn_over_spin": False, "exit_weights": [], "verified_fallback_rmse": 0.0,
}
"""Settings a stored calibration lacks were not there when it was fitted: off (each key is
filled in alone)."""


def read_manifest(model_dir: Path) -> ModelManifest:
    """Read and check ``model_dir/manifest.json`` and the checksums of the files it lists."""
    manifest_path = model_dir / MANIFEST_NAME
    if not manifest_path.is_file():
        raise ModelFileError(
            f"{manifest_path}: no model manifest here; pass the directory written by export/to_onnx.py"
        )
    try:
        manifest = ModelManifest.from_dict(json.loads(manifest_path.read_text()))
    except (ValueError, KeyError, TypeError) as error:
        raise ModelFileError(f"{manifest_path}: not a valid logdesc-rt model manifest ({error})") from error
    for name in (DESCRIPTOR_FILE, MATCHER_FILE, *sorted(set(manifest.checksums) - {DESCRIPTOR_FILE, MATCHER_FILE})):
        path = model_dir / name
        if name not in manifest.checksums:
            raise ModelFileError(f"{manifest_path}: no checksum recorded for {name}")
        if not path.is_file():
            raise ModelFileError(f"{path}: model file missing")
        actual = sha256_of(path)
        if actual != manifest.checksums[name]:
            raise ModelFileError(
                f"{path}: checksum mismatch (file {actual[:12]}..., manifest "
                f"{manifest.checksums[name][:12]}...): the file is corrupt or was replaced"
            )
    return manifest


def network_thread() -> ThreadPoolExecutor:
    """The one thread (per process) that creates and runs every onnxruntime session of this
    package: it carries onnxruntime's flush-to-zero mode (see :class:`OnnxNetwork`), which the
    caller's threads never see. Calls from several threads queue here, one graph at a time; each
    graph still uses its session's intra-op threads."""
    return _NETWORK_THREADS[0].executor()


def second_network_thread() -> ThreadPoolExecutor:
    """A second thread for the networks, with flush-to-zero set by this package
    (:func:`~logdesc_rt.denormals.flush_denormals_on_this_thread`): it runs one cloud's
    descriptor while :func:`network_thread` runs the other's (:meth:`OnnxNetwork.describe_pair`)."""
    return _NETWORK_THREADS[1].executor()


def _flush_denormals() -> bool:
    """Flush-to-zero on the calling thread, set by this package (each network thread's start,
    so that a thread started again, after a fork or after onnxruntime's once-per-process set-up
    went to another thread, has it as well). True if it is set; never raises: a thread pool
    whose initializer raises runs nothing."""
    try:
        from .denormals import flush_denormals_on_this_thread  # deferred: it loads numba

        return flush_denormals_on_this_thread()
    except Exception:  # noqa: BLE001 (an unusable numba / llvmlite: onnxruntime's own set-up stays)
        return False


# The threads of network_thread and second_network_thread, each with flush-to-zero set at its start
# (so that a thread started again, after a fork, has it as well).
_NETWORK_THREADS = (
    ResidentThread("logdesc-rt-network", initializer=_flush_denormals),
    ResidentThread("logdesc-rt-network-2", initializer=_flush_denormals),
)


class OnnxNetwork:
    """The two ONNX graphs of one model, loaded once, run on the CPU.

    Args:
        model_dir: directory with manifest.json and the two .onnx files; None = bundled model.
        threads: onnxruntime intra-op threads; None lets onnxruntime use every core.
        fixed_points: a point count (the working size) for which each graph also gets a session
            with its point axes fixed: onnxruntime then folds the graph's shape arithmetic (about
            a third of its nodes) into constants, which saves ~5 % of the networks' time on
            2 cores. Created on the first call at that size (0.1-0.2 s, ~9 MiB for both graphs);
            every other size runs the dynamic session. None: dynamic sessions only.

    Two clouds of ``fixed_points`` points each (:meth:`describe_pair`) go through the descriptor
    at once, each on its own thread with half the intra-op threads, where there are at least
    two and flush-to-zero can be set on both threads (x86-64): a graph's many small operators
    run on one thread and leave the other core idle, so on 2 cores two one-thread runs side by
    side take ~15 % less time than two two-thread runs one after the other. Elsewhere the two
    clouds go one after the other.
    """

    def __init__(
        self, model_dir: str | Path | None = None, threads: int | None = None, fixed_points: int | None = None
    ):
        self.model_dir = Path(model_dir) if model_dir is not None else bundled_model_dir()
        self.manifest = read_manifest(self.model_dir)
        if threads is not None and threads < 1:
            raise ValueError(f"threads: {threads} < 1")
        self.threads = threads
        self.fixed_points = fixed_points
        self._sessions: dict[str, Any] = {}  # file name -> its session with dynamic point counts
        self._fixed_sessions: dict[str, Any] = {}  # file name -> its session at fixed_points
        self._half_descriptor: Any = None  # the descriptor at fixed_points on half the threads
        self._side_by_side: bool | None = None  # describe_pair's choice, made at its first call
        try:
            for name in (DESCRIPTOR_FILE, MATCHER_FILE):
                self._sessions[name] = network_thread().submit(self._load, name).result()
        except Exception as error:  # onnxruntime raises its own untyped exceptions
            raise ModelFileError(f"{self.model_dir}: onnxruntime cannot load the model ({error})") from error
        self._descriptor_inputs = [i.name for i in self._sessions[DESCRIPTOR_FILE].get_inputs()]
        self._matcher_inputs = [i.name for i in self._sessions[MATCHER_FILE].get_inputs()]

    def _load(self, name: str, fixed_points: int | None = None, threads: int | None = None):
        """An onnxruntime session of graph ``name``; with ``fixed_points``, its point axes
        (``POINT_AXES``) fixed to that count; ``threads`` intra-op threads (None: this network's
        ``threads``). Called on the network thread (flush-to-zero)."""
        import onnxruntime  # deferred: importing the package stays cheap

        options = onnxruntime.SessionOptions()
        # Latency on a small CPU: full graph optimisation, one op at a time, spinning threads off
        # so that an idle registrar does not burn cores between calls.
        options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        # No memory pattern: point counts vary between calls, and from the second call on the
        # planner pre-allocates the recorded pattern beside the arena's blocks. Measured peak
        # above baseline, both networks, four calls at N = 1024 / 2048 / 4096 points:
        # 557 / 1980 / ~7640 MiB with it, 297 / 1201 / 4936 MiB without (benchmarks/latency.py).
        options.enable_mem_pattern = False
        # Denormal floats. Attention logits ~90 below their row's maximum give softmax terms in
        # float32's denormal range, which x86 cores process ~100x slower; the invariant network's
        # distance-biased heads give such entries (the bundled descriptor's two attention nodes
        # at 320 points, one thread: 4.6 ms with them, 1.4 ms flushed).
        # Flushing them to zero (FTZ/DAZ) changes no value above 1e-38. onnxruntime sets the mode on each
        # session's pool threads, and once per process (the first session only) on the thread
        # that creates it; so every session is created and run on this module's own threads
        # (network_thread; second_network_thread, which logdesc_rt.denormals sets up), and the
        # caller's threads keep IEEE denormals.
        options.add_session_config_entry("session.set_denormal_as_zero", "1")
        threads = self.threads if threads is None else threads
        if threads is not None:
            options.intra_op_num_threads = threads
            options.inter_op_num_threads = 1
        for axis in POINT_AXES if fixed_points is not None else ():
            options.add_free_dimension_override_by_name(axis, fixed_points)
        return onnxruntime.InferenceSession(str(self.model_dir / name), options, providers=["CPUExecutionProvider"])

    def describe(self, edges: np.ndarray, points: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        """Descriptors of one cloud.

        Args:
            edges: (N, k, C) float32 edge features (network units).
            points: (N, 3) positions, network units.
            normals: (N, 3) unit normals (read by models whose descriptor uses them: the
                invariant architecture).

        Returns:
            (N, d) float32 unit-norm descriptors.
        """
        arrays = {"edges": edges, "points": points, "normals": normals}
        return self._run(DESCRIPTOR_FILE, self._feeds(self._descriptor_inputs, arrays), len(points))

    def describe_pair(
        self, source: dict[str, np.ndarray], target: dict[str, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Descriptors of both clouds of a pair: :meth:`describe` of each, side by side where
        both have ``fixed_points`` points (see the class docstring).

        Args:
            source, target: each cloud's :meth:`describe` arguments by name ("edges",
                "points", and "normals" for models that read them).

        Returns:
            (N, d) and (M, d) float32 unit-norm descriptors.
        """
        feeds = [self._feeds(self._descriptor_inputs, cloud) for cloud in (source, target)]
        counts = [len(cloud["points"]) for cloud in (source, target)]
        if (
            self.fixed_points is None
            or any(count != self.fixed_points for count in counts)
            or not self._can_go_side_by_side()
        ):
            return tuple(self._run(DESCRIPTOR_FILE, feed, count) for feed, count in zip(feeds, counts))
        session = self._half_descriptor
        source_job = second_network_thread().submit(session.run, None, feeds[0])
        target_descriptors = network_thread().submit(session.run, None, feeds[1]).result()[0][0]
        return source_job.result()[0][0], target_descriptors

    def _can_go_side_by_side(self) -> bool:
        """Whether :meth:`describe_pair` runs its two clouds at once (decided at its first call:
        at least two threads, flush-to-zero set on both network threads); creates the session."""
        if self._side_by_side is None:
            cores = self.threads if self.threads is not None else (os.cpu_count() or 1)
            self._side_by_side = cores >= 2 and all(
                thread().submit(_flush_denormals).result() for thread in (network_thread, second_network_thread)
            )
            if self._side_by_side:
                self._half_descriptor = network_thread().submit(
                    self._load, DESCRIPTOR_FILE, self.fixed_points, cores // 2
                ).result()
        return self._side_by_side

    def match_scores(
        self,
        source_descriptors: np.ndarray,
        target_descriptors: np.ndarray,
        source_normals: np.ndarray,
        target_normals: np.ndarray,
        source_points: np.ndarray | None = None,
        target_points: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N, M) float32 scores <f_i, h_j> / sqrt(d) after the transformer.

        Positions (network units) are read by models whose transformer uses them (the invariant
        architecture). Two clouds of one size go through the model's same-size graph where it
        has one (``SAME_SIZE_MATCHER_FILE``), created at its first use.
        """
        arrays = {
            "descriptors_source": source_descriptors,
            "descriptors_target": target_descriptors,
            "normals_source": source_normals,
            "normals_target": target_normals,
            "points_source": source_points,
            "points_target": target_points,
        }
        counts = (len(source_descriptors), len(target_descriptors))
        same_size = counts[0] == counts[1] and SAME_SIZE_MATCHER_FILE in self.manifest.checksums
        return self._run(
            SAME_SIZE_MATCHER_FILE if same_size else MATCHER_FILE, self._feeds(self._matcher_inputs, arrays), *counts
        )

    def _run(self, name: str, feeds: dict[str, np.ndarray], *point_counts: int) -> np.ndarray:
        """Graph ``name``'s one output, batch axis dropped, computed on the network thread: by
        its fixed-size session where every point count is ``fixed_points``, else by its dynamic
        one; either is created at its first use if it does not exist yet."""

        def run():
            fixed = self.fixed_points is not None and all(count == self.fixed_points for count in point_counts)
            sessions = self._fixed_sessions if fixed else self._sessions
            if name not in sessions:
                sessions[name] = self._load(name, self.fixed_points if fixed else None)
            return sessions[name].run(None, feeds)[0][0]

        return network_thread().submit(run).result()

    def _feeds(self, input_names: list[str], arrays: dict[str, np.ndarray | None]) -> dict[str, np.ndarray]:
        """The graph's inputs, by name, as (1, ...) float32 batches of one."""
        feeds = {}
        for name in input_names:
            array = arrays.get(name)
            if array is None:
                raise ModelFileError(f"{self.model_dir}: the model needs input {name!r}, which was not given")
            feeds[name] = np.ascontiguousarray(array, dtype=np.float32)[None]
        return feeds

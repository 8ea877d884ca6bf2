"""Align a set of scans into one frame: candidate pairs, verified pairwise poses, a pose graph.

    result = align(["scan_a.ply", "scan_b.ply", "scan_c.ply"])   # in a script's main guard
    result.poses["scan_b.ply"]      # (4, 4): scan_b's points into the reference scan's frame
    result.reference                # "scan_a.ply": the first scan, unless it is cut off (5. below)
    result.disconnected             # scans no verified pair ties to the reference
    json.dumps(result.to_json())

Stages:

1. **Candidate pairs.** All N (N - 1) / 2 pairs up to ``AlignConfig.all_pairs_up_to`` scans.
   Beyond, each scan is paired with its ``neighbours`` nearest scans by a cheap global
   descriptor (:func:`global_descriptors`: histograms of point-to-centroid and point-to-point
   distances, and the PCA extents; rotation and translation invariant, O(N) to compute), plus
   the minimum spanning tree of those descriptor distances so the candidate graph is
   connected: at most N (k + 1) pairs instead of N^2 / 2. Scans of one campaign that overlap
   see the same part of the object or scene at one scale, so their distance statistics agree;
   a registration costs about a second, the descriptor distances microseconds.
2. **Pairwise registration** with :func:`~logdesc_rt.batch.register_many` (same backends:
   local processes or Ray), ICP on by default. A pair is kept when verification says
   ``success`` (or ``confidence >= AlignConfig.min_confidence`` when set).
3. **Pose graph.** One edge per kept pair: its pose, and a weight from its verification: the
   residuals are divided by the pair's inlier RMSE (user units: a sharper fit weighs more)
   and multiplied by sqrt(confidence). Each residual is 6 numbers, both lengths in user units:
   the rotation error as a rotation vector times the scan's radius (the displacement it causes
   at the scan's rim) and the displacement of the scan's centroid, so the weights do not
   depend on where the scans sit or on their unit.
4. **Optimisation** with ``scipy.optimize.least_squares`` (trust-region, soft-L1 robust loss,
   sparse Jacobian: a residual block touches two poses), starting from the maximum-confidence
   spanning tree. SciPy is already a dependency and a pose graph of tens to thousands of
   scans with 6-DoF poses is small for it; gtsam / g2o would add a heavy compiled
   dependency for no accuracy we need here. Edges still inconsistent after the
   optimisation (rotation residual > ``prune_rotation_deg`` or centroid residual >
   ``prune_translation_fraction`` of the radius) are dropped and the graph is solved again.
5. **Poses** in the frame of the reference scan for every scan connected to it; the others
   are listed in ``disconnected`` and get no pose (never placed at a guess). The reference is
   ``AlignConfig.reference`` when given; by default the first scan of the largest set of scans
   the verified pairs connect (the first scan itself when its set is as large as any), so one
   scan that matches nothing, given first, does not leave the others unplaced.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.sparse import coo_matrix, lil_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial.transform import Rotation

from .batch import register_many
from .config import RuntimeConfig
from .io import input_points, write_point_cloud
from .sampling import voxel_downsample
from .validation import as_points

_DESCRIPTOR_SAMPLES = 512  # points per scan for the global descriptor's distance histograms
_DESCRIPTOR_BINS = 32


@dataclass(frozen=True)
class AlignConfig:
    """Parameters of :func:`align`.

    Attributes:
        all_pairs_up_to: register every pair when there are at most this many scans.
        neighbours: beyond that, candidate partners per scan by global descriptor (k).
        refine: ICP of each pair (None, "point_to_point" or "point_to_plane").
        min_confidence: keep a pair when its confidence >= this; None = the pair's
            ``success`` flag (the calibrated threshold).
        robust_scale: soft-L1 loss scale, in units of an edge's residual scale (its inlier
            RMSE): residuals well beyond it count linearly, not squared.
        prune_rotation_deg: after optimisation, edges whose rotation disagrees with the graph
            by more than this are dropped (then the graph is solved again).
        prune_translation_fraction: same for the centroid's displacement, as a fraction of the
            scan's radius.
        max_prune_rounds: edges pruned at most (one per round, each followed by a new solve).
        seed: seeds registration (and the global descriptor's point subsets).
        reference: index of the scan whose frame the poses are in; None = the first scan of
            the largest connected set of scans (stage 5).
    """

    all_pairs_up_to: int = 12
    neighbours: int = 4
    refine: str | None = "point_to_plane"
    min_confidence: float | None = None
    robust_scale: float = 3.0
    prune_rotation_deg: float = 5.0
    prune_translation_fraction: float = 0.05
    max_prune_rounds: int = 20
    seed: int = 0
    reference: int | None = None

    def __post_init__(self) -> None:
        if self.all_pairs_up_to < 2 or self.neighbours < 1:
            raise ValueError(f"all_pairs_up_to {self.all_pairs_up_to} must be >= 2, neighbours {self.neighbours} >= 1")
        if self.min_confidence is not None and not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence {self.min_confidence} must be in [0, 1]")
        if not (self.robust_scale > 0 and self.prune_rotation_deg > 0 and self.prune_translation_fraction > 0):
            raise ValueError("robust_scale, prune_rotation_deg and prune_translation_fraction must be > 0")
        if self.reference is not None and (isinstance(self.reference, bool) or not isinstance(self.reference, int)
                                           or self.reference < 0):
            raise ValueError(f"reference {self.reference!r} must be a scan index >= 0 or None")


@dataclass(frozen=True)
class PoseEdge:
    """One verified pair in the pose graph.

    Attributes:
        first, second: scan indices (first < second).
        transformation: (4, 4) pairwise pose mapping scan ``second`` into scan ``first``'s frame.
        confidence: the pair's calibrated confidence; fitness: its overlap share.
        inlier_rmse: user units, the edge's residual scale.
        residual_rotation_deg, residual_translation: after optimisation, how far the graph's
            poses disagree with this edge (degrees; user units, at the scan's centroid).
        kept: False when pruned as inconsistent with the rest of the graph.
    """

    first: int
    second: int
    transformation: np.ndarray
    confidence: float
    fitness: float
    inlier_rmse: float
    residual_rotation_deg: float = float("nan")
    residual_translation: float = float("nan")
    kept: bool = True


@dataclass(frozen=True)
class AlignmentResult:
    """What :func:`align` found.

    Attributes:
        names: one name per scan, in the order given (paths as given, or ``scan_000`` ...).
        poses: name -> (4, 4) float64 pose mapping that scan into the reference scan's
            frame, for every scan connected to it (the reference: the identity).
        reference: the name of the scan whose frame ``poses`` are in (module docstring,
            stage 5: the first scan unless the verified pairs cut it off from a larger set).
        disconnected: names of the scans no kept pair ties to the reference (no pose).
        edges: every pair that passed verification, with its residual after optimisation
            (``kept`` False: pruned as inconsistent).
        rejected: the candidate pairs that did not pass: ``{"first", "second", "reason",
            "confidence"}`` (reason: the error, or "not verified").
        candidate_pairs: how many pairs were registered.
        records: the register_many records of the candidate pairs, in the order of
            ``candidate_pairs`` (id ``"NAME_J -> NAME_I"``: scan j registered onto scan i, i < j).
        timings: seconds per stage: load, candidates, pairwise, graph, total.
    """

    names: list[str]
    poses: dict[str, np.ndarray]
    reference: str
    disconnected: list[str]
    edges: list[PoseEdge]
    rejected: list[dict[str, Any]]
    candidate_pairs: int
    records: list[dict] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)

    def view(self, path, scans, *, max_points: int = 60_000, seed: int = 0):
        """Write an interactive 3D view of the aligned scans (each placed scan in its colour,
        the pose graph's pairs between their centres) as one self-contained HTML file
        (:mod:`logdesc_rt.tools.viewer`; needs plotly, the ``plot`` extra).

        Args:
            path: the .html file to write.
            scans: the scans as given to :func:`align` (arrays or paths), in ``names``' order.
            max_points: at most this many points on the page, shared by the scans.
            seed: seeds the thinning.

        Returns:
            The path written.
        """
        from .tools.viewer import write_alignment_view

        clouds, _ = _load_scans(scans, self.names)
        return write_alignment_view(path, clouds, self, max_points=max_points, seed=seed)

    def to_json(self) -> dict:
        """``{"reference": name, "poses": {name: 4x4 lists}, "pairs": [used pairs with
        residuals], "disconnected": [names], "rejected": [...], "pruned": [...],
        "candidate_pairs": int, "timings_s": {...}}``."""

        def edge_dict(edge: PoseEdge) -> dict:
            return {
                "source": self.names[edge.second],
                "target": self.names[edge.first],
                "transformation": edge.transformation.tolist(),
                "confidence": edge.confidence,
                "fitness": edge.fitness,
                "inlier_rmse": edge.inlier_rmse,
                "residual_rotation_deg": _finite_or_none(edge.residual_rotation_deg),
                "residual_translation": _finite_or_none(edge.residual_translation),
            }

        return {
            "reference": self.reference,
            "poses": {name: pose.tolist() for name, pose in self.poses.items()},
            "pairs": [edge_dict(edge) for edge in self.edges if edge.kept],
            "pruned": [edge_dict(edge) for edge in self.edges if not edge.kept],
            "disconnected": list(self.disconnected),
            "rejected": [
                {**item, "source": self.names[item["second"]], "target": self.names[item["first"]]}
                for item in self.rejected
            ],
            "candidate_pairs": self.candidate_pairs,
            "timings_s": dict(self.timings),
        }


def align(
    scans: Sequence,
    *,
    names: Sequence[str] | None = None,
    config: AlignConfig = AlignConfig(),
    runtime_config: RuntimeConfig | dict | None = None,
    backend: str = "local",
    workers: int | None = None,
    threads_per_worker: int | None = None,
    address: str | None = None,
    pairs_output: str | os.PathLike | None = None,
    progress: bool | None = None,
    model_dir: str | os.PathLike | None = None,
) -> AlignmentResult:
    """Bring N scans into one frame: the first scan's, unless it is cut off (stage 5).

    Args:
        scans: N >= 2 point clouds: (Ni, 3) arrays, Open3D PointClouds or file paths (meshes
            too: their surface samples, :func:`~logdesc_rt.io.read_registration_input`), one
            unit for all.
        names: one name per scan for the result (default: the paths, or ``scan_000`` ...).
        config: candidate pairs, verification, robust loss and pruning (:class:`AlignConfig`).
        runtime_config: the registration pipeline's configuration (None: the model's
            defaults; a dict: a partial one over them; see ``Registrar``).
        backend, workers, threads_per_worker, address, progress, model_dir: the pairwise
            stage's, as in :func:`~logdesc_rt.batch.register_many`.
        pairs_output: optional JSON-lines file for the pairwise records (then resumable).

    Returns:
        :class:`AlignmentResult`: a pose for each scan connected to the first, the others
        listed as disconnected, and the pairs used with their residuals.

    Raises:
        ValueError: fewer than 2 scans, names not unique or of the wrong count.
        InvalidPointCloudError, PointCloudFileError: a scan that cannot be read.
    """
    if not isinstance(config, AlignConfig):
        raise TypeError(f"config: expected an AlignConfig, got {type(config).__name__}")
    timings: dict[str, float] = {}
    start = time.perf_counter()
    clouds, names = _load_scans(scans, names)
    if config.reference is not None and config.reference >= len(clouds):  # before any registration
        raise ValueError(
            f"AlignConfig.reference {config.reference} is not a scan index (there are {len(clouds)} scans)"
        )
    timings["load"] = time.perf_counter() - start

    tick = time.perf_counter()
    pairs = candidate_pairs(clouds, config)
    timings["candidates"] = time.perf_counter() - tick

    tick = time.perf_counter()
    # Scan j onto scan i; ids by name, so a resumed run finds its pairs whatever the order.
    jobs = [(f"{names[j]} -> {names[i]}", clouds[j], clouds[i]) for i, j in pairs]
    records = register_many(
        jobs,
        workers=workers,
        backend=backend,
        address=address,
        output=pairs_output,
        progress=progress,
        threads_per_worker=threads_per_worker,
        model_dir=model_dir,
        config=runtime_config,
        refine=config.refine,
        seed=config.seed,
    )
    timings["pairwise"] = time.perf_counter() - tick

    tick = time.perf_counter()
    edges, rejected = _verified_edges(pairs, records, config)
    centroids = np.array([cloud.mean(axis=0) for cloud in clouds])
    radii = np.array([np.linalg.norm(cloud - cloud.mean(axis=0), axis=1).max() for cloud in clouds])
    reference = config.reference if config.reference is not None else largest_set_reference(len(clouds), edges)
    poses, edges = optimise_pose_graph(len(clouds), edges, centroids, radii, config, reference)
    timings["graph"] = time.perf_counter() - tick
    timings["total"] = time.perf_counter() - start
    return AlignmentResult(
        names=names,
        poses={names[index]: pose for index, pose in poses.items()},
        reference=names[reference],
        disconnected=[names[index] for index in range(len(clouds)) if index not in poses],
        edges=edges,
        rejected=rejected,
        candidate_pairs=len(pairs),
        records=records,
        timings=timings,
    )


# ---------------------------------------------------------------------------- candidates
def global_descriptors(clouds: Sequence[np.ndarray], seed: int = 0) -> np.ndarray:
    """A cheap rotation- and translation-invariant descriptor per scan.

    Concatenates a histogram of point-to-centroid distances, a histogram of distances between
    random point pairs (the D2 shape distribution; both over one shared range, so scale
    counts) and the square roots of the covariance eigenvalues relative to the largest radius.

    Args:
        clouds: N clouds, (Ni, 3) each, one unit.
        seed: seeds the point subsets (``_DESCRIPTOR_SAMPLES`` points per scan).

    Returns:
        (N, 2 * bins + 3) float64 descriptors, comparable by Euclidean distance.
    """
    generator = np.random.default_rng(seed)
    centred = [cloud - cloud.mean(axis=0) for cloud in clouds]
    reach = max(float(np.linalg.norm(cloud, axis=1).max()) for cloud in centred)
    rows = []
    for cloud in centred:
        subset = cloud[generator.choice(len(cloud), min(len(cloud), _DESCRIPTOR_SAMPLES), replace=False)]
        radial, _ = np.histogram(np.linalg.norm(subset, axis=1), bins=_DESCRIPTOR_BINS, range=(0, reach))
        half = len(subset) // 2
        pairwise, _ = np.histogram(
            np.linalg.norm(subset[:half] - subset[half : 2 * half], axis=1), bins=_DESCRIPTOR_BINS, range=(0, 2 * reach)
        )
        extents = np.sqrt(np.clip(np.sort(np.linalg.eigvalsh(np.cov(cloud.T)))[::-1], 0, None)) / reach
        rows.append(np.concatenate([radial / radial.sum(), pairwise / max(pairwise.sum(), 1), extents]))
    return np.array(rows)


def candidate_pairs(clouds: Sequence[np.ndarray], config: AlignConfig = AlignConfig()) -> list[tuple[int, int]]:
    """The pairs (i, j), i < j, worth registering (module docstring, stage 1).

    Returns:
        Sorted list of index pairs: all of them for N <= ``config.all_pairs_up_to``, else
        each scan's ``config.neighbours`` nearest by :func:`global_descriptors` plus the
        minimum spanning tree of the descriptor distances (a connected candidate graph).
    """
    count = len(clouds)
    if count <= config.all_pairs_up_to:
        return [(i, j) for i in range(count) for j in range(i + 1, count)]
    descriptors = global_descriptors(clouds, config.seed)
    distances = np.linalg.norm(descriptors[:, None, :] - descriptors[None, :, :], axis=-1)
    chosen: set[tuple[int, int]] = set()
    order = np.argsort(distances + np.diag(np.full(count, np.inf)), axis=1, kind="stable")
    for i in range(count):
        for j in order[i, : min(config.neighbours, count - 1)]:
            chosen.add((min(i, int(j)), max(i, int(j))))
    tree = minimum_spanning_tree(distances + 1e-12).tocoo()  # + tiny: equal scans still link
    for i, j in zip(tree.row, tree.col):
        chosen.add((min(int(i), int(j)), max(int(i), int(j))))
    return sorted(chosen)


# ---------------------------------------------------------------------------- pose graph
def _verified_edges(pairs, records, config: AlignConfig) -> tuple[list[PoseEdge], list[dict]]:
    edges, rejected = [], []
    for (i, j), record in zip(pairs, records):
        if not record.get("ok"):
            rejected.append({"first": i, "second": j,
                             "reason": record["error"]["type"] + ": " + record["error"]["message"],
                             "confidence": None})
            continue
        passed = record["success"] if config.min_confidence is None else record["confidence"] >= config.min_confidence
        if not passed or record["inlier_rmse"] is None:
            rejected.append({"first": i, "second": j, "reason": "not verified", "confidence": record["confidence"]})
            continue
        edges.append(
            PoseEdge(
                first=i,
                second=j,
                transformation=np.asarray(record["transformation"], dtype=np.float64),
                confidence=float(record["confidence"]),
                fitness=float(record["fitness"]),
                inlier_rmse=float(record["inlier_rmse"]),
            )
        )
    return edges, rejected


def largest_set_reference(count: int, edges: list[PoseEdge]) -> int:
    """The default reference scan (module docstring, stage 5): the lowest index of the largest
    set of scans ``edges`` connect; of sets of equal size, the one holding the lowest index,
    so scan 0 whenever its set is as large as any."""
    labels = _connected_sets(count, edges)
    sizes = np.bincount(labels)
    return int(np.flatnonzero(sizes[labels] == sizes.max())[0])


def optimise_pose_graph(
    count: int,
    edges: list[PoseEdge],
    centroids: np.ndarray,
    radii: np.ndarray,
    config: AlignConfig = AlignConfig(),
    reference: int = 0,
) -> tuple[dict[int, np.ndarray], list[PoseEdge]]:
    """Global poses of the scans connected to scan ``reference`` (module docstring, stages 3-5).

    Args:
        count: number of scans N.
        edges: verified pairwise poses (``edge.transformation`` maps scan ``second`` into
            scan ``first``'s frame).
        centroids: (N, 3) scan centroids, user units, each in its own scan's frame.
        radii: (N,) scan radii (largest distance to the centroid), user units.
        config: robust loss and pruning thresholds.
        reference: the scan whose frame the poses are in (its pose: the identity).

    Returns:
        (poses, edges): scan index -> (4, 4) pose into the reference's frame for the scans
        connected to it, and every edge with its residuals (NaN outside the reference's
        component) and its ``kept`` flag (False: pruned, worst first, one per round).
    """
    kept = list(edges)
    pruned: list[PoseEdge] = []
    poses: dict[int, np.ndarray] = {reference: np.eye(4)}
    for round_index in range(config.max_prune_rounds + 1):
        labels = _connected_sets(count, kept)
        component = [index for index in range(count) if labels[index] == labels[reference]]
        members = set(component)
        used = [edge for edge in kept if edge.first in members and edge.second in members]
        if len(component) > 1:
            poses = _solve(component, used, centroids, radii, config, reference)
        else:
            poses = {reference: np.eye(4)}
        used_ids = {id(edge) for edge in used}
        measured = [_with_residuals(edge, poses, centroids) if id(edge) in used_ids else edge for edge in kept]
        in_graph = [edge for edge, old in zip(measured, kept) if id(old) in used_ids]

        def excess(edge: PoseEdge) -> float:
            return max(
                edge.residual_rotation_deg / config.prune_rotation_deg,
                edge.residual_translation / (config.prune_translation_fraction * radii[edge.second]),
            )

        bad = [edge for edge in in_graph if excess(edge) > 1.0]
        kept = measured
        if not bad or round_index == config.max_prune_rounds:
            break
        # Drop the worst inconsistent edge only, then solve again: one wrong edge drags its
        # neighbours' residuals, which come back once it is gone.
        worst = max(bad, key=excess)
        pruned.append(dataclasses.replace(worst, kept=False))
        kept = [edge for edge in measured if edge is not worst]
    ordered = sorted(kept + pruned, key=lambda edge: (edge.first, edge.second))
    return poses, ordered


def _connected_sets(count: int, edges: list[PoseEdge]) -> np.ndarray:
    """(count,) int labels: scans ``edges`` connect share a label."""
    rows = [edge.first for edge in edges]
    cols = [edge.second for edge in edges]
    graph = coo_matrix((np.ones(len(edges)), (rows, cols)), shape=(count, count))
    return connected_components(graph, directed=False)[1]


def _initial_poses(component: list[int], edges: list[PoseEdge], reference: int) -> dict[int, np.ndarray]:
    """Poses from the maximum-confidence spanning tree, composed outward from ``reference``."""
    count = max(component) + 1
    weights = lil_matrix((count, count))
    lookup: dict[tuple[int, int], PoseEdge] = {}
    for edge in edges:
        cost = 2.0 - edge.confidence  # > 0: higher confidence, cheaper
        if (edge.first, edge.second) not in lookup or cost < weights[edge.first, edge.second]:
            weights[edge.first, edge.second] = cost
            lookup[(edge.first, edge.second)] = edge
    tree = minimum_spanning_tree(weights.tocsr())
    tree = tree + tree.T
    order, predecessors = breadth_first_order(tree, reference, directed=False, return_predecessors=True)
    poses = {reference: np.eye(4)}
    for index in order[1:]:
        parent = int(predecessors[index])
        if (parent, index) in lookup:  # parent = first: P_index = P_parent @ T
            poses[int(index)] = poses[parent] @ lookup[(parent, index)].transformation
        else:  # parent = second: P_parent = P_index @ T, so P_index = P_parent @ inv(T)
            poses[int(index)] = poses[parent] @ np.linalg.inv(lookup[(index, parent)].transformation)
    return poses


def _solve(component, edges, centroids, radii, config: AlignConfig, reference: int) -> dict[int, np.ndarray]:
    """Robust least squares over the poses of ``component`` (``reference`` fixed at the identity).

    Each scan's frame is centred on its centroid (and the result frame on the reference's), so a
    pose's translation is where that scan's centroid lands, of the scene's size wherever the
    scans sit, and an edge's translation residual is its centroid's displacement.
    """
    from scipy.optimize import least_squares  # deferred: importing the package stays cheap

    initial = _initial_poses(component, edges, reference)
    free = [index for index in component if index != reference]
    slot = {index: k for k, index in enumerate(free)}

    def centre(index):  # scan frame, centred -> scan frame
        move = np.eye(4)
        move[:3, 3] = centroids[index]
        return move

    def uncentre(index):  # scan (or result) frame -> centred
        move = np.eye(4)
        move[:3, 3] = -centroids[index]
        return move

    x0 = np.concatenate([_to_vector(uncentre(reference) @ initial[index] @ centre(index)) for index in free])
    relative_inverse = [
        np.linalg.inv(uncentre(edge.first) @ edge.transformation @ centre(edge.second)) for edge in edges
    ]
    scales = np.array([np.sqrt(edge.confidence) / max(edge.inlier_rmse, 1e-9 * radii[edge.second]) for edge in edges])
    firsts = np.array([edge.first for edge in edges])
    seconds = np.array([edge.second for edge in edges])
    edge_radii = radii[seconds]

    def all_poses(x):
        stack = np.tile(np.eye(4), (max(component) + 1, 1, 1))
        if free:
            vectors = x.reshape(-1, 6)
            stack[free, :3, :3] = Rotation.from_rotvec(vectors[:, :3]).as_matrix()
            stack[free, :3, 3] = vectors[:, 3:]
        return stack

    def residuals(x):
        poses = all_poses(x)
        error = np.stack(relative_inverse) @ np.linalg.inv(poses[firsts]) @ poses[seconds]
        out = np.empty((len(edges), 6))
        out[:, :3] = Rotation.from_matrix(error[:, :3, :3]).as_rotvec() * edge_radii[:, None]
        out[:, 3:] = error[:, :3, 3]
        return (out * scales[:, None]).ravel()

    sparsity = lil_matrix((6 * len(edges), 6 * len(free)), dtype=int)
    for k, edge in enumerate(edges):
        for index in (edge.first, edge.second):
            if index != reference:
                sparsity[6 * k : 6 * k + 6, 6 * slot[index] : 6 * slot[index] + 6] = 1
    solution = least_squares(
        residuals, x0, jac_sparsity=sparsity, loss="soft_l1", f_scale=config.robust_scale, method="trf", x_scale="jac"
    )
    poses = {reference: np.eye(4)}
    for index in free:
        poses[index] = (
            centre(reference) @ _from_vector(solution.x[6 * slot[index] : 6 * slot[index] + 6]) @ uncentre(index)
        )
    return poses


def _with_residuals(edge: PoseEdge, poses: dict[int, np.ndarray], centroids: np.ndarray) -> PoseEdge:
    """``edge`` with how far the graph's poses disagree with it (degrees; user units at the
    centroid of scan ``second``)."""
    error = np.linalg.inv(edge.transformation) @ np.linalg.inv(poses[edge.first]) @ poses[edge.second]
    angle = float(np.degrees(np.linalg.norm(Rotation.from_matrix(error[:3, :3]).as_rotvec())))
    centre = centroids[edge.second]
    shift = float(np.linalg.norm(error[:3, :3] @ centre + error[:3, 3] - centre))
    return dataclasses.replace(edge, residual_rotation_deg=angle, residual_translation=shift)


def _to_vector(pose: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(pose[:3, :3]).as_rotvec(), pose[:3, 3]])


def _from_vector(vector: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(vector[:3]).as_matrix()
    pose[:3, 3] = vector[3:]
    return pose


# ---------------------------------------------------------------------------- merged cloud
def merge_scans(
    scans: Sequence, result: AlignmentResult, voxel_size: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The aligned scans as one voxel-thinned cloud (disconnected scans left out).

    Args:
        scans: the clouds given to :func:`align`, same order ((Ni, 3) arrays or paths).
        result: :func:`align`'s result.
        voxel_size: grid cell, user units; None = 1/500 of the merged cloud's bounding-box
            diagonal (a few hundred thousand points at most for a surface).

    Returns:
        (points, scan): (M, 3) float64 points in the reference scan's frame, and (M,) int32 the
        index of the scan each point came from.
    """
    clouds, _ = _load_scans(scans, result.names)
    parts, labels = [], []
    for index, (cloud, name) in enumerate(zip(clouds, result.names)):
        pose = result.poses.get(name)
        if pose is None:
            continue
        parts.append(cloud @ pose[:3, :3].T + pose[:3, 3])
        labels.append(np.full(len(cloud), index, dtype=np.int32))
    points, scan = np.concatenate(parts), np.concatenate(labels)
    if voxel_size is None:
        voxel_size = float(np.linalg.norm(np.ptp(points, axis=0))) / 500.0
    kept = voxel_downsample(points, voxel_size)
    return points[kept], scan[kept]


def write_merged(
    path: str | os.PathLike, scans: Sequence, result: AlignmentResult, voxel_size: float | None = None
) -> int:
    """Write :func:`merge_scans`'s cloud with a per-point ``scan`` index (any format
    :func:`~logdesc_rt.write_point_cloud` writes with attributes: PLY, PCD, XYZ/TXT/CSV, NPY,
    LAS/LAZ; ``logdesc_rt.io.ATTRIBUTE_SUFFIXES``).

    Returns:
        The number of points written.
    """
    points, scan = merge_scans(scans, result, voxel_size)
    write_point_cloud(path, points, attributes={"scan": scan})
    return len(points)


# ---------------------------------------------------------------------------- helpers
def _load_scans(scans: Sequence, names: Sequence[str] | None) -> tuple[list[np.ndarray], list[str]]:
    scans = list(scans)
    if len(scans) < 2:
        raise ValueError(f"align: needs at least 2 scans, got {len(scans)}")
    clouds, default_names = [], []
    for index, scan in enumerate(scans):
        # Files, meshes and Open3D clouds become (N, 3) points; arrays pass as they are.
        clouds.append(as_points(input_points(scan), name=os.fspath(scan) if isinstance(scan, (str, os.PathLike))
                                else f"scans[{index}]"))
        default_names.append(os.fspath(scan) if isinstance(scan, (str, os.PathLike)) else f"scan_{index:03d}")
    names = default_names if names is None else [str(name) for name in names]
    if len(names) != len(clouds):
        raise ValueError(f"names: {len(names)} names for {len(clouds)} scans")
    if len(set(names)) != len(names):
        raise ValueError("names: scan names must be unique")
    return clouds, names


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None

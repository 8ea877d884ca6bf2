"""ICP refinement on the full clouds, from the pose the learned pipeline estimated.

Point-to-point (closed-form SVD each iteration) or point-to-plane (linearised least squares
with target normals from a PCA of each target point's nearest neighbours). Correspondences
farther than ``max_distance`` are ignored.

Adaptive distance (``adaptive=True``, what :class:`~logdesc_rt.config.RefinementConfig` uses by
default): once ICP converges, the correspondence distance halves and ICP runs again, as long as
at least half of the inliers stay within the tighter distance and it stays above three times
the target's point spacing (median nearest-neighbour distance); at most four stages. On a real
scan pair with little overlap, a distance of 5 % of the radius lets points beside the overlap
pull the pose: on Stanford Bunny bun000 -> bun270 (about 25 % overlap) ICP started *at the
truth* drifts to 2.6 degrees with it, and stays within 0.3 degree at 1/4 of it. On noisy data,
where residuals fill the distance already, halving would drop most inliers and does not happen.

Placement and unit do not matter: ICP runs in a working frame where the target is centred on
its centroid and lengths are divided by ``max_distance``, and the point-to-plane step
linearises the rotation about the centroid of the current correspondences, not about the
origin. The result is mapped back to the user's frame exactly (a similarity), so two clouds
shifted by 1e5 m or given in millimetres instead of metres refine to the same pose
(``tests/test_refinement.py``). Linearising about the origin, as before, made a rotation of
the clouds 5 m away look like a huge translation and the step diverged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial.transform import Rotation

from .config import REFINEMENT_METHODS
from .pose import rigid_transform_svd
from .pose.evaluation import check_rigid_transformation
from .pose.kernels import (
    correspondence_plane_equations,
    motion_size,
    neighbourhood_normals,
    plane_normal_equations,
    plane_step,
)
from .pose.svd import solve_rigid_batch
from .sampling import seeded_subset
from .validation import as_points

ICP_METHODS = REFINEMENT_METHODS  # one home: logdesc_rt.config
NORMAL_NEIGHBOURS = 10  # target points whose covariance gives each target normal
MIN_CORRESPONDENCES = 6  # fewer and a step is not well determined
# Adaptive distance: each stage halves the correspondence distance, down to SPACING_MULTIPLE x
# the target's point spacing, while at least KEEP_SHARE of the current inliers stay inliers;
# at most MAX_STAGES stages.
SPACING_MULTIPLE = 3.0
KEEP_SHARE = 0.25
MAX_STAGES = 4
# ICP stops when its pose comes back (within the tolerance) to where it was up to this many
# updates before: a cycle, which further iterations only go round.
MAX_CYCLE = 4
_IDENTITY = np.eye(4)


@dataclass(frozen=True)
class IcpResult:
    """Refined pose and how ICP ended.

    Attributes:
        transformation: (4, 4) float64, source -> target, user frame.
        iterations: ICP iterations run.
        converged: the last update moved less than the tolerance, or brought the pose back to
            where it was a few updates before (a cycle); False when ICP stopped for lack of
            correspondences, or ran out of iterations.
        fitness: share of source points with a target point within ``max_distance`` under
            ``transformation``, in [0, 1].
        inlier_rmse: RMS distance of those pairs, the clouds' unit; NaN when there are none.
        stop_reason: "converged", "cycle" (the cycle above), "max_iterations" or
            "too_few_correspondences".
    """

    transformation: np.ndarray
    iterations: int
    converged: bool
    fitness: float
    inlier_rmse: float
    stop_reason: str

    def to_dict(self) -> dict:
        """JSON-friendly summary (NaN becomes None)."""
        return {
            "iterations": self.iterations,
            "converged": self.converged,
            "fitness": self.fitness,
            "inlier_rmse": None if np.isnan(self.inlier_rmse) else self.inlier_rmse,
            "stop_reason": self.stop_reason,
        }


def estimate_normals(
    points: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS, tree: KDTree | None = None,
    index: np.ndarray | None = None,
) -> np.ndarray:
    """(N, 3) unit normals: the least-variance axis of each point's ``neighbours`` nearest.

    Args:
        points: (N, 3) float64, N >= 3; centre and scale them first for accuracy far away
            from the origin (covariances are taken about each neighbourhood's mean anyway).
        neighbours: k, the point itself included (capped at N).
        tree: a k-d tree of ``points`` the caller already has (built here otherwise).
        index: (K,) int, the points whose normals are wanted (each computed as it would be
            among all); None: all of them.

    Returns:
        (N, 3) (or (K, 3)) float64 unit vectors; their sign is arbitrary (point-to-plane does
        not care).
    """
    tree = KDTree(points) if tree is None else tree
    return LazyNormals(points, tree, neighbours).at(np.arange(len(points)) if index is None else np.asarray(index))


def refine_pose(source, target, initial: np.ndarray, max_distance: float, config) -> IcpResult:
    """:func:`icp` as ``register(refine=...)`` runs it: the method, limits, adaptive stages and
    source subset of a :class:`~logdesc_rt.config.RefinementConfig` whose method is set."""
    if config.method is None:
        raise ValueError("refine_pose: the refinement config has no method")
    return icp(
        source,
        target,
        initial,
        max_distance,
        method=config.method,
        max_iterations=config.max_iterations,
        tolerance=config.tolerance,
        adaptive=config.adaptive,
        max_source_points=config.max_source_points,
        coarse_source_points=config.coarse_source_points,
        seed=config.seed,
    )


class LazyNormals:
    """:func:`estimate_normals` of a cloud, computed only for the points asked for, once each.

    ICP on a large target meets a fraction of its points; the PCA of all of them cost most of
    a 200k-point refinement. Each normal is computed exactly as ``estimate_normals`` computes it
    (same tree, same neighbours, same covariance): asking for all points gives its result.
    Normals do not change with a translation or a uniform scale of the cloud, so one instance
    serves :func:`icp` in its working frame as well.

    Args:
        points: (N, 3) float64 cloud.
        tree: a k-d tree of ``points``.
        neighbours: k, the point itself included (capped at N).
    """

    def __init__(self, points: np.ndarray, tree: KDTree, neighbours: int = NORMAL_NEIGHBOURS):
        self.points, self.tree = points, tree
        self.neighbours = int(min(max(neighbours, 3), len(points)))
        self.normals = np.zeros((len(points), 3))
        self.known = np.zeros(len(points), dtype=bool)
        self.complete = False  # every normal known: nothing left to look up

    def at(self, index: np.ndarray) -> np.ndarray:
        """(K, 3) normals of the points ``index`` (K,) int."""
        self._compute(index)
        return self.normals[index]

    def covering(self, index: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """(M, 3) the normals of every point, computed at least where a k-d tree query's
        ``index`` (N,) int pairs a point (a finite ``distance`` (N,))."""
        self._compute(index[np.isfinite(distance)])
        return self.normals

    def _compute(self, index: np.ndarray) -> None:
        if self.complete:
            return
        missing = np.unique(index[~self.known[index]])
        if len(missing):
            k = self.neighbours
            _, neighbour_index = self.tree.query(self.points[missing], k=k)
            self.normals[missing] = neighbourhood_normals(
                np.ascontiguousarray(self.points, dtype=np.float64),
                neighbour_index.reshape(len(missing), k).astype(np.int64),
            )
            self.known[missing] = True
            self.complete = bool(self.known.all())


def icp(
    source,
    target,
    initial: np.ndarray,
    max_distance: float,
    method: str = "point_to_plane",
    max_iterations: int = 30,
    tolerance: float = 1e-7,
    adaptive: bool = False,
    target_normals: np.ndarray | LazyNormals | None = None,
    target_spacing: float | None = None,
    max_source_points: int | None = None,
    coarse_source_points: int | None = None,
    seed: int = 0,
) -> IcpResult:
    """Refine ``initial`` by iterative closest points.

    Args:
        source: (N, 3) points, any unit and placement, N >= 1.
        target: (M, 3) points, same unit, M >= 3.
        initial: (4, 4) rigid starting pose, source -> target.
        max_distance: > 0, correspondences farther than this are dropped (clouds' unit).
        method: "point_to_point" or "point_to_plane".
        max_iterations: upper bound on iterations (>= 1), per stage.
        tolerance: stop when an update's rotation (radians) plus translation (as a fraction of
            ``max_distance``) is below this.
        adaptive: after convergence, halve the distance and run again while the inliers hold
            (module docstring); at most 4 stages.
        target_normals: (M, 3) unit normals of ``target`` for point-to-plane, if the caller
            has them (verification refines several poses against one target), or a
            :class:`LazyNormals` of ``target`` (computed where ICP meets it, kept for the
            caller); else estimated here as :func:`estimate_normals` would, for the target
            points ICP meets only.
        target_spacing: the median nearest-neighbour distance among all ``target`` points,
            the clouds' unit, when the caller has it (the adaptive stages' floor; with
            ``max_source_points`` None it is what ICP would compute).
        max_source_points: iterate on a seeded uniform subset of at most this many source
            points (None: all). Its correspondences pull the pose as the whole cloud's do, at a
            fraction of the cost of a large cloud; the target is used whole. The adaptive
            stages read the target's point spacing from as many of its points.
        coarse_source_points: with ``adaptive``, the stages iterate on a seeded subset of at
            most this many of those source points, and one more stage at the last stage's
            distance then polishes the pose on all of them (None: every stage on all). The
            stages only bring the pose near the fixed point of the last distance, which the
            polish reaches from there in a few iterations: on 40k-300k-point pairs about two
            thirds of the time, for the same pose within ICP's tolerance.
        seed: seeds those subsets.

    Returns:
        :class:`IcpResult`; its fitness and inlier RMSE are those of the returned pose at
        ``max_distance`` (whatever distance the last stage used), over the seeded subset of
        ``max_source_points`` (all the source points ICP's last stage iterated on);
        ``iterations`` counts all stages.

    Raises:
        ValueError: unknown method, ``max_distance`` not > 0, ``initial`` not a rigid (4, 4)
            transform, or ``max_iterations`` < 1.
        InvalidPointCloudError (and subclasses): bad clouds.
    """
    if method not in ICP_METHODS:
        raise ValueError(f"refinement method {method!r}: expected one of {ICP_METHODS}")
    max_distance = float(max_distance)
    if not (np.isfinite(max_distance) and max_distance > 0):
        raise ValueError(f"max_distance: {max_distance} must be finite and > 0")
    if max_iterations < 1:
        raise ValueError(f"max_iterations: {max_iterations} must be >= 1")
    for name, count in (("max_source_points", max_source_points), ("coarse_source_points", coarse_source_points)):
        if count is not None and count < MIN_CORRESPONDENCES:
            raise ValueError(f"{name}: {count} must be None or >= {MIN_CORRESPONDENCES}")
    source = as_points(source, name="source", min_points=1)
    target = as_points(target, name="target", min_points=3)
    initial = check_rigid_transformation(initial, name="initial")
    generator = np.random.default_rng(seed)
    source = source[seeded_subset(len(source), max_source_points, generator)]

    # Working frame: x_w = (x - centre) / unit, the same similarity for both clouds.
    centre = target.mean(axis=0)
    unit = max_distance
    to_working = np.eye(4)
    to_working[:3, :3] /= unit
    to_working[:3, 3] = -centre / unit
    from_working = np.eye(4)
    from_working[:3, :3] *= unit
    from_working[:3, 3] = centre
    source_working = (source - centre) / unit
    target_working = (target - centre) / unit
    tree = KDTree(target_working)
    normals = None
    if method == "point_to_plane":
        if target_normals is None:
            normals = LazyNormals(target_working, tree)
        elif isinstance(target_normals, LazyNormals):
            if len(target_normals.points) != len(target):
                raise ValueError(
                    f"target_normals: normals of {len(target_normals.points)} points, expected {len(target)}"
                )
            normals = target_normals
        else:
            given = np.asarray(target_normals, dtype=np.float64)
            if given.shape != target.shape:
                raise ValueError(f"target_normals: shape {given.shape}, expected {target.shape}")
            normals = _GivenNormals(given)

    pose = to_working @ initial @ from_working
    floor = 0.0
    if adaptive and target_spacing is not None:
        floor = SPACING_MULTIPLE * float(target_spacing) / unit
    elif adaptive:
        spaced = target_working[seeded_subset(len(target_working), max_source_points, generator)]
        spacing, _ = tree.query(spaced, k=2)
        floor = SPACING_MULTIPLE * float(np.median(spacing[:, 1]))
    # The stages' source points: a coarse subset when one is asked for and smaller (see above).
    staged = source_working
    if adaptive and coarse_source_points is not None and coarse_source_points < len(source_working):
        staged = source_working[seeded_subset(len(source_working), coarse_source_points, generator)]
    stage_distance, iterations, stop_reason = 1.0, 0, "max_iterations"
    for _ in range(MAX_STAGES if adaptive else 1):
        last_distance = stage_distance
        pose, used, stop_reason = _icp_stage(
            staged, target_working, tree, normals, pose, stage_distance, max_iterations, tolerance
        )
        iterations += used
        if stop_reason == "too_few_correspondences" or stage_distance / 2 < floor:
            break
        distance, _ = tree.query(staged @ pose[:3, :3].T + pose[:3, 3], k=1, distance_upper_bound=stage_distance)
        inliers = np.count_nonzero(np.isfinite(distance))
        if np.count_nonzero(distance < stage_distance / 2) < KEEP_SHARE * inliers:
            break
        stage_distance /= 2
    if staged is not source_working and stop_reason != "too_few_correspondences":
        pose, used, stop_reason = _icp_stage(
            source_working, target_working, tree, normals, pose, last_distance, max_iterations, tolerance
        )
        iterations += used

    moved = source_working @ pose[:3, :3].T + pose[:3, 3]
    distance, _ = tree.query(moved, k=1, distance_upper_bound=1.0)
    inliers = distance[np.isfinite(distance)]
    rmse = float(np.sqrt(np.mean(inliers**2)) * unit) if inliers.size else float("nan")
    # Re-orthonormalise the rotation block, which repeated products drift by ~1e-16 each.
    result = from_working @ pose @ to_working
    result[:3, :3] = Rotation.from_matrix(result[:3, :3]).as_matrix()
    result[3] = [0.0, 0.0, 0.0, 1.0]
    return IcpResult(
        transformation=result,
        iterations=iterations,
        converged=stop_reason in ("converged", "cycle"),
        fitness=inliers.size / len(source),
        inlier_rmse=rmse,
        stop_reason=stop_reason,
    )


class _GivenNormals:
    """Normals the caller computed, read like :class:`LazyNormals`."""

    def __init__(self, normals: np.ndarray):
        self.normals = np.ascontiguousarray(normals, dtype=np.float64)

    def at(self, index: np.ndarray) -> np.ndarray:
        return self.normals[index]

    def covering(self, index: np.ndarray, distance: np.ndarray) -> np.ndarray:
        return self.normals


def _icp_stage(
    source: np.ndarray,
    target: np.ndarray,
    tree: KDTree,
    normals: LazyNormals | _GivenNormals | None,
    pose: np.ndarray,
    max_distance: float,
    max_iterations: int,
    tolerance: float,
) -> tuple[np.ndarray, int, str]:
    """ICP iterations at one correspondence distance (working frame); (pose, iterations, why it stopped)."""
    recent = [pose]  # this stage's latest MAX_CYCLE poses, the current one last
    for iteration in range(1, max_iterations + 1):
        moved = source @ pose[:3, :3].T + pose[:3, 3]
        distance, index = tree.query(moved, k=1, distance_upper_bound=max_distance)
        if normals is None:
            close = np.isfinite(distance)
            if np.count_nonzero(close) < MIN_CORRESPONDENCES:
                return pose, iteration - 1, "too_few_correspondences"
            step = rigid_transform_svd(moved[close], target[index[close]])
        else:
            # The pairs' normal equations straight from the query (no gathered copies of them).
            index = index.astype(np.int64, copy=False)
            matrix, rhs, pivot, pairs = correspondence_plane_equations(
                moved, target, normals.covering(index, distance), index, distance
            )
            if pairs < MIN_CORRESPONDENCES:
                return pose, iteration - 1, "too_few_correspondences"
            step = plane_step(matrix, rhs, pivot)
        pose = step @ pose
        if motion_size(step, _IDENTITY, max_distance) < tolerance:
            return pose, iteration, "converged"
        # A cycle: the correspondences come back to a set they had, and so does the pose; further
        # iterations only go round. On the real bun000 -> bun045 pair, stages on source subsets
        # alternated between two (or three) poses ~5e-6 apart for 25 of their 30 iterations,
        # the pose returning to within 1e-15 of itself.
        if any(motion_size(pose, earlier, max_distance) < tolerance for earlier in recent[:-1]):
            return pose, iteration, "cycle"  # back to where it was 2 ... MAX_CYCLE updates ago
        recent = [*recent, pose][-MAX_CYCLE:]
    return pose, max_iterations, "max_iterations"


def plane_fit_step(
    source: np.ndarray,
    target: np.ndarray,
    normals: np.ndarray,
    weights: np.ndarray | None = None,
    point_weight: float = 0.0,
) -> np.ndarray:
    """One linearised point-to-plane update, (4, 4), for (K, 3) pairs and target normals.

    Minimises sum_k w_k [((R (p_k - c) + c + t - q_k) . n_k)^2 + point_weight |R (p_k - c) + c
    + t - q_k|^2] with R = I + [w]x about c, the centroid of the p_k: the small-angle
    approximation is then accurate wherever the clouds sit, since |p_k - c| is the size of the
    overlap, not the distance to the origin. ICP uses the plain form (equal weights, no point
    term); :func:`~logdesc_rt.pose_selection.coarse_pose` the weighted one on learned matches,
    where the point term keeps the sliding directions of a flat patch determined. A point term
    is the plane term with the three axes as normals, so both share one Jacobian form.

    Args:
        source, target: (K, 3) float64 paired points, the same unit.
        normals: (K, 3) unit target normals (sign free).
        weights: (K,) non-negative pair weights, or None for equal weights.
        point_weight: lambda >= 0, the point-to-point term's weight relative to the plane's.
    """
    pivot = source.mean(axis=0)
    arm = source - pivot
    offset = target - source
    matrix, rhs = _normal_equations(arm, offset, normals, weights)
    if point_weight > 0.0:
        point_weights = point_weight * (np.ones(len(source)) if weights is None else np.asarray(weights))
        for axis in np.eye(3):
            axis_matrix, axis_rhs = _normal_equations(arm, offset, np.broadcast_to(axis, arm.shape), point_weights)
            matrix, rhs = matrix + axis_matrix, rhs + axis_rhs
    return plane_step(matrix, rhs, pivot)


def _normal_equations(
    arm: np.ndarray, offset: np.ndarray, directions: np.ndarray, weights: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """(6, 6) and (6,) normal equations of the residuals ``offset . d_k`` along one direction
    per pair, linearised in (rotation about the pivot, translation): rows [arm_k x d_k, d_k].
    The 6 x 6 form, not a K x 6 lstsq, accumulated in one compiled pass
    (:func:`~logdesc_rt.pose.kernels.plane_normal_equations`)."""
    weights = np.ones(len(arm)) if weights is None else np.asarray(weights, dtype=np.float64)
    return plane_normal_equations(
        np.ascontiguousarray(arm, dtype=np.float64), np.ascontiguousarray(offset, dtype=np.float64),
        np.ascontiguousarray(directions, dtype=np.float64), np.ascontiguousarray(weights),
    )


def point_to_point_icp_batch(
    source: np.ndarray, target_tree: KDTree, target: np.ndarray, initial: np.ndarray, max_distance: float,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """A few point-to-point ICP iterations of several poses at once: a cheap screen of starts.

    All poses share one k-d tree query and one batched SVD per iteration, so screening a handful
    of starting poses costs about one iteration of :func:`icp` each. There is no convergence
    test nor adaptive stage; poses whose correspondences fall below ``MIN_CORRESPONDENCES`` stay
    where they are.

    Args:
        source: (N, 3) float64 source points (a few hundred suffice).
        target_tree: k-d tree of ``target``.
        target: (M, 3) float64 target points.
        initial: (P, 4, 4) starting poses, source -> target.
        max_distance: correspondences farther than this are dropped (the clouds' unit).
        iterations: how many iterations, >= 0.

    Returns:
        ((P, 4, 4) float64 poses, (P,) float64 fitness: the share of ``source`` within
        ``max_distance`` of the target after each pose).
    """
    poses = np.array(initial, dtype=np.float64)
    count, size = len(poses), len(source)
    for iteration in range(iterations + 1):
        moved = source @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]  # (P, N, 3)
        distance, index = target_tree.query(moved.reshape(-1, 3), k=1, distance_upper_bound=max_distance)
        close = np.isfinite(distance).reshape(count, size)
        fitness = close.mean(axis=1)
        if iteration == iterations:
            break
        usable = close.sum(axis=1) >= MIN_CORRESPONDENCES
        matched = target[np.minimum(index, len(target) - 1)].reshape(count, size, 3)
        # One weighted Kabsch per usable pose (far points weigh 0): moved -> matched.
        rotation, translation, _ = solve_rigid_batch(
            moved[usable], matched[usable], close[usable].astype(np.float64), check_degenerate=False
        )
        step = np.tile(np.eye(4), (count, 1, 1))
        step[usable, :3, :3] = rotation
        step[usable, :3, 3] = translation
        poses = step @ poses
    return poses, fitness

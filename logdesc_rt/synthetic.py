"""Synthetic registration pairs with ground truth: the paper's protocol (after PRNet).

Used by training (:mod:`training.data`), the demo, the tests and the benchmarks, so that all
of them build pairs the same way. Pure NumPy/SciPy.

Protocol (../shared/data/README.md): source = the first 1024 points of a shape; target = the
same points rotated by Euler angles uniform in [0, 45] degrees per axis (scipy ``"zyx"``, as
DCP/PRNet) and translated uniformly in [-0.5, 0.5] per axis; both randomly permuted;
"noisy" adds N(0, 0.01^2) noise clipped to +-0.05 to every coordinate of both clouds;
"partial" adds the noise and keeps, independently in each cloud, the 768 points nearest to a
far point. Ground-truth correspondences are known by construction.

Beyond the paper: in its pairs both clouds hold the *same* samples of the surface (up to
noise), which real scan pairs never do; a network can learn to rely on it. The resampled
protocols split the shape's points at random into two disjoint halves, one per cloud, so no
point has a twin ("resampled": noise as "noisy"; "resampled_partial": also the crop). Their
correspondences come from geometry, as for real scans (SuperGlue's labelling): mutual nearest
neighbours (noise-free positions, one frame) closer than ``MATCH_RADIUS_SPACINGS`` x the
local point spacing are matches; a point with nothing of the other cloud within
``UNMATCHED_RADIUS_SPACINGS`` x spacing has no counterpart (-1); the rest are ``IGNORED``
(-2): near a counterpart, but not one-to-one, so neither label would be true. The spacing is
local (ModelNet's samples are not uniform: within one shape the nearest-neighbour distance
varies fourfold): a point's distance to its third nearest neighbour in the whole shape.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial.transform import Rotation

from .config import NormalizationConfig
from .metrics import IGNORED
from .normalization import PairNormalization
from .sampling import farthest_point_sampling, working_subset

PAPER_PROTOCOLS: tuple[str, ...] = ("clean", "noisy", "partial")
RESAMPLED_PROTOCOLS: tuple[str, ...] = ("resampled", "resampled_partial")
PROTOCOLS: tuple[str, ...] = PAPER_PROTOCOLS + RESAMPLED_PROTOCOLS
SOURCE_POINTS = 1024  # PRNet: the source is the first 1024 points of a shape
PARTIAL_FRACTION = 0.75  # 768 of 1024 points survive the partial crop
MAX_ANGLE_DEG = 45.0
MAX_TRANSLATION = 0.5
NOISE_SIGMA = 0.01
NOISE_CLIP = 0.05
FAR_POINT_DISTANCE = 500.0
# Upper bound of ||T_gt(x_i) - y_j|| for a ground-truth pair under noise: each cloud's noise
# is at most NOISE_CLIP per coordinate, i.e. NOISE_CLIP*sqrt(3) in norm, and a rotation keeps
# norms, so the two noises add up to at most twice that.
NOISE_BOUND = 2.0 * NOISE_CLIP * math.sqrt(3.0)
# Resampled pairs' labels, in units of a point's local spacing in the shape (the distance to its
# SPACING_NEIGHBOUR-th nearest neighbour): on ModelNet shapes about half the points of a
# resampled pair get a match, and almost none of an uncropped pair count as without counterpart.
SPACING_NEIGHBOUR = 3
MATCH_RADIUS_SPACINGS = 1.5
UNMATCHED_RADIUS_SPACINGS = 3.0


@dataclass(frozen=True)
class Pair:
    """A registration pair with its ground truth in the user and in the network frame.

    Attributes:
        protocol: one of :data:`PROTOCOLS`.
        source: (N, 3) float64 source points, user frame (dataset units, unit sphere).
        target: (M, 3) float64 target points, user frame.
        T_gt: (4, 4) float64 user-frame pose mapping source onto target: y = R x + t.
        gt_match_src: (N,) int64, index of the source point's counterpart in ``target``, -1 if
            it has none (cropped away in the target), ``IGNORED`` (-2, resampled protocols
            only) if it is unlabelled.
        gt_match_tgt: (M,) int64, the inverse map (index into ``source``, -1 or -2); the
            matches are one-to-one.
        normalization: the runtime's similarity transforms of this pair.
        source_network: (N, 3) float64 source in network units.
        target_network: (M, 3) float64 target in network units.
        T_gt_network: (4, 4) float64 pose between the network-frame clouds.
        euler_zyx_deg: (3,) float64 the drawn angles (z, y, x), degrees (the paper's motion:
            without ``make_pair``'s ``any_relative_rotation`` turn).
        shape_to_source: (4, 4) float64 pose placing the complete shape the pair was drawn from
            in the source's user frame (simulated scans, :mod:`logdesc_rt.scan_simulation`), so
            that an estimate can be judged on the whole object
            (:func:`~logdesc_rt.metrics.twin_distance`); None for the other protocols.
    """

    protocol: str
    source: np.ndarray
    target: np.ndarray
    T_gt: np.ndarray
    gt_match_src: np.ndarray
    gt_match_tgt: np.ndarray
    normalization: PairNormalization
    source_network: np.ndarray
    target_network: np.ndarray
    T_gt_network: np.ndarray
    euler_zyx_deg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    shape_to_source: np.ndarray | None = None


def pair_in_network_frame(
    protocol: str,
    source: np.ndarray,
    target: np.ndarray,
    pose: np.ndarray,
    gt_match_src: np.ndarray,
    gt_match_tgt: np.ndarray,
    normalization_config: NormalizationConfig,
    euler_zyx_deg: np.ndarray,
    shape_to_source: np.ndarray | None = None,
) -> Pair:
    """A :class:`Pair` from user-frame clouds, pose and labels: the runtime's normalisation is
    fitted to the clouds, and the network-frame clouds and pose are derived from it (every
    protocol, the simulated scans' too, builds its pair here)."""
    normalization = PairNormalization.fit(source, target, normalization_config)
    return Pair(
        protocol=protocol,
        source=source,
        target=target,
        T_gt=pose,
        gt_match_src=gt_match_src,
        gt_match_tgt=gt_match_tgt,
        normalization=normalization,
        source_network=normalization.source_to_network(source),
        target_network=normalization.target_to_network(target),
        T_gt_network=normalization.pose_to_network_frame(pose),
        euler_zyx_deg=euler_zyx_deg,
        shape_to_source=shape_to_source,
    )


def partial_keep(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices (ascending) of the ``count`` points nearest to a far point (PRNet's crop).

    The far point is a random sign times (500, 500, 500) plus a U[0, 1)^3 jitter, so the cut
    is close to a plane normal to (1, 1, 1). The kept indices are returned in ascending order
    rather than PRNet's distance order, so the cloud stays randomly ordered (its order came
    from a random permutation) instead of sorted along the cut direction.
    """
    sign = rng.choice([-1.0, 1.0])
    far_point = sign * FAR_POINT_DISTANCE + rng.random(3)
    distance = np.sum((points - far_point) ** 2, axis=1)
    return np.sort(np.argsort(distance, kind="stable")[:count])


def resampled_correspondences(
    base: np.ndarray, source_origin: np.ndarray, target_origin: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Labels of two clouds that sample one shape at different points (module docstring).

    Args:
        base: (P, 3) the shape's points (noise-free, one frame).
        source_origin: (N,) int64 the base point at each source position.
        target_origin: (M,) int64 the base point at each target position.

    Returns:
        (gt_match_src (N,), gt_match_tgt (M,)) int64: the counterpart's position, -1 (none
        within ``UNMATCHED_RADIUS_SPACINGS`` spacings) or ``IGNORED``; matches are mutual
        nearest neighbours within ``MATCH_RADIUS_SPACINGS`` spacings, so one-to-one.
    """
    base_distance, _ = KDTree(base).query(base, k=SPACING_NEIGHBOUR + 1)
    spacing = base_distance[:, SPACING_NEIGHBOUR]  # (P,) local spacing of every base point
    source_spacing, target_spacing = spacing[source_origin], spacing[target_origin]
    source_points, target_points = base[source_origin], base[target_origin]
    to_target, nearest_target = KDTree(target_points).query(source_points, k=1)
    to_source, nearest_source = KDTree(source_points).query(target_points, k=1)
    nearest_target, nearest_source = nearest_target.astype(np.int64), nearest_source.astype(np.int64)

    gt_match_src = np.full(len(source_points), IGNORED, dtype=np.int64)
    gt_match_tgt = np.full(len(target_points), IGNORED, dtype=np.int64)
    gt_match_src[to_target >= UNMATCHED_RADIUS_SPACINGS * source_spacing] = -1
    gt_match_tgt[to_source >= UNMATCHED_RADIUS_SPACINGS * target_spacing] = -1
    mutual = (nearest_source[nearest_target] == np.arange(len(source_points))) & (
        to_target < MATCH_RADIUS_SPACINGS * source_spacing
    )
    matched_sources = np.flatnonzero(mutual)
    gt_match_src[matched_sources] = nearest_target[matched_sources]
    gt_match_tgt[nearest_target[matched_sources]] = matched_sources
    return gt_match_src, gt_match_tgt


def _exact_working_subset(points: np.ndarray, count: int, normalization_config: NormalizationConfig) -> np.ndarray:
    """The runtime's working subset of ``points``, exactly ``count`` of them (training stacks
    clouds of one size): farthest-point sampling of the whole cloud when setting strays aside
    leaves fewer."""
    keep = working_subset(points, count, "fps", normalization_config)
    if len(keep) == count:
        return keep
    return np.sort(farthest_point_sampling(points, count)).astype(np.int64)


def make_pair(
    shape_points,
    protocol: str,
    rng: np.random.Generator,
    *,
    points_per_cloud: int | None = None,
    partial_points: int | None = None,
    normalization_config: NormalizationConfig = NormalizationConfig(),
    any_orientation: bool = False,
    any_relative_rotation: bool = False,
    working_size: int | None = None,
) -> Pair:
    """Build one registration pair from a shape (PRNet / LoGDesc protocol).

    Draw order (fixed, so that one seed gives the same motion under every protocol): the three
    angles, the translation, the optional point subset, the split into halves (resampled
    protocols only), the two permutations, the noise of the source, the noise of the target,
    the source crop, the target crop, the optional whole-pair rotation, and last the optional
    turn of the target alone (so a seed gives the same pair with or without either, only
    turned).

    Args:
        shape_points: (P, 3) points of one shape, P >= 1024 (or >= ``points_per_cloud``).
        protocol: ``"clean"``; ``"noisy"`` (independent N(0, 0.01^2) noise clipped to
            [-0.05, 0.05] on every coordinate of both clouds); ``"partial"`` (noise as in
            ``"noisy"`` plus, independently in each cloud, keeping the points nearest to a far
            point; the paper's noisy-partial protocol); ``"resampled"`` / ``"resampled_partial"``
            (as ``"noisy"`` / ``"partial"``, but each cloud holds its own half of the points:
            module docstring).
        rng: the generator all randomness comes from.
        points_per_cloud: optionally use a random subset of this many of the 1024 source
            points before building the pair (faster training); None keeps all 1024.
        partial_points: points kept by the partial crop; default ``round(0.75 * n)`` (768 of
            1024, PRNet).
        normalization_config: the network frame (the runtime's default unless overridden).
        any_orientation: turn both clouds by one uniformly random rotation G at the end. The
            paper's protocol leaves the source in the dataset's canonical pose, which a
            network can learn to rely on; users' scans arrive in any frame. The relative
            motion keeps its size; its matrix becomes G T G^T.
        any_relative_rotation: then turn the target alone about its centroid by a uniformly
            random rotation, so the relative rotation is of any size, as between scans taken
            from anywhere (the paper's motion stays at most 45 degrees per axis). Labels are
            unchanged; ``euler_zyx_deg`` still gives the drawn angles, before this turn.
        working_size: cut each cloud larger than this to exactly this many points with the
            runtime's working subset (:func:`~logdesc_rt.sampling.working_subset`: stray points
            set aside, farthest-point sampling), each cloud on its own, as ``register`` does;
            the labels then come from geometry (:func:`resampled_correspondences` on the
            noise-free positions), since a point's twin may not survive the other cloud's cut.
            None: no cut, labels by twin index.

    Returns:
        :class:`Pair`. Clean and noisy pairs have N = M = n points, partial ones
        ``partial_points`` each; resampled ones n // 2 (and the crop keeps 75 % of that, or
        ``partial_points``).
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; expected one of {PROTOCOLS}")
    shape_points = np.asarray(shape_points, dtype=np.float64)
    if shape_points.ndim != 2 or shape_points.shape[1] != 3 or len(shape_points) < SOURCE_POINTS:
        raise ValueError(
            f"shape_points must be (P >= {SOURCE_POINTS}, 3), got {shape_points.shape}"
        )
    base = shape_points[:SOURCE_POINTS]

    # DCP/PRNet: angles uniform in [0, pi/4] per axis, R = Rx Ry Rz = scipy "zyx" extrinsic.
    angles_xyz = rng.uniform(0.0, math.radians(MAX_ANGLE_DEG), size=3)
    rotation = Rotation.from_euler("zyx", angles_xyz[::-1]).as_matrix()
    translation = rng.uniform(-MAX_TRANSLATION, MAX_TRANSLATION, size=3)

    if points_per_cloud is not None and points_per_cloud != SOURCE_POINTS:
        if not 1 <= points_per_cloud <= SOURCE_POINTS:
            raise ValueError(f"points_per_cloud must be in [1, {SOURCE_POINTS}], got {points_per_cloud}")
        base = base[np.sort(rng.choice(SOURCE_POINTS, size=points_per_cloud, replace=False))]
    count = len(base)

    resampled = protocol in RESAMPLED_PROTOCOLS
    if resampled:  # each cloud its own half of the shape's points: no point has a twin
        halves = rng.permutation(count)
        source_members, target_members = halves[: count // 2], halves[count // 2 : 2 * (count // 2)]
    else:
        source_members = target_members = np.arange(count)
    source = base.copy()
    target = base @ rotation.T + translation
    # origin[k] = index into `base` of the point now at position k.
    source_origin = source_members[rng.permutation(len(source_members))]
    target_origin = target_members[rng.permutation(len(target_members))]
    if protocol != "clean":
        source = source + np.clip(rng.normal(0.0, NOISE_SIGMA, size=(count, 3)), -NOISE_CLIP, NOISE_CLIP)
        target = target + np.clip(rng.normal(0.0, NOISE_SIGMA, size=(count, 3)), -NOISE_CLIP, NOISE_CLIP)
    source, target = source[source_origin], target[target_origin]

    if protocol in ("partial", "resampled_partial"):
        cloud_count = len(source_origin)
        keep = round(PARTIAL_FRACTION * cloud_count) if partial_points is None else int(partial_points)
        if not 3 <= keep <= cloud_count:
            raise ValueError(f"partial_points must be in [3, {cloud_count}], got {keep}")
        source_keep = partial_keep(source, keep, rng)
        target_keep = partial_keep(target, keep, rng)
        source, source_origin = source[source_keep], source_origin[source_keep]
        target, target_origin = target[target_keep], target_origin[target_keep]

    cut = working_size is not None and max(len(source), len(target)) > working_size
    if cut:
        if len(source) > working_size:
            source_keep = _exact_working_subset(source, working_size, normalization_config)
            source, source_origin = source[source_keep], source_origin[source_keep]
        if len(target) > working_size:
            target_keep = _exact_working_subset(target, working_size, normalization_config)
            target, target_origin = target[target_keep], target_origin[target_keep]

    if resampled or cut:
        gt_match_src, gt_match_tgt = resampled_correspondences(base, source_origin, target_origin)
    else:  # by origin index: position of each base point in either cloud (or -1)
        target_position = np.full(count, -1, dtype=np.int64)
        target_position[target_origin] = np.arange(len(target_origin))
        source_position = np.full(count, -1, dtype=np.int64)
        source_position[source_origin] = np.arange(len(source_origin))
        gt_match_src = target_position[source_origin]
        gt_match_tgt = source_position[target_origin]

    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = translation
    if any_orientation:
        turn = np.eye(4)
        turn[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        source, target = source @ turn[:3, :3].T, target @ turn[:3, :3].T
        pose = turn @ pose @ turn.T
    if any_relative_rotation:
        relative_turn = np.eye(4)
        relative_turn[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        centre = target.mean(axis=0)
        relative_turn[:3, 3] = centre - relative_turn[:3, :3] @ centre
        target = target @ relative_turn[:3, :3].T + relative_turn[:3, 3]
        pose = relative_turn @ pose
    return pair_in_network_frame(
        protocol, source, target, pose, gt_match_src, gt_match_tgt, normalization_config,
        np.degrees(angles_xyz[::-1]),
    )

"""Simulated range-scan pairs: two views of one dense shape, each from its own samples.

The paper's pairs (:mod:`.synthetic`) crop one sampling of a whole shape by a plane, so both
clouds see most of the object and share their samples. A range scan sees only the side that faces
its sensor, two scans see different sides, and no two scans share a sample. A pair here:

1. **Separate samples.** The dense shape's points (P of them, e.g. 10,000 with normals) are split
   at random into two disjoint halves, one per view.
2. **Two sensors.** The first looks at the shape's centre from a direction uniform on the sphere;
   the second from a direction ``view_angle_deg`` (uniform in ``VIEW_ANGLE_DEG``) away from it,
   about a random axis. Each stands ``RANGE_RADII`` object radii from the centre (uniform).
3. **Visibility** by hidden-point removal (Katz, Tal & Basri 2007): in the sensor's frame every
   point p is flipped about a sphere of radius R, p' = p + 2 (R - |p|) p / |p|, and the points on
   the convex hull of the flipped set and the sensor are the visible ones. R = |p|max * 10^gamma,
   gamma drawn in ``HPR_LOG_RADIUS`` (smaller gamma hides more).
4. **Density** that falls with incidence and range: a visible point is kept with probability
   ``(floor + (1 - floor) |cos(incidence)|) * (nearest range / range)^2`` (the normal's sign does
   not matter), so grazing surfaces and the far side of the object are thinner.
5. **Noise along the ray**, sigma proportional to the range (``RAY_NOISE`` at the nearest range),
   plus a little across it.
6. **Stray points and outliers**: with probability ``STRAY_PROBABILITY`` a view gets one to three
   returns 2 to 30 radii away, and a share (uniform up to ``MAX_BOX_OUTLIER_FRACTION``) of points
   uniform in its bounding box grown by half.
7. **The runtime's working subset** (:func:`~logdesc_rt.sampling.working_subset`: stray points
   set aside, farthest-point sampling to ``points_per_cloud``), so the network trains on exactly
   what the runtime would feed it from such a scan.
8. **Any pose**: each view is turned by its own uniform random rotation (the relative rotation is of
   any size) and shifted.

Ground truth comes from geometry, as for real scans: :func:`.synthetic.resampled_correspondences`
on the noise-free positions of both working subsets (mutual nearest neighbours within 1.5 local
spacings are matches, nothing within 3 spacings means no counterpart, the rest are ignored).
Outliers and stray points have no counterpart. Overlap (the share of the source's points with a
match) spans about 20 to 95 %. Every draw comes from the one generator passed in.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from .config import NormalizationConfig
from .sampling import working_subset
from .synthetic import Pair, pair_in_network_frame, resampled_correspondences

SCAN_PROTOCOL = "scan"
VIEW_ANGLE_DEG = (15.0, 90.0)  # angle between the two sensors' directions, seen from the centre
RANGE_RADII = (2.5, 6.0)  # sensor distance from the shape's centre, object radii
HPR_LOG_RADIUS = (2.0, 3.5)  # gamma of the flipping sphere's radius
INCIDENCE_FLOOR = 0.25  # keep probability at grazing incidence (relative to head-on)
RAY_NOISE = (0.002, 0.012)  # sigma along the ray at the nearest range, object radii
CROSS_RAY_NOISE_FRACTION = 0.25  # sigma across the ray, as a fraction of the sigma along it
STRAY_PROBABILITY = 0.5
STRAY_DISTANCE_RADII = (2.0, 30.0)
MAX_BOX_OUTLIER_FRACTION = 0.02
MIN_VIEW_POINTS = 64  # a view with fewer visible points is redrawn
_MAX_ATTEMPTS = 8


def hidden_point_removal(points: np.ndarray, sensor: np.ndarray, log_radius: float) -> np.ndarray:
    """Indices (ascending) of the points visible from ``sensor`` (Katz, Tal & Basri 2007).

    Args:
        points: (P, 3) float64 surface samples.
        sensor: (3,) the viewpoint, outside the shape.
        log_radius: gamma: the flipping sphere's radius is max |p - sensor| * 10^gamma.

    Returns:
        (V,) int64 indices into ``points``.
    """
    relative = points - sensor
    norms = np.linalg.norm(relative, axis=1, keepdims=True)
    radius = float(norms.max()) * 10.0**log_radius
    flipped = relative + 2.0 * (radius - norms) * relative / norms
    hull = ConvexHull(np.vstack([flipped, np.zeros((1, 3))]))
    vertices = hull.vertices
    return np.sort(vertices[vertices < len(points)]).astype(np.int64)


def _view(
    points: np.ndarray, normals: np.ndarray, direction: np.ndarray, rng: np.random.Generator, thin: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """One simulated scan of a unit-sphere shape from ``direction`` (unit, shape centre -> sensor);
    ``thin=False`` keeps every visible point (no density fall-off).

    Returns (noisy points (V, 3), origin (V,) int64 index of each point's noise-free sample in
    ``points``, -1 for an outlier), in the shape's frame.
    """
    sensor = direction * rng.uniform(*RANGE_RADII)
    visible = hidden_point_removal(points, sensor, rng.uniform(*HPR_LOG_RADIUS))
    rays = points[visible] - sensor
    ranges = np.linalg.norm(rays, axis=1)
    rays /= ranges[:, None]
    incidence = np.abs(np.einsum("vc,vc->v", rays, normals[visible]))
    keep_probability = (INCIDENCE_FLOOR + (1.0 - INCIDENCE_FLOOR) * incidence) * (ranges.min() / ranges) ** 2
    kept = rng.random(len(visible)) < (keep_probability if thin else 1.0)
    origin, rays, ranges = visible[kept], rays[kept], ranges[kept]

    sigma = rng.uniform(*RAY_NOISE) * ranges / ranges.min()  # (V,) grows with range
    along = rng.normal(size=len(origin)) * sigma
    across = rng.normal(size=(len(origin), 3)) * (CROSS_RAY_NOISE_FRACTION * sigma)[:, None]
    across -= np.einsum("vc,vc->v", across, rays)[:, None] * rays  # keep it across the ray
    noisy = points[origin] + along[:, None] * rays + across

    extra = []
    if rng.random() < STRAY_PROBABILITY:
        stray_count = int(rng.integers(1, 4))
        stray_direction = Rotation.random(stray_count, random_state=rng).apply([1.0, 0.0, 0.0])
        extra.append(stray_direction.reshape(-1, 3) * rng.uniform(*STRAY_DISTANCE_RADII, size=(stray_count, 1)))
    box_count = int(round(rng.uniform(0.0, MAX_BOX_OUTLIER_FRACTION) * len(noisy)))
    if box_count:
        low, high = noisy.min(axis=0), noisy.max(axis=0)
        margin = 0.25 * (high - low)  # grown by half in all
        extra.append(rng.uniform(low - margin, high + margin, size=(box_count, 3)))
    if extra:
        outliers = np.vstack(extra)
        noisy = np.vstack([noisy, outliers])
        origin = np.concatenate([origin, np.full(len(outliers), -1, dtype=np.int64)])
    order = rng.permutation(len(noisy))  # outliers anywhere in the file, as in a real scan
    return noisy[order], origin[order]


def _second_direction(first: np.ndarray, angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A unit vector ``angle_deg`` away from ``first`` (unit), about a uniformly random axis."""
    axis = np.cross(first, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(math.radians(angle_deg) * axis).apply(first)


def make_scan_pair(
    dense_points,
    dense_normals,
    rng: np.random.Generator,
    *,
    points_per_cloud: int | None = 1024,
    normalization_config: NormalizationConfig = NormalizationConfig(),
    min_points: int = 31,
    exact_size: bool = False,
) -> Pair:
    """Two simulated range scans of one shape, in any relative pose (module docstring).

    Args:
        dense_points: (P, 3) surface samples of a shape inside the unit sphere (P of several
            thousand: each view keeps a few hundred to a few thousand of its half).
        dense_normals: (P, 3) unit normals, any signs.
        rng: the generator every draw comes from.
        points_per_cloud: the working size (each cloud is cut to at most this many by the
            runtime's :func:`~logdesc_rt.sampling.working_subset`, stray points set aside), or
            None for the raw views, stray points and all, as a scanner would deliver them
            (benchmarks: the registration under test chooses its own points).
        normalization_config: the network frame and the stray-point test (the runtime's).
        min_points: the geometry's minimum cloud size (the stray test never leaves fewer).
        exact_size: both clouds must hold exactly ``points_per_cloud`` points (training stacks
            pairs into batches): views that fall short are redrawn from new sensors, the later
            attempts without the density fall-off.

    Returns:
        :class:`~logdesc_rt.synthetic.Pair` with protocol ``"scan"``; ``euler_zyx_deg`` holds
        the view angle in its first entry (degrees) and zeros.

    Raises:
        ValueError: the shape is too sparse for two views of ``MIN_VIEW_POINTS`` points (of
            ``points_per_cloud`` with ``exact_size``).
    """
    dense_points = np.asarray(dense_points, dtype=np.float64)
    dense_normals = np.asarray(dense_normals, dtype=np.float64)
    if dense_points.ndim != 2 or dense_points.shape[1] != 3 or dense_normals.shape != dense_points.shape:
        raise ValueError(
            f"dense_points and dense_normals must both be (P, 3), got {dense_points.shape} and {dense_normals.shape}"
        )
    halves = rng.permutation(len(dense_points))
    source_members, target_members = halves[: len(halves) // 2], halves[len(halves) // 2 :]
    if exact_size and points_per_cloud is None:
        raise ValueError("exact_size needs a points_per_cloud")
    needed = points_per_cloud if exact_size else MIN_VIEW_POINTS
    for attempt in range(_MAX_ATTEMPTS):
        thin = attempt < _MAX_ATTEMPTS // 2
        first = Rotation.random(random_state=rng).apply([0.0, 0.0, 1.0])
        view_angle = rng.uniform(*VIEW_ANGLE_DEG)
        second = _second_direction(first, view_angle, rng)
        source_view, source_origin = _view(
            dense_points[source_members], dense_normals[source_members], first, rng, thin
        )
        target_view, target_origin = _view(
            dense_points[target_members], dense_normals[target_members], second, rng, thin
        )
        if points_per_cloud is None:  # the raw views
            source_keep, target_keep = np.arange(len(source_view)), np.arange(len(target_view))
        else:
            source_keep = working_subset(source_view, points_per_cloud, "fps", normalization_config, min_points)
            target_keep = working_subset(target_view, points_per_cloud, "fps", normalization_config, min_points)
        if min(len(source_keep), len(target_keep)) >= needed:
            break
    else:
        raise ValueError(f"the shape gave views of fewer than {needed} points {_MAX_ATTEMPTS} times")
    source_view, source_origin = source_view[source_keep], source_origin[source_keep]
    target_view, target_origin = target_view[target_keep], target_origin[target_keep]

    # Labels from the noise-free positions of both clouds (outliers: no counterpart).
    clean = np.vstack([
        np.where(source_origin[:, None] >= 0, dense_points[source_members][source_origin], source_view),
        np.where(target_origin[:, None] >= 0, dense_points[target_members][target_origin], target_view),
    ])
    source_count = len(source_view)
    gt_match_src, gt_match_tgt = resampled_correspondences(
        clean, np.arange(source_count), source_count + np.arange(len(target_view))
    )
    gt_match_src[source_origin < 0] = -1
    gt_match_tgt[target_origin < 0] = -1
    gt_match_src, gt_match_tgt = _drop_one_sided(gt_match_src, gt_match_tgt)

    # Each view in its own frame: source turned by G_s, target by G_t and shifted.
    source_turn = Rotation.random(random_state=rng).as_matrix()
    target_turn = Rotation.random(random_state=rng).as_matrix()
    target_shift = rng.uniform(-1.0, 1.0, size=3)
    source = source_view @ source_turn.T
    target = target_view @ target_turn.T + target_shift
    pose = np.eye(4)  # y = G_t G_s^T x + shift
    pose[:3, :3] = target_turn @ source_turn.T
    pose[:3, 3] = target_shift
    shape_to_source = np.eye(4)  # the views are in the shape's frame; the source turned by G_s
    shape_to_source[:3, :3] = source_turn

    return pair_in_network_frame(
        SCAN_PROTOCOL, source, target, pose, gt_match_src, gt_match_tgt, normalization_config,
        np.array([view_angle, 0.0, 0.0]), shape_to_source=shape_to_source,
    )


def _drop_one_sided(gt_match_src: np.ndarray, gt_match_tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the matches one-to-one after some endpoints were relabelled as outliers."""
    for labels, inverse in ((gt_match_src, gt_match_tgt), (gt_match_tgt, gt_match_src)):
        matched = np.flatnonzero(labels >= 0)
        broken = matched[inverse[labels[matched]] != matched]
        labels[broken] = -1
    return gt_match_src, gt_match_tgt

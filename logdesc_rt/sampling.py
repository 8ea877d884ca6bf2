"""Deterministic point subsampling: farthest-point sampling, voxel grids, the working subset.

Every function returns *indices* into the input cloud (int64), so callers can gather any
per-point attribute (normals, colours, descriptors) alongside the coordinates.

Farthest-point sampling picks the same points (same indices, same order) wherever the cloud
sits and however it is turned: it works on coordinates centred on the centroid, and distances
within a tiny relative tolerance count as ties, which go to the lowest index (so round-off of a
1 km shift or a rotation cannot reorder a lattice's equal distances). :func:`voxel_downsample`
is axis-aligned and anchored at the cloud's minimum corner: it depends on the frame by nature,
so :func:`working_subset` builds its grid in the cloud's principal frame
(:func:`principal_frame_coordinates`) instead. :func:`working_subset`, the one choice of the
points the networks see, is used by the runtime and by training alike.
"""

from __future__ import annotations

import operator

import numpy as np

from ._jit import jit
from .config import SUBSAMPLING_METHODS, NormalizationConfig
from .errors import InvalidPointCloudError, TooFewPointsError
from .outliers import stray_point_mask
from .validation import as_points

# A voxel grid with more cells than this along one axis is refused: the integer voxel
# coordinates would lose exactness, and such a grid keeps every point anyway.
MAX_VOXELS_PER_AXIS = 2.0**40
# Squared distances within this fraction of the cloud's squared radius count as equal in
# farthest-point sampling (float64 round-off of a rotation or a 1 km shift is ~1e-13 of it).
FPS_TIE_TOLERANCE = 2.0**-30
# working_subset first draws a seeded random subset of this many times the working size from a
# larger cloud: farthest-point sampling then costs O(max_points^2), whatever the cloud's size.
PRESAMPLE_FACTOR = 8


def _power_of_two_scale(points: np.ndarray) -> float:
    """The power of two at or just below the largest |coordinate|; 1.0 for an all-zero cloud.

    Dividing by a power of two is exact, so distances keep their order, and squared
    distances of clouds with coordinates near 1e308 no longer overflow to inf.
    """
    magnitude = float(np.abs(points).max()) if points.size else 0.0
    if magnitude == 0.0:
        return 1.0
    # frexp: magnitude = m * 2**e with 0.5 <= m < 1; 2**(e-1) cannot overflow.
    return float(np.ldexp(1.0, int(np.frexp(magnitude)[1]) - 1))


def _farthest_point_indices(points: np.ndarray, count: int, start_index: int) -> np.ndarray:
    """Greedy farthest-point sampling on validated, well-scaled (N, 3) float64 points.

    Returns (count,) int64. Each step picks the point whose squared distance to the chosen
    set is largest; distances within ``FPS_TIE_TOLERANCE`` x the largest squared distance from
    the origin (the centroid, for callers) tie, and the lowest index wins. Chosen points are
    marked -inf, so duplicates are still picked once each and ``count == N`` yields a
    permutation; the running minimum never lifts a mark back up because ``min(-inf, d) = -inf``.
    """
    return _farthest_point_indices_from(points, count, np.array([start_index]))[0]


def _farthest_point_indices_from(points: np.ndarray, count: int, start_indices: np.ndarray) -> np.ndarray:
    """:func:`_farthest_point_indices` from R starting points at once: (R, count) int64, row r
    exactly the single run from ``start_indices[r]``."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    starts = np.ascontiguousarray(start_indices, dtype=np.int64).reshape(-1)
    return _farthest_point_kernel(points, int(count), starts, FPS_TIE_TOLERANCE)


@jit
def _farthest_point_kernel(points, count, start_indices, tie_tolerance):
    """Compiled farthest-point sampling, one run per start (see :func:`_farthest_point_indices`).

    The squared distance to a chosen point c is ``(x - x_c)**2 + (y - y_c)**2 + (z - z_c)**2``,
    summed in that order; the tolerance is ``tie_tolerance`` times the largest
    ``x**2 + y**2 + z**2``; a pick is the lowest index whose running minimum is within the
    tolerance of the largest one.
    """
    total = points.shape[0]
    rounds = start_indices.shape[0]
    selected = np.empty((rounds, count), dtype=np.int64)
    if count == 0:
        return selected
    xs = points[:, 0].copy()
    ys = points[:, 1].copy()
    zs = points[:, 2].copy()
    largest_norm = -np.inf
    for point in range(total):
        largest_norm = max(largest_norm, xs[point] * xs[point] + ys[point] * ys[point] + zs[point] * zs[point])
    tolerance = tie_tolerance * largest_norm
    nearest = np.empty(total)
    for row in range(rounds):
        chosen = start_indices[row]
        selected[row, 0] = chosen
        for point in range(total):
            nearest[point] = np.inf
        for position in range(1, count):
            # The running minimum with the last pick's distances, and its largest value (the
            # pick itself holds 0 here, which cannot exceed a point still to pick).
            cx, cy, cz = xs[chosen], ys[chosen], zs[chosen]
            largest = -np.inf
            for point in range(total):
                dx = xs[point] - cx
                dy = ys[point] - cy
                dz = zs[point] - cz
                squared = dx * dx + dy * dy + dz * dz
                if squared < nearest[point]:
                    nearest[point] = squared
                if nearest[point] > largest:
                    largest = nearest[point]
            nearest[chosen] = -np.inf
            threshold = largest - tolerance
            for point in range(total):
                if nearest[point] >= threshold:
                    chosen = point
                    break
            selected[row, position] = chosen
    return selected


def seeded_subset(count: int, limit: int | None, generator: np.random.Generator) -> np.ndarray:
    """Indices (ascending, int64) of a uniform random subset of ``limit`` of ``count`` items
    drawn from ``generator``; all of them when ``limit`` is None or >= count (nothing drawn)."""
    if limit is None or count <= limit:
        return np.arange(count)
    return np.sort(generator.choice(count, limit, replace=False))


def farthest_point_sampling(points, count: int, start_index: int | None = None) -> np.ndarray:
    """Pick ``count`` well-spread points by greedy farthest-point sampling (deterministic).

    Starting from one point, each step adds the point farthest (Euclidean) from all points
    chosen so far. Cost O(N * count) time, O(N) memory.

    Args:
        points: (N, 3) real coordinates (any unit).
        count: how many points to pick, 0 <= count <= N. ``count == N`` returns a
            permutation of ``range(N)``.
        start_index: index of the first point. Default: the point farthest from the
            centroid (the lowest index among near-ties), so the result depends on no random
            state, nor on where the cloud sits or how it is turned.

    Returns:
        (count,) int64 indices into ``points``, in the order they were picked; distinct.
        Duplicate points are picked once each (lowest index first) once every distinct
        location is taken.

    Raises:
        PointCloudShapeError, NonFinitePointsError, TooFewPointsError: bad ``points``
            (see :func:`logdesc_rt.validation.as_points`); TooFewPointsError also when
            ``count > N``.
        ValueError: ``count`` negative, or ``start_index`` outside ``[0, N)``.
        TypeError: ``count`` or ``start_index`` is not an integer.
    """
    count = operator.index(count)
    if count < 0:
        raise ValueError(f"farthest_point_sampling: count must be >= 0, got {count}")
    points = as_points(points, name="points", min_points=1)
    if count > len(points):
        raise TooFewPointsError(
            f"farthest_point_sampling: cannot pick {count} points from a cloud of {len(points)}"
        )
    # Centred (translation drops out), then scaled by a power of two (exact; no overflow).
    points = points - points.mean(axis=0)
    points = points / _power_of_two_scale(points)
    if start_index is None:
        from_centre = np.sum(points**2, axis=1)
        start_index = int(np.argmax(from_centre >= from_centre.max() * (1.0 - FPS_TIE_TOLERANCE)))
    else:
        start_index = operator.index(start_index)
        if not 0 <= start_index < len(points):
            raise ValueError(
                f"farthest_point_sampling: start_index {start_index} is outside [0, {len(points)})"
            )
    return _farthest_point_indices(points, count, start_index)


def voxel_downsample(points, voxel_size: float) -> np.ndarray:
    """Keep one representative point per occupied voxel of a regular grid.

    Not invariant to the cloud's frame: the grid is axis-aligned, so turning the cloud keeps
    other points (prefer :func:`farthest_point_sampling` where that matters). It is anchored at
    the cloud's minimum corner: point p falls in voxel
    ``floor((p - min(points)) / voxel_size)``. Each occupied voxel is represented by its
    point nearest the mean of the voxel's points (lowest index on ties, up to round-off), so the result is
    a subset of the input, unlike Open3D's averaging ``voxel_down_sample``.

    Args:
        points: (N, 3) real coordinates, N >= 1.
        voxel_size: edge length of the cubic voxels, same unit as ``points``; > 0, finite.

    Returns:
        (V,) int64 indices into ``points``, sorted ascending, one per occupied voxel.

    Raises:
        PointCloudShapeError, NonFinitePointsError, TooFewPointsError: bad ``points``.
        ValueError: ``voxel_size`` is not a finite positive number.
        InvalidPointCloudError: the cloud spans more than 2**40 voxels along one axis.
    """
    voxel_size = float(voxel_size)
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"voxel_downsample: voxel_size must be finite and > 0, got {voxel_size}")
    points = as_points(points, name="points", min_points=1)
    lowest = points.min(axis=0)
    with np.errstate(over="ignore"):
        cells_per_axis = (points.max(axis=0) - lowest) / voxel_size
    if not (np.all(np.isfinite(cells_per_axis)) and cells_per_axis.max() < MAX_VOXELS_PER_AXIS):
        raise InvalidPointCloudError(
            f"points: extent {points.max(axis=0) - lowest} spans too many voxels of size "
            f"{voxel_size} (more than 2**40 along one axis); use a larger voxel_size"
        )
    voxel_coordinates = np.floor((points - lowest) / voxel_size).astype(np.int64)
    grid_shape = [int(extent) + 1 for extent in voxel_coordinates.max(axis=0)]
    # Stable sort of the points by voxel: within a voxel, points stay in index order.
    if grid_shape[0] * grid_shape[1] * grid_shape[2] < 2**62:
        keys = (voxel_coordinates[:, 0] * grid_shape[1] + voxel_coordinates[:, 1]) * grid_shape[2]
        keys += voxel_coordinates[:, 2]
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        starts_voxel = np.concatenate([[True], sorted_keys[1:] != sorted_keys[:-1]])
    else:  # too many cells for one int64 key per voxel
        order = np.lexsort(voxel_coordinates.T[::-1])
        sorted_coordinates = voxel_coordinates[order]
        changed = np.any(sorted_coordinates[1:] != sorted_coordinates[:-1], axis=1)
        starts_voxel = np.concatenate([[True], changed])
    voxel_of_sorted = np.cumsum(starts_voxel) - 1
    voxel_count = int(voxel_of_sorted[-1]) + 1
    voxel_of_point = np.empty(len(points), dtype=np.int64)
    voxel_of_point[order] = voxel_of_sorted

    # Mean of each voxel's points, computed relative to the grid corner for accuracy.
    local = points - lowest
    members = np.bincount(voxel_of_point, minlength=voxel_count).astype(np.float64)
    voxel_means = np.stack(
        [np.bincount(voxel_of_point, weights=local[:, axis], minlength=voxel_count) for axis in range(3)],
        axis=1,
    ) / members[:, None]
    distance_to_mean = np.sum((local - voxel_means[voxel_of_point]) ** 2, axis=1)

    # In each voxel, the first point (in index order) at the voxel's least distance wins;
    # distances within round-off tie (a voxel of two points: both equally far from their mean).
    sorted_distance = distance_to_mean[order]
    least_distance = np.minimum.reduceat(sorted_distance, np.flatnonzero(starts_voxel))
    tolerance = FPS_TIE_TOLERANCE * voxel_size**2
    candidates = np.flatnonzero(sorted_distance <= least_distance[voxel_of_sorted] + tolerance)
    candidate_voxels = voxel_of_sorted[candidates]
    first_in_voxel = np.concatenate([[True], candidate_voxels[1:] != candidate_voxels[:-1]])
    return np.sort(order[candidates[first_in_voxel]]).astype(np.int64)


def principal_frame_coordinates(points: np.ndarray) -> np.ndarray:
    """(N, 3) coordinates of ``points`` in their own principal frame: centred on the centroid,
    along the principal axes (largest variance first), each axis signed so that the third
    moment along it is positive. The same for the cloud wherever it sits and however it is
    turned, except where two principal variances tie or a third moment vanishes (a shape with
    that symmetry), where the frame is ambiguous.

    Args:
        points: (N, 3) float64 finite coordinates.
    """
    centred = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)  # rows: principal axes
    coordinates = centred @ axes.T
    signs = np.where(np.sum(coordinates**3, axis=0) < 0.0, -1.0, 1.0)
    return coordinates * signs


def working_subset(
    points,
    max_points: int,
    method: str = "fps",
    normalization: NormalizationConfig = NormalizationConfig(),
    min_points: int = 1,
) -> np.ndarray:
    """The points the networks see of one cloud: stray points set aside, then at most ``max_points``.

    A cloud of more than ``PRESAMPLE_FACTOR * max_points`` points is first cut to that many by a
    seeded uniform draw (the same indices for the same point count, wherever the cloud sits).
    Stray points (:mod:`.outliers`) are then dropped, so that neither the scale nor the
    sampling spends anything on them (unless fewer than ``min_points`` would remain). A cloud
    still larger than ``max_points`` is then subsampled: ``"fps"`` by farthest-point sampling,
    ``"voxel"`` by a grid in the cloud's principal frame sized to keep about ``2 * max_points``
    cells of a surface, trimmed by farthest-point sampling. Both give the same indices wherever
    the cloud sits and however it is turned (the voxel grid not where the principal frame is
    ambiguous: see :func:`principal_frame_coordinates`).

    Args:
        points: (N, 3) finite coordinates, any unit.
        max_points: the working size, >= 1.
        method: "fps" or "voxel".
        normalization: its ``stray_*`` fields set the stray-point test.
        min_points: the fewest points the caller needs.

    Returns:
        (K,) int64 ascending indices into ``points``, K <= min(N, max_points).
    """
    if method not in SUBSAMPLING_METHODS:
        raise ValueError(f"subsampling method {method!r}: expected one of {SUBSAMPLING_METHODS}")
    points = as_points(points, name="points", min_points=1)
    kept = np.arange(len(points))
    if len(points) > PRESAMPLE_FACTOR * max_points:
        kept = seeded_subset(len(points), PRESAMPLE_FACTOR * max_points, np.random.default_rng(len(points)))
    not_stray = kept[~stray_point_mask(points[kept], normalization)]
    if len(not_stray) >= min_points:
        kept = not_stray
    if len(kept) <= max_points:
        return kept.astype(np.int64)
    candidates = points[kept]
    if method == "voxel":
        # In the cloud's own principal frame, so that the grid turns and moves with the cloud.
        canonical = principal_frame_coordinates(candidates)
        # A scan is a surface: with its two largest extents a x b, cells of side
        # sqrt(a b / (2 max_points)) leave about 2 * max_points occupied, then FPS trims.
        largest_two = np.sort(np.ptp(canonical, axis=0))[1:]
        voxel = float(np.sqrt(np.prod(largest_two) / (2 * max_points)))
        kept = kept[voxel_downsample(canonical, max(voxel, 1e-12))]
        candidates = points[kept]
        if len(kept) <= max_points:
            return kept.astype(np.int64)
    return np.sort(kept[farthest_point_sampling(candidates, max_points)]).astype(np.int64)

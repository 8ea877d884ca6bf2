"""Compiled kernels of the per-point geometry: radius neighbourhoods on a grid, covariances.

:func:`neighbourhoods` finds, for every point of a cloud, in one pass over a uniform grid:

- the PCA neighbourhood: the point itself and its nearest neighbours strictly within
  ``radius``, at most ``max_neighbours`` of them (the nearest), and always the nearest
  ``min_neighbours`` whatever the radius (the point included in every count);
- the mean and covariance of that neighbourhood;
- the ``umbrella_neighbours`` nearest *other* points, nearest first.

Neighbours are ranked by squared distance, ties by index (exact duplicates of a point rank
after the point itself, so the point is never its own neighbour). The grid's cells are at least
``radius`` wide, and fewer than ``4 N + 64`` in all (a far stray point makes them wider, which
costs time, never correctness). A point with too few neighbours within ``radius`` searches a
window of cells that doubles until it holds enough points, up to the whole grid.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import jit

# Cells are this much wider than the radius, so that round-off cannot put a point within the
# radius outside the window of cells searched around the query point.
_CELL_MARGIN = 1.0 + 2.0**-20
# Slack (in cells) added to each side of a search window, for the same reason.
_WINDOW_SLACK = 1e-6


def neighbourhoods(
    points: np.ndarray, radius: float, max_neighbours: int, min_neighbours: int, umbrella_neighbours: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """PCA neighbourhoods (count, mean, covariance) and umbrella neighbours of every point.

    Args:
        points: (N, 3) float64 finite coordinates.
        radius: PCA radius, > 0, same units as ``points``.
        max_neighbours: at most this many points per PCA neighbourhood, >= 1.
        min_neighbours: at least this many (the nearest; capped by ``max_neighbours`` and N).
        umbrella_neighbours: k nearest other points to list, 0 <= k < N.

    Returns:
        count: (N,) int64 points in each PCA neighbourhood (the point included).
        mean: (N, 3) float64 their mean.
        covariance: (N, 3, 3) float64 their covariance (divided by count), symmetric.
        umbrella: (N, k) int64 the k nearest other points, nearest first.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    count = len(points)
    lowest, highest = points.min(axis=0), points.max(axis=0)
    half_extent = highest * 0.5 - lowest * 0.5  # no overflow, whatever the coordinates
    cell = float(radius) * _CELL_MARGIN
    max_cells = 4 * count + 64
    while True:
        with np.errstate(over="ignore"):
            cells_per_axis = np.floor(half_extent / (0.5 * cell)) + 1.0
        if float(np.prod(cells_per_axis)) <= max_cells:
            break
        cell *= 2.0
    return _neighbourhoods(
        points,
        lowest,
        cell,
        cells_per_axis.astype(np.int64),
        float(radius),
        int(max_neighbours),
        int(min_neighbours),
        int(umbrella_neighbours),
    )


@jit
def _cell_coordinate(value, lowest, inverse_cell):
    """Continuous grid coordinate of one coordinate (in cells from the grid's corner)."""
    offset = (value - lowest) * inverse_cell
    if math.isfinite(offset):
        return offset
    return value * inverse_cell - lowest * inverse_cell  # overflow of value - lowest


@jit
def _precedes(distance_a, index_a, distance_b, index_b, query):
    """Neighbour order: squared distance, then the query point first, then index."""
    if distance_a != distance_b:
        return distance_a < distance_b
    if index_a == query or index_b == query:
        return index_a == query
    return index_a < index_b


@jit
def _select(distance, index, start, stop, kth, query):
    """Reorder distance/index[start:stop] in place so that its ``kth`` first entries (in
    neighbour order, :func:`_precedes`) come first, in no particular order."""
    low, high = start, stop - 1
    target = start + kth - 1
    while low < high:
        middle = (low + high) // 2
        # Median of three as the pivot, moved to the end.
        if _precedes(distance[middle], index[middle], distance[low], index[low], query):
            _swap(distance, index, middle, low)
        if _precedes(distance[high], index[high], distance[low], index[low], query):
            _swap(distance, index, high, low)
        if _precedes(distance[middle], index[middle], distance[high], index[high], query):
            _swap(distance, index, middle, high)
        pivot_distance, pivot_index = distance[high], index[high]
        store = low
        for position in range(low, high):
            if _precedes(distance[position], index[position], pivot_distance, pivot_index, query):
                _swap(distance, index, position, store)
                store += 1
        _swap(distance, index, store, high)
        if store == target:
            return
        if store < target:
            low = store + 1
        else:
            high = store - 1


@jit
def _swap(distance, index, first, second):
    distance[first], distance[second] = distance[second], distance[first]
    index[first], index[second] = index[second], index[first]


@jit
def _sort(distance, index, start, stop, query):
    """Insertion sort of distance/index[start:stop] in neighbour order."""
    for position in range(start + 1, stop):
        value_distance, value_index = distance[position], index[position]
        slot = position
        while slot > start and _precedes(value_distance, value_index, distance[slot - 1], index[slot - 1], query):
            distance[slot] = distance[slot - 1]
            index[slot] = index[slot - 1]
            slot -= 1
        distance[slot] = value_distance
        index[slot] = value_index


@jit
def _neighbourhoods(points, lowest, cell, cells_per_axis, radius, max_neighbours, min_neighbours, umbrella_neighbours):
    count = points.shape[0]
    nx, ny, nz = cells_per_axis[0], cells_per_axis[1], cells_per_axis[2]
    inverse_cell = 1.0 / cell

    # Counting sort of the points by cell; coordinates copied in that order (contiguous reads).
    cell_of = np.empty(count, dtype=np.int64)
    grid = np.empty((count, 3), dtype=np.int64)
    for point in range(count):
        for axis in range(3):
            coordinate = int(math.floor(_cell_coordinate(points[point, axis], lowest[axis], inverse_cell)))
            grid[point, axis] = min(max(coordinate, 0), cells_per_axis[axis] - 1)
        cell_of[point] = (grid[point, 0] * ny + grid[point, 1]) * nz + grid[point, 2]
    cell_start = np.zeros(nx * ny * nz + 1, dtype=np.int64)
    for point in range(count):
        cell_start[cell_of[point] + 1] += 1
    for slot in range(nx * ny * nz):
        cell_start[slot + 1] += cell_start[slot]
    fill = cell_start[:-1].copy()
    order = np.empty(count, dtype=np.int64)
    for point in range(count):
        order[fill[cell_of[point]]] = point
        fill[cell_of[point]] += 1
    xs, ys, zs = np.empty(count), np.empty(count), np.empty(count)
    for slot in range(count):
        xs[slot] = points[order[slot], 0]
        ys[slot] = points[order[slot], 1]
        zs[slot] = points[order[slot], 2]

    neighbour_count = np.empty(count, dtype=np.int64)
    mean = np.empty((count, 3))
    covariance = np.empty((count, 3, 3))
    umbrella = np.empty((count, umbrella_neighbours), dtype=np.int64)
    # Candidates: those within the radius fill the buffers from the front, the others within
    # the window's complete radius from the back.
    distance = np.empty(count)
    index = np.empty(count, dtype=np.int64)
    need = min(max(umbrella_neighbours + 1, min(min_neighbours, max_neighbours)), count)
    largest_window = max(nx, max(ny, nz))
    # sqrt(squared) < radius, decided without the square root away from the boundary.
    inside_squared = radius * radius * (1.0 - 1e-9)
    outside_squared = radius * radius * (1.0 + 1e-9)

    for query in range(count):
        px, py, pz = points[query, 0], points[query, 1], points[query, 2]
        ux = _cell_coordinate(px, lowest[0], inverse_cell)
        uy = _cell_coordinate(py, lowest[1], inverse_cell)
        uz = _cell_coordinate(pz, lowest[2], inverse_cell)
        reach = 1  # window half-width in cells: every point closer than reach * cell is in it
        while True:
            span = reach + _WINDOW_SLACK
            x0 = max(int(math.floor(ux - span)), 0)
            x1 = min(int(math.floor(ux + span)), nx - 1)
            y0 = max(int(math.floor(uy - span)), 0)
            y1 = min(int(math.floor(uy + span)), ny - 1)
            z0 = max(int(math.floor(uz - span)), 0)
            z1 = min(int(math.floor(uz + span)), nz - 1)
            whole_grid = x0 == 0 and y0 == 0 and z0 == 0 and x1 == nx - 1 and y1 == ny - 1 and z1 == nz - 1
            complete_squared = (reach * cell) ** 2
            within = 0
            beyond = count  # entries [beyond, count) are complete but outside the radius
            for cx in range(x0, x1 + 1):
                for cy in range(y0, y1 + 1):
                    row = (cx * ny + cy) * nz
                    for slot in range(cell_start[row + z0], cell_start[row + z1 + 1]):
                        dx = xs[slot] - px
                        dy = ys[slot] - py
                        dz = zs[slot] - pz
                        squared = dx * dx + dy * dy + dz * dz
                        if squared < inside_squared or (
                            squared < outside_squared and math.sqrt(squared) < radius
                        ):
                            distance[within] = squared
                            index[within] = order[slot]
                            within += 1
                        elif squared < complete_squared or whole_grid:
                            beyond -= 1
                            distance[beyond] = squared
                            index[beyond] = order[slot]
            complete = within + count - beyond
            if within >= need or complete >= need or whole_grid:
                break
            reach = min(2 * reach, largest_window)

        # Candidates [0, available): within the radius only, unless that is too few.
        available = within
        if within < need:
            for slot in range(beyond, count):
                distance[available] = distance[slot]
                index[available] = index[slot]
                available += 1
        pca_count = min(max_neighbours, max(within, min_neighbours), count)
        ranked = min(umbrella_neighbours + 1, available)
        # The umbrella: the first umbrella_neighbours + 1 in order (the query point first).
        if ranked < available:
            _select(distance, index, 0, available, ranked, query)
        _sort(distance, index, 0, ranked, query)
        for slot in range(umbrella_neighbours):
            umbrella[query, slot] = index[slot + 1]
        # The PCA neighbourhood: the first pca_count in order.
        if ranked < pca_count < available:
            _select(distance, index, ranked, available, pca_count - ranked, query)

        sx = sy = sz = 0.0
        for slot in range(pca_count):
            neighbour = index[slot]
            sx += points[neighbour, 0]
            sy += points[neighbour, 1]
            sz += points[neighbour, 2]
        mx, my, mz = sx / pca_count, sy / pca_count, sz / pca_count
        cxx = cxy = cxz = cyy = cyz = czz = 0.0
        for slot in range(pca_count):
            neighbour = index[slot]
            ex = points[neighbour, 0] - mx
            ey = points[neighbour, 1] - my
            ez = points[neighbour, 2] - mz
            cxx += ex * ex
            cxy += ex * ey
            cxz += ex * ez
            cyy += ey * ey
            cyz += ey * ez
            czz += ez * ez
        neighbour_count[query] = pca_count
        mean[query, 0], mean[query, 1], mean[query, 2] = mx, my, mz
        covariance[query, 0, 0] = cxx / pca_count
        covariance[query, 0, 1] = covariance[query, 1, 0] = cxy / pca_count
        covariance[query, 0, 2] = covariance[query, 2, 0] = cxz / pca_count
        covariance[query, 1, 1] = cyy / pca_count
        covariance[query, 1, 2] = covariance[query, 2, 1] = cyz / pca_count
        covariance[query, 2, 2] = czz / pca_count
    return neighbour_count, mean, covariance, umbrella


@jit
def edge_channels(points, shape_features, normals, lrf, gate, neighbour_index, length_scale, invariant, chiral):
    """The invariant (11) and/or chiral (2) edge channels of :mod:`.invariant_features`.

    Args:
        points: (N, 3) float64 positions.
        shape_features: (N, 3) float64 anisotropy, planarity, omnivariance (read if ``invariant``).
        normals: (N, 3) float64 unit normals.
        lrf: (N, 3, 3) float64 frames, columns (u, v, w) (read if ``chiral``).
        gate: (N,) float64 g_i (read if ``chiral``).
        neighbour_index: (N, k) int64.
        length_scale: R, > 0.
        invariant, chiral: which channel groups to write, in that order.

    Returns:
        (N, k, 11 * invariant + 2 * chiral) float32.
    """
    count, k = neighbour_index.shape
    first_chiral = 11 if invariant else 0
    channels = np.empty((count, k, first_chiral + (2 if chiral else 0)), dtype=np.float32)
    omnivariance_scale = 1.0 / length_scale**2
    for point in range(count):
        x, y, z = points[point, 0], points[point, 1], points[point, 2]
        nx, ny, nz = normals[point, 0], normals[point, 1], normals[point, 2]
        if chiral:
            ux, uy, uz = lrf[point, 0, 0], lrf[point, 1, 0], lrf[point, 2, 0]
            wx, wy, wz = lrf[point, 0, 2], lrf[point, 1, 2], lrf[point, 2, 2]
            # u x w
            sx, sy, sz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
            point_gate = gate[point]
        if invariant:
            a, p, o = shape_features[point, 0], shape_features[point, 1], shape_features[point, 2] * omnivariance_scale
        for slot in range(k):
            m = neighbour_index[point, slot]
            dx, dy, dz = points[m, 0] - x, points[m, 1] - y, points[m, 2] - z
            distance = math.sqrt(dx * dx + dy * dy + dz * dz)
            divisor = distance if distance > 0.0 else 1.0
            ex, ey, ez = dx / divisor, dy / divisor, dz / divisor
            mx, my, mz = normals[m, 0], normals[m, 1], normals[m, 2]
            normal_i_offset = ex * nx + ey * ny + ez * nz
            normal_m_offset = ex * mx + ey * my + ez * mz
            out = channels[point, slot]
            if invariant:
                normal_i_normal_m = mx * nx + my * ny + mz * nz
                out[0] = distance / length_scale
                out[1] = abs(normal_i_offset)
                out[2] = abs(normal_m_offset)
                out[3] = abs(normal_i_normal_m)
                out[4] = normal_i_offset * normal_m_offset * normal_i_normal_m
                out[5] = a
                out[6] = p
                out[7] = o
                out[8] = shape_features[m, 0] - a
                out[9] = shape_features[m, 1] - p
                out[10] = shape_features[m, 2] * omnivariance_scale - o
            if chiral:
                # (n_i x n_m) . e
                twist = (ny * mz - nz * my) * ex + (nz * mx - nx * mz) * ey + (nx * my - ny * mx) * ez
                out[first_chiral] = np.cbrt(twist * normal_i_offset * normal_m_offset)
                octant = (ex * sx + ey * sy + ez * sz) * (ex * ux + ey * uy + ez * uz) * (ex * wx + ey * wy + ez * wz)
                out[first_chiral + 1] = np.cbrt(point_gate * octant)
    return channels

"""Compiled kernels of pose refinement and verification: normals from neighbour lists, and the
point-to-plane normal equations.

Both replace a handful of NumPy passes over (K, k, 3) or (K, 6) temporaries that, at the
1,000-10,000 points verification and ICP work on, cost more in allocation and dispatch than in
arithmetic. They compute what the NumPy forms computed, up to rounding:

- :func:`neighbourhood_normals`: the least-variance axis of each point's neighbours (the
  eigenvector of the smallest eigenvalue of their covariance about their mean), by cyclic Jacobi
  rotations on the 3 x 3 matrix (converged to machine precision; robust where two eigenvalues
  are close, where a closed-form eigenvector is not);
- :func:`plane_normal_equations`: the 6 x 6 system J^T W J, J^T W r of the residuals
  r_k = offset_k . d_k with Jacobian rows [arm_k x d_k, d_k];
- :func:`correspondence_plane_equations`: the same system for one point-to-plane ICP iteration,
  read straight from a k-d tree query's output (no gathered copies of the pairs).
"""

from __future__ import annotations

import numpy as np

from .._jit import jit

JACOBI_SWEEPS = 12  # a 3 x 3 symmetric matrix converges in 4-6; the loop stops when it has


@jit
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22, out):
    """Write into ``out`` (3,) the unit eigenvector of the smallest eigenvalue of the symmetric
    3 x 3 matrix [[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]] (cyclic Jacobi)."""
    a = np.empty((3, 3))
    a[0, 0], a[0, 1], a[0, 2] = a00, a01, a02
    a[1, 0], a[1, 1], a[1, 2] = a01, a11, a12
    a[2, 0], a[2, 1], a[2, 2] = a02, a12, a22
    v = np.eye(3)
    for _ in range(JACOBI_SWEEPS):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diagonal = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-30 * diagonal or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            if a[p, q] == 0.0:
                continue
            # The rotation that zeroes a[p, q] (the smaller of the two angles: stable).
            theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
            t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            for r in range(3):  # a <- a G (columns p, q)
                arp, arq = a[r, p], a[r, q]
                a[r, p], a[r, q] = c * arp - s * arq, s * arp + c * arq
            for r in range(3):  # a <- G^T a (rows p, q)
                apr, aqr = a[p, r], a[q, r]
                a[p, r], a[q, r] = c * apr - s * aqr, s * apr + c * aqr
            for r in range(3):  # v <- v G
                vrp, vrq = v[r, p], v[r, q]
                v[r, p], v[r, q] = c * vrp - s * vrq, s * vrp + c * vrq
    smallest = 0
    if a[1, 1] < a[smallest, smallest]:
        smallest = 1
    if a[2, 2] < a[smallest, smallest]:
        smallest = 2
    norm = np.sqrt(v[0, smallest] ** 2 + v[1, smallest] ** 2 + v[2, smallest] ** 2)
    for r in range(3):
        out[r] = v[r, smallest] / norm


@jit
def neighbourhood_normals(points: np.ndarray, neighbour_index: np.ndarray) -> np.ndarray:
    """(K, 3) unit normals: the least-variance axis of each row's neighbours.

    Args:
        points: (N, 3) float64.
        neighbour_index: (K, k) int64 indices into ``points``, k >= 3: each row one
            neighbourhood (the point itself among them, as a k-d tree query returns it).

    Returns:
        (K, 3) float64 unit vectors, signs arbitrary; where a neighbourhood has no least-variance
        axis (all its points equal) some unit vector.
    """
    count, k = neighbour_index.shape
    normals = np.empty((count, 3))
    for i in range(count):
        mx = my = mz = 0.0
        for j in range(k):
            n = neighbour_index[i, j]
            mx += points[n, 0]
            my += points[n, 1]
            mz += points[n, 2]
        mx, my, mz = mx / k, my / k, mz / k
        xx = xy = xz = yy = yz = zz = 0.0
        for j in range(k):
            n = neighbour_index[i, j]
            dx, dy, dz = points[n, 0] - mx, points[n, 1] - my, points[n, 2] - mz
            xx += dx * dx
            xy += dx * dy
            xz += dx * dz
            yy += dy * dy
            yz += dy * dz
            zz += dz * dz
        _smallest_eigenvector(xx, xy, xz, yy, yz, zz, normals[i])
    return normals


@jit(inline=True)
def _add_plane_pair(matrix, rhs, row, ax, ay, az, dx, dy, dz, offset_along, weight):
    """Add one pair to the upper triangle of ``matrix`` (6, 6) and to ``rhs`` (6,): Jacobian
    row [arm x d, d] (written into ``row`` (6,)), residual ``offset_along`` (offset . d)."""
    row[0], row[1], row[2] = ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx
    row[3], row[4], row[5] = dx, dy, dz
    residual = weight * offset_along
    for p in range(6):
        weighted = weight * row[p]
        rhs[p] += row[p] * residual
        for q in range(p, 6):
            matrix[p, q] += weighted * row[q]


@jit(inline=True)
def _mirror_upper_triangle(matrix):
    """Copy the upper triangle of ``matrix`` (6, 6) into its lower one."""
    for p in range(6):
        for q in range(p):
            matrix[p, q] = matrix[q, p]


@jit
def plane_normal_equations(arm: np.ndarray, offset: np.ndarray, directions: np.ndarray, weights: np.ndarray):
    """(6, 6) J^T W J and (6,) J^T W r for residuals r_k = offset_k . d_k, Jacobian rows
    [arm_k x d_k, d_k] (rotation about the pivot, then translation).

    Args:
        arm, offset, directions: (K, 3) float64 (``directions``: unit target normals, or an axis).
        weights: (K,) float64 non-negative pair weights.
    """
    matrix = np.zeros((6, 6))
    rhs = np.zeros(6)
    row = np.empty(6)
    for i in range(arm.shape[0]):
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        _add_plane_pair(
            matrix, rhs, row, arm[i, 0], arm[i, 1], arm[i, 2], dx, dy, dz,
            offset[i, 0] * dx + offset[i, 1] * dy + offset[i, 2] * dz, weights[i],
        )
    _mirror_upper_triangle(matrix)
    return matrix, rhs


@jit
def correspondence_plane_equations(
    moved: np.ndarray, target: np.ndarray, normals: np.ndarray, index: np.ndarray, distance: np.ndarray
):
    """The point-to-plane normal equations of one ICP iteration, about the pivot of its pairs.

    The pairs are (moved_i, target[index_i]) for every i with a finite ``distance_i`` (a k-d tree
    query with an upper bound marks the others infinite); the system is
    :func:`plane_normal_equations`' with arm = moved_i - pivot, offset = target[index_i] - moved_i,
    directions normals[index_i] and unit weights, the pivot the pairs' mean moved point.

    Args:
        moved: (N, 3) float64 source points after the current pose.
        target: (M, 3) float64 target points; normals: (M, 3) their unit normals (those at the
            paired points at least).
        index: (N,) int64 each moved point's nearest target point (any value where unpaired).
        distance: (N,) float64 its distance, inf where unpaired.

    Returns:
        (6, 6) matrix, (6,) rhs, (3,) pivot, and the number of pairs.
    """
    count = 0
    px = py = pz = 0.0
    for i in range(moved.shape[0]):
        if np.isfinite(distance[i]):
            count += 1
            px += moved[i, 0]
            py += moved[i, 1]
            pz += moved[i, 2]
    pivot = np.zeros(3)
    matrix = np.zeros((6, 6))
    rhs = np.zeros(6)
    if count == 0:
        return matrix, rhs, pivot, count
    pivot[0], pivot[1], pivot[2] = px / count, py / count, pz / count
    row = np.empty(6)
    for i in range(moved.shape[0]):
        if not np.isfinite(distance[i]):
            continue
        j = index[i]
        dx, dy, dz = normals[j, 0], normals[j, 1], normals[j, 2]
        _add_plane_pair(
            matrix, rhs, row, moved[i, 0] - pivot[0], moved[i, 1] - pivot[1], moved[i, 2] - pivot[2], dx, dy, dz,
            (target[j, 0] - moved[i, 0]) * dx + (target[j, 1] - moved[i, 1]) * dy + (target[j, 2] - moved[i, 2]) * dz,
            1.0,
        )
    _mirror_upper_triangle(matrix)
    return matrix, rhs, pivot, count


# numpy.linalg.lstsq's default cut-off (rcond=None): singular values below eps x max(6, 6) of
# the largest are zero, so a motion the surface leaves free (a plane's slide) gets no step.
_LSTSQ_RCOND = 6.0 * np.finfo(np.float64).eps


@jit
def plane_step(matrix: np.ndarray, rhs: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """(4, 4) rigid update from the (6, 6) / (6,) linearised plane-fit equations about ``pivot``
    (3,): a rotation about the pivot by the first three unknowns (axis-angle, Rodrigues'
    formula), then their translation. The minimum-norm least-squares solution (numpy.linalg's
    ``lstsq`` cut-off), so that a motion the surface leaves free (a plane, a cylinder) stays 0."""
    solution = np.linalg.lstsq(matrix, rhs, _LSTSQ_RCOND)[0]
    vx, vy, vz = solution[0], solution[1], solution[2]
    angle = np.sqrt(vx * vx + vy * vy + vz * vz)
    cross = np.zeros((3, 3))
    if angle < 1e-12:  # second order: exact to float precision here
        sine, one_minus_cosine = 1.0, 0.5
        x, y, z = vx, vy, vz
    else:
        sine, one_minus_cosine = np.sin(angle), 1.0 - np.cos(angle)
        x, y, z = vx / angle, vy / angle, vz / angle
    cross[0, 1], cross[0, 2], cross[1, 0], cross[1, 2], cross[2, 0], cross[2, 1] = -z, y, z, -x, -y, x
    rotation = np.eye(3) + sine * cross + one_minus_cosine * (cross @ cross)
    step = np.eye(4)
    step[:3, :3] = rotation
    for axis in range(3):
        step[axis, 3] = pivot[axis] + solution[3 + axis] - (
            rotation[axis, 0] * pivot[0] + rotation[axis, 1] * pivot[1] + rotation[axis, 2] * pivot[2]
        )
    return step


@jit
def motion_size(pose: np.ndarray, earlier: np.ndarray, distance: float) -> float:
    """How far the rigid (4, 4) ``pose`` is from ``earlier``: the rotation angle (radians) of
    pose @ earlier^-1 plus its translation divided by ``distance`` (a stage's correspondence
    distance, so that a tighter stage converges as tightly). The angle from the skew part of
    the relative rotation (2 sin(angle) times its axis) and its trace (the cosine's sign): exact
    at every angle."""
    relative = np.zeros((3, 3))
    for row in range(3):
        for column in range(3):
            for k in range(3):
                relative[row, column] += pose[row, k] * earlier[column, k]
    sine = 0.5 * np.sqrt(
        (relative[2, 1] - relative[1, 2]) ** 2 + (relative[0, 2] - relative[2, 0]) ** 2
        + (relative[1, 0] - relative[0, 1]) ** 2
    )
    angle = np.arcsin(min(sine, 1.0))
    if relative[0, 0] + relative[1, 1] + relative[2, 2] < 1.0:  # cos(angle) < 0: past 90 degrees
        angle = np.pi - angle
    squared = 0.0
    for axis in range(3):
        moved = pose[axis, 3] - (relative[axis, 0] * earlier[0, 3] + relative[axis, 1] * earlier[1, 3]
                                 + relative[axis, 2] * earlier[2, 3])
        squared += moved * moved
    return angle + np.sqrt(squared) / distance

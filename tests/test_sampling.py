"""Farthest-point sampling and voxel downsampling: correctness, determinism, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from logdesc_rt.errors import LogdescError, NonFinitePointsError, PointCloudShapeError, TooFewPointsError
from logdesc_rt.sampling import FPS_TIE_TOLERANCE, farthest_point_sampling, voxel_downsample


def _brute_force_fps(points: np.ndarray, count: int, start: int) -> list[int]:
    """Textbook FPS with an explicit loop over candidates, for comparison."""
    chosen = [start]
    while len(chosen) < count:
        best, best_distance = None, -1.0
        for index in range(len(points)):
            if index in chosen:
                continue
            distance = min(float(np.sum((points[index] - points[c]) ** 2)) for c in chosen)
            if distance > best_distance:
                best, best_distance = index, distance
        chosen.append(best)
    return chosen


def test_fps_matches_brute_force():
    points = np.random.default_rng(1).normal(size=(60, 3))
    for start in (0, 17, 59):
        expected = _brute_force_fps(points, 15, start)
        assert farthest_point_sampling(points, 15, start_index=start).tolist() == expected


def test_fps_default_start_is_farthest_from_centroid():
    points = np.random.default_rng(2).normal(size=(100, 3))
    expected_start = int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))
    indices = farthest_point_sampling(points, 10)
    assert indices[0] == expected_start
    assert indices.dtype == np.int64 and indices.shape == (10,)
    np.testing.assert_array_equal(indices, farthest_point_sampling(points, 10))


def test_fps_default_start_ties_take_lowest_index():
    # Square corners are all equally far from the centroid.
    square = np.array([[1, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]], dtype=float)
    assert farthest_point_sampling(square, 1)[0] == 0


def test_fps_full_count_is_permutation_even_with_duplicates():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(20, 3))
    points = np.concatenate([points, points[:5], np.zeros((3, 3))])
    indices = farthest_point_sampling(points, len(points))
    assert sorted(indices.tolist()) == list(range(len(points)))
    identical = farthest_point_sampling(np.ones((7, 3)), 7)
    assert sorted(identical.tolist()) == list(range(7))


def test_fps_picks_spread_points():
    # Two tight clusters: the first two picks must land in different clusters.
    rng = np.random.default_rng(4)
    points = np.concatenate([rng.normal(scale=0.01, size=(50, 3)), 5 + rng.normal(scale=0.01, size=(50, 3))])
    first, second = farthest_point_sampling(points, 2)
    assert (first < 50) != (second < 50)


def test_fps_zero_count_and_errors():
    points = np.random.default_rng(5).normal(size=(10, 3))
    assert farthest_point_sampling(points, 0).shape == (0,)
    with pytest.raises(TooFewPointsError, match="cannot pick 11 points from a cloud of 10"):
        farthest_point_sampling(points, 11)
    with pytest.raises(ValueError, match="count must be >= 0"):
        farthest_point_sampling(points, -1)
    with pytest.raises(ValueError, match="start_index 10 is outside"):
        farthest_point_sampling(points, 3, start_index=10)
    with pytest.raises(PointCloudShapeError, match=r"shape \(10, 2\) is not \(N, 3\)"):
        farthest_point_sampling(points[:, :2], 3)
    bad = points.copy()
    bad[4, 1] = np.nan
    with pytest.raises(NonFinitePointsError, match="NaN or inf"):
        farthest_point_sampling(bad, 3)
    with pytest.raises(TypeError):
        farthest_point_sampling(points, 2.5)


def test_fps_equals_the_greedy_definition_at_working_size():
    """4096 -> 1024 (the runtime's case): every pick is the point farthest from those before.

    Speed is measured in benchmarks/latency.py (the subsample stage), not asserted here.
    """
    points = np.random.default_rng(6).normal(size=(4096, 3))
    indices = farthest_point_sampling(points, 1024)
    assert len(np.unique(indices)) == 1024
    assert indices[0] == np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1))
    nearest_chosen = np.linalg.norm(points - points[indices[0]], axis=1)
    for index in indices[1:]:
        assert nearest_chosen[index] == nearest_chosen.max()
        nearest_chosen = np.minimum(nearest_chosen, np.linalg.norm(points - points[index], axis=1))


def _reference_fps_with_ties(points: np.ndarray, count: int, start: int) -> list[int]:
    """FPS with the documented tie rule, from scratch at every pick: the squared distance
    (x - x_c)**2 + (y - y_c)**2 + (z - z_c)**2 to the nearest chosen point; the lowest index
    within FPS_TIE_TOLERANCE x (the largest squared norm) of the largest such distance."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    tolerance = FPS_TIE_TOLERANCE * np.max(x * x + y * y + z * z)
    chosen = [start]
    while len(chosen) < count:
        nearest = np.min([(x - x[c]) ** 2 + (y - y[c]) ** 2 + (z - z[c]) ** 2 for c in chosen], axis=0)
        nearest[chosen] = -np.inf
        chosen.append(int(np.flatnonzero(nearest >= nearest.max() - tolerance)[0]))
    return chosen


def _fps_clouds() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(8)
    axis = np.linspace(-1.0, 1.0, 6)
    lattice = np.stack(np.meshgrid(axis, axis, axis[:3]), axis=-1).reshape(-1, 3)  # exact ties everywhere
    noisy = rng.normal(size=(150, 3))
    duplicated = np.concatenate([noisy[:60], noisy[:60], noisy[:10]])
    stray = np.concatenate([noisy[:90], [[40.0, 0.0, -30.0]]])
    return {"lattice": lattice, "noisy": noisy, "duplicated": duplicated, "stray": stray}


@pytest.mark.parametrize("name", ["lattice", "noisy", "duplicated", "stray"])
def test_fps_equals_the_reference_with_its_tie_rule(name):
    from logdesc_rt.sampling import _farthest_point_indices_from, _power_of_two_scale

    points = _fps_clouds()[name]
    centred = points - points.mean(axis=0)
    centred = centred / _power_of_two_scale(centred)
    starts = np.array([0, 3, len(points) - 1, 3])
    for count in (1, 40, len(points)):
        runs = _farthest_point_indices_from(centred, count, starts)
        assert runs.shape == (len(starts), count) and runs.dtype == np.int64
        for row, start in enumerate(starts):
            assert runs[row].tolist() == _reference_fps_with_ties(centred, count, int(start))
    default = farthest_point_sampling(points, 40)
    assert default.tolist() == _reference_fps_with_ties(centred, 40, int(default[0]))


def test_fps_large_coordinates():
    points = np.array([[1e15, 0, 0], [-1e15, 0, 0], [0, 0, 0], [0, 1e15, 0]])
    assert sorted(farthest_point_sampling(points, 4).tolist()) == [0, 1, 2, 3]


def test_voxel_downsample_one_point_per_voxel_nearest_to_mean():
    # Voxel grid anchored at the minimum corner (0, 0, 0), size 1.
    points = np.array(
        [
            [0.1, 0.1, 0.1],  # voxel (0,0,0)
            [0.4, 0.1, 0.1],  # voxel (0,0,0), nearest to its mean (0.275, 0.075, 0.075)
            [0.6, 0.1, 0.1],  # voxel (0,0,0)
            [1.5, 0.5, 0.5],  # voxel (1,0,0), alone
            [0.0, 0.0, 0.0],  # voxel (0,0,0); also the minimum corner
        ]
    )
    indices = voxel_downsample(points, 1.0)
    assert indices.tolist() == [1, 3]
    assert indices.dtype == np.int64


def test_voxel_downsample_ties_take_lowest_index_and_sorted():
    points = np.array([[0.2, 0, 0], [0.8, 0, 0], [2.5, 0, 0], [2.5, 0, 0]])
    assert voxel_downsample(points, 1.0).tolist() == [0, 2]


def test_voxel_downsample_count_matches_occupied_voxels():
    points = np.random.default_rng(7).uniform(0, 1, size=(2000, 3))
    voxel = 0.25
    occupied = {tuple(v) for v in np.floor((points - points.min(axis=0)) / voxel).astype(int)}
    indices = voxel_downsample(points, voxel)
    assert len(indices) == len(occupied)
    assert np.all(np.diff(indices) > 0)


def _brute_force_voxel(points: np.ndarray, voxel: float) -> list[int]:
    groups: dict[tuple, list[int]] = {}
    for index, cell in enumerate(np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)):
        groups.setdefault(tuple(cell), []).append(index)
    chosen = []
    for members in groups.values():
        mean = (points[members] - points.min(axis=0)).mean(axis=0)
        distances = np.array([np.sum((points[m] - points.min(axis=0) - mean) ** 2) for m in members])
        # Nearest the mean; distances equal up to round-off (two points: both equally far) tie,
        # and the lowest index wins, so the choice cannot depend on the frame's round-off.
        tied = distances <= distances.min() + FPS_TIE_TOLERANCE * voxel**2
        chosen.append(members[int(np.argmax(tied))])
    return sorted(chosen)


@pytest.mark.parametrize("far_corner", [10.0, 1e9])  # 1e9: too many cells for one int64 key
def test_voxel_downsample_matches_brute_force(far_corner):
    rng = np.random.default_rng(9)
    points = np.concatenate([rng.uniform(0, 2, size=(300, 3)), [[far_corner] * 3]])
    assert voxel_downsample(points, 0.5).tolist() == _brute_force_voxel(points, 0.5)


def test_voxel_downsample_errors():
    points = np.random.default_rng(8).normal(size=(10, 3))
    for bad_size in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="voxel_size must be finite and > 0"):
            voxel_downsample(points, bad_size)
    with pytest.raises(TooFewPointsError, match="at least 1"):
        voxel_downsample(np.empty((0, 3)), 0.1)
    with pytest.raises(LogdescError, match="too many voxels"):
        voxel_downsample(np.array([[0.0, 0, 0], [1e14, 0, 0]]), 1e-3)


finite_clouds = hnp.arrays(
    np.float64,
    st.tuples(st.integers(1, 12), st.just(3)),
    elements=st.floats(allow_nan=False, allow_infinity=False, width=64),
)


@settings(max_examples=60, deadline=None)
@given(points=finite_clouds, fraction=st.floats(0, 1))
def test_fps_property_random_input(points, fraction):
    count = int(round(fraction * len(points)))
    try:
        indices = farthest_point_sampling(points, count)
    except LogdescError:  # e.g. coordinates beyond validation.MAX_ABS_COORDINATE
        return
    assert len(indices) == count and len(np.unique(indices)) == count
    assert np.all((indices >= 0) & (indices < len(points)))


@settings(max_examples=60, deadline=None)
@given(points=finite_clouds, voxel_size=st.floats(1e-6, 1e6))
def test_voxel_property_random_input(points, voxel_size):
    try:
        indices = voxel_downsample(points, voxel_size)
    except LogdescError:
        return
    assert 1 <= len(indices) <= len(points)
    assert np.all(np.diff(indices) > 0)


@pytest.mark.parametrize("case", ["random", "lattice ties", "duplicates"])
def test_fps_from_several_starts_is_each_single_run(case):
    """FSR samples its rounds in one loop; row r must be exactly the run from start r."""
    from logdesc_rt.sampling import _farthest_point_indices, _farthest_point_indices_from

    rng = np.random.default_rng(0)
    points = rng.normal(size=(300, 3))
    if case == "lattice ties":
        points = np.round(points * 2.0) / 2.0
    elif case == "duplicates":
        points[:150] = points[0]
    starts = rng.integers(0, len(points), size=7)
    together = _farthest_point_indices_from(points, 60, starts)
    for row, start in zip(together, starts, strict=True):
        np.testing.assert_array_equal(row, _farthest_point_indices(points, 60, int(start)))


def test_seeded_subset_is_all_points_below_the_limit_and_a_sorted_draw_above():
    from logdesc_rt.sampling import seeded_subset

    np.testing.assert_array_equal(seeded_subset(5, 10, np.random.default_rng(0)), np.arange(5))
    np.testing.assert_array_equal(seeded_subset(5, None, np.random.default_rng(0)), np.arange(5))
    drawn = seeded_subset(1000, 100, np.random.default_rng(3))
    assert len(np.unique(drawn)) == 100 and np.all(np.diff(drawn) > 0)
    np.testing.assert_array_equal(drawn, seeded_subset(1000, 100, np.random.default_rng(3)))

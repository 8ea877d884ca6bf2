"""Stray points, box outliers, frame-independent sampling and pairs that cannot be registered.

Before v4's runtime work one stray point 100 radii away shrank the object to a speck in network
units (the scale came from the farthest point) and every such pair failed; farthest-point
sampling above the working size picked other points after a 1 km shift; a pair with no overlap
raised instead of returning a result.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from logdesc_rt import Registrar
from logdesc_rt.config import NormalizationConfig
from logdesc_rt.demo import make_demo_pair
from logdesc_rt.metrics import rotation_error_deg
from logdesc_rt.normalization import PairNormalization
from logdesc_rt.outliers import stray_point_mask
from logdesc_rt.sampling import farthest_point_sampling, working_subset
from logdesc_rt.synthetic import make_pair

from .shapes import fibonacci_sphere

FAR_SHIFT = np.array([1000.0, 250.0, -40.0])  # about a kilometre, in metres
TURN = Rotation.from_euler("xyz", [0.3, 1.1, -0.4])


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    return Registrar()


def _radius(points: np.ndarray) -> float:
    return float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())


def _stray_points(points: np.ndarray, count: int, radii: float, rng: np.random.Generator) -> np.ndarray:
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return points.mean(axis=0) + radii * _radius(points) * directions


def _box_outliers(points: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """``fraction`` x N points uniform in the bounding box grown by half (a quarter each side)."""
    low, high = points.min(axis=0), points.max(axis=0)
    margin = 0.25 * (high - low)
    return rng.uniform(low - margin, high + margin, size=(round(fraction * len(points)), 3))


# -- the pieces ----------------------------------------------------------------------------------


def test_the_stray_test_flags_far_points_and_clumps_and_leaves_a_surface_alone():
    rng = np.random.default_rng(0)
    surface = fibonacci_sphere(2000) * [1.0, 0.7, 0.4]
    strays = _stray_points(surface, 3, 50.0, rng)
    clump = surface.mean(axis=0) + [20.0, 0, 0] + rng.normal(scale=0.01, size=(4, 3))  # 4 < k = 6 points
    mask = stray_point_mask(np.vstack([surface, strays, clump]))
    assert not mask[: len(surface)].any()
    assert mask[len(surface):].all()
    # Distances only: the same points are flagged wherever the cloud sits, at any scale.
    moved = TURN.apply(np.vstack([surface, strays, clump]) * 1000.0) + FAR_SHIFT
    assert np.array_equal(stray_point_mask(moved), mask)


def test_one_stray_point_no_longer_sets_the_scale():
    pair = make_demo_pair()
    clean = PairNormalization.fit(pair.source, pair.target)
    stray = np.vstack([pair.source, _stray_points(pair.source, 1, 100.0, np.random.default_rng(1))])
    robust = PairNormalization.fit(stray, pair.target)
    assert robust.scale == pytest.approx(clean.scale, rel=1e-12)
    # With the test turned off (as before v4) the scale is a hundred times too large.
    naive = PairNormalization.fit(stray, pair.target, NormalizationConfig(stray_ratio=0))
    assert naive.scale > 50 * clean.scale


def _lattice() -> np.ndarray:
    """(3000, 3) a 60 x 50 lattice on a gently curved sheet: many exactly equal distances."""
    x, y = np.meshgrid(np.arange(60) * 0.01, np.arange(50) * 0.01)
    sheet = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    sheet[:, 2] = 0.05 * np.sin(3.0 * sheet[:, 0])
    return sheet


def test_farthest_point_sampling_above_the_working_size_ignores_where_the_cloud_sits():
    lattice = _lattice()
    reference = farthest_point_sampling(lattice, 1024)
    assert np.array_equal(farthest_point_sampling(lattice + FAR_SHIFT, 1024), reference)
    assert np.array_equal(farthest_point_sampling(TURN.apply(lattice) + FAR_SHIFT, 1024), reference)


@pytest.mark.parametrize("method", ["fps", "voxel"])
def test_the_working_subset_ignores_where_the_cloud_sits(method):
    """Above the working size, for both subsampling methods (the voxel grid is built in the
    cloud's own principal frame)."""
    rng = np.random.default_rng(2)
    surface = fibonacci_sphere(3000) * [1.0, 0.7, 0.4] + rng.normal(scale=0.003, size=(3000, 3))
    reference = working_subset(surface, 1024, method)
    assert len(reference) == 1024
    assert np.array_equal(working_subset(surface + FAR_SHIFT, 1024, method), reference)
    assert np.array_equal(working_subset(TURN.apply(surface) + FAR_SHIFT, 1024, method), reference)


def test_the_working_subset_sets_stray_points_aside():
    rng = np.random.default_rng(3)
    surface = fibonacci_sphere(1500)
    cloud = np.vstack([surface, _stray_points(surface, 3, 30.0, rng)])
    kept = working_subset(cloud, 1024)
    assert kept.max() < len(surface), "farthest-point sampling spent picks on stray points"


# -- registration --------------------------------------------------------------------------------


def test_one_stray_point_at_100_radii_moves_the_pose_by_under_half_a_degree(registrar):
    pair = make_demo_pair()
    clean = registrar.register(pair.source, pair.target)
    assert clean.success
    stray = np.vstack([pair.source, _stray_points(pair.source, 1, 100.0, np.random.default_rng(4))])
    disturbed = registrar.register(stray, pair.target)
    assert rotation_error_deg(disturbed.rotation, clean.rotation) < 0.5
    assert disturbed.success


def test_a_pair_with_no_overlap_is_a_result_not_an_exception(registrar):
    """No surface in common: the default reading of the matches (dustbin out of the mutual
    test) finds matches but no pose verification accepts; the paper's reading finds too few
    matches and returns the identity. Both are results with success False and a reason."""
    rng = np.random.default_rng(0)
    blob = rng.normal(size=(600, 3)) * [0.3, 0.05, 0.01]  # a flat blob against noise in a cube
    noise = rng.uniform(-1, 1, size=(600, 3))
    result = registrar.register(blob, noise)
    assert not result.success and result.confidence < result.config.verification.success_threshold
    assert result.reason is not None and result.reason.startswith("not verified")
    assert result.to_dict()["reason"] == result.reason
    paper_reading = registrar.register(blob, noise, config={"matching": {"dustbin_in_mutual_test": True}})
    assert not paper_reading.success and paper_reading.confidence == 0.0
    assert paper_reading.reason is not None and paper_reading.reason.startswith("too few matches")
    assert paper_reading.pose_estimator == "none" and np.array_equal(paper_reading.transformation, np.eye(4))


def test_box_outliers_in_both_clouds_cost_at_most_two_pairs_in_twenty(registrar, shared_data):
    """20 ModelNet10 test pairs (noisy, partial, any relative rotation), then the same pairs with
    2 % uniform outliers in each cloud's grown bounding box: at most 10 points of success lost.
    Measured when the bar was set: 19 clean, 17 with outliers. The two lost pairs (3 and 10) turn into
    half-turn flips of a symmetric shape; pair 10 was a near miss clean (5.2 degrees) until the
    pose without ICP gained its point-to-plane steps (4.4), so before them the same loss
    showed as one pair (18 -> 17) and this test allowed one."""
    h5py = pytest.importorskip("h5py")
    with h5py.File(shared_data / "modelnet10_hdf5_1024" / "ply_data_test0.h5", "r") as handle:
        shapes = handle["data"][:20].astype(np.float64)
    clean_hits = outlier_hits = 0
    for index, shape in enumerate(shapes):
        pair = make_pair(shape, "partial", np.random.default_rng([7, index]), any_relative_rotation=True)
        rng = np.random.default_rng([8, index])
        source = np.vstack([pair.source, _box_outliers(pair.source, 0.02, rng)])
        target = np.vstack([pair.target, _box_outliers(pair.target, 0.02, rng)])
        for clouds, hits in (((pair.source, pair.target), "clean"), ((source, target), "outliers")):
            result = registrar.register(*clouds)
            right = rotation_error_deg(result.rotation, pair.T_gt[:3, :3]) < 5.0
            if hits == "clean":
                clean_hits += right
            else:
                outlier_hits += right
    assert clean_hits >= 15, f"the clean pairs themselves fail: {clean_hits} of 20"
    assert outlier_hits >= clean_hits - 2, f"{clean_hits} of 20 clean, {outlier_hits} with 2 % box outliers"

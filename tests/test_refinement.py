"""ICP refinement on a real scan pair, wherever the clouds sit and whatever their unit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from logdesc_rt.metrics import rotation_error_deg
from logdesc_rt.refinement import ICP_METHODS, icp

from .bunny import bunny_pair

# A fixed direction for the shifts, not along an axis.
SHIFT_DIRECTION = np.array([1.0, -2.0, 3.0]) / np.sqrt(14.0)
# Placements: offset of both clouds (metres along SHIFT_DIRECTION) and unit (1 = metres,
# 1000 = millimetres, 0.01 = "hectometres").
PLACEMENTS = [(5.0, 1.0), (1e3, 1.0), (1e5, 1.0), (1e3, 100.0), (1e5, 1000.0), (0.0, 0.01), (10.0, 0.01)]


@pytest.fixture(scope="module")
def scan_pair(request, shared_data):
    """bun000 -> bun045 (3000 random source points, the full target), the truth, and a start 3 deg / 4 mm off."""
    source, _, truth = bunny_pair(shared_data, "bun000", "bun045", points=3000, seed=0)
    _, target, _ = bunny_pair(shared_data, "bun000", "bun045")
    generator = np.random.default_rng(1)
    perturbation = np.eye(4)
    axis = generator.normal(size=3)
    perturbation[:3, :3] = Rotation.from_rotvec(np.deg2rad(3.0) * axis / np.linalg.norm(axis)).as_matrix()
    perturbation[:3, 3] = 0.004 * SHIFT_DIRECTION
    return source, target, truth, perturbation @ truth


def _placement(offset: float, scale: float) -> np.ndarray:
    """(4, 4) similarity x -> scale * x + offset * SHIFT_DIRECTION, applied to both clouds."""
    placement = np.eye(4)
    placement[:3, :3] *= scale
    placement[:3, 3] = offset * SHIFT_DIRECTION
    return placement


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


@pytest.mark.parametrize("method", ICP_METHODS)
def test_icp_recovers_the_true_pose_of_a_real_pair(scan_pair, method):
    source, target, truth, initial = scan_pair
    assert rotation_error_deg(initial[:3, :3], truth[:3, :3]) > 2.9
    result = icp(source, target, initial, max_distance=0.005, method=method, max_iterations=60)
    assert rotation_error_deg(result.transformation[:3, :3], truth[:3, :3]) < 0.5
    assert np.linalg.norm(result.transformation[:3, 3] - truth[:3, 3]) < 0.001  # 1 mm
    assert result.converged
    assert 0 < result.iterations <= 60
    assert 0.5 < result.fitness <= 1.0 and 0 < result.inlier_rmse < 0.002


@pytest.mark.parametrize("method", ICP_METHODS)
@pytest.mark.parametrize(("offset", "scale"), PLACEMENTS)
def test_icp_result_does_not_depend_on_placement_or_unit(scan_pair, method, offset, scale):
    """Shift both clouds by up to 1e5 m and change their unit: the same pose comes back.

    The pose found on the moved clouds, mapped back to the original frame, must equal the
    pose found on the original clouds (within 0.01 deg and 10 micrometres).
    """
    source, target, _, initial = scan_pair
    reference = icp(source, target, initial, max_distance=0.005, method=method, max_iterations=60)
    placement = _placement(offset, scale)
    unplace = np.linalg.inv(placement)
    moved = icp(
        _apply(placement, source),
        _apply(placement, target),
        placement @ initial @ unplace,
        max_distance=0.005 * scale,
        method=method,
        max_iterations=60,
    )
    back = unplace @ moved.transformation @ placement
    assert rotation_error_deg(back[:3, :3], reference.transformation[:3, :3]) < 0.01
    assert np.linalg.norm(back[:3, 3] - reference.transformation[:3, 3]) < 1e-5
    assert moved.fitness == pytest.approx(reference.fitness, abs=0.002)
    assert moved.inlier_rmse == pytest.approx(reference.inlier_rmse * scale, rel=0.01)


def test_normals_computed_on_demand_are_estimate_normals():
    """ICP computes target normals only where it meets the target; each is exactly what
    estimate_normals gives that point (same tree, neighbours and covariance)."""
    from pykdtree.kdtree import KDTree

    from logdesc_rt.refinement import LazyNormals, estimate_normals

    points = np.random.default_rng(0).normal(size=(3000, 3)) * [1.0, 0.6, 0.1]
    everywhere = estimate_normals(points)
    lazy = LazyNormals(points, KDTree(points))
    picked = np.random.default_rng(1).integers(0, len(points), size=700)
    np.testing.assert_array_equal(lazy.at(picked), everywhere[picked])
    np.testing.assert_array_equal(lazy.at(np.arange(len(points))), everywhere)


def test_icp_with_the_callers_lazy_normals_and_spacing_refines_as_with_its_own():
    """A caller's LazyNormals of the target (user frame) and its median spacing give ICP the
    pose it finds computing both itself, and the normals ICP met stay computed for the caller;
    normals of another cloud are refused."""
    from pykdtree.kdtree import KDTree

    from logdesc_rt.refinement import LazyNormals, estimate_normals

    generator = np.random.default_rng(2)
    u, v = generator.uniform(-1.0, 1.0, size=(2, 4000))
    target = np.column_stack([u, v, 0.3 * np.sin(2.0 * u) * np.cos(3.0 * v)]) + [100.0, -50.0, 20.0]
    source = target[:1500] + generator.normal(scale=0.003, size=(1500, 3))
    start = np.eye(4)
    start[:3, :3] = Rotation.from_euler("xyz", [1.5, -2.0, 1.0], degrees=True).as_matrix()
    start[:3, 3] = start[:3, :3] @ -target.mean(axis=0) + target.mean(axis=0) + [0.01, 0.02, -0.01]
    tree = KDTree(target)
    spacing = float(np.median(tree.query(target, k=2)[0][:, 1]))
    lazy = LazyNormals(target, tree)
    own = icp(source, target, start, 0.1, adaptive=True, target_normals=estimate_normals(target))
    given = icp(source, target, start, 0.1, adaptive=True, target_normals=lazy, target_spacing=spacing)
    np.testing.assert_allclose(given.transformation, own.transformation, rtol=0, atol=1e-12)
    assert given.iterations == own.iterations
    assert 0 < lazy.known.sum() < len(target)  # computed where ICP met the target only
    with pytest.raises(ValueError, match="target_normals"):
        icp(source, target[:-1], start, 0.1, target_normals=lazy)


def test_icp_on_a_source_subset_lands_where_the_whole_cloud_does(scan_pair, shared_data):
    """A seeded subset of the source (max_source_points) pulls the pose as all points do:
    on the real bun000 -> bun045 pair (40k target) the two results agree within 0.05 degree
    and 0.2 mm, and the subset run is deterministic."""
    _, target, _, start = scan_pair
    full_source, _, _ = bunny_pair(shared_data, "bun000", "bun045")  # all 40k source points
    whole = icp(full_source, target, start, 0.005, adaptive=True)
    subset = icp(full_source, target, start, 0.005, adaptive=True, max_source_points=5000, seed=3)
    again = icp(full_source, target, start, 0.005, adaptive=True, max_source_points=5000, seed=3)
    np.testing.assert_array_equal(subset.transformation, again.transformation)
    assert rotation_error_deg(subset.transformation[:3, :3], whole.transformation[:3, :3]) < 0.05
    centre = full_source.mean(axis=0)
    moved = lambda pose: pose[:3, :3] @ centre + pose[:3, 3]  # noqa: E731
    assert np.linalg.norm(moved(subset.transformation) - moved(whole.transformation)) < 2e-4
    with pytest.raises(ValueError, match="max_source_points"):
        icp(full_source, target, start, 0.005, max_source_points=2)


def test_coarse_stages_land_where_every_stage_on_all_points_does(scan_pair, shared_data):
    """Adaptive stages on a coarse subset, then the polish at the last distance on the whole
    (coarse_source_points): on the real bun000 -> bun045 pair (40k points each) the pose agrees
    with every stage run on all points within 1e-3 degree and 0.01 mm, deterministically."""
    _, target, _, start = scan_pair
    full_source, _, _ = bunny_pair(shared_data, "bun000", "bun045")
    options = dict(adaptive=True, max_source_points=20_000, seed=3)
    every = icp(full_source, target, start, 0.005, **options)
    coarse = icp(full_source, target, start, 0.005, coarse_source_points=2000, **options)
    again = icp(full_source, target, start, 0.005, coarse_source_points=2000, **options)
    np.testing.assert_array_equal(coarse.transformation, again.transformation)
    assert rotation_error_deg(coarse.transformation[:3, :3], every.transformation[:3, :3]) < 1e-3
    centre = full_source.mean(axis=0)
    moved = lambda pose: pose[:3, :3] @ centre + pose[:3, 3]  # noqa: E731
    assert np.linalg.norm(moved(coarse.transformation) - moved(every.transformation)) < 1e-5
    assert coarse.fitness == pytest.approx(every.fitness, abs=1e-3)


def test_coarse_subset_changes_nothing_on_a_cloud_it_covers():
    """A source of at most coarse_source_points points refines exactly as without the option,
    and a coarse size below the minimum of correspondences is refused by name."""
    generator = np.random.default_rng(5)
    u, v = generator.uniform(-1.0, 1.0, size=(2, 3000))
    target = np.column_stack([u, v, 0.2 * np.sin(2.0 * u) * np.cos(3.0 * v)])
    start = np.eye(4)
    start[:3, :3] = Rotation.from_euler("xyz", [2.0, -1.0, 3.0], degrees=True).as_matrix()
    start[:3, 3] = [0.02, -0.01, 0.03]
    source = target[:2500] + generator.normal(scale=0.002, size=(2500, 3))
    plain = icp(source, target, start, 0.1, adaptive=True)
    covered = icp(source, target, start, 0.1, adaptive=True, coarse_source_points=2500)
    np.testing.assert_array_equal(covered.transformation, plain.transformation)
    assert covered.iterations == plain.iterations
    with pytest.raises(ValueError, match="coarse_source_points"):
        icp(source, target, start, 0.1, coarse_source_points=2)


@pytest.mark.parametrize("steps, stops_after", [((1, -1), 2), ((1, 1, -2), 3)])
def test_icp_stops_when_its_pose_comes_back(monkeypatch, steps, stops_after):
    """A stage whose updates go round (correspondences flipping between sets, as on source subsets
    of real scans) stops once the pose is back where it was, instead of running out of
    iterations; a sequence that does not come back runs on."""
    from pykdtree.kdtree import KDTree

    import logdesc_rt.refinement as refinement

    turn = Rotation.from_rotvec([0.0, 0.0, 1e-3])
    updates = iter([s for _ in range(20) for s in steps])

    def scripted_step(matrix, rhs, pivot):
        step = np.eye(4)
        step[:3, :3] = (turn ** next(updates)).as_matrix()
        return step

    monkeypatch.setattr(refinement, "plane_step", scripted_step)
    points = np.random.default_rng(0).normal(size=(50, 3))
    normals = refinement._GivenNormals(np.tile([0.0, 0.0, 1.0], (50, 1)))
    _, iterations, reason = refinement._icp_stage(points, points, KDTree(points), normals, np.eye(4), 10.0, 30, 1e-7)
    assert (iterations, reason) == (stops_after, "cycle")
    updates = iter([1] * 40)  # always the same way: never back
    _, iterations, reason = refinement._icp_stage(points, points, KDTree(points), normals, np.eye(4), 10.0, 30, 1e-7)
    assert (iterations, reason) == (30, "max_iterations")


def test_the_batched_screen_recovers_a_small_motion_and_leaves_a_hopeless_start():
    """point_to_point_icp_batch: one start near the truth converges to it, one at the truth
    stays, one with no target point within reach is left where it is (fitness 0)."""
    from pykdtree.kdtree import KDTree
    from scipy.spatial.transform import Rotation

    from logdesc_rt.refinement import point_to_point_icp_batch

    rng = np.random.default_rng(0)
    target = rng.normal(size=(3000, 3)) * [1.0, 0.6, 0.3]
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_rotvec([0.1, -0.05, 0.08]).as_matrix()
    truth[:3, 3] = [0.05, 0.02, -0.03]
    source = (target - truth[:3, 3]) @ truth[:3, :3]  # truth maps source onto target
    far = np.eye(4)
    far[:3, 3] = [100.0, 0.0, 0.0]
    starts = np.stack([np.eye(4), truth, far])
    poses, fitness = point_to_point_icp_batch(source[:300], KDTree(target), target, starts, 0.3, 15)
    assert np.allclose(poses[0], truth, atol=1e-9) and np.allclose(poses[1], truth, atol=1e-9)
    assert np.array_equal(poses[2], far) and fitness[2] == 0.0
    assert fitness[0] == fitness[1] == 1.0


def test_compiled_normals_and_normal_equations_equal_their_numpy_forms():
    """The compiled kernels (logdesc_rt.pose.kernels) compute what LAPACK's eigh and the NumPy
    Jacobian products compute, up to rounding: on flat, thin, random and rounded (duplicate,
    nearly isotropic) neighbourhoods."""
    from logdesc_rt.pose.kernels import neighbourhood_normals, plane_normal_equations

    rng = np.random.default_rng(7)
    for flatness in (1e-4, 0.05, 1.0):
        points = rng.normal(size=(600, 3)) * np.array([1.0, 0.5, flatness])
        for rounding in (None, 1):
            cloud = points if rounding is None else np.round(points, rounding)
            index = rng.integers(0, len(cloud), size=(300, 10)).astype(np.int64)
            neighbourhoods = cloud[index]
            centred = neighbourhoods - neighbourhoods.mean(axis=1, keepdims=True)
            values, vectors = np.linalg.eigh(centred.transpose(0, 2, 1) @ centred)
            normals = neighbourhood_normals(cloud, index)
            assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
            separated = values[:, 1] - values[:, 0] > 1e-6 * values[:, 2]  # a least axis exists
            assert separated.mean() > 0.9
            assert np.abs(np.sum(normals * vectors[:, :, 0], axis=1))[separated].min() > 1 - 1e-9

    arm, offset, directions = rng.normal(size=(3, 400, 3))
    weights = rng.uniform(0, 1, size=400)
    jacobian = np.concatenate([np.cross(arm, directions), directions], axis=1)
    residual = np.sum(offset * directions, axis=1)
    matrix, rhs = plane_normal_equations(arm, offset, directions, weights)
    assert np.allclose(matrix, (jacobian * weights[:, None]).T @ jacobian, rtol=1e-12, atol=1e-12)
    assert np.allclose(rhs, (jacobian * weights[:, None]).T @ residual, rtol=1e-12, atol=1e-12)

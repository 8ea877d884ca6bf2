"""align(): synthetic scans of the Bunny mesh with known poses come back in one scan's frame,
a scan that overlaps nothing is reported disconnected (and, given first, does not leave the
others unplaced); the pose graph alone recovers poses from noisy edges and prunes a wrong
one; candidate graphs stay below N^2 / 2.
(About 30 s on 2 cores, nearly all of it the pairwise registrations.)"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from logdesc_rt.align import (
    AlignConfig,
    PoseEdge,
    align,
    candidate_pairs,
    largest_set_reference,
    merge_scans,
    optimise_pose_graph,
    write_merged,
)
from logdesc_rt.io import read_point_attributes, read_point_cloud
from logdesc_rt.metrics import rotation_error_deg


def _rigid(rng: np.random.Generator, degrees: float, shift: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("zyx", rng.uniform(-degrees, degrees, 3), degrees=True).as_matrix()
    pose[:3, 3] = rng.uniform(-shift, shift, 3)
    return pose


def bunny_scans(mesh: np.ndarray, views_deg, seed: int = 0, points: int = 6000):
    """Synthetic range scans of the Bunny mesh: the vertices seen from each view direction
    (around the vertical axis), a random subset of ``points``, each moved by a random rigid
    motion (<= 20 degrees per axis, <= 5 cm). Returns the scans and the true poses (scan k ->
    scan 0's frame), (4, 4) each."""
    rng = np.random.default_rng(seed)
    centre = mesh.mean(axis=0)
    radius = np.linalg.norm(mesh - centre, axis=1).max()
    scans, motions = [], []
    for angle in np.radians(views_deg):
        view = np.array([np.sin(angle), 0.0, np.cos(angle)])
        seen = mesh[(mesh - centre) @ view > -0.1 * radius]
        seen = seen[rng.choice(len(seen), min(points, len(seen)), replace=False)]
        motion = _rigid(rng, 20.0, 0.05)
        scans.append(seen @ motion[:3, :3].T + motion[:3, 3])
        motions.append(motion)
    return scans, [motions[0] @ np.linalg.inv(motion) for motion in motions]


@pytest.fixture(scope="module")
def mesh(shared_data) -> np.ndarray:
    path = shared_data / "stanford_bunny" / "reconstruction" / "bun_zipper.ply"
    if not path.exists():
        pytest.skip(f"Bunny mesh not found at {path}")
    return read_point_cloud(path)


def test_align_recovers_known_poses_and_reports_the_scan_that_overlaps_nothing(mesh, tmp_path):
    """The scan that overlaps nothing is given first: the others are still placed, in the
    frame of the first scan of their connected set (a.ply), and the result says so."""
    scans, truth = bunny_scans(mesh, [0, 40, 80, 120])
    elsewhere = np.random.default_rng(1).normal(size=(3000, 3)) * [0.05, 0.02, 0.01] + [2.0, 0.0, 0.0]
    names = ["stray.ply", "a.ply", "b.ply", "c.ply", "d.ply"]
    pairs_file = tmp_path / "pairs.jsonl"
    result = align([elsewhere, *scans], names=names, workers=2, progress=False, pairs_output=pairs_file)

    radius = np.linalg.norm(scans[0] - scans[0].mean(axis=0), axis=1).max()
    assert result.disconnected == ["stray.ply"]
    assert result.reference == "a.ply"
    assert set(result.poses) == set(names[1:])
    np.testing.assert_array_equal(result.poses["a.ply"], np.eye(4))
    for name, true_pose in zip(names[1:], truth):
        pose = result.poses[name]
        assert rotation_error_deg(pose[:3, :3], true_pose[:3, :3]) < 1.0, name
        # 1 degree turns a point at the scan's radius by 1.75 % of it: the translation's bound
        # matches the rotation's.
        assert np.linalg.norm(pose[:3, 3] - true_pose[:3, 3]) < 0.02 * radius, name
    assert result.candidate_pairs == 10
    assert {(item["first"], item["second"]) for item in result.rejected} >= {(0, k) for k in range(1, 5)}

    payload = json.loads(json.dumps(result.to_json()))
    assert set(payload["poses"]) == set(names[1:]) and payload["disconnected"] == ["stray.ply"]
    assert payload["reference"] == "a.ply"
    assert payload["pairs"] and all(p["residual_rotation_deg"] is not None for p in payload["pairs"])
    assert all("stray.ply" not in (p["source"], p["target"]) for p in payload["pairs"])

    # Resumed from its pairs file, align registers nothing again and places the scans the same.
    again = align([elsewhere, *scans], names=names, workers=2, progress=False, pairs_output=pairs_file)
    assert len(pairs_file.read_text().splitlines()) == 10
    assert again.records == result.records
    for name in names[1:]:
        np.testing.assert_array_equal(again.poses[name], result.poses[name])

    points, scan = merge_scans([elsewhere, *scans], result, voxel_size=0.004)
    assert set(np.unique(scan)) == {1, 2, 3, 4}, "the disconnected scan is not merged"
    assert len(points) < sum(len(s) for s in scans)
    # The merged scans overlap: b's points lie on a's (the reference's) surface.
    from scipy.spatial import cKDTree

    distances, _ = cKDTree(scans[0]).query(points[scan == 2])
    assert np.median(distances) < 0.002
    written = write_merged(tmp_path / "merged.ply", [elsewhere, *scans], result, voxel_size=0.004)
    assert written == len(points)
    np.testing.assert_array_equal(read_point_attributes(tmp_path / "merged.ply")["scan"], scan)


def _edge(first, second, poses, rng, degrees=0.2, shift=0.001, confidence=0.9) -> PoseEdge:
    noise = _rigid(rng, degrees, shift)
    return PoseEdge(first, second, np.linalg.inv(poses[first]) @ poses[second] @ noise, confidence, 0.5, 0.002)


def test_pose_graph_averages_noisy_edges_and_prunes_a_wrong_one():
    rng = np.random.default_rng(3)
    count = 6
    poses = [np.eye(4)] + [_rigid(rng, 90.0, 0.3) for _ in range(count - 1)]
    centroids = rng.normal(size=(count, 3)) * 0.05
    radii = np.full(count, 0.1)
    edges = [_edge(i, j, poses, rng) for i in range(count) for j in range(i + 1, count)]
    wrong = PoseEdge(1, 4, _rigid(rng, 60.0, 0.1), 0.95, 0.5, 0.002)
    edges.append(wrong)
    found, scored = optimise_pose_graph(count, edges, centroids, radii, AlignConfig())
    assert sorted(found) == list(range(count))
    for index in range(count):
        assert rotation_error_deg(found[index][:3, :3], poses[index][:3, :3]) < 0.3
    pruned = [edge for edge in scored if not edge.kept]
    assert len(pruned) == 1 and pruned[0].transformation is wrong.transformation
    assert all(edge.residual_rotation_deg < 1.0 for edge in scored if edge.kept)


def test_pose_graph_leaves_unconnected_scans_without_a_pose():
    rng = np.random.default_rng(4)
    poses = [np.eye(4)] + [_rigid(rng, 30.0, 0.1) for _ in range(4)]
    edges = [_edge(0, 1, poses, rng), _edge(1, 2, poses, rng), _edge(3, 4, poses, rng)]
    found, scored = optimise_pose_graph(5, edges, np.zeros((5, 3)), np.full(5, 0.1))
    assert sorted(found) == [0, 1, 2]
    # A chain has no redundancy: the poses are the composed edges.
    np.testing.assert_allclose(found[2], edges[0].transformation @ edges[1].transformation, atol=1e-6)
    assert np.isnan(scored[-1].residual_rotation_deg), "edges outside scan 0's component are not solved"


def test_candidate_graph_is_all_pairs_for_few_scans_and_sparse_but_connected_for_many(mesh):
    few = [np.random.default_rng(k).normal(size=(50, 3)) for k in range(5)]
    assert candidate_pairs(few) == [(i, j) for i in range(5) for j in range(i + 1, 5)]
    scans, _ = bunny_scans(mesh, np.arange(0, 360, 18), points=1500)  # 20 views
    pairs = candidate_pairs(scans, AlignConfig(neighbours=3))
    count = len(scans)
    assert len(pairs) <= count * 4 < count * (count - 1) // 2
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(pairs)), tuple(np.array(pairs).T)), shape=(count, count))
    assert connected_components(graph, directed=False)[0] == 1


def test_the_default_reference_is_the_first_scan_of_the_largest_connected_set():
    rng = np.random.default_rng(5)
    poses = [_rigid(rng, 30.0, 0.1) for _ in range(6)]
    # Scan 0 alone, scans 1-3 connected, 4-5 connected: the reference is scan 1.
    edges = [_edge(1, 2, poses, rng), _edge(2, 3, poses, rng), _edge(4, 5, poses, rng)]
    assert largest_set_reference(6, edges) == 1
    # Sets of equal size: the one holding the lowest index, so scan 0 when it is in one.
    assert largest_set_reference(6, [_edge(0, 5, poses, rng), _edge(1, 2, poses, rng)]) == 0
    assert largest_set_reference(6, []) == 0
    found, _ = optimise_pose_graph(6, edges, np.zeros((6, 3)), np.full(6, 0.1), reference=1)
    assert sorted(found) == [1, 2, 3]
    np.testing.assert_array_equal(found[1], np.eye(4))
    expected = np.linalg.inv(poses[1]) @ poses[3]
    assert rotation_error_deg(found[3][:3, :3], expected[:3, :3]) < 0.5


def test_bad_inputs_are_named():
    cloud = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(ValueError, match="at least 2 scans"):
        align([cloud])
    with pytest.raises(ValueError, match="unique"):
        align([cloud, cloud + 1], names=["x", "x"])
    with pytest.raises(ValueError, match="min_confidence"):
        AlignConfig(min_confidence=1.5)
    with pytest.raises(ValueError, match="reference"):
        AlignConfig(reference=-1)
    with pytest.raises(ValueError, match="reference 5 is not a scan index"):
        align([cloud, cloud + 1], config=AlignConfig(reference=5))

"""The pair normalisation maps clouds into network units and poses back exactly."""

from __future__ import annotations

import numpy as np

from logdesc_rt.normalization import PairNormalization

from .shapes import fibonacci_sphere, random_rigid_transform


def kabsch(source, target):
    source_mean, target_mean = source.mean(0), target.mean(0)
    u, _, vt = np.linalg.svd((source - source_mean).T @ (target - target_mean))
    rotation = vt.T @ np.diag([1, 1, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = target_mean - rotation @ source_mean
    return pose


def test_pose_in_network_frame_maps_back_exactly_to_user_frame():
    rng = np.random.default_rng(0)
    # A metre-scale scan far from the origin, and a partial copy of it moved rigidly.
    source = fibonacci_sphere(500, radius=0.08) * [1.0, 0.5, 0.7] + [120.0, -40.0, 3.0]
    true_pose = random_rigid_transform(rng, translation_scale=10.0)
    target = (source @ true_pose[:3, :3].T + true_pose[:3, 3])[:350]
    normalization = PairNormalization.fit(source, target)
    network_source = normalization.source_to_network(source[:350])
    network_target = normalization.target_to_network(target)
    # Both clouds are centred and the larger fits the unit sphere exactly.
    assert np.allclose(network_target.mean(0), 0.0, atol=1e-12)
    radii = [np.linalg.norm(c - c.mean(0), axis=1).max()
             for c in (normalization.source_to_network(source), network_target)]
    assert np.isclose(max(radii), 1.0)
    network_pose = kabsch(network_source, network_target)
    recovered = normalization.pose_to_user_frame(network_pose)
    assert np.allclose(recovered, true_pose, atol=1e-9)
    assert np.allclose(normalization.pose_to_network_frame(true_pose), network_pose, atol=1e-9)

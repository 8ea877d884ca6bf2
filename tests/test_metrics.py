"""Registration metrics (DCP / the paper) and matching metrics (MDGAT)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from logdesc_rt.metrics import (
    IGNORED,
    euler_angles_deg,
    matching_metrics,
    registration_metrics,
    rotation_error_deg,
    transformed_source_rmse,
    translation_error,
    twin_distance,
)


def transform(rotation: np.ndarray, translation) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = translation
    return matrix


def rotation_z(degrees: float) -> np.ndarray:
    return Rotation.from_euler("z", degrees, degrees=True).as_matrix()


def test_euler_angles_follow_dcp_convention():
    angles = np.array([[30.0, -20.0, 10.0], [0.0, 0.0, 0.0]])
    rotations = Rotation.from_euler("zyx", angles, degrees=True).as_matrix()
    np.testing.assert_allclose(euler_angles_deg(rotations), angles, atol=1e-10)
    assert euler_angles_deg(rotations[0]).shape == (3,)
    np.testing.assert_allclose(euler_angles_deg(rotation_z(25.0)), [25.0, 0.0, 0.0], atol=1e-10)


def test_rotation_and_translation_errors():
    assert rotation_error_deg(rotation_z(10.0), np.eye(3)) == pytest.approx(10.0)
    assert rotation_error_deg(np.eye(3), np.eye(3)) == 0.0  # clipping: no NaN from rounding
    assert rotation_error_deg(rotation_z(180.0), np.eye(3)) == pytest.approx(180.0)
    batch = np.stack([rotation_z(5.0), rotation_z(-40.0)])
    np.testing.assert_allclose(rotation_error_deg(batch, np.eye(3)), [5.0, 40.0])
    assert translation_error([1.0, 2.0, 2.0], [0.0, 0.0, 0.0]) == pytest.approx(3.0)


def test_transformed_source_rmse_is_mean_distance():
    source = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 0]])
    truth = np.eye(4)
    shifted = transform(np.eye(3), [0.0, 0.0, 2.0])
    assert transformed_source_rmse(source, shifted, truth) == pytest.approx(2.0)
    # 90 degrees about z: (1,0,0) moves sqrt(2), (0,1,0) moves sqrt(2), the origin stays.
    turned = transform(rotation_z(90.0), [0.0, 0.0, 0.0])
    assert transformed_source_rmse(source, turned, truth) == pytest.approx(2 * math.sqrt(2) / 3)
    batched = transformed_source_rmse(
        np.stack([source, source]), np.stack([shifted, turned]), np.stack([truth, truth])
    )
    np.testing.assert_allclose(batched, [2.0, 2 * math.sqrt(2) / 3])
    with pytest.raises(ValueError, match="needs transforms of shape"):
        transformed_source_rmse(source, np.stack([shifted, turned]), np.stack([truth, truth]))


def test_registration_metrics_identity_is_zero():
    rng = np.random.default_rng(0)
    truth = np.stack(
        [transform(Rotation.random(random_state=i).as_matrix(), rng.normal(size=3)) for i in range(4)]
    )
    metrics = registration_metrics(truth, truth, sources=rng.normal(size=(4, 20, 3)))
    assert set(metrics) == {"rmse_r", "mae_r", "rmse_t", "mae_t", "l_r", "l_t", "l_rmse"}
    for name, value in metrics.items():
        assert value == pytest.approx(0.0, abs=1e-6), name


def test_registration_metrics_known_rotation_about_z():
    source = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    predicted = transform(rotation_z(10.0), [0.0, 0.0, 0.0])
    truth = np.eye(4)
    metrics = registration_metrics(predicted, truth, sources=[source])
    assert metrics["l_r"] == pytest.approx(10.0)
    # Euler differences (10, 0, 0): RMSE = sqrt(100 / 3), MAE = 10 / 3.
    assert metrics["rmse_r"] == pytest.approx(math.sqrt(100.0 / 3.0))
    assert metrics["mae_r"] == pytest.approx(10.0 / 3.0)
    assert metrics["l_t"] == 0.0 and metrics["rmse_t"] == 0.0
    assert metrics["l_rmse"] == pytest.approx(2 * math.sin(math.radians(5.0)))  # chord of 10 deg


def test_registration_metrics_translation_and_batches():
    truth = np.stack([np.eye(4), np.eye(4)])
    predicted = np.stack([transform(np.eye(3), [0.3, 0.0, 0.0]), transform(np.eye(3), [0.0, -0.6, 0.0])])
    metrics = registration_metrics(predicted, truth)
    assert metrics["l_t"] == pytest.approx(0.45)
    assert metrics["mae_t"] == pytest.approx(0.9 / 6)
    assert metrics["rmse_t"] == pytest.approx(math.sqrt((0.09 + 0.36) / 6))
    assert math.isnan(metrics["l_rmse"])
    with pytest.raises(ValueError, match="2 predicted but 1 true"):
        registration_metrics(predicted, truth[:1])


def test_registration_metrics_wraps_euler_differences():
    metrics = registration_metrics(
        transform(rotation_z(179.0), [0, 0, 0]), transform(rotation_z(-179.0), [0, 0, 0])
    )
    assert metrics["mae_r"] == pytest.approx(2.0 / 3.0)
    assert metrics["l_r"] == pytest.approx(2.0)


def test_matching_metrics_hand_made_example():
    # Ten source points; -1 in the truth means no counterpart, -1 predicted means unmatched.
    truth = np.array([0, 1, 2, 3, 4, 5, -1, -1, -1, 9])
    predicted = np.array([0, 1, 2, 7, -1, -1, -1, -1, 8, 9])
    # Correct matches: points 0, 1, 2, 9 -> 4. Predicted matches: 0, 1, 2, 3, 8, 9 -> 6.
    # True matches: 0-5 and 9 -> 7. Correctly unmatched: points 6, 7 -> 2.
    metrics = matching_metrics(predicted, truth)
    assert metrics["precision"] == pytest.approx(4 / 6)
    assert metrics["recall"] == pytest.approx(4 / 7)
    assert metrics["accuracy"] == pytest.approx((4 + 2) / 10)


def test_matching_metrics_perfect_and_undefined():
    truth = np.array([3, -1, 0])
    assert matching_metrics(truth, truth) == {"precision": 1.0, "accuracy": 1.0, "recall": 1.0}
    nothing = matching_metrics(np.full(3, -1), truth)
    assert math.isnan(nothing["precision"]) and nothing["recall"] == 0.0
    assert nothing["accuracy"] == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="differ"):
        matching_metrics(np.zeros(3, dtype=int), np.zeros(4, dtype=int))
    with pytest.raises(ValueError, match="1-D integer array"):
        matching_metrics(np.zeros(3), np.zeros(3, dtype=int))
    with pytest.raises(ValueError, match=">= 0 or -1"):
        matching_metrics(np.array([-2, 0, 1]), np.zeros(3, dtype=int))


def test_matching_metrics_leave_ignored_points_out():
    # Points 2 and 3 are unlabelled (two samplings of one surface): whatever is predicted for
    # them counts nowhere, so the scores equal those of the six labelled points alone.
    truth = np.array([0, 1, IGNORED, IGNORED, -1, 5])
    predicted = np.array([0, 4, 2, -1, -1, 5])
    labelled = truth != IGNORED
    assert matching_metrics(predicted, truth) == matching_metrics(predicted[labelled], truth[labelled])
    assert matching_metrics(predicted, truth)["precision"] == pytest.approx(2 / 3)
    with pytest.raises(ValueError, match="ignored"):
        matching_metrics(predicted, np.array([0, 1, -3, 0, 0, 0]))
    with pytest.raises(ValueError, match=">= 0 or -1"):  # a prediction is never "ignored"
        matching_metrics(truth, truth)


def test_twin_distance_forgives_a_shape_its_own_symmetry_and_nothing_else():
    rng = np.random.default_rng(0)
    # A cylinder-like drum (symmetric under any turn about z) and a lumpy, asymmetric body.
    angle = rng.uniform(0.0, 2.0 * np.pi, 10_000)  # as many as the benchmark's dense shapes
    height = rng.uniform(-0.5, 0.5, 10_000)
    drum = np.column_stack([0.8 * np.cos(angle), 0.8 * np.sin(angle), height])
    lumpy = np.column_stack([0.8 * np.cos(angle) * (1.0 + 0.3 * np.cos(angle)), 0.5 * np.sin(angle),
                             height + 0.2 * np.cos(angle)])
    truth = np.eye(4)
    truth[:3, 3] = [2.0, -1.0, 0.5]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 49.0, degrees=True).as_matrix()
    assert twin_distance(drum, truth, truth) == 0.0
    # The drum turned about its axis: a twin, at about the sampling's spacing, under the 0.02 of
    # benchmarks/scan_pairs.py's rule.
    assert twin_distance(drum, truth @ turn, truth) < 0.02
    # The asymmetric body turned the same way, or the drum shifted by 5 % of its radius: not.
    assert twin_distance(lumpy, truth @ turn, truth) > 0.05
    radius = np.linalg.norm(drum - drum.mean(axis=0), axis=1).max()
    across, along = truth.copy(), truth.copy()
    across[:3, 3] += [0.05 * radius, 0.0, 0.0]
    assert twin_distance(drum, across, truth) > 0.02
    # Its limit, by construction: a slide along the open drum's axis shows only at its two rims,
    # so it scores as a near-twin (benchmarks/results/symmetry_twins/README.md says so).
    along[:3, 3] += [0.0, 0.0, 0.05 * radius]
    assert twin_distance(drum, along, truth) < 0.02
    with pytest.raises(ValueError, match="all equal"):
        twin_distance(np.ones((5, 3)), truth, truth)
    with pytest.raises(ValueError, match="shape"):
        twin_distance(np.ones(3), truth, truth)

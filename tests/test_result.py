"""What a registration result reports: no inliers, ICP's ending, JSON without NaN."""

from __future__ import annotations

import json

import numpy as np
import pytest

from logdesc_rt import Registrar
from logdesc_rt.demo import make_demo_pair


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    return Registrar()


@pytest.fixture(scope="module")
def demo_pair():
    return make_demo_pair()


def test_no_inliers_means_nan_rmse_and_null_in_json(registrar, demo_pair):
    """A correspondence distance far below the noise leaves no inliers: RMSE is undefined."""
    result = registrar.register(demo_pair.source, demo_pair.target, max_correspondence_distance=1e-9)
    assert result.fitness == 0.0
    assert np.isnan(result.inlier_rmse)
    summary = result.to_dict()
    assert summary["inlier_rmse"] is None
    json.dumps(summary, allow_nan=False)  # strict JSON: would raise on NaN


def test_icp_ending_is_kept(registrar, demo_pair):
    refined = registrar.register(demo_pair.source, demo_pair.target, refine="point_to_plane")
    assert refined.icp is not None and refined.icp.iterations >= 1
    assert refined.icp.stop_reason in {"converged", "max_iterations", "too_few_correspondences"}
    assert np.array_equal(refined.icp.transformation, refined.transformation)
    summary = json.loads(json.dumps(refined.to_dict(), allow_nan=False))
    assert summary["icp"]["converged"] == refined.icp.converged
    assert summary["icp"]["iterations"] == refined.icp.iterations
    assert np.array_equal(np.array(summary["correspondences"]), refined.correspondences)
    coarse = registrar.register(demo_pair.source, demo_pair.target)
    assert coarse.icp is None and coarse.to_dict()["icp"] is None

"""Open3D PointCloud objects (legacy and tensor) are accepted by register / align and give the
same result as their points; logdesc-rt never imports Open3D itself. Skipped without Open3D."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import logdesc_rt
from logdesc_rt.demo import make_demo_pair
from logdesc_rt.errors import PointCloudShapeError
from logdesc_rt.io import open3d_points

o3d = pytest.importorskip("open3d")


@pytest.fixture(scope="module")
def pair():
    return make_demo_pair()


def _legacy(points: np.ndarray):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


def _tensor(points: np.ndarray):
    return o3d.t.geometry.PointCloud(o3d.core.Tensor(points))


def test_register_takes_open3d_clouds_and_gives_the_array_result(pair):
    expected = logdesc_rt.register(pair.source, pair.target, seed=0)
    legacy = logdesc_rt.register(_legacy(pair.source), _legacy(pair.target), seed=0)
    np.testing.assert_array_equal(legacy.transformation, expected.transformation)
    assert (legacy.success, legacy.confidence) == (expected.success, expected.confidence)
    # Tensor clouds, mixed with an array.
    mixed = logdesc_rt.register(_tensor(pair.source), pair.target, seed=0)
    np.testing.assert_array_equal(mixed.transformation, expected.transformation)


def test_align_takes_open3d_clouds(pair):
    result = logdesc_rt.align([_legacy(pair.source), _tensor(pair.target)], workers=0, progress=False)
    assert result.disconnected == [] and set(result.poses) == {"scan_000", "scan_001"}
    truth = np.linalg.inv(pair.true_transformation)  # scan 1 (the target) into scan 0's frame
    from logdesc_rt.metrics import rotation_error_deg

    assert rotation_error_deg(result.poses["scan_001"][:3, :3], truth[:3, :3]) < 2.0


def test_open3d_points_leaves_other_inputs_alone():
    points = np.arange(12.0).reshape(4, 3)
    np.testing.assert_array_equal(open3d_points(_legacy(points)), points)
    assert open3d_points(_tensor(points.astype(np.float32))).dtype == np.float64
    assert open3d_points(points) is None and open3d_points("cloud.ply") is None
    with pytest.raises(PointCloudShapeError, match="positions"):
        open3d_points(o3d.t.geometry.PointCloud())
    empty = o3d.geometry.PointCloud()
    with pytest.raises(Exception, match="0 points"):
        logdesc_rt.register(empty, points)


def test_logdesc_rt_does_not_import_open3d():
    code = (
        "import sys, numpy as np, logdesc_rt\n"
        "from logdesc_rt.io import open3d_points\n"
        "assert open3d_points(np.zeros((3, 3))) is None\n"
        "assert 'open3d' not in sys.modules, 'open3d imported'\n"
    )
    completed = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert completed.returncode == 0, completed.stderr

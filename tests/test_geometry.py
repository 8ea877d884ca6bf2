"""Per-point geometry against analytic truths, rigid-motion covariance and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from logdesc_rt import GeometryConfig, compute_geometry
from logdesc_rt.config import PAPER_GEOMETRY  # these tests check the paper geometry's rules
from logdesc_rt.errors import (
    DegenerateGeometryError,
    LogdescError,
    NonFinitePointsError,
    PointCloudShapeError,
    TooFewPointsError,
)
from logdesc_rt.geometry import knn_excluding_self, pca_features
from logdesc_rt.geometry.kernels import neighbourhoods

from .shapes import fibonacci_sphere, random_rigid_transform


def grid_plane(side: int = 40, extent: float = 1.0) -> np.ndarray:
    """(side^2, 3) regular grid on the plane z = 0."""
    axis = np.linspace(-extent, extent, side)
    x, y = np.meshgrid(axis, axis)
    return np.stack([x.ravel(), y.ravel(), np.zeros(side * side)], axis=1)


def test_plane_has_planarity_one_and_its_normal():
    points = grid_plane()
    geometry = compute_geometry(points, PAPER_GEOMETRY)
    interior = np.abs(points[:, :2]).max(axis=1) < 1.0 - 0.3  # full disc within the PCA radius
    assert interior.sum() > 100
    assert np.all(geometry.pca.planarity[interior] > 0.99)
    assert np.all(geometry.pca.anisotropy[interior] > 0.99)
    assert np.allclose(geometry.pca.omnivariance, 0.0, atol=1e-12)
    # Umbrella and PCA normals are the plane's normal (up to the sign, which a plane through
    # the centroid leaves open), everywhere including the border.
    assert np.all(np.abs(geometry.normals[:, 2]) > 1.0 - 1e-9)
    assert np.all(np.abs(geometry.pca.lrf[:, 2, 2]) > 1.0 - 1e-9)


def test_line_has_anisotropy_one():
    line = np.linspace(0.0, 1.0, 200)[:, None] * np.array([[1.0, 2.0, -0.5]])
    features = pca_features(line, radius=0.3, max_neighbours=128)
    assert np.all(features.anisotropy > 1.0 - 1e-9)
    assert np.all(features.planarity < 1e-9)
    # u is the line's direction.
    direction = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    assert np.all(np.abs(features.lrf[:, :, 0] @ direction) > 1.0 - 1e-9)


def test_sphere_normals_are_radial_and_outward():
    points = fibonacci_sphere(2000)
    geometry = compute_geometry(points, PAPER_GEOMETRY)
    radial = points / np.linalg.norm(points, axis=1, keepdims=True)
    cosine = np.sum(geometry.normals * radial, axis=1)
    assert cosine.min() > 0.99, cosine.min()
    assert np.all(np.sum(geometry.pca.lrf[:, :, 2] * radial, axis=1) > 0.99)


def test_lrf_is_a_rotation(sphere):
    lrf = compute_geometry(sphere, PAPER_GEOMETRY).pca.lrf
    assert np.allclose(lrf.transpose(0, 2, 1) @ lrf, np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(lrf), 1.0, atol=1e-9)


def test_geometry_moves_with_the_cloud():
    """Normals and LRFs rotate with the cloud, invariant channels stay (sign rule is covariant)."""
    rng = np.random.default_rng(3)
    points = rng.normal(size=(600, 3)) * [1.0, 0.6, 0.3]
    pose = random_rigid_transform(rng)
    moved = points @ pose[:3, :3].T + pose[:3, 3]
    before, after = compute_geometry(points, PAPER_GEOMETRY), compute_geometry(moved, PAPER_GEOMETRY)
    assert np.array_equal(before.neighbour_index, after.neighbour_index)
    assert np.allclose(before.normals @ pose[:3, :3].T, after.normals, atol=1e-6)
    assert np.allclose(pose[:3, :3] @ before.pca.lrf, after.pca.lrf, atol=1e-6)
    invariant = np.r_[3:6, 9:15]
    assert np.allclose(before.edges[..., invariant], after.edges[..., invariant], atol=1e-4)


def test_edge_feature_layout():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(200, 3))
    g = compute_geometry(points, PAPER_GEOMETRY)
    i, j = 17, 4
    m = g.neighbour_index[i, j]
    shape = np.stack([g.pca.anisotropy, g.pca.planarity, g.pca.omnivariance], axis=1)
    expected = np.concatenate(
        [points[i], shape[i], points[m] - points[i], shape[m] - shape[i], g.pca.lrf[i].T @ g.normals[m]]
    )
    assert g.edges.shape == (200, 30, 15) and g.edges.dtype == np.float32
    assert np.allclose(g.edges[i, j], expected, atol=1e-6)


def test_same_input_same_output(sphere):
    first, second = compute_geometry(sphere, PAPER_GEOMETRY), compute_geometry(sphere.copy(), PAPER_GEOMETRY)
    assert np.array_equal(first.edges, second.edges)
    assert np.array_equal(first.normals, second.normals)


def test_neighbours_exclude_self_even_with_duplicates():
    rng = np.random.default_rng(1)
    points = np.repeat(rng.normal(size=(40, 3)), 3, axis=0)  # every point three times
    index = knn_excluding_self(points, 5)
    assert not np.any(index == np.arange(len(points))[:, None])


@pytest.mark.parametrize(
    ("points", "error", "message"),
    [
        (np.full((100, 3), np.nan), NonFinitePointsError, "NaN or inf"),
        (np.r_[np.random.default_rng(0).normal(size=(99, 3)), [[np.inf, 0, 0]]], NonFinitePointsError, "row 99"),
        (np.random.default_rng(0).normal(size=(30, 3)), TooFewPointsError, "at least 31"),
        (np.ones((100, 3)), DegenerateGeometryError, "coincide"),
        (np.linspace(0, 1, 100)[:, None] * [[1.0, 1.0, 1.0]], DegenerateGeometryError, "one line"),
        (np.zeros((100, 2)), PointCloudShapeError, r"not \(N, 3\)"),
        (np.zeros(3), PointCloudShapeError, r"not \(N, 3\)"),
        (np.zeros((100, 3), dtype=complex), PointCloudShapeError, "not a real number"),
        (np.zeros((100, 3), dtype=bool), PointCloudShapeError, "not a real number"),
        (np.array([["a", "b", "c"]] * 100), PointCloudShapeError, "not a real number"),
    ],
)
def test_bad_input_raises_a_named_error(points, error, message):
    with pytest.raises(error, match=message):
        compute_geometry(points, PAPER_GEOMETRY)


SMALL = GeometryConfig(pca_max_neighbours=8, pca_min_neighbours=4, umbrella_neighbours=4)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    arrays(
        np.float64,
        st.tuples(st.integers(0, 40), st.sampled_from([2, 3, 4])),
        elements=st.floats(allow_nan=True, allow_infinity=True, width=64),
    )
)
def test_random_input_raises_only_logdesc_errors(points):
    try:
        geometry = compute_geometry(points, SMALL)
    except LogdescError:
        return
    # Anything that got through was valid input, and gives finite features.
    assert np.isfinite(points).all(), "a cloud with NaN or inf coordinates was accepted"
    assert np.isfinite(geometry.edges).all()


@settings(max_examples=100, deadline=None)
@given(
    arrays(np.float64, st.tuples(st.integers(6, 40), st.just(3)), elements=st.floats(-1e3, 1e3)),
)
def test_finite_input_gives_finite_unit_normals(points):
    try:
        geometry = compute_geometry(points, SMALL)
    except (DegenerateGeometryError, TooFewPointsError):
        return
    assert np.isfinite(geometry.edges).all()
    assert np.allclose(np.linalg.norm(geometry.normals, axis=1), 1.0)


def test_defaults_are_the_shipped_geometry_and_old_files_keep_the_papers():
    import json
    from pathlib import Path

    import logdesc_rt

    manifest = json.loads((Path(logdesc_rt.__file__).parent / "models" / "manifest.json").read_text())
    assert GeometryConfig() == GeometryConfig.from_stored(manifest["geometry"])  # the bundled model's
    # A geometry stored before the edge layouts existed (small-h100-v2's) is the paper's.
    legacy = {key: value for key, value in PAPER_GEOMETRY.to_dict().items() if key not in ("edge_layout", "normals")}
    assert GeometryConfig.from_stored(legacy) == PAPER_GEOMETRY
    assert GeometryConfig.from_stored({**legacy, "edge_layout": "chiral"}).edge_layout == "chiral"
    # ... and without its neighbour count too: the paper's 30, not the shipped default.
    unsized = {key: value for key, value in legacy.items() if key != "umbrella_neighbours"}
    assert GeometryConfig.from_stored(unsized).umbrella_neighbours == 30 != GeometryConfig().umbrella_neighbours


# -- the compiled neighbourhoods against a brute-force reference --------------------------------


def _brute_force_neighbourhoods(points, radius, max_neighbours, min_neighbours, k):
    """Sizes, means, covariances and umbrella neighbours from the full distance matrix."""
    count = len(points)
    squared = np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=2)
    sizes, means, covariances, umbrella = [], [], [], []
    for row in range(count):
        others = np.r_[0:row, row + 1 : count]
        # Nearest first; among exact ties, the lowest index first; the point itself first of all.
        order = np.r_[row, others[np.lexsort((others, squared[row, others]))]]
        within = int(np.sum(np.sqrt(squared[row]) < radius))
        size = min(max_neighbours, max(within, min_neighbours), count)
        members = points[order[:size]]
        sizes.append(size)
        means.append(members.mean(axis=0))
        covariances.append((members - members.mean(axis=0)).T @ (members - members.mean(axis=0)) / size)
        umbrella.append(order[1 : k + 1])
    return np.array(sizes), np.array(means), np.array(covariances), np.array(umbrella, dtype=np.int64)


def _clouds_with_hard_cases():
    rng = np.random.default_rng(7)
    surface = fibonacci_sphere(300) * (1.0 + 0.1 * rng.normal(size=(300, 1)))
    duplicated = np.concatenate([surface[:120], surface[:120], surface[:40]])  # 2 and 3 copies
    stray = np.concatenate([surface[:250], [[60.0, -40.0, 25.0]]])  # a far stray point
    sparse = rng.normal(size=(80, 3)) * 3.0  # most points have no neighbour within the radius
    dense = rng.normal(size=(600, 3)) * 0.2  # far more than max_neighbours within the radius
    return {"surface": surface, "duplicated": duplicated, "stray": stray, "sparse": sparse, "dense": dense}


@pytest.mark.parametrize("name", ["surface", "duplicated", "stray", "sparse", "dense"])
@pytest.mark.parametrize(("radius", "max_neighbours", "min_neighbours", "k"), [(0.3, 128, 8, 30), (0.2, 20, 12, 10)])
def test_neighbourhoods_equal_a_brute_force_reference(name, radius, max_neighbours, min_neighbours, k):
    points = _clouds_with_hard_cases()[name]
    sizes, means, covariances, umbrella = neighbourhoods(points, radius, max_neighbours, min_neighbours, k)
    expected = _brute_force_neighbourhoods(points, radius, max_neighbours, min_neighbours, k)
    np.testing.assert_array_equal(sizes, expected[0])
    np.testing.assert_allclose(means, expected[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(covariances, expected[2], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(umbrella, expected[3])
    assert not np.any(umbrella == np.arange(len(points))[:, None])


def test_neighbourhoods_of_more_duplicates_than_neighbours():
    # Every point seven times, k = 4: the umbrella is four of the point's copies, never itself.
    points = np.repeat(np.random.default_rng(2).normal(size=(30, 3)), 7, axis=0)
    _, _, _, umbrella = neighbourhoods(points, 0.3, 16, 4, 4)
    copies = np.arange(len(points)) // 7
    assert np.all(copies[umbrella] == copies[:, None])
    np.testing.assert_array_equal(umbrella, _brute_force_neighbourhoods(points, 0.3, 16, 4, 4)[3])


def test_geometry_neighbours_are_the_nearest_in_order():
    rng = np.random.default_rng(11)
    points = fibonacci_sphere(500) + rng.normal(scale=0.01, size=(500, 3))
    geometry = compute_geometry(points)
    squared = np.sum((points[:, None] - points[None]) ** 2, axis=2)
    np.fill_diagonal(squared, np.inf)
    np.testing.assert_array_equal(
        geometry.neighbour_index, np.argsort(squared, axis=1)[:, : GeometryConfig().umbrella_neighbours]
    )
    sizes = geometry.pca.neighbour_count
    np.fill_diagonal(squared, 0.0)
    within = np.sum(np.sqrt(squared) < 0.3, axis=1)
    np.testing.assert_array_equal(sizes, np.clip(within, 8, 128))


@pytest.mark.parametrize("user_cache_writable", [True, False])
def test_kernels_work_from_a_package_directory_that_cannot_be_written(tmp_path, user_cache_writable):
    """The kernels' disk cache goes to the user's cache directory when the package's cannot be
    written; with no writable cache directory at all, they compile in the process and run."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import logdesc_rt

    site = tmp_path / "site"
    shutil.copytree(Path(logdesc_rt.__file__).parent, site / "logdesc_rt", ignore=shutil.ignore_patterns("__pycache__"))
    # A file named __pycache__ in every package folder: no cache can be made there, even by root.
    for init in (site / "logdesc_rt").rglob("__init__.py"):
        (init.parent / "__pycache__").write_text("")
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    user_cache = tmp_path / "user_cache" if user_cache_writable else blocked / "cache"
    env = {key: value for key, value in os.environ.items() if not key.startswith("NUMBA_")}
    env.update(PYTHONPATH=str(site), XDG_CACHE_HOME=str(user_cache), HOME=str(blocked / "home"))
    script = (
        "import numpy as np, logdesc_rt\n"
        "from logdesc_rt import compute_geometry\n"
        "from logdesc_rt.sampling import farthest_point_sampling\n"
        f"assert logdesc_rt.__file__.startswith({str(site)!r})\n"
        "points = np.random.default_rng(0).normal(size=(200, 3))\n"
        f"assert compute_geometry(points).edges.shape == (200, {GeometryConfig().umbrella_neighbours}, 13)\n"
        "assert len(set(farthest_point_sampling(points, 50).tolist())) == 50\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr
    cached = list(user_cache.rglob("*.nbi")) if user_cache_writable else []
    assert bool(cached) == user_cache_writable


def test_the_kernels_cache_goes_to_the_user_directory_not_into_the_package(tmp_path):
    """A cache written into an installed package outlives ``pip uninstall`` and, left behind in
    site-packages, shadows a later editable install: the kernels cache in the user's cache
    directory even where the package directory is writable."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import logdesc_rt

    site = tmp_path / "site"
    shutil.copytree(Path(logdesc_rt.__file__).parent, site / "logdesc_rt", ignore=shutil.ignore_patterns("__pycache__"))
    user_cache = tmp_path / "user_cache"
    env = {key: value for key, value in os.environ.items() if not key.startswith("NUMBA_")}
    env.update(PYTHONPATH=str(site), XDG_CACHE_HOME=str(user_cache), PYTHONDONTWRITEBYTECODE="1")
    script = (
        "import numpy as np\n"
        "from logdesc_rt import compute_geometry\n"
        "edges = compute_geometry(np.random.default_rng(0).normal(size=(200, 3))).edges\n"
        f"assert edges.shape == (200, {GeometryConfig().umbrella_neighbours}, 13)\n"
    )
    result = subprocess.run([sys.executable, "-c", script], env=env, cwd=tmp_path, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr
    assert list(user_cache.rglob("*.nbi"))
    assert not list((site / "logdesc_rt").rglob("*.nbi")) and not list((site / "logdesc_rt").rglob("*.nbc"))

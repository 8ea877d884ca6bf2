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
    legacy = {key: value for key, value in GeometryConfig().to_dict().items() if key not in ("edge_layout", "normals")}
    assert GeometryConfig.from_stored(legacy) == PAPER_GEOMETRY
    assert GeometryConfig.from_stored({**legacy, "edge_layout": "chiral"}).edge_layout == "chiral"

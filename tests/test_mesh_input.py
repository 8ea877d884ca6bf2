"""Meshes as input: every format offered, the sampling's count, seed and area weighting, the
PLY / OFF policy (vertices or surface), meshes without faces, corrupt files, and a mesh
registered to a scan of it (the pose maps the mesh into the scan's frame)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

import logdesc_rt  # noqa: E402
from logdesc_rt.errors import PointCloudFileError  # noqa: E402
from logdesc_rt.io import (  # noqa: E402
    DEFAULT_SURFACE_SAMPLES,
    Mesh,
    read_mesh,
    read_point_cloud,
    read_registration_input,
    sample_surface,
)
from logdesc_rt.io.mesh import vertex_sampling_problem  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402
from logdesc_rt.tools.cli import main  # noqa: E402

from .shapes import random_rigid_transform  # noqa: E402

MESH_FORMATS = (".obj", ".stl", ".ply", ".off", ".glb")


def _box_mesh() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 2.0, 3.0))


@pytest.mark.parametrize("suffix", MESH_FORMATS)
def test_every_mesh_format_reads_its_triangles_and_samples_its_surface(tmp_path, suffix):
    path = tmp_path / f"box{suffix}"
    _box_mesh().export(path)
    mesh = read_mesh(path)
    assert len(mesh.faces) == 12
    assert mesh.area == pytest.approx(2 * (1 * 2 + 1 * 3 + 2 * 3))
    points = sample_surface(path, count=777, seed=0)
    assert points.shape == (777, 3) and points.dtype == np.float64
    # Every sample lies on the box's surface: one coordinate at its half-extent.
    on_face = np.isclose(np.abs(points), [0.5, 1.0, 1.5], atol=1e-9).any(axis=1)
    assert on_face.all()


@pytest.mark.parametrize("suffix", (".obj", ".stl", ".glb"))
def test_mesh_only_formats_are_sampled_with_the_default_count(tmp_path, suffix):
    path = tmp_path / f"box{suffix}"
    _box_mesh().export(path)
    points, mesh = read_registration_input(path)
    assert points.shape == (DEFAULT_SURFACE_SAMPLES, 3)
    assert mesh is not None and len(mesh.faces) == 12
    chosen, _ = read_registration_input(path, sample_surface=321)
    assert chosen.shape == (321, 3)


def test_sampling_is_seeded(tmp_path):
    path = tmp_path / "sphere.stl"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    first = sample_surface(path, 500, seed=4)
    again = sample_surface(read_mesh(path), 500, seed=4)
    other = sample_surface(path, 500, seed=5)
    assert np.array_equal(first, again)
    assert not np.allclose(first, other)
    # register() samples a mesh path the same way every time: same input, same output.
    assert np.array_equal(read_registration_input(path)[0], read_registration_input(path)[0])


def _uneven_strip() -> Mesh:
    """A 2 x 1 rectangle in z = 0: its left half (x < 1) cut into 2 x 40 x 40 tiny triangles, its
    right half two large ones. 99 % of the vertices are on the left; half the area is right."""
    cells = 40
    grid = np.linspace(0.0, 1.0, cells + 1)
    xs, ys = np.meshgrid(grid, grid, indexing="ij")
    left = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    index = np.arange(xs.size).reshape(cells + 1, cells + 1)
    a, b = index[:-1, :-1].ravel(), index[1:, :-1].ravel()
    c, d = index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    # Right half: reuse the left half's right edge corners (1, 0) and (1, 1), add (2, 0), (2, 1).
    right = np.array([[2.0, 0.0, 0.0], [2.0, 1.0, 0.0]])
    vertices = np.concatenate([left, right])
    corner_low, corner_high = index[-1, 0], index[-1, -1]
    far_low, far_high = len(left), len(left) + 1
    faces = np.concatenate([faces, [[corner_low, far_low, far_high], [corner_low, far_high, corner_high]]])
    return Mesh(vertices, faces.astype(np.int64))


def test_sampling_is_area_weighted_on_very_uneven_triangles():
    mesh = _uneven_strip()
    assert np.mean(mesh.vertices[:, 0] > 1.0) < 0.01  # the vertices say "all left"
    points = mesh.sample(20_000, seed=0)
    right = np.mean(points[:, 0] > 1.0)
    # Half the area is on the right: binomial sd 0.0035 at 20k samples; 0.02 is ~6 sd.
    assert abs(right - 0.5) < 0.02
    # Finer: uniform in x over [0, 2] (each quarter ~25 %).
    quarters = np.histogram(points[:, 0], bins=4, range=(0.0, 2.0))[0] / len(points)
    assert np.allclose(quarters, 0.25, atol=0.02)
    assert vertex_sampling_problem(mesh, working_size=1024) is not None  # its vertices would mislead


def test_ply_or_off_with_faces_uses_its_vertices_when_they_cover_the_surface(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=4)  # 2562 even vertices
    for suffix in (".ply", ".off"):
        path = tmp_path / f"sphere{suffix}"
        sphere.export(path)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no note: nothing was sampled
            points, mesh = read_registration_input(path)
        assert mesh is not None
        assert np.array_equal(points, read_point_cloud(path))


@pytest.mark.parametrize("suffix", (".ply", ".off"))
def test_ply_or_off_with_too_few_or_uneven_vertices_is_sampled_and_says_so(tmp_path, suffix):
    few = tmp_path / f"box{suffix}"
    _box_mesh().export(few)  # 8 vertices
    notes: list[str] = []
    points, _ = read_registration_input(few, notify=notes.append)
    assert points.shape == (DEFAULT_SURFACE_SAMPLES, 3)
    assert len(notes) == 1 and "only 8 vertices" in notes[0] and str(few) in notes[0]

    uneven = _uneven_strip()  # 1683 vertices, above the working size of 512 given below: only evenness fails
    path = tmp_path / f"uneven{suffix}"
    trimesh.Trimesh(uneven.vertices, uneven.faces, process=False).export(path)
    notes.clear()
    points, _ = read_registration_input(path, working_size=512, notify=notes.append)
    assert points.shape == (DEFAULT_SURFACE_SAMPLES, 3)
    assert len(notes) == 1 and "uneven" in notes[0]


def test_sample_surface_on_a_point_cloud_without_faces_is_a_clear_error(tmp_path, sphere):
    path = tmp_path / "cloud.ply"
    logdesc_rt.write_point_cloud(path, sphere)
    with pytest.raises(PointCloudFileError, match=r"cloud\.ply: has no faces"):
        read_registration_input(path, sample_surface=1000)


def test_a_mesh_file_with_no_faces_is_a_clear_error(tmp_path):
    path = tmp_path / "vertices_only.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(PointCloudFileError, match=r"vertices_only\.obj: no faces could be read"):
        read_mesh(path)
    with pytest.raises(PointCloudFileError, match="no faces"):
        logdesc_rt.register(path, np.random.default_rng(0).normal(size=(100, 3)))


def test_faces_of_zero_area_are_a_clear_error(tmp_path):
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(PointCloudFileError, match="zero total area"):
        read_mesh(path)


@pytest.mark.parametrize(
    "name, content, problem",
    [
        ("truncated.stl", None, "truncated or corrupt"),
        ("garbage.obj", b"v 0 0\nf 1 2 x\n", "cannot parse as OBJ mesh"),
        ("garbage.glb", b"glTF\x02\x00\x00\x00garbage", "cannot parse as GLB mesh"),
        ("empty.stl", b"", "empty"),
    ],
)
def test_a_corrupt_mesh_file_is_a_clear_error_naming_it(tmp_path, name, content, problem):
    path = tmp_path / name
    if content is None:  # a binary STL cut short
        full = tmp_path / "full.stl"
        _box_mesh().export(full)
        content = full.read_bytes()[:300]
    path.write_bytes(content)
    with pytest.raises(PointCloudFileError, match=problem) as raised:
        read_mesh(path)
    assert str(path) in str(raised.value)


def test_a_moved_mesh_writes_back_with_its_faces(tmp_path):
    mesh = Mesh(*(_box_mesh().vertices, _box_mesh().faces))
    pose = random_rigid_transform(np.random.default_rng(1))
    path = tmp_path / "moved.ply"
    mesh.transformed(pose).write(path)
    back = read_mesh(path)
    assert np.array_equal(back.faces, mesh.faces)
    assert np.allclose(back.vertices, mesh.vertices @ pose[:3, :3].T + pose[:3, 3], atol=1e-6)


# ---------------------------------------------------------------------------- registration
def _bunny_mesh_and_scan(shared_data, seed: int = 3):
    """The Bunny's reconstruction (a real mesh, metres) and a synthetic scan of it: other surface
    samples, moved by a known pose, with noise of 0.5 mm."""
    path = shared_data / "stanford_bunny" / "reconstruction" / "bun_zipper.ply"
    rng = np.random.default_rng(seed)
    pose = random_rigid_transform(rng, translation_scale=0.5)
    scan = read_mesh(path).sample(3000, seed=11)
    scan = scan @ pose[:3, :3].T + pose[:3, 3] + rng.normal(0.0, 5e-4, scan.shape)
    return path, scan, pose


def test_a_mesh_registers_to_a_scan_of_it_and_its_pose_maps_the_mesh(shared_data):
    path, scan, pose = _bunny_mesh_and_scan(shared_data)
    for source in (path, trimesh.load(path, process=False), read_mesh(path)):
        result = logdesc_rt.register(source, scan, refine="point_to_plane")
        assert result.success
        assert rotation_error_deg(result.rotation, pose[:3, :3]) < 2.0
        assert np.linalg.norm(result.translation - pose[:3, 3]) < 0.005  # 5 mm on a 15 cm bunny


def test_cli_registers_a_mesh_and_writes_it_moved_with_its_faces(shared_data, tmp_path, capsys):
    path, scan, pose = _bunny_mesh_and_scan(shared_data)
    stl = tmp_path / "bunny.stl"
    trimesh.load(path, process=False).export(stl)
    scan_path = tmp_path / "scan.ply"
    logdesc_rt.write_point_cloud(scan_path, scan)
    out = tmp_path / "moved.ply"
    code = main(["register", str(stl), str(scan_path), "--sample-surface", "4000", "--write-aligned", str(out),
                 "--refine", "point_to_plane", "--json"])
    assert code == 0
    moved = read_mesh(out)
    original = read_mesh(stl)
    assert np.array_equal(moved.faces, original.faces)
    expected = original.vertices @ pose[:3, :3].T + pose[:3, 3]
    assert np.percentile(np.linalg.norm(moved.vertices - expected, axis=1), 95) < 0.005
    assert "4000 points sampled on its surface" in capsys.readouterr().err


def test_cli_refuses_a_mesh_output_for_a_point_cloud_source(tmp_path, sphere):
    source, target = tmp_path / "a.ply", tmp_path / "b.ply"
    logdesc_rt.write_point_cloud(source, sphere)
    logdesc_rt.write_point_cloud(target, sphere)
    assert main(["register", str(source), str(target), "--write-aligned", str(tmp_path / "out.stl")]) == 2
    # --sample-surface with no mesh among the inputs is a mistake, said before any work.
    assert main(["register", str(source), str(target), "--sample-surface", "2000"]) == 2


def test_register_many_and_align_take_mesh_paths(shared_data, tmp_path):
    path, scan, pose = _bunny_mesh_and_scan(shared_data)
    scan_path = tmp_path / "scan.npy"
    np.save(scan_path, scan)
    records = logdesc_rt.register_many([(path, scan_path)], workers=0, refine="point_to_plane")
    assert records[0]["ok"] and records[0]["success"]
    assert rotation_error_deg(np.asarray(records[0]["transformation"])[:3, :3], pose[:3, :3]) < 2.0
    alignment = logdesc_rt.align([path, scan_path], workers=0, progress=False)
    assert not alignment.disconnected


def test_without_trimesh_a_mesh_file_names_the_extra_and_a_ply_gives_its_vertices(tmp_path, monkeypatch):
    stl, ply = tmp_path / "box.stl", tmp_path / "box.ply"
    _box_mesh().export(stl)
    _box_mesh().export(ply)
    monkeypatch.setitem(__import__("sys").modules, "trimesh", None)  # "import trimesh" now fails
    with pytest.raises(PointCloudFileError, match=r"box\.stl: .*logdesc-rt\[mesh\]"):
        read_registration_input(stl)
    notes: list[str] = []
    points, mesh = read_registration_input(ply, notify=notes.append)
    assert mesh is None and len(points) == 8  # the vertices, as before meshes were read
    assert len(notes) == 1 and "logdesc-rt[mesh]" in notes[0]
    assert main(["register", str(stl), str(ply)]) == 2  # stopped before any work, naming the extra


def test_the_default_working_size_is_the_bundled_models():
    from logdesc_rt.io import DEFAULT_WORKING_SIZE

    assert logdesc_rt.Registrar().max_points == DEFAULT_WORKING_SIZE

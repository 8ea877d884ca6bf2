"""Tests of logdesc_rt.io: round trips, hand-written files of every format, the Stanford
bunny scan, error messages, and a fuzz test that corrupt files only raise logdesc errors."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from logdesc_rt.errors import (
    LogdescError,
    NonFinitePointsError,
    PointCloudFileError,
    PointCloudShapeError,
)
from logdesc_rt.io import CORE_SUFFIXES, SUPPORTED_SUFFIXES, read_point_cloud, read_stanford_conf, write_point_cloud
from logdesc_rt.io.pcd import lzf_decompress as _lzf_decompress
from logdesc_rt.io.ply import SCALAR_TYPES, read_header
from logdesc_rt.validation import MAX_ABS_COORDINATE

DATA_ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BUNNY_SCAN = DATA_ROOT / "stanford_bunny" / "data" / "bun000.ply"

# Coordinates that stress text formatting: tiny, huge (as_points allows up to
# MAX_ABS_COORDINATE), subnormal, negative zero, many digits.
AWKWARD_POINTS = np.array(
    [
        [0.1, -0.2, 0.30000000000000004],
        [1e-300, -MAX_ABS_COORDINATE, 5e-324],
        [-0.0, 123456789.123456789, 2.0**-40],
        [np.pi, np.e, -1.0 / 3.0],
    ]
)


ASCII_PLY_XYZ_HEADER = (
    "ply\nformat ascii 1.0\nelement vertex {count}\nproperty float x\nproperty float y\nproperty float z\n"
    "end_header\n"
)


def write_bytes(path: Path, data: bytes | str) -> Path:
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def path_and(path: Path, problem: str) -> str:
    """A ``match`` pattern: the message names ``path`` and then the problem (a regex)."""
    return re.escape(str(path)) + ".*" + problem


# --------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------


# Exact round trips: the formats of the run-time dependencies (LAS / E57 store scaled integers
# or single precision: tests/test_io_scanner_formats.py).
@pytest.mark.parametrize("suffix", CORE_SUFFIXES + (".PLY", ".Npy", ".CSV"))
def test_round_trip_is_exact(tmp_path, suffix):
    path = tmp_path / f"cloud{suffix}"
    write_point_cloud(path, AWKWARD_POINTS)
    loaded = read_point_cloud(path)
    assert loaded.dtype == np.float64 and loaded.flags.c_contiguous
    assert loaded.tobytes() == AWKWARD_POINTS.tobytes()  # bit for bit, -0.0 included
    assert path.exists() and len(list(tmp_path.iterdir())) == 1  # no ".npy" appended etc.


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    points=hnp.arrays(
        np.float64,
        st.tuples(st.integers(1, 20), st.just(3)),
        elements=st.floats(-MAX_ABS_COORDINATE, MAX_ABS_COORDINATE),
    )
)
def test_round_trip_random_points(tmp_path, points):
    for suffix in CORE_SUFFIXES:
        path = tmp_path / f"random{suffix}"
        write_point_cloud(path, points)
        np.testing.assert_array_equal(read_point_cloud(path), points)


def test_written_csv_has_header_and_ply_is_binary_double(tmp_path):
    write_point_cloud(tmp_path / "a.csv", [[1, 2, 3]])
    assert (tmp_path / "a.csv").read_text().splitlines() == ["x,y,z", "1.0,2.0,3.0"]
    write_point_cloud(tmp_path / "a.ply", [[1, 2, 3]])
    header = (tmp_path / "a.ply").read_bytes().split(b"end_header\n")[0]
    assert b"format binary_little_endian 1.0" in header
    assert b"property double x" in header


def test_write_accepts_integer_lists_and_str_paths(tmp_path):
    write_point_cloud(str(tmp_path / "a.npy"), [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(read_point_cloud(str(tmp_path / "a.npy")), [[1, 2, 3], [4, 5, 6]])


# --------------------------------------------------------------------------------------
# Real data: a Stanford bunny range scan (ASCII PLY with a range_grid element)
# --------------------------------------------------------------------------------------


def test_reads_stanford_bunny_scan(shared_data):
    if not BUNNY_SCAN.is_file():
        pytest.skip(f"{BUNNY_SCAN} not available")
    text = BUNNY_SCAN.read_text()
    vertex_count = int(re.search(r"^element vertex (\d+)$", text, re.MULTILINE).group(1))
    points = read_point_cloud(BUNNY_SCAN)
    assert points.shape == (vertex_count, 3) and points.dtype == np.float64
    # Independent parse: the vertex rows follow the header, one "x y z" line each.
    body = text.split("end_header\n", 1)[1].splitlines()
    expected = np.loadtxt(body[:vertex_count], dtype=np.float32).astype(np.float64)
    np.testing.assert_array_equal(points, expected)
    extent = points.max(axis=0) - points.min(axis=0)
    assert np.all(extent > 0.05) and np.all(extent < 0.5)  # a bunny, in metres


def test_reads_stanford_bunny_scan_vertices_not_its_range_grid(shared_data):
    """The 40,256 vertex rows are read; the 204,800 range_grid rows after them are not points.

    (Reading speed belongs to benchmarks, not to an assertion on a shared machine.)
    """
    if not BUNNY_SCAN.is_file():
        pytest.skip(f"{BUNNY_SCAN} not available")
    points = read_point_cloud(BUNNY_SCAN)
    assert points.shape == (40256, 3)
    text = BUNNY_SCAN.read_text()
    body = text.split("end_header\n", 1)[1].splitlines()
    np.testing.assert_array_equal(points[[0, 20000, -1]], np.loadtxt(body[:40256], dtype=np.float32)[[0, 20000, -1]])


# --------------------------------------------------------------------------------------
# Hand-written files, one reader at a time
# --------------------------------------------------------------------------------------

EXPECTED_3 = np.array([[0.0, 1.0, 2.0], [3.5, -4.25, 5.0], [6.0, 7.0, -8.125]])


def test_ply_ascii_with_extra_properties_and_elements(tmp_path):
    path = write_bytes(
        tmp_path / "a.ply",
        "ply\nformat ascii 1.0\ncomment made by hand\nobj_info scanner 1\n"
        "element camera 1\nproperty float fx\nproperty list uchar int ids\n"
        "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty uchar red\n"
        "element face 2\nproperty list uchar int vertex_indices\n"
        "end_header\n"
        "500 2 7 8\n"
        "0 1 2 0.5 255\n3.5 -4.25 5 0.5 0\n6 7 -8.125 1 12\n"
        "3 0 1 2\n3 2 1 0\n",
    )
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def test_ply_ascii_with_crlf_lines(tmp_path):
    path = write_bytes(
        tmp_path / "a.ply",
        "ply\r\nformat ascii 1.0\r\nelement vertex 3\r\nproperty double x\r\nproperty double y\r\n"
        "property double z\r\nelement range_grid 2\r\nproperty list uchar int vertex_indices\r\n"
        "end_header\r\n0 1 2\r\n3.5 -4.25 5\r\n6 7 -8.125\r\n0\r\n1 2\r\n",
    )
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def binary_ply_mesh(byte_order: str, face_sizes: tuple[int, ...]) -> bytes:
    """EXPECTED_3 as a binary PLY with mixed property types and faces of the given sizes."""
    ply_format = {"<": "binary_little_endian", ">": "binary_big_endian"}[byte_order]
    header = (
        f"ply\nformat {ply_format} 1.0\nelement vertex 3\nproperty float x\nproperty double y\n"
        f"property float z\nproperty uchar red\nelement face {len(face_sizes)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    ).encode()
    body = b"".join(struct.pack(f"{byte_order}fdfB", x, y, z, 7) for x, y, z in EXPECTED_3)
    for size in face_sizes:
        body += struct.pack(f"{byte_order}B{size}i", size, *range(size))
    return header + body


@pytest.mark.parametrize("byte_order", ["<", ">"])
@pytest.mark.parametrize("face_sizes", [(3, 3), (4,), (3, 4, 3)])  # faces after the vertices
def test_ply_binary_with_faces(tmp_path, byte_order, face_sizes):
    path = write_bytes(tmp_path / "a.ply", binary_ply_mesh(byte_order, face_sizes))
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


PLY_FORMATS = {"<": "binary_little_endian", ">": "binary_big_endian"}


def binary_ply_faces_first(byte_order: str, face_sizes: tuple[int, ...]) -> bytes:
    """EXPECTED_3 after an element with no properties and a face element with two lists.

    Rows of the faces are (uchar flag, list of int indices, list of float weights with a
    ushort length), so their size varies with ``face_sizes`` and must be walked.
    """
    header = (
        f"ply\nformat {PLY_FORMATS[byte_order]} 1.0\ncomment faces first\nelement marker 4\n"
        f"element face {len(face_sizes)}\nproperty uchar flag\nproperty list uchar int vertex_indices\n"
        "property list ushort float weights\n"
        "element vertex 3\nproperty short id\nproperty double z\nproperty float y\nproperty double x\n"
        "end_header\n"
    ).encode()
    body = b""
    for size in face_sizes:
        body += struct.pack(f"{byte_order}BB{size}iH{size % 3}f", 9, size, *range(size), size % 3, *[0.5] * (size % 3))
    body += b"".join(struct.pack(f"{byte_order}hdfd", -1, z, y, x) for x, y, z in EXPECTED_3)
    return header + body


@pytest.mark.parametrize("byte_order", ["<", ">"])
@pytest.mark.parametrize("face_sizes", [(), (3,), (3, 3, 3), (4, 3, 0, 5)])
def test_ply_binary_with_list_elements_before_vertices(tmp_path, byte_order, face_sizes):
    path = write_bytes(tmp_path / "a.ply", binary_ply_faces_first(byte_order, face_sizes))
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


@pytest.mark.parametrize("byte_order", ["<", ">"])
@pytest.mark.parametrize("lengths", [(2, 2, 2), (0, 3, 1)])
def test_ply_binary_vertices_with_a_list_property(tmp_path, byte_order, lengths):
    header = (
        f"ply\nformat {PLY_FORMATS[byte_order]} 1.0\nelement vertex 3\nproperty float x\n"
        "property list uchar float uv\nproperty float y\nproperty float z\nend_header\n"
    ).encode()
    body = b"".join(
        struct.pack(f"{byte_order}fB{length}fff", x, length, *[0.25] * length, y, z)
        for (x, y, z), length in zip(EXPECTED_3, lengths)
    )
    path = write_bytes(tmp_path / "a.ply", header + body)
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def test_ply_ascii_vertices_with_a_list_property(tmp_path):
    path = write_bytes(
        tmp_path / "a.ply",
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty list uchar float uv\n"
        "property float y\nproperty float z\nend_header\n"
        "0 2 0.5 0.5 1 2\n3.5 0 -4.25 5\n6 1 9 7 -8.125\n",
    )
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


@pytest.mark.parametrize("byte_order", ["<", ">", "ascii"])
@pytest.mark.parametrize("type_name", sorted(SCALAR_TYPES))
def test_ply_every_scalar_type_name(tmp_path, byte_order, type_name):
    """Each PLY type name and alias, in each format, for x, y and z and a property before them."""
    kind = SCALAR_TYPES[type_name]
    values = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 127]]).astype(kind)  # fits every type
    ply_format = PLY_FORMATS.get(byte_order, "ascii")
    header = (
        f"ply\nformat {ply_format} 1.0\nelement vertex 3\nproperty {type_name} w\nproperty {type_name} x\n"
        f"property {type_name} y\nproperty {type_name} z\nend_header\n"
    )
    rows = np.column_stack([values[:, :1], values])
    if byte_order == "ascii":
        body = "".join(" ".join(str(value) for value in row) + "\n" for row in rows.tolist()).encode()
    else:
        body = rows.astype(byte_order + kind).tobytes()
    path = write_bytes(tmp_path / "a.ply", header.encode() + body)
    np.testing.assert_array_equal(read_point_cloud(path), values.astype(np.float64))


def test_ply_ascii_float32_values_round_like_binary(tmp_path):
    path = write_bytes(tmp_path / "a.ply", ASCII_PLY_XYZ_HEADER.format(count=1) + "0.1 0.2 1e39\n")
    with pytest.raises(NonFinitePointsError):  # 1e39 overflows float32 to inf
        read_point_cloud(path)
    write_bytes(path, ASCII_PLY_XYZ_HEADER.format(count=1) + "0.1 0.2 0.3\n")
    np.testing.assert_array_equal(read_point_cloud(path), np.array([[0.1, 0.2, 0.3]], np.float32).astype(np.float64))


def test_ply_ascii_with_cr_lines_and_list_elements_before_vertices(tmp_path):
    path = write_bytes(
        tmp_path / "a.ply",
        "ply\rformat ascii 1.0\rcomment old Mac line ends\relement empty 2\relement face 3\r"
        "property list uchar int vertex_indices\rproperty uchar flag\r"
        "element vertex 3\rproperty double x\rproperty double y\rproperty double z\rend_header\r"
        "\r\r3 0 1 2 1\r0 1\r4 0 1 2 3 0\r0 1 2\r3.5 -4.25 5\r6 7 -8.125",  # no final line break
    )
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def test_ply_rows_after_the_vertices_are_not_read(tmp_path):
    """Elements after the vertices may even be malformed: their rows are never parsed."""
    header = ASCII_PLY_XYZ_HEADER.format(count=3).replace(
        "end_header", "element range_grid 204800\nproperty list uchar int vertex_indices\nend_header"
    )
    rows = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in EXPECTED_3.tolist())
    path = write_bytes(tmp_path / "a.ply", header + rows + "not a row\n" * 10)
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)
    binary = binary_ply_mesh("<", (3, 3)) + b"trailing garbage"
    path = write_bytes(tmp_path / "b.ply", binary[:-30])  # the faces are cut short
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def test_ply_header_parse():
    import io

    data = (
        b"ply\r\nformat binary_big_endian 1.0\r\ncomment  two  spaces\r\nobj_info num_cols 512\r\n"
        b"element vertex 2\r\nproperty float32 x\r\nproperty list uint8 int32 ids\r\ncomment late\r\n"
        b"element face 0\r\nend_header\r\n\x01\x02"
    )
    header = read_header(io.BytesIO(data))
    assert header.format == "binary_big_endian" and header.byte_order == ">"
    assert header.comments == (" two  spaces", "late") and header.obj_info == ("num_cols 512",)
    assert header.element_names == ("vertex", "face")
    vertex = header.element("vertex")
    assert vertex.count == 2 and vertex.property_names == ("x", "ids")
    assert vertex.property("x").kind == "f4" and not vertex.property("x").is_list
    assert vertex.property("ids").kind == "i4" and vertex.property("ids").count_kind == "u1"
    assert header.element("face").count == 0 and header.element("face").properties == ()
    assert data[header.data_offset :] == b"\x01\x02" and header.newline == b"\r\n"


def test_written_ply_is_exactly_the_documented_layout(tmp_path):
    points = np.array([[1.0, -2.0, 3.5], [0.0, 1e-300, -0.0]])
    write_point_cloud(tmp_path / "a.ply", points)
    assert (tmp_path / "a.ply").read_bytes() == (
        b"ply\nformat binary_little_endian 1.0\ncomment written by logdesc-rt\nelement vertex 2\n"
        b"property double x\nproperty double y\nproperty double z\nend_header\n" + points.astype("<f8").tobytes()
    )


@pytest.mark.parametrize("text", [False, True])
@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_ply_matches_plyfile(tmp_path, text, byte_order):
    """Optional cross-check against plyfile (GPL, never a dependency): skipped when absent."""
    plyfile = pytest.importorskip("plyfile")
    rng = np.random.default_rng(7)
    faces = np.empty(50, dtype=[("flag", "u1"), ("vertex_indices", object)])
    faces["flag"] = 1
    faces["vertex_indices"] = [np.arange(rng.integers(0, 6), dtype=np.int32) for _ in range(50)]
    vertices = np.empty(200, dtype=[("nx", "f4"), ("x", "f4"), ("y", "f8"), ("z", "i2"), ("red", "u1")])
    for name in vertices.dtype.names:
        vertices[name] = (rng.normal(size=200) * 100).astype(vertices.dtype[name])
    elements = [plyfile.PlyElement.describe(faces, "face"), plyfile.PlyElement.describe(vertices, "vertex")]
    path = tmp_path / "a.ply"
    plyfile.PlyData(elements, text=text, byte_order=byte_order).write(str(path))
    expected = np.column_stack([vertices["x"], vertices["y"], vertices["z"]])
    np.testing.assert_array_equal(read_point_cloud(path), expected)


PCD_HEADER = (
    "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
    "FIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\n"
    "WIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA {encoding}\n"
)


def test_pcd_ascii_with_extra_fields(tmp_path):
    header = PCD_HEADER.format(
        fields="rgb x normal y z", sizes="4 4 4 8 4", types="F F F F F", counts="1 1 3 1 1", encoding="ascii"
    )
    rows = "".join(f"4.2e6 {x} 0 0 1 {y} {z}\n" for x, y, z in EXPECTED_3)
    path = write_bytes(tmp_path / "a.pcd", header + rows)
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def test_pcd_ascii_rounds_float32_fields_like_binary(tmp_path):
    header = PCD_HEADER.format(fields="x y z", sizes="4 4 8", types="F F F", counts="1 1 1", encoding="ascii")
    path = write_bytes(tmp_path / "a.pcd", header + "0.1 0.1 0.1\n" * 3)
    np.testing.assert_array_equal(read_point_cloud(path)[0], [np.float32(0.1), np.float32(0.1), 0.1])


def test_pcd_binary(tmp_path):
    header = PCD_HEADER.format(
        fields="x y _ z intensity", sizes="4 8 1 4 2", types="F F U F U", counts="1 1 3 1 1", encoding="binary"
    )
    body = b"".join(struct.pack("<fd3BfH", x, y, 0, 0, 0, z, 9) for x, y, z in EXPECTED_3)
    path = write_bytes(tmp_path / "a.pcd", header.encode() + body)
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def lzf_literals(data: bytes) -> bytes:
    """A valid LZF stream of literal runs only (up to 32 bytes each): no compression."""
    return b"".join(bytes([len(chunk) - 1]) + chunk for chunk in (data[i : i + 32] for i in range(0, len(data), 32)))


def test_pcd_binary_compressed(tmp_path):
    header = PCD_HEADER.format(
        fields="intensity x y z", sizes="2 4 4 8", types="U F F F", counts="1 1 1 1", encoding="binary_compressed"
    )
    # Column-major: every field's values for all points, field after field.
    raw = (
        struct.pack("<3H", 1, 2, 3)
        + struct.pack("<3f", *EXPECTED_3[:, 0])
        + struct.pack("<3f", *EXPECTED_3[:, 1])
        + struct.pack("<3d", *EXPECTED_3[:, 2])
    )
    compressed = lzf_literals(raw)
    sizes = struct.pack("<II", len(compressed), len(raw))
    path = write_bytes(tmp_path / "a.pcd", header.encode() + sizes + compressed)
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_files_written_by_pypcd4(tmp_path, encoding):
    """Cross-check against an independent writer (real LZF back-references included)."""
    pypcd4 = pytest.importorskip("pypcd4")
    rng = np.random.default_rng(3)
    xyz = np.round(rng.normal(size=(500, 3)), 2).astype(np.float32)  # repeats -> LZF back-references
    rgb = rng.integers(0, 2**24, size=500).astype(np.float32)
    cloud = pypcd4.PointCloud.from_points(
        [rgb, xyz[:, 0], xyz[:, 1], xyz[:, 2]], ("rgb", "x", "y", "z"), [np.float32] * 4
    )
    path = tmp_path / "a.pcd"
    cloud.save(str(path), encoding=pypcd4.Encoding(encoding))
    loaded = read_point_cloud(path)
    if encoding == "ascii":  # pypcd4 prints 10 decimals, not enough to round-trip float32 exactly
        np.testing.assert_allclose(loaded, xyz, rtol=1e-6, atol=1e-9)
    else:
        np.testing.assert_array_equal(loaded, xyz.astype(np.float64))


def test_lzf_overlapping_back_reference():
    # Literal "ab", then copy 7 bytes from 2 back (overlapping): "ab" repeats.
    stream = b"\x01ab" + bytes([(5 << 5) | 0, 1])
    assert _lzf_decompress(stream, 9) == b"ababababa"
    # A long back-reference: length field 7 plus an extra byte (7 + 3 + 2 = 12).
    stream = b"\x02xyz" + bytes([(7 << 5) | 0, 3, 2])
    assert _lzf_decompress(stream, 15) == b"xyz" * 5


@pytest.mark.parametrize(
    "stream, problem",
    [
        (b"\x05ab", "past the end"),
        (b"\x01ab" + bytes([5 << 5]), "cut off"),
        (b"\x01ab" + bytes([5 << 5, 9]), "before the start"),
        (b"\x01ab", "2 bytes, not the announced 3"),
    ],
)
def test_lzf_rejects_corrupt_streams(stream, problem):
    with pytest.raises(ValueError, match=problem):
        _lzf_decompress(stream, 3)


@pytest.mark.parametrize(
    "text",
    [
        "OFF\n# a comment\n3 2 0\n0 1 2\n3.5 -4.25 5  # inline comment\n\n6 7 -8.125\n3 0 1 2\n3 2 1 0\n",
        "OFF 3 1 0\n0 1 2\n3.5 -4.25 5\n6 7 -8.125\n3 0 1 2\n",
        "OFF3 1 0\n0 1 2\n3.5 -4.25 5\n6 7 -8.125\n3 0 1 2\n",  # ModelNet's fused header
        "# header comment first\nCOFF\n3 1 0\n0 1 2 255 0 0 255\n3.5 -4.25 5 0 255 0 255\n6 7 -8.125 0 0 255 255\n"
        "3 0 1 2\n",
        "3 0 0\n0 1 2\n3.5 -4.25 5\n6 7 -8.125\n",  # keyword omitted
    ],
)
def test_off_variants(tmp_path, text):
    path = write_bytes(tmp_path / "a.off", text)
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def test_csv_with_header_and_extra_columns(tmp_path):
    path = write_bytes(
        tmp_path / "a.csv",
        "x, y, z, nx, ny, nz\n0, 1, 2, 0, 0, 1\n3.5,-4.25,5,0,0,1\n\n6 , 7 , -8.125 , 0 , 0 , 1\n",
    )
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def test_whitespace_xyz_with_extra_columns_and_comments(tmp_path):
    path = write_bytes(
        tmp_path / "a.xyz",
        "# scanner export\n0 1 2 255 0 0\n3.5\t-4.25\t5\t0\t255\t0\n\n   6   7   -8.125 0 0 255   \n",
    )
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


def test_txt_with_plain_header_and_bom(tmp_path):
    path = write_bytes(tmp_path / "a.TXT", "\ufeffX Y Z\n0 1 2\n3.5 -4.25 5\n6 7 -8.125\n")
    np.testing.assert_array_equal(read_point_cloud(path), EXPECTED_3)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
def test_npy_takes_first_three_columns(tmp_path, dtype):
    array = np.arange(24).reshape(4, 6).astype(dtype)
    np.save(tmp_path / "a.npy", array)
    loaded = read_point_cloud(tmp_path / "a.npy")
    assert loaded.dtype == np.float64
    np.testing.assert_array_equal(loaded, array[:, :3])


# --------------------------------------------------------------------------------------
# Errors: each names the file and the problem
# --------------------------------------------------------------------------------------


def test_missing_file(tmp_path):
    path = tmp_path / "nothing.ply"
    with pytest.raises(PointCloudFileError, match=path_and(path, "no such file")):
        read_point_cloud(path)


def test_directory(tmp_path):
    path = tmp_path / "folder.xyz"
    path.mkdir()
    with pytest.raises(PointCloudFileError, match=path_and(path, "is a directory")):
        read_point_cloud(path)


@pytest.mark.parametrize("suffix", SUPPORTED_SUFFIXES)
def test_empty_file(tmp_path, suffix):
    path = write_bytes(tmp_path / f"empty{suffix}", b"")
    with pytest.raises(PointCloudFileError, match=path_and(path, "empty")):
        read_point_cloud(path)


@pytest.mark.parametrize("name", ["cloud.obj", "cloud", "cloud.ply.gz"])
def test_unsupported_suffix(tmp_path, name):
    path = write_bytes(tmp_path / name, "0 0 0\n")
    with pytest.raises(PointCloudFileError, match=path_and(path, r"unsupported file suffix.*\.ply, \.pcd")):
        read_point_cloud(path)
    with pytest.raises(PointCloudFileError, match="unsupported file suffix"):
        write_point_cloud(path, EXPECTED_3)


def test_truncated_binary_ply(tmp_path):
    full = tmp_path / "full.ply"
    write_point_cloud(full, EXPECTED_3)
    path = write_bytes(tmp_path / "cut.ply", full.read_bytes()[:-5])
    with pytest.raises(PointCloudFileError, match=path_and(path, "early end-of-file")):
        read_point_cloud(path)


XYZ_PROPERTIES = "property float x\nproperty float y\nproperty float z\n"


@pytest.mark.parametrize(
    "content, problem",
    [
        # Header
        ("ply\nformat ascii 2.0\nelement vertex 1\n" + XYZ_PROPERTIES + "end_header\n1 2 3\n", "version '2.0'"),
        ("ply\nformat binary 1.0\nelement vertex 1\n" + XYZ_PROPERTIES + "end_header\n", "expected 'format <ascii"),
        ("ply\nelement vertex 1\n" + XYZ_PROPERTIES + "end_header\n1 2 3\n", "'element' before the 'format'"),
        ("ply\nformat ascii 1.0\nelement vertex 1\n" + XYZ_PROPERTIES + "1 2 3\n", "no 'end_header'"),
        ("ply\nformat ascii 1.0\nproperty float x\nend_header\n", "'property' before any 'element'"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty real x\nend_header\n", "unknown property type 'real'"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty int x\nend_header\n", "'x' twice"),
        ("ply\nformat ascii 1.0\nelement f 1\nproperty list float int v\nend_header\n", "integer type, not 'float'"),
        ("ply\nformat ascii 1.0\nelement vertex -1\n" + XYZ_PROPERTIES + "end_header\n", "non-negative integer"),
        ("ply\nformat ascii 1.0\nelement vertex 1e3\n" + XYZ_PROPERTIES + "end_header\n", "non-negative integer"),
        ("ply\nformat ascii 1.0\n\nelement vertex 1\n" + XYZ_PROPERTIES + "end_header\n", "header line 3 is empty"),
        ("ply\nformat ascii 1.0\nvertex 1\nend_header\n", "unknown keyword 'vertex'"),
        (
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\nproperty float y\n"
            "property float z\nend_header\n1 0 2 3\n",
            "'x' of element 'vertex' is a list",
        ),
        # ASCII rows
        (
            ASCII_PLY_XYZ_HEADER.format(count=3) + "1 2 3\n4 5 6\n",
            "early end-of-file: element 'vertex' declares 3 rows, the file ends after 2",
        ),
        (
            ASCII_PLY_XYZ_HEADER.format(count=2) + "1 2 3 4 5 6\n",
            "line 8: 6 values, but the properties of 'vertex' take 3",
        ),
        (ASCII_PLY_XYZ_HEADER.format(count=2) + "1 2 3\n\n4 5 6\n", "line 9: property 'x' is missing"),
        (ASCII_PLY_XYZ_HEADER.format(count=1) + "1 2 zz\n", "line 8: property 'z': 'zz' is not a number"),
        (
            "ply\nformat ascii 1.0\nelement vertex 1\n" + XYZ_PROPERTIES
            + "property uchar red\nend_header\n1 2 3 256\n",
            "property 'red': 256 is out of range",
        ),
        (
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty int x\nproperty int y\nproperty int z\n"
            "end_header\n1 2.5 3\n",
            "property 'y': '2.5' is not an integer",
        ),
        (
            "ply\nformat ascii 1.0\nelement face 2\nproperty list uchar int v\nelement vertex 1\n" + XYZ_PROPERTIES
            + "end_header\n3 0 1 2\n3 0 1\n1 2 3\n",
            "element 'face', line 11: item 2 of list 'v' is missing",
        ),
        (
            "ply\nformat ascii 1.0\nelement face 1\nproperty list char int v\nelement vertex 1\n" + XYZ_PROPERTIES
            + "end_header\n-1\n1 2 3\n",
            "list 'v' has negative length -1",
        ),
        (
            "ply\nformat ascii 1.0\nelement camera 2\nproperty float f\nelement vertex 1\n" + XYZ_PROPERTIES
            + "end_header\n500\n",
            "early end-of-file: element 'camera' declares 2 rows, the file ends after 1",
        ),
        # Binary rows
        (
            b"ply\nformat binary_little_endian 1.0\nelement camera 2\nproperty double f\nelement vertex 1\n"
            + XYZ_PROPERTIES.encode() + b"end_header\n" + bytes(10),
            "early end-of-file: element 'camera' needs 16 bytes from byte 150, the file has 10",
        ),
        (
            b"ply\nformat binary_big_endian 1.0\nelement face 2\nproperty list uchar int v\nelement vertex 1\n"
            + XYZ_PROPERTIES.encode() + b"end_header\n" + struct.pack(">B3iB", 3, 0, 1, 2, 200) + bytes(12),
            "early end-of-file: element 'face' row 1 \\(of 2\\), list 'v', runs past the end",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list char int v\nelement vertex 1\n"
            + XYZ_PROPERTIES.encode() + b"end_header\n" + struct.pack("<b3f", -2, 1, 2, 3),
            "element 'face' row 0: list 'v' has negative length -2",
        ),
    ],
)
def test_corrupt_ply(tmp_path, content, problem):
    path = write_bytes(tmp_path / "bad.ply", content)
    with pytest.raises(PointCloudFileError, match=path_and(path, "cannot parse as PLY: .*" + problem)):
        read_point_cloud(path)


def test_truncated_binary_pcd(tmp_path):
    header = PCD_HEADER.format(fields="x y z", sizes="4 4 4", types="F F F", counts="1 1 1", encoding="binary")
    path = write_bytes(tmp_path / "cut.pcd", header.encode() + bytes(30))
    with pytest.raises(PointCloudFileError, match=path_and(path, "truncated.*36 bytes.*found 30")):
        read_point_cloud(path)


@pytest.mark.parametrize(
    "name, content, problem",
    [
        ("garbage.xyz", "hello world\nthis is not a cloud\n", "cannot parse as XYZ"),
        ("garbage.csv", "x,y,z\n1,2\n", "cannot parse as CSV"),
        ("binary.txt", b"\x00\xff\xfe garbage", "not a text file"),
        ("garbage.ply", "plyx\n", "cannot parse as PLY"),
        ("garbage.ply", "hello", "not a PLY file"),
        ("garbage.pcd", "hello world\n", "not a PCD file"),
        ("garbage.off", "hello world\n", "not an OFF file"),
        ("garbage.npy", "hello world\n", "cannot parse as NPY"),
        ("short.off", "OFF\n5 0 0\n1 2 3\n", "announces 5 vertices, the file has 1"),
        ("four.off", "4OFF\n1 0 0\n1 2 3 1\n", "not supported"),
        ("noxyz.ply", "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int v\nend_header\n", "no 'vertex'"),
        (
            "noz.ply",
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
            "lacks property z",
        ),
        ("nodata.pcd", "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\n", "without a DATA line"),
        (
            "count.pcd",
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 2\nDATA ascii\n1 2 3\n",
            "POINTS 2 but the ascii data has 1 lines",
        ),
        ("fields.pcd", "FIELDS x y\nSIZE 4 4\nTYPE F F\nPOINTS 1\nDATA ascii\n1 2\n", "must name 'z'"),
    ],
)
def test_corrupt_content(tmp_path, name, content, problem):
    path = write_bytes(tmp_path / name, content)
    with pytest.raises(PointCloudFileError, match=path_and(path, problem)):
        read_point_cloud(path)


@pytest.mark.parametrize(
    "name, content",
    [
        ("zero.off", "OFF\n0 0 0\n"),
        ("header_only.csv", "x,y,z\n"),
        ("comments.xyz", "# nothing here\n\n"),
        ("zero.ply", ASCII_PLY_XYZ_HEADER.format(count=0)),
        ("zero.pcd", "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 0\nPOINTS 0\nDATA ascii\n"),
    ],
)
def test_zero_points(tmp_path, name, content):
    path = write_bytes(tmp_path / name, content)
    with pytest.raises(PointCloudFileError, match=path_and(path, "no points")):
        read_point_cloud(path)


def test_zero_points_npy(tmp_path):
    np.save(tmp_path / "zero.npy", np.zeros((0, 3)))
    with pytest.raises(PointCloudFileError, match="no points"):
        read_point_cloud(tmp_path / "zero.npy")


@pytest.mark.parametrize("shape", [(5, 2), (5,), (2, 5, 3)])
def test_npy_wrong_shape(tmp_path, shape):
    path = tmp_path / "wrong.npy"
    np.save(path, np.zeros(shape))
    with pytest.raises(PointCloudFileError, match=path_and(path, re.escape(f"shape {shape}"))):
        read_point_cloud(path)


def test_npy_refuses_pickles_and_archives(tmp_path):
    pickled = tmp_path / "objects.npy"
    np.save(pickled, np.array([[1, 2, 3]], dtype=object), allow_pickle=True)
    with pytest.raises(PointCloudFileError, match=path_and(pickled, "(pickle|Python objects)")):
        read_point_cloud(pickled)
    archive = tmp_path / "archive.npy"
    with archive.open("wb") as file:
        np.savez(file, points=EXPECTED_3)
    with pytest.raises(PointCloudFileError, match=path_and(archive, "npz archive")):
        read_point_cloud(archive)


def test_npy_of_strings_is_a_shape_error_naming_the_file(tmp_path):
    path = tmp_path / "strings.npy"
    np.save(path, np.array([["a", "b", "c"]]))
    with pytest.raises(PointCloudShapeError, match=re.escape(str(path))):
        read_point_cloud(path)


def test_npy_header_claiming_huge_shape(tmp_path):
    path = tmp_path / "huge.npy"
    np.save(path, np.zeros((2, 3)))
    data = path.read_bytes().replace(b"(2, 3)", b"(9999999999999, 3)".ljust(6))
    write_bytes(path, data)
    with pytest.raises(PointCloudFileError, match=re.escape(str(path))):
        read_point_cloud(path)


@pytest.mark.parametrize(
    "name, content",
    [
        ("nan.xyz", "0 0 0\n1 nan 2\n"),
        ("inf.csv", "x,y,z\n0,0,0\n1,2,inf\n"),
        ("nan.off", "OFF\n2 0 0\n0 0 0\nnan 1 1\n"),
        ("nan.ply", ASCII_PLY_XYZ_HEADER.format(count=1) + "nan 0 0\n"),
    ],
)
def test_non_finite_coordinates_name_the_file(tmp_path, name, content):
    path = write_bytes(tmp_path / name, content)
    with pytest.raises(NonFinitePointsError, match=path_and(path, "NaN or inf")):
        read_point_cloud(path)


def test_write_errors(tmp_path):
    missing_folder = tmp_path / "no" / "such" / "cloud.ply"
    with pytest.raises(PointCloudFileError, match=path_and(missing_folder, "cannot write")):
        write_point_cloud(missing_folder, EXPECTED_3)
    with pytest.raises(PointCloudShapeError, match="points"):
        write_point_cloud(tmp_path / "a.xyz", np.zeros((3, 2)))
    with pytest.raises(NonFinitePointsError):
        write_point_cloud(tmp_path / "a.xyz", [[0, 0, np.nan]])
    assert not (tmp_path / "a.xyz").exists()


def test_file_errors_are_os_errors(tmp_path):
    """Generic handlers written for file problems (``except OSError``) keep working."""
    with pytest.raises(OSError):
        read_point_cloud(tmp_path / "missing.npy")


# --------------------------------------------------------------------------------------
# Fuzz: corrupt files of every suffix give a valid cloud or a logdesc error, nothing else
# --------------------------------------------------------------------------------------


def _seed_files() -> dict[str, list[bytes]]:
    """Valid files of each suffix, as bytes, for the fuzzer to corrupt."""
    import tempfile

    seeds: dict[str, list[bytes]] = {suffix: [] for suffix in CORE_SUFFIXES}
    with tempfile.TemporaryDirectory() as folder:
        for suffix in CORE_SUFFIXES:
            path = Path(folder) / f"seed{suffix}"
            write_point_cloud(path, EXPECTED_3)
            seeds[suffix].append(path.read_bytes())
    seeds[".ply"].append(
        b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        b"element face 1\nproperty list uchar int vertex_indices\nend_header\n1 2 3\n4 5 6\n2 0 1\n"
    )
    seeds[".ply"].append(binary_ply_mesh("<", (3, 4)))
    seeds[".ply"].append(binary_ply_faces_first(">", (4, 3, 0)))
    seeds[".ply"].append(
        b"ply\nformat ascii 1.0\nelement face 2\nproperty list uchar int vertex_indices\nelement vertex 2\n"
        b"property float x\nproperty list uchar float uv\nproperty float y\nproperty float z\nend_header\n"
        b"3 0 1 2\n0\n1 2 0.5 0.5 2 3\n4 0 5 6\n"
    )
    raw = struct.pack("<6f", 1, 2, 3, 4, 5, 6)
    # x values 1, 2 as literals, then a back-reference (length 7 + 3 + 2 = 12, 12 bytes back)
    # copying them again: the cloud (1, 2, 1), (2, ...) is odd but valid.
    compressed = lzf_literals(raw[:12]) + bytes([7 << 5, 3, 11])
    seeds[".pcd"].append(
        b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary_compressed\n"
        + struct.pack("<II", len(compressed), 24)
        + compressed
    )
    seeds[".pcd"].append(
        b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary\n" + raw
    )
    return seeds


SEEDS = _seed_files()


@st.composite
def corrupted(draw, seeds: list[bytes]) -> bytes:
    """A seed file with a few random edits: truncation, byte changes, insertions, deletions."""
    data = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(1, 4))):
        position = draw(st.integers(0, len(data)))
        edit = draw(st.sampled_from(["truncate", "replace", "insert", "delete"]))
        if edit == "truncate":
            del data[position:]
        elif edit == "replace" and position < len(data):
            data[position] = draw(st.integers(0, 255))
        elif edit == "insert":
            data[position:position] = draw(st.binary(min_size=1, max_size=8))
        elif edit == "delete":
            del data[position : position + draw(st.integers(1, 8))]
    return bytes(data)


TEXTISH = st.text(alphabet="0123456789 .,-+eE\nnaifOFplyx#\t", max_size=200).map(str.encode)


# numpy's notice on Python-2 style NPY headers, which corrupted headers can resemble.
@pytest.mark.filterwarnings("ignore:Reading `.npy` or `.npz` file required additional header parsing")
@pytest.mark.parametrize("suffix", CORE_SUFFIXES)
def test_fuzz_corrupt_files_raise_only_logdesc_errors(tmp_path, suffix):
    path = tmp_path / f"fuzz{suffix}"

    @settings(max_examples=50, deadline=None, database=None)
    @given(content=st.one_of(st.binary(max_size=300), TEXTISH, corrupted(SEEDS[suffix])))
    def check(content):
        path.write_bytes(content)
        try:
            points = read_point_cloud(path)
        except LogdescError:
            return
        assert isinstance(points, np.ndarray) and points.dtype == np.float64
        assert points.ndim == 2 and points.shape[1] == 3 and points.shape[0] >= 1
        assert np.isfinite(points).all()

    check()


# ----------------------------------------------------------------------------- attributes
def _attributes(count: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(count, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return {
        "nx": normals[:, 0].astype(np.float32),
        "ny": normals[:, 1].astype(np.float32),
        "nz": normals[:, 2].astype(np.float32),
        "red": rng.integers(0, 256, count).astype(np.uint8),
        "intensity": rng.random(count),
    }


def test_ply_keeps_attributes_in_their_types(tmp_path):
    from logdesc_rt.io import read_point_attributes

    points = np.random.default_rng(90).normal(size=(40, 3))
    attributes = _attributes(40, 91)
    write_point_cloud(tmp_path / "cloud.ply", points, attributes)
    assert np.array_equal(read_point_cloud(tmp_path / "cloud.ply"), points)
    back = read_point_attributes(tmp_path / "cloud.ply")
    assert list(back) == list(attributes)
    for name, values in attributes.items():
        assert back[name].dtype == values.dtype and np.array_equal(back[name], values), name


@pytest.mark.parametrize("suffix", [".pcd", ".xyz", ".csv", ".npy"])
def test_other_formats_write_attributes_as_extra_columns(tmp_path, suffix):
    points = np.random.default_rng(92).normal(size=(30, 3))
    attributes = _attributes(30, 93)
    path = tmp_path / f"cloud{suffix}"
    write_point_cloud(path, points, attributes)
    assert np.array_equal(read_point_cloud(path), points)  # x, y, z still read exactly
    if suffix == ".csv":
        assert path.read_text().splitlines()[0] == "x,y,z,nx,ny,nz,red,intensity"
    if suffix == ".npy":
        assert np.load(path).shape == (30, 8)


def test_attributes_are_checked_and_off_refuses_them(tmp_path):
    points = np.zeros((5, 3)) + np.arange(5)[:, None]
    with pytest.raises(PointCloudFileError, match="OFF"):
        write_point_cloud(tmp_path / "cloud.off", points, {"intensity": np.ones(5)})
    with pytest.raises(ValueError, match="intensity"):
        write_point_cloud(tmp_path / "cloud.ply", points, {"intensity": np.ones(4)})
    with pytest.raises(ValueError, match="name"):
        write_point_cloud(tmp_path / "cloud.ply", points, {"x": np.ones(5)})


def test_normals_turn_with_the_pose_and_colours_do_not():
    from scipy.spatial.transform import Rotation

    from logdesc_rt.io import transform_attributes

    attributes = _attributes(20, 94)
    rotation = Rotation.from_euler("xyz", [10, 50, -30], degrees=True).as_matrix()
    moved = transform_attributes(attributes, rotation)
    normals = np.stack([attributes[n] for n in ("nx", "ny", "nz")], axis=1).astype(np.float64)
    turned = np.stack([moved[n] for n in ("nx", "ny", "nz")], axis=1)
    assert np.allclose(turned, normals @ rotation.T, atol=1e-6)
    assert moved["nx"].dtype == np.float32
    assert np.array_equal(moved["red"], attributes["red"]) and np.array_equal(
        moved["intensity"], attributes["intensity"]
    )


def test_stanford_conf_poses_overlay_two_real_scans(shared_data):
    conf = BUNNY_SCAN.parent / "bun.conf"
    if not conf.is_file():
        pytest.skip(f"shared data not found at {conf}")
    poses = read_stanford_conf(conf)
    assert len(poses) == 10 and {"bun000.ply", "bun045.ply"} <= set(poses)
    from pykdtree.kdtree import KDTree

    source, target = (read_point_cloud(BUNNY_SCAN.parent / name) for name in ("bun000.ply", "bun045.ply"))
    moved = source @ poses["bun000.ply"][:3, :3].T + poses["bun000.ply"][:3, 3]
    in_target = (moved - poses["bun045.ply"][:3, 3]) @ poses["bun045.ply"][:3, :3]
    distance, _ = KDTree(target).query(in_target, k=1)
    # The scans overlap by about 80 % at 0.5 mm spacing: with the convention's sign of qw the
    # overlap lines up to scanner noise; with the quaternion as written, it would not.
    assert np.median(distance) < 0.001


def test_stanford_conf_reads_bmesh_lines_and_skips_the_camera(tmp_path):
    conf = tmp_path / "scans.conf"
    # A quarter turn about z written as scanalyze does: (qx, qy, qz, qw) with qw's sign flipped.
    half = np.sqrt(0.5)
    conf.write_text(f"camera 0 0 1 0 0 0 1\nbmesh a.ply 1 2 3 0 0 {half} {-half}\n\nbmesh b.ply 0 0 0 0 0 0 1\n")
    poses = read_stanford_conf(conf)
    assert list(poses) == ["a.ply", "b.ply"]
    expected = np.array([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    np.testing.assert_allclose(poses["a.ply"], expected, atol=1e-12)
    np.testing.assert_allclose(poses["b.ply"], np.eye(4), atol=1e-12)


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ("camera 0 0 0 0 0 0 1\n", "no 'bmesh' line"),
        ("bmesh a.ply 1 2 3 0 0 0\n", "line 1: expected seven finite numbers"),
        ("bmesh a.ply 1 2 x 0 0 0 1\n", "line 1: expected 'bmesh NAME"),
        ("bmesh a.ply 1 2 nan 0 0 0 1\n", "line 1: expected seven finite numbers"),
        ("bmesh a.ply 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\n", "line 2: scan a.ply is listed twice"),
        ("bmesh a.ply 0 0 0 0 0 0 0\n", "quaternion of a.ply is zero"),
    ],
)
def test_stanford_conf_errors_name_the_file_and_line(tmp_path, content, problem):
    conf = tmp_path / "scans.conf"
    conf.write_text(content)
    with pytest.raises(PointCloudFileError, match=re.escape(problem)) as error:
        read_stanford_conf(conf)
    assert str(error.value).startswith(str(conf))


def test_stanford_conf_missing_file(tmp_path):
    with pytest.raises(PointCloudFileError, match="no such file"):
        read_stanford_conf(tmp_path / "absent.conf")

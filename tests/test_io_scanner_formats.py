"""LAS / LAZ (laspy) and E57 (pye57): round trips within the formats' precision, attributes,
bad files (empty, wrong magic, truncated, corrupt, no points) as PointCloudFileError naming
the file, and a clear error naming the extra when the library is missing. Every file is
written by the tests themselves. Skipped where the extra is not installed (CI installs both)."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from logdesc_rt.errors import LogdescError, PointCloudFileError
from logdesc_rt.io import (
    check_format_available,
    read_point_attributes,
    read_point_cloud,
    writable_attributes,
    write_point_cloud,
)

HAS_LASPY = importlib.util.find_spec("laspy") is not None
HAS_PYE57 = importlib.util.find_spec("pye57") is not None
needs_laspy = pytest.mark.skipif(not HAS_LASPY, reason="laspy not installed (pip install '.[las]')")
needs_pye57 = pytest.mark.skipif(not HAS_PYE57, reason="pye57 not installed (pip install '.[e57]')")
LAS_SUFFIXES = [pytest.param(".las", marks=needs_laspy), pytest.param(".laz", marks=needs_laspy)]
ALL_SUFFIXES = [*LAS_SUFFIXES, pytest.param(".e57", marks=needs_pye57)]
# Relative precision of the written coordinates (module docstrings of las.py and e57.py).
RELATIVE_PRECISION = {".las": 2.5e-9, ".laz": 2.5e-9, ".e57": 6e-8}


def _cloud(seed: int, count: int = 300, scale: float = 1.0, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(count, 3)) * scale + np.asarray(shift)


def _named(path: Path, problem: str) -> str:
    return re.escape(str(path)) + ".*" + problem


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
@pytest.mark.parametrize(
    ("scale", "shift"),
    [(1.0, (0.0, 0.0, 0.0)), (0.001, (0.0, 0.0, 0.0)), (30.0, (500_000.0, 4_000_000.0, 250.0))],
    ids=["metre", "millimetre", "utm"],
)
def test_round_trip_within_the_format_precision(tmp_path, suffix, scale, shift):
    points = _cloud(1, scale=scale, shift=shift)
    path = tmp_path / f"cloud{suffix}"
    write_point_cloud(path, points)
    back = read_point_cloud(path)
    extent = np.ptp(points, axis=0).max()
    assert back.shape == points.shape and back.dtype == np.float64
    error = np.abs(back - points).max()
    assert error <= RELATIVE_PRECISION[suffix] * extent, error
    write_point_cloud(path, points[:7])  # overwrite with fewer points: no stale data
    assert read_point_cloud(path).shape == (7, 3)


@needs_laspy
def test_laz_is_compressed_and_las_is_not(tmp_path):
    points = _cloud(2, count=2000)
    write_point_cloud(tmp_path / "a.las", points)
    write_point_cloud(tmp_path / "a.laz", points)
    assert (tmp_path / "a.laz").stat().st_size < 0.8 * (tmp_path / "a.las").stat().st_size
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "a.las"), read_point_cloud(tmp_path / "a.laz"))


@pytest.mark.parametrize("suffix", LAS_SUFFIXES)
def test_las_keeps_attributes_as_standard_or_extra_dimensions(tmp_path, suffix):
    rng = np.random.default_rng(3)
    points = _cloud(3, count=50)
    attributes = {
        "intensity": rng.integers(0, 65535, 50).astype(np.uint16),
        "scan": rng.integers(0, 7, 50).astype(np.int32),
        "confidence": rng.random(50).astype(np.float32),
        "red": rng.integers(0, 256, 50).astype(np.uint8),
        "green": rng.integers(0, 256, 50).astype(np.uint8),
        "blue": rng.integers(0, 256, 50).astype(np.uint8),
    }
    path = tmp_path / f"cloud{suffix}"
    write_point_cloud(path, points, attributes)
    back = read_point_attributes(path)
    assert set(back) == set(attributes)
    for name, values in attributes.items():
        np.testing.assert_array_equal(back[name], values, err_msg=name)
    assert back["scan"].dtype == np.int32 and back["confidence"].dtype == np.float32
    # A float intensity does not fit LAS's uint16 intensity: named, not silently rounded.
    with pytest.raises(ValueError, match="'intensity'.*uint16"):
        write_point_cloud(path, points, {"intensity": rng.random(50)})
    assert set(writable_attributes(path, {"intensity": rng.random(50), "scan": attributes["scan"]})) == {"scan"}


@needs_pye57
def test_e57_keeps_intensity_and_colours_and_refuses_other_attributes(tmp_path):
    rng = np.random.default_rng(4)
    points = _cloud(4, count=60)
    attributes = {
        "intensity": rng.random(60),
        "red": rng.integers(0, 256, 60).astype(np.uint8),
        "green": rng.integers(0, 256, 60).astype(np.uint8),
        "blue": rng.integers(0, 256, 60).astype(np.uint8),
    }
    path = tmp_path / "cloud.e57"
    write_point_cloud(path, points, attributes)
    back = read_point_attributes(path)
    assert set(back) == set(attributes)
    for name in ("red", "green", "blue"):
        np.testing.assert_array_equal(back[name], attributes[name])
    np.testing.assert_allclose(back["intensity"], attributes["intensity"], rtol=1e-6)
    with pytest.raises(ValueError, match="E57 has no field for attribute.*scan"):
        write_point_cloud(path, points, {"scan": np.zeros(60, dtype=np.int32)})
    assert set(writable_attributes(path, {**attributes, "scan": np.zeros(60)})) == set(attributes)


@needs_pye57
def test_e57_reads_every_scan_with_its_pose(tmp_path):
    import pye57

    first, second = _cloud(5, count=40), _cloud(6, count=30)
    path = tmp_path / "two_scans.e57"
    writer = pye57.E57(str(path), mode="w")
    writer.write_scan_raw({"cartesianX": first[:, 0], "cartesianY": first[:, 1], "cartesianZ": first[:, 2]})
    # The second scan sits 10 units along x and turned 90 degrees about z (quaternion w, x, y, z).
    turn = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    writer.write_scan_raw({"cartesianX": second[:, 0], "cartesianY": second[:, 1], "cartesianZ": second[:, 2]},
                          rotation=turn, translation=np.array([10.0, 0.0, 0.0]))
    writer.close()
    points = read_point_cloud(path)
    assert points.shape == (70, 3)
    np.testing.assert_allclose(points[:40], first, atol=1e-6)
    expected = np.column_stack([-second[:, 1] + 10.0, second[:, 0], second[:, 2]])
    np.testing.assert_allclose(points[40:], expected, atol=1e-5)


# ----------------------------------------------------------------------------- bad files
@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
def test_empty_file(tmp_path, suffix):
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    with pytest.raises(PointCloudFileError, match=_named(path, "empty")):
        read_point_cloud(path)


@pytest.mark.parametrize(("suffix", "magic"), [(".las", "not a LAS/LAZ file"), (".laz", "not a LAS/LAZ file"),
                                               (".e57", "not an E57 file")])
def test_wrong_magic(tmp_path, suffix, magic):
    if not (HAS_LASPY if suffix != ".e57" else HAS_PYE57):
        pytest.skip("library not installed")
    path = tmp_path / f"cloud{suffix}"
    write_point_cloud(tmp_path / "cloud.ply", _cloud(7))
    path.write_bytes((tmp_path / "cloud.ply").read_bytes())  # a PLY file under a scanner suffix
    with pytest.raises(PointCloudFileError, match=_named(path, magic)):
        read_point_cloud(path)
    with pytest.raises(PointCloudFileError, match=_named(path, magic)):
        read_point_attributes(path)


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
@pytest.mark.parametrize("keep", [0.5, 0.97])
def test_truncated_file(tmp_path, suffix, keep):
    full = tmp_path / f"full{suffix}"
    write_point_cloud(full, _cloud(8, count=3000))
    data = full.read_bytes()
    path = tmp_path / f"cut{suffix}"
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(PointCloudFileError, match=_named(path, "cannot parse as")):
        read_point_cloud(path)


@needs_pye57
def test_e57_corrupt_page_fails_its_checksum(tmp_path):
    path = tmp_path / "cloud.e57"
    write_point_cloud(path, _cloud(9, count=2000))
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte in a data page
    path.write_bytes(bytes(data))
    with pytest.raises(PointCloudFileError, match=_named(path, "corrupt E57")):
        read_point_cloud(path)


@needs_laspy
def test_las_without_points(tmp_path):
    import laspy

    path = tmp_path / "none.las"
    laspy.LasData(laspy.LasHeader(point_format=6, version="1.4")).write(path)
    with pytest.raises(PointCloudFileError, match=_named(path, "contains no points")):
        read_point_cloud(path)


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
def test_fuzz_corrupt_files_raise_only_logdesc_errors(tmp_path, suffix):
    seed_path = tmp_path / f"seed{suffix}"
    write_point_cloud(seed_path, _cloud(10, count=20))
    seed = seed_path.read_bytes()
    path = tmp_path / f"fuzz{suffix}"

    @settings(max_examples=25, deadline=None, database=None)
    @given(cut=st.integers(0, len(seed)), position=st.integers(0, len(seed) - 1), byte=st.integers(0, 255))
    def check(cut, position, byte):
        data = bytearray(seed)
        data[position] = byte
        path.write_bytes(bytes(data[: max(cut, 1)]))
        try:
            points = read_point_cloud(path)
        except LogdescError:
            return
        assert points.dtype == np.float64 and points.ndim == 2 and points.shape[1] == 3
        assert np.isfinite(points).all()

    check()


# ----------------------------------------------------------------------------- missing library
@pytest.mark.parametrize(("suffix", "module", "extra"),
                         [(".las", "laspy", "logdesc-rt[las]"), (".laz", "laspy", "logdesc-rt[las]"),
                          (".e57", "pye57", "logdesc-rt[e57]")])
def test_missing_library_names_the_extra(tmp_path, monkeypatch, suffix, module, extra):
    monkeypatch.setitem(sys.modules, module, None)  # import fails as if not installed
    path = tmp_path / f"cloud{suffix}"
    with pytest.raises(PointCloudFileError, match=_named(path, re.escape(extra))):
        check_format_available(path)
    with pytest.raises(PointCloudFileError, match=_named(path, re.escape(extra))):
        write_point_cloud(path, _cloud(11))
    assert not path.exists()
    path.write_bytes(b"LASF" + bytes(400) if suffix != ".e57" else b"ASTM-E57" + bytes(2040))
    with pytest.raises(PointCloudFileError, match=_named(path, re.escape(extra))):
        read_point_cloud(path)


@needs_laspy
def test_laz_without_a_laz_backend_names_the_extra(tmp_path, monkeypatch):
    import laspy

    write_point_cloud(tmp_path / "cloud.laz", _cloud(12))
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    with pytest.raises(PointCloudFileError, match="LAZ backend.*logdesc-rt\\[las\\]"):
        read_point_cloud(tmp_path / "cloud.laz")
    write_point_cloud(tmp_path / "cloud.las", _cloud(12))  # plain LAS needs no backend
    assert read_point_cloud(tmp_path / "cloud.las").shape == (300, 3)


# ----------------------------------------------------------------------------- corrupt counts
def _read_in_subprocess(path: Path) -> subprocess.CompletedProcess:
    """read_point_cloud in a fresh interpreter: a native abort (lazrs allocating terabytes)
    fails the test instead of killing the test run."""
    code = (
        "import sys\nfrom logdesc_rt.io import read_point_cloud\nfrom logdesc_rt.errors import PointCloudFileError\n"
        "try:\n    read_point_cloud(sys.argv[1])\nexcept PointCloudFileError as error:\n    print(error)\n"
    )
    return subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=60)


def _corrupt(path: Path, out: Path, position: int, value: bytes) -> Path:
    data = bytearray(path.read_bytes())
    data[position : position + len(value)] = value
    out.write_bytes(bytes(data))
    return out


@needs_laspy
def test_las_corrupt_counts_fail_fast(tmp_path):
    import struct

    write_point_cloud(tmp_path / "good.las", _cloud(13, count=20))
    good = tmp_path / "good.las"
    # Number of VLRs (uint32 at byte 100) made huge: laspy alone would loop over absent records.
    completed = _read_in_subprocess(_corrupt(good, tmp_path / "vlrs.las", 100, struct.pack("<I", 0xFF000000)))
    assert completed.returncode == 0 and "VLRs" in completed.stdout, completed.stderr
    # Point count (LAS 1.4, uint64 at byte 247) beyond the file: truncated, said so.
    completed = _read_in_subprocess(_corrupt(good, tmp_path / "count.las", 247, struct.pack("<Q", 10**9)))
    assert completed.returncode == 0 and "truncated" in completed.stdout, completed.stderr


@needs_laspy
def test_laz_corrupt_chunk_tables_fail_without_crashing(tmp_path):
    import struct

    good = tmp_path / "good.laz"
    write_point_cloud(good, _cloud(14, count=20))
    data = good.read_bytes()
    header_size, offset = struct.unpack_from("<HI", data, 94)
    # The laszip VLR (the only VLR) holds the chunk size at byte 12 of its data.
    chunk_size_at = header_size + 54 + 12
    completed = _read_in_subprocess(
        _corrupt(good, tmp_path / "chunk.laz", chunk_size_at, struct.pack("<I", 0x7F000000))
    )
    assert completed.returncode == 0 and "chunk size" in completed.stdout, completed.stderr
    # The chunk table (at the offset stored in the first 8 bytes of the point data) starts
    # with a version and the number of chunks.
    table = struct.unpack_from("<q", data, offset)[0]
    completed = _read_in_subprocess(_corrupt(good, tmp_path / "table.laz", table + 4, struct.pack("<I", 0x7F000001)))
    assert completed.returncode == 0 and "chunk table" in completed.stdout, completed.stderr
    # And LAZ's point count, like LAS's, is held to the file's size.
    completed = _read_in_subprocess(_corrupt(good, tmp_path / "count.laz", 247, struct.pack("<Q", 10**12)))
    assert completed.returncode == 0 and "corrupt point count" in completed.stdout, completed.stderr

"""LAS / LAZ point clouds through laspy (optional: ``pip install "logdesc-rt[las]"``).

laspy (BSD-2-Clause, maintained by the ASPRS LAS community) with its ``lazrs`` backend
(MIT, Rust) reads and writes every LAS version (1.0-1.4) and point format, and
LAZ compression. A codec of our own would have to follow fourteen point formats, extra-bytes
descriptors and LAZ's arithmetic coder; laspy is the library the field uses, so it is an
optional extra rather than a run-time dependency (most users have PLY or text files).

Coordinates: a LAS file stores each coordinate as a signed 32-bit integer ``X`` with a
per-axis scale and offset, ``x = X * scale + offset``. Reading returns those float64 values
as they are. Writing picks, per file, offset = the cloud's minimum and the power-of-ten scale
that spreads the cloud's largest extent over at most 2e9 steps (1e-9 m for a metre-sized
cloud, 1e-6 m for a kilometre-sized one; never below 1e-12), so coordinates read back within
half a step, at most 2.5e-9 of the extent, not bit for bit as the other formats do.

Attributes: written as LAS 1.4 point format 6 (7 when red, green and blue are given).
Attributes named like a standard dimension of that format (``intensity``, ``classification``,
``user_data``, ``point_source_id``, ``gps_time``, ``red`` ...) go into it when their values fit
its type exactly; any other name becomes an "extra bytes" dimension in the array's own type
(e.g. the ``scan`` index of a merged cloud). Reading attributes gives the extra-bytes
dimensions, ``intensity``, and ``red``, ``green``, ``blue`` for formats that have colours.

Errors are raised as plain exceptions here; :mod:`logdesc_rt.io` turns them into
:class:`~logdesc_rt.errors.PointCloudFileError` naming the file.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ._common import MissingLibraryError

MAGIC = b"LASF"
EXTRA = "las"
INSTALL_HINT = 'pip install "logdesc-rt[las]" (laspy with its lazrs LAZ backend)'
_MAX_STEPS = 2.0e9  # int32 holds +-2.1e9
_MIN_SCALE = 1e-12
_STANDARD_READ = ("intensity", "red", "green", "blue")


def _laspy():
    try:
        import laspy
    except ImportError as error:
        raise MissingLibraryError(f"LAS / LAZ files need laspy, which is not installed: {INSTALL_HINT}") from error
    return laspy


def check_available(compressed: bool) -> None:
    """Raise :class:`MissingLibraryError` unless laspy (and, for LAZ, a LAZ backend) is installed."""
    laspy = _laspy()
    if compressed and not laspy.LazBackend.detect_available():
        raise MissingLibraryError(f"LAZ files need a LAZ backend for laspy (lazrs or laszip): {INSTALL_HINT}")


# Header layout (LAS 1.0-1.4 public header block, little-endian): the fields checked before
# laspy sees the file, so that a corrupt count fails fast instead of making laspy loop over
# millions of absent records or lazrs allocate terabytes.
_MIN_HEADER_SIZE = 227
_VLR_HEADER_SIZE = 54
_EVLR_HEADER_SIZE = 60
# A LAZ stream decompresses to at most this many times its size (LAZ reaches ~10-20x on real
# data; identical points compress further, but not by three orders of magnitude).
_MAX_LAZ_RATIO = 1000
_MIN_DECOMPRESSED_LIMIT = 1 << 26
_LAZ_DEFAULT_CHUNK = 50_000  # points per chunk laszip writes by default


def _check_header(path: Path) -> None:
    """Raise ValueError when the header's counts cannot fit the file (truncated or corrupt)."""
    size = path.stat().st_size
    with path.open("rb") as file:
        head = file.read(375)
    if len(head) < _MIN_HEADER_SIZE:
        raise ValueError(f"truncated: a LAS header needs {_MIN_HEADER_SIZE} bytes, the file has {len(head)}")
    minor = head[25]
    header_size, offset, vlr_count = struct.unpack_from("<HII", head, 94)
    point_format, record_length, count = struct.unpack_from("<BHI", head, 104)
    if minor >= 4 and len(head) >= 255:
        count = struct.unpack_from("<Q", head, 247)[0] or count
        evlr_start, evlr_count = struct.unpack_from("<QI", head, 235)
        if evlr_count and evlr_start + evlr_count * _EVLR_HEADER_SIZE > size:
            raise ValueError(f"header announces {evlr_count} extended VLRs at byte {evlr_start}: beyond the file's end")
    if not _MIN_HEADER_SIZE <= header_size <= size or not header_size <= offset <= size:
        raise ValueError(f"header size {header_size} / point data offset {offset} do not fit a {size}-byte file")
    if vlr_count * _VLR_HEADER_SIZE > offset - header_size:
        raise ValueError(f"header announces {vlr_count} VLRs, which cannot fit before the point data at byte {offset}")
    points_bytes = count * record_length
    if point_format & 0xC0:  # compressed (LAZ): bit 7 (or 6) of the format id
        if points_bytes > max(_MAX_LAZ_RATIO * size, _MIN_DECOMPRESSED_LIMIT):
            raise ValueError(f"header announces {count} points of {record_length} bytes in a {size}-byte LAZ file: "
                             "a corrupt point count")
        _check_laz_tables(path, size, header_size, offset, vlr_count, count)
    elif offset + points_bytes > size:
        raise ValueError(f"truncated: {count} points of {record_length} bytes need {offset + points_bytes} bytes, "
                         f"the file has {size}")


def _check_laz_tables(path: Path, size: int, header_size: int, offset: int, vlr_count: int, count: int) -> None:
    """The laszip VLR's chunk size and the chunk table's chunk count must fit ``count`` points:
    lazrs allocates by them before it reads anything, and aborts the process when it cannot."""
    with path.open("rb") as file:
        file.seek(header_size)
        vlrs = file.read(offset - header_size)
        file.seek(offset)
        table_field = file.read(8)
        table_offset = struct.unpack("<q", table_field)[0] if len(table_field) == 8 else -1
        table = b""
        if 0 < table_offset <= size - 8:
            file.seek(table_offset)
            table = file.read(8)
    position = 0
    for _ in range(vlr_count):
        if position + _VLR_HEADER_SIZE > len(vlrs):
            raise ValueError("truncated VLRs")
        user = vlrs[position + 2 : position + 18].rstrip(b"\0")
        record_id, length = struct.unpack_from("<HH", vlrs, position + 18)
        data = vlrs[position + _VLR_HEADER_SIZE : position + _VLR_HEADER_SIZE + length]
        if user == b"laszip encoded" and record_id == 22204 and len(data) >= 16:
            chunk_size = struct.unpack_from("<I", data, 12)[0]
            if chunk_size != 0xFFFFFFFF and chunk_size > max(count, _LAZ_DEFAULT_CHUNK):
                raise ValueError(f"laszip VLR: chunk size {chunk_size} for {count} points, a corrupt value")
        position += _VLR_HEADER_SIZE + length
    if len(table) == 8:
        chunks = struct.unpack_from("<I", table, 4)[0]
        if chunks > count + 1:
            raise ValueError(f"LAZ chunk table announces {chunks} chunks for {count} points, a corrupt value")


def _read(path: Path):
    """The file's LasData, after checking the signature and the header's counts."""
    with path.open("rb") as file:
        signature = file.read(4)
    if signature != MAGIC:
        raise ValueError(f"not a LAS/LAZ file (it starts with {signature!r}, not {MAGIC!r})")
    check_available(compressed=path.suffix.lower() == ".laz")
    _check_header(path)
    laspy = _laspy()
    try:
        return laspy.read(path)
    except (OSError, MemoryError, KeyboardInterrupt, SystemExit):
        raise
    except BaseException as error:
        # laspy raises LaspyException, its LAZ backends their own errors (lazrs.LazrsError on a
        # truncated LAZ stream; a Rust panic arrives as pyo3's PanicException, a BaseException)
        # and NumPy ValueErrors: all mean corrupt content here.
        raise ValueError(f"{type(error).__name__}: {error}") from error


def read_xyz(path: Path) -> np.ndarray:
    """x, y, z of a LAS / LAZ file (scale and offset applied): (N, 3) float64, N may be 0.

    Raises:
        MissingLibraryError: laspy (or the LAZ backend) is not installed.
        ValueError: not a LAS file, or corrupt / truncated content.
    """
    data = _read(path)
    points = np.column_stack([np.asarray(data.x), np.asarray(data.y), np.asarray(data.z)]).astype(np.float64)
    if len(points) != data.header.point_count:
        raise ValueError(f"truncated: the header announces {data.header.point_count} points, {len(points)} read")
    return points


def read_attributes(path: Path) -> dict[str, np.ndarray]:
    """Extra-bytes dimensions, ``intensity`` and (when the format has them) ``red``, ``green``,
    ``blue`` of a LAS / LAZ file: name -> (N,) array in the stored type."""
    data = _read(path)
    names = [name for name in data.point_format.dimension_names if name in _STANDARD_READ]
    names += list(data.point_format.extra_dimension_names)
    return {name: np.asarray(data[name]).copy() for name in names}


# The standard dimensions of point formats 6 and 7 (what write() produces) and their types.
_STANDARD_TYPES = {
    "intensity": np.uint16, "return_number": np.uint8, "number_of_returns": np.uint8,
    "synthetic": np.uint8, "key_point": np.uint8, "withheld": np.uint8, "overlap": np.uint8,
    "scanner_channel": np.uint8, "scan_direction_flag": np.uint8, "edge_of_flight_line": np.uint8,
    "classification": np.uint8, "user_data": np.uint8, "scan_angle": np.int16, "point_source_id": np.uint16,
    "gps_time": np.float64, "red": np.uint16, "green": np.uint16, "blue": np.uint16,
}


def fits_standard(name: str, values: np.ndarray) -> bool:
    """False when ``name`` is a standard LAS dimension whose type cannot hold ``values``
    exactly (e.g. float intensities); True otherwise (any other name is an extra dimension).
    Bit fields (return_number: 3 bits, classification: 5 bits ...) are checked by laspy."""
    kind = _STANDARD_TYPES.get(name)
    if kind is None:
        return True
    values = np.asarray(values)
    with np.errstate(invalid="ignore", over="ignore"):
        return bool(np.array_equal(values.astype(kind).astype(values.dtype), values))


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    """Write (N, 3) float64 ``points`` (and ``attributes``) as LAS, or LAZ for a ``.laz`` path.

    Raises:
        MissingLibraryError: laspy (or the LAZ backend for .laz) is not installed.
        ValueError: an attribute named like a standard dimension whose values do not fit it.
        OSError: the file cannot be written.
    """
    compressed = path.suffix.lower() == ".laz"
    check_available(compressed)
    laspy = _laspy()
    has_colour = all(name in attributes for name in ("red", "green", "blue"))
    header = laspy.LasHeader(point_format=7 if has_colour else 6, version="1.4")
    minimum = points.min(axis=0)
    extent = float(np.ptp(points, axis=0).max())
    scale = 10.0 ** np.ceil(np.log10(max(extent / _MAX_STEPS, _MIN_SCALE)))
    header.offsets = minimum
    header.scales = np.full(3, scale)
    standard = set(header.point_format.dimension_names)
    extra = [name for name in attributes if name not in standard]
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=attributes[name].dtype) for name in extra])
    data = laspy.LasData(header)
    data.x, data.y, data.z = points[:, 0], points[:, 1], points[:, 2]
    for name, values in attributes.items():
        if name in standard:
            if not fits_standard(name, values):
                raise ValueError(
                    f"attribute {name!r}: LAS stores {name} as {np.dtype(_STANDARD_TYPES[name])}; these "
                    f"{values.dtype} values do not fit (rename the attribute to keep it as an extra-bytes dimension)"
                )
            data[name] = values.astype(_STANDARD_TYPES[name])
        else:
            data[name] = values
    data.write(path, do_compress=compressed)

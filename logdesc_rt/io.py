"""Read and write point-cloud files: PLY, PCD, XYZ/TXT/CSV, NPY, OFF; LAS/LAZ and E57 (extras).

:func:`read_point_cloud` returns the x, y, z coordinates of a file as a float64 array of
shape (N, 3), in the file's own units (metres for most scanners); colours, normals, faces
and other attributes are ignored. :func:`write_point_cloud` writes such an array so that
reading it back gives the same float64 values bit for bit, in every format.

Per-point attributes (colours, normals, intensity, confidence, ...): :func:`read_point_attributes`
reads the other scalar vertex properties of a PLY file, and :func:`write_point_cloud` writes
``attributes`` into every format but OFF (PLY properties in their own types, PCD fields,
extra text / NPY columns). :func:`transform_attributes` turns normals with a pose. So
``logdesc-rt register --write-aligned`` keeps what a PLY input had.

Every problem with a file (missing, a directory, empty, unsupported suffix, corrupt or
truncated content, no points) raises :class:`~logdesc_rt.errors.PointCloudFileError`
whose message starts with the path. Coordinates that parse but are unusable (NaN, inf,
absurdly large) raise the same errors as arrays passed in directly (e.g.
``NonFinitePointsError``), again naming the file.

Formats (read times for 1M points on a slow 2-core machine in brackets):
    PLY: own small codec (:mod:`logdesc_rt.ply`), not ``plyfile``, which is GPL-3.0 and so
        cannot be a run-time dependency of this MIT package; PLY's vertex part is simple
        enough to read directly. ascii, binary_little_endian and binary_big_endian; only the
        rows up to the ``vertex`` element are read, so elements after it (the Stanford
        scans' ``range_grid``, faces) cost nothing. Binary vertex rows are read in one go
        [0.1 s]; ASCII rows by NumPy's C parser [0.7 s; a 40k-point Stanford scan takes
        0.03 s]. Written as binary little-endian float64 x, y, z.
    PCD: own small reader, not ``pypcd4``, which would add pydantic (+ compiled core) and a C
        LZF extension as run-time dependencies for a ten-keyword header and a 40-line decoder.
        Reads ascii [3 s], binary [0.2 s] and binary_compressed (pure-Python LZF) [3 s];
        writes ascii.
    XYZ/TXT/CSV: numeric text, whitespace or comma separated, x y z in the first three
        columns, extra columns ignored, an optional single header line, ``#`` comments [3 s].
    NPY: an (N, 3) or (N, >3) numeric array (first three columns), never unpickled.
    OFF: vertices of an (ST)(C)(N)OFF file; faces are ignored.
    LAS/LAZ: through laspy and its lazrs backend, an optional extra (``pip install
        "logdesc-rt[las]"``; :mod:`logdesc_rt.las`). Stored as scaled 32-bit integers, so
        written coordinates read back within 2.5e-9 of the cloud's extent, not bit for bit.
    E57: through pye57 (libE57Format), an optional extra (``pip install "logdesc-rt[e57]"``;
        :mod:`logdesc_rt.e57`). Every scan of the file, its pose applied; written as one scan
        (pye57 writes single precision: within about 6e-8 of the cloud's extent).

Without the extra, reading or writing such a file raises PointCloudFileError naming the
extra to install; :func:`check_format_available` says so before any work.
"""

from __future__ import annotations

import math
import os
import re
import stat
import struct
from pathlib import Path
from typing import Callable

import numpy as np

from . import e57, las, ply
from .errors import LogdescError, PointCloudFileError
from .validation import as_points

CORE_SUFFIXES: tuple[str, ...] = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".off")
"""Suffixes read and written with the run-time dependencies alone, float64 values exactly."""
OPTIONAL_SUFFIXES: dict[str, str] = {".las": "las", ".laz": "las", ".e57": "e57"}
"""Suffixes that need an optional extra (suffix -> extra name: ``pip install "logdesc-rt[las]"``)."""
SUPPORTED_SUFFIXES: tuple[str, ...] = CORE_SUFFIXES + tuple(OPTIONAL_SUFFIXES)
"""File suffixes (lower case) that :func:`read_point_cloud` and :func:`write_point_cloud` accept."""

# Errors that parsers (ours, including ply.PlyError, and numpy's) raise on malformed content;
# read_point_cloud turns them into PointCloudFileError. LogdescError subclasses ValueError, so
# it is let through first.
_PARSE_ERRORS = (
    ValueError,
    KeyError,
    IndexError,
    UnicodeError,
    struct.error,
    EOFError,
    OverflowError,
)
# A PCD header is a dozen short lines; a longer "line" before DATA means this is no PCD file.
_MAX_PCD_HEADER_LINE_BYTES = 1 << 16
# Counts in headers: ASCII digits only (str.isdigit would also accept e.g. "²").
_DECIMAL_INTEGER = re.compile(r"[0-9]+")


def _file_error(path: Path, problem: str) -> PointCloudFileError:
    return PointCloudFileError(f"{path}: {problem}")


# --------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------


def read_point_cloud(path: str | os.PathLike) -> np.ndarray:
    """Read the x, y, z coordinates of a point-cloud file.

    The format follows the suffix, case-insensitively: see :data:`SUPPORTED_SUFFIXES`.

    Args:
        path: the file to read.

    Returns:
        (N, 3) float64, C-contiguous, finite, N >= 1; in the file's units.

    Raises:
        PointCloudFileError: unsupported suffix; missing, unreadable, non-regular or empty
            file; content that does not parse as the format; no points.
        NonFinitePointsError: a coordinate is NaN, infinite or beyond
            ``validation.MAX_ABS_COORDINATE`` (from :func:`as_points`).
        PointCloudShapeError: coordinates of a non-numeric type (e.g. an NPY of strings).
    """
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise _file_error(
            path,
            f"unsupported file suffix {path.suffix!r}; supported: {', '.join(SUPPORTED_SUFFIXES)}",
        )
    _check_readable_file(path)
    try:
        coordinates = reader(path)
    except LogdescError:
        raise
    except (las.MissingLibraryError, e57.MissingLibraryError) as error:
        raise _file_error(path, str(error)) from error
    except MemoryError as error:
        # Only a corrupt header (a huge element count) gets here for files that fit on disk.
        raise _file_error(path, "not enough memory to read it; is a point count in its header corrupt?") from error
    except _PARSE_ERRORS as error:
        raise _file_error(path, f"cannot parse as {path.suffix.lower()[1:].upper()}: {error}") from error
    except OSError as error:  # read failures after the checks above (I/O error, permissions)
        raise _file_error(path, f"cannot read: {error.strerror or error}") from error
    if coordinates.shape[0] == 0:
        raise _file_error(path, "contains no points")
    return as_points(coordinates, name=str(path))


# Attribute names that hold a normal's components (PLY's and PCL's spellings).
NORMAL_NAMES: tuple[tuple[str, str, str], ...] = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))


def read_point_attributes(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Per-point attributes of a point-cloud file, besides x, y, z.

    PLY: every scalar property of the ``vertex`` element (e.g. nx ny nz, red green blue,
    alpha, intensity, confidence), each an (N,) array in its declared type, in header order.
    LAS/LAZ: the extra-bytes dimensions, intensity, and red green blue where the point format
    has colours. E57: intensity and red green blue where every scan has them.
    Other formats: an empty dict (their extra columns or fields are not read).

    Raises:
        PointCloudFileError: as :func:`read_point_cloud`.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in OPTIONAL_SUFFIXES:
        _check_readable_file(path)
        codec = las if OPTIONAL_SUFFIXES[suffix] == "las" else e57
        try:
            return codec.read_attributes(path)
        except (las.MissingLibraryError, e57.MissingLibraryError) as error:
            raise _file_error(path, str(error)) from error
        except _PARSE_ERRORS as error:
            raise _file_error(path, f"cannot parse as {suffix[1:].upper()}: {error}") from error
        except OSError as error:
            raise _file_error(path, f"cannot read: {error.strerror or error}") from error
    if suffix != ".ply":
        return {}
    _check_readable_file(path)
    try:
        with path.open("rb") as file:
            header = ply.read_header(file)
            vertex = header.element("vertex")
            if vertex is None:
                return {}
            names = [p.name for p in vertex.properties if not p.is_list and p.name not in ("x", "y", "z")]
            if not names:
                return {}
            values = ply.read_scalar_properties(file, header, "vertex", names)
    except _PARSE_ERRORS as error:
        raise _file_error(path, f"cannot parse as PLY: {error}") from error
    except OSError as error:
        raise _file_error(path, f"cannot read: {error.strerror or error}") from error
    return dict(zip(names, values, strict=True))


def transform_attributes(attributes: dict[str, np.ndarray], rotation: np.ndarray) -> dict[str, np.ndarray]:
    """``attributes`` with every normal triplet (nx ny nz, normal_x normal_y normal_z) turned
    by the (3, 3) ``rotation``; other attributes (colours, intensity) unchanged."""
    moved = dict(attributes)
    for triplet in NORMAL_NAMES:
        if all(name in attributes for name in triplet):
            normals = np.stack([np.asarray(attributes[name], dtype=np.float64) for name in triplet], axis=1)
            turned = normals @ np.asarray(rotation, dtype=np.float64).T
            for column, name in enumerate(triplet):
                moved[name] = turned[:, column].astype(np.asarray(attributes[name]).dtype)
    return moved


def write_point_cloud(path: str | os.PathLike, points, attributes: dict[str, np.ndarray] | None = None) -> None:
    """Write an (N, 3) point cloud; the format follows the suffix (:data:`SUPPORTED_SUFFIXES`).

    Every format but LAS/LAZ and E57 stores float64 values exactly (LAS: within 2.5e-9 of the
    cloud's extent, E57: 6e-8; :mod:`logdesc_rt.las`, :mod:`logdesc_rt.e57`): PLY as binary little-endian ``double``
    x, y, z (CloudCompare, MeshLab and Open3D read it), NPY as a float64 (N, 3) array, and
    the text formats (PCD ascii, XYZ/TXT/CSV, OFF) with the shortest decimal that reads
    back to the same float64. A CSV file gets an ``x,y,z`` header line. An existing file
    is overwritten.

    Args:
        path: the file to write; its folder must exist.
        points: array-like (N, 3) of real numbers, N >= 1.
        attributes: optional name -> (N,) real array (e.g. from :func:`read_point_attributes`),
            written after x, y, z: PLY properties in the array's own type, PCD ascii fields,
            extra columns of XYZ/TXT/CSV (named in the CSV header) and NPY (as float64), LAS
            standard dimensions or extra-bytes dimensions (:mod:`logdesc_rt.las`). E57 keeps
            intensity and red, green, blue only (others: ValueError); OFF has no place for
            them: PointCloudFileError. :func:`writable_attributes` says what a format keeps.

    Raises:
        PointCloudFileError: unsupported suffix, the file cannot be written, attributes for
            OFF, or the optional library of LAS/LAZ/E57 is not installed (the message names
            the extra).
        PointCloudShapeError, NonFinitePointsError, TooFewPointsError: bad ``points``.
        ValueError: an attribute that is not an (N,) real array, or has a bad name.
    """
    path = Path(path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise _file_error(
            path,
            f"unsupported file suffix {path.suffix!r}; supported: {', '.join(SUPPORTED_SUFFIXES)}",
        )
    points = as_points(points, name="points")
    extra = _check_attributes(attributes or {}, len(points))
    if extra and path.suffix.lower() == ".off":
        raise _file_error(path, "OFF has no per-point attributes; write PLY, PCD, XYZ/TXT/CSV, NPY or LAS instead")
    try:
        if extra:
            _ATTRIBUTE_WRITERS[path.suffix.lower()](path, points, extra)
        else:
            writer(path, points)
    except (las.MissingLibraryError, e57.MissingLibraryError) as error:
        raise _file_error(path, str(error)) from error
    except OSError as error:
        raise _file_error(path, f"cannot write: {error.strerror or error}") from error


def open3d_points(cloud) -> np.ndarray | None:
    """The points of an Open3D point cloud, or None when ``cloud`` is not one.

    Accepts ``open3d.geometry.PointCloud`` and the tensor ``open3d.t.geometry.PointCloud``
    (its ``positions``). Open3D is never imported here: it is looked up in ``sys.modules``,
    since a caller holding an Open3D object has imported it already, so logdesc-rt runs and
    imports as fast without Open3D installed.

    Returns:
        (N, 3) float64 copy of the points (user units), or None for anything else (arrays,
        paths), which the caller handles as before.

    Raises:
        PointCloudShapeError: a tensor point cloud without positions.
    """
    import sys

    open3d = sys.modules.get("open3d")
    if open3d is None:
        return None
    if isinstance(cloud, open3d.geometry.PointCloud):
        return np.array(cloud.points, dtype=np.float64).reshape(-1, 3)
    if isinstance(cloud, open3d.t.geometry.PointCloud):
        if "positions" not in cloud.point:
            from .errors import PointCloudShapeError

            raise PointCloudShapeError("Open3D tensor PointCloud has no 'positions' attribute")
        return np.array(cloud.point.positions.cpu().numpy(), dtype=np.float64).reshape(-1, 3)
    return None


def check_format_available(path: str | os.PathLike) -> None:
    """Raise :class:`PointCloudFileError` unless ``path``'s format can be read and written here.

    Checks the suffix, and for LAS/LAZ/E57 that their optional library is installed (the
    message names the extra to install). Reads nothing: for checks before long work.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise _file_error(path, f"unsupported file suffix {path.suffix!r}; supported: {', '.join(SUPPORTED_SUFFIXES)}")
    try:
        if suffix in (".las", ".laz"):
            las.check_available(compressed=suffix == ".laz")
        elif suffix == ".e57":
            e57.check_available()
    except (las.MissingLibraryError, e57.MissingLibraryError) as error:
        raise _file_error(path, str(error)) from error


def writable_attributes(path: str | os.PathLike, attributes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The part of ``attributes`` that :func:`write_point_cloud` keeps, exactly, in ``path``'s
    format: all of them for PLY, PCD, XYZ/TXT/CSV and NPY; none for OFF; intensity and
    red / green / blue (0-255 integers) for E57; for LAS/LAZ all but those named like a standard
    LAS dimension whose values do not fit its type (e.g. float ``intensity``)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".off":
        return {}
    if suffix == ".e57":
        kept = {name: values for name, values in attributes.items() if name == "intensity"}
        colours = {name: np.asarray(attributes[name]) for name in ("red", "green", "blue") if name in attributes}
        if len(colours) == 3 and all(
            values.min(initial=0) >= 0 and values.max(initial=0) <= 255 and np.array_equal(values, np.round(values))
            for values in colours.values()
        ):
            kept.update(colours)
        return kept
    if suffix in (".las", ".laz"):
        return {name: values for name, values in attributes.items() if las.fits_standard(name, np.asarray(values))}
    return dict(attributes)


def _check_attributes(attributes: dict, count: int) -> dict[str, np.ndarray]:
    checked = {}
    for name, values in attributes.items():
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name) or name in ("x", "y", "z"):
            raise ValueError(f"attribute name {name!r}: expected an identifier other than x, y, z")
        array = np.asarray(values)
        if array.shape != (count,) or not (np.issubdtype(array.dtype, np.number) and not np.issubdtype(array.dtype, np.complexfloating)):
            raise ValueError(f"attribute {name!r}: expected ({count},) real numbers, got {array.dtype} {array.shape}")
        checked[name] = array
    return checked


_PLY_TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                   "f4": "float", "f8": "double"}


def _write_ply_with_attributes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    """Binary little-endian PLY: double x, y, z, then each attribute in its own type."""
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    for name, values in attributes.items():
        code = values.dtype.str[1:]
        if code not in _PLY_TYPE_NAMES:  # int64, float16, ...: widest PLY type of the kind
            code = "f8" if values.dtype.kind == "f" else ("i4" if values.dtype.kind == "i" else "u4")
        fields.append((name, "<" + code))
    table = np.empty(len(points), dtype=fields)
    for column, axis in enumerate("xyz"):
        table[axis] = points[:, column]
    for name, values in attributes.items():
        table[name] = values
    lines = ["ply", "format binary_little_endian 1.0", "comment written by logdesc-rt",
             f"element vertex {len(points)}"]
    lines += [f"property {_PLY_TYPE_NAMES[code[1:]]} {name}" for name, code in fields]
    lines.append("end_header")
    with path.open("wb") as file:
        file.write(("\n".join(lines) + "\n").encode("ascii"))
        file.write(table.tobytes())


def _write_pcd_with_attributes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    """ascii PCD: x y z as F 8, float attributes as F 8, integer ones as I/U 8."""
    names = ["x", "y", "z", *attributes]
    types = ["F", "F", "F"] + ["F" if v.dtype.kind == "f" else ("U" if v.dtype.kind == "u" else "I") for v in attributes.values()]
    count = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (written by logdesc-rt)\n"
        f"VERSION 0.7\nFIELDS {' '.join(names)}\nSIZE {' '.join(['8'] * len(names))}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join(['1'] * len(names))}\n"
        f"WIDTH {count}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\nDATA ascii\n"
    )
    path.write_text(header + _attribute_rows(points, attributes, " "), encoding="ascii")


def _attribute_rows(points: np.ndarray, attributes: dict[str, np.ndarray], separator: str) -> str:
    """Text rows: x y z then each attribute; floats as the shortest exact decimal, ints as ints."""

    def formatted(column: np.ndarray) -> list[str]:
        if column.dtype.kind == "f":
            return [repr(value) for value in column.astype(np.float64).tolist()]
        return [str(value) for value in column.tolist()]

    columns = [formatted(points[:, axis]) for axis in range(3)]
    columns += [formatted(np.asarray(values)) for values in attributes.values()]
    return "".join(separator.join(row) + "\n" for row in zip(*columns))


def _write_text_with_attributes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    separator = "," if path.suffix.lower() == ".csv" else " "
    header = ",".join(["x", "y", "z", *attributes]) + "\n" if separator == "," else ""
    path.write_text(header + _attribute_rows(points, attributes, separator), encoding="ascii")


def _write_npy_with_attributes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    table = np.column_stack([points, *[np.asarray(v, dtype=np.float64) for v in attributes.values()]])
    with path.open("wb") as file:
        np.save(file, table, allow_pickle=False)


def _check_readable_file(path: Path) -> None:
    """Raise PointCloudFileError unless ``path`` is an existing, non-empty regular file."""
    try:
        status = path.stat()
    except FileNotFoundError as error:
        raise _file_error(path, "no such file") from error
    except OSError as error:
        raise _file_error(path, f"cannot access: {error.strerror or error}") from error
    if stat.S_ISDIR(status.st_mode):
        raise _file_error(path, "is a directory, not a point-cloud file")
    if not stat.S_ISREG(status.st_mode):  # a FIFO or device would block or never end
        raise _file_error(path, "is not a regular file")
    if status.st_size == 0:
        raise _file_error(path, "file is empty (0 bytes)")


def _read_text(path: Path) -> str:
    """The file decoded as UTF-8 (a leading byte-order mark is dropped)."""
    data = path.read_bytes().removeprefix(b"\xef\xbb\xbf")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise _file_error(
            path, f"is not a text file (byte 0x{data[error.start]:02x} at offset {error.start} is not UTF-8)"
        ) from error


def _load_columns(lines: list[str], columns: tuple[int, ...], delimiter: str | None) -> np.ndarray:
    """Parse numeric text lines with numpy's C parser; return (rows, 3) float64.

    ``columns`` are the zero-based indices of x, y, z; other columns may hold anything
    numeric. Blank lines and ``#`` comments are skipped by the parser.
    """
    if not lines:
        return np.empty((0, 3))
    return np.loadtxt(lines, dtype=np.float64, delimiter=delimiter, usecols=columns, ndmin=2, comments="#")


# --------------------------------------------------------------------------------------
# PLY (own codec in .ply; see the module docstring)
# --------------------------------------------------------------------------------------


def _read_ply(path: Path) -> np.ndarray:
    """Vertex x, y, z of a PLY file: (N, 3) in the file's dtype (float32 usually)."""
    with path.open("rb") as file:
        if file.read(3) != b"ply":
            raise _file_error(path, "not a PLY file (it does not start with 'ply')")
        file.seek(0)
        header = ply.read_header(file)
        vertex = header.element("vertex")
        if vertex is None:
            raise _file_error(
                path, f"has no 'vertex' element (elements: {', '.join(header.element_names) or 'none'})"
            )
        missing = [axis for axis in ("x", "y", "z") if vertex.property(axis) is None]
        if missing:
            raise _file_error(
                path,
                f"vertex element lacks propert{'y' if len(missing) == 1 else 'ies'} "
                f"{', '.join(missing)} (has: {', '.join(vertex.property_names) or 'none'})",
            )
        return np.column_stack(ply.read_scalar_properties(file, header, "vertex", ("x", "y", "z")))


def _write_ply(path: Path, points: np.ndarray) -> None:
    with path.open("wb") as file:
        ply.write_binary_xyz(file, points, comments=["written by logdesc-rt"])


# --------------------------------------------------------------------------------------
# PCD (own reader; see the module docstring)
# --------------------------------------------------------------------------------------

# PCD TYPE letter and SIZE in bytes -> numpy kind; PCD binary data is little-endian in practice.
_PCD_KINDS = {"F": "f", "I": "i", "U": "u"}
_PCD_SIZES = {"F": (2, 4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
_PCD_ENCODINGS = ("ascii", "binary", "binary_compressed")
_PCD_KEYWORDS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def _read_pcd(path: Path) -> np.ndarray:
    """x, y, z of a PCD file (v0.5-0.7; ascii, binary or binary_compressed): (N, 3)."""
    with path.open("rb") as file:
        header = _read_pcd_header(path, file)
        data = file.read()

    fields: list[str] = header["FIELDS"]
    field_count = len(fields)
    for key in ("SIZE", "TYPE"):
        if key not in header:
            raise _file_error(path, f"PCD header has no {key} line")
    counts = header.get("COUNT", ["1"] * field_count)
    for key, values in (("SIZE", header["SIZE"]), ("TYPE", header["TYPE"]), ("COUNT", counts)):
        if len(values) != field_count:
            raise _file_error(path, f"PCD header lists {field_count} FIELDS but {len(values)} {key} values")
    sizes = [_pcd_int(path, "SIZE", value) for value in header["SIZE"]]
    counts = [_pcd_int(path, "COUNT", value) for value in counts]
    field_dtypes = []
    for name, type_letter, size, count in zip(fields, header["TYPE"], sizes, counts):
        type_letter = type_letter.upper()
        if type_letter not in _PCD_KINDS or size not in _PCD_SIZES[type_letter]:
            raise _file_error(path, f"PCD field {name!r} has unsupported TYPE {type_letter} with SIZE {size}")
        if count < 1:
            raise _file_error(path, f"PCD field {name!r} has COUNT {count}; it must be at least 1")
        field_dtypes.append(np.dtype(f"<{_PCD_KINDS[type_letter]}{size}"))

    axis_fields = []
    for axis in ("x", "y", "z"):
        if fields.count(axis) != 1:
            raise _file_error(path, f"PCD FIELDS must name {axis!r} once (FIELDS: {' '.join(fields)})")
        index = fields.index(axis)
        if counts[index] != 1:
            raise _file_error(path, f"PCD field {axis!r} has COUNT {counts[index]}; expected 1")
        axis_fields.append(index)

    point_count = _pcd_point_count(path, header)
    encoding = header["DATA"]
    if encoding == "ascii":
        # Columns: each field contributes COUNT values per line.
        first_column = np.concatenate([[0], np.cumsum(counts)])
        columns = tuple(int(first_column[index]) for index in axis_fields)
        text = data.decode("utf-8")
        lines = [line for line in text.splitlines() if line.strip()]
        if len(lines) != point_count:
            raise _file_error(path, f"PCD header says POINTS {point_count} but the ascii data has {len(lines)} lines")
        values = _load_columns(lines, columns, delimiter=None)
        # Round floats to the declared type, as a binary file of the same cloud would hold them.
        for column, index in enumerate(axis_fields):
            if field_dtypes[index].kind == "f":
                values[:, column] = values[:, column].astype(field_dtypes[index])
        return values

    record = np.dtype(
        [(f"f{index}", dtype, (count,)) for index, (dtype, count) in enumerate(zip(field_dtypes, counts))]
    )
    expected_bytes = point_count * record.itemsize
    if encoding == "binary":
        # Row-major: one packed record of all fields per point.
        if len(data) < expected_bytes:
            raise _file_error(
                path,
                f"truncated: {point_count} points of {record.itemsize} bytes need {expected_bytes} bytes "
                f"of binary data, found {len(data)}",
            )
        rows = np.frombuffer(data, dtype=record, count=point_count)
        return np.column_stack([rows[f"f{index}"][:, 0] for index in axis_fields])

    # binary_compressed: two uint32 sizes, then LZF data that decompresses to the fields
    # one after another (column-major): all x values, then all y values, ...
    if len(data) < 8:
        raise _file_error(path, "truncated: binary_compressed data lacks its 8-byte size prefix")
    compressed_size, uncompressed_size = struct.unpack("<II", data[:8])
    if uncompressed_size != expected_bytes:
        raise _file_error(
            path,
            f"binary_compressed data decompresses to {uncompressed_size} bytes, but {point_count} points "
            f"of {record.itemsize} bytes need {expected_bytes}",
        )
    if len(data) - 8 < compressed_size:
        raise _file_error(
            path, f"truncated: {compressed_size} bytes of compressed data announced, {len(data) - 8} present"
        )
    try:
        raw = _lzf_decompress(data[8 : 8 + compressed_size], uncompressed_size)
    except ValueError as error:
        raise _file_error(path, f"corrupt binary_compressed data: {error}") from error
    field_bytes = [point_count * dtype.itemsize * count for dtype, count in zip(field_dtypes, counts)]
    field_offsets = np.concatenate([[0], np.cumsum(field_bytes)])
    return np.column_stack(
        [
            np.frombuffer(raw, dtype=field_dtypes[index], count=point_count, offset=int(field_offsets[index]))
            for index in axis_fields
        ]
    )


def _read_pcd_header(path: Path, file) -> dict:
    """Parse header lines up to and including DATA; leave ``file`` at the first data byte.

    Returns {keyword: list of str values}, except DATA -> the encoding (lower case).
    """
    header: dict = {}
    line_number = 0
    while True:
        raw_line = file.readline(_MAX_PCD_HEADER_LINE_BYTES)
        line_number += 1
        if not raw_line:
            raise _file_error(path, "not a PCD file: the header ends without a DATA line")
        if len(raw_line) == _MAX_PCD_HEADER_LINE_BYTES and not raw_line.endswith(b"\n"):
            raise _file_error(path, f"not a PCD file: header line {line_number} is longer than 64 KiB")
        try:
            line = raw_line.decode("ascii").strip()
        except UnicodeDecodeError as error:
            raise _file_error(path, f"not a PCD file: header line {line_number} is not ASCII text") from error
        if not line or line.startswith("#"):
            continue
        keyword, *values = line.split()
        keyword = keyword.upper()
        if keyword == "COLUMNS":  # the PCD v0.5 name of FIELDS
            keyword = "FIELDS"
        if keyword not in _PCD_KEYWORDS:
            raise _file_error(path, f"not a PCD file: unknown header keyword {keyword!r} on line {line_number}")
        if keyword in header:
            raise _file_error(path, f"PCD header repeats {keyword} on line {line_number}")
        if keyword == "DATA":
            encoding = values[0].lower() if len(values) == 1 else " ".join(values)
            if encoding not in _PCD_ENCODINGS:
                raise _file_error(
                    path, f"PCD DATA {encoding!r} is not one of {', '.join(_PCD_ENCODINGS)}"
                )
            header["DATA"] = encoding
            break
        header[keyword] = values
    if not header.get("FIELDS"):
        raise _file_error(path, "PCD header has no FIELDS line")
    return header


def _pcd_int(path: Path, keyword: str, text: str) -> int:
    if not _DECIMAL_INTEGER.fullmatch(text):
        raise _file_error(path, f"PCD {keyword} value {text!r} is not a non-negative integer")
    return int(text)


def _pcd_point_count(path: Path, header: dict) -> int:
    """POINTS, or WIDTH * HEIGHT where POINTS is absent; they must agree when both given."""

    def single(keyword: str) -> int | None:
        if keyword not in header:
            return None
        if len(header[keyword]) != 1:
            raise _file_error(path, f"PCD {keyword} needs one value, got {' '.join(header[keyword]) or 'none'}")
        return _pcd_int(path, keyword, header[keyword][0])

    points, width, height = single("POINTS"), single("WIDTH"), single("HEIGHT")
    if width is not None:
        organised = width * (1 if height is None else height)
        if points is None:
            points = organised
        elif points != organised:
            raise _file_error(path, f"PCD header says POINTS {points} but WIDTH x HEIGHT = {organised}")
    if points is None:
        raise _file_error(path, "PCD header has neither POINTS nor WIDTH")
    return points


def _lzf_decompress(data: bytes, expected_size: int) -> bytes:
    """Decode an LZF stream (the liblzf format PCL uses) of known decompressed size.

    Each token starts with a control byte c. c < 32: copy the next c + 1 bytes literally.
    Otherwise a back-reference: length L = c >> 5 (7 means "7 + next byte"), then offset
    D = ((c & 31) << 8 | next byte) + 1; copy L + 2 bytes starting D bytes back in the
    output, which may overlap what is being written (a repeating pattern).

    Raises:
        ValueError: the stream is truncated, refers before its start, or decodes to a
            length other than ``expected_size``.
    """
    output = bytearray()
    position, end = 0, len(data)
    while position < end:
        control = data[position]
        position += 1
        if control < 32:
            literal_end = position + control + 1
            if literal_end > end:
                raise ValueError("a literal run goes past the end of the compressed data")
            output += data[position:literal_end]
            position = literal_end
        else:
            length = control >> 5
            if length == 7:
                if position >= end:
                    raise ValueError("a back-reference is cut off")
                length += data[position]
                position += 1
            if position >= end:
                raise ValueError("a back-reference is cut off")
            distance = ((control & 0x1F) << 8 | data[position]) + 1
            position += 1
            length += 2
            start = len(output) - distance
            if start < 0:
                raise ValueError("a back-reference points before the start of the data")
            if distance >= length:
                output += output[start : start + length]
            else:  # the copy overlaps its own output: the last `distance` bytes repeat
                pattern = output[start:]
                output += (pattern * math.ceil(length / distance))[:length]
        if len(output) > expected_size:
            raise ValueError(f"the data decompresses to more than the announced {expected_size} bytes")
    if len(output) != expected_size:
        raise ValueError(f"the data decompresses to {len(output)} bytes, not the announced {expected_size}")
    return bytes(output)


def _write_pcd(path: Path, points: np.ndarray) -> None:
    count = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (written by logdesc-rt)\n"
        "VERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {count}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\nDATA ascii\n"
    )
    path.write_text(header + _format_rows(points, " "), encoding="ascii")


# --------------------------------------------------------------------------------------
# XYZ / TXT / CSV
# --------------------------------------------------------------------------------------

_FIELD_SPLIT = re.compile(r"[,\s]+")


def _is_numeric_row(line: str) -> bool:
    """Whether the first three comma/whitespace separated fields of ``line`` are numbers."""
    fields = _FIELD_SPLIT.split(line.strip())
    if len(fields) < 3:
        return False
    try:
        for field in fields[:3]:
            float(field)
    except ValueError:
        return False
    return True


def _read_delimited_text(path: Path) -> np.ndarray:
    """x, y, z from the first three columns of numeric text: (N, 3) float64."""
    lines = _read_text(path).splitlines()
    meaningful = (index for index, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#"))
    first = next(meaningful, None)
    if first is None:
        return np.empty((0, 3))  # only blank lines and comments: "contains no points"
    start = first
    if not _is_numeric_row(lines[first]):
        start = first + 1  # a header line such as "x,y,z,nx,ny,nz"
    first_data = next(meaningful, None) if start != first else first
    if first_data is None:
        return np.empty((0, 3))
    # The first data row decides the separator for the whole file.
    delimiter = "," if "," in lines[first_data] else None
    return _load_columns(lines[start:], (0, 1, 2), delimiter)


def _write_delimited_text(path: Path, points: np.ndarray) -> None:
    if path.suffix.lower() == ".csv":
        path.write_text("x,y,z\n" + _format_rows(points, ","), encoding="ascii")
    else:
        path.write_text(_format_rows(points, " "), encoding="ascii")


def _format_rows(points: np.ndarray, separator: str) -> str:
    """One line per point; repr() gives the shortest text that reads back to the same float64."""
    return "".join(f"{x!r}{separator}{y!r}{separator}{z!r}\n" for x, y, z in points.tolist())


# --------------------------------------------------------------------------------------
# NPY
# --------------------------------------------------------------------------------------


def _read_npy(path: Path) -> np.ndarray:
    """First three columns of an (N, >=3) array: (N, 3) in the file's dtype."""
    # Memory-mapping checks the header's shape against the file size before anything is
    # allocated, so a corrupt header cannot ask for terabytes; allow_pickle=False keeps
    # object arrays (arbitrary code on load) out.
    try:
        loaded = np.load(path, mmap_mode="r", allow_pickle=False)
    except OSError:
        raise
    except Exception as error:
        # The header is a Python literal parsed with tokenize and ast: on corrupt bytes they
        # raise SyntaxError, tokenize.TokenError, RecursionError... beyond _PARSE_ERRORS.
        raise _file_error(path, f"cannot parse as NPY: {error}") from error
    if not isinstance(loaded, np.ndarray):  # an .npz archive under an .npy name
        loaded.close()
        raise _file_error(path, "is an .npz archive, not a single .npy array")
    if loaded.ndim != 2 or loaded.shape[1] < 3:
        raise _file_error(path, f"array has shape {loaded.shape}; expected (N, 3) or (N, >3) with x, y, z first")
    if loaded.dtype.fields is not None:
        raise _file_error(path, f"array has structured dtype {loaded.dtype}; expected plain numbers")
    return np.array(loaded[:, :3])  # copy out of the memory map


def _write_npy(path: Path, points: np.ndarray) -> None:
    # An open file, because np.save(name) appends ".npy" to a name ending in ".NPY".
    with path.open("wb") as file:
        np.save(file, points, allow_pickle=False)


# --------------------------------------------------------------------------------------
# OFF
# --------------------------------------------------------------------------------------

_OFF_KEYWORD = re.compile(r"(ST)?C?N?(4)?(n)?OFF")


def _read_off(path: Path) -> np.ndarray:
    """Vertices of an OFF file: (N, 3) float64; faces and per-vertex colours ignored.

    Accepts the keyword line (OFF, COFF, NOFF, STOFF, ...) with the counts on the next
    line, on the same line, or fused to the keyword ("OFF490 518 0", as in ModelNet);
    a missing keyword; ``#`` comments and blank lines anywhere.
    """
    text = _read_text(path)
    # (line number, text without comment) of every line that holds something.
    lines = ((number, line.split("#", 1)[0].strip()) for number, line in enumerate(text.splitlines(), start=1))
    content = ((number, line) for number, line in lines if line)
    first = next(content, None)
    if first is None:
        raise _file_error(path, "OFF file holds only comments and blank lines")
    keyword_match = _OFF_KEYWORD.match(first[1])
    if keyword_match:
        if keyword_match.group(2) or keyword_match.group(3):
            raise _file_error(path, f"OFF variant {keyword_match.group(0)!r} (4-D or n-D vertices) is not supported")
        rest = first[1][keyword_match.end() :].split()
        if rest[:1] == ["BINARY"]:
            raise _file_error(path, "binary OFF is not supported")
        if not rest:
            counts_line = next(content, None)
            if counts_line is None:
                raise _file_error(path, "OFF file ends before its vertex count line")
            rest = counts_line[1].split()
    elif first[1][:1] in "0123456789":
        rest = first[1].split()  # no keyword: the file starts with the counts
    else:
        raise _file_error(path, f"not an OFF file: line {first[0]} starts with {first[1][:20]!r}, not 'OFF'")
    if not _DECIMAL_INTEGER.fullmatch(rest[0]):
        raise _file_error(path, f"OFF vertex count {rest[0]!r} is not a non-negative integer")
    vertex_count = int(rest[0])

    vertex_lines = []
    for _ in range(vertex_count):  # stops at the file's end even if the count is huge
        line = next(content, None)
        if line is None:
            raise _file_error(path, f"OFF header announces {vertex_count} vertices, the file has {len(vertex_lines)}")
        vertex_lines.append(line[1])
    return _load_columns(vertex_lines, (0, 1, 2), delimiter=None)


def _write_off(path: Path, points: np.ndarray) -> None:
    path.write_text(f"OFF\n{len(points)} 0 0\n" + _format_rows(points, " "), encoding="ascii")


# --------------------------------------------------------------------------------------

_READERS: dict[str, Callable[[Path], np.ndarray]] = {
    ".ply": _read_ply,
    ".pcd": _read_pcd,
    ".xyz": _read_delimited_text,
    ".txt": _read_delimited_text,
    ".csv": _read_delimited_text,
    ".npy": _read_npy,
    ".off": _read_off,
}
_READERS.update({".las": las.read_xyz, ".laz": las.read_xyz, ".e57": e57.read_xyz})
_ATTRIBUTE_WRITERS: dict[str, Callable[[Path, np.ndarray, dict[str, np.ndarray]], None]] = {
    ".ply": _write_ply_with_attributes,
    ".pcd": _write_pcd_with_attributes,
    ".xyz": _write_text_with_attributes,
    ".txt": _write_text_with_attributes,
    ".csv": _write_text_with_attributes,
    ".npy": _write_npy_with_attributes,
    ".las": las.write,
    ".laz": las.write,
}
ATTRIBUTE_SUFFIXES: tuple[str, ...] = tuple(_ATTRIBUTE_WRITERS)
"""Suffixes :func:`write_point_cloud` writes any per-point attribute into (all but OFF, E57)."""
_ATTRIBUTE_WRITERS[".e57"] = e57.write
_WRITERS: dict[str, Callable[[Path, np.ndarray], None]] = {
    ".ply": _write_ply,
    ".pcd": _write_pcd,
    ".xyz": _write_delimited_text,
    ".txt": _write_delimited_text,
    ".csv": _write_delimited_text,
    ".npy": _write_npy,
    ".off": _write_off,
    ".las": lambda path, points: las.write(path, points, {}),
    ".laz": lambda path, points: las.write(path, points, {}),
    ".e57": lambda path, points: e57.write(path, points, {}),
}

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

from pathlib import Path

import numpy as np

MAGIC = b"LASF"
EXTRA = "las"
INSTALL_HINT = 'pip install "logdesc-rt[las]" (laspy with its lazrs LAZ backend)'
_MAX_STEPS = 2.0e9  # int32 holds +-2.1e9
_MIN_SCALE = 1e-12
_STANDARD_READ = ("intensity", "red", "green", "blue")


class MissingLibraryError(ImportError):
    """laspy, or its LAZ backend for a .laz file, is not installed."""


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


def _read(path: Path):
    """The file's LasData, after checking the signature (so a wrong file says so)."""
    with path.open("rb") as file:
        signature = file.read(4)
    if signature != MAGIC:
        raise ValueError(f"not a LAS/LAZ file (it starts with {signature!r}, not {MAGIC!r})")
    check_available(compressed=path.suffix.lower() == ".laz")
    laspy = _laspy()
    try:
        return laspy.read(path)
    except (OSError, MemoryError):
        raise
    except Exception as error:
        # laspy raises LaspyException, its LAZ backends their own errors (lazrs.LazrsError on a
        # truncated LAZ stream) and NumPy ValueErrors: all mean corrupt content here.
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

"""Read and write point-cloud files: PLY, PCD, XYZ/TXT/CSV, NPY, OFF; LAS/LAZ and E57 (extras).

One module per format family (:mod:`.ply`, :mod:`.pcd`, :mod:`.text` for XYZ/TXT/CSV,
:mod:`.npy`, :mod:`.off`, :mod:`.las`, :mod:`.e57`); this package's functions pick one by the
file's suffix and turn every problem into the errors below.

:func:`read_point_cloud` returns the x, y, z coordinates of a file as a float64 array of
shape (N, 3), in the file's own units (metres for most scanners); colours, normals, faces
and other attributes are ignored. :func:`write_point_cloud` writes such an array so that
reading it back gives the same float64 values bit for bit, in every format but LAS/LAZ and
E57 (below).

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
    PLY: own small codec (:mod:`logdesc_rt.io.ply`), not ``plyfile``, which is GPL-3.0 and so
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
        "logdesc-rt[las]"``; :mod:`logdesc_rt.io.las`). Stored as scaled 32-bit integers, so
        written coordinates read back within 2.5e-9 of the cloud's extent, not bit for bit.
    E57: through pye57 (libE57Format), an optional extra (``pip install "logdesc-rt[e57]"``;
        :mod:`logdesc_rt.io.e57`). Every scan of the file, its pose applied; written as one scan
        (pye57 writes single precision: within about 6e-8 of the cloud's extent).

Without the extra, reading or writing such a file raises PointCloudFileError naming the
extra to install; :func:`check_format_available` says so before any work.

Meshes (OBJ, STL, PLY / OFF with faces, GLB / glTF; the ``mesh`` extra, trimesh): :mod:`.mesh`
reads them and samples their surface; :func:`read_registration_input` is what ``register``,
``align`` and the CLI read a file with (a point cloud's points, or a mesh's surface samples).

Scan sets: :func:`read_stanford_conf` reads the scans' poses from a Stanford 3D Scanning
Repository ``.conf`` file (:mod:`.scan_set_poses`), e.g. to check ``logdesc_rt.align`` against them.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import LogdescError, PointCloudFileError  # noqa: F401 (PointCloudFileError: re-exported)
from ..validation import as_points
from . import e57, las, npy, off, pcd, ply, text
from ._common import PARSE_ERRORS, MissingLibraryError, check_readable_file, file_error
from .mesh import (  # noqa: F401 (re-exported)
    DEFAULT_SURFACE_SAMPLES,
    DEFAULT_WORKING_SIZE,
    MESH_ONLY_SUFFIXES,
    MESH_WRITE_SUFFIXES,
    Mesh,
    read_mesh,
    read_registration_input,
    sample_surface,
)
from .scan_set_poses import read_stanford_conf  # noqa: F401 (re-exported)

CORE_SUFFIXES: tuple[str, ...] = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".off")
"""Suffixes read and written with the run-time dependencies alone, float64 values exactly."""
OPTIONAL_SUFFIXES: dict[str, str] = {".las": "las", ".laz": "las", ".e57": "e57"}
"""Suffixes that need an optional extra (suffix -> extra name: ``pip install "logdesc-rt[las]"``)."""
SUPPORTED_SUFFIXES: tuple[str, ...] = CORE_SUFFIXES + tuple(OPTIONAL_SUFFIXES)
"""File suffixes (lower case) that :func:`read_point_cloud` and :func:`write_point_cloud` accept."""
INPUT_SUFFIXES: tuple[str, ...] = SUPPORTED_SUFFIXES + MESH_ONLY_SUFFIXES
"""File suffixes :func:`read_registration_input` reads: point clouds and meshes."""

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
        raise _unsupported_suffix(path)
    check_readable_file(path)
    try:
        coordinates = reader(path)
    except LogdescError:
        raise
    except MissingLibraryError as error:
        raise file_error(path, str(error)) from error
    except MemoryError as error:
        # Only a corrupt header (a huge element count) gets here for files that fit on disk.
        raise file_error(path, "not enough memory to read it; is a point count in its header corrupt?") from error
    except PARSE_ERRORS as error:
        raise file_error(path, f"cannot parse as {path.suffix.lower()[1:].upper()}: {error}") from error
    except OSError as error:  # read failures after the checks above (I/O error, permissions)
        raise file_error(path, f"cannot read: {error.strerror or error}") from error
    if coordinates.shape[0] == 0:
        raise file_error(path, "contains no points")
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
        check_readable_file(path)
        codec = las if OPTIONAL_SUFFIXES[suffix] == "las" else e57
        try:
            return codec.read_attributes(path)
        except MissingLibraryError as error:
            raise file_error(path, str(error)) from error
        except PARSE_ERRORS as error:
            raise file_error(path, f"cannot parse as {suffix[1:].upper()}: {error}") from error
        except OSError as error:
            raise file_error(path, f"cannot read: {error.strerror or error}") from error
    if suffix != ".ply":
        return {}
    check_readable_file(path)
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
    except PARSE_ERRORS as error:
        raise file_error(path, f"cannot parse as PLY: {error}") from error
    except OSError as error:
        raise file_error(path, f"cannot read: {error.strerror or error}") from error
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
    cloud's extent, E57: 6e-8; :mod:`logdesc_rt.io.las`, :mod:`logdesc_rt.io.e57`): PLY as binary little-endian
    ``double`` x, y, z (CloudCompare, MeshLab and Open3D read it), NPY as a float64 (N, 3) array, and
    the text formats (PCD ascii, XYZ/TXT/CSV, OFF) with the shortest decimal that reads
    back to the same float64. A CSV file gets an ``x,y,z`` header line. An existing file
    is overwritten.

    Args:
        path: the file to write; its folder must exist.
        points: array-like (N, 3) of real numbers, N >= 1.
        attributes: optional name -> (N,) real array (e.g. from :func:`read_point_attributes`),
            written after x, y, z: PLY properties in the array's own type, PCD ascii fields,
            extra columns of XYZ/TXT/CSV (named in the CSV header) and NPY (as float64), LAS
            standard dimensions or extra-bytes dimensions (:mod:`logdesc_rt.io.las`). E57 keeps
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
        raise _unsupported_suffix(path)
    points = as_points(points, name="points")
    extra = _check_attributes(attributes or {}, len(points))
    if extra and path.suffix.lower() == ".off":
        raise file_error(path, "OFF has no per-point attributes; write PLY, PCD, XYZ/TXT/CSV, NPY or LAS instead")
    try:
        if extra:
            _ATTRIBUTE_WRITERS[path.suffix.lower()](path, points, extra)
        else:
            writer(path, points)
    except MissingLibraryError as error:
        raise file_error(path, str(error)) from error
    except OSError as error:
        raise file_error(path, f"cannot write: {error.strerror or error}") from error


def _unsupported_suffix(path: Path) -> PointCloudFileError:
    return file_error(path, f"unsupported file suffix {path.suffix!r}; supported: {', '.join(SUPPORTED_SUFFIXES)}")


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
            from ..errors import PointCloudShapeError

            raise PointCloudShapeError("Open3D tensor PointCloud has no 'positions' attribute")
        return np.array(cloud.point.positions.cpu().numpy(), dtype=np.float64).reshape(-1, 3)
    return None


def input_points(cloud, *, working_size: int = DEFAULT_WORKING_SIZE, notify: Callable[[str], None] | None = None):
    """What the registration reads from any input it takes: a file (a point cloud's points, a
    mesh's seeded surface samples, :func:`read_registration_input`), a :class:`Mesh` or
    ``trimesh.Trimesh`` (surface samples), an Open3D point cloud (its points); anything else
    (arrays) is returned as it is, for the caller's checks.

    Args:
        cloud: the input.
        working_size: the registration's working size (whether a PLY / OFF's vertices suffice).
        notify: see :func:`read_registration_input`.
    """
    from .mesh import trimesh_mesh

    if isinstance(cloud, (str, os.PathLike)):
        return read_registration_input(cloud, working_size=working_size, notify=notify)[0]
    if isinstance(cloud, Mesh):
        return cloud.sample()
    points = open3d_points(cloud)
    if points is None and (mesh := trimesh_mesh(cloud)) is not None:
        points = mesh.sample()
    return cloud if points is None else points


def check_format_available(path: str | os.PathLike) -> None:
    """Raise :class:`PointCloudFileError` unless ``path``'s format can be read and written here.

    Checks the suffix, for meshes that trimesh is installed, and for LAS/LAZ/E57 that their optional library is
    installed (the message names the extra to install). Reads nothing: for checks before long work.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in MESH_ONLY_SUFFIXES:
        from .mesh import _trimesh

        _trimesh(path)  # raises, naming the extra, without trimesh
        return
    if suffix not in SUPPORTED_SUFFIXES:
        raise _unsupported_suffix(path)
    try:
        if suffix in (".las", ".laz"):
            las.check_available(compressed=suffix == ".laz")
        elif suffix == ".e57":
            e57.check_available()
    except MissingLibraryError as error:
        raise file_error(path, str(error)) from error


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
        if array.shape != (count,) or not (
            np.issubdtype(array.dtype, np.number) and not np.issubdtype(array.dtype, np.complexfloating)
        ):
            raise ValueError(f"attribute {name!r}: expected ({count},) real numbers, got {array.dtype} {array.shape}")
        checked[name] = array
    return checked




# --------------------------------------------------------------------------------------
# Dispatch by suffix
# --------------------------------------------------------------------------------------

_READERS: dict[str, Callable[[Path], np.ndarray]] = {
    ".ply": ply.read,
    ".pcd": pcd.read,
    ".xyz": text.read,
    ".txt": text.read,
    ".csv": text.read,
    ".npy": npy.read,
    ".off": off.read,
    ".las": las.read_xyz,
    ".laz": las.read_xyz,
    ".e57": e57.read_xyz,
}
_ATTRIBUTE_WRITERS: dict[str, Callable[[Path, np.ndarray, dict[str, np.ndarray]], None]] = {
    ".ply": ply.write_with_attributes,
    ".pcd": pcd.write_with_attributes,
    ".xyz": text.write_with_attributes,
    ".txt": text.write_with_attributes,
    ".csv": text.write_with_attributes,
    ".npy": npy.write_with_attributes,
    ".las": las.write,
    ".laz": las.write,
}
ATTRIBUTE_SUFFIXES: tuple[str, ...] = tuple(_ATTRIBUTE_WRITERS)
"""Suffixes :func:`write_point_cloud` writes any per-point attribute into (all but OFF, E57)."""
_ATTRIBUTE_WRITERS[".e57"] = e57.write
_WRITERS: dict[str, Callable[[Path, np.ndarray], None]] = {
    ".ply": ply.write,
    ".pcd": pcd.write,
    ".xyz": text.write,
    ".txt": text.write,
    ".csv": text.write,
    ".npy": npy.write,
    ".off": off.write,
    ".las": lambda path, points: las.write(path, points, {}),
    ".laz": lambda path, points: las.write(path, points, {}),
    ".e57": lambda path, points: e57.write(path, points, {}),
}

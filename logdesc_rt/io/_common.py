"""What the format modules share: the file error, text decoding, numeric columns, exact rows."""

from __future__ import annotations

import re
import stat
import struct
from pathlib import Path

import numpy as np

from ..errors import PointCloudFileError

# Errors that parsers (ours, including ply.PlyError, and numpy's) raise on malformed content;
# read_point_cloud turns them into PointCloudFileError. LogdescError subclasses ValueError, so
# it is let through first.
PARSE_ERRORS = (
    ValueError,
    KeyError,
    IndexError,
    UnicodeError,
    struct.error,
    EOFError,
    OverflowError,
)
# Counts in headers: ASCII digits only (str.isdigit would also accept e.g. "²").
DECIMAL_INTEGER = re.compile(r"[0-9]+")


class MissingLibraryError(ImportError):
    """The optional library of a format (laspy and its LAZ backend, pye57) is not installed;
    the message names the extra to install."""


def file_error(path: Path, problem: str) -> PointCloudFileError:
    """The error of every problem with a file: its message starts with the path."""
    return PointCloudFileError(f"{path}: {problem}")


def check_readable_file(path: Path) -> None:
    """Raise PointCloudFileError unless ``path`` is an existing, non-empty regular file."""
    try:
        status = path.stat()
    except FileNotFoundError as error:
        raise file_error(path, "no such file") from error
    except OSError as error:
        raise file_error(path, f"cannot access: {error.strerror or error}") from error
    if stat.S_ISDIR(status.st_mode):
        raise file_error(path, "is a directory, not a point-cloud file")
    if not stat.S_ISREG(status.st_mode):  # a FIFO or device would block or never end
        raise file_error(path, "is not a regular file")
    if status.st_size == 0:
        raise file_error(path, "file is empty (0 bytes)")


def read_text(path: Path) -> str:
    """The file decoded as UTF-8 (a leading byte-order mark is dropped)."""
    data = path.read_bytes().removeprefix(b"\xef\xbb\xbf")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise file_error(
            path, f"is not a text file (byte 0x{data[error.start]:02x} at offset {error.start} is not UTF-8)"
        ) from error


def load_columns(lines: list[str], columns: tuple[int, ...], delimiter: str | None) -> np.ndarray:
    """Parse numeric text lines with numpy's C parser; return (rows, 3) float64.

    ``columns`` are the zero-based indices of x, y, z; other columns may hold anything
    numeric. Blank lines and ``#`` comments are skipped by the parser.
    """
    if not lines:
        return np.empty((0, 3))
    return np.loadtxt(lines, dtype=np.float64, delimiter=delimiter, usecols=columns, ndmin=2, comments="#")


def format_rows(points: np.ndarray, separator: str) -> str:
    """One line per point; repr() gives the shortest text that reads back to the same float64."""
    return "".join(f"{x!r}{separator}{y!r}{separator}{z!r}\n" for x, y, z in points.tolist())


def attribute_rows(points: np.ndarray, attributes: dict[str, np.ndarray], separator: str) -> str:
    """Text rows: x y z then each attribute; floats as the shortest exact decimal, ints as ints."""

    def formatted(column: np.ndarray) -> list[str]:
        if column.dtype.kind == "f":
            return [repr(value) for value in column.astype(np.float64).tolist()]
        return [str(value) for value in column.tolist()]

    columns = [formatted(points[:, axis]) for axis in range(3)]
    columns += [formatted(np.asarray(values)) for values in attributes.values()]
    return "".join(separator.join(row) + "\n" for row in zip(*columns))

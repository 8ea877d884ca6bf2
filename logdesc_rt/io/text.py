"""XYZ / TXT / CSV: numeric text, whitespace or comma separated, x y z in the first three columns,
extra columns ignored, an optional single header line, ``#`` comments. Written with the
shortest decimal that reads back to the same float64 (a CSV file gets an ``x,y,z`` header)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ._common import attribute_rows, format_rows, load_columns, read_text

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


def read(path: Path) -> np.ndarray:
    """x, y, z from the first three columns of numeric text: (N, 3) float64."""
    lines = read_text(path).splitlines()
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
    return load_columns(lines[start:], (0, 1, 2), delimiter)


def write(path: Path, points: np.ndarray) -> None:
    if path.suffix.lower() == ".csv":
        path.write_text("x,y,z\n" + format_rows(points, ","), encoding="ascii")
    else:
        path.write_text(format_rows(points, " "), encoding="ascii")


def write_with_attributes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    separator = "," if path.suffix.lower() == ".csv" else " "
    header = ",".join(["x", "y", "z", *attributes]) + "\n" if separator == "," else ""
    path.write_text(header + attribute_rows(points, attributes, separator), encoding="ascii")

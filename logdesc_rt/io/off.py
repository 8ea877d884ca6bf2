"""OFF: the vertices of an (ST)(C)(N)OFF file; per-vertex colours are ignored, faces counted
(:func:`face_count`; :mod:`.mesh` reads them)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Iterator

import numpy as np

from ._common import DECIMAL_INTEGER, file_error, format_rows, load_columns, read_text

_OFF_KEYWORD = re.compile(r"(ST)?C?N?(4)?(n)?OFF")


def read(path: Path) -> np.ndarray:
    """Vertices of an OFF file: (N, 3) float64; faces and per-vertex colours ignored.

    Accepts the keyword line (OFF, COFF, NOFF, STOFF, ...) with the counts on the next
    line, on the same line, or fused to the keyword ("OFF490 518 0", as in ModelNet);
    a missing keyword; ``#`` comments and blank lines anywhere.
    """
    counts, content = _header(path)
    vertex_count = counts[0]
    vertex_lines = []
    for _ in range(vertex_count):  # stops at the file's end even if the count is huge
        line = next(content, None)
        if line is None:
            raise file_error(path, f"OFF header announces {vertex_count} vertices, the file has {len(vertex_lines)}")
        vertex_lines.append(line[1])
    return load_columns(vertex_lines, (0, 1, 2), delimiter=None)


def face_count(path: Path) -> int:
    """The face count an OFF file's header announces (0 when it gives none)."""
    counts, _ = _header(path)
    return counts[1]


def _header(path: Path) -> tuple[tuple[int, int], Iterator[tuple[int, str]]]:
    """(vertex count, face count) and the content lines after the counts: (line number, text)."""
    text = read_text(path)
    # (line number, text without comment) of every line that holds something.
    lines = ((number, line.split("#", 1)[0].strip()) for number, line in enumerate(text.splitlines(), start=1))
    content = ((number, line) for number, line in lines if line)
    first = next(content, None)
    if first is None:
        raise file_error(path, "OFF file holds only comments and blank lines")
    keyword_match = _OFF_KEYWORD.match(first[1])
    if keyword_match:
        if keyword_match.group(2) or keyword_match.group(3):
            raise file_error(path, f"OFF variant {keyword_match.group(0)!r} (4-D or n-D vertices) is not supported")
        rest = first[1][keyword_match.end() :].split()
        if rest[:1] == ["BINARY"]:
            raise file_error(path, "binary OFF is not supported")
        if not rest:
            counts_line = next(content, None)
            if counts_line is None:
                raise file_error(path, "OFF file ends before its vertex count line")
            rest = counts_line[1].split()
    elif first[1][:1] in "0123456789":
        rest = first[1].split()  # no keyword: the file starts with the counts
    else:
        raise file_error(path, f"not an OFF file: line {first[0]} starts with {first[1][:20]!r}, not 'OFF'")
    if not DECIMAL_INTEGER.fullmatch(rest[0]):
        raise file_error(path, f"OFF vertex count {rest[0]!r} is not a non-negative integer")
    faces = int(rest[1]) if len(rest) > 1 and DECIMAL_INTEGER.fullmatch(rest[1]) else 0
    return (int(rest[0]), faces), content


def write(path: Path, points: np.ndarray) -> None:
    path.write_text(f"OFF\n{len(points)} 0 0\n" + format_rows(points, " "), encoding="ascii")

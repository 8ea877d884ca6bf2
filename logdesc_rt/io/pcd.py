"""PCD (Point Cloud Library): own small reader, not ``pypcd4``, which would add pydantic (+ compiled
core) and a C LZF extension as run-time dependencies for a ten-keyword header and a 40-line
decoder. Reads ascii, binary and binary_compressed (pure-Python LZF); writes ascii."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np

from ._common import DECIMAL_INTEGER, attribute_rows, file_error, format_rows, load_columns

# A PCD header is a dozen short lines; a longer "line" before DATA means this is no PCD file.
_MAX_PCD_HEADER_LINE_BYTES = 1 << 16
# PCD TYPE letter and SIZE in bytes -> numpy kind; PCD binary data is little-endian in practice.
_PCD_KINDS = {"F": "f", "I": "i", "U": "u"}
_PCD_SIZES = {"F": (2, 4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
_PCD_ENCODINGS = ("ascii", "binary", "binary_compressed")
_PCD_KEYWORDS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def read(path: Path) -> np.ndarray:
    """x, y, z of a PCD file (v0.5-0.7; ascii, binary or binary_compressed): (N, 3)."""
    with path.open("rb") as file:
        header = _read_header(path, file)
        data = file.read()

    fields: list[str] = header["FIELDS"]
    field_count = len(fields)
    for key in ("SIZE", "TYPE"):
        if key not in header:
            raise file_error(path, f"PCD header has no {key} line")
    counts = header.get("COUNT", ["1"] * field_count)
    for key, values in (("SIZE", header["SIZE"]), ("TYPE", header["TYPE"]), ("COUNT", counts)):
        if len(values) != field_count:
            raise file_error(path, f"PCD header lists {field_count} FIELDS but {len(values)} {key} values")
    sizes = [_header_int(path, "SIZE", value) for value in header["SIZE"]]
    counts = [_header_int(path, "COUNT", value) for value in counts]
    field_dtypes = []
    for name, type_letter, size, count in zip(fields, header["TYPE"], sizes, counts):
        type_letter = type_letter.upper()
        if type_letter not in _PCD_KINDS or size not in _PCD_SIZES[type_letter]:
            raise file_error(path, f"PCD field {name!r} has unsupported TYPE {type_letter} with SIZE {size}")
        if count < 1:
            raise file_error(path, f"PCD field {name!r} has COUNT {count}; it must be at least 1")
        field_dtypes.append(np.dtype(f"<{_PCD_KINDS[type_letter]}{size}"))

    axis_fields = []
    for axis in ("x", "y", "z"):
        if fields.count(axis) != 1:
            raise file_error(path, f"PCD FIELDS must name {axis!r} once (FIELDS: {' '.join(fields)})")
        index = fields.index(axis)
        if counts[index] != 1:
            raise file_error(path, f"PCD field {axis!r} has COUNT {counts[index]}; expected 1")
        axis_fields.append(index)

    point_count = _point_count(path, header)
    encoding = header["DATA"]
    if encoding == "ascii":
        # Columns: each field contributes COUNT values per line.
        first_column = np.concatenate([[0], np.cumsum(counts)])
        columns = tuple(int(first_column[index]) for index in axis_fields)
        text = data.decode("utf-8")
        lines = [line for line in text.splitlines() if line.strip()]
        if len(lines) != point_count:
            raise file_error(path, f"PCD header says POINTS {point_count} but the ascii data has {len(lines)} lines")
        values = load_columns(lines, columns, delimiter=None)
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
            raise file_error(
                path,
                f"truncated: {point_count} points of {record.itemsize} bytes need {expected_bytes} bytes "
                f"of binary data, found {len(data)}",
            )
        rows = np.frombuffer(data, dtype=record, count=point_count)
        return np.column_stack([rows[f"f{index}"][:, 0] for index in axis_fields])

    # binary_compressed: two uint32 sizes, then LZF data that decompresses to the fields
    # one after another (column-major): all x values, then all y values, ...
    if len(data) < 8:
        raise file_error(path, "truncated: binary_compressed data lacks its 8-byte size prefix")
    compressed_size, uncompressed_size = struct.unpack("<II", data[:8])
    if uncompressed_size != expected_bytes:
        raise file_error(
            path,
            f"binary_compressed data decompresses to {uncompressed_size} bytes, but {point_count} points "
            f"of {record.itemsize} bytes need {expected_bytes}",
        )
    if len(data) - 8 < compressed_size:
        raise file_error(
            path, f"truncated: {compressed_size} bytes of compressed data announced, {len(data) - 8} present"
        )
    try:
        raw = lzf_decompress(data[8 : 8 + compressed_size], uncompressed_size)
    except ValueError as error:
        raise file_error(path, f"corrupt binary_compressed data: {error}") from error
    field_bytes = [point_count * dtype.itemsize * count for dtype, count in zip(field_dtypes, counts)]
    field_offsets = np.concatenate([[0], np.cumsum(field_bytes)])
    return np.column_stack(
        [
            np.frombuffer(raw, dtype=field_dtypes[index], count=point_count, offset=int(field_offsets[index]))
            for index in axis_fields
        ]
    )


def _read_header(path: Path, file) -> dict:
    """Parse header lines up to and including DATA; leave ``file`` at the first data byte.

    Returns {keyword: list of str values}, except DATA -> the encoding (lower case).
    """
    header: dict = {}
    line_number = 0
    while True:
        raw_line = file.readline(_MAX_PCD_HEADER_LINE_BYTES)
        line_number += 1
        if not raw_line:
            raise file_error(path, "not a PCD file: the header ends without a DATA line")
        if len(raw_line) == _MAX_PCD_HEADER_LINE_BYTES and not raw_line.endswith(b"\n"):
            raise file_error(path, f"not a PCD file: header line {line_number} is longer than 64 KiB")
        try:
            line = raw_line.decode("ascii").strip()
        except UnicodeDecodeError as error:
            raise file_error(path, f"not a PCD file: header line {line_number} is not ASCII text") from error
        if not line or line.startswith("#"):
            continue
        keyword, *values = line.split()
        keyword = keyword.upper()
        if keyword == "COLUMNS":  # the PCD v0.5 name of FIELDS
            keyword = "FIELDS"
        if keyword not in _PCD_KEYWORDS:
            raise file_error(path, f"not a PCD file: unknown header keyword {keyword!r} on line {line_number}")
        if keyword in header:
            raise file_error(path, f"PCD header repeats {keyword} on line {line_number}")
        if keyword == "DATA":
            encoding = values[0].lower() if len(values) == 1 else " ".join(values)
            if encoding not in _PCD_ENCODINGS:
                raise file_error(
                    path, f"PCD DATA {encoding!r} is not one of {', '.join(_PCD_ENCODINGS)}"
                )
            header["DATA"] = encoding
            break
        header[keyword] = values
    if not header.get("FIELDS"):
        raise file_error(path, "PCD header has no FIELDS line")
    return header


def _header_int(path: Path, keyword: str, text: str) -> int:
    if not DECIMAL_INTEGER.fullmatch(text):
        raise file_error(path, f"PCD {keyword} value {text!r} is not a non-negative integer")
    return int(text)


def _point_count(path: Path, header: dict) -> int:
    """POINTS, or WIDTH * HEIGHT where POINTS is absent; they must agree when both given."""

    def single(keyword: str) -> int | None:
        if keyword not in header:
            return None
        if len(header[keyword]) != 1:
            raise file_error(path, f"PCD {keyword} needs one value, got {' '.join(header[keyword]) or 'none'}")
        return _header_int(path, keyword, header[keyword][0])

    points, width, height = single("POINTS"), single("WIDTH"), single("HEIGHT")
    if width is not None:
        organised = width * (1 if height is None else height)
        if points is None:
            points = organised
        elif points != organised:
            raise file_error(path, f"PCD header says POINTS {points} but WIDTH x HEIGHT = {organised}")
    if points is None:
        raise file_error(path, "PCD header has neither POINTS nor WIDTH")
    return points


def lzf_decompress(data: bytes, expected_size: int) -> bytes:
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


def write(path: Path, points: np.ndarray) -> None:
    count = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (written by logdesc-rt)\n"
        "VERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {count}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\nDATA ascii\n"
    )
    path.write_text(header + format_rows(points, " "), encoding="ascii")


def write_with_attributes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    """ascii PCD: x y z as F 8, float attributes as F 8, integer ones as I/U 8."""
    names = ["x", "y", "z", *attributes]
    types = ["F", "F", "F"] + [
        "F" if v.dtype.kind == "f" else ("U" if v.dtype.kind == "u" else "I") for v in attributes.values()
    ]
    count = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (written by logdesc-rt)\n"
        f"VERSION 0.7\nFIELDS {' '.join(names)}\nSIZE {' '.join(['8'] * len(names))}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join(['1'] * len(names))}\n"
        f"WIDTH {count}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\nDATA ascii\n"
    )
    path.write_text(header + attribute_rows(points, attributes, " "), encoding="ascii")

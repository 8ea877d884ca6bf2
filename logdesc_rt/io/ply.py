"""PLY: a small codec of our own (header, scalar properties of one element) and the file readers / writers.

Why our own: ``plyfile`` is GPL-3.0-or-later, which an MIT package cannot ship as a
run-time dependency, and the part of PLY we need (the vertex coordinates) is simple enough
to read directly with NumPy.

The format, as written by scanners and meshing tools:

* The header is ASCII text, one statement per line: ``ply``; ``format ascii 1.0`` (or
  ``binary_little_endian`` / ``binary_big_endian``); ``comment ...`` and ``obj_info ...``
  lines anywhere; ``element <name> <count>`` followed by its ``property <type> <name>`` and
  ``property list <count type> <item type> <name>`` lines; ``end_header``. Lines end in
  ``\\n``, ``\\r\\n`` or ``\\r``; the ``ply`` line decides which.
* The data holds every element's rows, element after element in header order. ASCII: one
  row per line, values separated by whitespace. Binary: rows packed without padding, in
  the declared byte order. A list value is its length followed by that many items.

Reading walks only as far as the requested element: rows of the elements before it are
skipped (their structure checked), rows after it are never looked at. Fixed-size rows are
read with one ``np.frombuffer`` (binary) or ``np.loadtxt`` (ASCII) call; rows with list
properties are walked in Python, after a vectorised try that assumes every row's lists
have the lengths of the first row's (true for triangle meshes).

Every problem with the content raises :class:`PlyError` (a ``ValueError``) saying what is
wrong and where.
"""

from __future__ import annotations

import os
import re
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Iterable, Sequence

import numpy as np

from ._common import file_error

# PLY scalar type names (the 1994 spec's names and the sized aliases) -> NumPy kind.
SCALAR_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
FORMATS: dict[str, str | None] = {
    "ascii": None,
    "binary_little_endian": "<",
    "binary_big_endian": ">",
}
_HEADER_CHUNK_BYTES = 1 << 16
# A header is a few dozen lines; megabytes without end_header mean this is no PLY header.
_MAX_HEADER_BYTES = 1 << 24
_ASCII_INTEGER = re.compile(r"[+-]?[0-9]+")
# struct codes of the integer kinds, for list lengths.
_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}
_DECIMAL_COUNT = re.compile(r"[0-9]+")


class PlyError(ValueError):
    """The PLY content is malformed, truncated or not what the reader needs."""


@dataclass(frozen=True)
class PlyProperty:
    """One ``property`` line: a scalar, or a list when ``count_kind`` is set."""

    name: str
    kind: str  # NumPy kind of the value (of each item, for a list), e.g. "f4"
    count_kind: str | None = None  # NumPy kind of a list's length; None for a scalar

    @property
    def is_list(self) -> bool:
        return self.count_kind is not None


@dataclass(frozen=True)
class PlyElement:
    """One ``element`` line and its properties."""

    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    @property
    def has_lists(self) -> bool:
        return any(prop.is_list for prop in self.properties)

    @property
    def property_names(self) -> tuple[str, ...]:
        return tuple(prop.name for prop in self.properties)

    def property(self, name: str) -> PlyProperty | None:
        return next((prop for prop in self.properties if prop.name == name), None)


@dataclass(frozen=True)
class PlyHeader:
    """A parsed header; ``data_offset`` is the byte where the data starts."""

    format: str
    elements: tuple[PlyElement, ...]
    comments: tuple[str, ...]
    obj_info: tuple[str, ...]
    data_offset: int
    line_count: int  # header lines, end_header included
    newline: bytes

    @property
    def byte_order(self) -> str | None:
        """``"<"`` or ``">"`` for binary formats, None for ASCII."""
        return FORMATS[self.format]

    @property
    def element_names(self) -> tuple[str, ...]:
        return tuple(element.name for element in self.elements)

    def element(self, name: str) -> PlyElement | None:
        """The first element called ``name``, or None."""
        return next((element for element in self.elements if element.name == name), None)


# --------------------------------------------------------------------------------------
# Header
# --------------------------------------------------------------------------------------


def read_header(file: BinaryIO) -> PlyHeader:
    """Parse the header of the PLY file open in binary mode at its start.

    Raises:
        PlyError: the file does not start with a ``ply`` line, the header has no
            ``end_header`` line, or a header line is malformed.
    """
    buffer = file.read(_HEADER_CHUNK_BYTES)
    first_line = re.match(rb"ply[ \t]*(\r\n|\n|\r|\Z)", buffer)
    if not buffer.startswith(b"ply"):
        raise PlyError("not a PLY file (it does not start with 'ply')")
    if first_line is None:
        shown = buffer.split(b"\n", 1)[0].split(b"\r", 1)[0][:40].decode("latin-1")
        raise PlyError(f"line 1 is {shown!r}; a PLY file starts with a line 'ply'")
    newline = first_line.group(1) or b"\n"
    end_line = re.compile(re.escape(newline) + rb"end_header[ \t]*" + re.escape(newline))
    buffer = bytearray(buffer)
    searched = 0  # the end_header line cannot start before this offset
    at_eof = False
    while True:
        match = end_line.search(buffer, searched)
        if match is None and at_eof:  # "end_header" as the very last bytes of the file
            match = re.compile(re.escape(newline) + rb"end_header[ \t]*\Z").search(buffer, searched)
        if match is not None:
            break
        if at_eof:
            raise PlyError("the header has no 'end_header' line")
        if len(buffer) > _MAX_HEADER_BYTES:
            raise PlyError(f"no 'end_header' line in the first {_MAX_HEADER_BYTES >> 20} MiB; not a PLY header")
        # The end_header line, if it begins in this buffer, begins at its last line break.
        searched = max(buffer.rfind(newline), 0)
        more = file.read(_HEADER_CHUNK_BYTES)
        at_eof = not more
        buffer += more
    lines = bytes(buffer[: match.start()]).split(newline)
    header = _parse_header_lines([line.decode("latin-1") for line in lines])
    return PlyHeader(
        **header, data_offset=match.end(), line_count=len(lines) + 1, newline=newline
    )


def _parse_header_lines(lines: Sequence[str]) -> dict:
    """The header lines before ``end_header`` (the first is ``ply``) -> PlyHeader fields."""
    ply_format: str | None = None
    comments: list[str] = []
    obj_info: list[str] = []
    # Elements under construction: [name, count, [properties]].
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words:
            raise PlyError(f"header line {number} is empty")
        keyword = words[0]
        if keyword in ("comment", "obj_info"):
            text = line.lstrip()[len(keyword) :]
            text = text[1:] if text[:1] in (" ", "\t") else text
            (comments if keyword == "comment" else obj_info).append(text)
        elif keyword == "format":
            if ply_format is not None:
                raise PlyError(f"header line {number} repeats the 'format' line")
            if elements:
                raise PlyError(f"header line {number}: 'format' must come before the first 'element'")
            if len(words) != 3 or words[1] not in FORMATS:
                raise PlyError(
                    f"header line {number}: expected 'format <{'|'.join(FORMATS)}> 1.0', got {line.strip()!r}"
                )
            if words[2] != "1.0":
                raise PlyError(f"header line {number}: PLY version {words[2]!r} is not supported (only 1.0)")
            ply_format = words[1]
        elif keyword == "element":
            if ply_format is None:
                raise PlyError(f"header line {number}: 'element' before the 'format' line")
            if len(words) != 3 or not _DECIMAL_COUNT.fullmatch(words[2]):
                raise PlyError(
                    f"header line {number}: expected 'element <name> <count>' with a non-negative "
                    f"integer count, got {line.strip()!r}"
                )
            if len(words[2]) > 18:  # also keeps int() clear of its 4300-digit limit
                raise PlyError(f"header line {number}: element count {words[2][:40]} is too large")
            elements.append((words[1], int(words[2]), []))
        elif keyword == "property":
            if not elements:
                raise PlyError(f"header line {number}: 'property' before any 'element' line")
            prop = _parse_property(words, number, line)
            element_name, _, properties = elements[-1]
            if any(existing.name == prop.name for existing in properties):
                raise PlyError(
                    f"header line {number}: element '{element_name}' declares property '{prop.name}' twice"
                )
            properties.append(prop)
        else:
            raise PlyError(
                f"header line {number}: unknown keyword {keyword!r} (expected format, comment, "
                "obj_info, element, property or end_header)"
            )
    if ply_format is None:
        raise PlyError("the header has no 'format' line")
    return {
        "format": ply_format,
        "elements": tuple(PlyElement(name, count, tuple(props)) for name, count, props in elements),
        "comments": tuple(comments),
        "obj_info": tuple(obj_info),
    }


def _parse_property(words: list[str], number: int, line: str) -> PlyProperty:
    def kind_of(type_name: str) -> str:
        if type_name not in SCALAR_TYPES:
            raise PlyError(
                f"header line {number}: unknown property type {type_name!r} "
                f"(PLY types: {', '.join(SCALAR_TYPES)})"
            )
        return SCALAR_TYPES[type_name]

    if len(words) >= 2 and words[1] == "list":
        if len(words) != 5:
            raise PlyError(
                f"header line {number}: expected 'property list <count type> <item type> <name>', "
                f"got {line.strip()!r}"
            )
        count_kind = kind_of(words[2])
        if count_kind[0] == "f":
            raise PlyError(f"header line {number}: a list length must have an integer type, not {words[2]!r}")
        return PlyProperty(words[4], kind_of(words[3]), count_kind)
    if len(words) != 3:
        raise PlyError(f"header line {number}: expected 'property <type> <name>', got {line.strip()!r}")
    return PlyProperty(words[2], kind_of(words[1]))


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


def read_scalar_properties(
    file: BinaryIO, header: PlyHeader, element_name: str, names: Sequence[str]
) -> list[np.ndarray]:
    """Read scalar properties of the first element called ``element_name``.

    Args:
        file: the PLY file, open in binary mode (any position).
        header: its header, from :func:`read_header`.
        element_name: the element, e.g. ``"vertex"``.
        names: its scalar properties to return, e.g. ``("x", "y", "z")``.

    Returns:
        One 1-D array per name, ``count`` values each, in the property's declared type.

    Raises:
        PlyError: the element or a property is missing, a property is a list, or the data
            up to the end of the element is truncated or malformed.
    """
    index = next((i for i, element in enumerate(header.elements) if element.name == element_name), None)
    if index is None:
        raise PlyError(f"no element '{element_name}' (elements: {', '.join(header.element_names) or 'none'})")
    target = header.elements[index]
    for name in names:
        prop = target.property(name)
        if prop is None:
            raise PlyError(f"element '{element_name}' has no property '{name}'")
        if prop.is_list:
            raise PlyError(f"property '{name}' of element '{element_name}' is a list, not a number")
    if header.byte_order is None:
        return _read_ascii(file, header, index, names)
    return _read_binary(file, header, index, names)


# ---- ASCII ----------------------------------------------------------------------------


def _read_ascii(file: BinaryIO, header: PlyHeader, index: int, names: Sequence[str]) -> list[np.ndarray]:
    file.seek(header.data_offset)
    # latin-1 maps every byte to one character, so decoding cannot fail; a stray byte
    # shows up as a value that does not parse.
    body = file.read().decode("latin-1")
    separator = "\r" if header.newline == b"\r" else "\n"  # a "\r\n" row keeps its "\r": whitespace
    needed = sum(element.count for element in header.elements[: index + 1])
    # Split off only the rows up to the end of the element; the rest stays one piece.
    rows = body.split(separator, min(needed, len(body) + 1))
    if len(rows) > needed:
        del rows[needed:]
    elif rows[-1] == "":  # the final line break, not an empty row
        rows.pop()
    first = 0
    line_number = header.line_count + 1
    for position, element in enumerate(header.elements[: index + 1]):
        element_rows = rows[first : first + element.count]
        if len(element_rows) < element.count:
            # A malformed row (e.g. two rows on one line) explains a short file better.
            _parse_ascii_rows(element_rows, element, line_number, ())
            raise PlyError(
                f"early end-of-file: element '{element.name}' declares {element.count} rows, "
                f"the file ends after {len(element_rows)}"
            )
        wanted = names if position == index else ()
        values = _parse_ascii_element(element_rows, element, line_number, wanted)
        first += element.count
        line_number += element.count
    return values


def _parse_ascii_element(
    rows: list[str], element: PlyElement, first_line: int, names: Sequence[str]
) -> list[np.ndarray]:
    """Check the rows of ``element`` and return the columns ``names`` (scalar properties)."""
    if element.count == 0:
        return [np.empty(0, dtype=element.property(name).kind) for name in names]
    if element.properties and not element.has_lists:
        # Fast path: NumPy's C parser, with every column in its declared type (so an
        # integer column rejects "2.5" and a uchar column rejects 300).
        record = np.dtype([(f"p{i}", prop.kind) for i, prop in enumerate(element.properties)])
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                table = np.loadtxt(rows, dtype=record, comments=None, ndmin=1)
        except (ValueError, OverflowError):
            table = None
        if table is not None and len(table) == element.count:  # loadtxt skips blank lines
            positions = element.property_names
            return [np.ascontiguousarray(table[f"p{positions.index(name)}"]) for name in names]
    # Rows with lists, without properties, or a problem to find and describe.
    return _parse_ascii_rows(rows, element, first_line, names)


def _parse_ascii_rows(
    rows: list[str], element: PlyElement, first_line: int, names: Sequence[str]
) -> list[np.ndarray]:
    """Row-by-row version of :func:`_parse_ascii_element`; raises PlyError at the first bad row."""
    columns: dict[str, list] = {name: [] for name in names}
    for row_index, raw in enumerate(rows):
        where = f"element '{element.name}', line {first_line + row_index}"
        tokens = raw.split()  # at whitespace as NumPy's loadtxt sees it (U+00A0 included)
        position = 0
        for prop in element.properties:
            if prop.is_list:
                length = _ascii_value(tokens, position, prop.count_kind, f"{where}: length of list '{prop.name}'")
                if length < 0:
                    raise PlyError(f"{where}: list '{prop.name}' has negative length {length}")
                position += 1
                for item in range(length):
                    _ascii_value(tokens, position + item, prop.kind, f"{where}: item {item} of list '{prop.name}'")
                position += length
            else:
                value = _ascii_value(tokens, position, prop.kind, f"{where}: property '{prop.name}'")
                if prop.name in columns:
                    columns[prop.name].append(value)
                position += 1
        if position != len(tokens):
            raise PlyError(
                f"{where}: {len(tokens)} values, but the properties of '{element.name}' take {position}"
            )
    with warnings.catch_warnings(), np.errstate(over="ignore"):
        warnings.simplefilter("ignore")  # float32 overflow gives inf, as the fast path does
        return [np.array(columns[name], dtype=element.property(name).kind) for name in names]


def _ascii_value(tokens: list[str], position: int, kind: str, what: str) -> int | float:
    """``tokens[position]`` parsed as NumPy ``kind``; PlyError naming ``what`` otherwise."""
    if position >= len(tokens):
        raise PlyError(f"{what} is missing (the row ends early)")
    token = tokens[position]
    if kind[0] == "f":
        try:
            if "_" in token:  # Python's float() accepts "1_0"; NumPy and PLY do not
                raise ValueError
            return float(token)
        except ValueError:
            raise PlyError(f"{what}: {token!r} is not a number") from None
    if not _ASCII_INTEGER.fullmatch(token):
        raise PlyError(f"{what}: {token!r} is not an integer")
    value = int(token)
    limits = np.iinfo(kind)
    if not limits.min <= value <= limits.max:
        raise PlyError(f"{what}: {value} is out of range for its type ({limits.min} to {limits.max})")
    return value


# ---- Binary ---------------------------------------------------------------------------


def _read_binary(file: BinaryIO, header: PlyHeader, index: int, names: Sequence[str]) -> list[np.ndarray]:
    order = header.byte_order
    target = header.elements[index]
    before = header.elements[:index]
    if not any(element.has_lists for element in header.elements[: index + 1]):
        # Every row has a fixed size: seek to the element, read exactly its bytes.
        file_size = file.seek(0, os.SEEK_END)
        offset = header.data_offset
        for element in before:
            size = element.count * _fixed_row_dtype(element, order).itemsize
            if offset + size > file_size:
                raise PlyError(_early_end(element, size, offset, file_size))
            offset += size
        size = target.count * _fixed_row_dtype(target, order).itemsize
        if offset + size > file_size:
            raise PlyError(_early_end(target, size, offset, file_size))
        file.seek(offset)
        data = file.read(size)
        if len(data) < size:
            raise PlyError(_early_end(target, size, offset, offset + len(data)))
        table = np.frombuffer(data, dtype=_fixed_row_dtype(target, order), count=target.count)
        return [_field(table, target, name) for name in names]
    # Lists up to the element: their lengths decide where rows start, so walk the data.
    file.seek(header.data_offset)
    data = file.read()
    position = 0
    for element in before:
        _, position = _binary_rows(data, position, element, order, (), header.data_offset)
    values, _ = _binary_rows(data, position, target, order, names, header.data_offset)
    return values


def _early_end(element: PlyElement, size: int, offset: int, file_size: int) -> str:
    return (
        f"early end-of-file: element '{element.name}' needs {size} bytes from byte {offset}, "
        f"the file has {max(file_size - offset, 0)}"
    )


def _fixed_row_dtype(element: PlyElement, order: str, list_lengths: Sequence[int] = ()) -> np.dtype:
    """The packed row of ``element``; list properties take the given lengths, in order."""
    fields = []
    lengths = iter(list_lengths)
    for i, prop in enumerate(element.properties):
        if prop.is_list:
            fields.append((f"n{i}", order + prop.count_kind))
            fields.append((f"p{i}", order + prop.kind, (next(lengths),)))
        else:
            fields.append((f"p{i}", order + prop.kind))
    return np.dtype(fields)


def _field(table: np.ndarray, element: PlyElement, name: str) -> np.ndarray:
    """Column ``name`` of a structured row array, as a new array in native byte order."""
    column = table[f"p{element.property_names.index(name)}"]
    return column.astype(column.dtype.newbyteorder("="))


def _binary_rows(
    data: bytes, start: int, element: PlyElement, order: str, names: Sequence[str], data_offset: int
) -> tuple[list[np.ndarray], int]:
    """Step over the rows of ``element`` from ``data[start]``, lists and all.

    ``data_offset`` is where ``data`` lies in the file (for messages). Returns the columns
    ``names`` and the offset in ``data`` just past the element.
    """
    if not element.has_lists:
        record = _fixed_row_dtype(element, order)
        end = start + element.count * record.itemsize
        if end > len(data):
            size = element.count * record.itemsize
            raise PlyError(_early_end(element, size, data_offset + start, data_offset + len(data)))
        if not names:
            return [], end
        table = np.frombuffer(data, dtype=record, count=element.count, offset=start)
        return [_field(table, element, name) for name in names], end
    if element.count == 0:
        return [np.empty(0, dtype=element.property(name).kind) for name in names], start
    plan = _row_plan(element, order, names)
    # Guess: every row's lists are as long as the first row's (triangle meshes); then the
    # rows have one fixed size and NumPy checks the guess in one pass.
    lengths = []
    _walk_rows(data, start, element, plan, 1, data_offset, lengths=lengths)
    record = _fixed_row_dtype(element, order, lengths)
    end = start + element.count * record.itemsize
    if end <= len(data):
        table = np.frombuffer(data, dtype=record, count=element.count, offset=start)
        list_fields = [f"n{i}" for i, prop in enumerate(element.properties) if prop.is_list]
        if all(np.all(table[field] == length) for field, length in zip(list_fields, lengths)):
            return [_field(table, element, name) for name in names], end
    # Lists of varying lengths: walk row by row, noting where the wanted values lie.
    offsets: dict[str, list[int]] = {name: [] for name in names}
    end = _walk_rows(data, start, element, plan, element.count, data_offset, offsets=offsets)
    return [_gather(data, offsets[name], order + element.property(name).kind) for name in names], end


def _row_plan(element: PlyElement, order: str, names: Sequence[str]) -> list[tuple]:
    """The steps of one binary row: ("fixed", bytes, [(name, offset), ...]) for runs of
    scalars (with the offsets of wanted ones), ("list", count struct, item bytes, name)."""
    plan: list[tuple] = []
    run, wanted = 0, []
    for prop in element.properties:
        if prop.is_list:
            if run or wanted:
                plan.append(("fixed", run, wanted))
            run, wanted = 0, []
            count_format = struct.Struct(order + _STRUCT_CODES[prop.count_kind])
            plan.append(("list", count_format, np.dtype(prop.kind).itemsize, prop.name))
        else:
            if prop.name in names:
                wanted.append((prop.name, run))
            run += np.dtype(prop.kind).itemsize
    if run or wanted:
        plan.append(("fixed", run, wanted))
    return plan


def _walk_rows(
    data: bytes,
    position: int,
    element: PlyElement,
    plan: list[tuple],
    rows: int,
    data_offset: int,
    offsets: dict[str, list[int]] | None = None,
    lengths: list[int] | None = None,
) -> int:
    """Step over ``rows`` binary rows from ``data[position]``; return the offset after them.

    Appends the offsets of the wanted scalars to ``offsets`` and every list length to
    ``lengths``, where given.
    """
    size = len(data)
    for row in range(rows):
        for step in plan:
            if step[0] == "fixed":
                if offsets is not None:
                    for name, offset in step[2]:
                        offsets[name].append(position + offset)
                position += step[1]
            else:
                _, count_format, item_size, name = step
                if position + count_format.size > size:
                    raise PlyError(_row_end(element, row, name, data_offset + size))
                (length,) = count_format.unpack_from(data, position)
                if length < 0:
                    raise PlyError(
                        f"element '{element.name}' row {row}: list '{name}' has negative length {length}"
                    )
                if lengths is not None:
                    lengths.append(length)
                position += count_format.size + length * item_size
                if position > size:
                    raise PlyError(_row_end(element, row, name, data_offset + size))
        if position > size:
            raise PlyError(_row_end(element, row, None, data_offset + size))
    return position


def _row_end(element: PlyElement, row: int, name: str | None, file_size: int) -> str:
    where = f", list '{name}'," if name else ""
    return (
        f"early end-of-file: element '{element.name}' row {row} (of {element.count}){where} "
        f"runs past the end of the file ({file_size} bytes)"
    )


def _gather(data: bytes, offsets: list[int], dtype: str) -> np.ndarray:
    """Values of ``dtype`` stored at the given byte offsets of ``data``, native byte order."""
    dtype = np.dtype(dtype)
    if not offsets:
        return np.empty(0, dtype=dtype.newbyteorder("="))
    raw = np.frombuffer(data, dtype=np.uint8)
    byte_index = np.asarray(offsets, dtype=np.int64)[:, None] + np.arange(dtype.itemsize)
    return raw[byte_index].view(dtype).reshape(-1).astype(dtype.newbyteorder("="))


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def write_binary_xyz(file: BinaryIO, points: np.ndarray, comments: Iterable[str] = ()) -> None:
    """Write (N, 3) points as a binary little-endian PLY with ``double`` x, y, z.

    Args:
        file: open in binary mode for writing.
        points: (N, 3) real numbers; stored as float64.
        comments: header comment lines (no line breaks).
    """
    points = np.ascontiguousarray(points, dtype="<f8")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), not {points.shape}")
    lines = ["ply", "format binary_little_endian 1.0"]
    for comment in comments:
        if "\n" in comment or "\r" in comment:
            raise ValueError(f"a PLY comment cannot contain a line break: {comment!r}")
        lines.append(f"comment {comment}")
    lines += [f"element vertex {len(points)}", "property double x", "property double y", "property double z"]
    lines.append("end_header")
    file.write(("\n".join(lines) + "\n").encode("ascii"))
    file.write(points.data)


# ----------------------------------------------------------------------------- files
def read(path: Path) -> np.ndarray:
    """Vertex x, y, z of a PLY file: (N, 3) in the file's dtype (float32 usually)."""
    with path.open("rb") as file:
        if file.read(3) != b"ply":
            raise file_error(path, "not a PLY file (it does not start with 'ply')")
        file.seek(0)
        header = read_header(file)
        vertex = header.element("vertex")
        if vertex is None:
            raise file_error(
                path, f"has no 'vertex' element (elements: {', '.join(header.element_names) or 'none'})"
            )
        missing = [axis for axis in ("x", "y", "z") if vertex.property(axis) is None]
        if missing:
            raise file_error(
                path,
                f"vertex element lacks propert{'y' if len(missing) == 1 else 'ies'} "
                f"{', '.join(missing)} (has: {', '.join(vertex.property_names) or 'none'})",
            )
        return np.column_stack(read_scalar_properties(file, header, "vertex", ("x", "y", "z")))


def write(path: Path, points: np.ndarray) -> None:
    with path.open("wb") as file:
        write_binary_xyz(file, points, comments=["written by logdesc-rt"])


_PLY_TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                   "f4": "float", "f8": "double"}


def write_with_attributes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
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

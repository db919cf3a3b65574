"""PLY files whose faces are triangle strips (``element tristrips``), which trimesh reads as bare points.

Scanners and older exporters (the Stanford repository, VTK) write a surface as strips: one list of
vertex indices per strip, ``-1`` between strips. Triangle i of strip ``s`` is ``(s[i], s[i+1], s[i+2])``
for even i and ``(s[i+1], s[i], s[i+2])`` for odd i, so every triangle keeps the strip's orientation;
triangles with a repeated index only join strips and are dropped. This module reads such a file
(ASCII, binary little- or big-endian), with any ``face`` element beside the strips, into the same
vertices and faces as its triangle-list twin.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

HEADER_LIMIT = 65536
"""A PLY header longer than this is not one."""
_TYPES = {
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
_END_HEADER = re.compile(rb"end_header[ \t]*\r?\n")


class PlyError(ValueError):
    """The file is not a PLY this module reads; the message says what is wrong with it."""


@dataclass(frozen=True)
class _Property:
    name: str
    dtype: str
    """Numpy type (no byte order) of the value, or of the items of a list."""
    count_dtype: str | None = None
    """For a list: numpy type of its length; None for a single value."""


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: tuple[_Property, ...]


def has_strips(path: Path) -> bool:
    """Whether ``path`` is a PLY file whose header declares ``element tristrips`` (reads the header only)."""
    try:
        with path.open("rb") as handle:
            head = handle.read(HEADER_LIMIT)
    except OSError:
        return False
    end = _END_HEADER.search(head)
    if not head.startswith(b"ply") or end is None:
        return False
    return re.search(rb"^element[ \t]+tristrips[ \t]", head[: end.start()], re.MULTILINE) is not None


def read_strip_ply(path: Path) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """Vertices (n, 3) and triangles (m, 3) of a PLY file with triangle strips (and perhaps faces);
    `PlyError` naming the defect otherwise."""
    data = path.read_bytes()
    end = _END_HEADER.search(data[:HEADER_LIMIT])
    if not data.startswith(b"ply") or end is None:
        raise PlyError("no 'ply' ... 'end_header' header")
    encoding, elements = _parse_header(data[: end.start()].decode("ascii", errors="replace"))
    body = data[end.end() :]
    if encoding == "ascii":
        values = _read_ascii(elements, body)
    else:
        values = _read_binary(elements, body, "<" if encoding == "binary_little_endian" else ">")
    vertices = _vertices(values)
    triangles = [_fan_faces(values["face"])] if "face" in values else []
    triangles.append(strip_triangles(_single_list(values["tristrips"], "tristrips")))
    faces = np.concatenate(triangles).astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        bad = int(faces.max() if faces.max() >= len(vertices) else faces.min())
        raise PlyError(f"vertex index {bad} is outside 0..{len(vertices) - 1}")
    return vertices, faces


def strip_triangles(strips: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """The triangles of strips given as one index array with ``-1`` between strips, in strip order,
    alternate ones flipped to keep the orientation, those with a repeated index dropped."""
    strips = np.asarray(strips, dtype=np.int64).ravel()
    if strips.size and strips.min() < -1:
        raise PlyError(f"strip index {int(strips.min())}; strips hold vertex indices and -1 between strips")
    if strips.size < 3:
        return np.zeros((0, 3), dtype=np.int64)
    positions = np.arange(strips.size)
    is_break = strips == -1
    # Where each position's strip begins: one past the last -1 at or before it.
    starts = np.maximum.accumulate(np.where(is_break, positions + 1, 0))
    first = positions[:-2]
    whole = ~(is_break[:-2] | is_break[1:-1] | is_break[2:])
    a, b, c = strips[:-2], strips[1:-1], strips[2:]
    odd = (first - starts[:-2]) % 2 == 1
    triangles = np.stack([np.where(odd, b, a), np.where(odd, a, b), c], axis=1)[whole]
    degenerate = (
        (triangles[:, 0] == triangles[:, 1])
        | (triangles[:, 1] == triangles[:, 2])
        | (triangles[:, 0] == triangles[:, 2])
    )
    return triangles[~degenerate]


def _parse_header(text: str) -> tuple[str, list[_Element]]:
    encoding = ""
    elements: list[_Element] = []
    name, count = "", 0
    properties: list[_Property] = []
    for number, line in enumerate(text.splitlines()[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                encoding = words[1]
            elif words[0] == "element":
                if name:
                    elements.append(_Element(name, count, tuple(properties)))
                name, count, properties = words[1], int(words[2]), []
            elif words[0] == "property" and words[1] == "list":
                properties.append(_Property(words[4], _TYPES[words[3]], _TYPES[words[2]]))
            elif words[0] == "property":
                properties.append(_Property(words[2], _TYPES[words[1]]))
            else:
                raise PlyError(f"header line {number} {line.strip()!r} is not a format, element or property")
        except (IndexError, KeyError, ValueError) as exc:
            if isinstance(exc, PlyError):
                raise
            raise PlyError(f"header line {number} {line.strip()!r} is malformed") from None
        if words[0] == "property" and not name:
            raise PlyError(f"header line {number}: a property before any element")
    if name:
        elements.append(_Element(name, count, tuple(properties)))
    if encoding not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PlyError(f"format {encoding or '(none)'!r}; PLY is ascii, binary_little_endian or binary_big_endian")
    return encoding, elements


_Values = dict[str, dict[str, list[npt.NDArray[np.generic]] | npt.NDArray[np.generic]]]
"""Element name -> property name -> a column (single values) or a list of arrays (list values)."""


def _list_rows(
    element: _Element,
    take_count: Callable[[_Property], int],
    take: Callable[[_Property, int], npt.NDArray[np.generic]],
) -> dict[str, list[npt.NDArray[np.generic]] | npt.NDArray[np.generic]]:
    """The columns of an element with a list property, read row by row in the file's order: each
    list's length by ``take_count``, then its values (or a single value) by ``take``."""
    rows: dict[str, list[npt.NDArray[np.generic]]] = {p.name: [] for p in element.properties}
    for _ in range(element.count):
        for p in element.properties:
            length = take_count(p) if p.count_dtype is not None else 1
            if length < 0:
                raise PlyError(f"element {element.name!r} has a list of negative length")
            rows[p.name].append(take(p, length))
    return {p.name: _column(p, rows[p.name]) for p in element.properties}


def _read_binary(elements: list[_Element], body: bytes, order: str) -> _Values:
    values: _Values = {}
    offset, where = 0, ""

    def read(dtype: np.dtype[Any], count: int) -> npt.NDArray[Any]:
        nonlocal offset
        if offset + dtype.itemsize * count > len(body):
            raise PlyError(f"the file ends inside element {where!r}")
        found = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
        offset += dtype.itemsize * count
        return found

    def count_of(prop: _Property) -> int:
        return int(read(np.dtype(order + str(prop.count_dtype)), 1)[0])

    def values_of(prop: _Property, count: int) -> npt.NDArray[Any]:
        return read(np.dtype(order + prop.dtype), count)

    for element in elements:
        where = element.name
        if all(p.count_dtype is None for p in element.properties):
            table = read(np.dtype([(p.name, order + p.dtype) for p in element.properties]), element.count)
            values[element.name] = {p.name: table[p.name] for p in element.properties}
        else:
            values[element.name] = _list_rows(element, count_of, values_of)
    return values


def _read_ascii(elements: list[_Element], body: bytes) -> _Values:
    tokens = body.split()
    values: _Values = {}
    at, where = 0, ""

    def read(count: int) -> list[bytes]:
        nonlocal at
        chunk = tokens[at : at + count]
        if len(chunk) < count:
            raise PlyError(f"the file ends inside element {where!r}")
        at += count
        return chunk

    def count_of(prop: _Property) -> int:
        return int(read(1)[0])

    def values_of(prop: _Property, count: int) -> npt.NDArray[Any]:
        return np.array(read(count), dtype=np.float64)

    for element in elements:
        where = element.name
        try:
            if all(p.count_dtype is None for p in element.properties):
                width = len(element.properties)
                table = np.array(read(width * element.count), dtype=np.float64).reshape(element.count, width)
                values[element.name] = {p.name: table[:, i] for i, p in enumerate(element.properties)}
            else:
                values[element.name] = _list_rows(element, count_of, values_of)
        except (IndexError, ValueError) as exc:
            if isinstance(exc, PlyError):
                raise
            raise PlyError(f"element {element.name!r} holds a value that is not a number, or ends early") from None
    return values


def _column(
    prop: _Property, rows: list[npt.NDArray[np.generic]]
) -> list[npt.NDArray[np.generic]] | npt.NDArray[np.generic]:
    """A list property keeps its rows; a single value becomes one column."""
    if prop.count_dtype is not None:
        return rows
    return np.concatenate(rows) if rows else np.zeros(0)


def _vertices(values: _Values) -> npt.NDArray[np.float64]:
    vertex = values.get("vertex", {})
    missing = [axis for axis in "xyz" if axis not in vertex or isinstance(vertex[axis], list)]
    if missing:
        raise PlyError(f"element 'vertex' lacks property {missing[0]!r}")
    return np.column_stack([np.asarray(vertex[axis], dtype=np.float64) for axis in "xyz"])


def _single_list(
    columns: dict[str, list[npt.NDArray[np.generic]] | npt.NDArray[np.generic]], element: str
) -> npt.NDArray[np.int64]:
    """The index arrays of an element's one list property (``vertex_indices`` or ``vertex_index``)."""
    lists = [column for column in columns.values() if isinstance(column, list)]
    if len(lists) != 1:
        raise PlyError(f"element {element!r} must have one list property (vertex_indices), it has {len(lists)}")
    rows = lists[0]
    if not rows:
        return np.zeros(0, dtype=np.int64)
    # Rows of one element are strips too: join them with -1 so no triangle spans two rows.
    joined = [np.append(np.asarray(row, dtype=np.int64), -1) for row in rows]
    return np.concatenate(joined)


def _fan_faces(columns: dict[str, list[npt.NDArray[np.generic]] | npt.NDArray[np.generic]]) -> npt.NDArray[np.int64]:
    """Triangles of a ``face`` element: each polygon as a fan from its first corner."""
    lists = [column for column in columns.values() if isinstance(column, list)]
    if len(lists) != 1:
        raise PlyError(f"element 'face' must have one list property (vertex_indices), it has {len(lists)}")
    triangles = []
    for polygon in lists[0]:
        corners = np.asarray(polygon, dtype=np.int64)
        if corners.size < 3:
            raise PlyError(f"a face has {corners.size} corners; faces need 3 or more")
        triangles.append(np.column_stack([np.full(corners.size - 2, corners[0]), corners[1:-1], corners[2:]]))
    return np.concatenate(triangles) if triangles else np.zeros((0, 3), dtype=np.int64)

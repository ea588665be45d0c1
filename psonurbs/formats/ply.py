"""PLY point clouds: the header read here, the vertices by numpy.

The header names every element (vertex, face, ...) with its count and properties; x, y
and z are taken from the vertex element by name, in any order and among any other
properties (normals, colours, intensities). Binary bodies (either byte order) are read
as numpy records at the offset the elements before the vertices imply, ASCII bodies as a
table of numbers; either is refused when it holds fewer vertices than the header
declares. Only a layout numpy records cannot describe (a list property in the vertex
element, or before it in a binary file) is left to open3d, whose count is checked too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psonurbs.errors import InputError
from psonurbs.formats.open3d_reader import read_with_open3d
from psonurbs.formats.records import (
    ascii_table,
    check_holds,
    check_point_count,
    check_text_size,
    declared_count,
    read_binary,
    xyz_columns,
)

__all__ = ["PlyHeader", "parse_header", "read_ply"]

SCALARS = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
           "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
           "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass
class Element:
    name: str
    count: int
    properties: list[tuple[str, str]] = field(default_factory=list)  # (name, numpy code or "list")

    @property
    def has_lists(self) -> bool:
        return any(code == "list" for _, code in self.properties)

    def dtype(self, order: str) -> np.dtype:
        return np.dtype([(f"p{k}_{name}", order + code) for k, (name, code) in enumerate(self.properties)])


@dataclass
class PlyHeader:
    format: str
    elements: list[Element]
    body_offset: int  # bytes from the start of the file to the first element's data
    lines: int  # lines of the header, for line numbers in messages

    def element(self, name: str) -> Element | None:
        return next((e for e in self.elements if e.name == name), None)


def parse_header(name: str, head: bytes) -> PlyHeader:
    """The header of a PLY file from its first bytes; InputError for anything malformed."""
    if not head.startswith(b"ply"):
        raise InputError(f"{name}: not a PLY file (it does not start with 'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise InputError(f"{name}: malformed PLY header (no 'end_header' line in the first 64 KiB)")
    body = end + len(b"end_header")
    if head[body:body + 2] == b"\r\n":
        body += 2
    elif head[body:body + 1] in (b"\n", b"\r"):
        body += 1
    fmt, elements = None, []
    for raw in head[:end].decode("ascii", "replace").splitlines()[1:]:
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        line = raw.strip()[:60]
        if words[0] == "format":
            if len(words) < 2 or words[1] not in FORMATS:
                raise InputError(f"{name}: malformed PLY header line '{line}' "
                                 f"(expected one of: {', '.join(FORMATS)})")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3:
                raise InputError(f"{name}: malformed PLY header line '{line}'")
            elements.append(Element(words[1], declared_count(name, f"element {words[1][:20]} count", words[2])))
        elif words[0] == "property":
            if not elements:
                raise InputError(f"{name}: malformed PLY header: property before any element ('{line}')")
            if len(words) == 5 and words[1] == "list":
                elements[-1].properties.append((words[4], "list"))
            elif len(words) == 3 and words[1] in SCALARS:
                elements[-1].properties.append((words[2], SCALARS[words[1]]))
            else:
                raise InputError(f"{name}: malformed PLY header line '{line}'")
        else:
            raise InputError(f"{name}: malformed PLY header line '{line}'")
    if fmt is None:
        raise InputError(f"{name}: malformed PLY header (no 'format' line)")
    return PlyHeader(fmt, elements, body, head[:body].count(b"\n"))


def read_ply(path: Path, name: str, head: bytes, size: int, max_points: int | None = None) -> np.ndarray:
    """The (N, 3) vertex coordinates of a PLY file (``head``: its first bytes, ``size``: its
    length); more vertices declared than ``max_points`` are refused before reading."""
    header = parse_header(name, head)
    vertex = header.element("vertex")
    if vertex is None:
        others = ", ".join(e.name for e in header.elements) or "none"
        raise InputError(f"{name}: PLY file has no vertices (no 'vertex' element; elements: {others})")
    if vertex.count == 0:
        raise InputError(f"{name}: PLY file has no vertices (header declares 0)")
    check_point_count(name, vertex.count, max_points)
    fields = [p for p, _ in vertex.properties]
    columns = xyz_columns(name, fields, "PLY vertices")
    before = header.elements[:header.elements.index(vertex)]
    order = FORMATS[header.format]
    if order is None:
        if vertex.has_lists:
            return _by_open3d(path, name, vertex.count)
        check_text_size(name, size, "an ASCII PLY")
        return _ascii_vertices(path, name, header, before, vertex, columns)
    if vertex.has_lists or any(e.has_lists for e in before):
        return _by_open3d(path, name, vertex.count)
    offset = header.body_offset + sum(e.count * e.dtype(order).itemsize for e in before)
    dtype = vertex.dtype(order)
    check_holds(name, "PLY", vertex.count, dtype.itemsize, size - offset, "vertices")  # before reading anything
    with open(path, "rb") as f:
        f.seek(offset)
        data = f.read(vertex.count * dtype.itemsize)
    records = read_binary(name, "PLY", data, 0, dtype, vertex.count, "vertices")
    return np.column_stack([records[dtype.names[c]].astype(np.float64) for c in columns])


def _ascii_vertices(path: Path, name: str, header: PlyHeader, before: list[Element], vertex: Element,
                    columns: list[int]) -> np.ndarray:
    with open(path, "rb") as f:
        f.seek(header.body_offset)
        text = f.read().decode("ascii", "replace")
    lines = text.splitlines()
    skip = sum(e.count for e in before)  # one line per instance of an earlier element
    table = ascii_table(name, "PLY", lines[skip:], vertex.count, len(vertex.properties), header.lines + skip + 1,
                        "vertices")
    return table[:, columns]


def _by_open3d(path: Path, name: str, expected: int) -> np.ndarray:
    return read_with_open3d(path, name, "ply", expected)

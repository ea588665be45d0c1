"""PCD point clouds (the Point Cloud Library's format): the header read here, the points by numpy.

The header lists the FIELDS with their SIZE, TYPE and COUNT, the number of POINTS (or
WIDTH x HEIGHT) and the DATA layout. ``ascii`` and ``binary`` bodies are read here, x, y
and z by name; a body holding fewer points than POINTS is refused with both counts
(open3d fills the missing points with garbage). ``binary_compressed`` (LZF) is left to
open3d, after its two size words are checked against POINTS.
"""
from __future__ import annotations

import struct
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

__all__ = ["read_pcd"]

_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
          ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}
_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def read_pcd(path: Path, name: str, head: bytes, size: int, max_points: int | None = None) -> np.ndarray:
    """The (N, 3) coordinates of a PCD file (``head``: its first bytes, ``size``: its length);
    more points declared than ``max_points`` are refused before reading."""
    fields: dict[str, list[str]] = {}
    offset = 0
    lines = 0
    for raw in head.splitlines(keepends=True):
        offset += len(raw)
        lines += 1
        text = raw.decode("ascii", "replace").strip()
        if not text or text.startswith("#"):
            continue
        words = text.split()
        key = words[0].upper()
        if key not in _KEYS:
            raise InputError(f"{name}: malformed or truncated PCD file: unknown header line '{text[:40]}'")
        fields[key] = words[1:]
        if key == "DATA":
            break
    else:
        raise InputError(f"{name}: malformed or truncated PCD file: no DATA line in the first 64 KiB")
    names = fields.get("FIELDS", [])
    if not names:
        raise InputError(f"{name}: malformed PCD header: no FIELDS")
    sizes = fields.get("SIZE", [])
    types = fields.get("TYPE", [])
    counts = fields.get("COUNT", ["1"] * len(names))
    if not (len(sizes) == len(types) == len(counts) == len(names)):
        raise InputError(f"{name}: malformed PCD header: FIELDS, SIZE, TYPE and COUNT differ in length "
                         f"({len(names)}, {len(sizes)}, {len(types)}, {len(counts)})")
    columns = xyz_columns(name, names, "PCD points")
    layout = []
    for field, s, t, c in zip(names, sizes, types, counts):
        code = _TYPES.get((t.upper(), declared_count(name, f"SIZE of {field[:20]}", s)))
        if code is None:
            raise InputError(f"{name}: malformed PCD header: field {field[:20]} has TYPE {t[:4]} "
                             f"with SIZE {s[:8]}")
        layout.append((field, code, declared_count(name, f"COUNT of {field[:20]}", c)))
    count = _point_count(name, fields)
    check_point_count(name, count, max_points)
    data = (fields["DATA"] or ["?"])[0].lower()
    if data == "ascii":
        check_text_size(name, size, "an ASCII PCD")
        with open(path, "rb") as f:
            f.seek(offset)
            body = f.read().decode("ascii", "replace").splitlines()
        width = sum(c for _, _, c in layout)
        starts = np.cumsum([0] + [c for _, _, c in layout])
        table = ascii_table(name, "PCD", body, count, width, lines + 1)
        return table[:, [starts[k] for k in columns]]
    if data not in ("binary", "binary_compressed"):
        raise InputError(f"{name}: malformed PCD header: DATA '{data[:20]}' (expected ascii, binary "
                         "or binary_compressed)")
    record = np.dtype([(f"f{k}", "<" + code, (c,)) if c != 1 else (f"f{k}", "<" + code)
                       for k, (_, code, c) in enumerate(layout)])
    if data == "binary":
        check_holds(name, "PCD", count, record.itemsize, size - offset)
        with open(path, "rb") as f:
            f.seek(offset)
            records = read_binary(name, "PCD", f.read(count * record.itemsize), 0, record, count)
        return np.column_stack([_first(records[f"f{k}"]) for k in columns]).astype(np.float64)
    with open(path, "rb") as f:
        f.seek(offset)
        words = f.read(8)
    if len(words) < 8:
        raise InputError(f"{name}: truncated file: no compressed block after the header")
    compressed, uncompressed = struct.unpack("<II", words)
    if uncompressed != count * record.itemsize or compressed > size - offset - 8:
        raise InputError(f"{name}: malformed or truncated PCD file: the compressed block holds "
                         f"{compressed:,} of {size - offset - 8:,} bytes and unpacks to {uncompressed:,}, "
                         f"the header declares {count:,} points of {record.itemsize} bytes")
    return read_with_open3d(path, name, "pcd", count)


def _point_count(name: str, fields: dict[str, list[str]]) -> int:
    if fields.get("POINTS"):
        return declared_count(name, "POINTS", fields["POINTS"][0])
    width = declared_count(name, "WIDTH", (fields.get("WIDTH") or ["?"])[0])
    height = declared_count(name, "HEIGHT", (fields.get("HEIGHT") or ["1"])[0])
    return width * height


def _first(column: np.ndarray) -> np.ndarray:
    """A field's values; of a field with COUNT > 1, the first."""
    return column if column.ndim == 1 else column[:, 0]

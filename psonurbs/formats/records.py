"""Point records of the formats that declare a point count (PLY, PCD): binary records as
numpy structured types, ASCII rows as a number table, both checked against the count
the header promises before anything is allocated.

Both readers share the same rules: the coordinates are taken by name (x, y, z, in any
order, among any other fields), a body shorter than the header promises is refused with
both counts, and a promise that the file's size cannot hold (a billion points in a
kilobyte, a negative count) is refused before reading.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from psonurbs.errors import InputError


@dataclass(frozen=True)
class Cloud:
    """A cloud as read: ``points`` ``(N, 3)`` float64, and the reader's notes (E57: how
    many scans were merged), which a fit reports with its own."""

    points: np.ndarray
    notes: tuple[str, ...] = ()


MAX_TEXT_BYTES = 512 << 20  # a cloud parsed as text (XYZ, ASCII PLY or PCD): at most 512 MiB

_NUMBER_SPLIT = re.compile(r"[,\s]+")


def declared_count(name: str, what: str, word: str) -> int:
    """The integer of a header's count field, or InputError (not a number, negative)."""
    try:
        count = int(word)
    except ValueError:
        raise InputError(f"{name}: malformed header: {what} '{word[:40]}' is not a whole number") from None
    if count < 0:
        raise InputError(f"{name}: malformed header: {what} is negative ({count})")
    return count


def read_binary(name: str, kind: str, data: memoryview | bytes, offset: int, dtype: np.dtype, count: int,
                noun: str = "points") -> np.ndarray:
    """``count`` records of ``dtype`` from ``data[offset:]``; refused when they are not all there."""
    check_holds(name, kind, count, dtype.itemsize, len(data) - offset, noun)
    return np.frombuffer(data, dtype=dtype, count=count, offset=offset)


def check_holds(name: str, kind: str, count: int, record_bytes: int, available: int,
                noun: str = "points") -> None:
    """Refuse a body of ``available`` bytes that cannot hold ``count`` records of this size."""
    available = max(available, 0)
    if count * record_bytes > available:
        held = available // record_bytes if record_bytes else 0
        raise InputError(f"{name}: malformed or truncated {kind} file: the header declares {count:,} {noun} "
                         f"({count * record_bytes:,} bytes), the file holds {held:,} ({available:,} bytes)")


def xyz_columns(name: str, fields: Sequence[str], noun: str) -> list[int]:
    """Indices of the x, y and z fields, or InputError naming what is missing."""
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise InputError(f"{name}: {noun} have no {'/'.join(missing)} coordinate "
                         f"(properties: {', '.join(fields[:12]) or 'none'})")
    return [list(fields).index(c) for c in "xyz"]


def ascii_table(name: str, kind: str, lines: Sequence[str], count: int, columns: int, first_line: int,
                noun: str = "points") -> np.ndarray:
    """A (count, columns) float table from the first ``count`` non-empty lines.

    ``first_line`` is the line number of ``lines[0]`` in the file, for the message.
    """
    rows = [(k, ln) for k, ln in enumerate(lines) if ln.strip()][:count]
    if len(rows) < count:
        raise InputError(f"{name}: malformed or truncated {kind} file: the header declares {count:,} {noun}, "
                         f"the body holds {len(rows):,}")
    if count == 0:
        return np.zeros((0, columns))
    try:  # the fast path: numpy's parser; the loop below says which line is wrong
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            table = np.loadtxt([ln for _, ln in rows], ndmin=2, dtype=np.float64, comments=None)
        if table.shape == (count, columns):
            return table
    except ValueError:
        pass
    table = np.empty((count, columns))
    for i, (k, line) in enumerate(rows):
        tokens = [t for t in _NUMBER_SPLIT.split(line.strip()) if t]
        if len(tokens) != columns:
            raise InputError(f"{name}: malformed or truncated {kind} file: line {first_line + k}: expected "
                             f"{columns} values, found {len(tokens)}")
        try:
            table[i] = [float(t) for t in tokens]
        except ValueError:
            bad = next(t for t in tokens if not is_number(t))
            raise InputError(f"{name}: malformed or truncated {kind} file: line {first_line + k}: "
                             f"'{bad[:40]}' is not a number") from None
    return table


def check_point_count(name: str, count: int, max_points: int | None) -> None:
    """Refuse a cloud of more points than the caller can fit (checked from a header's count
    before the body is read)."""
    if max_points is not None and count > max_points:
        raise InputError(f"{name}: {count:,} points are more than this config can fit "
                         f"(at most {max_points:,} within the memory budget)")


def check_text_size(name: str, size: int, what: str) -> None:
    if size > MAX_TEXT_BYTES:
        raise InputError(f"{name}: file is too large for {what} ({size / 2**20:.0f} MiB; at most "
                         f"{MAX_TEXT_BYTES >> 20} MiB of text; use a binary PLY)")


def is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False

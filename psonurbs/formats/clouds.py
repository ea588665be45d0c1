"""Reading point clouds (PLY, PCD, XYZ text; LAS, LAZ, E57 through
:mod:`psonurbs.formats.scans`) as (N, 3) arrays, refusing what is not one.

Reading refuses anything that is not a usable cloud with an
:class:`~psonurbs.errors.InputError` whose message starts with the file name
(``"scan.ply: file is empty"``): a path that is not a regular file (a named pipe, a
device, a symlink to one), a PLY or PCD whose body holds fewer points than its header
declares (or a count its size cannot hold), text beyond :data:`MAX_TEXT_BYTES`, and
NaN or infinite coordinates. PLY and PCD are read by :mod:`.ply` and :mod:`.pcd`
(x, y, z by name); open3d only for the layouts those leave to it
(:mod:`.open3d_reader`), its messages captured and turned into the error.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from psonurbs.errors import InputError, existing_file
from psonurbs.formats.pcd import read_pcd
from psonurbs.formats.ply import read_ply
from psonurbs.formats.records import MAX_TEXT_BYTES, Cloud, check_point_count, check_text_size, is_number
from psonurbs.formats.scans import SCAN_SUFFIXES, read_scan

__all__ = ["CLOUD_SUFFIXES", "MAX_TEXT_BYTES", "Cloud", "load_cloud", "read_cloud"]

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".txt", ".pts") + SCAN_SUFFIXES
_TEXT_SUFFIXES = (".xyz", ".txt", ".pts")


# ---- reading ---------------------------------------------------------------

def read_cloud(path: str | os.PathLike, max_points: int | None = None) -> np.ndarray:
    """Read a point cloud file as an ``(N, 3)`` float64 array (see :func:`load_cloud`)."""
    return load_cloud(path, max_points).points


def load_cloud(path: str | os.PathLike, max_points: int | None = None) -> Cloud:
    """Read a point cloud file: its points as an ``(N, 3)`` float64 array, and notes.

    ``.ply`` and ``.pcd`` are read by their headers (:mod:`.ply`, :mod:`.pcd`); ``.xyz``,
    ``.txt`` and ``.pts`` are text with x, y, z in the first three columns, separated by
    whitespace or commas (``#`` starts a comment; a ``.pts`` file may begin with a point
    count); ``.las``, ``.laz`` and ``.e57`` need the optional extra ``scan``
    (:mod:`psonurbs.formats.scans`: real coordinates, E57 scans merged by their poses).
    With ``max_points``, a PLY or PCD whose header declares more points is refused
    before its body is read (the caller knows what it can fit).

    Raises :class:`InputError` (message starting with the path) for a missing
    file, a directory or anything else that is not a regular file, an unknown
    extension, an unreadable, empty or malformed file, a PLY or PCD body shorter than
    its header declares, a PLY without vertices, and NaN or infinite coordinates.
    """
    path = existing_file(path, "a point cloud file", InputError)
    name = str(path)
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        shown = f"'{path.suffix[:20]}'" if path.suffix else "no extension"
        raise InputError(f"{name}: unknown point cloud type ({shown}); "
                         f"expected one of {', '.join(CLOUD_SUFFIXES)}")
    notes: tuple[str, ...] = ()
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
            size = os.fstat(f.fileno()).st_size
        if not head:
            points = None
        elif suffix in SCAN_SUFFIXES:
            scan = read_scan(path, name)
            points, notes = scan.points, scan.notes
        elif suffix == ".ply":
            points = read_ply(path, name, head, size, max_points)
        elif suffix == ".pcd":
            points = read_pcd(path, name, head, size, max_points)
        else:
            check_text_size(name, size, "a text cloud")
            points = _read_text(path, name, suffix)
    except OSError as e:
        raise InputError(f"{name}: cannot read file ({e.strerror or e})") from None
    except MemoryError:
        raise InputError(f"{name}: not enough memory to read the file") from None
    if points is None:
        raise InputError(f"{name}: file is empty")
    check_point_count(name, len(points), max_points)

    if len(points) == 0:
        raise InputError(f"{name}: no points found in the file")
    bad_nan = np.isnan(points).any(axis=1)
    bad_inf = np.isinf(points).any(axis=1) & ~bad_nan
    n_bad = int(bad_nan.sum() + bad_inf.sum())
    if n_bad:
        raise InputError(f"{name}: {n_bad} of {len(points)} points have non-finite coordinates "
                         f"({int(bad_nan.sum())} NaN, {int(bad_inf.sum())} infinite)")
    return Cloud(np.ascontiguousarray(points, dtype=np.float64), notes)


_SPLIT = re.compile(r"[,\s]+")


def _read_text(path: Path, name: str, suffix: str) -> np.ndarray:
    try:
        text = path.read_bytes().decode("utf-8-sig")  # a byte-order mark is not data
    except UnicodeDecodeError:
        raise InputError(f"{name}: not a text point cloud (the file contains binary data)") from None

    # Fast path: numpy's C parser (a .pts file's count line set aside). Anything it
    # does not like (too few columns, a bad token) goes through the slow path, which
    # either reads it or says exactly which line is wrong.
    lines = text.replace(",", " ").splitlines()
    if suffix == ".pts":
        lines = _after_count_line(lines)
    try:
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            points = np.loadtxt(lines, usecols=(0, 1, 2), comments="#", ndmin=2, dtype=np.float64)
        return points.reshape(-1, 3)
    except (ValueError, IndexError):
        pass

    rows: list[tuple[float, float, float]] = []
    errors: list[str] = []
    first_data = True
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        tokens = [t for t in _SPLIT.split(line) if t]
        if first_data and suffix == ".pts" and len(tokens) == 1 and tokens[0].isdigit():
            first_data = False  # the point count that starts a .pts file
            continue
        first_data = False
        if len(tokens) < 3:
            errors.append(f"line {lineno}: expected at least 3 numbers (x y z), "
                          f"found {len(tokens)}")
            continue
        try:
            rows.append((float(tokens[0]), float(tokens[1]), float(tokens[2])))
        except ValueError:
            bad = next(t for t in tokens[:3] if not is_number(t))
            errors.append(f"line {lineno}: '{bad[:40]}' is not a number")
    if errors:
        more = f" (and {len(errors) - 1} more bad lines)" if len(errors) > 1 else ""
        raise InputError(f"{name}: malformed point data at {errors[0]}{more}")
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def _after_count_line(lines: list[str]) -> list[str]:
    """The lines after a .pts file's point count (its first data line, a lone integer),
    or all of them if it has none."""
    for k, line in enumerate(lines):
        tokens = line.split("#", 1)[0].split()
        if tokens:
            return lines[k + 1:] if len(tokens) == 1 and tokens[0].isdigit() else lines
    return lines


"""Reading surveyors' and scanners' files: LAS / LAZ (laspy, LAZ through lazrs) and E57 (pye57).

Both libraries are the optional extra ``scan`` (``pip install 'psonurbs[scan]'``); without
them reading such a file is an :class:`~psonurbs.errors.InputError` that names the extra.

* **LAS / LAZ** store each coordinate as a 32-bit integer ``X`` with a per-file scale and
  offset; the real coordinate is ``x = X * scale + offset`` (float64), which is what is
  returned. The file is read in chunks and only x, y, z are kept (24 bytes a point, not
  the whole point record). Survey offsets are large (UTM: 5e6 m); the fit centres and
  scales the cloud itself (:mod:`psonurbs.fitting.prepare.organise`), so nothing is shifted here.
* **E57** holds one or more scans, each in its own frame with a pose (rotation
  quaternion, translation) into the file's frame. Every scan is read (Cartesian or
  spherical coordinates, scaled integers or floats, invalid points dropped), placed by
  its pose, and the scans are merged in file order; a note says how many.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from psonurbs.errors import InputError
from psonurbs.formats.records import Cloud

__all__ = ["SCAN_SUFFIXES", "read_scan"]

SCAN_SUFFIXES = (".las", ".laz", ".e57")
_INSTALL = "pip install 'psonurbs[scan]'"
_CHUNK = 1 << 20  # LAS points read at a time


def read_scan(path: Path, name: str) -> Cloud:
    """Read a ``.las``, ``.laz`` or ``.e57`` file; ``name`` starts every error message."""
    suffix = path.suffix.lower()
    if suffix in (".las", ".laz"):
        return _read_las(path, name, suffix)
    if suffix == ".e57":
        return _read_e57(path, name)
    raise InputError(f"{name}: not a scan file ({path.suffix})")


def _missing(name: str, what: str, package: str) -> InputError:
    return InputError(f"{name}: reading {what} files needs the optional package {package}, "
                      f"which is not installed: {_INSTALL}")


def _read_las(path: Path, name: str, suffix: str) -> Cloud:
    kind = suffix[1:].upper()
    try:
        import laspy
    except ImportError:
        raise _missing(name, kind, "laspy") from None
    try:
        with laspy.open(str(path)) as reader:
            if reader.header.are_points_compressed and not laspy.LazBackend.detect_available():
                raise _missing(name, "compressed LAZ", "lazrs")
            expected = int(reader.header.point_count)
            parts = [np.column_stack([np.asarray(chunk.x, np.float64), np.asarray(chunk.y, np.float64),
                                      np.asarray(chunk.z, np.float64)])
                     for chunk in reader.chunk_iterator(_CHUNK)]
    except InputError:
        raise
    except Exception as e:  # laspy and lazrs raise their own types for a bad file
        raise InputError(f"{name}: not a readable {kind} file ({_detail(e)})") from None
    points = np.concatenate(parts) if parts else np.zeros((0, 3))
    if len(points) != expected:
        raise InputError(f"{name}: truncated {kind} file (header declares {expected} points, "
                         f"{len(points)} read)")
    return Cloud(points)


def _read_e57(path: Path, name: str) -> Cloud:
    try:
        import pye57
    except ImportError:
        raise _missing(name, "E57", "pye57") from None
    try:
        e57 = pye57.E57(str(path))
    except Exception as e:  # libe57's own exception types
        raise InputError(f"{name}: not a readable E57 file ({_detail(e)})") from None
    try:
        count = e57.scan_count
        parts = []
        for index in range(count):
            data = e57.read_scan(index, ignore_missing_fields=True, transform=True)
            parts.append(np.column_stack([np.asarray(data[c], np.float64)
                                          for c in ("cartesianX", "cartesianY", "cartesianZ")]))
    except Exception as e:
        raise InputError(f"{name}: malformed E57 file ({_detail(e)})") from None
    finally:
        e57.close()
    if count == 0:
        raise InputError(f"{name}: E57 file holds no scans")
    points = np.concatenate(parts)
    sizes = " + ".join(str(len(p)) for p in parts)
    if count == 1:
        note = f"E57: 1 scan ({sizes} valid points), placed by its pose in the file's frame"
    else:
        note = f"E57: {count} scans merged ({sizes} valid points), each placed by its pose in the file's frame"
    return Cloud(points, (note,))


def _detail(error: BaseException) -> str:
    text = " ".join(str(error).split())
    text = text if len(text) <= 160 else text[:157] + "..."
    return f"{type(error).__name__}: {text}" if text else type(error).__name__

"""open3d's reading of the PLY and PCD layouts the own readers leave to it, refused unless
it read exactly the points the header declares and said nothing alarming; what open3d
prints meanwhile is captured and becomes the error's detail.
"""
from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np

from psonurbs.errors import InputError

_ANSI = re.compile(r"\x1b\[[0-9;]*m")


@contextlib.contextmanager
def _captured_output() -> Iterator[list[str]]:
    """Capture what open3d prints while it reads.

    open3d's logger writes through Python's ``sys.stdout`` and RPly (its PLY
    parser) writes to file descriptor 2 from C; both are noise for our users but
    useful in an error message. So both the Python streams and descriptors 1 and 2
    are redirected; the captured text is appended to the yielded list at the end.
    """
    out: list[str] = []
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved = []
    python_text = io.StringIO()
    with tempfile.TemporaryFile() as sink:
        try:
            for fd in (1, 2):
                try:
                    saved.append((fd, os.dup(fd)))
                    os.dup2(sink.fileno(), fd)
                except OSError:
                    pass
            with contextlib.redirect_stdout(python_text), contextlib.redirect_stderr(python_text):
                yield out
        finally:
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            text = python_text.getvalue() + sink.read().decode("utf-8", "replace")
            out.append(_ANSI.sub("", text))


def _open3d_detail(captured: str) -> str:
    lines = [ln.strip() for ln in captured.splitlines() if ln.strip()]
    lines = [re.sub(r"^\[Open3D (WARNING|ERROR|INFO|DEBUG)\]\s*", "", ln) for ln in lines]
    return "; ".join(lines[:2])


def read_with_open3d(path: Path, name: str, fmt: str, expected: int) -> np.ndarray:
    """open3d's reading of a layout the own readers leave to it; refused unless it read
    exactly the ``expected`` number of points and said nothing alarming."""
    import open3d as o3d

    with _captured_output() as captured, \
            o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Warning):
        cloud = o3d.io.read_point_cloud(str(path), format=fmt, remove_nan_points=False,
                                        remove_infinite_points=False, print_progress=False)
    points = np.asarray(cloud.points, dtype=np.float64).reshape(-1, 3)
    detail = _open3d_detail(captured[0])
    failed = "RPly" in detail or "failed" in detail.lower() or len(points) != expected
    if failed or (len(points) == 0 and detail):
        what = f"malformed or truncated {fmt.upper()} file"
        if len(points) != expected:
            what += f" (header declares {expected} points, {len(points)} read)"
        raise InputError(f"{name}: {what}" + (f": {detail}" if detail else ""))
    return points

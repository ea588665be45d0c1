"""Writing a fit's outputs: the JSON, the mesh (OBJ, PLY), the error curve (CSV).

Writing is atomic per file (write ``NAME.tmp-<pid>`` beside the target, then
``os.replace``) and all-or-nothing per fit (:func:`write_fit_outputs`). Outputs are
byte-identical for identical inputs: no timestamps, no paths.
"""
from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = [
    "atomic_write",
    "output_paths",
    "render_json",
    "render_obj",
    "render_ply",
    "render_csv",
    "write_fit_outputs",
]


def atomic_write(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` to ``path`` atomically.

    The data go to ``path.tmp-<pid>`` in the same directory, which is then
    renamed over ``path`` with :func:`os.replace`; a reader sees the old file or
    the new one, never a part. Text is encoded as UTF-8 with ``\\n`` newlines.
    """
    path = Path(path)
    if isinstance(data, str):
        data = data.encode("utf-8")
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    return path


def output_paths(out_dir: str | os.PathLike, stem: str) -> dict[str, Path]:
    """The four files a fit writes, in the order they are written (JSON last)."""
    out_dir = Path(out_dir)
    return {
        "obj": out_dir / f"{stem}.obj",
        "ply": out_dir / f"{stem}.ply",
        "csv": out_dir / f"{stem}_error.csv",
        "json": out_dir / f"{stem}.json",
    }


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (tuple, set, frozenset)):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def render_json(document: dict) -> str:
    """``document`` as indented JSON; numpy values become plain numbers/lists.

    NaN and infinity are refused (``ValueError``): JSON has no such numbers.
    """
    try:
        return json.dumps(document, indent=2, sort_keys=False, allow_nan=False,
                          default=_json_default) + "\n"
    except ValueError as e:
        raise ValueError(f"fit document is not valid JSON: {e}") from None


def _mesh_arrays(vertices: Any, triangles: Any) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"mesh vertices must have shape (M, 3), got {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("mesh vertices contain NaN or infinity")
    if t.size == 0:
        t = t.reshape(0, 3)
    if t.ndim != 2 or t.shape[1] != 3 or not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"mesh triangles must be integers of shape (K, 3), got {t.dtype} {t.shape}")
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise ValueError("mesh triangles index vertices out of range")
    return v, t.astype(np.int64)


def render_obj(vertices: Any, triangles: Any) -> str:
    """Wavefront OBJ text: ``v x y z`` (``%.17g``, exact) and 1-based ``f a b c``."""
    v, t = _mesh_arrays(vertices, triangles)
    parts = [f"# psonurbs surface mesh: {len(v)} vertices, {len(t)} triangles\n"]
    parts += ["v %.17g %.17g %.17g\n" % tuple(row) for row in v.tolist()]
    parts += ["f %d %d %d\n" % tuple(row) for row in (t + 1).tolist()]
    return "".join(parts)


def render_ply(vertices: Any, triangles: Any) -> bytes:
    """Binary little-endian PLY: double x y z, faces as ``list uchar int``."""
    v, t = _mesh_arrays(vertices, triangles)
    header = ("ply\n"
              "format binary_little_endian 1.0\n"
              "comment psonurbs surface mesh\n"
              f"element vertex {len(v)}\n"
              "property double x\nproperty double y\nproperty double z\n"
              f"element face {len(t)}\n"
              "property list uchar int vertex_indices\n"
              "end_header\n").encode("ascii")
    faces = np.empty(len(t), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    faces["n"] = 3
    faces["idx"] = t
    return header + np.ascontiguousarray(v, dtype="<f8").tobytes() + faces.tobytes()


def render_csv(header: Sequence[str], rows: Any) -> str:
    """CSV text: the header, then one row per iteration.

    A column named ``iteration`` is written as an integer, every other one with
    ``%.17g`` (round-trips exactly).
    """
    header = [str(h) for h in header]
    for h in header:
        if any(c in h for c in ',"\n\r'):
            raise ValueError(f"CSV column name {h!r} contains a comma, quote or newline")
    r = np.asarray(rows, dtype=np.float64)
    if r.size == 0:
        r = r.reshape(0, len(header))
    if r.ndim != 2 or r.shape[1] != len(header):
        raise ValueError(f"error curve has shape {r.shape}, expected (n, {len(header)}) "
                         f"for columns {header}")
    int_cols = [i for i, h in enumerate(header) if h == "iteration"]
    for i in int_cols:
        if not np.array_equal(r[:, i], np.round(r[:, i])):
            raise ValueError("the 'iteration' column of the error curve is not integral")
    fmt = ",".join("%d" if i in int_cols else "%.17g" for i in range(len(header))) + "\n"
    values = r.tolist()
    for i in int_cols:
        for row in values:
            row[i] = int(row[i])
    return ",".join(header) + "\n" + "".join(fmt % tuple(row) for row in values)


def write_fit_outputs(out_dir: str | os.PathLike, stem: str, document: dict,
                      vertices: Any, triangles: Any, curve_header: Sequence[str],
                      curve_rows: Any, *, obj_extra: str = "",
                      extra_files: Mapping[str, bytes | str] | None = None) -> dict[str, Path]:
    """Write ``STEM.json``, ``STEM.obj``, ``STEM.ply`` and ``STEM_error.csv``.

    ``obj_extra`` is appended to the OBJ text (the exact NURBS block of
    ``--format obj-nurbs``); ``extra_files`` maps a suffix (``".igs"``, ``".3dm"``,
    ``"_tolerance.csv"``) to the content of ``STEM + suffix``, written with the others.

    All are rendered in memory first; then each is written atomically, the JSON
    last. If anything fails (including Ctrl-C), the files already placed for this
    stem are removed and the exception propagates, so a fit leaves all its files or
    none. ``out_dir`` is created if needed. Returns the paths by kind (``"obj"``,
    ``"ply"``, ``"csv"``, the extra suffixes, ``"json"``).
    """
    paths = output_paths(out_dir, stem)
    rendered = {
        "obj": render_obj(vertices, triangles) + obj_extra,
        "ply": render_ply(vertices, triangles),
        "csv": render_csv(curve_header, curve_rows),
        "json": render_json(document),
    }
    json_path = paths.pop("json")
    for suffix, data in (extra_files or {}).items():
        if not suffix.startswith((".", "_")) or suffix in (".json", ".obj", ".ply", "_error.csv"):
            raise ValueError(f"extra output suffix {suffix!r} is not allowed")
        paths[suffix] = Path(out_dir) / f"{stem}{suffix}"
        rendered[suffix] = data
    paths["json"] = json_path
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    placed: list[Path] = []
    try:
        for kind, path in paths.items():
            atomic_write(path, rendered[kind])
            placed.append(path)
    except BaseException:
        for path in placed:
            with contextlib.suppress(OSError):
                path.unlink()
        raise
    return paths

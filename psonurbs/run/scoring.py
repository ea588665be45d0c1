"""Distances from a point cloud to a saved surface (``psonurbs score``).

The distance of a point is the distance to its closest point on the surface, found by
:func:`psonurbs.geometry.projection.closest_parameters` (a global search on a tessellation, then
Newton steps), the same projection the fitter uses for its own metrics.
"""
from __future__ import annotations

import json
import os

import numpy as np

from psonurbs.errors import InputError, existing_file
from psonurbs.geometry.nurbs import NurbsSurface

__all__ = ["load_faces", "load_surface", "point_distances", "nearest_distances", "score", "PERCENTILES"]

PERCENTILES = (50, 90, 95, 99)


def load_faces(path: str | os.PathLike) -> tuple[list[tuple[NurbsSurface, object]], dict]:
    """The faces of a fit's ``STEM.json``, each (surface, its Trim or None): the one
    ``surface``, the ``surfaces`` of an object of several faces, or a bare surface
    mapping; and the document. Raises :class:`InputError` naming the file for anything
    that is not a surface."""
    path = existing_file(path, "a surface JSON file", InputError)
    name = str(path)
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InputError(f"{name}: not a surface JSON file (not UTF-8 text)") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{name}: malformed JSON ({e.msg} at line {e.lineno})") from None
    except OSError as e:
        raise InputError(f"{name}: cannot read file ({e.strerror or e})") from None
    if not isinstance(document, dict):
        raise InputError(f"{name}: not a surface JSON file (expected an object)")
    several = document.get("surfaces")
    entries = several if isinstance(several, list) and several else [document.get("surface", document)]
    faces = []
    for data in entries:
        if not isinstance(data, dict):
            raise InputError(f"{name}: 'surface' is not an object")
        faces.append((_surface_of(data, name), _trim_of(data, name)))
    return faces, document


def load_surface(path: str | os.PathLike) -> tuple[NurbsSurface, dict]:
    """The (first) surface of a fit's ``STEM.json`` and the document (:func:`load_faces`)."""
    faces, document = load_faces(path)
    return faces[0][0], document


def _surface_of(data: dict, name: str) -> NurbsSurface:
    missing = [k for k in ("degree_u", "degree_v", "knots_u", "knots_v", "control_points")
               if k not in data]
    if missing:
        raise InputError(f"{name}: not a surface JSON file (missing {', '.join(missing)})")
    try:
        surface = NurbsSurface.from_dict(data)
    except (ValueError, TypeError) as e:
        raise InputError(f"{name}: invalid surface: {e}") from None
    if not np.all(np.isfinite(surface.control_points)):
        raise InputError(f"{name}: invalid surface: control points are not finite")
    return surface


def _trim_of(data: dict, name: str):
    from psonurbs.geometry.trim import Trim

    try:
        return Trim.from_list(data.get("trim"))
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{name}: invalid trim loops: {e}") from None


def point_distances(surface: NurbsSurface, points: np.ndarray, trim=None) -> np.ndarray:
    """Distance of each point to the surface (to the trimmed face when ``trim`` is given,
    a :class:`~psonurbs.geometry.trim.Trim`), shape (N,)."""
    from psonurbs.geometry.projection import closest_parameters
    from psonurbs.geometry.trim import distances_to_face

    points = np.asarray(points, float).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0)
    uv, distances = closest_parameters(surface, points)
    if trim is not None:
        distances = distances_to_face(surface, trim, points, uv, distances)
    return np.asarray(distances, float)


def nearest_distances(faces: list[tuple[NurbsSurface, object]], points: np.ndarray) -> np.ndarray:
    """Distance of each point (N, 3) to its nearest face (surface, trim or None), (N,)."""
    return np.min([point_distances(surface, points, trim) for surface, trim in faces], axis=0)


def score(faces: list[tuple[NurbsSurface, object]], points: np.ndarray) -> dict:
    """Figures of the distances from ``points`` to their nearest face ((surface, trim or
    None) pairs, :func:`load_faces`).

    ``rmse``, ``max_error``, ``mean_error`` and the percentiles ``p50`` ... ``p99``
    are in the cloud's units; ``*_relative`` are divided by the cloud's bounding-box
    diagonal (``bbox_diagonal``).
    """
    points = np.asarray(points, float).reshape(-1, 3)
    d = nearest_distances(faces, points)
    diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    out = {
        "points": int(len(points)),
        "rmse": float(np.sqrt(np.mean(d ** 2))),
        "max_error": float(d.max()),
        "mean_error": float(d.mean()),
    }
    for p, value in zip(PERCENTILES, np.percentile(d, PERCENTILES)):
        out[f"p{p}"] = float(value)
    out["bbox_diagonal"] = diag
    for key in ("rmse", "max_error", "mean_error", *(f"p{p}" for p in PERCENTILES)):
        out[f"{key}_relative"] = out[key] / diag if diag > 0 else None
    return out

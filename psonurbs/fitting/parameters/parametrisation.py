"""First parameters: the (u, v) in [0, 1]^2 of every point, and what all ways of making them share.

A :class:`Parametrisation` is the uv (N, 2) with a note of how they were made; plane
coordinates become parameters by :func:`unit_square` (the sides of their minimum-area
rectangle scaled to [0, 1]).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull, QhullError

FLAT = float(np.cos(np.radians(15.0)))  # |n . d| above this nearly everywhere: flat over the plane, its projection near-isometric
FILL_MARGIN = 0.03  # of the unit square's cells: above the jitter of a sampled boundary (8 of 256 cells)


@dataclass
class Parametrisation:
    uv: np.ndarray  # (N, 2) in [0, 1]^2
    info: dict = field(default_factory=dict)

    def swapped(self) -> "Parametrisation":
        """The same mapping with the roles of u and v exchanged."""
        return Parametrisation(self.uv[:, ::-1].copy(), {**self.info, "swapped": not self.info.get("swapped")})


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """Two unit vectors spanning the plane orthogonal to ``normal`` (rows)."""
    normal = normal / np.linalg.norm(normal)
    helper = np.eye(3)[np.argmin(np.abs(normal))]
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(normal, e1)])


def plane_bases(normals: np.ndarray) -> np.ndarray:
    """(N, 2, 3): :func:`plane_basis` for N directions (N, 3) at once, by the same rule
    (the first vector orthogonal to the coordinate axis the direction leans on least).
    plane_basis keeps its scalar operations: the fits depend on their last bits."""
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.eye(3)[np.argmin(np.abs(normals), axis=1)]
    e1 = np.cross(normals, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(normals, e1)], axis=1)


def min_area_rectangle(q: np.ndarray) -> np.ndarray:
    """2 x 2 rotation whose rows are the sides of the smallest rectangle around ``q``.

    The minimum-area enclosing rectangle has a side along an edge of the convex hull
    (Freeman & Shapira 1975), so every hull edge direction is tried.
    """
    try:
        hull = q[ConvexHull(q).vertices]
    except (QhullError, ValueError):
        return np.eye(2)
    edges = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    angles = np.arctan2(edges[:, 1], edges[:, 0]) % (np.pi / 2)
    c, s = np.cos(angles), np.sin(angles)
    x = hull @ np.stack([c, s])  # (h, E): coordinate along each candidate side
    y = hull @ np.stack([-s, c])
    area = np.ptp(x, axis=0) * np.ptp(y, axis=0)
    k = int(np.argmin(area))
    return np.array([[c[k], s[k]], [-s[k], c[k]]])


def cell_counts(uv: np.ndarray, cells: int) -> np.ndarray:
    """How many points fall in each cell of the cells x cells grid on [0, 1]^2."""
    idx = np.minimum((uv * cells).astype(int), cells - 1)
    return np.bincount(idx[:, 0] * cells + idx[:, 1], minlength=cells * cells)


def fill_cells(points: int) -> int:
    """The grid on which ``points`` parameters' :func:`fill` is judged: about 8 points a
    cell, 2 to 16 cells a side."""
    return int(np.clip(np.sqrt(points / 8.0), 2, 16))


def fill(uv: np.ndarray, cells: int) -> float:
    """Share of the cells x cells grid on [0, 1]^2 holding a point."""
    return float(np.mean(cell_counts(uv, cells) > 0))


def unit_square(q: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
    """Plane coordinates (N, 2) scaled onto [0, 1]^2 along the sides of the minimum-area
    rectangle around them (or around the ``reference`` points: the others are clipped),
    u along the longer side."""
    rect = q if reference is None else reference
    turn = min_area_rectangle(rect).T
    q, rect = q @ turn, rect @ turn
    lo, span = rect.min(axis=0), np.ptp(rect, axis=0)
    uv = (q - lo) / np.where(span > 0, span, 1.0)
    if span[1] > span[0]:  # u along the longer side
        uv = uv[:, ::-1]
    return np.clip(uv, 0.0, 1.0)

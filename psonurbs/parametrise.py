"""First parameters (u, v) in [0, 1]^2 for every point, by topology.

``open``: project on a plane and scale the footprint to the unit square. The PCA plane
is only a start: on a peaked height field it tilts far from the natural plane and
leaves cells of the square without data. So several planes are tried (the PCA plane,
the plane across the dominant direction of the local normals) and the one whose
footprint fills its minimum-area rectangle best wins; the rectangle's sides become
the u and v directions.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .organise import local_normals


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


def occupancy(uv: np.ndarray, cells: int) -> float:
    """Share of the cells of the grid that hold at least one point."""
    return float(np.mean(cell_counts(uv, cells) > 0))


def project_on_plane(points: np.ndarray, normal: np.ndarray) -> Parametrisation:
    q = points @ plane_basis(normal).T
    q = q @ min_area_rectangle(q).T
    lo, span = q.min(axis=0), np.ptp(q, axis=0)
    uv = (q - lo) / np.where(span > 0, span, 1.0)
    if span[1] > span[0]:  # u along the longer side
        uv = uv[:, ::-1]
    return Parametrisation(np.clip(uv, 0.0, 1.0), {"method": "plane", "normal": [float(c) for c in normal]})


def hemisphere_directions(count: int) -> np.ndarray:
    """``count`` nearly uniform unit vectors with z >= 0 (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1.0 - k / count
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def footprint_quality(points: np.ndarray, normal: np.ndarray, cells: int) -> tuple[float, float]:
    """(fill, spread) of the projection on the plane across ``normal``.

    fill: share of occupied cells of the footprint's rectangle; spread: coefficient of
    variation of the cell counts (0 for perfectly even sampling).
    """
    q = points @ plane_basis(normal).T
    q = q @ min_area_rectangle(q).T
    counts = cell_counts((q - q.min(axis=0)) / np.maximum(np.ptp(q, axis=0), 1e-300), cells)
    return float(np.mean(counts > 0)), float(np.std(counts) / np.mean(counts))


def best_plane(points: np.ndarray, candidates: np.ndarray, cells: int) -> tuple[np.ndarray, float]:
    """The candidate normal that fills best; within 2% of the best fill, the most even."""
    scores = np.array([footprint_quality(points, n, cells) for n in candidates])
    good = scores[:, 0] >= scores[:, 0].max() - 0.02
    k = int(np.argmin(np.where(good, scores[:, 1], np.inf)))
    return candidates[k], float(scores[k, 0])


def directions_around(normal: np.ndarray, radius: float, steps: int = 4) -> np.ndarray:
    """Unit vectors on a (2 steps + 1)^2 grid of tilts up to ``radius`` around ``normal``."""
    e = plane_basis(normal)
    t = np.linspace(-radius, radius, 2 * steps + 1)
    a, b = np.meshgrid(t, t, indexing="ij")
    d = normal[None, :] + a.reshape(-1, 1) * e[0] + b.reshape(-1, 1) * e[1]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def parametrise_open(points: np.ndarray, directions: int = 200, max_points: int = 4000) -> Parametrisation:
    """Projection on the plane whose footprint fills its rectangle best and most evenly.

    Candidates: the PCA normal, the dominant local-normal direction and a lattice of
    directions over the hemisphere, then two finer searches around the winner. The
    footprint fill decides; among planes that fill equally well (within 2%) the most
    even spread of points over the cells wins: the plane that distorts the sampling
    least. On a peaked height field this is the natural plane, not the tilted PCA one.
    """
    sample = points[:: max(1, len(points) // max_points)]
    _, _, vt = np.linalg.svd(sample - sample.mean(axis=0), full_matrices=False)
    normals = local_normals(sample)
    _, vecs = np.linalg.eigh(normals.T @ normals)
    cells = int(np.clip(np.sqrt(len(sample) / 8.0), 2, 16))
    normal, _ = best_plane(sample, np.vstack([vt[2], vecs[:, 2], hemisphere_directions(directions)]), cells)
    for radius in (0.1, 0.02):
        normal, fill = best_plane(sample, np.vstack([normal, directions_around(normal, radius)]), cells)
    best = project_on_plane(points, normal)
    best.info["footprint_fill"] = fill
    return best

"""First parameters of an open patch by projection on a plane, the footprint scaled to the unit square.

The PCA plane is only a start: on a peaked height field it tilts far from the natural
plane and leaves cells of the square without data. So several planes are tried (the PCA
plane, the plane across the dominant direction of the local normals, a lattice over the
hemisphere) and the one the surface faces most squarely wins; the sides of its
footprint's minimum-area rectangle become the u and v directions.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from psonurbs.fitting.prepare.organise import local_normals

from .parametrisation import FLAT, Parametrisation, cell_counts, min_area_rectangle, plane_basis, unit_square


def project_on_plane(points: np.ndarray, normal: np.ndarray) -> Parametrisation:
    return Parametrisation(unit_square(points @ plane_basis(normal).T),
                           {"method": "plane", "normal": [float(c) for c in normal]})


def hemisphere_directions(count: int) -> np.ndarray:
    """``count`` nearly uniform unit vectors with z >= 0 (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1.0 - k / count
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def footprint_quality(points: np.ndarray, normal: np.ndarray, cells: int) -> tuple[float, float]:
    """(fill, rectangularity) of the projection on the plane across ``normal``.

    fill: share of occupied cells of the footprint's minimum-area rectangle;
    rectangularity: convex hull area over rectangle area (1 when the footprint's
    outline is the rectangle, as for a height field over a rectangle seen square on).
    """
    q = points @ plane_basis(normal).T
    q = q @ min_area_rectangle(q).T
    extent = np.maximum(np.ptp(q, axis=0), 1e-300)
    counts = cell_counts((q - q.min(axis=0)) / extent, cells)
    try:
        hull_area = ConvexHull(q).volume
    except (QhullError, ValueError):
        hull_area = 0.0
    return float(np.mean(counts > 0)), float(hull_area / np.prod(extent))


def facing(normals: np.ndarray, direction: np.ndarray) -> float:
    """How squarely the surface faces ``direction``: the 5th percentile of |n . d| over
    the local normals. Near 0 where the projection folds or sees a wall edge-on."""
    return float(np.quantile(np.abs(normals @ direction), 0.05))


def best_plane(points: np.ndarray, normals: np.ndarray, candidates: np.ndarray, cells: int) -> np.ndarray:
    """The best projection normal among ``candidates``.

    Admissible: the surface faces it at least 80% as squarely as the best candidate
    (:func:`facing`; no folds, no flank seen edge-on). Among those whose footprint
    outline is as rectangular as the best (to 0.5%: a height field over a rectangle
    seen square on projects onto exactly its rectangle, a tilted view does not), the
    one the surface faces most squarely.
    """
    face = np.array([facing(normals, d) for d in candidates])
    admissible = np.flatnonzero(face >= 0.8 * face.max())
    rect = np.array([footprint_quality(points, candidates[k], cells)[1] for k in admissible])
    square = admissible[rect >= rect.max() - 0.005]
    return candidates[square[int(np.argmax(face[square]))]]


def directions_around(normal: np.ndarray, radius: float, steps: int = 4) -> np.ndarray:
    """Unit vectors on a (2 steps + 1)^2 grid of tilts up to ``radius`` around ``normal``."""
    e = plane_basis(normal)
    t = np.linspace(-radius, radius, 2 * steps + 1)
    a, b = np.meshgrid(t, t, indexing="ij")
    d = normal[None, :] + a.reshape(-1, 1) * e[0] + b.reshape(-1, 1) * e[1]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def parametrise_open(points: np.ndarray, directions: int = 200, max_points: int = 4000) -> Parametrisation:
    """Projection on the plane the surface faces most squarely, its footprint's
    minimum-area rectangle scaled to the unit square.

    The PCA plane is only a start: on a peaked height field it tilts far from the
    natural plane, folds the steep flanks and leaves cells of the square without data.
    The plane normal here maximises the 5th percentile of |n . d| over the local
    normals (:func:`facing`): the direction along which the surface is most surely a
    height field. Candidates: the PCA normal, the dominant normal direction and a
    lattice over the hemisphere, then finer searches around the winner. A flat surface
    (95% of its normals within 15 degrees of the PCA normal, :data:`FLAT`) is projected on
    its own plane: a view tilted up to the search's allowance would square a
    non-rectangular outline (an L seen 30 degrees off) at the cost of an oblique map.
    """
    sample = points[:: max(1, len(points) // max_points)]
    _, _, vt = np.linalg.svd(sample - sample.mean(axis=0), full_matrices=False)
    normals = local_normals(sample)
    _, vecs = np.linalg.eigh(normals.T @ normals)
    cells = int(np.clip(np.sqrt(len(sample) / 8.0), 2, 16))
    if facing(normals, vt[2]) >= FLAT:  # flat: its own plane, not a tilted view whose outline looks squarer
        normal = vt[2]
    else:
        normal = best_plane(sample, normals, np.vstack([vt[2], vecs[:, 2], hemisphere_directions(directions)]), cells)
        for radius in (0.1, 0.02, 0.004):
            normal = best_plane(sample, normals, np.vstack([normal, directions_around(normal, radius)]), cells)
    best = project_on_plane(points, normal)
    best.info["footprint_fill"], _ = footprint_quality(sample, normal, cells)
    best.info["facing"] = facing(normals, normal)
    return best

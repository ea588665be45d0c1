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
    lattice over the hemisphere, then finer searches around the winner.
    """
    sample = points[:: max(1, len(points) // max_points)]
    _, _, vt = np.linalg.svd(sample - sample.mean(axis=0), full_matrices=False)
    normals = local_normals(sample)
    _, vecs = np.linalg.eigh(normals.T @ normals)
    cells = int(np.clip(np.sqrt(len(sample) / 8.0), 2, 16))
    normal = best_plane(sample, normals, np.vstack([vt[2], vecs[:, 2], hemisphere_directions(directions)]), cells)
    for radius in (0.1, 0.02, 0.004):
        normal = best_plane(sample, normals, np.vstack([normal, directions_around(normal, radius)]), cells)
    best = project_on_plane(points, normal)
    best.info["footprint_fill"], _ = footprint_quality(sample, normal, cells)
    best.info["facing"] = facing(normals, normal)
    return best


# ---- closed topologies ------------------------------------------------------

def fit_circle(q: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle through 2D points (Kasa: linear in centre and r^2 - |c|^2)."""
    a = np.column_stack([2.0 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(a, np.sum(q * q, axis=1), rcond=None)
    centre = sol[:2]
    return centre, float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere (algebraic fit, linear in centre and r^2 - |c|^2)."""
    a = np.column_stack([2.0 * points, np.ones(len(points))])
    sol, *_ = np.linalg.lstsq(a, np.sum(points * points, axis=1), rcond=None)
    centre = sol[:3]
    return centre, float(np.sqrt(max(sol[3] + centre @ centre, 0.0)))


def frame_around(axis: np.ndarray) -> np.ndarray:
    """Rows e1, e2, axis: a right-handed orthonormal frame with the given third axis."""
    axis = axis / np.linalg.norm(axis)
    e1, e2 = plane_basis(axis)
    if np.dot(np.cross(e1, e2), axis) < 0:
        e2 = -e2
    return np.stack([e1, e2, axis])


def turn_fraction(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Angle of (x, y) as a fraction of a full turn, in [0, 1)."""
    return np.mod(np.arctan2(y, x) / (2.0 * np.pi), 1.0)


STRAY_SHARE = 0.005  # share of a cloud that may be strays when its extent is judged (gaps, poles)


def largest_gap(turns: np.ndarray, strays: float = STRAY_SHARE) -> tuple[float, float]:
    """(size, middle) of the widest arc of angles (given in turns) with at most a share
    ``strays`` of the points inside: the widest empty arc, a few stray points (a scan's
    background, a flying pixel) notwithstanding."""
    s = np.sort(turns)
    m = min(int(strays * len(s)) + 1, len(s))
    gaps = np.r_[s, s[:m] + 1.0][m:m + len(s)] - s
    k = int(np.argmax(gaps))
    return float(gaps[k]), float(np.mod(s[k] + gaps[k] / 2.0, 1.0))


def seam_at_gap(turns: np.ndarray) -> tuple[np.ndarray, float]:
    """Rotate angles so that the seam (0 = 1) sits in the middle of the widest gap."""
    gap, middle = largest_gap(turns)
    return np.mod(turns - middle, 1.0), gap


def cylinder_axis(points: np.ndarray) -> np.ndarray:
    """The direction most orthogonal to the local normals (normals of a cylinder are radial)."""
    normals = local_normals(points[:: max(1, len(points) // 4000)])
    _, vecs = np.linalg.eigh(normals.T @ normals)
    return vecs[:, 0]


def parametrise_cylinder(points: np.ndarray) -> Parametrisation:
    """u: angle around the axis (seam in the widest gap), v: height along the axis."""
    frame = frame_around(cylinder_axis(points))
    local = (points - points.mean(axis=0)) @ frame.T
    centre, radius = fit_circle(local[:, :2])
    u, gap = seam_at_gap(turn_fraction(local[:, 0] - centre[0], local[:, 1] - centre[1]))
    h = local[:, 2]
    v = (h - h.min()) / max(np.ptp(h), 1e-300)
    return Parametrisation(np.column_stack([u, v]), {
        "method": "cylinder", "axis": [float(c) for c in frame[2]], "radius": radius,
        "angular_gap": gap})


def sphere_axis(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Pole axis: along the mean direction for a cap, else the cloud's thinnest PCA axis."""
    d = points - centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    mean = d.mean(axis=0)
    if np.linalg.norm(mean) > 0.3:
        return mean / np.linalg.norm(mean)
    _, _, vt = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)
    return vt[2]


def parametrise_sphere(points: np.ndarray) -> Parametrisation:
    """u: longitude (seam in the widest gap), v: latitude from pole (0) to pole (1)."""
    centre, radius = fit_sphere(points)
    frame = frame_around(sphere_axis(points, centre))
    local = (points - centre) @ frame.T
    u, gap = seam_at_gap(turn_fraction(local[:, 0], local[:, 1]))
    r = np.maximum(np.linalg.norm(local, axis=1), 1e-300)
    v = np.arccos(np.clip(-local[:, 2] / r, -1.0, 1.0)) / np.pi
    return Parametrisation(np.column_stack([u, v]), {
        "method": "sphere", "centre": [float(c) for c in centre], "radius": radius,
        "axis": [float(c) for c in frame[2]], "angular_gap": gap,
        "latitude_range": [float(q) for q in np.quantile(v, [STRAY_SHARE, 1.0 - STRAY_SHARE])]})


def parametrise_torus(points: np.ndarray) -> Parametrisation:
    """u: angle around the axis, v: angle around the tube (both seams in their widest gap)."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    frame = frame_around(vt[2])
    local = (points - centroid) @ frame.T
    rho = np.hypot(local[:, 0], local[:, 1])
    major = float(np.median(rho))
    u, gap_u = seam_at_gap(turn_fraction(local[:, 0], local[:, 1]))
    v, gap_v = seam_at_gap(turn_fraction(rho - major, local[:, 2]))
    return Parametrisation(np.column_stack([u, v]), {
        "method": "torus", "axis": [float(c) for c in frame[2]], "major_radius": major,
        "angular_gaps": [gap_u, gap_v]})


PARAMETRISATIONS = {"open": parametrise_open, "cylinder": parametrise_cylinder,
                    "sphere": parametrise_sphere, "torus": parametrise_torus}


def parametrise(points: np.ndarray, topology: str) -> Parametrisation:
    """First (u, v) in [0, 1]^2 for every point, for the given topology."""
    return PARAMETRISATIONS[topology](points)

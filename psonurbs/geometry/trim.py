"""Trim loops in a surface's parameter domain: curves, inside tests, trimmed meshes, distances.

A trimmed surface is a NURBS surface S(u, v) and closed loops in its (u, v) domain; the
face is the part of the domain inside the loops by the even-odd rule. The first loop is
the outer boundary, counter-clockwise; the others are holes, clockwise (the face is on
the left of every loop). Each loop is a clamped B-spline curve of degree d,

    C(t) = sum_i N_i,d(t) P_i,   t in [0, 1],   P_0 = P_{n-1}  (closed),

and for d >= 2 with equal first and last spans also P_1 - P_0 = P_{n-1} - P_{n-2}, so it
is C1 where it closes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.interpolate import BSpline
from scipy.sparse.linalg import spsolve
from scipy.spatial import Delaunay, cKDTree

from psonurbs.geometry.basis import clamped_knots
from psonurbs.geometry.nurbs import NurbsSurface

__all__ = ["TrimLoop", "Trim", "fit_closed_curve", "polygon_loop", "inside", "crossing", "signed_area",
           "trimmed_mesh", "distances_to_boundary", "distances_to_face"]

LOOP_SAMPLES = 2000  # samples of a loop for inside tests and intersection checks


@dataclass(frozen=True)
class TrimLoop:
    """One closed loop: a clamped B-spline curve in the parameter domain."""

    degree: int
    knots: np.ndarray  # (n + degree + 1,), clamped on [0, 1]
    control_points: np.ndarray  # (n, 2), first == last

    def __post_init__(self):
        knots = np.asarray(self.knots, float)
        cps = np.asarray(self.control_points, float)
        object.__setattr__(self, "knots", knots)
        object.__setattr__(self, "control_points", cps)
        if cps.ndim != 2 or cps.shape[1] != 2 or len(knots) != len(cps) + self.degree + 1:
            raise ValueError(f"trim loop: {len(cps)} control points, {len(knots)} knots, degree {self.degree}")
        if not 1 <= self.degree <= 3 or np.any(np.diff(knots) < 0):
            raise ValueError("trim loop: degree 1 to 3 and non-decreasing knots")
        if not np.array_equal(cps[0], cps[-1]):
            raise ValueError("trim loop: not closed (first and last control points differ)")

    def evaluate(self, t: np.ndarray) -> np.ndarray:
        """Points C(t), shape (N, 2)."""
        return BSpline(self.knots, self.control_points, self.degree)(np.asarray(t, float))

    def polygon(self, samples: int = LOOP_SAMPLES) -> np.ndarray:
        """The loop sampled at ``samples`` equal parameter steps, (M, 2), the end not repeated; a
        degree-1 loop also at its knots (its corners), so that the polygon is the loop."""
        t0, t1 = self.knots[self.degree], self.knots[-self.degree - 1]
        t = np.linspace(t0, t1, samples + 1)[:-1]
        if self.degree == 1:
            t = np.union1d(t, self.knots[(self.knots > t0) & (self.knots < t1)])
        return self.evaluate(t)

    def to_dict(self) -> dict:
        return {"degree": int(self.degree), "knots": [float(k) for k in self.knots],
                "control_points": self.control_points.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "TrimLoop":
        return cls(int(d["degree"]), d["knots"], d["control_points"])


@dataclass(frozen=True)
class Trim:
    """The loops of a trimmed face: the outer boundary first, then the holes."""

    loops: tuple[TrimLoop, ...]

    def polygons(self, samples: int = LOOP_SAMPLES) -> list[np.ndarray]:
        return [loop.polygon(samples) for loop in self.loops]

    def contains(self, uv: np.ndarray) -> np.ndarray:
        """Mask (N,) of the parameters (N, 2) inside the face (even-odd over all loops)."""
        return inside(self.polygons(), uv)

    def to_list(self) -> list[dict]:
        return [loop.to_dict() for loop in self.loops]

    @classmethod
    def from_list(cls, loops: list[dict] | None) -> "Trim | None":
        """The trim of a JSON ``surface["trim"]``; ``None`` when there is none."""
        if not loops:
            return None
        return cls(tuple(TrimLoop.from_dict(d) for d in loops))


def signed_area(polygon: np.ndarray) -> float:
    """Shoelace area of a closed polygon (M, 2): positive when counter-clockwise."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def inside(polygons: list[np.ndarray], q: np.ndarray, bands: int = 64) -> np.ndarray:
    """Even-odd point-in-polygon over all ``polygons`` for the points ``q`` (N, 2).

    A point is inside when a ray towards +u crosses the polygons' edges an odd number
    of times (half-open in v: an edge counts for v in [min, max)). The edges are
    bucketed into horizontal bands so each point meets only the edges of its band.
    """
    q = np.asarray(q, float).reshape(-1, 2)
    out = np.zeros(len(q), bool)
    if not polygons or len(q) == 0:
        return out
    a = np.concatenate(polygons)
    b = np.concatenate([np.roll(p, -1, axis=0) for p in polygons])
    lo, hi = np.minimum(a[:, 1], b[:, 1]), np.maximum(a[:, 1], b[:, 1])
    edges = np.flatnonzero(hi > lo)  # horizontal edges never cross a horizontal ray
    y0, y1 = float(q[:, 1].min()), float(q[:, 1].max())
    cuts = np.linspace(y0, y1 + 1e-12 * max(1.0, abs(y1)), bands + 1)
    band_of = np.clip(np.searchsorted(cuts, q[:, 1], side="right") - 1, 0, bands - 1)
    for k in range(bands):
        pts = np.flatnonzero(band_of == k)
        if len(pts) == 0:
            continue
        e = edges[(hi[edges] > cuts[k]) & (lo[edges] <= cuts[k + 1])]
        if len(e) == 0:
            continue
        for s in range(0, len(pts), max(1, 2_000_000 // len(e))):
            idx = pts[s:s + max(1, 2_000_000 // len(e))]
            x, y = q[idx, :1], q[idx, 1:]
            ay, by = a[e, 1][None, :], b[e, 1][None, :]
            crosses = (ay > y) != (by > y)
            with np.errstate(divide="ignore", invalid="ignore"):
                xs = a[e, 0] + (y - ay) * (b[e, 0] - a[e, 0]) / (by - ay)
            out[idx] = (np.sum(crosses & (x < xs), axis=1) % 2) == 1
    return out


def crossing(polygons: list[np.ndarray]) -> bool:
    """Whether any two edges of the closed polygons cross or touch (adjacent edges of
    one polygon excepted): a loop that is not simple, or two loops that meet. Two edges
    on one line touch only where their extents along it overlap (a loop clamped to the
    domain runs along its edge in several collinear edges in a row, apart)."""
    a = np.concatenate(polygons)
    b = np.concatenate([np.roll(p, -1, axis=0) for p in polygons])
    owner = np.concatenate([np.full(len(p), k) for k, p in enumerate(polygons)])
    index = np.concatenate([np.arange(len(p)) for p in polygons])
    size = np.concatenate([np.full(len(p), len(p)) for p in polygons])
    reach = float(np.max(np.hypot(*(b - a).T)))
    pairs = cKDTree(0.5 * (a + b)).query_pairs(reach * 1.0000001, output_type="ndarray")
    if len(pairs) == 0:
        return False
    i, j = pairs[:, 0], pairs[:, 1]
    gap = np.abs(index[i] - index[j])
    adjacent = (owner[i] == owner[j]) & ((gap == 1) | (gap == size[i] - 1))
    i, j = i[~adjacent], j[~adjacent]

    def orient(p, q, r):
        return np.sign((q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0]))

    o1, o2 = orient(a[i], b[i], a[j]), orient(a[i], b[i], b[j])
    o3, o4 = orient(a[j], b[j], a[i]), orient(a[j], b[j], b[i])
    collinear = (o1 == 0) & (o2 == 0)
    lo = np.maximum(np.minimum(a[i], b[i]), np.minimum(a[j], b[j]))
    hi = np.minimum(np.maximum(a[i], b[i]), np.maximum(a[j], b[j]))
    overlap = np.all(lo <= hi, axis=1)  # the two edges' boxes meet: on one line, their extents do
    return bool(np.any((o1 * o2 <= 0) & (o3 * o4 <= 0) & (~collinear | overlap)))


def _closed_basis(n: int, degree: int) -> tuple[np.ndarray, sp.csr_array]:
    """Clamped uniform knots for ``n`` control points and the map from the free ones.

    Returns (knots, T) with the full control polygon ``P = T @ X``: ``X`` holds the start
    point Q, (for degree >= 2) the start tangent D, and the inner points, so that
    ``P_0 = P_{n-1} = Q`` and ``P_1 = Q + D``, ``P_{n-2} = Q - D``.
    """
    knots = clamped_knots(n, degree)
    if degree == 1:
        rows = list(range(n))
        cols = list(range(n - 1)) + [0]
        vals = [1.0] * n
        shape = (n, n - 1)
    else:
        rows, cols, vals = [0, n - 1, 1, 1, n - 2, n - 2], [0, 0, 0, 1, 0, 1], [1, 1, 1, 1, 1, -1]
        rows += list(range(2, n - 2))
        cols += list(range(2, n - 2))
        vals += [1.0] * (n - 4)
        shape = (n, n - 2)
    return knots, sp.csr_array((vals, (rows, cols)), shape=shape)


def fit_closed_curve(polygon: np.ndarray, n: int, degree: int = 3, smoothing: float = 1e-6,
                     bounds: tuple[tuple[float, float], tuple[float, float]] | None = None,
                     snap: tuple[float, float] = (0.0, 0.0)) -> TrimLoop:
    """Least-squares closed B-spline curve of ``n`` control points through a closed polygon.

    The polygon's vertices (M, 2) are given chord-length parameters on [0, 1) (its
    first vertex at t = 0 = 1); the control polygon is found from
    ``min |B T X - y|^2 + smoothing L^2 |D2 T X|^2`` (D2 the second differences of the
    control polygon, L its length scale). With ``bounds`` ((u0, u1), (v0, v1)) the
    control points are clamped into the rectangle, which holds the curve there too
    (a B-spline lies in the convex hull of its control points), and those within
    ``snap`` (per direction) of its sides moved onto them: where ``degree + 1`` in a row
    are on a side, so is the curve.
    """
    p = np.asarray(polygon, float)
    seg = np.hypot(*(np.roll(p, -1, axis=0) - p).T)
    total = float(seg.sum())
    t = np.concatenate([[0.0], np.cumsum(seg)]) / total  # the polygon closed: t = 1 is the first vertex again
    y = np.concatenate([p, p[:1]])
    min_n = degree + 1 if degree == 1 else max(degree + 1, 5)
    n = max(int(n), min_n)
    knots, T = _closed_basis(n, degree)
    B = BSpline.design_matrix(np.clip(t, 0.0, 1.0), knots, degree)
    A = (B @ T).tocsc()
    D2 = sp.diags([np.ones(n - 2), -2 * np.ones(n - 2), np.ones(n - 2)], [0, 1, 2], shape=(n - 2, n))
    R = (D2 @ T).tocsc()
    lhs = (A.T @ A + smoothing * len(t) * (R.T @ R)).tocsc()
    lhs = lhs + 1e-12 * lhs.diagonal().mean() * sp.eye(lhs.shape[0], format="csc")
    x = spsolve(lhs, A.T @ y)
    cps = T @ x
    if bounds is not None:
        for k in (0, 1):
            lo, hi = bounds[k]
            c = np.clip(cps[:, k], lo, hi)
            c[c <= lo + snap[k]] = lo
            c[c >= hi - snap[k]] = hi
            cps[:, k] = c
    cps[-1] = cps[0]
    return TrimLoop(degree, knots, cps)


def polygon_loop(polygon: np.ndarray) -> TrimLoop:
    """The closed polygon (M, 2) itself as a degree-1 loop: knots at its chord lengths."""
    p = np.asarray(polygon, float)
    p = p[np.any(p != np.roll(p, -1, axis=0), axis=1)]  # no repeated vertex (a zero-length edge)
    seg = np.hypot(*(np.roll(p, -1, axis=0) - p).T)
    t = np.minimum(np.concatenate([[0.0], np.cumsum(seg)]) / float(seg.sum()), 1.0)
    knots = np.concatenate([[0.0], t[:-1], [1.0, 1.0]])
    return TrimLoop(1, knots, np.concatenate([p, p[:1]]))


def trimmed_mesh(surface: NurbsSurface, trim: Trim, n_u: int, n_v: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle mesh of the trimmed surface: (vertices (N, 3), triangles (K, 3), their uv (N, 2)).

    The vertices are the n_u x n_v parameter grid's points inside the face that are at
    least half a cell from every loop, and the loops sampled at about half a cell; they
    are triangulated (Delaunay, in the parameter domain) and a triangle is kept when
    its centroid is inside the face. The mesh's boundary therefore runs along the
    loops, within the chord of half a cell. Triangles are counter-clockwise in (u, v),
    as those of :meth:`NurbsSurface.tessellate`.
    """
    us, vs = surface.parameter_grid(n_u, n_v)
    (u0, u1), (v0, v1) = surface.domain_u, surface.domain_v
    cell = min((u1 - u0) / (n_u - 1), (v1 - v0) / (n_v - 1))
    boundary = []
    for loop in trim.loops:
        dense = loop.polygon(LOOP_SAMPLES)
        length = float(np.sum(np.hypot(*(np.roll(dense, -1, axis=0) - dense).T)))
        boundary.append(loop.polygon(max(16, int(np.ceil(2.0 * length / cell)))))
    edge_points = np.concatenate(boundary)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    grid = np.stack([uu.ravel(), vv.ravel()], axis=1)
    polygons = trim.polygons()
    keep = inside(polygons, grid)
    keep[keep] = cKDTree(edge_points).query(grid[keep])[0] > 0.5 * cell
    uv = np.concatenate([grid[keep], edge_points])
    uv[:, 0] = np.clip(uv[:, 0], u0, u1)
    uv[:, 1] = np.clip(uv[:, 1], v0, v1)
    tri = Delaunay(uv).simplices
    a, b, c = uv[tri[:, 0]], uv[tri[:, 1]], uv[tri[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    tri = np.where((cross < 0)[:, None], tri[:, [0, 2, 1]], tri)
    centroid = (a + b + c) / 3.0
    tri = tri[inside(polygons, centroid) & (np.abs(cross) > 1e-14 * cell * cell)]
    used = np.unique(tri)
    renumber = np.full(len(uv), -1)
    renumber[used] = np.arange(len(used))
    uv = uv[used]
    return surface.evaluate(uv[:, 0], uv[:, 1]), renumber[tri].astype(np.int64), uv


def distances_to_boundary(surface: NurbsSurface, trim: Trim, points: np.ndarray,
                          samples: int = 4 * LOOP_SAMPLES) -> np.ndarray:
    """Distance of each point (N, 3) to the face's boundary curves S(C_k(t)) in space.

    Each boundary is sampled densely; a point's distance is the least to the two
    chords beside its nearest sample. For a point whose foot point on the untrimmed
    surface is outside the face, this is its distance to the trimmed surface.
    """
    best = np.full(len(points), np.inf)
    for loop in trim.loops:
        uv = loop.polygon(samples)
        curve = surface.evaluate(uv[:, 0], uv[:, 1])
        k = cKDTree(curve).query(points)[1]
        for step in (-1, 1):
            a, b = curve[k], curve[(k + step) % len(curve)]
            ab = b - a
            s = np.clip(np.sum((points - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0, 1)
            best = np.minimum(best, np.linalg.norm(points - (a + s[:, None] * ab), axis=1))
    return best


def distances_to_face(surface: NurbsSurface, trim: Trim, points: np.ndarray, uv: np.ndarray,
                      distances: np.ndarray) -> np.ndarray:
    """Distances (N,) of the points to the trimmed surface, from their foot points uv (N, 2)
    and distances on the untrimmed one: unchanged where the foot point is on the face,
    else the distance to the face's boundary (:func:`distances_to_boundary`)."""
    out = np.array(distances, float)
    off = ~trim.contains(uv)
    if off.any():
        out[off] = np.maximum(out[off], distances_to_boundary(surface, trim, points[off]))
    return out

#!/usr/bin/env python3
"""Score a fit independently of psonurbs: the JSON's NURBS re-evaluated with scipy alone.

    python benchmarks/score.py CLOUD OUTDIR [--gt CASE.gt.npz] [--stem NAME] [--res 301]

Reads CLOUD (.ply or text x y z) and, from OUTDIR, what ``psonurbs fit`` wrote for it:
STEM.json (the surface), STEM.ply (its mesh) and STEM_error.csv (the error curve). Nothing
of psonurbs is imported: the surface is evaluated from the JSON with
``scipy.interpolate.BSpline`` (values and first and second derivatives, in homogeneous
coordinates), the PLY files are parsed here, and distances are measured exactly:

* to the surface, by the closest point: the nearest of a dense parameter grid, then
  projected Newton steps on |S(u, v) - q|^2 (second derivatives; a point beyond an open
  edge slides along it; closed directions wrap), never worse than the grid sample;
* to a triangle mesh (the ground truth, the tool's mesh), by the exact point-triangle
  distance to the triangles around the nearest vertices, with a check that no other
  triangle can be nearer (a wider search where it could).

Prints one JSON line; every distance is relative to the cloud's bounding-box diagonal:
  rmse, p99, max          cloud -> surface (root mean square, 99th percentile, maximum)
  claimed_rmse            the JSON's metrics.rmse over the diagonal, for comparison
  inlier_rmse, inliers    as rmse, on the points within 4 noise sigmas of the truth (1e-4 if noise-free)
                          (cases with outliers, --gt)
  truth_rms, truth_max    surface (a res x res parameter grid) -> true surface (--gt)
  truth_sigma             truth_rms over the noise sigma (--gt, noisy cases)
  cover_rms, cover_max    true surface (its vertices) -> fitted surface (--gt)
  overhang                share of the parameter grid farther than 2% of the diagonal
                          from every cloud point (surface where there are no data)
  mesh_vs_nurbs           largest distance between the tool's mesh and the surface, both
                          ways: the tool evaluates and tessellates its NURBS right
  seam_u, seam_v          gap across a seam the JSON declares closed
  pole_spread             "topology": "sphere": how far each end row of the open direction
                          is from collapsing to a point
  curve_ok                the error curve has >= 2 rows and its "best" column never rises
  spacing                 the median over the points of their local spacing, a point's mean
                          distance to its 6 nearest neighbours; the points here and below are
                          the cloud's, or only its inliers when the truth has outliers (--gt)
  overrun_max, overrun_p95
                          where the data end, the surface should end: its boundary (each trim
                          loop, or the domain's edges but a closed direction's seam and an
                          edge collapsed to a point) sampled evenly in arc length on the
                          surface, each sample's distance to the nearest point over that
                          point's local spacing (a count of spacings, not a share of the
                          diagonal); the largest, and the 95th percentile by arc length
  cover_max_sp            cover_max over spacing (--gt): the truth left uncovered, in spacings
  sample_cover_sp         the truth's farthest vertex from the points, over spacing (--gt): what a
                          surface ending at its data would leave uncovered, the sample's own gaps
  bare_share              share of the untrimmed surface's area (|S_u x S_v|, grid weights)
                          farther from the nearest point than 3 of that point's local spacings
  trimmed                 whether "surface" has "trim" loops: closed B-spline curves
                          {"degree", "knots", "control_points": [[u, v], ...]} in the
                          parameter domain, the first the outer boundary, the others holes.
                          Every figure is then taken on the trimmed surface (even-odd rule
                          over all loops); STEM.ply is expected to be the trimmed mesh.
A JSON of several faces (``"surfaces"``, ``psonurbs fit --patches auto``) is scored as one
object (:func:`score_object`): rmse, p99, max to the nearest trimmed face, far_max (the
farthest point from every face in median spacings of the points, nearest-neighbour
distances), faces, and with --gt truth_rms, truth_max (the faces' samples to the truth) and
cover_max (the truth's vertices to the nearest face).

Exit status 0 when it could score, 2 when an output is missing or malformed.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

OVERHANG = 0.02  # of the diagonal
INLIER_SIGMAS = 4.0
# of the diagonal: a noise-free cloud's inliers lie within the truth triangulation's chords
# of it (up to 3e-5 on the benchmark's 241 x 241 truths), not on it
TRUTH_CHORD = 1e-4
NEIGHBOURS = 6  # a point's local spacing: its mean distance to this many nearest neighbours
BARE_SPACINGS = 3.0  # surface farther than this many local spacings from the data is bare
BOUNDARY_SAMPLES = 2000  # per trim loop or domain edge


# ---- files -------------------------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices (N, 3) and triangles (M, 3) (None without faces) of a PLY file."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    body = data[data.index(b"\n", end) + 1:]
    elements: list[tuple[str, int, list[tuple]]] = []
    fmt = "ascii"
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            props = elements[-1][2]
            if words[1] == "list":
                props.append((words[4], "list", _PLY_TYPES[words[2]], _PLY_TYPES[words[3]]))
            else:
                props.append((words[2], _PLY_TYPES[words[1]]))
    if fmt == "ascii":
        return _ply_ascii(body, elements)
    order = "<" if fmt == "binary_little_endian" else ">"
    vertices, triangles, offset = None, None, 0
    for name, count, props in elements:
        if any(p[1] == "list" for p in props):  # faces: triangles expected (count 3 each)
            (label, _, count_type, index_type), = props
            dtype = np.dtype([("n", order + count_type), ("i", order + index_type, (3,))])
            records = np.frombuffer(body, dtype, count, offset)
            if np.any(records["n"] != 3):
                raise ValueError(f"{path}: faces other than triangles")
            offset += dtype.itemsize * count
            if name == "face":
                triangles = records["i"].astype(np.int64)
            continue
        dtype = np.dtype([(p[0], order + p[1]) for p in props])
        records = np.frombuffer(body, dtype, count, offset)
        offset += dtype.itemsize * count
        if name == "vertex":
            vertices = np.column_stack([records[c].astype(np.float64) for c in "xyz"])
    if vertices is None:
        raise ValueError(f"{path}: no vertices")
    return vertices, triangles


def _ply_ascii(body: bytes, elements) -> tuple[np.ndarray, np.ndarray | None]:
    lines = iter(body.decode("ascii").splitlines())
    vertices, triangles = None, None
    for name, count, props in elements:
        rows = [next(lines).split() for _ in range(count)]
        if name == "vertex":
            names = [p[0] for p in props]
            vertices = np.array([[float(r[names.index(c)]) for c in "xyz"] for r in rows]).reshape(-1, 3)
        elif name == "face":
            triangles = np.array([[int(x) for x in r[1:4]] for r in rows], np.int64).reshape(-1, 3)
    return vertices, triangles


def read_points(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".ply":
        return read_ply(path)[0]
    return np.loadtxt(path, usecols=(0, 1, 2), ndmin=2, comments="#")


def curve_ok(path: Path) -> bool:
    if not path.exists():
        return False
    with path.open() as f:
        rows = [r for r in csv.reader(f) if r]
    if len(rows) < 3:
        return False
    header = [h.strip().lower() for h in rows[0]]
    column = next((i for i, h in enumerate(header) if "best" in h), 1)
    best = np.array([float(r[column]) for r in rows[1:]])
    return len(best) >= 2 and bool(np.all(best[1:] <= best[:-1] * (1 + 1e-9) + 1e-300))


# ---- the surface, evaluated with scipy ------------------------------------------------------

class Direction:
    """One parameter direction: its basis functions and their first two derivatives."""

    def __init__(self, knots, degree: int, closed: bool):
        self.knots = np.asarray(knots, float)
        self.degree = int(degree)
        self.closed = bool(closed)
        self.count = len(self.knots) - self.degree - 1
        self.lo, self.hi = self.knots[self.degree], self.knots[self.count]
        unit = BSpline(self.knots, np.eye(self.count), self.degree, extrapolate=False)
        self.splines = [unit, unit.derivative(1), unit.derivative(2)] if self.degree >= 2 else \
            [unit, unit.derivative(1)]

    def clamp(self, x: np.ndarray) -> np.ndarray:
        if self.closed:
            return self.lo + np.mod(x - self.lo, self.hi - self.lo)
        return np.clip(x, self.lo, self.hi)

    def basis(self, x: np.ndarray, order: int) -> list[np.ndarray]:
        """Basis values (N, count) and derivatives up to ``order`` at x (inside the domain)."""
        x = np.clip(np.asarray(x, float), self.lo, self.hi)
        out = []
        for d in range(order + 1):
            if d < len(self.splines):
                b = self.splines[d](x)
                out.append(np.nan_to_num(b, nan=0.0))
            else:
                out.append(np.zeros((len(x), self.count)))
        # the domain's right end belongs to the last span (extrapolate=False gives NaN there)
        end = x >= self.hi
        if np.any(end):
            ends = [self.splines[d](np.nextafter(self.hi, self.lo)) if d < len(self.splines)
                    else np.zeros(self.count) for d in range(order + 1)]
            for d in range(order + 1):
                out[d][end] = np.nan_to_num(ends[d], nan=0.0)
        return out


class Surface:
    """The NURBS of a psonurbs JSON ``surface``: S = sum N_i N_j w_ij P_ij / sum N_i N_j w_ij."""

    def __init__(self, doc: dict):
        points = np.asarray(doc["control_points"], float)
        nu, nv = points.shape[:2]
        weights = np.asarray(doc.get("weights", np.ones((nu, nv))), float).reshape(nu, nv)
        self.u = Direction(doc["knots_u"], doc["degree_u"], doc.get("closed_u", False))
        self.v = Direction(doc["knots_v"], doc["degree_v"], doc.get("closed_v", False))
        if (self.u.count, self.v.count) != (nu, nv):
            raise ValueError(f"knot vectors of {len(self.u.knots)} and {len(self.v.knots)} knots do not fit a "
                             f"{nu} x {nv} net of degrees {self.u.degree}, {self.v.degree}")
        if np.any(np.diff(self.u.knots) < 0) or np.any(np.diff(self.v.knots) < 0):
            raise ValueError("knot vectors must be non-decreasing")
        if np.any(weights <= 0):
            raise ValueError("weights must be positive")
        self.homogeneous = np.concatenate([points * weights[..., None], weights[..., None]], -1)  # (nu, nv, 4)
        self.trim = [TrimLoop(loop) for loop in doc.get("trim") or []]

    def parameters(self, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit-square coordinates to the surface's own domain."""
        return (self.u.lo + (self.u.hi - self.u.lo) * np.asarray(s, float),
                self.v.lo + (self.v.hi - self.v.lo) * np.asarray(t, float))

    def grid(self, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
        """S on the tensor grid us x vs: (len(us), len(vs), 3)."""
        bu, bv = self.u.basis(us, 0)[0], self.v.basis(vs, 0)[0]
        h = np.einsum("ai,ijc,bj->abc", bu, self.homogeneous, bv)
        return h[..., :3] / h[..., 3:]

    def grid_tangents(self, us: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """S_u and S_v on the tensor grid us x vs, each (len(us), len(vs), 3)."""
        bu, dbu = self.u.basis(us, 1)
        bv, dbv = self.v.basis(vs, 1)
        h, hu, hv = (np.einsum("ai,ijc,bj->abc", a, self.homogeneous, b) for a, b in ((bu, bv), (dbu, bv), (bu, dbv)))
        w = h[..., 3:]
        s = h[..., :3] / w
        return (hu[..., :3] - hu[..., 3:] * s) / w, (hv[..., :3] - hv[..., 3:] * s) / w

    def at(self, u: np.ndarray, v: np.ndarray, derivatives: bool = False):
        """S at the pairs (u_k, v_k): (N, 3); with ``derivatives`` also
        (S_u, S_v, S_uu, S_uv, S_vv) by the quotient rule on the homogeneous sums."""
        order = 2 if derivatives else 0
        bu, bv = self.u.basis(u, order), self.v.basis(v, order)
        nu, nv = self.homogeneous.shape[:2]
        flat = self.homogeneous.reshape(nu, nv * 4)

        def h(a: int, b: int) -> np.ndarray:
            return np.einsum("rj,rjc->rc", bv[b], (bu[a] @ flat).reshape(-1, nv, 4))

        h00 = h(0, 0)
        w = h00[:, 3:]
        s = h00[:, :3] / w
        if not derivatives:
            return s
        h10, h01, h20, h11, h02 = h(1, 0), h(0, 1), h(2, 0), h(1, 1), h(0, 2)
        su = (h10[:, :3] - h10[:, 3:] * s) / w
        sv = (h01[:, :3] - h01[:, 3:] * s) / w
        suu = (h20[:, :3] - 2 * h10[:, 3:] * su - h20[:, 3:] * s) / w
        suv = (h11[:, :3] - h10[:, 3:] * sv - h01[:, 3:] * su - h11[:, 3:] * s) / w
        svv = (h02[:, :3] - 2 * h01[:, 3:] * sv - h02[:, 3:] * s) / w
        return s, su, sv, suu, suv, svv

    def inside(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Whether (u, v) lies on the trimmed surface (all True when untrimmed)."""
        if not self.trim:
            return np.ones(len(u), bool)
        return even_odd([loop.polygon for loop in self.trim], np.column_stack([u, v]))


@dataclass
class TrimLoop:
    """A closed B-spline curve in the parameter domain, sampled densely as a polygon."""

    polygon: np.ndarray

    def __init__(self, loop: dict, samples: int = 4000):
        degree = int(loop["degree"])
        knots = np.asarray(loop["knots"], float)
        points = np.asarray(loop["control_points"], float)
        if points.ndim != 2 or points.shape[1] != 2 or len(knots) != len(points) + degree + 1:
            raise ValueError(f"trim loop of {len(points)} control points, {len(knots)} knots, degree {degree}")
        t = np.linspace(knots[degree], knots[len(points)], samples)
        self.polygon = BSpline(knots, points, degree)(t)


def even_odd(polygons: list[np.ndarray], q: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Even-odd rule over all polygons: a point is inside when a ray to +u crosses an odd
    number of edges."""
    a = np.concatenate(polygons)
    b = np.concatenate([np.roll(p, -1, axis=0) for p in polygons])
    keep = a[:, 1] != b[:, 1]  # horizontal edges are never crossed
    a, b = a[keep], b[keep]
    slope = (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    inside = np.zeros(len(q), bool)
    for start in range(0, len(q), chunk):
        u, v = q[start:start + chunk, :1], q[start:start + chunk, 1:]
        straddles = (a[:, 1] <= v) != (b[:, 1] <= v)
        crossing_u = a[:, 0] + (v - a[:, 1]) * slope
        inside[start:start + chunk] = (np.count_nonzero(straddles & (crossing_u > u), axis=1) % 2) == 1
    return inside


def distance_to_polygons(polygons: list[np.ndarray], q: np.ndarray) -> np.ndarray:
    """Distance in the parameter plane from each point of q to the nearest polygon vertex."""
    return cKDTree(np.concatenate(polygons)).query(q)[0]


# ---- where the data end ----------------------------------------------------------------------

def local_spacing(points: np.ndarray, k: int = NEIGHBOURS) -> np.ndarray:
    """Each point's mean distance to its k nearest other points (N,)."""
    k = min(k, len(points) - 1)
    if k < 1:
        return np.zeros(len(points))
    d = cKDTree(points).query(points, k=k + 1)[0]
    return d[:, 1:].mean(axis=1)  # the first column is the point itself (or a copy of it)


def boundary(surface: Surface, diag: float, samples: int = BOUNDARY_SAMPLES,
             dense: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """The surface's boundary: points on the surface and the arc length each stands for.

    Each trim loop's polygon, or (untrimmed) each edge of the parameter domain but those of
    a closed direction (its seam) and those shorter than 1e-9 of the diagonal (a pole),
    resampled to ``samples`` points evenly in arc length on the surface."""
    if surface.trim:
        curves = [loop.polygon for loop in surface.trim]
    else:
        t = np.linspace(0.0, 1.0, dense)
        us, vs = surface.parameters(t, t)
        u, v = surface.u, surface.v
        curves = [] if u.closed else [np.column_stack([np.full(dense, x), vs]) for x in (u.lo, u.hi)]
        curves += [] if v.closed else [np.column_stack([us, np.full(dense, y)]) for y in (v.lo, v.hi)]
    points, lengths = [], []
    for uv in curves:
        u, v = surface.u.clamp(uv[:, 0]), surface.v.clamp(uv[:, 1])
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(surface.at(u, v), axis=0), axis=1))])
        if along[-1] < 1e-9 * diag:
            continue
        s = np.linspace(0.0, along[-1], samples)
        # interpolated in the polygon's own (u, v), not across a closed direction's wrap
        points.append(surface.at(surface.u.clamp(np.interp(s, along, uv[:, 0])),
                                 surface.v.clamp(np.interp(s, along, uv[:, 1]))))
        lengths.append(np.full(samples, along[-1] / samples))
    if not points:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(points), np.concatenate(lengths)


def weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The least value below which at least a share q of the weight lies."""
    order = np.argsort(values, kind="stable")
    total = np.cumsum(weights[order])
    return float(values[order][min(np.searchsorted(total, q * total[-1]), len(values) - 1)])


def edge_figures(surface: Surface, grid: np.ndarray, us: np.ndarray, vs: np.ndarray, support: np.ndarray,
                 diag: float) -> dict:
    """spacing, overrun_max, overrun_p95 and bare_share (see the module) against the
    points ``support``; ``grid`` is the untrimmed surface on us x vs."""
    if len(support) < 2:
        return {}
    spacing = local_spacing(support)
    floor = 1e-12 * diag  # a point with 6 copies of itself has no spacing
    tree = cKDTree(support)
    out = {"spacing": float(np.median(spacing)) / diag}
    rim, lengths = boundary(surface, diag)
    if len(rim):
        d, nearest = tree.query(rim)
        ratio = d / np.maximum(spacing[nearest], floor)
        out.update(overrun_max=float(ratio.max()), overrun_p95=weighted_quantile(ratio, lengths, 0.95))
    su, sv = surface.grid_tangents(us, vs)
    wu, wv = (np.r_[0.5, np.ones(len(x) - 2), 0.5] * np.diff(x).mean() for x in (us, vs))  # trapezoid
    area = (np.linalg.norm(np.cross(su, sv), axis=2) * np.outer(wu, wv)).ravel()
    if area.sum() > 0:
        d, nearest = tree.query(grid.reshape(-1, 3))
        bare = d > BARE_SPACINGS * np.maximum(spacing[nearest], floor)
        out["bare_share"] = float(area[bare].sum() / area.sum())
    return out


# ---- closest points on the surface ----------------------------------------------------------

POLE_STARTS = 16  # Newton's starts for a point whose foot search ended on a pole


class SurfaceDistance:
    """Distance from points to the (trimmed) surface, by the closest point (see the module)."""

    def __init__(self, surface: Surface, start: int = 201, trimmed: bool = True):
        self.surface = surface
        self.trimmed = trimmed and bool(surface.trim)
        n = max(start, 8 * max(surface.u.count, surface.v.count))
        us, vs = surface.parameters(np.linspace(0, 1, n), np.linspace(0, 1, n))
        uu, vv = np.meshgrid(us, vs, indexing="ij")
        self.params = np.column_stack([uu.ravel(), vv.ravel()])
        points = surface.grid(us, vs).reshape(-1, 3)
        if self.trimmed:
            keep = surface.inside(*self.params.T)
            self.params, points = self.params[keep], points[keep]
            rim = np.concatenate([loop.polygon for loop in surface.trim])  # the loops' image on the surface
            self.rim = cKDTree(surface.at(rim[:, 0], rim[:, 1]))
        self.samples = points
        self.tree = cKDTree(points)
        # Newton starts from the nearest sample off a row collapsed to a point (a pole): at
        # the pole every u is the same point, and a start at the wrong one pushes out of the domain
        rows = points.reshape(len(us), -1, 3) if not self.trimmed else None
        seeds = np.ones(len(points), bool)
        if rows is not None:
            extent = float(np.ptp(points, axis=0).max()) or 1.0
            for j in (0, rows.shape[1] - 1):
                if np.ptp(rows[:, j], axis=0).max() <= 1e-9 * extent:
                    seeds.reshape(len(us), -1)[:, j] = False
        self.seed_params = self.params[seeds]
        self.seed_tree = cKDTree(points[seeds]) if not seeds.all() else self.tree
        self.poles = not seeds.all()

    def __call__(self, q: np.ndarray, chunk: int = 20000) -> np.ndarray:
        q = np.asarray(q, float)
        return np.concatenate([self._chunk(q[i:i + chunk]) for i in range(0, len(q), chunk)]) if len(q) else \
            np.zeros(0)

    def _chunk(self, q: np.ndarray) -> np.ndarray:
        d0, nearest = self.tree.query(q)
        if self.poles:  # the nearest sample off the poles instead
            nearest = self.seed_tree.query(q)[1]
        u, v = self.seed_params[nearest].T.copy()
        u, v = self._newton(q, u, v)
        d = np.linalg.norm(self.surface.at(u, v) - q, axis=1)
        if self.poles:  # ended on a pole: from the other sides of it too (the foot may lie across it)
            ended = np.flatnonzero((v <= self.surface.v.lo) | (v >= self.surface.v.hi))
            if len(ended):
                starts = self.seed_tree.query(q[ended], k=POLE_STARTS)[1]
                for k in range(POLE_STARTS):
                    su, sv = self.seed_params[starts[:, k]].T.copy()
                    su, sv = self._newton(q[ended], su, sv)
                    d[ended] = np.minimum(d[ended], np.linalg.norm(self.surface.at(su, sv) - q[ended], axis=1))
        if self.trimmed:
            off = ~self.surface.inside(u, v)
            d[off] = np.minimum(d0[off], self.rim.query(q[off])[0])
        return np.minimum(d, d0)

    def _newton(self, q, u, v, rounds: int = 40):
        su_dir, sv_dir = self.surface.u, self.surface.v
        active = np.ones(len(q), bool)
        for _ in range(rounds):
            if not active.any():
                break
            idx = np.flatnonzero(active)
            s, su, sv, suu, suv, svv = self.surface.at(u[idx], v[idx], derivatives=True)
            r = s - q[idx]
            f = np.einsum("ij,ij->i", r, r)
            g = np.column_stack([np.einsum("ij,ij->i", r, su), np.einsum("ij,ij->i", r, sv)])
            a = np.einsum("ij,ij->i", su, su)
            b = np.einsum("ij,ij->i", su, sv)
            c = np.einsum("ij,ij->i", sv, sv)
            an, bn, cn = a + np.einsum("ij,ij->i", r, suu), b + np.einsum("ij,ij->i", r, suv), \
                c + np.einsum("ij,ij->i", r, svv)
            newton = (an > 0) & (an * cn - bn * bn > 0)
            a, b, c = np.where(newton, an, a), np.where(newton, bn, b), np.where(newton, cn, c)
            scale = 1e-12 * (a + c) + 1e-300
            a, c = a + scale, c + scale
            det = a * c - b * b
            du = -(c * g[:, 0] - b * g[:, 1]) / det
            dv = -(a * g[:, 1] - b * g[:, 0]) / det
            # an open edge that the step pushes against holds: slide along it (1D Newton)
            stuck_u = (((u[idx] <= su_dir.lo) & (du < 0)) | ((u[idx] >= su_dir.hi) & (du > 0))) & (not su_dir.closed)
            stuck_v = (((v[idx] <= sv_dir.lo) & (dv < 0)) | ((v[idx] >= sv_dir.hi) & (dv > 0))) & (not sv_dir.closed)
            du = np.where(stuck_u, 0.0, np.where(stuck_v, -g[:, 0] / a, du))
            dv = np.where(stuck_v, 0.0, np.where(stuck_u, -g[:, 1] / c, dv))
            step = np.ones(len(idx))
            accepted = np.zeros(len(idx), bool)
            nu_, nv_ = u[idx].copy(), v[idx].copy()
            for _ in range(10):  # backtracking: the distance never grows
                tu, tv = su_dir.clamp(u[idx] + step * du), sv_dir.clamp(v[idx] + step * dv)
                rt = self.surface.at(tu, tv) - q[idx]
                better = ~accepted & (np.einsum("ij,ij->i", rt, rt) <= f)
                nu_[better], nv_[better] = tu[better], tv[better]
                accepted |= better
                if accepted.all():
                    break
                step = np.where(accepted, step, step / 2)
            span = 1e-14 * np.maximum(su_dir.hi - su_dir.lo, sv_dir.hi - sv_dir.lo)
            moved = np.abs(nu_ - u[idx]) + np.abs(nv_ - v[idx])
            u[idx], v[idx] = nu_, nv_
            active[idx[~accepted | (moved <= span)]] = False
        return u, v


# ---- distances to a triangle mesh ------------------------------------------------------------

def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact distance from points p to triangles (a, b, c), all (..., 3): the closest point
    by the Voronoi regions of the vertices, edges and face (Ericson, Real-Time Collision
    Detection, 5.1.5); degenerate triangles fall back to their edges."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("...i,...i", ab, ap), np.einsum("...i,...i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("...i,...i", ab, bp), np.einsum("...i,...i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("...i,...i", ab, cp), np.einsum("...i,...i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        closest = a + ab * v[..., None] + ac * w[..., None]  # inside the face
    face = (va >= 0) & (vb >= 0) & (vc >= 0) & (denom > 0)
    best = np.where(face, np.linalg.norm(p - np.where(face[..., None], closest, p), axis=-1), np.inf)
    for e0, e1 in ((a, b), (b, c), (c, a)):  # the edges and, at their ends, the vertices
        edge = e1 - e0
        length2 = np.einsum("...i,...i", edge, edge)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip(np.where(length2 > 0, np.einsum("...i,...i", p - e0, edge) / length2, 0.0), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(p - (e0 + edge * t[..., None]), axis=-1))
    return best


class MeshDistance:
    """Exact distance from points to a triangle mesh.

    First the exact point-triangle distance d to every triangle around the point's k
    nearest (distinct) vertices. A triangle T that was not seen has all its corners
    farther than d_k, the k-th neighbour's distance, and every point of T lies within
    L_T / sqrt(3) of a corner (L_T: its longest edge), so T can only be nearer than d if
    L_T > sqrt(3) (d_k - d): such a point is then measured to every triangle whose
    centroid is within its reach (the tests check the result against a search over every
    triangle)."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, neighbours: int = 6):
        vertices = np.asarray(vertices, float)
        if len(triangles) == 0:
            raise ValueError("mesh without triangles")
        # one vertex per position: the collapsed pole row of a sphere's tessellation would
        # otherwise fill the nearest neighbours with copies of one point
        extent = float(np.ptp(vertices, axis=0).max()) or 1.0
        keys = np.round((vertices - vertices.min(0)) / (1e-12 * extent)).astype(np.int64)
        _, first, merged = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        self.vertices = vertices[first]
        self.triangles = merged.reshape(-1)[np.asarray(triangles, np.int64)]
        self.tree = cKDTree(self.vertices)
        self.k = min(neighbours, len(self.vertices))
        corners = self.vertices[self.triangles]
        longest = np.max([np.linalg.norm(corners[:, i] - corners[:, j], axis=1)
                          for i, j in ((0, 1), (1, 2), (2, 0))], axis=0)
        self.lengths = np.sort(longest)[::-1]  # the longest first
        centroids = corners.mean(axis=1)
        radii = np.linalg.norm(corners - centroids[:, None], axis=2).max(axis=1)
        # triangles in classes of radii within a factor 2: a point searches each class
        # within its own largest radius, so a few long triangles (a wild fit's) do not put
        # every triangle of the mesh within every point's reach
        classes = np.floor(np.log2(np.maximum(radii, 1e-300))).astype(np.int64)
        self.classes = []  # (the class's largest radius, its triangles, their centroids' tree)
        for c in np.unique(classes):
            members = np.flatnonzero(classes == c)
            self.classes.append((float(radii[members].max()), members, cKDTree(centroids[members])))
        order = np.argsort(self.triangles.ravel(), kind="stable")
        counts = np.bincount(self.triangles.ravel(), minlength=len(self.vertices))
        starts = np.concatenate([[0], np.cumsum(counts)])
        self.incident = np.full((len(self.vertices), max(int(counts.max()), 1)), -1, np.int64)  # vertex -> triangles
        slot = np.arange(len(order)) - np.repeat(starts[:-1], counts)
        self.incident[np.repeat(np.arange(len(self.vertices)), counts), slot] = order // 3

    def __call__(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, float)
        d = np.empty(len(q))
        unsure = []
        chunk = max(1, 32768 // self.k)
        for start in range(0, len(q), chunk):  # most points are settled by their k neighbours
            part = np.arange(start, min(start + chunk, len(q)))
            dk, near = self.tree.query(q[part], k=self.k)
            near, dk = near.reshape(len(part), -1), dk.reshape(len(part), -1)[:, -1]
            d[part] = self._distances(q[part], self.incident[near].reshape(len(part), -1))
            if self.k < len(self.vertices):
                unsure.append(part[self._long_enough(dk, d[part]) > 0])
        unsure = np.concatenate(unsure) if unsure else np.zeros(0, np.int64)
        if len(unsure):
            d[unsure] = self._within_reach(q[unsure], d[unsure])
        return d

    def _within_reach(self, q: np.ndarray, d: np.ndarray, pairs: int = 1 << 18) -> np.ndarray:
        """The least distance over every triangle that could be nearer than d: a triangle T
        lies within R_T (its corners' farthest from its centroid c_T) of c_T, so only those
        with |q - c_T| < d + R_T can (a point far from the mesh, against its spacing). Each
        class of radii is searched within d + its largest R_T, the shortest triangles
        first (d shrinks as nearer ones are found). Points go in groups of about ``pairs``
        point-triangle pairs, each group's triangles listed only when it is measured."""
        out = d.copy()
        for radius, members, centroids in self.classes:
            reach = out + radius
            count = np.asarray(centroids.query_ball_point(q, reach, return_length=True))
            order = np.argsort(count, kind="stable")
            order = order[count[order] > 0]
            start = 0
            while start < len(order):  # groups of similar counts
                stop = start + 1
                while stop < len(order) and (stop - start + 1) * int(count[order[stop]]) <= pairs:
                    stop += 1
                group = order[start:stop]
                found = centroids.query_ball_point(q[group], reach[group])
                candidates = np.full((len(group), int(count[group].max())), -1, np.int64)
                for row, near in enumerate(found):
                    candidates[row, :len(near)] = members[near]
                out[group] = np.minimum(out[group], self._distances(q[group], candidates))
                start = stop
        return out

    def _long_enough(self, dk: np.ndarray, d: np.ndarray) -> np.ndarray:
        """How many triangles (the longest first) could be nearer than d unseen."""
        return np.searchsorted(-self.lengths, -np.sqrt(3.0) * (dk - d), side="left")

    def _distances(self, q: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """Least distance from each q[i] to the triangles candidates[i] (-1: none)."""
        candidates = np.sort(candidates, axis=1)
        repeated = np.zeros_like(candidates, bool)
        repeated[:, 1:] = candidates[:, 1:] == candidates[:, :-1]
        candidates[repeated] = -1
        width = int((candidates >= 0).sum(axis=1).max())
        candidates = -np.sort(-candidates, axis=1)[:, :max(width, 1)]  # the distinct ones first
        corner = self.vertices[self.triangles[np.maximum(candidates, 0)]]  # (n, c, 3, 3)
        d = point_triangle_distance(q[:, None, :], corner[:, :, 0], corner[:, :, 1], corner[:, :, 2])
        return np.where(candidates >= 0, d, np.inf).min(axis=1)


# ---- the figures ------------------------------------------------------------------------------

def score(cloud: Path, outdir: Path, gt: Path | None = None, stem: str | None = None, res: int = 301) -> dict:
    stem = stem or cloud.stem
    points = read_points(cloud)
    diag = float(np.linalg.norm(points.max(0) - points.min(0)))
    doc = json.loads((outdir / f"{stem}.json").read_text())
    surface = Surface(doc["surface"])
    us, vs = surface.parameters(np.linspace(0, 1, res), np.linspace(0, 1, res))
    grid = surface.grid(us, vs)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    inside = surface.inside(uu.ravel(), vv.ravel())
    if not inside.any():
        raise ValueError("the trim loops enclose no part of the surface")
    samples = grid.reshape(-1, 3)[inside]
    to_surface = SurfaceDistance(surface)

    d = to_surface(points) / diag
    out: dict = {"points": len(points), "rmse": float(np.sqrt(np.mean(d * d))),
                 "p99": float(np.quantile(d, 0.99)), "max": float(d.max())}
    claimed = doc.get("metrics", {}).get("rmse")
    out["claimed_rmse"] = None if claimed is None else float(claimed) / diag
    out["overhang"] = float(np.mean(cKDTree(points).query(samples)[0] / diag > OVERHANG))
    out["trimmed"] = bool(surface.trim)

    mesh_vertices, mesh_triangles = read_ply(outdir / f"{stem}.ply")
    if mesh_triangles is None or len(mesh_triangles) == 0:
        raise ValueError(f"{outdir / stem}.ply holds no triangles")
    probes = samples
    if surface.trim:  # away from the loops, where the mesh's edge and the grid's differ
        cell = max((surface.u.hi - surface.u.lo), (surface.v.hi - surface.v.lo)) / (res - 1)
        params = np.column_stack([uu.ravel(), vv.ravel()])[inside]
        far = distance_to_polygons([loop.polygon for loop in surface.trim], params) > 2.5 * cell
        probes = samples[far]
    mesh_to_surface = SurfaceDistance(surface, trimmed=False)(mesh_vertices) / diag
    surface_to_mesh = MeshDistance(mesh_vertices, mesh_triangles)(probes) / diag if len(probes) else np.zeros(1)
    out["mesh_vs_nurbs"] = float(max(mesh_to_surface.max(), surface_to_mesh.max()))

    for key, axis in (("closed_u", 0), ("closed_v", 1)):
        if doc["surface"].get(key):
            first, last = (grid[0], grid[-1]) if axis == 0 else (grid[:, 0], grid[:, -1])
            out["seam_" + key[-1]] = float(np.linalg.norm(first - last, axis=1).max() / diag)
    if doc.get("topology") == "sphere":
        ends = (grid[:, 0], grid[:, -1]) if doc["surface"].get("closed_u") else (grid[0], grid[-1])
        out["pole_spread"] = float(max(np.linalg.norm(e - e.mean(0), axis=1).max() for e in ends) / diag)

    support = points  # the points the edge figures measure against: the inliers where there is junk
    if gt is not None:
        truth = np.load(gt)
        to_truth = MeshDistance(truth["vertices"], truth["triangles"])
        t = to_truth(samples) / diag
        c = to_surface(truth["vertices"]) / diag
        out.update(truth_rms=float(np.sqrt(np.mean(t * t))), truth_max=float(t.max()),
                   cover_rms=float(np.sqrt(np.mean(c * c))), cover_max=float(c.max()))
        sigma = float(truth["noise"])
        if float(truth["outliers"]) > 0:
            inliers = to_truth(points) / diag <= max(INLIER_SIGMAS * sigma, TRUTH_CHORD)
            out["inlier_rmse"] = float(np.sqrt(np.mean(d[inliers] ** 2)))
            out["inliers"] = int(inliers.sum())
            support = points[inliers]
        out["noise"] = sigma
        if sigma > 0:
            out["truth_sigma"] = out["truth_rms"] / sigma
    out.update(edge_figures(surface, grid, us, vs, support, diag))
    if "cover_max" in out and out.get("spacing"):
        out["cover_max_sp"] = out["cover_max"] / out["spacing"]
        out["sample_cover_sp"] = float(cKDTree(support).query(truth["vertices"])[0].max()) / diag / out["spacing"]
    out["curve_ok"] = curve_ok(outdir / f"{stem}_error.csv")
    return out


def score_object(cloud: Path, outdir: Path, gt: Path | None = None, stem: str | None = None,
                 res: int = 101, cover_samples: int = 20000) -> dict:
    """An object of several trimmed faces (JSON ``surfaces``): see the module; cover_max
    over at most ``cover_samples`` of the truth's vertices (a fixed draw)."""
    stem = stem or cloud.stem
    points = read_points(cloud)
    diag = float(np.linalg.norm(points.max(0) - points.min(0)))
    doc = json.loads((outdir / f"{stem}.json").read_text())
    faces = [Surface(face) for face in doc["surfaces"]]
    d = np.min([SurfaceDistance(face)(points) for face in faces], axis=0) / diag
    spacing = float(np.median(cKDTree(points).query(points, 2)[0][:, 1])) / diag
    out: dict = {"points": len(points), "faces": len(faces), "rmse": float(np.sqrt(np.mean(d * d))),
                 "p99": float(np.quantile(d, 0.99)), "max": float(d.max()), "far_max": float(d.max() / spacing)}
    if gt is not None:
        truth = np.load(gt)
        samples = []
        for face in faces:
            us, vs = face.parameters(np.linspace(0, 1, res), np.linspace(0, 1, res))
            uu, vv = np.meshgrid(us, vs, indexing="ij")
            samples.append(face.grid(us, vs).reshape(-1, 3)[face.inside(uu.ravel(), vv.ravel())])
        t = MeshDistance(truth["vertices"], truth["triangles"])(np.concatenate(samples)) / diag
        vertices = truth["vertices"]
        if len(vertices) > cover_samples:
            vertices = vertices[np.random.default_rng(0).choice(len(vertices), cover_samples, replace=False)]
        c = np.min([SurfaceDistance(face)(vertices) for face in faces], axis=0) / diag
        out.update(truth_rms=float(np.sqrt(np.mean(t * t))), truth_max=float(t.max()), cover_max=float(c.max()),
                   noise=float(truth["noise"]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cloud", type=Path)
    ap.add_argument("outdir", type=Path)
    ap.add_argument("--gt", type=Path, help="the case's ground truth (CASE.gt.npz from benchmarks/cases.py)")
    ap.add_argument("--stem", help="the outputs' stem (default: the cloud's)")
    ap.add_argument("--res", type=int, default=301, help="parameter grid of the surface samples (default 301)")
    args = ap.parse_args(argv)
    try:
        stem = args.stem or args.cloud.stem
        several = "surfaces" in json.loads((args.outdir / f"{stem}.json").read_text())
        figures = score_object(args.cloud, args.outdir, args.gt, args.stem) if several else \
            score(args.cloud, args.outdir, args.gt, args.stem, args.res)
    except (OSError, KeyError, ValueError, json.JSONDecodeError) as e:
        print(json.dumps({"error": f"{type(e).__name__}: {e}"}))
        return 2
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())

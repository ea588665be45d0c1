"""The NURBS surface type: evaluation, derivatives, tessellation and JSON round trip.

A NURBS surface of degrees (p, q) with control net P_ij and weights w_ij is

    S(u, v) = sum_ij w_ij N_i,p(u) N_j,q(v) P_ij / sum_ij w_ij N_i,p(u) N_j,q(v)

evaluated on the domain [t_p, t_{-p-1}] x [s_q, s_{-q-1}]. The net is stored whole:
a closed direction repeats its first ``degree`` rows at the end and carries an
unclamped periodic knot vector, so that any standard evaluator draws the closed
surface (see :mod:`psonurbs.geometry.basis`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from psonurbs.geometry.basis import clamped_knots, design_matrix, tensor_basis

from .compiled import chunks

EVALUATION_CHUNK = 1 << 15  # points evaluated together: some 20 MB of basis and derivative arrays


@dataclass
class NurbsSurface:
    degree_u: int
    degree_v: int
    knots_u: np.ndarray
    knots_v: np.ndarray
    control_points: np.ndarray  # (nu, nv, 3), [i][j] = i-th along u, j-th along v
    weights: np.ndarray  # (nu, nv), positive
    closed_u: bool = False
    closed_v: bool = False

    def __post_init__(self):
        self.knots_u = np.asarray(self.knots_u, float)
        self.knots_v = np.asarray(self.knots_v, float)
        self.control_points = np.asarray(self.control_points, float)
        nu, nv = self.control_points.shape[:2]
        self.weights = np.asarray(self.weights, float).reshape(nu, nv)
        if self.control_points.shape != (nu, nv, 3):
            raise ValueError("control_points must have shape (nu, nv, 3)")
        if len(self.knots_u) != nu + self.degree_u + 1 or len(self.knots_v) != nv + self.degree_v + 1:
            raise ValueError(f"knot vectors of length {len(self.knots_u)}, {len(self.knots_v)} do not "
                             f"fit a {nu} x {nv} net of degrees {self.degree_u}, {self.degree_v}")
        if not (np.all(np.diff(self.knots_u) >= 0) and np.all(np.diff(self.knots_v) >= 0)):
            raise ValueError("knot vectors must be finite and non-decreasing")
        if not np.all(self.weights > 0) or not np.all(np.isfinite(self.weights)):
            raise ValueError("weights must be finite and positive")

    @property
    def shape(self) -> tuple[int, int]:
        return self.control_points.shape[:2]

    @property
    def domain_u(self) -> tuple[float, float]:
        return float(self.knots_u[self.degree_u]), float(self.knots_u[-self.degree_u - 1])

    @property
    def domain_v(self) -> tuple[float, float]:
        return float(self.knots_v[self.degree_v]), float(self.knots_v[-self.degree_v - 1])

    def tensor(self, u: np.ndarray, v: np.ndarray, du: int = 0, dv: int = 0) -> sp.csr_array:
        """Non-rational tensor basis (or its derivative) at the points (u_r, v_r)."""
        bu = design_matrix(u, self.knots_u, self.degree_u, du)
        bv = design_matrix(v, self.knots_v, self.degree_v, dv)
        return tensor_basis(bu, bv)

    def evaluate(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Points S(u_r, v_r), shape (N, 3)."""
        return self.derivatives(u, v, first=False)[0]

    def derivatives(self, u: np.ndarray, v: np.ndarray, first: bool = True, second: bool = False):
        """S; with ``first`` also S_u, S_v; with ``second`` also S_uu, S_uv, S_vv; each (N, 3).

        Quotient rule on S = A / w (A the weighted net's spline, w the weights' spline):
        S_u = (A_u - w_u S) / w,  S_uu = (A_uu - 2 w_u S_u - w_uu S) / w,
        S_uv = (A_uv - w_u S_v - w_v S_u - w_uv S) / w.
        Evaluated ``EVALUATION_CHUNK`` points at a time (the basis matrices of a chunk
        are its only intermediate arrays); every point's values are its own.
        """
        u, v = np.asarray(u, float), np.asarray(v, float)
        if len(u) <= EVALUATION_CHUNK:
            return self._derivatives(u, v, first, second)
        count = 6 if second else 3 if first else 1
        out = tuple(np.empty((len(u), 3)) for _ in range(count))
        for part in chunks(len(u), EVALUATION_CHUNK):
            for whole, piece in zip(out, self._derivatives(u[part], v[part], first, second)):
                whole[part] = piece
        return out

    def _derivatives(self, u: np.ndarray, v: np.ndarray, first: bool, second: bool):
        w = self.weights.reshape(-1)
        aw = (self.control_points * self.weights[..., None]).reshape(-1, 3)
        orders = range(3 if second else 2 if first else 1)
        bu = [design_matrix(u, self.knots_u, self.degree_u, d) for d in orders]
        bv = [design_matrix(v, self.knots_v, self.degree_v, d) for d in orders]

        def spline(du: int, dv: int) -> tuple[np.ndarray, np.ndarray]:
            t = tensor_basis(bu[du], bv[dv])
            return t @ aw, t @ w

        a, den = spline(0, 0)
        s = a / den[:, None]
        if not (first or second):
            return (s,)
        (a_u, w_u), (a_v, w_v) = spline(1, 0), spline(0, 1)
        s_u = (a_u - w_u[:, None] * s) / den[:, None]
        s_v = (a_v - w_v[:, None] * s) / den[:, None]
        if not second:
            return s, s_u, s_v
        (a_uu, w_uu), (a_uv, w_uv), (a_vv, w_vv) = spline(2, 0), spline(1, 1), spline(0, 2)
        s_uu = (a_uu - 2 * w_u[:, None] * s_u - w_uu[:, None] * s) / den[:, None]
        s_uv = (a_uv - w_u[:, None] * s_v - w_v[:, None] * s_u - w_uv[:, None] * s) / den[:, None]
        s_vv = (a_vv - 2 * w_v[:, None] * s_v - w_vv[:, None] * s) / den[:, None]
        return s, s_u, s_v, s_uu, s_uv, s_vv

    def parameter_grid(self, n_u: int, n_v: int) -> tuple[np.ndarray, np.ndarray]:
        """Equally spaced parameters spanning the whole domain in each direction."""
        return np.linspace(*self.domain_u, n_u), np.linspace(*self.domain_v, n_v)

    def evaluate_grid(self, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
        """S on the tensor grid us x vs, shape (len(us), len(vs), 3)."""
        uu, vv = np.meshgrid(us, vs, indexing="ij")
        return self.evaluate(uu.ravel(), vv.ravel()).reshape(len(us), len(vs), 3)

    def tessellate(self, n_u: int = 101, n_v: int = 101) -> tuple[np.ndarray, np.ndarray]:
        """Triangle mesh of the surface on an n_u x n_v parameter grid."""
        grid = self.evaluate_grid(*self.parameter_grid(n_u, n_v))
        return grid.reshape(-1, 3), grid_triangles(n_u, n_v)

    def restricted(self, u_range: tuple[float, float] = (0.0, 1.0),
                   v_range: tuple[float, float] = (0.0, 1.0)) -> "NurbsSurface":
        """The same surface on the domain u_range x v_range, reparametrised onto [0, 1]^2
        with the same net size (open directions only). A range inside [0, 1] restricts
        the surface; one reaching past it extends it (its end spans' polynomials
        continued, as a CAD kernel extends a face past its edges).

        Exact: the restriction of a spline to [a, b] lies in the spline space of the knots
        inside (a, b), clamped at a and b (knot insertion); spans whose knots fall
        outside are given back by halving the widest span, so the net keeps its size. An
        extension keeps every inner knot: the end spans only grow. The homogeneous net
        (w P, w) is solved direction by direction from collocation.
        """
        from scipy.interpolate import BSpline

        net = np.concatenate([self.control_points * self.weights[..., None], self.weights[..., None]], axis=2)
        knots = [self.knots_u, self.knots_v]
        for k, ((a, b), degree, closed) in enumerate(((u_range, self.degree_u, self.closed_u),
                                                      (v_range, self.degree_v, self.closed_v))):
            if (a, b) == (0.0, 1.0):
                continue
            if closed:
                raise ValueError("a closed direction cannot be restricted or extended")
            n = net.shape[k]
            inner = knots[k][degree + 1:n]
            inner = list((inner[(inner > a) & (inner < b)] - a) / (b - a))
            while len(inner) < n - degree - 1:
                edges = np.concatenate([[0.0], inner, [1.0]])
                widest = int(np.argmax(np.diff(edges)))
                inner = sorted(inner + [0.5 * (edges[widest] + edges[widest + 1])])
            new_knots = clamped_knots(n, degree, np.array(inner))
            x = np.linspace(0.0, 1.0, 4 * n)
            old = BSpline.design_matrix(a + (b - a) * x, knots[k], degree, extrapolate=True).toarray()
            new = design_matrix(x, new_knots, degree).toarray()
            moved = np.moveaxis(net, k, 0)
            solved = np.linalg.lstsq(new, np.einsum("xi,i...->x...", old, moved).reshape(len(x), -1), rcond=None)[0]
            net = np.moveaxis(solved.reshape(moved.shape), 0, k)
            knots[k] = new_knots
        return NurbsSurface(self.degree_u, self.degree_v, knots[0], knots[1], net[..., :3] / net[..., 3:],
                            net[..., 3], self.closed_u, self.closed_v)

    def to_dict(self) -> dict:
        return {
            "degree_u": int(self.degree_u),
            "degree_v": int(self.degree_v),
            "knots_u": [float(x) for x in self.knots_u],
            "knots_v": [float(x) for x in self.knots_v],
            "control_points": self.control_points.tolist(),
            "weights": self.weights.tolist(),
            "closed_u": bool(self.closed_u),
            "closed_v": bool(self.closed_v),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "NurbsSurface":
        cp = np.asarray(d["control_points"], float)
        return cls(int(d["degree_u"]), int(d["degree_v"]), d["knots_u"], d["knots_v"], cp,
                   d.get("weights", np.ones(cp.shape[:2])),
                   bool(d.get("closed_u", False)), bool(d.get("closed_v", False)))


def grid_triangles(n_u: int, n_v: int) -> np.ndarray:
    """Two triangles per cell of an n_u x n_v vertex grid stored row-major."""
    i, j = np.meshgrid(np.arange(n_u - 1), np.arange(n_v - 1), indexing="ij")
    a = (i * n_v + j).ravel()
    b, c, d = a + n_v, a + 1, a + n_v + 1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, d], 1)]).astype(np.int64)

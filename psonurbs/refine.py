"""Joint refinement: Levenberg-Marquardt over control points, weights and parameters.

Alternating parameter correction and least squares converges slowly, and it cannot
move the weights at all. Here all three are unknowns of one non-linear least-squares
problem (knots stay where the swarm put them):

    min  sum_i |S(u_i, v_i; P, w) - x_i|^2 + lam |L P|^2

solved by :func:`scipy.optimize.least_squares` (trust region reflective, sparse
Jacobian, LSMR). With R the rational basis at the points, the Jacobian blocks are

    dS_i / dP_c       = R_ic                       (per coordinate)
    dS_i / d log w_c  = R_ic (P_c - S_i)
    dS_i / d(u_i, v_i) = (S_u, S_v)(u_i, v_i)      (each point moves only itself)

Log-weights keep the weights positive and are bounded as in the swarm; parameters of
an open direction stay in [0, 1], those of a closed one wrap.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from .net import NetLayout
from .polish import keep_in_domain
from .solve import RegularisedLeastSquares


class JointProblem:
    def __init__(self, layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray,
                 inner_u: np.ndarray, inner_v: np.ndarray):
        self.layout, self.points = layout, points
        self.inner = (inner_u, inner_v)
        self.n, self.m = layout.n_free, len(points)
        self.smoothness = sp.csr_array(layout.smoothness_operator())
        self.solver = solver

    def split(self, x: np.ndarray):
        n = self.n
        control = x[:3 * n].reshape(n, 3)
        weights = np.exp(x[3 * n:4 * n])
        uv = keep_in_domain(x[4 * n:].reshape(-1, 2), self.layout.closed)
        return control, weights, uv

    def pack(self, control, weights, uv) -> np.ndarray:
        return np.concatenate([control.ravel(), np.log(weights), uv.ravel()])

    def bounds(self, log_bounds) -> tuple[np.ndarray, np.ndarray]:
        n, m = self.n, self.m
        lo_uv = np.tile([-np.inf if c else 0.0 for c in self.layout.closed], m)
        hi_uv = np.tile([np.inf if c else 1.0 for c in self.layout.closed], m)
        return (np.concatenate([np.full(3 * n, -np.inf), np.full(n, log_bounds[0]), lo_uv]),
                np.concatenate([np.full(3 * n, np.inf), np.full(n, log_bounds[1]), hi_uv]))

    def penalty_scale(self, rows) -> float:
        gram_trace = float(np.sum(rows.values ** 2))
        return np.sqrt(self.solver.smoothing * gram_trace / self.solver.penalty_trace) \
            if self.solver.penalty_trace > 0 else 0.0

    def residuals(self, x: np.ndarray) -> np.ndarray:
        control, weights, uv = self.split(x)
        rows = self.layout.rows(uv, weights, *self.inner)
        data = (rows @ control - self.points).ravel()
        return np.concatenate([data, self.penalty_scale(rows) * (self.smoothness @ control).ravel()])

    def jacobian(self, x: np.ndarray) -> sp.csr_array:
        control, weights, uv = self.split(x)
        n, m = self.n, self.m
        rows = self.layout.rows(uv, weights, *self.inner)
        surface = self.layout.surface(control, weights, *self.inner)
        s, su, sv = surface.derivatives(uv[:, 0], uv[:, 1])
        k = rows.values.shape[1]
        point = np.repeat(np.arange(m), k)
        col, val = rows.columns.ravel(), rows.values.ravel()
        r_idx, c_idx, v_idx = [], [], []
        for d in range(3):
            r_idx += [3 * point + d, 3 * point + d]
            c_idx += [3 * col + d, 3 * n + col]
            v_idx += [val, val * (control[col, d] - s[point, d])]
            r_idx += [3 * np.arange(m) + d, 3 * np.arange(m) + d]
            c_idx += [4 * n + 2 * np.arange(m), 4 * n + 2 * np.arange(m) + 1]
            v_idx += [su[:, d], sv[:, d]]
        data_jac = sp.csr_array((np.concatenate(v_idx), (np.concatenate(r_idx), np.concatenate(c_idx))),
                                shape=(3 * m, 4 * n + 2 * m))
        reg = sp.kron(self.smoothness, sp.identity(3), format="csr") * self.penalty_scale(rows)
        reg = sp.hstack([reg, sp.csr_array((reg.shape[0], n + 2 * m))])
        return sp.csr_array(sp.vstack([data_jac, reg]))


def refine_jointly(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
                   control: np.ndarray, weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray,
                   log_bounds, max_evaluations: int = 40):
    """Jointly optimised (control, weights, uv), started from the given ones."""
    problem = JointProblem(layout, solver, points, inner_u, inner_v)
    lower, upper = problem.bounds(log_bounds)
    x0 = np.clip(problem.pack(control, np.clip(weights, *np.exp(log_bounds)), uv), lower, upper)
    result = least_squares(problem.residuals, x0, jac=problem.jacobian, bounds=(lower, upper),
                           method="trf", tr_solver="lsmr", x_scale="jac", max_nfev=max_evaluations,
                           ftol=1e-12, xtol=1e-12, gtol=1e-12)
    return problem.split(result.x)

"""Joint refinement: Levenberg-Marquardt over control points, weights and parameters.

Alternating parameter correction with linear least squares converges slowly and
cannot move the weights. Here all of them are the unknowns of one non-linear least
squares problem (the knots stay where the swarm put them):

    min  sum_i c_i |S(u_i, v_i; P, w) - x_i|^2 + lam |L P|^2 + kappa |C P|^2

(c_i > 0 the robust loss's point weights, 1 without them; below, every point's residual
and Jacobian rows are scaled by sqrt(c_i), which makes the problem the unweighted one)

With R the rational basis at the points, the Jacobian of point i's residual is

    dS_i / dP_c        = R_ic                (per coordinate)
    dS_i / d log w_c   = R_ic (P_c - S_i)
    dS_i / d(u_i, v_i) = [S_u  S_v]          (each point moves only its own parameters)

so the damped normal equations have a small dense block G for the net (4 unknowns per
control point), a 2 x 2 block C_i per point and a coupling B_i between them. The
points are eliminated exactly (Schur complement, as in bundle adjustment):

    (G - sum_i B_i C_i^-1 B_i^T) d_net = -g + sum_i B_i C_i^-1 c_i
    d_i = -C_i^-1 (c_i + B_i^T d_net)

Every point's block touches only its knot-span cell's control points, so the sums are
cell-block Grams (:class:`psonurbs.geometry.rows.CellBlocks`) and the net system is solved by
Cholesky. Levenberg damping ``mu * mean(diag) * I`` also tames the exact null
directions of a rational patch (the weights' common scale, their Moebius
reparametrisation). Log-weights stay inside their bounds; parameters of an open
direction inside [0, 1], those of a closed one wrap.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as la

from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.projection import keep_in_domain
from psonurbs.geometry.rows import Rows

from .solve import RegularisedLeastSquares


class JointProblem:
    def __init__(self, layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray,
                 inner_u: np.ndarray, inner_v: np.ndarray, point_weights: np.ndarray | None = None):
        self.layout, self.solver, self.points = layout, solver, points
        self.inner = (inner_u, inner_v)
        self.n = layout.n_free
        self.root = np.ones(len(points)) if point_weights is None else np.sqrt(point_weights)  # sqrt(c_i)

    def evaluate(self, control: np.ndarray, weights: np.ndarray, uv: np.ndarray) -> dict:
        """Residuals, objective and the basis rows at the given unknowns."""
        rows = self.layout.rows(uv, weights, *self.inner)
        residual = self.root[:, None] * (rows @ control - self.points)
        regulariser = self.solver.regulariser(float(np.sum(self.root[:, None] ** 2 * rows.values ** 2)))
        objective = float(np.sum(residual ** 2) + np.sum(control * (regulariser @ control)))
        return {"rows": rows, "residual": residual, "regulariser": regulariser, "objective": objective}

    def pinned(self, uv: np.ndarray, d_uv: np.ndarray) -> np.ndarray:
        """(N, 2) mask of open-direction parameters that the step would push out of [0, 1]:
        they stay on the bound (the active set of the bound constraints)."""
        target = uv + d_uv
        return ((target < 0.0) | (target > 1.0)) & ~np.array(self.layout.closed)[None, :]

    def linearise(self, control: np.ndarray, weights: np.ndarray, uv: np.ndarray, ev: dict) -> dict:
        """The parts of the normal equations that do not depend on the damping."""
        n, rows, res = self.n, ev["rows"], ev["residual"]
        surface = self.layout.surface(control, weights, *self.inner)
        _, su, sv = surface.derivatives(uv[:, 0], uv[:, 1])
        c, v = rows.columns, self.root[:, None] * rows.values
        s = control[c] - (rows @ control)[:, None, :]  # P_c - S_i, (N, m, 3)
        columns = np.concatenate([3 * c, 3 * c + 1, 3 * c + 2, 3 * n + c], axis=1)
        zeros = np.zeros_like(v)
        # row k (coordinate k of every point's residual) of the Jacobian in the net unknowns
        jn = np.stack([np.concatenate([v if j == k else zeros for j in range(3)] + [v * s[:, :, k]], axis=1)
                       for k in range(3)], axis=1)  # (N, 3, 4m)
        stacked = Rows(jn.reshape(-1, jn.shape[2]), np.repeat(columns, 3, axis=0), 4 * n, np.repeat(rows.cells, 3))
        penalty = np.zeros((4 * n, 4 * n))
        penalty[:3 * n, :3 * n] = np.kron(ev["regulariser"], np.eye(3))
        gram = stacked.gram() + penalty
        g = stacked.project(res.reshape(-1, 1))[:, 0] + penalty @ np.concatenate([control.ravel(), np.zeros(n)])
        jl = self.root[:, None, None] * np.stack([su, sv], axis=2)
        return {"v": v, "s": s, "jl": jl, "columns": columns, "cells": rows.cells,
                "gram": gram, "g": g, "residual": res}

    def step(self, lin: dict, damping: float, frozen: np.ndarray | None = None):
        """The damped Gauss-Newton step (d_control, d_log_weights, d_uv); parameters
        marked ``frozen`` (N, 2) stay where they are. The 2 x 2 blocks are inverted
        in closed form."""
        n, v, s, columns, cells, res = self.n, lin["v"], lin["s"], lin["columns"], lin["cells"], lin["residual"]
        jl = lin["jl"] if frozen is None else lin["jl"] * ~frozen[:, None, :]  # (N, 3, 2)
        a = np.sum(jl[:, :, 0] ** 2, axis=1)
        c = np.sum(jl[:, :, 1] ** 2, axis=1)
        off = np.sum(jl[:, :, 0] * jl[:, :, 1], axis=1)
        shift = damping * np.maximum((a + c) / 2.0, 1e-300)
        a, c = a + shift, c + shift
        if frozen is not None:
            a, c = a + frozen[:, 0], c + frozen[:, 1]
        # B_i = J_net,i^T J_l,i: control blocks v_c * J_l[k], weight block v_c * (P_c - S_i) . J_l
        b = np.concatenate([v[:, :, None] * jl[:, k, None, :] for k in range(3)]
                           + [v[:, :, None] * np.einsum("nmk,nkj->nmj", s, jl)], axis=1)  # (N, 4m, 2)
        l11 = np.sqrt(a)
        l21 = off / l11
        l22 = np.sqrt(np.maximum(c - l21 ** 2, 1e-300))
        y0 = b[:, :, 0] / l11[:, None]  # B_i L_i^-T, C_i = L_i L_i^T
        y1 = (b[:, :, 1] - b[:, :, 0] * (l21 / l11)[:, None]) / l22[:, None]
        schur = lin["gram"] - Rows(np.concatenate([y0, y1]), np.concatenate([columns, columns]),
                                   4 * n, np.concatenate([cells, cells])).gram()
        schur[np.diag_indices_from(schur)] += damping * np.trace(schur) / len(schur)
        det = a * c - off ** 2

        def c_inverse(x: np.ndarray) -> np.ndarray:  # C_i^-1 x_i for (N, 2) x
            return np.stack([c * x[:, 0] - off * x[:, 1], a * x[:, 1] - off * x[:, 0]], axis=1) / det[:, None]

        c_vec = np.einsum("nki,nk->ni", jl, res)  # J_l^T r
        w_vec = c_inverse(c_vec)
        rhs = -lin["g"] + Rows(b[:, :, 0] * w_vec[:, 0:1] + b[:, :, 1] * w_vec[:, 1:2], columns, 4 * n,
                               cells).project(np.ones((len(res), 1)))[:, 0]
        d_net = la.cho_solve(la.cho_factor(schur, check_finite=False), rhs, check_finite=False)
        picked = d_net[columns]
        bt_d = np.stack([np.sum(b[:, :, 0] * picked, axis=1), np.sum(b[:, :, 1] * picked, axis=1)], axis=1)
        d_uv = -c_inverse(c_vec + bt_d)
        return d_net[:3 * n].reshape(n, 3), d_net[3 * n:], d_uv


def refine_jointly(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
                   control: np.ndarray, weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray,
                   log_bounds, iterations: int = 12, tolerance: float = 1e-6,
                   point_weights: np.ndarray | None = None):
    """Refined (control, weights, uv) and the rounds taken, started from the given ones;
    ``point_weights`` (N,), all positive, weigh the points' squared distances."""
    problem = JointProblem(layout, solver, points, inner_u, inner_v, point_weights)
    log_w = np.clip(np.log(weights), *log_bounds)
    uv = keep_in_domain(uv, layout.closed)
    ev = problem.evaluate(control, np.exp(log_w), uv)
    damping, taken = 1e-3, 0
    for taken in range(1, iterations + 1):
        gain = None
        lin = problem.linearise(control, np.exp(log_w), uv, ev)
        while damping < 1e6:
            try:
                d_control, d_log_w, d_uv = problem.step(lin, damping)
                pinned = problem.pinned(uv, d_uv)
                if pinned.any():
                    d_control, d_log_w, d_uv = problem.step(lin, damping, pinned)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            trial = (control + d_control, np.clip(log_w + d_log_w, *log_bounds),
                     keep_in_domain(uv + d_uv, layout.closed))
            trial_ev = problem.evaluate(trial[0], np.exp(trial[1]), trial[2])
            if trial_ev["objective"] < ev["objective"]:
                gain = 1.0 - trial_ev["objective"] / ev["objective"]
                (control, log_w, uv), ev = trial, trial_ev
                damping = max(damping / 4.0, 1e-9)
                break
            damping *= 8.0
        if gain is None or gain < tolerance:
            break
    return control, np.exp(log_w), uv, taken

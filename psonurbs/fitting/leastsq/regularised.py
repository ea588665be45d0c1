"""Control points by regularised linear least squares, and its leave-one-out error.

With knots, weights and parameters fixed, the surface is linear in its control points:
``S = R P`` with R the rational basis at the points. We solve

    min_P  |R P - X|^2 + lam |L P|^2,       lam = smoothing * tr(R^T R) / tr(L^T L)

by the normal equations ``M P = R^T X``, ``M = R^T R + lam L^T L``, and a Cholesky
factorisation (at most a few hundred unknowns). L is the net's thin-plate operator: it
decides the net where data are thin (16 points on a 5 x 5 net) and keeps it from
flapping into empty regions. The smoothing weight is relative, so it means the same
for any cloud size or net.

The fit is a linear smoother ``X_hat = H X`` with ``H = R M^-1 R^T``, so the error at
point i of the fit that did not see point i is exact and cheap (no refit):
``e_i / (1 - h_ii)`` with ``h_ii = r_i^T M^-1 r_i``.

With per-point weights w (N,) in [0, 1] (``point_weights``: a robust loss's weights, 0
leaves a point out) the problem is ``min sum_i w_i |r_i P - x_i|^2 + lam |L P|^2`` with
``M = R^T W R + lam L^T L`` (lam from ``tr(R^T W R)``). Taking point i out of it lowers M
by ``w_i r_i r_i^T``, so the leave-one-out residual stays exact:
``e_i / (1 - w_i h_ii)``, ``h_ii = r_i^T M^-1 r_i``. Both are the unweighted formulas on
the rows scaled by ``sqrt(w_i)`` (the residual e_i on the unscaled ones). Without
weights (None) every number is the unweighted one.

R comes as :class:`psonurbs.geometry.rows.Rows` (m non-zeros per row, grouped by
knot-span cell), so ``R^T R`` and the leverages h_ii are sums of small dense blocks.

This module is the computation's one definition, for one net; the swarm evaluates it
for many particles at once by its two twins, the numpy
:class:`psonurbs.fitting.leastsq.stacked.StackedLeastSquares` and the compiled
:mod:`psonurbs.fitting.leastsq.stacked_compiled`, which take the constants below
(:data:`CONSTRAINT_WEIGHT`, :data:`RIDGE`, :data:`LEVERAGE_FLOOR`) from here and scale
the regulariser per particle as ``(lam / tr(L^T L)) t`` where this solver forms
``lam t / tr(L^T L)``: the same numbers to rounding, each path's operations fixed so
that a fit gives the same bits every time.
"""
from __future__ import annotations

import copy

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp

from psonurbs.geometry.rows import Rows

CONSTRAINT_WEIGHT = 1e4  # a condition C P = 0 weighs this much more than the data: imposed
RIDGE = 1e-12  # added to M's diagonal, relative to its mean: keeps M positive definite
LEVERAGE_FLOOR = 1e-12  # 1 - h_ii at least this: a point that alone decides its fit keeps a finite error


class RegularisedLeastSquares:
    """Solver for ``min |R P - X|^2 + lam |L P|^2 + kappa |C P|^2``.

    L is the smoothness operator, weighted by the smoothing ``lam``; C holds linear
    conditions the net must meet (``C P = 0``, e.g. a tangent plane at a pole), imposed
    by a penalty ``CONSTRAINT_WEIGHT`` times stronger than the data. Both weights are
    relative: scaled by ``tr(R^T R)`` over the trace of their own term.
    """

    def __init__(self, smoothness: sp.csr_array, smoothing: float, constraints: sp.csr_array | None = None):
        self.penalty = (smoothness.T @ smoothness).toarray()
        self.penalty_trace = float(np.trace(self.penalty))
        self.condition = None if constraints is None else (constraints.T @ constraints).toarray()
        self.condition_trace = None if constraints is None else float(np.trace(self.condition))
        self.smoothing = smoothing

    def with_smoothing(self, smoothing: float) -> "RegularisedLeastSquares":
        """The same operator with another smoothing weight (no recomputation)."""
        other = copy.copy(self)
        other.smoothing = float(smoothing)
        return other

    def regulariser(self, trace: float) -> np.ndarray:
        """``lam L^T L + kappa C^T C`` for data whose Gram matrix has this trace."""
        out = (self.smoothing * trace / self.penalty_trace) * self.penalty if self.penalty_trace > 0 \
            else np.zeros_like(self.penalty)
        if self.condition is not None:
            out = out + (CONSTRAINT_WEIGHT * trace / self.condition_trace) * self.condition
        return out

    def normal_matrix(self, gram: np.ndarray) -> np.ndarray:
        """``M = R^T R + lam L^T L + kappa C^T C`` plus a tiny ridge that keeps M positive definite."""
        trace = float(np.trace(gram))
        system = gram + self.regulariser(trace)
        system[np.diag_indices_from(system)] += RIDGE * trace / len(gram)
        return system

    def solve(self, rows: Rows, data: np.ndarray, point_weights: np.ndarray | None = None) -> np.ndarray:
        """Control points (n, 3); raises LinAlgError if the system is singular."""
        rows, data = weighted(rows, data, point_weights)
        factor = la.cho_factor(self.normal_matrix(rows.gram()), check_finite=False)
        return la.cho_solve(factor, rows.project(data), check_finite=False)

    def leave_one_out(self, rows: Rows, data: np.ndarray,
                      point_weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Control points (n, 3), and each point's residual (N, 3) under the fit that did
        not see it (exact LOO: ``e_i / (1 - w_i h_ii)``; a point of weight 0 keeps e_i)."""
        scaled, scaled_data = weighted(rows, data, point_weights)
        blocks = scaled.blocks()
        factor = la.cho_factor(self.normal_matrix(blocks.gram()), check_finite=False)
        control = la.cho_solve(factor, scaled.project(scaled_data), check_finite=False)
        inverse = la.cho_solve(factor, np.eye(rows.n_columns), check_finite=False)
        leverage = blocks.quadratic_forms(inverse)  # w_i h_ii
        return control, (rows @ control - data) / np.maximum(1.0 - leverage, LEVERAGE_FLOOR)[:, None]

    def own_leverage(self, rows: Rows, point_weights: np.ndarray | None = None,
                     of: np.ndarray | None = None) -> np.ndarray:
        """The share of its own fitted value each point ``of`` (M,; default all N) would
        decide at full weight, the others at theirs: ``q_i / (1 + (1 - w_i) q_i)`` with
        ``q_i = r_i^T M^-1 r_i`` (M at the weights w; Sherman-Morrison for
        ``M + (1 - w_i) r_i r_i^T``). Near 1, the point alone holds its part of the net:
        nothing else in the data says where the surface is there."""
        scaled = rows if point_weights is None else rows.scaled(np.sqrt(point_weights))
        factor = la.cho_factor(self.normal_matrix(scaled.blocks().gram()), check_finite=False)
        of = np.arange(rows.shape[0]) if of is None else of
        q = rows.take(of).blocks().quadratic_forms(la.cho_solve(factor, np.eye(rows.n_columns), check_finite=False))
        unseen = 0.0 if point_weights is None else 1.0 - point_weights[of]
        return q / (1.0 + unseen * q)

    def leave_one_out_rmse(self, rows: Rows, data: np.ndarray, point_weights: np.ndarray | None = None) -> float:
        """RMSE of each point's residual under the fit that did not see it (exact LOO),
        weighted by the point weights (the robust loss's mean)."""
        residual = self.leave_one_out(rows, data, point_weights)[1]
        return weighted_rms(np.sum(residual ** 2, axis=1), point_weights)


def weighted(rows: Rows, data: np.ndarray, point_weights: np.ndarray | None) -> tuple[Rows, np.ndarray]:
    """Rows and data scaled by ``sqrt(w_i)``: their least squares is the weighted one."""
    if point_weights is None:
        return rows, data
    root = np.sqrt(point_weights)
    return rows.scaled(root), data * root[:, None]


def weighted_rms(squares: np.ndarray, point_weights: np.ndarray | None) -> float:
    """``sqrt(sum w_i d_i^2 / sum w_i)`` of squared distances (N,); the plain RMS without weights."""
    if point_weights is None:
        return float(np.sqrt(np.mean(squares)))
    return float(np.sqrt(np.sum(point_weights * squares) / np.sum(point_weights)))

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

**Where the data leave the net free** (:meth:`RegularisedLeastSquares.supported_by`): a
control point whose basis function barely reaches the data (the corners of a square
over a disc of data) is pinned by them only to within ``a_j`` times a point's own
scatter, ``a_j^2 = (M^-1)_jj tr(R^T W R) / n`` (a point pulled like an average one has
``a_j`` of order 1). With lam chosen by the leave-one-out error of the data, nothing
holds such a point: the noise of the few points at its support's edge is amplified
into a flap far off the cloud (a cap of noise 0.6% of its size: 6.5 times the cloud's
size). Each such point gets ``f_j = clip(log10(a_j / FREE_AMPLIFICATION), 0, 1)``, each
row of L the mean ``v_k`` of f over its stencil (weighted by |L|), and the problem the
fairness term ``mu |V^1/2 L P|^2``, ``mu = FAIRNESS tr(R^T W R) / n``: where no data
decide the net it continues as the thin-plate energy makes it, and a point the data do
pin (a sparse but real edge: ``a_j`` up to some 50) is left to them. With no more points
than unknowns the data pin no part of the net (every a_j is large) and the smoothing the
leave-one-out error chose decides it all: no term (the seed paper's 16 points on a 5 x 5
net stay interpolated). ``FAIRNESS`` is
``1 / FREE_AMPLIFICATION^2``: a free point's stencil weighs as much as the data weigh a
point pinned at the threshold (``mean / a_j^2``), so the term decides the points the data
hold more loosely and barely moves the loosely pinned points beside them (stronger, it
pulled the data's edge: a noiseless L-shaped wave's rmse 1.8 times, at weight 1). The
term is set once for a set of parameters and kept (both twins take it as one more fixed
term).

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
FREE_AMPLIFICATION = 100.0  # a control point the data pin only to this many times a point's scatter is free
# the fairness term's weight where the data leave the net free, relative to the mean of R^T
# W R's diagonal: as the data hold a point pinned at FREE_AMPLIFICATION, so that it
# decides the points the data hold more loosely and barely moves those they pin
FAIRNESS = FREE_AMPLIFICATION ** -2


class RegularisedLeastSquares:
    """Solver for ``min |R P - X|^2 + lam |L P|^2 + kappa |C P|^2``.

    L is the smoothness operator, weighted by the smoothing ``lam``; C holds linear
    conditions the net must meet (``C P = 0``, e.g. a tangent plane at a pole), imposed
    by a penalty ``CONSTRAINT_WEIGHT`` times stronger than the data. Both weights are
    relative: scaled by ``tr(R^T R)`` over the trace of their own term.
    """

    def __init__(self, smoothness: sp.csr_array, smoothing: float, constraints: sp.csr_array | None = None):
        self.smoothness = sp.csr_array(smoothness)
        self.penalty = (smoothness.T @ smoothness).toarray()
        self.penalty_trace = float(np.trace(self.penalty))
        self.condition = None if constraints is None else (constraints.T @ constraints).toarray()
        self.condition_trace = None if constraints is None else float(np.trace(self.condition))
        self.smoothing = smoothing
        self.fairness = None  # L^T V L (n, n) over the control points the data leave free (supported_by)

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
        if self.fairness is not None:
            out = out + (FAIRNESS * trace / len(self.penalty)) * self.fairness
        return out

    def supported_by(self, rows: Rows, point_weights: np.ndarray | None = None) -> "RegularisedLeastSquares":
        """This problem with the fairness term (see the module) of the control points that
        the data at these rows leave free, or with none if they pin every point."""
        plain = copy.copy(self)
        plain.fairness = None
        gram = (rows if point_weights is None else rows.scaled(np.sqrt(point_weights))).gram()
        n, trace = len(gram), float(np.trace(gram))
        if (len(rows.values) if point_weights is None else np.count_nonzero(point_weights)) <= n:
            return plain  # no more points than unknowns: they pin no part of the net, the smoothing decides it all
        try:
            factor = la.cho_factor(plain.normal_matrix(gram), check_finite=False)
        except np.linalg.LinAlgError:
            return plain
        pinned = np.diag(la.cho_solve(factor, np.eye(n), check_finite=False))  # (M^-1)_jj
        amplification = np.sqrt(np.maximum(pinned, 0.0) * trace / n)
        free = np.clip(np.log10(np.maximum(amplification, 1e-300) / FREE_AMPLIFICATION), 0.0, 1.0)
        if not free.any():
            return plain
        stencil = abs(self.smoothness)
        rows_free = (stencil @ free) / np.maximum(stencil @ np.ones(n), 1e-300)  # v_k
        plain.fairness = (self.smoothness.T @ self.smoothness.multiply(rows_free[:, None])).toarray()
        return plain

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

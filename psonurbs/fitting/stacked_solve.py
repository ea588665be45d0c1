"""The regularised least squares and its leave-one-out error for P particles at once.

The batched counterpart of :class:`psonurbs.fitting.solve.RegularisedLeastSquares` for
the swarm: particle k has its own rows R_k (knots, weights) and smoothing lam_k, all
share the points X, the smoothness operator L, the pole conditions C and optional
per-point weights w (N,). For each particle

    M_k = R_k^T W R_k + lam_k t_k / tr(L^T L) L^T L + kappa t_k / tr(C^T C) C^T C + ridge,
    t_k = tr(R_k^T W R_k),        M_k P_k = R_k^T W X,

exactly as the single solver does, and the leave-one-out residual of point i is
``e_i / (1 - w_i h_i)`` with ``h_i = r_i^T M_k^-1 r_i`` (exact for the weighted solve).

The Gram matrix is a sum of m x m blocks, one per chunk of rows of one cell (a
product over the chunk's slots, :class:`psonurbs.geometry.stacked_rows.StackedRows`).
The systems are factored in a banded order (:mod:`psonurbs.fitting.banded`) and the
leverages read the blocks of M^-1 at each cell's columns from its selected inverse.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from psonurbs.geometry.stacked_rows import CellLayout, StackedRows

from .banded import BandOrder, StackedBandedCholesky
from .solve import CONSTRAINT_WEIGHT, RegularisedLeastSquares

RIDGE = 1e-12  # relative to the mean diagonal, as in RegularisedLeastSquares.normal_matrix


class StackedLeastSquares:
    """``solver``'s problem for many particles on one layout's cells."""

    def __init__(self, solver: RegularisedLeastSquares, cells: CellLayout):
        self.solver, self.cells = solver, cells
        n = self.n = len(solver.penalty)
        columns = cells.columns
        pattern = np.eye(n, dtype=bool) | (solver.penalty != 0)
        if solver.condition is not None:
            pattern |= solver.condition != 0
        pattern[columns[:, :, None], columns[:, None, :]] = True
        self.order = BandOrder.for_pattern(pattern)
        self.columns = self.order.position[columns]  # (cells, m) in band order
        self.terms = []  # (rows, columns, values, weight) of L^T L and C^T C in band order
        if solver.penalty_trace > 0:
            self.terms.append(self._entries(solver.penalty) + (None,))
        if solver.condition is not None:
            self.terms.append(self._entries(solver.condition) + (CONSTRAINT_WEIGHT / solver.condition_trace,))

    def _entries(self, matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r, c = np.nonzero(matrix)
        return self.order.position[r], self.order.position[c], matrix[r, c]

    @lru_cache(maxsize=8)  # noqa: B019 - one per batch size, for the life of the search
    def _pair_index(self, n_particles: int) -> np.ndarray:
        """(P * cells * m * m,) flat indices into (P, n, n) of every block's column pairs."""
        pairs = (self.columns[:, :, None] * self.n + self.columns[:, None, :]).ravel()
        return ((np.arange(n_particles) * self.n * self.n)[:, None] + pairs).ravel()

    @lru_cache(maxsize=8)  # noqa: B019
    def _column_index(self, n_particles: int) -> np.ndarray:
        """(P * cells * m,) flat indices into (P, n) of every block's columns."""
        return ((np.arange(n_particles) * self.n)[:, None] + self.columns.ravel()).ravel()

    def normal_matrices(self, rows: StackedRows, slot_weights: np.ndarray | None,
                        smoothing: np.ndarray) -> np.ndarray:
        """(P, n, n) normal matrices in band order."""
        n_particles, n = rows.n_particles, self.n
        weighted = rows.values if slot_weights is None else rows.values * slot_weights[..., None]
        blocks = rows.per_block(np.matmul(weighted.transpose(0, 2, 1), rows.values))  # (P * cells, m, m)
        out = np.bincount(self._pair_index(n_particles), blocks.ravel(), n_particles * n * n)
        out = out.reshape(n_particles, n, n)
        diagonal = np.arange(n)
        trace = out[:, diagonal, diagonal].sum(axis=1)
        for r, c, values, weight in self.terms:
            factor = smoothing / self.solver.penalty_trace if weight is None else np.full(n_particles, weight)
            out[:, r, c] += (factor * trace)[:, None] * values
        out[:, diagonal, diagonal] += (RIDGE * trace / n)[:, None]
        return out

    def fit(self, rows: StackedRows, data: np.ndarray, smoothing: np.ndarray,
            point_weights: np.ndarray | None = None):
        """Residuals at the slots (T, slots, 3), the factorisation, and the point
        weights at the slots (T, slots; None when unweighted)."""
        n_particles, n = rows.n_particles, self.n
        slot_data = rows.gather(data)
        slot_weights = None if point_weights is None else rows.gather(np.asarray(point_weights, float))
        factor = StackedBandedCholesky(self.normal_matrices(rows, slot_weights, smoothing),
                                       self.order.half_bandwidth, self.order.block, overwrite=True)
        weighted = slot_data if slot_weights is None else slot_data * slot_weights[..., None]
        local = rows.per_block(np.matmul(rows.values.transpose(0, 2, 1), weighted))  # (P * cells, m, 3)
        index = self._column_index(n_particles)
        rhs = np.stack([np.bincount(index, local[..., k].ravel(), n_particles * n)
                        for k in range(data.shape[1])], axis=1)
        control = factor.solve(rhs.reshape(n_particles, n, -1)).reshape(n_particles * n, -1)
        at_cells = np.take(control, index, axis=0).reshape(local.shape)  # (P * cells, m, 3)
        fitted = np.matmul(rows.values, np.take(at_cells, rows.chunk_block, axis=0))
        return fitted - slot_data, factor, slot_weights

    def leverages(self, rows: StackedRows, factor: StackedBandedCholesky) -> np.ndarray:
        """``h_i = r_i^T M^-1 r_i`` at the slots, (T, slots)."""
        m = self.columns.shape[1]
        blocks = np.take(factor.selected_inverse(), self._pair_index(rows.n_particles)).reshape(-1, m, m)
        return np.einsum("tsm,tsm->ts", np.matmul(rows.values, np.take(blocks, rows.chunk_block, axis=0)),
                         rows.values)

    def errors(self, rows: StackedRows, data: np.ndarray, smoothing: np.ndarray, cross_validation: bool,
               point_weights: np.ndarray | None = None) -> np.ndarray:
        """Per particle (P,): the RMSE of the leave-one-out residuals (``cross_validation``)
        or of the plain residuals; a weighted RMSE under point weights."""
        residual, factor, slot_weights = self.fit(rows, data, smoothing, point_weights)
        if cross_validation:
            leverage = self.leverages(rows, factor)
            if slot_weights is not None:
                leverage = leverage * slot_weights
            residual = residual / np.maximum(1.0 - leverage, 1e-12)[..., None]
        squared = np.einsum("tsk,tsk->ts", residual, residual)
        if slot_weights is None:
            return np.sqrt(rows.per_particle(squared) / len(data))
        return np.sqrt(rows.per_particle(squared * slot_weights) / np.sum(point_weights))

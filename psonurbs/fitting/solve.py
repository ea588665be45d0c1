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

Every point's row of R has the same number m of non-zeros, so R is kept as two dense
(N, m) arrays (values, columns). Points in one knot-span cell share their columns, so
the Gram matrix is a sum of dense m x m blocks ``B_c^T B_c``, one small matrix
product per cell, and h_ii uses the matching m x m blocks of M^-1.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp

CONSTRAINT_WEIGHT = 1e4  # a condition C P = 0 weighs this much more than the data: imposed


@dataclass
class Rows:
    """A sparse matrix with m entries in every row, as (N, m) values and columns.

    ``cells`` labels the rows by knot-span cell: rows of one cell share their columns,
    so products like ``R^T R`` are sums of dense m x m blocks, one per cell, each a
    small matrix product (:class:`CellBlocks`).
    """

    values: np.ndarray
    columns: np.ndarray
    n_columns: int
    cells: np.ndarray

    @classmethod
    def from_csr(cls, mat: sp.csr_array, column_map: np.ndarray | None = None) -> "Rows":
        n = mat.shape[0]
        m = int(mat.indptr[1] - mat.indptr[0]) if n else 0
        cols = mat.indices.reshape(n, m)
        cells = cols[:, 0].copy() if m else np.zeros(n, np.int64)
        n_cols = mat.shape[1]
        if column_map is not None:
            cols, n_cols = column_map[cols], int(column_map.max()) + 1
        return cls(mat.data.reshape(n, m), cols, n_cols, cells)

    def take(self, index: np.ndarray) -> "Rows":
        """The rows at ``index`` (a mask or indices)."""
        return Rows(self.values[index], self.columns[index], self.n_columns, self.cells[index])

    def rational(self, weights: np.ndarray) -> "Rows":
        """Rows of the rational basis: ``w_c B_c / sum_c w_c B_c`` (weights per column)."""
        wb = self.values * weights[self.columns]
        return Rows(wb / wb.sum(axis=1, keepdims=True), self.columns, self.n_columns, self.cells)

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self.values), self.n_columns)

    def __matmul__(self, coeffs: np.ndarray) -> np.ndarray:
        return np.einsum("nm,nm...->n...", self.values, coeffs[self.columns])

    def toarray(self) -> np.ndarray:
        """The dense (N, n) matrix (entries of a repeated column add up)."""
        dense = np.zeros(self.shape)
        np.add.at(dense, (np.arange(len(self.values))[:, None], self.columns), self.values)
        return dense

    def blocks(self) -> "CellBlocks":
        return CellBlocks(self)

    def gram(self) -> np.ndarray:
        """``R^T R``, shape (n, n)."""
        return self.blocks().gram()

    def project(self, data: np.ndarray) -> np.ndarray:
        """``R^T X``, shape (n, 3)."""
        cols = self.columns.ravel()
        return np.stack([np.bincount(cols, (self.values * data[:, c:c + 1]).ravel(), self.n_columns)
                         for c in range(data.shape[1])], axis=1)


class CellBlocks:
    """The rows grouped by cell into a zero-padded (cells, most rows, m) array."""

    def __init__(self, rows: Rows):
        n_rows, m = rows.values.shape
        self.rows = rows
        self.order = np.argsort(rows.cells, kind="stable")
        sorted_cells = rows.cells[self.order]
        starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])
        counts = np.diff(np.r_[starts, n_rows])
        self.group = np.repeat(np.arange(len(starts)), counts)
        self.slot = np.arange(n_rows) - np.repeat(starts, counts)
        self.padded = np.zeros((len(starts), counts.max(initial=0), m))
        self.padded[self.group, self.slot] = rows.values[self.order]
        self.columns = rows.columns[self.order[starts]]  # (cells, m)

    def _scatter_index(self) -> np.ndarray:
        n = self.rows.n_columns
        return self.columns[:, :, None] * n + self.columns[:, None, :]

    def gram(self) -> np.ndarray:
        """``R^T R = sum over cells of B_c^T B_c`` placed at the cell's columns."""
        n = self.rows.n_columns
        local = np.matmul(self.padded.transpose(0, 2, 1), self.padded)
        return np.bincount(self._scatter_index().ravel(), local.ravel(), n * n).reshape(n, n)

    def quadratic_forms(self, matrix: np.ndarray) -> np.ndarray:
        """``r_i^T A r_i`` for every row i (in the rows' original order)."""
        local = matrix.ravel()[self._scatter_index()]  # (cells, m, m)
        forms = np.sum(np.matmul(self.padded, local) * self.padded, axis=2)
        out = np.empty(len(self.order))
        out[self.order] = forms[self.group, self.slot]
        return out


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
        system[np.diag_indices_from(system)] += 1e-12 * trace / len(gram)
        return system

    def solve(self, rows: Rows, data: np.ndarray) -> np.ndarray:
        """Control points (n, 3); raises LinAlgError if the system is singular."""
        factor = la.cho_factor(self.normal_matrix(rows.gram()), check_finite=False)
        return la.cho_solve(factor, rows.project(data), check_finite=False)

    def leave_one_out(self, rows: Rows, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Control points (n, 3), and each point's residual (N, 3) under the fit that did
        not see it (exact LOO: ``e_i / (1 - h_ii)``)."""
        blocks = rows.blocks()
        factor = la.cho_factor(self.normal_matrix(blocks.gram()), check_finite=False)
        control = la.cho_solve(factor, rows.project(data), check_finite=False)
        inverse = la.cho_solve(factor, np.eye(rows.n_columns), check_finite=False)
        leverage = blocks.quadratic_forms(inverse)
        return control, (rows @ control - data) / np.maximum(1.0 - leverage, 1e-12)[:, None]

    def leave_one_out_rmse(self, rows: Rows, data: np.ndarray) -> float:
        """RMSE of each point's residual under the fit that did not see it (exact LOO)."""
        residual = self.leave_one_out(rows, data)[1]
        return float(np.sqrt(np.mean(np.sum(residual ** 2, axis=1))))

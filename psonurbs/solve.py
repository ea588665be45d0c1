"""Control points by regularised linear least squares, and its cross-validated error.

With knots, weights and parameters fixed, the surface is linear in its control points:
``S = R P`` with R the rational basis at the points. We solve

    min_P  |R P - X|^2 + lam |L P|^2,       lam = smoothing * tr(R^T R) / tr(L^T L)

by the normal equations and a Cholesky factorisation (the systems have at most a few
hundred unknowns). L is the net's thin-plate operator: it decides the net where data
are thin (16 points on a 5 x 5 net) and keeps it from flapping into empty regions.
The smoothing weight is relative, so it means the same for any cloud size or net.

Every point's row of R has the same number m of non-zeros, so R is kept as two dense
(N, m) arrays (values, columns) and the Gram matrices are assembled with one
``bincount``: no Python loop over points, and K folds cost one pass.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp


@dataclass
class Rows:
    """A sparse matrix with m entries in every row, as (N, m) values and columns."""

    values: np.ndarray
    columns: np.ndarray
    n_columns: int

    @classmethod
    def from_csr(cls, mat: sp.csr_array, column_map: np.ndarray | None = None) -> "Rows":
        n = mat.shape[0]
        m = int(mat.indptr[1] - mat.indptr[0]) if n else 0
        cols = mat.indices.reshape(n, m)
        n_cols = mat.shape[1]
        if column_map is not None:
            cols, n_cols = column_map[cols], int(column_map.max()) + 1
        return cls(mat.data.reshape(n, m), cols, n_cols)

    def rational(self, weights: np.ndarray) -> "Rows":
        """Rows of the rational basis: ``w_c B_c / sum_c w_c B_c`` (weights per column)."""
        wb = self.values * weights[self.columns]
        return Rows(wb / wb.sum(axis=1, keepdims=True), self.columns, self.n_columns)

    def __matmul__(self, coeffs: np.ndarray) -> np.ndarray:
        return np.einsum("nm,nm...->n...", self.values, coeffs[self.columns])

    def gram(self, groups: np.ndarray | None = None, n_groups: int = 1) -> np.ndarray:
        """``R_g^T R_g`` for each group of rows, shape (n_groups, n, n)."""
        n, (rows, m) = self.n_columns, self.values.shape
        g = np.zeros(rows, np.int64) if groups is None else groups
        idx = (g[:, None, None] * n + self.columns[:, :, None]) * n + self.columns[:, None, :]
        val = self.values[:, :, None] * self.values[:, None, :]
        return np.bincount(idx.ravel(), val.ravel(), n_groups * n * n).reshape(n_groups, n, n)

    def project(self, data: np.ndarray, groups: np.ndarray | None = None, n_groups: int = 1) -> np.ndarray:
        """``R_g^T X_g`` for each group, shape (n_groups, n, 3)."""
        n = self.n_columns
        g = np.zeros(len(data), np.int64) if groups is None else groups
        idx = (g[:, None] * n + self.columns).ravel()
        out = np.empty((n_groups * n, data.shape[1]))
        for c in range(data.shape[1]):
            out[:, c] = np.bincount(idx, (self.values * data[:, c:c + 1]).ravel(), n_groups * n)
        return out.reshape(n_groups, n, data.shape[1])


class RegularisedLeastSquares:
    """Solver for ``min |R P - X|^2 + lam |L P|^2`` with a fixed operator L."""

    def __init__(self, smoothness: sp.csr_array, smoothing: float):
        self.penalty = (smoothness.T @ smoothness).toarray()
        self.penalty_trace = float(np.trace(self.penalty))
        self.smoothing = smoothing

    def _system(self, gram: np.ndarray, reference_trace: float) -> np.ndarray:
        lam = self.smoothing * reference_trace / self.penalty_trace if self.penalty_trace > 0 else 0.0
        ridge = 1e-12 * reference_trace / len(gram)
        return gram + lam * self.penalty + ridge * np.eye(len(gram))

    def solve(self, rows: Rows, data: np.ndarray) -> np.ndarray:
        """Control points (n, 3) for all rows; raises LinAlgError if singular."""
        gram = rows.gram()[0]
        rhs = rows.project(data)[0]
        return la.cho_solve(la.cho_factor(self._system(gram, np.trace(gram))), rhs)

    def cross_validated_rmse(self, rows: Rows, data: np.ndarray, folds: np.ndarray, n_folds: int) -> float:
        """RMSE of every point predicted by the solve on the other folds (K-fold CV).

        The fold Grams sum to the full Gram, so the K solves share one assembly.
        """
        grams = rows.gram(folds, n_folds)
        rhs = rows.project(data, folds, n_folds)
        total_gram, total_rhs = grams.sum(axis=0), rhs.sum(axis=0)
        trace = float(np.trace(total_gram))
        solutions = np.empty_like(rhs)
        for f in range(n_folds):
            system = self._system(total_gram - grams[f], trace)
            solutions[f] = la.cho_solve(la.cho_factor(system, check_finite=False),
                                        total_rhs - rhs[f], check_finite=False)
        pred = np.einsum("nm,nmc->nc", rows.values, solutions[folds[:, None], rows.columns])
        return float(np.sqrt(np.mean(np.sum((pred - data) ** 2, axis=1))))

"""Sparse basis rows with the same number of entries in every row, grouped by knot-span cell.

A B-spline basis matrix evaluated at N points has exactly m = (p + 1)(q + 1) non-zeros per
row (per point), so it is kept as two dense (N, m) arrays: values and columns. Points in
one knot-span cell share their columns, so the Gram matrix ``R^T R`` is a sum of dense
m x m blocks ``B_c^T B_c``, one small matrix product per cell (:class:`CellBlocks`), and
quadratic forms ``r_i^T A r_i`` (leverages) use the matching m x m blocks of A.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


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

    def scaled(self, factors: np.ndarray) -> "Rows":
        """Every row times its factor (N,): ``diag(factors) R``."""
        return Rows(self.values * factors[:, None], self.columns, self.n_columns, self.cells)

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

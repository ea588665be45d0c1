"""Sparse basis rows with the same number of entries in every row, grouped by knot-span cell.

A B-spline basis matrix evaluated at N points has exactly m = (p + 1)(q + 1) non-zeros per
row (per point), so it is kept as two dense (N, m) arrays: values and columns. Points in
one knot-span cell share their columns, so the Gram matrix ``R^T R`` is a sum of dense
m x m blocks ``B_c^T B_c``, one small matrix product per cell (:class:`CellBlocks`), and
quadratic forms ``r_i^T A r_i`` (leverages) use the matching m x m blocks of A. Sums
over rows run a chunk of rows at a time, so no work array grows with N beyond a chunk.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .compiled import chunks

ROW_CHUNK = 1 << 17  # rows summed together: work arrays of some 20 MB (m = 16) whatever N
BLOCK_HEIGHT = 64  # at most this many rows of a cell in one dense block


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
        """``R C`` for coefficients (n, ...), ``ROW_CHUNK`` rows at a time."""
        if len(self.values) <= ROW_CHUNK:
            return np.einsum("nm,nm...->n...", self.values, coeffs[self.columns])
        out = np.empty((len(self.values),) + coeffs.shape[1:])
        for part in chunks(len(self.values), ROW_CHUNK):
            out[part] = np.einsum("nm,nm...->n...", self.values[part], coeffs[self.columns[part]])
        return out

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
        """``R^T X`` for data (N, k), shape (n, k); summed ``ROW_CHUNK`` rows at a time."""
        out = np.zeros((self.n_columns, data.shape[1]))
        for part in chunks(len(self.values), ROW_CHUNK):
            cols, values = self.columns[part].ravel(), self.values[part]
            out += np.stack([np.bincount(cols, (values * data[part, c:c + 1]).ravel(), self.n_columns)
                             for c in range(data.shape[1])], axis=1)
        return out


class CellBlocks:
    """The rows grouped by cell into zero-padded dense blocks, taken a batch at a time.

    While one block per cell, padded to the most rows of a cell, fits in a batch of
    ``ROW_CHUNK`` rows, that is the layout (one batch). Otherwise the rows of a cell are
    cut into blocks of ``height = BLOCK_HEIGHT`` rows (a cell's last block zero-padded),
    so the padded rows number at most N + cells x height (a dense cell never inflates
    the others), and the blocks are processed in batches (``batches``: slices of
    blocks) of about ``ROW_CHUNK`` rows: the work arrays have a chunk's size whatever N.

    Any per-row quantity (N, ...) is laid out like the rows by :meth:`pad`, and dense
    per-block products (blocks, m, m) are added at their columns by :meth:`place`.
    """

    def __init__(self, rows: Rows):
        n_rows, m = rows.values.shape
        self.rows, self.m, self.n = rows, m, rows.n_columns
        self.order = np.argsort(rows.cells, kind="stable")
        sorted_cells = rows.cells[self.order]
        starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]]) if n_rows else np.zeros(0, int)
        counts = np.diff(np.r_[starts, n_rows])
        most = int(counts.max(initial=0)) or 1
        # one block per cell while all of them fit in a batch; else blocks of BLOCK_HEIGHT rows
        self.height = most if len(counts) * (most + m) <= ROW_CHUNK else min(most, BLOCK_HEIGHT)
        blocks_of_cell = -(-counts // self.height)
        first_block = np.cumsum(blocks_of_cell) - blocks_of_cell
        rank = np.arange(n_rows) - np.repeat(starts, counts)  # of a sorted row within its cell
        self.block = np.repeat(first_block, counts) + rank // self.height  # (N,) per sorted row
        self.slot = rank % self.height
        self.columns = np.repeat(rows.columns[self.order[starts]], blocks_of_cell, axis=0)  # (blocks, m)
        # block b holds the sorted rows block_start[b]:block_start[b + 1]
        self.block_start = np.searchsorted(self.block, np.arange(len(self.columns) + 1))
        per_batch = max(1, ROW_CHUNK // (self.height + m))
        self.batches = [slice(b, min(b + per_batch, len(self.columns))) for b in range(0, len(self.columns), per_batch)]

    def _sorted_rows(self, batch: slice) -> slice:
        return slice(self.block_start[batch.start], self.block_start[batch.stop])

    def pad(self, values: np.ndarray, batch: slice) -> np.ndarray:
        """``values`` (N, ...) given per row, in the rows' order, laid out as the batch's
        zero-padded blocks: (blocks, height, ...)."""
        rows = self._sorted_rows(batch)
        out = np.zeros((batch.stop - batch.start, self.height) + values.shape[1:])
        out[self.block[rows] - batch.start, self.slot[rows]] = values[self.order[rows]]
        return out

    def unpad(self, padded: np.ndarray, batch: slice, out: np.ndarray) -> None:
        """Write per-row values laid out as the batch's blocks back into ``out`` (N, ...)."""
        rows = self._sorted_rows(batch)
        out[self.order[rows]] = padded[self.block[rows] - batch.start, self.slot[rows]]

    def _scatter_index(self, batch: slice) -> np.ndarray:
        cols = self.columns[batch].astype(np.int64)
        return cols[:, :, None] * self.n + cols[:, None, :]

    def place(self, local: np.ndarray, batch: slice) -> np.ndarray:
        """The sum of the batch's dense blocks (blocks, m, m), each at its columns: (n, n)."""
        return np.bincount(self._scatter_index(batch).ravel(), local.ravel(), self.n * self.n).reshape(self.n, self.n)

    def gram(self, left: np.ndarray | None = None, right: np.ndarray | None = None) -> np.ndarray:
        """``R^T R = sum over blocks of B_b^T B_b`` placed at the block's columns, shape (n, n).

        With ``left`` and ``right`` (N, m), values on the rows' columns (either defaults
        to the rows' own): the cross Gram ``sum_i x_i y_i^T`` of those instead.
        """
        out = np.zeros((self.n, self.n))
        for batch in self.batches:
            x = self.pad(self.rows.values if left is None else left, batch)
            y = x if right is None and left is None else self.pad(self.rows.values if right is None else right, batch)
            out += self.place(np.matmul(x.transpose(0, 2, 1), y), batch)
        return out

    def quadratic_forms(self, matrix: np.ndarray) -> np.ndarray:
        """``r_i^T A r_i`` for every row i (in the rows' original order)."""
        out = np.empty(len(self.order))
        flat = matrix.ravel()
        for batch in self.batches:
            padded = self.pad(self.rows.values, batch)
            local = flat[self._scatter_index(batch)]  # (blocks, m, m)
            self.unpad(np.sum(np.matmul(padded, local) * padded, axis=2), batch, out)
        return out

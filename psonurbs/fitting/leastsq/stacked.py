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

:func:`particle_errors` is the compiled twin (numba, :mod:`psonurbs.geometry.compiled`)
of the same computation, one particle at a time in a loop instead of numpy's passes over
padded (chunks, slots, m) arrays: about 3 x faster, the same numbers to rounding. Its
normal equations (:func:`normal_equations`) also solve a single net at given parameters
(:func:`least_squares_at`, the polish's solve in every round): some 10 x faster than
building the rows through scipy and summing their Gram blocks.
"""
from __future__ import annotations

from functools import cached_property, lru_cache
from typing import Callable

import numpy as np

from psonurbs.geometry import compiled
from psonurbs.geometry.basis import uniform_inner_knots
from psonurbs.geometry.compiled import kernel
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.stacked_rows import LANES, CellLayout, StackedRows, knot_vectors, particle_cells, particle_rows

from .banded import BandOrder, StackedBandedCholesky, band_cholesky, band_selected_inverse, band_solve
from .solve import CONSTRAINT_WEIGHT, RegularisedLeastSquares

RIDGE = 1e-12  # relative to the mean diagonal, as in RegularisedLeastSquares.normal_matrix
PER_PARTICLE = ("knots_u", "knots_v", "weights", "term_scales")  # the kernels' inputs with a row per particle


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

    @cached_property
    def _upper_terms(self) -> tuple[np.ndarray, np.ndarray]:
        """The regulariser's entries on and above the diagonal in band order, for
        :func:`particle_errors`: (E, 3) (row, column, term) and their values (E,)."""
        entries, values = [], []
        for term, (r, c, v, _) in enumerate(self.terms):
            upper = c >= r
            entries.append(np.column_stack([r[upper], c[upper], np.full(upper.sum(), term)]))
            values.append(v[upper])
        return (np.concatenate(entries or [np.zeros((0, 3), np.int64)]).astype(np.int64),
                np.concatenate(values or [np.zeros(0)]).astype(float))

    def _kernel_inputs(self, weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray, smoothing: np.ndarray,
                       uv: np.ndarray, data: np.ndarray, point_weights: np.ndarray | None) -> dict:
        """The arguments :func:`particle_errors` and :func:`particle_control` share, as
        contiguous arrays: P particles' full knot vectors, weights and regulariser scales."""
        layout = self.cells.layout
        knots = [np.ascontiguousarray(knot_vectors(n, d, c, inner)) for n, d, c, inner in
                 zip(layout.size, layout.degrees, layout.closed, (inner_u, inner_v))]
        knots = [k if len(k) == len(weights) else np.repeat(k, len(weights), axis=0) for k in knots]  # a row each
        smoothing = np.asarray(smoothing, float)
        scales = np.column_stack([smoothing / self.solver.penalty_trace if weight is None
                                  else np.full(len(smoothing), weight) for *_, weight in self.terms]
                                 or [np.zeros(len(smoothing))])
        entries, values = self._upper_terms
        point_weights = np.ones(len(data)) if point_weights is None else np.asarray(point_weights, float)
        return dict(uv=np.ascontiguousarray(uv, float), data=np.ascontiguousarray(data, float),
                    point_weights=np.ascontiguousarray(point_weights, float), knots_u=knots[0], knots_v=knots[1],
                    weights=np.ascontiguousarray(weights, float), degrees=np.asarray(layout.degrees, np.int64),
                    cells_v=self.cells.shape[1], free_columns=self.cells.columns.astype(np.int64),
                    band_columns=self.columns.astype(np.int64), half_bandwidth=self.order.half_bandwidth,
                    term_entries=entries, term_values=values, term_scales=np.ascontiguousarray(scales))

    def compiled_errors(self, uv: np.ndarray, weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray,
                        data: np.ndarray, smoothing: np.ndarray, cross_validation: bool,
                        point_weights: np.ndarray | None = None) -> np.ndarray:
        """:meth:`errors` of the rows ``stacked_rows(self.cells, uv, weights, inner_u, inner_v)``
        by the compiled kernel (:func:`particle_errors`), particle by particle: (P,), inf
        for a particle whose normal matrix is not positive definite."""
        given = self._kernel_inputs(weights, inner_u, inner_v, smoothing, uv, data, point_weights)
        out = np.empty(len(weights))

        def evaluate(part: slice) -> None:  # particles are independent: a part's errors are its own
            out[part] = particle_errors(**{**given, **{key: given[key][part] for key in PER_PARTICLE}},
                                        cross_validation=bool(cross_validation))

        compiled.over_parts(len(weights), evaluate)
        return out

    def compiled_control(self, uv: np.ndarray, shape: NetShape, data: np.ndarray,
                         point_weights: np.ndarray | None = None) -> np.ndarray:
        """The free control points (n, dim) of one net ``shape`` (weights, inner knots or
        None for uniform) at the parameters uv (N, 2): the solver's
        ``solve(layout.rows(uv, *shape), data, point_weights)`` by the compiled kernel
        (:func:`particle_control`), the same numbers to rounding. Raises LinAlgError if
        the normal matrix is not positive definite."""
        inner = [uniform_inner_knots(count) if knots is None else knots
                 for count, knots in zip(self.cells.layout.inner_counts, (shape.inner_u, shape.inner_v))]
        given = self._kernel_inputs(np.asarray(shape.weights, float)[None], inner[0], inner[1],
                                    np.array([self.solver.smoothing]), uv, data, point_weights)
        control = np.empty((self.n, np.shape(data)[1]))
        if not particle_control(**{**given, **{key: given[key][0] for key in PER_PARTICLE}}, control=control):
            raise np.linalg.LinAlgError("the normal matrix is not positive definite")
        return control[self.order.position]

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


@kernel
def cell_order(cell_of: np.ndarray, first: np.ndarray, order: np.ndarray) -> None:
    """Counting sort of the points by cell: ``order`` (N,) the points of cell c, in their
    given order, at ``first[c]:first[c + 1]`` (``first`` (cells + 1,))."""
    first[:] = 0
    for i in range(cell_of.shape[0]):
        first[cell_of[i] + 1] += 1
    for c in range(first.shape[0] - 1):
        first[c + 1] += first[c]
    for i in range(cell_of.shape[0]):
        order[first[cell_of[i]]] = i
        first[cell_of[i]] += 1
    for c in range(first.shape[0] - 1, 0, -1):
        first[c] = first[c - 1]
    first[0] = 0


@kernel
def normal_equations(uv: np.ndarray, data: np.ndarray, point_weights: np.ndarray, knots_u: np.ndarray,
                     knots_v: np.ndarray, weights: np.ndarray, degrees: np.ndarray, cells_v: int,
                     free_columns: np.ndarray, band_columns: np.ndarray, term_entries: np.ndarray,
                     term_values: np.ndarray, term_scales: np.ndarray, cell_of: np.ndarray, first: np.ndarray,
                     order: np.ndarray, augmented: np.ndarray, sorted_weights: np.ndarray, block: np.ndarray,
                     band: np.ndarray, control: np.ndarray) -> None:
    """One particle's normal equations ``M P = R^T W X`` in the upper band (band order):
    ``band`` (n, w + 1) holds M, ``control`` (n, dim) the right-hand side.

    The particle has full knot vectors ``knots_u``, ``knots_v`` and free ``weights``
    (:func:`particle_rows`); its points sorted by cell (:func:`cell_order`: ``first``,
    ``order``), each cell adds its m x m Gram block and its right-hand side at
    ``band_columns[cell]``; the regulariser is ``term_values[e] * term_scales[term] * t``
    at the upper entries ``term_entries[e] = (row, column, term)``, then the ridge
    (:meth:`StackedLeastSquares.normal_matrices`). The work arrays are the caller's:
    ``augmented`` (N, width) holds each sorted point's [row (m), point (dim), 0 ...]
    afterwards, ``sorted_weights`` (N,) its weight, ``cell_of`` (N,), ``block`` (m, width)."""
    n_points, dim = uv.shape[0], data.shape[1]
    n_cells, m = band_columns.shape[0], band_columns.shape[1]
    n, width = band.shape[0], augmented.shape[1]
    particle_cells(uv, knots_u, knots_v, degrees, cells_v, cell_of)
    cell_order(cell_of, first, order)
    particle_rows(uv, knots_u, knots_v, degrees, cells_v, weights, free_columns, first, order, augmented)
    for s in range(n_points):
        i = order[s]
        sorted_weights[s] = point_weights[i]
        for d in range(dim):
            augmented[s, m + d] = data[i, d]
    band[:] = 0.0
    control[:] = 0.0
    for c in range(n_cells):  # the Gram blocks and right-hand sides: sum of w r [r, x]
        if first[c] == first[c + 1]:
            continue
        block[:] = 0.0
        start, end = first[c], first[c + 1]
        while start + 4 <= end:  # four points a pass: a quarter of the loads and stores of block
            s = start
            r0, r1, r2, r3 = augmented[s], augmented[s + 1], augmented[s + 2], augmented[s + 3]
            w0, w1, w2, w3 = sorted_weights[s], sorted_weights[s + 1], sorted_weights[s + 2], sorted_weights[s + 3]
            for a in range(m):
                x0, x1, x2, x3, gram = r0[a] * w0, r1[a] * w1, r2[a] * w2, r3[a] * w3, block[a]
                for b in range(width):  # (1-d rows, loops from 0 over whole LANES: numba vectorises)
                    gram[b] += ((x0 * r0[b] + x1 * r1[b]) + x2 * r2[b]) + x3 * r3[b]
            start += 4
        for s in range(start, end):
            row = augmented[s]
            for a in range(m):
                ra, gram = row[a] * sorted_weights[s], block[a]
                for b in range(width):
                    gram[b] += ra * row[b]
        for a in range(m):
            ca = band_columns[c, a]
            for b in range(m):
                cb = band_columns[c, b]
                if cb >= ca:
                    band[ca, cb - ca] += block[a, b]
            for d in range(dim):
                control[ca, d] += block[a, m + d]
    trace = 0.0
    for j in range(n):
        trace += band[j, 0]
    for e in range(term_values.shape[0]):
        r, c = term_entries[e, 0], term_entries[e, 1]
        band[r, c - r] += term_scales[term_entries[e, 2]] * trace * term_values[e]
    for j in range(n):
        band[j, 0] += RIDGE * trace / n


@kernel
def particle_control(uv: np.ndarray, data: np.ndarray, point_weights: np.ndarray, knots_u: np.ndarray,
                     knots_v: np.ndarray, weights: np.ndarray, degrees: np.ndarray, cells_v: int,
                     free_columns: np.ndarray, band_columns: np.ndarray, half_bandwidth: int,
                     term_entries: np.ndarray, term_values: np.ndarray, term_scales: np.ndarray,
                     control: np.ndarray) -> bool:
    """One particle's control points ``control`` (n, dim) in band order (the weighted,
    regularised least squares of :func:`normal_equations`); False where M is not
    positive definite."""
    n_points, dim = uv.shape[0], data.shape[1]
    n_cells, m = band_columns.shape[0], band_columns.shape[1]
    n, width = control.shape[0], -(-(m + dim) // LANES) * LANES
    cell_of, order, first = np.empty(n_points, np.int64), np.empty(n_points, np.int64), np.empty(n_cells + 1, np.int64)
    augmented, sorted_weights = np.zeros((n_points, width)), np.empty(n_points)
    block, band = np.empty((m, width)), np.empty((n, half_bandwidth + 1))
    normal_equations(uv, data, point_weights, knots_u, knots_v, weights, degrees, cells_v, free_columns, band_columns,
                     term_entries, term_values, term_scales, cell_of, first, order, augmented, sorted_weights, block,
                     band, control)
    if not band_cholesky(band):
        return False
    band_solve(band, control)
    return True


@kernel
def particle_errors(uv: np.ndarray, data: np.ndarray, point_weights: np.ndarray, knots_u: np.ndarray,
                    knots_v: np.ndarray, weights: np.ndarray, degrees: np.ndarray, cells_v: int,
                    free_columns: np.ndarray, band_columns: np.ndarray, half_bandwidth: int,
                    term_entries: np.ndarray, term_values: np.ndarray, term_scales: np.ndarray,
                    cross_validation: bool) -> np.ndarray:
    """The compiled twin of :meth:`StackedLeastSquares.errors` after :func:`stacked_rows`,
    one particle at a time: (P,) errors, inf where M_k is not positive definite.

    Particle k's normal equations come from :func:`normal_equations` (its knots
    ``knots_u[k]``, ``knots_v[k]``, weights ``weights[k]``, regulariser scales
    ``term_scales[k]``); the leverages read each cell's m x m block of the selected
    inverse. ``point_weights`` are ones for the unweighted fitness (the same numbers)."""
    n_particles, n_points, dim = weights.shape[0], uv.shape[0], data.shape[1]
    n_cells, m = band_columns.shape[0], band_columns.shape[1]
    n, width = band_columns.max() + 1, -(-(m + dim) // LANES) * LANES
    cell_of = np.empty(n_points, np.int64)
    first, order = np.empty(n_cells + 1, np.int64), np.empty(n_points, np.int64)
    augmented = np.zeros((n_points, width))  # by cell: [row (m), point (dim), 0 ...]
    sorted_weights = np.empty(n_points)
    band, control = np.empty((n, half_bandwidth + 1)), np.empty((n, dim))
    inverse = np.zeros((n, 2 * half_bandwidth + 1 + LANES))
    block, product = np.empty((m, width)), np.empty(width)
    total_weight = 0.0
    for i in range(n_points):
        total_weight += point_weights[i]
    out = np.empty(n_particles)
    for k in range(n_particles):
        normal_equations(uv, data, point_weights, knots_u[k], knots_v[k], weights[k], degrees, cells_v, free_columns,
                         band_columns, term_entries, term_values, term_scales[k], cell_of, first, order, augmented,
                         sorted_weights, block, band, control)
        if not band_cholesky(band):
            out[k] = np.inf
            continue
        band_solve(band, control)
        if cross_validation:
            band_selected_inverse(band, inverse)
        squares = 0.0
        for c in range(n_cells):  # the (leave-one-out) residuals: r^T [S_c, P_c] = [S r, fitted]
            if first[c] == first[c + 1]:
                continue
            block[:] = 0.0
            for a in range(m):
                ca = band_columns[c, a]
                if cross_validation:
                    for b in range(m):
                        block[a, b] = inverse[ca, half_bandwidth + band_columns[c, b] - ca]
                for d in range(dim):
                    block[a, m + d] = control[ca, d]
            for s in range(first[c], first[c + 1]):
                row = augmented[s]
                product[:] = 0.0
                done = 0
                while done + 4 <= m:  # four rows of the block a pass
                    a = done
                    x0, x1, x2, x3 = row[a], row[a + 1], row[a + 2], row[a + 3]
                    b0, b1, b2, b3 = block[a], block[a + 1], block[a + 2], block[a + 3]
                    for b in range(width):
                        product[b] += ((x0 * b0[b] + x1 * b1[b]) + x2 * b2[b]) + x3 * b3[b]
                    done += 4
                for a in range(done, m):
                    ra, cell_row = row[a], block[a]
                    for b in range(width):
                        product[b] += ra * cell_row[b]
                divisor = 1.0
                if cross_validation:
                    leverage = 0.0
                    for b in range(m):
                        leverage += row[b] * product[b]
                    divisor = max(1.0 - leverage * sorted_weights[s], 1e-12)
                norm = 0.0
                for d in range(dim):
                    residual = (product[m + d] - row[m + d]) / divisor
                    norm += residual * residual
                squares += norm * sorted_weights[s]
        out[k] = np.sqrt(squares / total_weight) if total_weight > 0.0 else np.nan
    return out


def least_squares_at(layout: NetLayout, solver: RegularisedLeastSquares
                     ) -> Callable[[np.ndarray, NetShape, np.ndarray, np.ndarray | None], np.ndarray]:
    """``fit(uv, shape, points, point_weights)``: the free control points of ``solver``'s
    problem for one net of ``layout`` at the parameters uv, as
    ``solver.solve(layout.rows(uv, *shape), points, point_weights)`` computes them; by
    the compiled kernel (:meth:`StackedLeastSquares.compiled_control`, some 10 x faster)
    where :data:`psonurbs.geometry.compiled.ENABLED`."""
    if compiled.ENABLED:
        return StackedLeastSquares(solver, CellLayout(layout)).compiled_control
    return lambda uv, shape, points, point_weights=None: solver.solve(layout.rows(uv, *shape), points, point_weights)

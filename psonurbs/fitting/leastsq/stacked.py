"""The regularised least squares and its leave-one-out error for P particles at once.

The batched counterpart of :class:`psonurbs.fitting.leastsq.regularised.RegularisedLeastSquares` for
the swarm: particle k has its own rows R_k (knots, weights) and smoothing lam_k, all
share the points X, the smoothness operator L, the pole conditions C and optional
per-point weights w (N,). For each particle

    M_k = R_k^T W R_k + lam_k t_k / tr(L^T L) L^T L + kappa t_k / tr(C^T C) C^T C + ridge,
    t_k = tr(R_k^T W R_k),        M_k P_k = R_k^T W X,

exactly as the single solver does, and the leave-one-out residual of point i is
``e_i / (1 - w_i h_i)`` with ``h_i = r_i^T M_k^-1 r_i`` (exact for the weighted solve).

The Gram matrix is a sum of m x m blocks, one per chunk of rows of one cell (a
product over the chunk's slots, :class:`psonurbs.geometry.stacked_rows.StackedRows`).
The systems are factored in a banded order (:mod:`psonurbs.fitting.leastsq.banded`) and the
leverages read the blocks of M^-1 at each cell's columns from its selected inverse.

Its compiled twin is :mod:`psonurbs.fitting.leastsq.stacked_compiled` (numba, one particle
at a time: :meth:`StackedLeastSquares.compiled_errors`), used where
:data:`psonurbs.geometry.compiled.ENABLED`; both read the regulariser's scales from
:meth:`StackedLeastSquares.term_scales`. Its single-net solve also serves the polish
(:func:`least_squares_at`).
"""
from __future__ import annotations

from functools import cached_property, lru_cache
from typing import Callable

import numpy as np

from psonurbs.geometry import compiled
from psonurbs.geometry.basis import uniform_inner_knots
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.stacked_rows import CellLayout, StackedRows, knot_vectors

from .banded import BandOrder, StackedBandedCholesky
from .regularised import CONSTRAINT_WEIGHT, LEVERAGE_FLOOR, RIDGE, RegularisedLeastSquares
from .stacked_compiled import particle_control, particle_errors

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

    def term_scales(self, smoothing: np.ndarray) -> np.ndarray:
        """(P, terms) the regulariser's scale per particle and term: term j adds
        ``scale[k, j] * t_k * values_j`` to M_k, with ``lam_k / tr(L^T L)`` for the
        smoothness and ``kappa / tr(C^T C)`` for the conditions (both twins use these)."""
        return np.column_stack([smoothing / self.solver.penalty_trace if weight is None
                                else np.full(len(smoothing), weight) for *_, weight in self.terms]
                               or [np.zeros(len(smoothing))])

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
        scales = self.term_scales(np.asarray(smoothing, float))
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
        for (r, c, values, _), factor in zip(self.terms, self.term_scales(smoothing).T):
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
            residual = residual / np.maximum(1.0 - leverage, LEVERAGE_FLOOR)[..., None]
        squared = np.einsum("tsk,tsk->ts", residual, residual)
        if slot_weights is None:
            return np.sqrt(rows.per_particle(squared) / len(data))
        return np.sqrt(rows.per_particle(squared * slot_weights) / np.sum(point_weights))


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

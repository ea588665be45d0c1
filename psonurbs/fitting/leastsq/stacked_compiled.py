"""The compiled (numba) twin of :mod:`psonurbs.fitting.leastsq.stacked`: the same
regularised least squares and leave-one-out error, one particle at a time.

Where numpy makes passes over padded (chunks, slots, m) arrays for all particles at
once, these kernels loop over one particle's points sorted by knot-span cell: each cell
adds its m x m Gram block and right-hand side to the band of M (band order,
:mod:`psonurbs.fitting.leastsq.banded`), the regulariser and the ridge are added as
:mod:`psonurbs.fitting.leastsq.regularised` defines them, M is factored in the band, and
the leverages ``h_i = r_i^T M^-1 r_i`` read each cell's block of the selected inverse.
About 3 x faster than the numpy twin for the swarm, the same numbers to rounding
(``tests/test_stacked_compiled.py``); the single-net solve (:func:`particle_control`)
some 10 x faster than building the rows through scipy.
"""
from __future__ import annotations

import numpy as np

from psonurbs.geometry.compiled import kernel
from psonurbs.geometry.stacked_rows import LANES, particle_cells, particle_rows

from .banded import band_cholesky, band_selected_inverse, band_solve
from .regularised import LEVERAGE_FLOOR, RIDGE


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
    (:meth:`psonurbs.fitting.leastsq.stacked.StackedLeastSquares.normal_matrices`). The work arrays are the caller's:
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
    """The compiled twin of :meth:`psonurbs.fitting.leastsq.stacked.StackedLeastSquares.errors`
    after :func:`psonurbs.geometry.stacked_rows.stacked_rows`,
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
                    divisor = max(1.0 - leverage * sorted_weights[s], LEVERAGE_FLOOR)
                norm = 0.0
                for d in range(dim):
                    residual = (product[m + d] - row[m + d]) / divisor
                    norm += residual * residual
                squares += norm * sorted_weights[s]
        out[k] = np.sqrt(squares / total_weight) if total_weight > 0.0 else np.nan
    return out

"""Basis rows of many knot vectors at once: the swarm's particles evaluated together.

Every particle of a swarm iteration has its own knot vectors and weights but the same
points. The row of point i for a particle is the rational tensor basis

    r_i = w_c o (u_i (x) v_i) / W_i,      W_i = sum_c w_c (u_i (x) v_i)_c,

where u_i (p + 1) and v_i (q + 1) are the non-zero B-spline values along u and v at
the point, c its knot-span cell and w_c the weights of the cell's m = (p + 1)(q + 1)
control points. Points of one cell share the cell's columns, and which columns a
cell has depends only on the layout (cell (a, b) starts at full-net column (a, b)),
never on the knots (:class:`CellLayout`).

:func:`stacked_rows` sorts each particle's points by cell into chunks of a few slots
and evaluates u and v there by de Boor's triangular recurrence ("The NURBS Book",
A2.2) over all chunks of all particles at once, as :meth:`NetLayout.rows` does for one
particle through scipy. A chunk's points share their span, so the recurrence's knot
differences are computed once per chunk.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from psonurbs.geometry.compiled import kernel
from psonurbs.geometry.net import NetLayout


def knot_vectors(n: int, degree: int, closed: bool, inner: np.ndarray) -> np.ndarray:
    """Full knot vectors (P, K) from P rows of inner knots, as
    :func:`psonurbs.geometry.basis.make_knots` builds one."""
    inner = np.atleast_2d(np.asarray(inner, float))
    rows = len(inner)
    if not closed:
        return np.concatenate([np.zeros((rows, degree + 1)), inner, np.ones((rows, degree + 1))], axis=1)
    b = np.concatenate([np.zeros((rows, 1)), inner, np.ones((rows, 1))], axis=1)
    return np.concatenate([b[:, n - degree:n] - 1.0, b, b[:, 1:degree + 1] + 1.0], axis=1)


def domain_spans(x: np.ndarray, knots: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Parameters (N,) clipped to each knot vector's domain ``[t_p, t_n]``, (P, N), and
    their spans k with ``t_k <= x < t_{k+1}`` (x = t_n in the last span, n - 1)."""
    n = knots.shape[1] - degree - 1
    x = np.clip(x[None, :], knots[:, degree:degree + 1], knots[:, n:n + 1])
    span = np.full(x.shape, degree)
    for k in range(degree + 1, n):
        span += x >= knots[:, k:k + 1]
    return x, span


def local_basis(x: np.ndarray, local_knots: np.ndarray, degree: int) -> np.ndarray:
    """The degree + 1 non-zero B-spline values at x (S, T), every column of x in one span
    k, given the knots ``t_{k-p+1} .. t_{k+p}`` around it (2p, T): shape (p + 1, S, T).

    De Boor's recurrence, ``left_i = x - t_{k+1-i}``, ``right_i = t_{k+i} - x``: level j
    takes ``N_r <- right_{r+1} N_r / d_r + left_{j-r+1} N_{r-1} / d_{r-1}`` with
    ``d_r = t_{k+r+1} - t_{k+r+1-j}``, a knot difference (one per column). The columns
    are the last axis, so every operation runs along them.
    """
    t = local_knots[:, None, :]  # t_{k-p+1+l} = t[l], (2p, 1, T)
    left = x - t[degree - 1::-1]  # left_1 .. left_p, (p, S, T)
    right = t[degree:] - x  # right_1 .. right_p
    values = np.ones((1,) + x.shape)
    for j in range(1, degree + 1):
        temp = values * (1.0 / (t[degree:degree + j] - t[degree - j:degree]))  # N_r / d_r, r < j
        new = np.empty((j + 1,) + x.shape)
        np.multiply(right[:j], temp, out=new[:j])
        new[j] = 0.0
        new[1:] += left[j - 1::-1] * temp
        values = new
    return values


@dataclass(frozen=True)
class CellLayout:
    """The knot-span cells of a net layout and the free columns each one touches.

    Cell ``c = a * cells_v + b`` (a, b the first non-zero basis function along u, v)
    touches the full-net columns ``(a + i) * full_v + b + j``, i <= p, j <= q, mapped
    to free control points: ``columns[c]`` (m,), in row-major (i, j) order.
    """

    layout: NetLayout

    @property
    def shape(self) -> tuple[int, int]:
        (fu, fv), (p, q) = self.layout.full_shape, self.layout.degrees
        return fu - p, fv - q

    @property
    def count(self) -> int:
        return self.shape[0] * self.shape[1]

    @cached_property
    def columns(self) -> np.ndarray:
        (cu, cv), (p, q), fv = self.shape, self.layout.degrees, self.layout.full_shape[1]
        a, b = np.meshgrid(np.arange(cu), np.arange(cv), indexing="ij")
        i, j = np.meshgrid(np.arange(p + 1), np.arange(q + 1), indexing="ij")
        full = (a.reshape(-1, 1) + i.reshape(1, -1)) * fv + b.reshape(-1, 1) + j.reshape(1, -1)
        return self.layout.free_index[full]


@dataclass(frozen=True)
class StackedRows:
    """The rational rows of P particles at the same N points, in chunks by cell.

    The points of particle k in cell c (the *block* ``k * cells + c``) are cut into
    chunks of ``slots`` rows, the last one zero-padded: ``values[t]`` (T, slots, m) are
    chunk t's rows, in block ``chunk_block[t]``, so at the columns
    ``cells.columns[chunk_block[t] % cells]``. Chunks are sorted by block;
    ``slot_of[k, i]`` (P, N) is where point i of particle k went, the flat slot
    ``t * slots + s``. Chunks bound the padding whatever the knots do to the counts per
    cell: a cell holding many points takes several chunks.
    """

    cells: CellLayout
    values: np.ndarray
    chunk_block: np.ndarray
    slot_of: np.ndarray

    @property
    def n_particles(self) -> int:
        return self.slot_of.shape[0]

    def gather(self, data: np.ndarray) -> np.ndarray:
        """Per-point data (N, ...) laid out like the rows: (T, slots, ...), zero-padded."""
        out = np.zeros((self.values.shape[0] * self.values.shape[1],) + data.shape[1:])
        out[self.slot_of] = data
        return out.reshape(self.values.shape[:2] + data.shape[1:])

    def scatter(self, chunked: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`gather`: (T, slots, ...) -> (P, N, ...)."""
        return chunked.reshape((-1,) + chunked.shape[2:])[self.slot_of]

    @cached_property
    def _summation(self) -> sp.csr_array:
        """(P * cells, T) 0/1 matrix adding up each block's chunks."""
        count = len(self.chunk_block)
        return sp.csr_array((np.ones(count), (self.chunk_block, np.arange(count))),
                            shape=(self.n_particles * self.cells.count, count))

    def per_block(self, chunked: np.ndarray) -> np.ndarray:
        """Sums over each block's chunks of (T, ...) values: (P * cells, ...), zero for
        the blocks without points."""
        flat = self._summation @ chunked.reshape(len(chunked), -1)
        return flat.reshape((-1,) + chunked.shape[1:])

    def per_particle(self, chunked: np.ndarray) -> np.ndarray:
        """Sum of (T, slots) values over each particle's slots, (P,)."""
        return np.bincount(self.chunk_block // self.cells.count, chunked.sum(axis=1), self.n_particles)


def chunk_slots(block: np.ndarray, n_blocks: int, slots: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat slot ``t * slots + s`` of every entry of ``block`` (M,) and the block of
    every chunk (T,), chunks sorted by block, a block's entries in their given order."""
    order = np.argsort(block.astype(np.int16) if n_blocks < 2 ** 15 else block, kind="stable")  # radix sort
    counts = np.bincount(block, minlength=n_blocks)
    chunks = -(-counts // slots)
    first_chunk = np.cumsum(chunks) - chunks
    rank = np.arange(len(block)) - np.repeat(np.cumsum(counts) - counts, counts)
    slot_of = np.empty(len(block), np.int64)
    slot_of[order] = (first_chunk[block[order]] + rank // slots) * slots + rank % slots
    return slot_of, np.repeat(np.arange(n_blocks), chunks)


def stacked_rows(cells: CellLayout, uv: np.ndarray, weights: np.ndarray,
                 inner_u: np.ndarray, inner_v: np.ndarray) -> StackedRows:
    """Rational rows of P particles of ``cells.layout`` at the points ``uv`` (N, 2):
    ``weights`` (P, n_free), inner knots (P, count_u) and (P, count_v). Particle k's rows
    equal ``layout.rows(uv, weights[k], inner_u[k], inner_v[k])`` up to rounding."""
    layout = cells.layout
    knots = [knot_vectors(n, d, c, inner) for n, d, c, inner in
             zip(layout.size, layout.degrees, layout.closed, (inner_u, inner_v))]
    (xu, su), (xv, sv) = (domain_spans(uv[:, k], knots[k], layout.degrees[k]) for k in (0, 1))
    n_particles, n_points = su.shape
    (p, q), m = layout.degrees, np.prod(np.add(layout.degrees, 1))
    first_u, first_v = su - p, sv - q
    block = (first_u * cells.shape[1] + first_v + cells.count * np.arange(n_particles)[:, None]).ravel()
    slots = int(np.clip(np.ceil(n_points / cells.count), 4, m))
    slot_of, chunk_block = chunk_slots(block, n_particles * cells.count, slots)
    chunks = len(chunk_block)
    particle, cell = chunk_block // cells.count, chunk_block % cells.count
    across = (slot_of % slots) * chunks + slot_of // slots  # the same slots, laid out (slots, chunks)
    filled = np.zeros(slots * chunks, bool)
    filled[across] = True
    filled = filled.reshape(slots, chunks)
    directions = []
    for x, degree, first, knot in ((xu, p, cell // cells.shape[1], knots[0]),
                                   (xv, q, cell % cells.shape[1], knots[1])):
        placed = np.empty(slots * chunks)
        placed[across] = x.ravel()
        start = knot[particle, first + degree]
        placed = np.where(filled, placed.reshape(slots, chunks), start)  # padding on the span's left knot
        around = knot[particle, first + 1 + np.arange(2 * degree)[:, None]]  # t_{k-p+1} .. t_{k+p}, (2p, T)
        directions.append(local_basis(placed, around, degree))
    u, v = directions
    u *= filled  # padding rows are 0
    tensor = (u[:, None] * v[None, :]).reshape(m, slots, chunks)
    tensor *= weights[particle, cells.columns[cell].T][:, None, :]
    tensor /= np.where(filled, tensor.sum(axis=0), 1.0)
    values = np.ascontiguousarray(tensor.transpose(2, 1, 0))  # (T, slots, m) for the products per chunk
    return StackedRows(cells, values, chunk_block, slot_of.reshape(n_particles, n_points))


# Compiled twins (numba, :mod:`psonurbs.geometry.compiled`) for one particle: the cells
# of the points first, then the rows cell by cell, the recurrence running over a cell's
# points (one span, the same knots) as numpy runs it over the columns of a chunk.

LANES = 8  # compiled inner loops run over multiples of this (a vector's doubles): no scalar tails


@kernel
def span_of(x: float, knots: np.ndarray, degree: int) -> int:
    """The span of x (:func:`domain_spans`) in the full knot vector ``knots`` (K,)."""
    n = knots.shape[0] - degree - 1
    x = min(max(x, knots[degree]), knots[n])
    span = degree
    for k in range(degree + 1, n):
        if x >= knots[k]:
            span += 1
    return span


@kernel
def particle_cells(uv: np.ndarray, knots_u: np.ndarray, knots_v: np.ndarray, degrees: np.ndarray, cells_v: int,
                   cell_of: np.ndarray) -> None:
    """The cell ``a * cells_v + b`` of each point ``uv[i]`` (a, b its spans less the
    degrees) in ``cell_of[i]``, for one particle's full knot vectors."""
    p, q = degrees[0], degrees[1]
    for i in range(uv.shape[0]):
        cell_of[i] = (span_of(uv[i, 0], knots_u, p) - p) * cells_v + span_of(uv[i, 1], knots_v, q) - q


@kernel
def cell_basis(x: np.ndarray, knots: np.ndarray, span: int, degree: int, out: np.ndarray) -> None:
    """The compiled twin of :func:`local_basis`: the degree + 1 non-zero B-spline values
    ``out[:, s]`` at the parameters ``x[s]`` (S,) of one span, the same recurrence in
    the same order, S a multiple of LANES (the padding is discarded)."""
    n = knots.shape[0] - degree - 1
    for s in range(x.shape[0]):
        x[s] = min(max(x[s], knots[degree]), knots[n])
    first = out[0]
    for s in range(x.shape[0]):
        first[s] = 1.0
    for j in range(1, degree + 1):
        saved = out[j]
        for s in range(x.shape[0]):
            saved[s] = 0.0
        for r in range(j):
            gap = knots[span + 1 + r] - knots[span + 1 + r - j]  # d_r
            inverse_gap = 1.0 / gap if gap != 0.0 else np.inf  # (as numpy divides)
            right, left = knots[span + 1 + r], knots[span + r + 1 - j]
            values = out[r]
            for s in range(x.shape[0]):
                temp = values[s] * inverse_gap  # N_r / d_r
                values[s] = (right - x[s]) * temp + saved[s]  # right_{r+1} N_r / d_r + ...
                saved[s] = (x[s] - left) * temp  # left_{j-r} N_r / d_r


@kernel
def particle_rows(uv: np.ndarray, knots_u: np.ndarray, knots_v: np.ndarray, degrees: np.ndarray, cells_v: int,
                  weights: np.ndarray, free_columns: np.ndarray, first: np.ndarray, order: np.ndarray,
                  rows: np.ndarray) -> None:
    """The compiled twin of :func:`stacked_rows` for one particle: ``rows[s, :m]`` the
    rational row of the point ``order[s]``, where the points of cell c are at
    ``first[c]:first[c + 1]`` (:func:`particle_cells`, then a sort), for the full knot
    vectors, free ``weights`` and ``free_columns`` (cells, m) = ``CellLayout.columns``
    (entry a (q + 1) + b: the a-th basis function along u times the b-th along v)."""
    p, q = degrees[0], degrees[1]
    most = 0
    for c in range(first.shape[0] - 1):
        most = max(most, first[c + 1] - first[c])
    most = -(-most // LANES) * LANES
    x_u, x_v = np.empty(most), np.empty(most)
    along_u, along_v = np.empty((p + 1, most)), np.empty((q + 1, most))
    for c in range(first.shape[0] - 1):
        start, count = first[c], first[c + 1] - first[c]
        if count == 0:
            continue
        padded = -(-count // LANES) * LANES
        for s in range(padded):
            i = order[start + min(s, count - 1)]
            x_u[s], x_v[s] = uv[i, 0], uv[i, 1]
        cell_basis(x_u[:padded], knots_u, c // cells_v + p, p, along_u[:, :padded])
        cell_basis(x_v[:padded], knots_v, c % cells_v + q, q, along_v[:, :padded])
        columns = free_columns[c]
        for s in range(count):
            row, total = rows[start + s], 0.0
            for a in range(p + 1):
                for b in range(q + 1):
                    e = a * (q + 1) + b
                    value = along_u[a, s] * along_v[b, s] * weights[columns[e]]
                    row[e] = value
                    total += value
            scale = 1.0 / total if total != 0.0 else np.nan  # (numpy's 0 / 0; one division, not m)
            for e in range((p + 1) * (q + 1)):
                row[e] *= scale

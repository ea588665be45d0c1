"""Banded factorisation: P symmetric banded systems at once, with selected inversion (the
swarm's fitness), and one system assembled and solved in LAPACK's band storage
(:class:`BandOrder`: the joint refinement's net system of 4 unknowns per control point).

The normal matrix of a tensor-product net couples control points (i, j) and (i', j')
only if |i - i'| <= p and |j - j'| <= q, so in row-major order it is banded with half
bandwidth w ~ p * nv + q, much less than its size n (w = 39, n = 144 on a 12 x 12
cubic net), and its factors stay inside the band. Leave-one-out leverages
``h_i = r_i^T M^-1 r_i`` only need the entries of M^-1 at pairs of columns one row
touches, which lie inside the band too; Takahashi's recurrences give exactly those
entries from the factors, in O(n w^2) instead of the O(n^3) of a full inverse.

Everything runs on dense (P, n, n) storage, b columns at a time (a block LDL^T), so a
step is a few batched matrix products over all P systems. With J a block's columns and
R the rows below it inside the band (J's next w rows):

    factor:   D_J = A_JJ,  G_J = A_RJ D_J^-1,  A_RR -= G_J A_RJ^T
    inverse:  S_RJ = -S_RR G_J,  S_JJ = D_J^-1 - G_J^T S_RJ      (last block first)
    solve:    y_R -= G_J y_J (forward),  x_J = D_J^-1 y_J - G_J^T x_R (backward)

S_RR was filled by the blocks after J. Only band entries of S (and a few just past it)
are computed; the rest stay 0. Each D_J is checked positive definite by a Cholesky
factorisation, as the single solver's ``cho_factor`` would.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from psonurbs.geometry.compiled import kernel
from psonurbs.geometry.stacked_rows import LANES

BLOCK = 16  # columns per step of the factorisation


@dataclass(frozen=True)
class BandOrder:
    """An ordering of n unknowns in which a sparsity pattern is banded.

    ``position[c]`` is where unknown c goes; ``half_bandwidth`` the largest
    ``|position[a] - position[b]|`` over the pattern's non-zeros; ``block`` the number
    of columns the factorisation takes per step.
    """

    position: np.ndarray
    half_bandwidth: int
    block: int

    @classmethod
    def for_pattern(cls, pattern: np.ndarray) -> "BandOrder":
        """The narrower of the natural order and reverse Cuthill-McKee's for the (n, n)
        boolean ``pattern`` (RCM puts a periodic direction's wrap-around in the band)."""
        n = len(pattern)
        rows, cols = np.nonzero(pattern)
        natural = np.arange(n)
        rcm = np.empty(n, np.int64)
        rcm[reverse_cuthill_mckee(sp.csr_array(pattern.astype(np.int8)), symmetric_mode=True)] = natural
        best = min((natural, rcm), key=lambda pos: int(np.abs(pos[rows] - pos[cols]).max(initial=0)))
        width = int(np.abs(best[rows] - best[cols]).max(initial=0))
        return cls(best, width, BLOCK)

    def places(self, rows: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the entries M[rows, columns] (same shape) of a symmetric matrix go in
        LAPACK's lower band storage of the reordered matrix, ``band[d, j] = M'[j + d, j]``
        flattened ((w + 1) n): (flat index, kept), kept False for an entry above the
        diagonal (its mirror image below carries it)."""
        pr, pc = self.position[rows], self.position[columns]
        kept = pr >= pc
        return (pr - pc) * len(self.position) + pc, kept

    def gathered(self, flat: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Values (k,) at flat band places (k,) summed into the band storage, (w + 1, n)."""
        n = len(self.position)
        return np.bincount(flat, values, (self.half_bandwidth + 1) * n).reshape(self.half_bandwidth + 1, n)

    def solve(self, band: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """``M^-1 rhs`` for rhs (n,) or (n, k), M symmetric positive definite given by its
        reordered lower ``band`` (:meth:`places`): LAPACK's banded Cholesky factorisation,
        n w^2 operations against the dense n^3 / 3. Raises numpy.linalg.LinAlgError unless
        M is positive definite."""
        factor = la.cholesky_banded(band, lower=True, check_finite=False)
        at = self.position
        return la.cho_solve_banded((factor, True), rhs[np.argsort(at)], check_finite=False)[at]


class StackedBandedCholesky:
    """Block LDL^T factors of P symmetric positive definite (n, n) matrices with half
    bandwidth ``w`` (in the order they are given), ``block`` columns at a time.

    Raises numpy.linalg.LinAlgError if any of the matrices is not positive definite.
    With ``overwrite`` the factorisation works in ``matrices`` (a float array the caller
    no longer needs) instead of a copy.
    """

    def __init__(self, matrices: np.ndarray, half_bandwidth: int, block: int, overwrite: bool = False):
        a = matrices if overwrite and isinstance(matrices, np.ndarray) and matrices.dtype == float \
            else np.array(matrices, float)
        n = self.n = a.shape[1]
        self.steps = []
        for j0 in range(0, n, block):
            j1 = min(j0 + block, n)
            end = min(j1 + half_bandwidth, n)
            pivot = a[:, j0:j1, j0:j1]
            np.linalg.cholesky(pivot)  # raises unless positive definite
            inverse = np.linalg.inv(pivot)  # D_J^-1
            below = a[:, j1:end, j0:j1]  # A_RJ
            g = below @ inverse  # G_J
            if end > j1:
                a[:, j1:end, j1:end] -= g @ below.transpose(0, 2, 1)
            self.steps.append((j0, j1, end, inverse, g))
        self._storage = a  # the factors are in steps: the selected inverse reuses it

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``M^-1 rhs`` for rhs (P, n, k): forward then backward substitution by blocks."""
        y = np.array(rhs, float)
        for j0, j1, end, _, g in self.steps:
            if end > j1:
                y[:, j1:end] -= g @ y[:, j0:j1]
        for j0, j1, end, inverse, g in reversed(self.steps):
            top = inverse @ y[:, j0:j1]
            if end > j1:
                top -= g.transpose(0, 2, 1) @ y[:, j1:end]
            y[:, j0:j1] = top
        return y

    def selected_inverse(self) -> np.ndarray:
        """(P, n, n) holding the entries of ``M^-1`` inside the band (Takahashi's
        recurrences, last block first), in the factorisation's storage; the entries
        outside the band are left as they were (0 for a banded M). Every entry the
        recurrence reads it has written before, so it needs no zeroed array."""
        s = self._storage
        for j0, j1, end, inverse, g in reversed(self.steps):
            diagonal = inverse.copy()
            if end > j1:
                below = -(s[:, j1:end, j1:end] @ g)
                s[:, j1:end, j0:j1] = below
                s[:, j0:j1, j1:end] = below.transpose(0, 2, 1)
                diagonal -= g.transpose(0, 2, 1) @ below
            s[:, j0:j1, j0:j1] = diagonal
        return s


# Compiled twins for one system in upper band storage: ``band[i, d] = M[i, i + d]``,
# (n, w + 1), entries past the end unused. The factor is M = U^T U (Cholesky, U upper,
# ``band[i, d] = U[i, i + d]`` after the factorisation), each pivot checked positive.

@kernel
def band_cholesky(band: np.ndarray) -> bool:
    """Factor ``band`` in place (right-looking); False if M is not positive definite.
    (Inner loops run over 1-d rows from 0, which numba vectorises.)"""
    n, w = band.shape[0], band.shape[1] - 1
    for i in range(n):
        pivot = band[i, 0]
        if not pivot > 0.0:  # also NaN
            return False
        pivot = np.sqrt(pivot)
        band[i, 0] = pivot
        reach = min(w, n - 1 - i)
        source = band[i]
        for t in range(1, reach + 1):
            source[t] /= pivot
        for t in range(1, reach + 1):
            a = source[t]
            target = band[i + t]
            for j in range(reach + 1 - t):
                target[j] -= a * source[j + t]
    return True


@kernel
def band_solve(band: np.ndarray, rhs: np.ndarray) -> None:
    """``rhs`` (n, k) <- M^-1 rhs from the factor: U^T y = rhs, then U x = y."""
    n, w, k = band.shape[0], band.shape[1] - 1, rhs.shape[1]
    for i in range(n):
        reach = min(w, n - 1 - i)
        for c in range(k):
            y = rhs[i, c] / band[i, 0]
            rhs[i, c] = y
            for t in range(1, reach + 1):
                rhs[i + t, c] -= band[i, t] * y
    for i in range(n - 1, -1, -1):
        reach = min(w, n - 1 - i)
        for c in range(k):
            total = rhs[i, c]
            for t in range(1, reach + 1):
                total -= band[i, t] * rhs[i + t, c]
            rhs[i, c] = total / band[i, 0]


@kernel
def band_selected_inverse(band: np.ndarray, inverse: np.ndarray) -> None:
    """The entries of Z = M^-1 inside the band from the factor, both triangles:
    ``inverse[i, w + d] = Z[i, i + d]`` for |d| <= w, (n, 2w + 1 + LANES) zeroed before
    the first use (the columns past 2w are scratch). Last row first (Takahashi):
    U Z = U^-T is lower triangular with diagonal 1 / U_ii, so for j >= i
    ``Z_ij = (delta_ij / U_ii - sum_{k > i} U_ik Z_kj) / U_ii``, the Z_kj (k, j in
    i + 1 .. i + w) from the rows already done. Row i's products ``sum_k U_ik Z_kj`` run
    along the rows of Z (the storage holds both triangles for that), one pass per k,
    over a whole number of LANES (the entries past the band are discarded)."""
    n, w = band.shape[0], band.shape[1] - 1
    work = np.empty(w + LANES)
    for i in range(n - 1, -1, -1):
        reach = min(w, n - 1 - i)
        padded = -(-reach // LANES) * LANES
        pivot = band[i, 0]
        work[:padded] = 0.0
        for k in range(1, reach + 1):  # Z[i, i + 1 ..] = -(U[i, i + 1 ..] @ Z[i + 1 .., i + 1 ..]) / U_ii
            a = band[i, k] / pivot
            source = inverse[i + k, w + 1 - k:w + 1 - k + padded]
            for j in range(padded):
                work[j] -= a * source[j]
        target = inverse[i]
        diagonal = 1.0 / pivot
        for t in range(1, reach + 1):
            target[w + t] = work[t - 1]
            diagonal -= band[i, t] * work[t - 1]
            inverse[i + t, w - t] = work[t - 1]
        target[w] = diagonal / pivot

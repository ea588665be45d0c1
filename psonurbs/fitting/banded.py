"""Stacked banded Cholesky and selected inversion: P symmetric banded systems at once.

The normal matrix of a tensor-product net couples control points (i, j) and (i', j')
only if |i - i'| <= p and |j - j'| <= q, so in row-major order it is banded with half
bandwidth w ~ p * nv + q, much less than its size n (w = 39, n = 144 on a 12 x 12
cubic net). Its Cholesky factor L stays inside the band. Leave-one-out leverages
``h_i = r_i^T M^-1 r_i`` only need the entries of M^-1 at pairs of columns one row
touches, which lie inside the band too; Takahashi's recurrences give exactly those
entries from L, in O(n w^2) instead of the O(n^3) of a full inverse.

Everything runs on dense (P, n, n) storage, block column by block column (b columns
at a time), so a step is a few batched matrix products over all P systems:

    factor:   L_JJ = chol(A_JJ),  L_RJ = A_RJ L_JJ^-T,  A_RR -= L_RJ L_RJ^T
    inverse:  G = L_RJ L_JJ^-1,   S_RJ = -S_RR G,      S_JJ = L_JJ^-T L_JJ^-1 - G^T S_RJ

with J the block's columns and R the rows below it inside the band (R = J's next w
rows). The inverse runs from the last block to the first; S_RR was filled by the blocks
after J. Only band entries of S (and a few just past it) are computed; the rest stay 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

BLOCK = 16  # columns per step of the factorisation (a power of two)


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


def lower_inverse(lower: np.ndarray) -> np.ndarray:
    """Inverses of P lower-triangular (b, b) matrices, b a power of two, by halving:
    ``[[A, 0], [B, C]]^-1 = [[A^-1, 0], [-C^-1 B A^-1, C^-1]]``, all blocks of one size
    at once (log2 b batched products instead of one LAPACK call per matrix)."""
    n_mats, b, _ = lower.shape
    out = np.zeros_like(lower)
    diag = np.arange(b)
    out[:, diag, diag] = 1.0 / lower[:, diag, diag]
    size = 1
    while size < b:
        pairs = b // (2 * size)
        blocks = lower.reshape(n_mats, pairs, 2, size, pairs, 2, size)
        inverses = out.reshape(n_mats, pairs, 2, size, pairs, 2, size)
        k = np.arange(pairs)
        # fancy indices k, k on axes 1 and 4 move to the front: (pairs, P, size, size)
        inverses[:, k, 1, :, k, 0, :] = -(inverses[:, k, 1, :, k, 1, :] @ blocks[:, k, 1, :, k, 0, :]
                                         @ inverses[:, k, 0, :, k, 0, :])
        size *= 2
    return out


class StackedBandedCholesky:
    """Cholesky factors of P symmetric positive definite (n, n) matrices with half
    bandwidth ``w`` (in the order they are given), ``block`` columns at a time
    (a power of two; the systems are padded with identity rows to a multiple of it).

    Raises numpy.linalg.LinAlgError if any of the matrices is not positive definite.
    """

    def __init__(self, matrices: np.ndarray, half_bandwidth: int, block: int):
        n_mats, n, _ = matrices.shape
        size = -(-n // block) * block
        a = np.zeros((n_mats, size, size))
        a[:, :n, :n] = matrices
        pad = np.arange(n, size)
        a[:, pad, pad] = 1.0
        self.n, self.size, self.steps = n, size, []
        for j0 in range(0, size, block):
            j1 = j0 + block
            end = min(j1 + half_bandwidth, size)
            inverse = lower_inverse(np.linalg.cholesky(a[:, j0:j1, j0:j1]))  # L_JJ^-1
            panel = a[:, j1:end, j0:j1] @ inverse.transpose(0, 2, 1)  # L_RJ
            if end > j1:
                a[:, j1:end, j1:end] -= panel @ panel.transpose(0, 2, 1)
            self.steps.append((j0, j1, end, inverse, panel))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``M^-1 rhs`` for rhs (P, n, k): forward then backward substitution by blocks."""
        y = np.zeros((rhs.shape[0], self.size, rhs.shape[2]))
        y[:, :self.n] = rhs
        for j0, j1, end, inverse, panel in self.steps:
            y[:, j0:j1] = inverse @ y[:, j0:j1]
            if end > j1:
                y[:, j1:end] -= panel @ y[:, j0:j1]
        for j0, j1, end, inverse, panel in reversed(self.steps):
            top = y[:, j0:j1]
            if end > j1:
                top = top - panel.transpose(0, 2, 1) @ y[:, j1:end]
            y[:, j0:j1] = inverse.transpose(0, 2, 1) @ top
        return y[:, :self.n]

    def selected_inverse(self) -> np.ndarray:
        """(P, size, size) holding the entries of ``M^-1`` inside the band (Takahashi's
        recurrences, last block first); entries far outside the band are 0, and rows
        and columns from n on belong to the padding."""
        s = np.zeros((self.steps[0][3].shape[0], self.size, self.size))
        for j0, j1, end, inverse, panel in reversed(self.steps):
            diagonal = inverse.transpose(0, 2, 1) @ inverse
            if end > j1:
                g = panel @ inverse
                below = -(s[:, j1:end, j1:end] @ g)
                s[:, j1:end, j0:j1] = below
                s[:, j0:j1, j1:end] = below.transpose(0, 2, 1)
                diagonal -= g.transpose(0, 2, 1) @ below
            s[:, j0:j1, j0:j1] = diagonal
        return s

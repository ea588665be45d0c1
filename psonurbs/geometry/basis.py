"""B-spline basis functions: knot vectors and sparse collocation matrices.

Everything here is on the parameter domain [0, 1]. The basis values themselves come
from :func:`scipy.interpolate.BSpline.design_matrix` (de Boor's recurrence in C), which
gets right what the seed paper got wrong: the first basis function, the clamped ends
and ``x = 1`` belonging to the last non-empty span.

Two kinds of knot vector:

* **clamped** (open direction), ``n`` basis functions of degree ``p``::

      t = (0, ..., 0, t_1, ..., t_{n-p-1}, 1, ..., 1)      (p+1 zeros and ones)

  The curve interpolates its first and last control points.
* **periodic** (closed direction), ``n`` distinct control points and breakpoints
  ``0 = b_0 < b_1 < ... < b_n = 1``. The knot vector is the breakpoints extended by
  the period on both sides; it has ``n + 2p + 1`` knots for ``n + p`` basis functions,
  of which the last ``p`` repeat the first ``p`` control points. The curve is then
  C^(p-1) across the seam u = 0 = 1.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.interpolate import BSpline


def uniform_inner_knots(count: int) -> np.ndarray:
    """``count`` equally spaced knots strictly inside (0, 1)."""
    return np.arange(1, count + 1) / (count + 1)


def random_inner_knots(count: int, gap: float, rng: np.random.Generator) -> np.ndarray:
    """Random increasing knots in (0, 1) with every gap (ends included) at least ``gap``."""
    spacing = gap + (1.0 - (count + 1) * gap) * rng.dirichlet(np.ones(count + 1))
    return np.cumsum(spacing)[:-1]


def clamped_knots(n: int, degree: int, inner: np.ndarray | None = None) -> np.ndarray:
    """Full clamped knot vector for ``n`` basis functions (uniform inner knots by default)."""
    count = n - degree - 1
    if count < 0:
        raise ValueError(f"{n} control points cannot carry degree {degree}")
    inner = uniform_inner_knots(count) if inner is None else np.asarray(inner, float)
    if len(inner) != count:
        raise ValueError(f"expected {count} inner knots, got {len(inner)}")
    return np.concatenate([np.zeros(degree + 1), inner, np.ones(degree + 1)])


def periodic_knots(n: int, degree: int, inner: np.ndarray | None = None) -> np.ndarray:
    """Periodic knot vector for ``n`` distinct control points on the period [0, 1].

    ``inner`` holds the ``n - 1`` breakpoints inside (0, 1) (uniform by default).
    """
    if n < degree + 1:
        raise ValueError(f"a closed direction needs at least {degree + 1} control points")
    inner = uniform_inner_knots(n - 1) if inner is None else np.asarray(inner, float)
    if len(inner) != n - 1:
        raise ValueError(f"expected {n - 1} inner breakpoints, got {len(inner)}")
    b = np.concatenate([[0.0], inner, [1.0]])
    return np.concatenate([b[n - degree:n] - 1.0, b, b[1:degree + 1] + 1.0])


def inner_knot_count(n: int, degree: int, closed: bool) -> int:
    """How many free knots a direction has: n-p-1 (clamped) or n-1 (periodic)."""
    return n - 1 if closed else n - degree - 1


def make_knots(n: int, degree: int, closed: bool, inner: np.ndarray | None = None) -> np.ndarray:
    return periodic_knots(n, degree, inner) if closed else clamped_knots(n, degree, inner)


def design_matrix(x: np.ndarray, knots: np.ndarray, degree: int, derivative: int = 0) -> sp.csr_array:
    """Sparse matrix ``B[r, i] = d^derivative N_{i,p}(x_r) / dx^derivative``.

    ``x`` is clipped to the domain ``[t_p, t_n]``. Every row stores exactly
    ``degree + 1`` entries in increasing column order (some may be zero), which
    :func:`tensor_basis` relies on. Derivatives follow from the degree ``p - 1`` basis
    on ``t[1:-1]``:  ``N'_{i,p} = p/(t_{i+p}-t_i) N_{i,p-1} - p/(t_{i+p+1}-t_{i+1}) N_{i+1,p-1}``.
    """
    knots = np.asarray(knots, float)
    x = np.clip(np.asarray(x, float), knots[degree], knots[-degree - 1])
    n = len(knots) - degree - 1
    k = degree + 1
    if len(x) == 0:
        return sp.csr_array((np.zeros(0), np.zeros(0, np.int32), np.zeros(1, np.int32)), shape=(0, n))
    if derivative == 0:
        # x is inside the domain already: scipy's own bounds check (a Python min and max
        # over x) is skipped, the values are the same
        return BSpline.design_matrix(x, knots, degree, extrapolate=True)
    if degree == 0:
        lower_vals = np.zeros((len(x), 0))
        first = np.searchsorted(knots, x, side="right") - 1
        first = np.clip(first, 0, n - 1)
    else:
        lower = design_matrix(x, knots[1:-1], degree - 1, derivative - 1)
        lower_vals = lower.data.reshape(len(x), degree)
        first = lower.indices.reshape(len(x), degree)[:, 0]
    # lower column m is N_{m+1,p-1}; row r's support in the degree-p basis is first..first+p
    padded = np.zeros((len(x), k + 1))
    padded[:, 1:k] = lower_vals
    cols = first[:, None] + np.arange(k)[None, :]
    left = knots[cols + degree] - knots[cols]
    right = knots[cols + degree + 1] - knots[cols + 1]
    a = np.divide(degree, left, out=np.zeros_like(left), where=left > 0)
    b = np.divide(degree, right, out=np.zeros_like(right), where=right > 0)
    vals = a * padded[:, :k] - b * padded[:, 1:]
    indptr = np.arange(0, len(x) * k + 1, k)
    return sp.csr_array((vals.reshape(-1), cols.reshape(-1), indptr), shape=(len(x), n))


def periodic_fold(n: int, degree: int) -> sp.csr_array:
    """Map the ``n`` distinct control points to the ``n + p`` of a periodic vector.

    ``(B @ F)`` folds the last ``p`` basis columns onto the first ``p``.
    """
    rows = np.arange(n + degree)
    return sp.csr_array((np.ones(n + degree), (rows, rows % n)), shape=(n + degree, n))


def tensor_basis(bu: sp.csr_array, bv: sp.csr_array) -> sp.csr_array:
    """Row-wise tensor product: ``T[r, i * nv + j] = bu[r, i] * bv[r, j]``.

    Both inputs must store a fixed number of entries per row (as
    :func:`design_matrix` does), so the product is assembled without any loop.
    """
    n_pts = bu.shape[0]
    nv = bv.shape[1]
    ku = bu.indptr[1] - bu.indptr[0] if n_pts else 1
    kv = bv.indptr[1] - bv.indptr[0] if n_pts else 1
    du, iu = bu.data.reshape(n_pts, ku), bu.indices.reshape(n_pts, ku)
    dv, iv = bv.data.reshape(n_pts, kv), bv.indices.reshape(n_pts, kv)
    data = (du[:, :, None] * dv[:, None, :]).reshape(-1)
    cols = (iu[:, :, None] * nv + iv[:, None, :]).reshape(-1)
    indptr = np.arange(0, n_pts * ku * kv + 1, ku * kv)
    return sp.csr_array((data, cols, indptr), shape=(n_pts, bu.shape[1] * nv))

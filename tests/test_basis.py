"""B-spline basis: the properties the seed paper got wrong, pinned against known answers.

Reference values come from a hand-written Cox-de Boor recursion (pure Python, below)
and from scipy.interpolate.BSpline, never from psonurbs itself.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline

from psonurbs.geometry.basis import (
    clamped_knots,
    design_matrix,
    inner_knot_count,
    make_knots,
    periodic_fold,
    periodic_knots,
    tensor_basis,
    uniform_inner_knots,
)

DEGREES = [1, 2, 3, 4]
KINDS = ["clamped", "periodic"]


# ---------------------------------------------------------------------------
# Helpers: random knot vectors and an independent Cox-de Boor recursion
# ---------------------------------------------------------------------------

def random_inner(rng, count, min_gap=0.04):
    """``count`` sorted, clearly non-uniform knots in (0, 1), at least ``min_gap`` apart."""
    while True:
        inner = np.sort(rng.uniform(0.0, 1.0, count))
        pts = np.concatenate([[0.0], inner, [1.0]])
        if count == 0 or np.min(np.diff(pts)) >= min_gap:
            return inner


def knot_case(kind, degree, seed):
    """(knots, number of basis functions, number of distinct control points)."""
    rng = np.random.default_rng(1000 * degree + seed + (0 if kind == "clamped" else 500))
    if kind == "clamped":
        n = degree + 1 + 4
        t = clamped_knots(n, degree, random_inner(rng, n - degree - 1))
        return t, n, n
    n = degree + 4
    t = periodic_knots(n, degree, random_inner(rng, n - 1))
    return t, n + degree, n


def sample_points(knots, degree, rng, count=60):
    """Random points of the domain plus every knot in it, plus both ends exactly."""
    a, b = knots[degree], knots[-degree - 1]
    inside = knots[(knots >= a) & (knots <= b)]
    return np.concatenate([[a, b], inside, rng.uniform(a, b, count)])


def reference_span(x, t, n_basis):
    """Index i with t_i <= x < t_{i+1}; the right end of the domain belongs to the
    last non-empty span (not to an empty one beyond it)."""
    if x >= t[n_basis]:
        i = n_basis - 1
        while t[i] == t[i + 1]:
            i -= 1
        return i
    i = n_basis - 1
    while t[i] > x:
        i -= 1
    return i


def cox_de_boor(i, p, x, t, span):
    """N_{i,p}(x) by the Cox-de Boor recursion, with 0/0 := 0."""
    if p == 0:
        return 1.0 if i == span else 0.0
    out = 0.0
    d1 = t[i + p] - t[i]
    if d1 > 0:
        out += (x - t[i]) / d1 * cox_de_boor(i, p - 1, x, t, span)
    d2 = t[i + p + 1] - t[i + 1]
    if d2 > 0:
        out += (t[i + p + 1] - x) / d2 * cox_de_boor(i + 1, p - 1, x, t, span)
    return out


def reference_matrix(xs, t, p):
    t = [float(v) for v in t]
    n_basis = len(t) - p - 1
    out = np.zeros((len(xs), n_basis))
    for r, x in enumerate(xs):
        x = float(x)
        span = reference_span(x, t, n_basis)
        for i in range(n_basis):
            out[r, i] = cox_de_boor(i, p, x, t, span)
    return out


def dense(m):
    return m.toarray()


# ---------------------------------------------------------------------------
# Knot vectors written out by hand
# ---------------------------------------------------------------------------

def test_uniform_inner_knots():
    np.testing.assert_allclose(uniform_inner_knots(3), [0.25, 0.5, 0.75], rtol=0, atol=1e-15)
    assert len(uniform_inner_knots(0)) == 0


@pytest.mark.parametrize("args, expected", [
    ((5, 2), [0, 0, 0, 1 / 3, 2 / 3, 1, 1, 1]),
    ((4, 3), [0, 0, 0, 0, 1, 1, 1, 1]),
    ((2, 1), [0, 0, 1, 1]),
    ((4, 1), [0, 0, 1 / 3, 2 / 3, 1, 1]),
    ((6, 3), [0, 0, 0, 0, 1 / 3, 2 / 3, 1, 1, 1, 1]),
])
def test_clamped_knots_by_hand(args, expected):
    t = clamped_knots(*args)
    assert len(t) == args[0] + args[1] + 1
    np.testing.assert_allclose(t, expected, rtol=0, atol=1e-15)


def test_clamped_knots_with_given_inner():
    np.testing.assert_allclose(clamped_knots(3, 1, inner=[0.25]), [0, 0, 0.25, 1, 1], rtol=0, atol=0)
    np.testing.assert_allclose(clamped_knots(5, 2, inner=[0.1, 0.7]),
                               [0, 0, 0, 0.1, 0.7, 1, 1, 1], rtol=0, atol=0)


@pytest.mark.parametrize("args, expected", [
    ((4, 2), [-0.5, -0.25, 0, 0.25, 0.5, 0.75, 1, 1.25, 1.5]),
    ((3, 1), [-1 / 3, 0, 1 / 3, 2 / 3, 1, 4 / 3]),
    ((4, 3), [-0.75, -0.5, -0.25, 0, 0.25, 0.5, 0.75, 1, 1.25, 1.5, 1.75]),
])
def test_periodic_knots_by_hand(args, expected):
    n, p = args
    t = periodic_knots(n, p)
    assert len(t) == n + 2 * p + 1
    np.testing.assert_allclose(t, expected, rtol=0, atol=1e-15)
    # domain is [t_p, t_{n+p}] = [0, 1]
    assert t[p] == 0.0 and t[n + p] == 1.0


def test_periodic_knots_with_given_inner():
    # breakpoints 0, 0.2, 0.7, 1 extended by the period on both sides
    np.testing.assert_allclose(periodic_knots(3, 1, inner=[0.2, 0.7]),
                               [-0.3, 0, 0.2, 0.7, 1, 1.2], rtol=0, atol=1e-15)
    np.testing.assert_allclose(periodic_knots(3, 2, inner=[0.2, 0.7]),
                               [-0.8, -0.3, 0, 0.2, 0.7, 1, 1.2, 1.7], rtol=0, atol=1e-15)


def test_make_knots_dispatch_and_inner_count():
    np.testing.assert_array_equal(make_knots(5, 2, False), clamped_knots(5, 2))
    np.testing.assert_array_equal(make_knots(5, 2, True), periodic_knots(5, 2))
    np.testing.assert_array_equal(make_knots(4, 1, False, [0.1, 0.6]), [0, 0, 0.1, 0.6, 1, 1])
    assert inner_knot_count(7, 3, closed=False) == 3
    assert inner_knot_count(7, 3, closed=True) == 6
    assert len(make_knots(7, 3, False, np.zeros(3) + 0.5)) == 7 + 3 + 1
    assert len(make_knots(7, 3, True)) == 7 + 2 * 3 + 1


def test_knot_constructors_reject_impossible_input():
    with pytest.raises(ValueError):
        clamped_knots(2, 2)
    with pytest.raises(ValueError):
        clamped_knots(5, 2, inner=[0.5])
    with pytest.raises(ValueError):
        periodic_knots(2, 2)
    with pytest.raises(ValueError):
        periodic_knots(4, 2, inner=[0.5])


# ---------------------------------------------------------------------------
# Partition of unity, non-negativity, local support
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("seed", [0, 1])
def test_partition_of_unity_and_non_negativity(kind, degree, seed):
    t, n_basis, _ = knot_case(kind, degree, seed)
    rng = np.random.default_rng(seed)
    x = sample_points(t, degree, rng, 200)
    B = design_matrix(x, t, degree)
    assert B.shape == (len(x), n_basis)
    M = dense(B)
    np.testing.assert_allclose(M.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert M.min() >= 0.0
    # a periodic vector keeps every row on the same n + p functions; the folded
    # matrix on the n distinct control points is a partition of unity too
    if kind == "periodic":
        F = periodic_fold(n_basis - degree, degree)
        np.testing.assert_allclose(dense(B @ F).sum(axis=1), 1.0, rtol=0, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("degree", DEGREES)
def test_local_support_and_fixed_row_storage(kind, degree):
    t, n_basis, _ = knot_case(kind, degree, 3)
    rng = np.random.default_rng(3)
    x = sample_points(t, degree, rng, 100)
    B = design_matrix(x, t, degree)
    assert np.all(np.diff(B.indptr) == degree + 1)
    M = dense(B)
    for r, xr in enumerate(x):
        span = reference_span(float(xr), list(t), n_basis)
        cols = B.indices[B.indptr[r]:B.indptr[r + 1]]
        np.testing.assert_array_equal(cols, np.arange(span - degree, span + 1))
        outside = np.ones(n_basis, bool)
        outside[span - degree:span + 1] = False
        assert np.all(M[r, outside] == 0.0)
        # inside a span (not at a knot) all p+1 functions are strictly positive
        if not np.any(np.isclose(xr, t, atol=1e-12, rtol=0)):
            assert np.all(M[r, span - degree:span + 1] > 0)


def test_local_support_with_repeated_inner_knot():
    # degree 3 with a double inner knot at 0.5: span at x = 0.5 is the one starting there
    t = np.array([0, 0, 0, 0, 0.25, 0.5, 0.5, 0.8, 1, 1, 1, 1], float)
    B = design_matrix(np.array([0.5]), t, 3)
    np.testing.assert_array_equal(B.indices, [3, 4, 5, 6])
    np.testing.assert_allclose(dense(B), reference_matrix([0.5], t, 3), rtol=0, atol=1e-14)
    np.testing.assert_allclose(dense(B).sum(), 1.0, rtol=0, atol=1e-14)


# ---------------------------------------------------------------------------
# Clamped ends
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("degree", DEGREES)
def test_clamped_end_interpolation(degree):
    t, n, _ = knot_case("clamped", degree, 5)
    M = dense(design_matrix(np.array([0.0, 1.0]), t, degree))
    e0 = np.zeros(n)
    e0[0] = 1.0
    e1 = np.zeros(n)
    e1[-1] = 1.0
    np.testing.assert_array_equal(M[0], e0)
    np.testing.assert_array_equal(M[1], e1)  # x = 1 is in the last span, not a zero row


@pytest.mark.parametrize("degree", DEGREES)
def test_clamped_first_basis_function_known_values(degree):
    # Bezier case (no inner knots): N_0(x) = (1-x)^p, N_{p}(x) = x^p, binomial in between
    from math import comb
    t = clamped_knots(degree + 1, degree)
    x = np.linspace(0.0, 1.0, 41)
    M = dense(design_matrix(x, t, degree))
    expected = np.stack([comb(degree, i) * x ** i * (1 - x) ** (degree - i)
                         for i in range(degree + 1)], axis=1)
    np.testing.assert_allclose(M, expected, rtol=0, atol=1e-14)


def test_points_outside_domain_are_clipped():
    t = clamped_knots(5, 2)
    M = dense(design_matrix(np.array([-0.5, 1.5]), t, 2))
    np.testing.assert_array_equal(M, dense(design_matrix(np.array([0.0, 1.0]), t, 2)))


# ---------------------------------------------------------------------------
# Against an independent Cox-de Boor recursion
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("degree", DEGREES)
def test_values_match_hand_written_cox_de_boor(kind, degree):
    t, _, _ = knot_case(kind, degree, 7)
    rng = np.random.default_rng(7 + degree)
    x = sample_points(t, degree, rng, 80)
    np.testing.assert_allclose(dense(design_matrix(x, t, degree)),
                               reference_matrix(x, t, degree), rtol=0, atol=1e-13)


@pytest.mark.parametrize("degree", [2, 3])
def test_values_match_cox_de_boor_with_multiple_knots(degree):
    # inner knots of multiplicity up to the degree exercise the 0/0 := 0 convention
    inner = [0.2] * degree + [0.55, 0.55]
    n = len(inner) + degree + 1
    t = clamped_knots(n, degree, inner)
    rng = np.random.default_rng(11)
    x = sample_points(t, degree, rng, 80)
    M = dense(design_matrix(x, t, degree))
    np.testing.assert_allclose(M, reference_matrix(x, t, degree), rtol=0, atol=1e-13)
    np.testing.assert_allclose(M.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    # full multiplicity p at 0.2: the curve interpolates a control point there
    row = M[np.flatnonzero(x == 0.2)[0]]
    assert np.count_nonzero(np.abs(row) > 1e-15) == 1


# ---------------------------------------------------------------------------
# Derivatives
# ---------------------------------------------------------------------------

def points_off_knots(t, degree, rng, count, margin):
    a, b = t[degree], t[-degree - 1]
    x = rng.uniform(a + margin, b - margin, 4 * count)
    far = np.min(np.abs(x[:, None] - t[None, :]), axis=1) > margin
    return x[far][:count]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("degree", DEGREES)
def test_first_derivative_matches_finite_differences(kind, degree):
    t, _, _ = knot_case(kind, degree, 13)
    rng = np.random.default_rng(13)
    h = 1e-6
    x = points_off_knots(t, degree, rng, 50, 10 * h)
    d1 = dense(design_matrix(x, t, degree, derivative=1))
    fd = (dense(design_matrix(x + h, t, degree)) - dense(design_matrix(x - h, t, degree))) / (2 * h)
    scale = np.abs(d1).max()
    np.testing.assert_allclose(d1, fd, rtol=0, atol=1e-6 * scale)
    # derivatives of a partition of unity sum to zero
    np.testing.assert_allclose(d1.sum(axis=1), 0.0, rtol=0, atol=1e-10 * scale)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("degree", [2, 3, 4])
def test_second_derivative_matches_finite_differences(kind, degree):
    t, _, _ = knot_case(kind, degree, 17)
    rng = np.random.default_rng(17)
    h = 1e-4
    x = points_off_knots(t, degree, rng, 50, 10 * h)
    d2 = dense(design_matrix(x, t, degree, derivative=2))
    f0 = dense(design_matrix(x, t, degree))
    fp = dense(design_matrix(x + h, t, degree))
    fm = dense(design_matrix(x - h, t, degree))
    fd2 = (fp - 2 * f0 + fm) / h ** 2
    scale = np.abs(d2).max()
    np.testing.assert_allclose(d2, fd2, rtol=0, atol=1e-5 * scale)
    # and the second derivative is the central difference of the first
    g = 1e-6
    fd1 = (dense(design_matrix(x + g, t, degree, 1)) - dense(design_matrix(x - g, t, degree, 1))) / (2 * g)
    np.testing.assert_allclose(d2, fd1, rtol=0, atol=1e-6 * scale)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("order", [1, 2])
def test_derivatives_match_scipy_bspline_derivative(kind, degree, order):
    t, n_basis, _ = knot_case(kind, degree, 19)
    rng = np.random.default_rng(19)
    # include the domain ends and the knots themselves: where a derivative jumps
    # (order >= degree) both take the right-hand span, and x = b the last span
    a, b = t[degree], t[-degree - 1]
    x = np.concatenate([[a, b], t[(t >= a) & (t <= b)], rng.uniform(a, b, 100)])
    if order <= degree:
        ref = BSpline(t, np.eye(n_basis), degree).derivative(order)(x)
    else:  # scipy refuses a derivative above the degree; it is identically zero
        ref = np.zeros((len(x), n_basis))
    got = dense(design_matrix(x, t, degree, derivative=order))
    scale = max(1.0, np.abs(ref).max())
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-11 * scale)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_derivative_beyond_degree_is_zero(degree):
    t, _, _ = knot_case("clamped", degree, 21)
    x = np.linspace(0.01, 0.99, 23)
    d = dense(design_matrix(x, t, degree, derivative=degree + 1))
    np.testing.assert_array_equal(d, 0.0)


@pytest.mark.parametrize("degree", DEGREES)
def test_derivative_rows_keep_support(degree):
    t, n_basis, _ = knot_case("clamped", degree, 23)
    x = sample_points(t, degree, np.random.default_rng(23), 40)
    B = design_matrix(x, t, degree)
    for order in (1, 2):
        D = design_matrix(x, t, degree, derivative=order)
        assert D.shape == (len(x), n_basis)
        assert np.all(np.diff(D.indptr) == degree + 1)
        np.testing.assert_array_equal(D.indices, B.indices)


# ---------------------------------------------------------------------------
# Periodic directions close up smoothly
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_periodic_fold_closes_curve_with_continuous_derivatives(degree, seed):
    t, n_basis, n = knot_case("periodic", degree, seed)
    rng = np.random.default_rng(100 + seed)
    c = rng.normal(size=n)
    F = periodic_fold(n, degree)
    assert F.shape == (n + degree, n)
    ends = np.array([0.0, 1.0])
    for order in range(degree):
        f = (design_matrix(ends, t, degree, derivative=order) @ F) @ c
        assert np.isclose(f[0], f[1], rtol=1e-9, atol=1e-9), (order, f)
    # the test is not vacuous: without folding the curve does not close
    c_unfolded = rng.normal(size=n_basis)
    f = design_matrix(ends, t, degree) @ c_unfolded
    assert abs(f[0] - f[1]) > 1e-6


def test_periodic_fold_matrix_by_hand():
    F = dense(periodic_fold(4, 2))
    expected = np.array([
        [1, 0, 0, 0],
        [0, 1, 0, 0],
        [0, 0, 1, 0],
        [0, 0, 0, 1],
        [1, 0, 0, 0],
        [0, 1, 0, 0],
    ], float)
    np.testing.assert_array_equal(F, expected)


def test_periodic_uniform_cubic_known_values():
    # uniform cubic B-spline at a breakpoint: weights 1/6, 2/3, 1/6 (and 0)
    t = periodic_knots(5, 3)
    M = dense(design_matrix(np.array([0.0, 0.4]), t, 3))
    np.testing.assert_allclose(M[0, :4], [1 / 6, 2 / 3, 1 / 6, 0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(M[1, 2:6], [1 / 6, 2 / 3, 1 / 6, 0], rtol=0, atol=1e-15)
    # at the span midpoint: 1/48, 23/48, 23/48, 1/48
    m = dense(design_matrix(np.array([0.1]), t, 3))
    np.testing.assert_allclose(m[0, :4], [1 / 48, 23 / 48, 23 / 48, 1 / 48], rtol=0, atol=1e-15)


# ---------------------------------------------------------------------------
# Tensor product
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("pu, pv, kind_u, kind_v", [
    (1, 1, "clamped", "clamped"),
    (2, 3, "clamped", "periodic"),
    (3, 2, "periodic", "clamped"),
    (4, 1, "periodic", "periodic"),
])
def test_tensor_basis_equals_dense_rowwise_kronecker(pu, pv, kind_u, kind_v):
    tu, nu, _ = knot_case(kind_u, pu, 29)
    tv, nv, _ = knot_case(kind_v, pv, 31)
    rng = np.random.default_rng(37)
    u = np.concatenate([[0.0, 1.0, 0.0, 1.0], rng.uniform(0, 1, 100)])
    v = np.concatenate([[0.0, 0.0, 1.0, 1.0], rng.uniform(0, 1, 100)])
    for du, dv in ((0, 0), (1, 0), (0, 2)):
        bu = design_matrix(u, tu, pu, du)
        bv = design_matrix(v, tv, pv, dv)
        T = tensor_basis(bu, bv)
        assert T.shape == (len(u), nu * nv)
        assert np.all(np.diff(T.indptr) == (pu + 1) * (pv + 1))
        expected = np.einsum("ri,rj->rij", dense(bu), dense(bv)).reshape(len(u), nu * nv)
        np.testing.assert_allclose(dense(T), expected, rtol=0, atol=1e-15 * max(1, np.abs(expected).max()))
    T = dense(tensor_basis(design_matrix(u, tu, pu), design_matrix(v, tv, pv)))
    np.testing.assert_allclose(T.sum(axis=1), 1.0, rtol=0, atol=1e-12)


def test_tensor_basis_index_layout_by_hand():
    # bilinear on [0,1]^2 with no inner knots: T[r, i*2 + j] = N_i(u) N_j(v)
    t = clamped_knots(2, 1)
    T = dense(tensor_basis(design_matrix(np.array([0.25]), t, 1),
                           design_matrix(np.array([0.5]), t, 1)))
    np.testing.assert_allclose(T[0], [0.75 * 0.5, 0.75 * 0.5, 0.25 * 0.5, 0.25 * 0.5], rtol=0, atol=1e-16)
    T = dense(tensor_basis(design_matrix(np.array([0.25]), t, 1),
                           design_matrix(np.array([0.1]), t, 1)))
    np.testing.assert_allclose(T[0], [0.75 * 0.9, 0.75 * 0.1, 0.25 * 0.9, 0.25 * 0.1], rtol=0, atol=1e-16)


# ---------------------------------------------------------------------------
# Empty input
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("derivative", [0, 1])
def test_design_matrix_of_no_points_is_empty(derivative):
    t = clamped_knots(6, 3)
    B = design_matrix(np.array([]), t, 3, derivative)
    assert B.shape == (0, 6)
    assert B.nnz == 0

"""Regularised least squares (psonurbs.fitting.leastsq.regularised) against dense numpy computations:
the stacked least-squares solution, an explicit leave-one-out refit, and the
cell-block Gram / quadratic forms on an open and on a sphere layout."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline

from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.rows import Rows

LAYOUTS = {
    "open": NetLayout((5, 4), (2, 3)),
    "sphere": NetLayout((5, 5), (2, 2), (True, False), poles=True),
}


def dense_rational(layout: NetLayout, uv, free_weights):
    """R (N, n_free) built independently: scipy BSpline per direction, outer product,
    rational weighting on the full net, then summing columns that share a free point."""
    ku, kv = layout.knots()
    (pu, pv), (fu, fv) = layout.degrees, layout.full_shape
    bu = BSpline.design_matrix(np.clip(uv[:, 0], ku[pu], ku[-pu - 1]), ku, pu).toarray()
    bv = BSpline.design_matrix(np.clip(uv[:, 1], kv[pv], kv[-pv - 1]), kv, pv).toarray()
    t = (bu[:, :, None] * bv[:, None, :]).reshape(len(uv), fu * fv)
    w_full = free_weights[layout.free_index]
    r_full = t * w_full / (t @ w_full)[:, None]
    fold = np.zeros((fu * fv, layout.n_free))
    fold[np.arange(fu * fv), layout.free_index] = 1.0
    return r_full @ fold


def problem(name, n_points=70, seed=0):
    layout = LAYOUTS[name]
    rng = np.random.default_rng(seed)
    uv = rng.random((n_points, 2))
    uv[:4] = [[0, 0], [1, 1], [0, 1], [1, 0]]  # domain corners (u = 1 in the last span)
    weights = rng.uniform(0.5, 2.0, layout.n_free)
    rows = layout.rows(uv, weights)
    data = rng.normal(size=(n_points, 3))
    return layout, rows, data, dense_rational(layout, uv, weights)


def to_dense(rows: Rows) -> np.ndarray:
    out = np.zeros((len(rows.values), rows.n_columns))
    np.add.at(out, (np.repeat(np.arange(len(rows.values)), rows.values.shape[1]), rows.columns.ravel()),
              rows.values.ravel())
    return out


@pytest.mark.parametrize("name", ["open", "sphere"])
def test_rows_match_dense_rational_basis(name):
    layout, rows, data, r = problem(name)
    np.testing.assert_allclose(to_dense(rows), r, atol=1e-14)
    np.testing.assert_allclose(r.sum(axis=1), 1.0, atol=1e-14)  # partition of unity
    np.testing.assert_allclose(rows @ data[: rows.n_columns], r @ data[: rows.n_columns], atol=1e-13)
    np.testing.assert_allclose(rows.project(data), r.T @ data, atol=1e-12)


@pytest.mark.parametrize("name", ["open", "sphere"])
def test_gram_and_quadratic_forms_match_dense(name):
    layout, rows, data, r = problem(name, seed=1)
    assert rows.n_columns == layout.n_free
    np.testing.assert_allclose(rows.gram(), r.T @ r, atol=1e-13)
    blocks = rows.blocks()
    np.testing.assert_allclose(blocks.gram(), r.T @ r, atol=1e-13)
    a = np.random.default_rng(2).normal(size=(layout.n_free, layout.n_free))
    np.testing.assert_allclose(blocks.quadratic_forms(a), np.einsum("ni,ij,nj->n", r, a, r), atol=1e-12)


def test_sphere_layout_pole_columns_collapse():
    layout, rows, _, r = problem("sphere", seed=3)
    assert layout.n_free == 5 * 3 + 2
    pole_lo, pole_hi = 0, layout.n_free - 1
    uv = np.array([[0.1, 0.0], [0.7, 0.0], [0.3, 1.0]])
    on_pole = to_dense(layout.rows(uv, np.ones(layout.n_free)))
    # a point on a pole is the pole control point alone
    np.testing.assert_allclose(on_pole[:2, pole_lo], 1.0, atol=1e-14)
    np.testing.assert_allclose(on_pole[2, pole_hi], 1.0, atol=1e-14)


def stacked_solution(r, l, data, smoothing):
    lam = smoothing * np.trace(r.T @ r) / np.trace(l.T @ l)
    a = np.vstack([r, np.sqrt(lam) * l])
    b = np.vstack([data, np.zeros((len(l), data.shape[1]))])
    return np.linalg.lstsq(a, b, rcond=None)[0], lam


@pytest.mark.parametrize("name", ["open", "sphere"])
@pytest.mark.parametrize("smoothing", [1e-4, 0.1])
def test_solve_equals_stacked_dense_least_squares(name, smoothing):
    layout, rows, data, r = problem(name, seed=4)
    l_op = layout.smoothness_operator().toarray()
    solver = RegularisedLeastSquares(layout.smoothness_operator(), smoothing)
    expected, _ = stacked_solution(r, l_op, data, smoothing)
    got = solver.solve(rows, data)
    assert got.shape == (layout.n_free, 3)
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())


def test_under_determined_problem_is_decided_by_smoothness():
    """12 points on a 5 x 4 open net (20 control points): still a unique solution,
    and it equals the stacked dense least-squares solution."""
    layout = LAYOUTS["open"]
    rng = np.random.default_rng(5)
    uv = rng.random((12, 2))
    weights = np.ones(layout.n_free)
    rows = layout.rows(uv, weights)
    data = rng.normal(size=(12, 3))
    r = dense_rational(layout, uv, weights)
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-3)
    expected, _ = stacked_solution(r, layout.smoothness_operator().toarray(), data, 1e-3)
    np.testing.assert_allclose(solver.solve(rows, data), expected, rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize("name", ["open", "sphere"])
def test_leave_one_out_equals_brute_force_refits(name):
    layout, rows, data, r = problem(name, n_points=50, seed=6)
    smoothing = 1e-3
    solver = RegularisedLeastSquares(layout.smoothness_operator(), smoothing)
    l_op = layout.smoothness_operator().toarray()
    gram = r.T @ r
    lam = smoothing * np.trace(gram) / np.trace(l_op.T @ l_op)  # fixed by the FULL fit
    ridge = 1e-12 * np.trace(gram) / len(gram)  # the solver's documented tiny ridge
    errors = []
    for i in range(len(r)):
        keep = np.arange(len(r)) != i
        ri = r[keep]
        m = ri.T @ ri + lam * l_op.T @ l_op + ridge * np.eye(len(gram))
        p = np.linalg.solve(m, ri.T @ data[keep])
        errors.append(np.sum((r[i] @ p - data[i]) ** 2))
    brute = np.sqrt(np.mean(errors))
    assert solver.leave_one_out_rmse(rows, data) == pytest.approx(brute, rel=1e-8)
    # and LOO is worse than the in-sample fit error
    p = solver.solve(rows, data)
    assert solver.leave_one_out_rmse(rows, data) > np.sqrt(np.mean(np.sum((r @ p - data) ** 2, axis=1)))


def test_with_smoothing_changes_only_the_weight():
    layout, rows, data, r = problem("open", seed=7)
    base = RegularisedLeastSquares(layout.smoothness_operator(), 1e-6)
    other = base.with_smoothing(0.05)
    assert base.smoothing == 1e-6 and other.smoothing == 0.05
    assert other.penalty is base.penalty
    expected, _ = stacked_solution(r, layout.smoothness_operator().toarray(), data, 0.05)
    np.testing.assert_allclose(other.solve(rows, data), expected, rtol=1e-8, atol=1e-10)


def test_interpolating_data_has_zero_fit_and_exact_reproduction():
    """Data on a surface of the same net is reproduced (tiny smoothing) and an affine
    net is reproduced exactly whatever the smoothing (L annihilates it)."""
    layout = LAYOUTS["open"]
    rng = np.random.default_rng(8)
    uv = rng.random((80, 2))
    weights = np.ones(layout.n_free)
    rows = layout.rows(uv, weights)
    i, j = np.meshgrid(np.arange(5), np.arange(4), indexing="ij")
    affine = np.stack([1 + 2 * i - j, 0.5 * i + 3 * j, -i + 0.25 * j + 7], axis=-1).reshape(-1, 3).astype(float)
    data = rows @ affine
    control = RegularisedLeastSquares(layout.smoothness_operator(), 0.5).solve(rows, data)
    np.testing.assert_allclose(control, affine, atol=1e-8)


def robust_weights(n, seed):
    """Weights as a robust loss makes them: most near 1, some partial, a few exactly 0."""
    w = np.random.default_rng(seed).uniform(0.3, 1.0, n)
    w[::7] = 0.0
    return w


@pytest.mark.parametrize("name", ["open", "sphere"])
def test_weighted_solve_equals_stacked_dense_weighted_least_squares(name):
    layout, rows, data, r = problem(name, seed=9)
    w = robust_weights(len(r), 10)
    l_op = layout.smoothness_operator().toarray()
    root = np.sqrt(w)[:, None]
    lam = 1e-3 * np.trace(r.T @ (w[:, None] * r)) / np.trace(l_op.T @ l_op)  # from tr(R^T W R)
    a = np.vstack([root * r, np.sqrt(lam) * l_op])
    b = np.vstack([root * data, np.zeros((len(l_op), 3))])
    expected = np.linalg.lstsq(a, b, rcond=None)[0]
    got = RegularisedLeastSquares(layout.smoothness_operator(), 1e-3).solve(rows, data, w)
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())


def test_zero_weight_is_leaving_the_point_out_and_no_weights_are_unit_weights():
    layout, rows, data, _ = problem("open", seed=11)
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-3)
    w = np.ones(len(data))
    # None and unit weights give bit-identical numbers (today's unweighted solve)
    assert np.array_equal(solver.solve(rows, data), solver.solve(rows, data, w))
    assert solver.leave_one_out_rmse(rows, data) == solver.leave_one_out_rmse(rows, data, w)
    w[[3, 10, 20]] = 0.0
    keep = w > 0
    np.testing.assert_allclose(solver.solve(rows, data, w), solver.solve(rows.take(keep), data[keep]),
                               rtol=1e-10, atol=1e-12)
    # a left-out point does not count in the weighted LOO error, and keeps its plain residual
    control, loo = solver.leave_one_out(rows, data, w)
    np.testing.assert_allclose(loo[~keep], (rows @ control - data)[~keep], atol=1e-14)
    assert solver.leave_one_out_rmse(rows, data, w) == pytest.approx(
        solver.leave_one_out_rmse(rows.take(keep), data[keep]), rel=1e-10)


@pytest.mark.parametrize("name", ["open", "sphere"])
def test_weighted_leave_one_out_equals_brute_force_refits(name):
    """e_i / (1 - w_i h_ii) is the residual at point i of the weighted fit without point i."""
    layout, rows, data, r = problem(name, n_points=50, seed=12)
    w = robust_weights(len(r), 13)
    smoothing = 1e-3
    solver = RegularisedLeastSquares(layout.smoothness_operator(), smoothing)
    l_op = layout.smoothness_operator().toarray()
    gram = r.T @ (w[:, None] * r)
    lam = smoothing * np.trace(gram) / np.trace(l_op.T @ l_op)  # fixed by the full weighted fit
    ridge = 1e-12 * np.trace(gram) / len(gram)
    brute = np.empty((len(r), 3))
    for i in range(len(r)):
        wi = w.copy()
        wi[i] = 0.0
        m = r.T @ (wi[:, None] * r) + lam * l_op.T @ l_op + ridge * np.eye(len(gram))
        brute[i] = r[i] @ np.linalg.solve(m, r.T @ (wi[:, None] * data)) - data[i]
    _, loo = solver.leave_one_out(rows, data, w)
    np.testing.assert_allclose(loo, brute, rtol=1e-7, atol=1e-9)
    expected = np.sqrt(np.sum(w * np.sum(brute ** 2, axis=1)) / np.sum(w))
    assert solver.leave_one_out_rmse(rows, data, w) == pytest.approx(expected, rel=1e-8)


def test_an_integer_weight_is_the_point_given_that_many_times():
    """Weight 2 on a point is the point twice: the data term, the smoothing's relative
    weight (from tr(R^T W R)) and the leave-one-out residuals of the other points."""
    layout, rows, data, _ = problem("open", seed=14)
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-3)
    w = np.ones(len(data))
    w[[2, 9]] = 2.0
    twice = np.r_[np.arange(len(data)), [2, 9]]
    np.testing.assert_allclose(solver.solve(rows, data, w), solver.solve(rows.take(twice), data[twice]),
                               rtol=1e-10, atol=1e-12)
    others = np.setdiff1d(np.arange(len(data)), [2, 9])
    np.testing.assert_allclose(solver.leave_one_out(rows, data, w)[1][others],
                               solver.leave_one_out(rows.take(twice), data[twice])[1][others], rtol=1e-8, atol=1e-12)

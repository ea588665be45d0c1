"""Big clouds in bounded memory: every chunked computation equals the unchunked one.

The chunk sizes are module constants; here they are made tiny (a few rows, blocks of
two or three rows) so that small problems cross every chunk and block boundary, and
the results are compared with dense computations and with the one-chunk path.
"""
from __future__ import annotations

import numpy as np
import pytest

from psonurbs.fitting.finish import refine
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.geometry import nurbs, projection, rows
from psonurbs.geometry.net import NetLayout


def skewed_parameters(n: int, seed: int) -> np.ndarray:
    """Parameters whose density varies a hundredfold: some cells hold many rows, some one."""
    rng = np.random.default_rng(seed)
    uv = rng.random((n, 2)) ** 4
    uv[:4] = [[0, 0], [1, 1], [0, 1], [1, 0]]
    return uv


@pytest.mark.parametrize("layout", [NetLayout((5, 4), (2, 3)), NetLayout((5, 5), (2, 2), (True, False), poles=True)])
def test_cell_block_sums_equal_dense_products_across_chunks(layout, monkeypatch):
    uv = skewed_parameters(300, 1)
    rng = np.random.default_rng(2)
    r = layout.rows(uv, rng.uniform(0.5, 2.0, layout.n_free))
    full = r.toarray()
    data = rng.normal(size=(len(uv), 3))
    a = rng.normal(size=(layout.n_free, layout.n_free))
    x, y = rng.normal(size=r.values.shape), rng.normal(size=r.values.shape)
    dense_x, dense_y = (rows.Rows(z, r.columns, r.n_columns, r.cells).toarray() for z in (x, y))
    results = []
    for chunk, height in ((1 << 17, 64), (7, 3), (1, 1)):
        monkeypatch.setattr(rows, "ROW_CHUNK", chunk)
        monkeypatch.setattr(rows, "BLOCK_HEIGHT", height)
        blocks = r.blocks()
        if chunk == 7:
            assert len(blocks.batches) > 1 and blocks.height == 3
        got = (blocks.gram(), blocks.quadratic_forms(a), r.project(data), r @ data[:layout.n_free], blocks.gram(x, y))
        np.testing.assert_allclose(got[0], full.T @ full, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[1], np.einsum("ni,ij,nj->n", full, a, full), rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[2], full.T @ data, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[3], full @ data[:layout.n_free], rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[4], dense_x.T @ dense_y, rtol=0, atol=1e-12)
        results.append(got)
    for other in results[1:]:
        for g, h in zip(results[0], other):
            np.testing.assert_allclose(g, h, rtol=0, atol=1e-12)


def test_cells_within_the_block_height_make_one_block_each_and_one_batch():
    """Few rows: the layout of a single batch with one block per cell (as the swarm's
    fitness sees it)."""
    layout = NetLayout((5, 5), (3, 3))
    r = layout.rows(np.random.default_rng(3).random((200, 2)), np.ones(25))
    blocks = r.blocks()
    assert len(blocks.batches) == 1
    assert len(blocks.columns) == len(np.unique(r.cells)) and blocks.height == np.bincount(r.cells).max()


def test_chunked_evaluation_and_foot_points_are_the_unchunked_ones(monkeypatch):
    layout = NetLayout((6, 5), (3, 2))
    rng = np.random.default_rng(4)
    surface = layout.surface(rng.normal(size=(30, 3)) * 0.1 + np.c_[np.linspace(0, 1, 30), np.zeros((30, 2))],
                             rng.uniform(0.5, 2.0, 30))
    uv = rng.random((97, 2))
    points = surface.evaluate(uv[:, 0], uv[:, 1]) + 0.05 * rng.normal(size=(97, 3))
    whole = (surface.derivatives(uv[:, 0], uv[:, 1], second=True), closest_parameters_both(surface, points, uv))
    monkeypatch.setattr(nurbs, "EVALUATION_CHUNK", 5)
    monkeypatch.setattr(projection, "FOOT_POINT_CHUNK", 6)
    parts = (surface.derivatives(uv[:, 0], uv[:, 1], second=True), closest_parameters_both(surface, points, uv))
    for a, b in zip(whole[0] + whole[1], parts[0] + parts[1]):
        np.testing.assert_array_equal(a, b)


def closest_parameters_both(surface, points, uv):
    """Foot points from given starts and from the global search."""
    return projection.closest_parameters(surface, points, uv) + projection.closest_parameters(surface, points)


def dense_damped_step(problem: refine.JointProblem, control, weights, uv, damping, frozen):
    """The damped Gauss-Newton step of the joint problem from its dense Jacobian over
    every unknown (net, log-weights, parameters), solved as one system.

    The damping is the refinement's: each point's 2 x 2 block gets ``damping`` times
    its mean diagonal, the net ``damping`` times the mean diagonal of the Schur
    complement (formed densely here to know it); a frozen parameter's column is zero
    and its diagonal 1.
    """
    n, n_pts = problem.n, len(uv)
    ev = problem.evaluate(control, weights, uv)
    r = ev["rows"].toarray()  # (N, n)
    s = r @ control
    _, su, sv = problem.layout.surface(control, weights, *problem.inner).derivatives(uv[:, 0], uv[:, 1])
    jac = np.zeros((3 * n_pts, 4 * n + 2 * n_pts))
    for k in range(3):
        jac[k::3, k:3 * n:3] = r
        jac[k::3, 3 * n:4 * n] = r * (control[:, k][None, :] - s[:, k:k + 1])
        jac[k::3, 4 * n::2][np.arange(n_pts), np.arange(n_pts)] = su[:, k]
        jac[k::3, 4 * n + 1::2][np.arange(n_pts), np.arange(n_pts)] = sv[:, k]
    jac[:, 4 * n:][:, frozen.ravel()] = 0.0
    jac *= np.repeat(problem.root, 3)[:, None]  # the weighted problem: every row times sqrt(c_i)
    res = ev["residual"].ravel()
    a = jac.T @ jac
    a[:3 * n, :3 * n] += np.kron(ev["regulariser"], np.eye(3))
    g = jac.T @ res
    g[:3 * n] += np.kron(ev["regulariser"], np.eye(3)) @ control.ravel()
    point = slice(4 * n, None)
    blocks = a[point, point].diagonal().reshape(n_pts, 2)
    shift = damping * np.maximum(blocks.mean(axis=1), 1e-300)
    a[point, point] += np.diag(np.repeat(shift, 2) + frozen.ravel())
    net = slice(0, 4 * n)
    schur = a[net, net] - a[net, point] @ np.linalg.solve(a[point, point], a[point, net])
    a[net, net] += np.eye(4 * n) * damping * np.trace(schur) / (4 * n)
    step = np.linalg.solve(a, -g)
    return step[:3 * n].reshape(n, 3), step[3 * n:4 * n], step[4 * n:].reshape(n_pts, 2)


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("layout", [NetLayout((5, 4), (3, 2)), NetLayout((5, 5), (2, 2), (True, False), poles=True)])
def test_refinement_step_is_the_dense_damped_gauss_newton_step_in_any_chunks(layout, weighted, monkeypatch):
    """With and without the robust loss's point weights c_i (the dense Jacobian's rows
    and the residuals times sqrt(c_i))."""
    rng = np.random.default_rng(5)
    point_weights = rng.uniform(0.05, 1.0, 60) if weighted else None
    uv = skewed_parameters(60, 6)
    points = np.c_[uv, 0.2 * np.sin(3 * uv[:, 0])] + 0.01 * rng.normal(size=(60, 3))
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-3, layout.constraint_operator())
    weights = rng.uniform(0.7, 1.4, layout.n_free)
    control = solver.solve(layout.rows(uv, weights), points)
    frozen = rng.random((60, 2)) < 0.1
    steps = []
    for chunk, row_chunk, height in ((1 << 14, 1 << 17, 64), (11, 7, 3)):
        monkeypatch.setattr(refine, "REFINE_CHUNK", chunk)
        monkeypatch.setattr(rows, "ROW_CHUNK", row_chunk)
        monkeypatch.setattr(rows, "BLOCK_HEIGHT", height)
        problem = refine.JointProblem(layout, solver, points, None, None, point_weights)
        lin = problem.linearise(control, weights, uv, problem.evaluate(control, weights, uv))
        for damping, mask in ((1e-3, None), (0.3, frozen)):
            got = problem.step(lin, damping, mask)
            want = dense_damped_step(problem, control, weights, uv, damping,
                                     np.zeros((60, 2), bool) if mask is None else mask)
            for g, w in zip(got, want):
                np.testing.assert_allclose(g, w, rtol=0, atol=1e-9 * np.abs(w).max())
            steps.append(got)
    for g, w in zip(steps[0] + steps[1], steps[2] + steps[3]):
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-12 * max(np.abs(w).max(), 1.0))


def test_foot_points_of_points_that_stopped_moving_are_not_searched_again(monkeypatch):
    """Started at their foot points, the points take one Newton step each and drop out
    (only those whose step is still above the tolerance, a few at the floor of rounding,
    go on); of a mixed set only the points still moving take further steps. (The numpy
    search, whose steps can be counted; the compiled one finds the same foot points.)"""
    monkeypatch.setattr(projection, "COMPILED", False)
    layout = NetLayout((5, 5), (3, 3))
    i, j = np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 1, 5), indexing="ij")
    surface = layout.surface(np.stack([i, j, 0.2 * np.sin(3 * i) * j], -1).reshape(-1, 3), np.ones(25))
    rng = np.random.default_rng(7)
    points = surface.evaluate(*rng.uniform(0.1, 0.9, (2, 200))) + 0.01 * rng.normal(size=(200, 3))
    foot, dist = projection.closest_parameters(surface, points)
    still = int(np.sum(np.abs(projection.foot_point_step(surface, points, foot, (False, False))).max(axis=1)
                       > projection.PARAMETER_TOLERANCE))
    assert still < 20
    stepped = []
    step = projection.foot_point_step
    monkeypatch.setattr(projection, "foot_point_step", lambda s, p, uv, c: stepped.append(len(p)) or step(s, p, uv, c))
    again, again_dist = projection.closest_parameters(surface, points, foot)
    np.testing.assert_allclose(again, foot, rtol=0, atol=1e-9)
    assert np.all(again_dist <= dist)
    assert stepped[0] == 200 and max(stepped[1:], default=0) <= still
    start = foot.copy()
    start[:10] += 0.01  # ten points moved off their foot points
    stepped.clear()
    projection.closest_parameters(surface, points, start)
    assert stepped[0] == 200 and max(stepped[1:]) <= 10 + still


def test_refinement_step_in_threads_gives_the_bytes_of_one(monkeypatch):
    """The chunks' sums are formed in threads (compiled.in_order) and added in chunk
    order: 1, 2 and 3 threads give the same bytes."""
    layout = NetLayout((5, 4), (3, 2))
    rng = np.random.default_rng(8)
    uv = skewed_parameters(90, 9)
    points = np.c_[uv, 0.2 * np.sin(3 * uv[:, 0])] + 0.01 * rng.normal(size=(90, 3))
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-3)
    weights = rng.uniform(0.7, 1.4, layout.n_free)
    control = solver.solve(layout.rows(uv, weights), points)
    monkeypatch.setattr(refine, "REFINE_CHUNK", 13)  # 7 chunks
    found = []
    for n in (1, 2, 3):
        monkeypatch.setenv("PSONURBS_THREADS", str(n))
        problem = refine.JointProblem(layout, solver, points, None, None)
        lin = problem.linearise(control, weights, uv, problem.evaluate(control, weights, uv))
        found.append(b"".join(a.tobytes() for a in (lin["gram"], lin["g"], *problem.step(lin, 1e-3))))
    assert found[0] == found[1] == found[2]

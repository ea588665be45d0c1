"""The compiled twin of the swarm's fitness (numba kernels in geometry/stacked_rows,
fitting/banded, fitting/stacked_solve) against the numpy reference: the rows, the band
factorisation and selected inverse, the (leave-one-out) error on several nets and layouts,
with point weights, and a particle whose normal matrix is not positive definite.

Without numba (or with PSONURBS_NO_JIT=1) the kernels run as plain Python: the same
comparisons then check their source, slowly, so the problems here are small."""
from __future__ import annotations

import numpy as np
import pytest
from test_stacked import LAYOUTS, banded_spd, search_for

from psonurbs.fitting.leastsq.banded import band_cholesky, band_selected_inverse, band_solve
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.leastsq.stacked import StackedLeastSquares
from psonurbs.fitting.leastsq.stacked_compiled import cell_order
from psonurbs.fitting.search.knot_weight_space import KnotWeightSpace
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.stacked_rows import CellLayout, knot_vectors, particle_cells, particle_rows, stacked_rows

NETS = {  # more degrees and sizes: m = 16, 12, 9, 6 columns a row
    "cubic 9 x 8": NetLayout((9, 8), (3, 3)),
    "quadratic-cubic": NetLayout((6, 7), (2, 3)),
    "quadratic cylinder": NetLayout((7, 5), (2, 2), (True, False)),
    "linear-quadratic torus": NetLayout((6, 6), (1, 2), (True, True)),
}


def net_search(name: str, cross_validation: bool, n_points: int = 900, seed: int = 0) -> KnotWeightSpace:
    """A well-posed fitness (tens of points a cell: with a handful, leverages near 1 make the
    error ill-conditioned, and numpy's own two paths differ in the 6th digit)."""
    if name in LAYOUTS:
        return search_for(name, cross_validation, n_points=n_points, seed=seed)
    layout = NETS[name]
    rng = np.random.default_rng(seed)
    uv = rng.random((n_points, 2))
    points = np.column_stack([uv, np.sin(3 * uv[:, 0]) * np.cos(2 * uv[:, 1])])
    points += 0.01 * rng.normal(size=points.shape)
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-6, layout.constraint_operator())
    return KnotWeightSpace(layout, solver, points, uv, cross_validation, 0.2, (0.2, 5.0))


def band_of(matrix: np.ndarray, width: int, extra: int = 0) -> np.ndarray:
    """Upper band storage ``band[i, d] = M[i, i + d]``, (n, width + 1 + extra)."""
    n = len(matrix)
    band = np.zeros((n, width + 1 + extra))
    for d in range(width + 1):
        band[:n - d, d] = np.diagonal(matrix, d)
    return band


@pytest.mark.parametrize("name", list(LAYOUTS) + list(NETS))
def test_compiled_rows_equal_the_stacked_rows(name):
    search = net_search(name, True, n_points=200)
    swarm = search.initial_swarm(3, np.random.default_rng(1))
    cu, cv = search.counts
    layout, cells = search.layout, search.stacked.cells
    numpy_rows = stacked_rows(cells, search.uv, np.exp(swarm[:, cu + cv:-1]), swarm[:, :cu], swarm[:, cu:cu + cv])
    expected = numpy_rows.scatter(numpy_rows.values)  # (P, N, m)
    expected_cell = numpy_rows.scatter(np.broadcast_to((numpy_rows.chunk_block % cells.count)[:, None],
                                                       numpy_rows.values.shape[:2]))
    m = cells.columns.shape[1]
    for k, x in enumerate(swarm):
        knots = [knot_vectors(n, d, c, inner) for n, d, c, inner in
                 zip(layout.size, layout.degrees, layout.closed, (x[None, :cu], x[None, cu:cu + cv]))]
        cell_of = np.empty(len(search.uv), np.int64)
        degrees = np.asarray(layout.degrees, np.int64)
        particle_cells(search.uv, knots[0][0], knots[1][0], degrees, cells.shape[1], cell_of)
        np.testing.assert_array_equal(cell_of, expected_cell[k])
        first, order = np.empty(cells.count + 1, np.int64), np.empty(len(search.uv), np.int64)
        cell_order(cell_of, first, order)
        assert np.all(np.diff(cell_of[order]) >= 0) and sorted(order) == list(range(len(order)))
        np.testing.assert_array_equal(first[1:] - first[:-1], np.bincount(cell_of, minlength=cells.count))
        rows = np.full((len(search.uv), m + 3), 7.0)  # the kernel writes [:m] only
        particle_rows(search.uv, knots[0][0], knots[1][0], degrees, cells.shape[1], np.exp(x[cu + cv:-1]),
                      cells.columns.astype(np.int64), first, order, rows)
        np.testing.assert_allclose(rows[:, :m], expected[k][order], rtol=0, atol=2e-16)
        assert np.all(rows[:, m:] == 7.0)


@pytest.mark.parametrize("n, width", [(30, 7), (61, 13), (20, 19), (5, 2), (9, 0)])
def test_band_kernels_solve_and_give_the_inverse_inside_the_band(n, width):
    m = banded_spd(n, width, 1, seed=n)[0]
    band = band_of(m, width)
    assert band_cholesky(band)
    np.testing.assert_allclose(band, band_of(np.linalg.cholesky(m).T, width), rtol=0, atol=1e-13)
    rhs = np.random.default_rng(0).normal(size=(n, 3))
    x = rhs.copy()
    band_solve(band, x)
    np.testing.assert_allclose(x, np.linalg.solve(m, rhs), rtol=0, atol=1e-13)
    inverse = np.zeros((n, 2 * width + 1 + 8))
    band_selected_inverse(band, inverse)
    expected = np.linalg.inv(m)
    for d in range(-width, width + 1):
        i = np.arange(max(0, -d), min(n, n - d))
        np.testing.assert_allclose(inverse[i, width + d], expected[i, i + d], rtol=0, atol=1e-14)


def test_band_cholesky_refuses_an_indefinite_or_nan_matrix():
    m = banded_spd(12, 3, 1, seed=1)[0]
    m[5, 5] = -1.0
    assert not band_cholesky(band_of(m, 3))
    m[5, 5] = np.nan
    assert not band_cholesky(band_of(m, 3))


@pytest.mark.parametrize("cross_validation", [True, False])
@pytest.mark.parametrize("name", list(LAYOUTS) + list(NETS))
def test_compiled_fitness_equals_the_numpy_fitness(name, cross_validation):
    search = net_search(name, cross_validation)
    swarm = search.initial_swarm(6, np.random.default_rng(2))
    compiled = search.compiled_fitness(swarm)
    np.testing.assert_allclose(compiled, search.numpy_fitness(swarm), rtol=1e-11, atol=0)
    np.testing.assert_allclose(compiled, [search.error(x) for x in swarm], rtol=1e-11, atol=0)
    assert np.all(np.diff(compiled) != 0)  # the particles really differ


@pytest.mark.parametrize("cross_validation", [True, False])
@pytest.mark.parametrize("name", ["open", "sphere", "quadratic-cubic"])
def test_compiled_fitness_with_point_weights_equals_the_numpy_fitness(name, cross_validation):
    search = net_search(name, cross_validation)
    w = np.random.default_rng(6).uniform(0.0, 1.0, len(search.points))
    w[:30] = 0.0  # left out entirely, as a redescending weight does with gross outliers
    search.point_weights = w
    swarm = search.initial_swarm(4, np.random.default_rng(5))
    compiled = search.compiled_fitness(swarm)
    np.testing.assert_allclose(compiled, search.numpy_fitness(swarm), rtol=1e-11, atol=0)
    search.point_weights = None
    assert np.all(np.abs(compiled / search.compiled_fitness(swarm) - 1) > 1e-6)  # the weights count


def test_compiled_fitness_is_deterministic_and_each_particle_its_own():
    search = net_search("open", True)
    swarm = search.initial_swarm(8, np.random.default_rng(3))
    whole = search.compiled_fitness(swarm)
    assert whole.tobytes() == search.compiled_fitness(swarm).tobytes()
    # particle by particle: another grouping gives the same bytes
    parts = np.concatenate([search.compiled_fitness(swarm[:3]), search.compiled_fitness(swarm[3:])])
    assert parts.tobytes() == whole.tobytes()


def test_a_particle_that_is_not_positive_definite_scores_inf_and_the_others_are_kept():
    search = net_search("open", True)
    swarm = search.initial_swarm(4, np.random.default_rng(4))
    cu, cv = search.counts
    smoothing = 10.0 ** swarm[:, -1]
    smoothing[2] = -1e3  # M = R^T R - big L^T L: indefinite
    args = (search.uv, np.exp(swarm[:, cu + cv:-1]), swarm[:, :cu], swarm[:, cu:cu + cv], search.points)
    got = search.stacked.compiled_errors(*args, smoothing, True)
    rows = search.rows(swarm)
    with pytest.raises(np.linalg.LinAlgError):  # the numpy path refuses the group (fitness then retries)
        search.stacked.errors(rows, search.points, smoothing, True)
    assert got[2] == np.inf
    keep = [0, 1, 3]
    expected = search.stacked.errors(search.rows(swarm[keep]), search.points, smoothing[keep], True)
    np.testing.assert_allclose(got[keep], expected, rtol=1e-11, atol=0)


@pytest.mark.parametrize("name", ["open", "quadratic cylinder"])
def test_the_fitness_in_threads_is_the_fitness_in_one(name, monkeypatch):
    """Particles are split among threads (compiled.over_parts): the same bytes with 1, 2 or 3."""
    search = net_search(name, True)
    swarm = search.initial_swarm(11, np.random.default_rng(4))
    found = {}
    for n in (1, 2, 3):
        monkeypatch.setenv("PSONURBS_THREADS", str(n))
        found[n] = search.compiled_fitness(swarm).tobytes()
    assert found[1] == found[2] == found[3]


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("name", list(LAYOUTS) + list(NETS))
def test_compiled_control_points_equal_the_solvers(name, weighted):
    """One net's least squares by the kernel (the polish's solve) against the solver's
    numpy path: searched knots and weights, and uniform knots (None) with unit weights."""
    search = net_search(name, False)
    layout, cu, cv = search.layout, *search.counts
    w = np.random.default_rng(7).uniform(0.0, 1.0, len(search.points)) if weighted else None
    if weighted:
        w[:20] = 0.0
    position = search.initial_swarm(2, np.random.default_rng(8))[1]
    shapes = [NetShape(np.exp(position[cu + cv:-1]), position[:cu], position[cu:cu + cv]),
              NetShape(np.ones(layout.n_free))]
    stacked = StackedLeastSquares(search.solver, CellLayout(layout))
    for shape in shapes:
        expected = search.solver.solve(layout.rows(search.uv, *shape), search.points, w)
        got = stacked.compiled_control(search.uv, shape, search.points, w)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10 * np.abs(expected).max())
    assert np.abs(got - stacked.compiled_control(search.uv, shapes[0], search.points, w)).max() > 1e-3


def test_compiled_control_refuses_a_matrix_that_is_not_positive_definite():
    search = net_search("open", False)
    stacked = StackedLeastSquares(search.solver.with_smoothing(-1e3), CellLayout(search.layout))
    with pytest.raises(np.linalg.LinAlgError):
        stacked.compiled_control(search.uv, NetShape(np.ones(search.layout.n_free)), search.points)

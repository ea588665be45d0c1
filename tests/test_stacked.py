"""The batched fitness (geometry/stacked_rows, fitting/banded, fitting/stacked_solve) against
the single-particle path and against dense numpy: the rows of many knot vectors, the banded
factorisation and its selected inverse, the leave-one-out error with and without point
weights, on open, cylinder, sphere (poles + tangent planes) and torus layouts."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from psonurbs.fitting.leastsq.banded import BandOrder, StackedBandedCholesky
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.search.knot_weight_space import KnotWeightSpace
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.stacked_rows import CellLayout, stacked_rows

LAYOUTS = {
    "open": NetLayout((7, 6), (3, 2)),
    "cylinder": NetLayout((8, 5), (3, 3), (True, False)),
    "sphere": NetLayout((6, 6), (2, 3), (True, False), poles=True),
    "torus": NetLayout((7, 6), (3, 2), (True, True)),
}


def search_for(name: str, cross_validation: bool, n_points: int = 900, seed: int = 0) -> KnotWeightSpace:
    """A well-posed swarm fitness (many points per cell): a smooth surface of (u, v), noisy."""
    layout = LAYOUTS[name]
    rng = np.random.default_rng(seed)
    uv = rng.random((n_points, 2))
    uv[:4] = [[0, 0], [1, 1], [0, 1], [1, 0]]  # domain corners: x = 1 belongs to the last span
    a, b = 2 * np.pi * uv[:, 0], np.pi * uv[:, 1]
    points = np.column_stack([np.cos(a) * (2 + np.sin(b)), np.sin(a) * (2 + np.sin(b)), np.cos(b)])
    points += 0.01 * rng.normal(size=points.shape)
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-6, layout.constraint_operator())
    return KnotWeightSpace(layout, solver, points, uv, cross_validation, 0.2, (0.2, 5.0))


def dense_rows(search: KnotWeightSpace, x: np.ndarray) -> np.ndarray:
    return search.layout.rows(search.uv, *search.split(x).shape).toarray()


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_stacked_rows_equal_the_single_particle_rows(name):
    search = search_for(name, True, n_points=300)
    swarm = search.initial_swarm(6, np.random.default_rng(1))
    cu, cv = search.counts
    rows = stacked_rows(CellLayout(search.layout), search.uv, np.exp(swarm[:, cu + cv:-1]), swarm[:, :cu],
                        swarm[:, cu:cu + cv])
    values = rows.scatter(rows.values)  # (P, N, m)
    cells = rows.scatter(np.broadcast_to((rows.chunk_block % rows.cells.count)[:, None], rows.values.shape[:2]))
    columns = rows.cells.columns[cells]  # (P, N, m)
    n = search.layout.n_free
    for k, x in enumerate(swarm):
        dense = np.zeros((len(search.uv), n))
        np.add.at(dense, (np.arange(len(search.uv))[:, None], columns[k]), values[k])
        np.testing.assert_allclose(dense, dense_rows(search, x), rtol=0, atol=1e-14)
    # padding slots hold zero rows
    assert rows.values.shape[0] * rows.values.shape[1] > values.shape[0] * values.shape[1]
    np.testing.assert_allclose(rows.per_particle(rows.values.sum(axis=2)), len(search.uv), rtol=1e-13)


@pytest.mark.parametrize("cross_validation", [True, False])
@pytest.mark.parametrize("name", list(LAYOUTS))
def test_batched_fitness_equals_the_single_particle_error(name, cross_validation):
    search = search_for(name, cross_validation)
    swarm = search.initial_swarm(10, np.random.default_rng(2))
    single = np.array([search.error(x) for x in swarm])
    np.testing.assert_allclose(search.numpy_fitness(swarm), single, rtol=1e-12, atol=0)


def test_batched_fitness_is_deterministic_and_independent_of_the_grouping():
    search = search_for("open", True)
    swarm = search.initial_swarm(12, np.random.default_rng(3))
    whole = search.numpy_fitness(swarm)
    assert whole.tobytes() == search.numpy_fitness(swarm).tobytes()  # the same call, the same bytes
    # each particle's numbers are its own: another grouping changes at most the last bit
    # (numpy's vector reductions depend on the alignment of the data in memory)
    parts = np.concatenate([search.numpy_fitness(swarm[:5]), search.numpy_fitness(swarm[5:])])
    np.testing.assert_allclose(parts, whole, rtol=1e-15, atol=0)
    assert np.all(np.diff(whole) != 0)  # the particles really differ


def test_a_particle_whose_solve_fails_scores_inf_and_the_others_are_kept(monkeypatch):
    # the numpy path: a group whose solve fails is retried particle by particle
    search = search_for("open", True)
    swarm = search.initial_swarm(5, np.random.default_rng(4))
    expected = search.numpy_fitness(swarm)
    errors = search.stacked.errors

    def failing(rows, data, smoothing, *args, **kwargs):  # particle 2 has a singular system
        if np.any(np.isclose(smoothing, 10.0 ** swarm[2, -1], rtol=0, atol=0)):
            raise np.linalg.LinAlgError("not positive definite")
        return errors(rows, data, smoothing, *args, **kwargs)

    monkeypatch.setattr(search.stacked, "errors", failing)
    got = search.numpy_fitness(swarm)
    assert got[2] == np.inf
    np.testing.assert_allclose(np.delete(got, 2), np.delete(expected, 2), rtol=1e-15, atol=0)


def weighted_reference(search: KnotWeightSpace, x: np.ndarray, w: np.ndarray, cross_validation: bool) -> float:
    """The weighted solve by dense numpy: M = R^T W R + regulariser(tr R^T W R), leave-one-out
    residual e_i / (1 - w_i h_i), weighted RMSE."""
    r = dense_rows(search, x)
    solver = search.solver.with_smoothing(search.split(x).smoothing)
    gram = r.T @ (w[:, None] * r)
    m = solver.normal_matrix(gram)
    control = np.linalg.solve(m, r.T @ (w[:, None] * search.points))
    residual = r @ control - search.points
    if cross_validation:
        h = np.einsum("ni,ij,nj->n", r, np.linalg.inv(m), r)
        residual = residual / (1.0 - w * h)[:, None]
    return float(np.sqrt(np.sum(w * np.sum(residual ** 2, axis=1)) / np.sum(w)))


@pytest.mark.parametrize("cross_validation", [True, False])
@pytest.mark.parametrize("name", ["open", "sphere"])
def test_point_weights_give_the_weighted_solve(name, cross_validation):
    search = search_for(name, cross_validation, n_points=600)
    swarm = search.initial_swarm(4, np.random.default_rng(5))
    w = np.random.default_rng(6).uniform(0.0, 1.0, len(search.points))
    w[:30] = 0.0  # left out entirely, as a redescending weight does with gross outliers
    cu, cv = search.counts
    rows = stacked_rows(search.stacked.cells, search.uv, np.exp(swarm[:, cu + cv:-1]), swarm[:, :cu],
                        swarm[:, cu:cu + cv])
    got = search.stacked.errors(rows, search.points, 10.0 ** swarm[:, -1], cross_validation, w)
    expected = [weighted_reference(search, x, w, cross_validation) for x in swarm]
    np.testing.assert_allclose(got, expected, rtol=1e-11)
    # unit weights are the unweighted fitness
    ones = search.stacked.errors(rows, search.points, 10.0 ** swarm[:, -1], cross_validation,
                                 np.ones(len(search.points)))
    np.testing.assert_allclose(ones, search.numpy_fitness(swarm), rtol=1e-13)


def banded_spd(n: int, width: int, count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    i = np.arange(n)
    band = np.abs(i[:, None] - i[None, :]) <= width
    a = rng.normal(size=(count, n, n)) * band
    return a @ a.transpose(0, 2, 1) * (np.abs(i[:, None] - i[None, :]) <= width) + n * np.eye(n)


@pytest.mark.parametrize("n, width, block", [(30, 7, 8), (61, 13, 16), (20, 19, 16), (5, 2, 8)])
def test_banded_cholesky_solves_and_gives_the_inverse_inside_the_band(n, width, block):
    m = banded_spd(n, width, 3, seed=n)
    factor = StackedBandedCholesky(m, width, block)
    rhs = np.random.default_rng(0).normal(size=(3, n, 2))
    np.testing.assert_allclose(factor.solve(rhs), np.linalg.solve(m, rhs), rtol=0, atol=1e-13)
    inverse = np.linalg.inv(m)
    band = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]) <= width
    selected = factor.selected_inverse()
    np.testing.assert_allclose(selected * band, inverse * band, rtol=0, atol=1e-14)


def test_banded_cholesky_in_place_gives_the_same_factors_and_inverse():
    m = banded_spd(40, 9, 3, seed=4)
    rhs = np.random.default_rng(1).normal(size=(3, 40, 3))
    copied = StackedBandedCholesky(m, 9, 16)
    expected = copied.solve(rhs), copied.selected_inverse().copy()
    work = m.copy()
    in_place = StackedBandedCholesky(work, 9, 16, overwrite=True)
    assert not np.array_equal(work, m)  # the factorisation ran in the given array
    np.testing.assert_array_equal(in_place.solve(rhs), expected[0])
    np.testing.assert_array_equal(in_place.selected_inverse(), expected[1])
    # the selected inverse reuses the storage, and asking again gives the same entries
    np.testing.assert_array_equal(in_place.selected_inverse(), expected[1])
    band = np.abs(np.arange(40)[:, None] - np.arange(40)[None, :]) <= 9
    np.testing.assert_allclose(expected[1] * band, np.linalg.inv(m) * band, rtol=0, atol=1e-14)


def test_banded_cholesky_refuses_an_indefinite_matrix():
    m = banded_spd(12, 3, 2, seed=1)
    m[1, 5, 5] = -1.0
    with pytest.raises(np.linalg.LinAlgError):
        StackedBandedCholesky(m, 3, 8)


def test_band_order_puts_a_periodic_direction_in_the_band():
    # a cycle of 40 unknowns, each coupled to its 3 neighbours on either side (wrapping)
    n, reach = 40, 3
    i = np.arange(n)
    gap = np.abs(i[:, None] - i[None, :])
    pattern = np.minimum(gap, n - gap) <= reach
    order = BandOrder.for_pattern(pattern)
    assert sorted(order.position) == list(range(n))
    r, c = np.nonzero(pattern)
    assert np.abs(order.position[r] - order.position[c]).max() == order.half_bandwidth
    assert order.half_bandwidth <= 3 * reach  # reverse Cuthill-McKee: 8 here; the natural order has 39
    # natural order for a band it already is
    banded = gap <= reach
    assert BandOrder.for_pattern(banded).half_bandwidth == reach


def periodic_spd(n: int, reach: int, seed: int) -> np.ndarray:
    """A symmetric positive definite (n, n) matrix coupling each unknown of a cycle to its
    ``reach`` neighbours on either side, shuffled (its band only in another order)."""
    i = np.arange(n)
    gap = np.abs(i[:, None] - i[None, :])
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, n)) * (np.minimum(gap, n - gap) <= reach)
    m = (a + a.T) + 4 * n * np.eye(n)
    shuffle = rng.permutation(n)
    return m[np.ix_(shuffle, shuffle)]


def assembled(order: BandOrder, m: np.ndarray, pieces: int = 1) -> np.ndarray:
    """The band storage of m assembled from its non-zeros, given in ``pieces`` parts whose
    entries overlap (each entry split between them), as a net system is summed over cells."""
    r, c = np.nonzero(m)
    flat, kept = order.places(r, c)
    return sum(order.gathered(flat[kept], m[r, c][kept] / pieces) for _ in range(pieces))


def test_a_system_assembled_in_its_band_solves_as_the_dense_one():
    m = periodic_spd(120, 4, seed=0)
    order = BandOrder.for_pattern(m != 0)
    assert 2 * order.half_bandwidth < 120  # the shuffled natural order holds no band
    rhs = np.random.default_rng(1).normal(size=(120, 3))
    band = assembled(order, m)
    np.testing.assert_allclose(order.solve(band, rhs), np.linalg.solve(m, rhs), rtol=0, atol=1e-13)
    np.testing.assert_allclose(assembled(order, m, pieces=3), band, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(band[0], m.diagonal()[np.argsort(order.position)], rtol=0, atol=0)


def test_a_banded_system_that_is_not_positive_definite_is_refused():
    m = periodic_spd(80, 3, seed=2)
    m[5, 5] = -1.0
    order = BandOrder.for_pattern(m != 0)
    with pytest.raises(np.linalg.LinAlgError):
        order.solve(assembled(order, m), np.ones(80))


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_normal_matrices_match_the_single_solver(name):
    search = search_for(name, True, n_points=300)
    x = search.initial_swarm(3, np.random.default_rng(8))[2]
    (weights, inner_u, inner_v), smoothing = search.split(x)
    rows = stacked_rows(search.stacked.cells, search.uv, weights[None], inner_u[None], inner_v[None])
    stacked = search.stacked.normal_matrices(rows, None, np.array([smoothing]))[0]
    single = search.solver.with_smoothing(smoothing).normal_matrix(
        search.layout.rows(search.uv, weights, inner_u, inner_v).gram())
    pos = search.stacked.order.position
    np.testing.assert_allclose(stacked, single[np.argsort(pos)][:, np.argsort(pos)], rtol=0,
                               atol=1e-13 * np.abs(single).max())
    assert sp.csr_array(single).nnz > 0

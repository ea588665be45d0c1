"""Particle swarm (psonurbs.fitting.search.swarm): convergence on a known minimum, monotone best
history, feasibility of every evaluated position, determinism, and the closed-form
largest feasible step."""
from __future__ import annotations

import numpy as np
import pytest

from psonurbs.fitting.search.swarm import Polytope, minimise


def shifted_sphere(centre):
    def f(x):
        return np.sum((x - centre) ** 2, axis=1)
    return f


def random_start(rng, n, lower, upper):
    return lower + (upper - lower) * rng.random((n, len(lower)))


@pytest.mark.parametrize("dim", [5, 8])
def test_minimise_finds_shifted_sphere_minimum(dim):
    rng = np.random.default_rng(dim)
    centre = rng.uniform(-3.0, 3.0, dim)
    lower, upper = np.full(dim, -5.0), np.full(dim, 5.0)
    res = minimise(shifted_sphere(centre), random_start(rng, 30, lower, upper), Polytope.box(lower, upper),
                   iterations=300, inertia=0.6, c1=1.5, c2=1.5, rng=np.random.default_rng(11))
    np.testing.assert_allclose(res.best_position, centre, atol=1e-3)
    assert res.best_value == pytest.approx(np.sum((res.best_position - centre) ** 2), abs=1e-15)
    assert res.best_value < 1e-6
    assert res.evaluations == 30 * 300
    assert res.best_history.shape == (300,) and res.mean_history.shape == (300,)
    assert res.best_history[-1] == res.best_value


def test_minimum_on_the_box_boundary():
    """The unconstrained minimum lies outside the box: the swarm ends on the face."""
    dim = 6
    centre = np.array([2.0, -0.5, 0.3, 4.0, -3.0, 0.0])  # box is [-1, 1]^6
    lower, upper = -np.ones(dim), np.ones(dim)
    rng = np.random.default_rng(3)
    res = minimise(shifted_sphere(centre), random_start(rng, 20, lower, upper), Polytope.box(lower, upper),
                   iterations=200, inertia=0.6, c1=1.5, c2=1.5, rng=rng)
    np.testing.assert_allclose(res.best_position, np.clip(centre, -1, 1), atol=1e-3)
    assert res.best_value == pytest.approx(np.sum((centre - np.clip(centre, -1, 1)) ** 2), abs=1e-4)


def test_best_history_never_rises_and_mean_is_swarm_mean():
    dim = 7
    rng = np.random.default_rng(5)
    centre = rng.uniform(-1, 1, dim)
    lower, upper = np.full(dim, -4.0), np.full(dim, 4.0)
    seen = []

    def f(x):
        val = np.sum((x - centre) ** 2, axis=1) + 0.3 * np.sum(np.sin(5 * x), axis=1)  # rugged
        seen.append(val.copy())
        return val

    calls = []
    res = minimise(f, random_start(rng, 12, lower, upper), Polytope.box(lower, upper), iterations=40,
                   inertia=0.7, c1=1.5, c2=1.5, rng=rng, on_iteration=lambda i, b, m: calls.append((i, b, m)))
    assert np.all(np.diff(res.best_history) <= 0.0)
    # the best after iteration k is the minimum of everything evaluated so far
    np.testing.assert_allclose(res.best_history, np.minimum.accumulate([s.min() for s in seen]), rtol=0, atol=0)
    np.testing.assert_allclose(res.mean_history, [s.mean() for s in seen], rtol=1e-14)
    assert [c[0] for c in calls] == list(range(1, 41))
    np.testing.assert_array_equal([c[1] for c in calls], res.best_history)


def test_non_finite_fitness_counts_as_infinitely_bad():
    dim = 3
    lower, upper = np.zeros(dim), np.ones(dim)

    def f(x):
        out = np.sum((x - 0.25) ** 2, axis=1)
        return np.where(x[:, 0] > 0.5, np.nan, out)

    rng = np.random.default_rng(0)
    res = minimise(f, random_start(rng, 10, lower, upper), Polytope.box(lower, upper), 60, 0.6, 1.5, 1.5, rng)
    assert np.isfinite(res.best_value) and res.best_position[0] <= 0.5
    assert np.all(np.isfinite(res.mean_history))


def test_every_evaluated_particle_is_feasible_box_and_ordered_knots():
    """Knots (ordered, gap >= 0.05) followed by box-bounded values; the optimum pulls
    the knots together and the values out of the box, so the swarm presses on every
    constraint, and no evaluated position may violate one."""
    count, gap, extra = 4, 0.05, 3
    dim = count + extra
    knots = Polytope.ordered(count, gap).embed(dim, 0)
    lo = np.r_[np.full(count, -np.inf), np.full(extra, -1.0)]
    hi = np.r_[np.full(count, np.inf), np.full(extra, 1.0)]
    feasible = Polytope.stack(knots, Polytope.box(lo, hi))
    target = np.r_[0.5, 0.5, 0.5, 0.5, 3.0, -3.0, 0.0]
    visited = []

    def f(x):
        visited.append(x.copy())
        return np.sum((x - target) ** 2, axis=1)

    rng = np.random.default_rng(42)
    start = []
    for _ in range(10):
        spacing = gap + (1 - (count + 1) * gap) * rng.dirichlet(np.ones(count + 1))
        start.append(np.r_[np.cumsum(spacing)[:-1], rng.uniform(-1, 1, extra)])
    res = minimise(f, np.array(start), feasible, 30, 0.7, 1.5, 1.5, rng)
    pos = np.concatenate(visited)
    assert len(pos) == 300
    assert np.all(feasible.contains(pos))
    t = pos[:, :count]
    assert np.all(t[:, 0] >= gap - 1e-12)
    assert np.all(np.diff(t, axis=1) >= gap - 1e-12)
    assert np.all(t[:, -1] <= 1 - gap + 1e-12)
    assert np.all(np.abs(pos[:, count:]) <= 1 + 1e-12)
    # the constrained optimum: knots pressed together around 0.5, values on the faces
    assert res.best_position[count] == pytest.approx(1.0, abs=0.05)
    assert res.best_position[count + 1] == pytest.approx(-1.0, abs=0.05)


def test_infeasible_start_is_refused():
    feasible = Polytope.ordered(2, 0.1)
    with pytest.raises(ValueError):
        minimise(lambda x: np.zeros(len(x)), np.array([[0.6, 0.3]]), feasible, 2, 0.7, 1.5, 1.5,
                 np.random.default_rng(0))


def test_same_seed_same_result_other_seed_differs():
    dim = 5
    centre = np.linspace(-1, 1, dim)
    lower, upper = np.full(dim, -2.0), np.full(dim, 2.0)
    start = random_start(np.random.default_rng(9), 10, lower, upper)

    def run(seed):
        return minimise(shifted_sphere(centre), start, Polytope.box(lower, upper), 25, 0.7, 1.5, 1.5,
                        np.random.default_rng(seed))

    a, b, c = run(1), run(1), run(2)
    np.testing.assert_array_equal(a.best_position, b.best_position)
    np.testing.assert_array_equal(a.best_history, b.best_history)
    np.testing.assert_array_equal(a.mean_history, b.mean_history)
    assert not np.array_equal(a.mean_history, c.mean_history)


def test_max_step_box_by_hand():
    box = Polytope.box(np.zeros(2), np.ones(2))
    x = np.array([[0.5, 0.5], [0.5, 0.5], [0.2, 0.9], [1.0, 0.3]])
    v = np.array([[1.0, 0.25], [0.2, -0.1], [-0.8, 0.4], [0.5, 0.0]])
    # row 0: x hits 1 at s = 0.5; row 1: whole step; row 2: x hits 0 at 0.25, y hits 1 at 0.25;
    # row 3: already on the face x = 1 moving out: no step
    np.testing.assert_allclose(box.max_step(x, v), [0.5, 1.0, 0.25, 0.0], rtol=0, atol=1e-15)
    # the step found is exactly feasible and exactly on the boundary
    s = box.max_step(x, v)
    assert np.all(box.contains(x + s[:, None] * v))


def test_max_step_ordered_by_hand():
    poly = Polytope.ordered(2, 0.1)  # 0.1 <= t1, t1 + 0.1 <= t2, t2 <= 0.9
    x = np.array([[0.3, 0.6], [0.3, 0.6], [0.3, 0.6], [0.3, 0.6]])
    v = np.array([[0.4, 0.0], [0.0, 0.6], [-0.4, 0.0], [0.1, 0.1]])
    # row 0: gap closes (slack 0.2) at 0.5; row 1: t2 reaches 0.9 at 0.5;
    # row 2: t1 reaches 0.1 at 0.5; row 3: parallel shift, t2 reaches 0.9 at s = 3 -> 1
    np.testing.assert_allclose(poly.max_step(x, v), [0.5, 0.5, 0.5, 1.0], rtol=1e-14)
    assert poly.A.shape == (3, 2)
    np.testing.assert_array_equal(poly.contains(np.array([[0.1, 0.2], [0.1, 0.19], [0.5, 0.91]])),
                                  [True, False, False])


def test_box_leaves_out_infinite_bounds_and_embed_offsets():
    box = Polytope.box(np.array([-np.inf, 0.0]), np.array([1.0, np.inf]))
    assert box.A.shape == (2, 2)
    np.testing.assert_array_equal(box.contains(np.array([[-1e9, 1e9], [1.5, 0.0], [0.0, -0.1]])),
                                  [True, False, False])
    emb = Polytope.ordered(2, 0.1).embed(5, 2)
    np.testing.assert_array_equal(emb.contains(np.array([[9, 9, 0.2, 0.5, -9], [0, 0, 0.5, 0.2, 0]])),
                                  [True, False])

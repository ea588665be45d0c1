"""The robust loss (psonurbs.fitting.robust): the biweight and its scale, the reweighted
classical fit, and whole fits with junk: what is left out, what the surface does."""
from __future__ import annotations

import dataclasses

import numpy as np
from conftest import franke, franke_z
from test_fit import config

from psonurbs.fitting.pipeline import fit_points
from psonurbs.fitting.robust import CUTOFF_SIGMAS, biweights, classical_weights, kept_sample
from psonurbs.fitting.solve import RegularisedLeastSquares
from psonurbs.geometry.net import NetLayout


def test_normal_residuals_keep_their_weight_and_junk_loses_it():
    rng = np.random.default_rng(0)
    d = np.abs(rng.normal(0.0, 1e-3, 200_000))  # the foot distances of normal noise
    w = biweights(d)
    assert w.min() > 0.0  # nothing left out: 10 sigmas is never reached
    sigma = 1.4826 * np.median(d)
    assert np.allclose(sigma, 1e-3, rtol=0.01)
    # the biweight itself: (1 - (d / 10 sigma)^2)^2
    np.testing.assert_allclose(w, (1.0 - (d / (CUTOFF_SIGMAS * sigma)) ** 2) ** 2)
    d[:50] = 12e-3  # 12 sigma
    d[50:60] = 5e-3  # 5 sigma: counts about half
    w = biweights(d)
    assert np.all(w[:50] == 0.0) and np.allclose(w[50:60], 0.5625, rtol=0.02) and np.all(w[60:] > 0)


def test_an_exact_fit_weighs_nothing_down():
    # distances at evaluation noise: the scale floor keeps a 100x larger one at full weight
    d = np.r_[np.full(999, 1e-10), 1e-8]
    assert biweights(d).min() > 0.999


def wave_grid(junk_height=None):
    g = np.linspace(0, 1, 20)
    x, y = np.meshgrid(g, g, indexing="ij")
    noise = np.random.default_rng(2).normal(0.0, 1e-3, 400)
    pts = np.column_stack([x.ravel(), y.ravel(), 0.1 * np.sin(3 * x.ravel() + 2 * y.ravel()) + noise])
    if junk_height is not None:
        pts[0, 2] = junk_height
    return pts


def test_junk_above_a_corner_gets_no_weight_and_its_neighbours_keep_theirs():
    # a noisy wave on a grid, one junk point above a corner, where one point weighs most
    # on the least-squares surface (the plain residual there is small: leave-one-out sees it)
    pts = wave_grid(0.3)
    layout = NetLayout((8, 8), (3, 3))
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-6)
    w = classical_weights(layout, solver, pts, pts[:, :2].copy())
    assert w[0] == 0.0 and w[1:].min() > 0.5 and np.median(w[1:]) > 0.95


def test_reweighting_stops_the_pull_of_moderate_junk():
    """A point 12 sigmas off is left out; its neighbours then sit on the clean surface."""
    layout = NetLayout((8, 8), (3, 3))
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-6)
    clean, junk = wave_grid(), wave_grid()
    centre = 210  # an inner grid point
    junk[centre, 2] += 0.012
    rows = layout.rows(junk[:, :2].copy(), np.ones(layout.n_free))
    w = classical_weights(layout, solver, junk, junk[:, :2].copy())
    assert w[centre] == 0.0 and w[np.arange(400) != centre].min() > 0.3
    pulled = rows @ solver.solve(rows, junk) - rows @ solver.solve(rows, clean)
    robust = rows @ solver.solve(rows, junk, w) - rows @ solver.solve(rows, clean)
    # measured: plain least squares moves the surface there by 7.5e-4 (0.75 sigma); the
    # weighted one differs from the clean fit by 9.3e-5 at most (the soft weights of the others)
    assert np.abs(pulled[centre, 2]) > 5e-4 and np.abs(robust).max() < 1.5e-4


def test_kept_sample_indexes_the_kept_points():
    keep = np.array([True, False, True, True, False, True])
    np.testing.assert_array_equal(kept_sample(np.array([0, 1, 3, 4, 5]), keep), [0, 2, 3])


def test_three_percent_junk_is_left_out_and_the_fit_is_the_clean_one():
    pts = franke(n=1500, seed=8, noise=0.002)
    rng = np.random.default_rng(9)
    junk = rng.uniform(pts.min(0), pts.max(0), (45, 3))
    order = rng.permutation(1545)
    cloud = np.vstack([pts, junk])[order]

    def deviation(result) -> float:
        grid = result.surface.evaluate_grid(*result.surface.parameter_grid(60, 60)).reshape(-1, 3)
        inside = np.all((grid[:, :2] > 0.05) & (grid[:, :2] < 0.95), axis=1)
        return float(np.sqrt(np.mean((grid[inside, 2] - franke_z(grid[inside, 0], grid[inside, 1])) ** 2)))

    cfg = config(net_size=[8, 8], orders=[4, 4])
    robust = fit_points(cloud, cfg)
    clean = fit_points(pts, cfg)
    plain = fit_points(cloud, dataclasses.replace(cfg, robust=False))
    # 43 junk points lie over 0.045 above or below the surface (over 12 sigma along its
    # normal): they must go. Two lie 0.028 and 0.017 above it and may go either way; no
    # real point may go
    assert 43 <= robust.metrics["outliers"] <= 45 and clean.metrics["outliers"] == 0
    assert f"{robust.metrics['outliers']} gross outliers" in " ".join(robust.notes)
    assert deviation(robust) < 1.2 * deviation(clean) < 0.01 * deviation(plain)
    # the metrics still count every point
    assert robust.metrics["points"] == 1545 and robust.metrics["rmse"] > 0.05

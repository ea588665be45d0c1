"""The robust loss (psonurbs.fitting.prepare.robust_weights): the biweight and its scale, the reweighted
classical fit, and whole fits with junk: what is left out, what the surface does."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import franke, franke_z
from scipy.spatial import cKDTree
from test_fit import config

from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.pipeline import fit_points
from psonurbs.fitting.prepare.outliers import Neighbourhoods, local_outliers
from psonurbs.fitting.prepare.robust_weights import (
    CUTOFF_SIGMAS,
    UNCONFIRMED_LEVERAGE,
    VOUCHED_FLOOR,
    biweights,
    classical_weights,
    doubted_points,
    kept_sample,
)
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


def test_a_neighbourhood_the_fit_misses_keeps_its_weight_and_lone_junk_loses_it():
    rng = np.random.default_rng(1)
    n = 400
    d = np.abs(rng.normal(0.0, 1e-3, n))
    index = np.stack([(np.arange(n) + s) % n for s in range(1, 9)], axis=1)  # 8 neighbours along a ring
    main, vouched = np.ones(n, bool), np.zeros(n, bool)
    d[100:140] = 0.02 + 0.002 * rng.random(40)  # a stretch the fit misses by 20 sigmas
    d[300] = 0.02  # junk among points on the fit
    main[200:210] = False  # a separate piece, as far off
    d[200:210] = 0.02
    index[200:210] = -1
    w = biweights(d, Neighbourhoods(index, main, vouched))
    assert w[108:132].min() > 0.95  # inside the stretch: its neighbours are as far off
    assert w[300] == 0.0 and np.all(w[200:210] == 0.0)
    assert np.all(biweights(d)[100:140] == 0.0)  # without neighbours, the stretch would go
    vouched[300] = True  # its neighbours vouch for it (the fit folds there): a little weight,
    cutoff = CUTOFF_SIGMAS * 1.4826 * np.median(d)  # and no more pull w d than the floor's at the cut-off
    for far in (0.02, 2.0):
        d[300] = far
        w = biweights(d, Neighbourhoods(index, main, vouched))[300]
        assert w > 0.0 and np.isclose(w * far, VOUCHED_FLOOR * cutoff, rtol=1e-9)
    d[300] = 0.5 * cutoff  # within the cut-off, the biweight's own (above the floor)
    assert np.isclose(biweights(d, Neighbourhoods(index, main, vouched))[300], 0.5625)


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


def test_own_leverage_is_the_share_a_point_decides_at_full_weight():
    """``q / (1 + (1 - w) q)``, q = r^T M^-1 r, is r^T (M + (1 - w) r r^T)^-1 r: the point's
    leverage with its own weight raised to 1, the others' and the regulariser as they are."""
    rng = np.random.default_rng(3)
    layout = NetLayout((6, 6), (3, 3))
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-4)
    uv = rng.random((300, 2))
    w = rng.choice([0.0, 0.3, 1.0], 300)
    rows = layout.rows(uv, np.ones(layout.n_free))
    dense = rows.toarray()
    normal = solver.normal_matrix(dense.T @ (w[:, None] * dense))
    got = solver.own_leverage(rows, w)
    for i in (0, 1, 2, 150, 299):
        r = dense[i]
        assert got[i] == pytest.approx(r @ np.linalg.solve(normal + (1 - w[i]) * np.outer(r, r), r), rel=1e-9)
    assert np.all((got > 0) & (got < 1))


def disc_wave(stray_uv):
    """A noisy wave (sigma 1e-3) sampled over the disc inscribed in the unit square, its own
    parameters, and a point at ``stray_uv`` 4 sigmas off the plain fit's surface there; the
    local test vouches for every point but that one."""
    rng = np.random.default_rng(4)
    uv = rng.random((3000, 2))
    uv = uv[np.linalg.norm(uv - 0.5, axis=1) < 0.5][:1500]
    pts = np.column_stack([uv, 0.1 * np.sin(3 * uv[:, 0] + 2 * uv[:, 1]) + rng.normal(0, 1e-3, len(uv))])
    layout = NetLayout((8, 8), (3, 3))
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-6)
    at = np.asarray([stray_uv], float)
    clean = layout.rows(at, np.ones(layout.n_free)) @ solver.solve(layout.rows(uv, np.ones(layout.n_free)), pts)
    pts, uv = np.vstack([pts, clean + [0, 0, 4e-3]]), np.vstack([uv, at])
    n = len(pts)
    index = cKDTree(pts).query(pts, 9)[1][:, 1:]
    vouched = np.ones(n, bool)
    vouched[-1] = False
    return layout, solver, pts, uv, Neighbourhoods(index, np.ones(n, bool), vouched)


def test_a_doubted_point_alone_over_an_empty_corner_is_left_out_and_one_among_data_is_not():
    """A point the local test doubts, 4 sigmas off the fit that did not see it: over the
    square's empty corner nothing else holds the net there (own leverage near 1), and at
    any weight it would pin the corner, so it is left out; among the data (leverage a few
    hundredths) it keeps its biweight, as it does over the corner without the leverage rule
    (measured: leverage 0.99998 over the corner, 0.015 among the data)."""
    layout, solver, pts, uv, neighbourhoods = disc_wave((0.96, 0.04))
    rows = layout.rows(uv, np.ones(layout.n_free))
    w = classical_weights(layout, solver, pts, uv, neighbourhoods)
    assert solver.own_leverage(rows, w)[-1] > UNCONFIRMED_LEVERAGE
    assert w[-1] == 0.0 and np.median(w[:-1]) > 0.95
    residual = np.linalg.norm(solver.leave_one_out(rows, pts, w)[1], axis=1)
    assert 0.5 < biweights(residual, neighbourhoods)[-1] < 1.0  # the distance alone would keep it
    layout, solver, pts, uv, neighbourhoods = disc_wave((0.5, 0.6))
    w = classical_weights(layout, solver, pts, uv, neighbourhoods)
    assert solver.own_leverage(layout.rows(uv, np.ones(layout.n_free)), w)[-1] < 0.1
    assert 0.5 < w[-1] < 1.0


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


def tilted_saddle(u, v):
    """A saddle over [-1, 1]^2, tilted 40 degrees about (1, 1, 0): the projection plane matters."""
    x, y = 2 * u - 1, 2 * v - 1
    p = np.stack([x, y, 0.4 * (x * x - y * y)], -1)
    k = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = np.radians(40.0)
    return p @ (np.eye(3) + np.sin(t) * kx + (1 - np.cos(t)) * kx @ kx).T


def test_junk_steers_neither_the_projection_plane_nor_the_fit():
    """5% junk in the bounding box of a tilted saddle: the local test takes it out before
    the cloud is parametrised, and the fit is as near the truth as the clean cloud's."""
    rng = np.random.default_rng(5)
    u, v = rng.random((2, 1500))
    diag = np.linalg.norm(np.ptp(tilted_saddle(u, v), axis=0))
    pts = tilted_saddle(u, v) + rng.normal(0, 0.002 * diag, (1500, 3))
    cloud = np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (75, 3))])
    g = np.linspace(0, 1, 300)
    truth = cKDTree(tilted_saddle(*(a.ravel() for a in np.meshgrid(g, g, indexing="ij"))))
    cfg = config(orders=[4, 4], net_size=[6, 6], swarm={"particles": 1, "iterations": 1})
    fits = {name: fit_points(c, cfg) for name, c in (("clean", pts), ("junk", cloud))}
    normals = {name: np.asarray(f.info["parametrisation"]["normal"]) for name, f in fits.items()}
    deviation = {name: truth.query(f.surface.evaluate_grid(*f.surface.parameter_grid(60, 60)).reshape(-1, 3))[0]
                 / (0.002 * diag) for name, f in fits.items()}
    # the planes come out 5.7 degrees apart, truth rms 0.52 sigma (clean 0.48), max 2.4 (clean 2.2);
    # junk judged against a global fit only would tilt the plane 16 degrees, truth rms 0.64, max 6.8
    assert abs(normals["clean"] @ normals["junk"]) > np.cos(np.radians(8.0))
    assert np.sqrt(np.mean(deviation["junk"] ** 2)) < 1.2 * np.sqrt(np.mean(deviation["clean"] ** 2))
    assert deviation["junk"].max() < 4.0
    assert fits["clean"].metrics["outliers"] == 0 and 60 <= fits["junk"].metrics["outliers"] <= 75


def test_the_weighted_paired_test_reduces_to_the_plain_one():
    """Unit weights give the plain paired test; weight 0 on a point is the test without it;
    the weighted mean and spread of d follow sum w d / sum w with n_eff = (sum w)^2 / sum w^2."""
    from psonurbs.fitting.search.validation import paired_test
    rng = np.random.default_rng(5)
    classical, swarm = np.abs(rng.normal(1.0, 0.3, 200)), np.abs(rng.normal(0.95, 0.3, 200))
    plain = paired_test(classical, swarm)
    unit = paired_test(classical, swarm, np.ones(200))
    assert unit.z == pytest.approx(plain.z, rel=1e-12) and unit.swarm_error == pytest.approx(plain.swarm_error)
    w = np.ones(200)
    w[:20] = 0.0
    assert paired_test(classical, swarm, w).z == pytest.approx(paired_test(classical[20:], swarm[20:]).z, rel=1e-12)
    w = rng.uniform(0.2, 1.0, 200)
    d = swarm ** 2 - classical ** 2
    mean = np.sum(w * d) / np.sum(w)
    n_eff = np.sum(w) ** 2 / np.sum(w ** 2)
    sd = np.sqrt(np.sum(w * (d - mean) ** 2) / np.sum(w) * n_eff / (n_eff - 1))
    assert paired_test(classical, swarm, w).z == pytest.approx(mean * np.sqrt(n_eff) / sd, rel=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_junk_joining_the_surface_from_afar_is_doubted_and_a_piece_apart_is_not(seed):
    """Franke's surface on x < 0.7, a piece of it apart on x > 0.85, y > 0.5 (a gap of
    about twelve spacings), 5% junk in the box. Junk the local test keeps and that joins
    the main piece from more than 5 spacings off the data (beyond every neighbour's reach)
    is doubted; no point of the data is, the piece apart included (a part of the scan apart
    from the rest marks data: a doubted piece would be left off the trimmed face)."""
    rng = np.random.default_rng(seed)
    n, far, spacing = 4500, 600, np.sqrt(0.7 / 4500)
    x = np.r_[0.7 * rng.random(n), 0.85 + 0.15 * rng.random(far)]
    y = np.r_[rng.random(n), 0.5 + 0.5 * rng.random(far)]
    data = np.column_stack([x, y, franke_z(x, y)])
    data += rng.normal(0, 1.5e-3, data.shape)
    pts = np.vstack([data, rng.uniform(data.min(axis=0), data.max(axis=0), (250, 3))])
    scale = np.linalg.norm(np.ptp(pts, axis=0))
    pts = (pts - pts.mean(axis=0)) / scale
    verdict = local_outliers(pts)
    pieces = verdict.neighbourhoods()
    kept = verdict.inliers
    source = np.where(kept, np.cumsum(kept) - 1, -1)
    doubted = doubted_points(pieces, source)
    gap = cKDTree(pts[:n + far]).query(pts[n + far:])[0] * scale / spacing
    on_main = np.zeros(len(pts), bool)
    on_main[kept] = pieces.on_main_piece
    joined_from_afar = kept[n + far:] & on_main[n + far:] & (gap > 5.0)
    assert kept[:n + far].all() and on_main[:n].all() and not on_main[n:n + far].any()
    assert not doubted[:n + far].any()
    assert joined_from_afar.sum() >= 5 and doubted[n + far:][joined_from_afar].all()

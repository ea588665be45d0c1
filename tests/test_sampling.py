"""Big clouds (psonurbs.fitting.prepare.big_clouds): fitted on a subsample holding the swarm's
points, finished on every point. The subsample size is made small here so that a
cloud of a few thousand points is a big one."""
from __future__ import annotations

import numpy as np
import pytest

from psonurbs.config import config_from_dict
from psonurbs.fitting.pipeline import fit_points
from psonurbs.fitting.prepare import big_clouds
from psonurbs.fitting.prepare.organise import organise
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.trim import distances_to_face


def config(**kw):
    return config_from_dict({"orders": [4, 4], "net_size": [6, 6], "swarm": {"particles": 4, "iterations": 4},
                             "swarm_points": 300, **kw})


def test_the_subsample_holds_the_swarm_points_and_is_fixed(monkeypatch):
    monkeypatch.setattr(big_clouds, "SUBSAMPLE_POINTS", 500)
    swarm = np.sort(np.random.default_rng(0).choice(3000, 300, replace=False))
    assert big_clouds.big_cloud_sample(500, swarm[:100]) is None
    big = big_clouds.big_cloud_sample(3000, swarm)
    assert len(big) == 500 and np.all(np.diff(big) > 0) and np.isin(swarm, big).all()
    np.testing.assert_array_equal(big, big_clouds.big_cloud_sample(3000, swarm))
    # swarm_points above the subsample's size: the swarm's sample is the subsample
    many = np.random.default_rng(1).permutation(3000)[:800]
    np.testing.assert_array_equal(big_clouds.big_cloud_sample(3000, many), np.sort(many))
    assert big_clouds.big_cloud_sample(800, np.arange(800)) is None


@pytest.mark.parametrize("layout", [NetLayout((5, 4), (3, 2)), NetLayout((5, 4), (2, 2), (True, False)),
                                    NetLayout((5, 5), (2, 2), (True, False), poles=True),
                                    NetLayout((5, 4), (2, 2), (True, True))])
def test_free_state_gives_back_the_weights_and_knots_of_a_surface(layout):
    rng = np.random.default_rng(1)
    weights = rng.uniform(0.5, 2.0, layout.n_free)
    inner = [np.sort(rng.uniform(0.1, 0.9, c)) for c in layout.inner_counts]
    surface = layout.surface(rng.normal(size=(layout.n_free, 3)), weights, *inner)
    got = big_clouds.free_state(layout, surface)
    np.testing.assert_array_equal(got.weights, weights)
    np.testing.assert_array_equal(got.inner_u, inner[0])
    np.testing.assert_array_equal(got.inner_v, inner[1])


def test_a_big_cloud_is_fitted_as_well_as_every_point_and_its_junk_counted(monkeypatch):
    """2500 points of a smooth sheet with noise (sigma 0.01) and 25 junk points: fitted
    on 800 of them and finished, the fit is as near every clean point as the fit of all
    of them (within 0.5%), and the outliers are those of all 2500 points (the junk,
    found on the finished surface)."""
    rng = np.random.default_rng(2)
    x, y = rng.random((2, 2500))
    points = np.c_[x, y, 0.3 * np.sin(2 * x) * np.cos(1.5 * y) + 0.01 * rng.normal(size=2500)]
    points[:25] = rng.uniform(points.min(0), points.max(0), (25, 3)) + [0, 0, 1.0]
    cfg = config()
    whole = fit_points(points, cfg)
    monkeypatch.setattr(big_clouds, "SUBSAMPLE_POINTS", 800)
    big = fit_points(points, cfg)
    assert big.info["subsample"]["points"] == 800 and "subsample" not in whole.info
    assert any("fitted on 800 of the 2500 points" in note for note in big.notes)
    clean = np.arange(25, 2500)
    d_whole = closest_parameters(whole.surface, points[clean])[1]
    d_big = closest_parameters(big.surface, points[clean])[1]
    assert np.sqrt(np.mean(d_big ** 2)) <= 1.005 * np.sqrt(np.mean(d_whole ** 2))
    assert big.metrics["outliers"] == whole.metrics["outliers"] == 25


def test_an_exact_surface_is_finished_unchanged(monkeypatch):
    """Noise-free points of a cubic patch the net represents: the subsample's fit is
    exact on every point, and the finishing keeps it as it is (no round)."""
    layout = NetLayout((4, 4), (3, 3))
    i, j = np.meshgrid(np.linspace(0, 1, 4), np.linspace(0, 1, 4), indexing="ij")
    truth = layout.surface(np.stack([i, j, 0.2 * i * j * (1 - i)], -1).reshape(-1, 3), np.ones(16))
    uv = np.random.default_rng(4).random((3000, 2))
    points = truth.evaluate(uv[:, 0], uv[:, 1])
    done = big_clouds.finished(layout, truth, points, 1e-6, True, False)
    assert done.surface is truth and done.rounds == 0 and (done.point_weights > 0).all()


def test_a_big_closed_cloud_is_fitted_the_same_twice_near_its_noise(monkeypatch):
    """3000 noisy points (sigma 0.005) of a cylinder of radius 1, fitted on 800 with
    topology cylinder: the same fit twice (the subsample is fixed), the finishing ran
    (a noisy cloud is not exact), the seam stays closed, and every point is within the
    noise of the fit (rms distance 1.01 sigma) and the fit within 0.2 sigma of the true
    cylinder (the fit of all 3000 points: 0.999 and 0.157 sigma)."""
    rng = np.random.default_rng(5)
    angle, height = rng.uniform(0, 2 * np.pi, 3000), rng.uniform(0, 2, 3000)
    radius = 1 + 0.005 * rng.normal(size=3000)
    points = np.c_[radius * np.cos(angle), radius * np.sin(angle), height]
    monkeypatch.setattr(big_clouds, "SUBSAMPLE_POINTS", 800)
    cfg = config(topology="cylinder", net_size=[8, 5])
    first, second = fit_points(points, cfg), fit_points(points, cfg)
    np.testing.assert_array_equal(first.surface.control_points, second.surface.control_points)
    assert first.info["subsample"]["points"] == 800 and first.info["subsample"]["final_rounds"] >= 1
    assert first.surface.closed_u or first.surface.closed_v
    uv, dist = closest_parameters(first.surface, points)
    assert np.sqrt(np.mean(dist ** 2)) < 1.01 * 0.005
    on = first.surface.evaluate(uv[:, 0], uv[:, 1])
    assert np.sqrt(np.mean((np.hypot(on[:, 0], on[:, 1]) - 1) ** 2)) < 0.2 * 0.005


def test_a_big_cloud_s_metrics_are_every_input_point_s_distance(monkeypatch):
    """The finished fit's rmse and max_error take every input point, duplicates and the
    junk left out before the fit included, from the parameters the finishing left them
    at: the same as a global foot-point search of every point on the fitted surface,
    measured to the face where a point's foot lies off it (the surface runs past the
    data's straight edges here, and is cut there)."""
    rng = np.random.default_rng(6)
    x, y = rng.random((2, 2500))
    points = np.c_[x, y, 0.3 * np.sin(2 * x) * np.cos(1.5 * y) + 0.01 * rng.normal(size=2500)]
    points[:25] = rng.uniform(points.min(0), points.max(0), (25, 3)) + [0, 0, 1.0]
    points = np.concatenate([points, points[rng.choice(2500, 200)]])  # 200 duplicates
    monkeypatch.setattr(big_clouds, "SUBSAMPLE_POINTS", 800)
    big = fit_points(points, config())
    uv, dist = closest_parameters(big.surface, points)
    if big.trim is not None:
        dist = distances_to_face(big.surface, big.trim, points, uv, dist)
    assert big.metrics["points"] == 2700 and big.metrics["outliers"] == 25
    assert big.metrics["rmse"] == pytest.approx(np.sqrt(np.mean(dist ** 2)), rel=1e-9)
    assert big.metrics["max_error"] == pytest.approx(dist.max(), rel=1e-9)


def test_every_input_point_knows_its_distinct_point():
    rng = np.random.default_rng(7)
    points = rng.random((500, 3))
    points = points[rng.choice(500, 800)]  # every point several times, in no order
    cloud = organise(points, (4, 4))
    assert len(cloud) == len(np.unique(points, axis=0)) and cloud.duplicates == 800 - len(cloud)
    np.testing.assert_array_equal(cloud.points[cloud.source], cloud.frame.to_local(points))

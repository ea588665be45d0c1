"""The fairness term where the data leave the net free
(:meth:`psonurbs.fitting.leastsq.regularised.RegularisedLeastSquares.supported_by`): which
control points it holds, its twins' agreement with the solver, and a noisy cap over a disc
whose empty corners no longer flap."""
from __future__ import annotations

import numpy as np
import pytest

from psonurbs.config import config_from_dict
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.leastsq.stacked import StackedLeastSquares
from psonurbs.fitting.pipeline import fit_points
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.stacked_rows import CellLayout

LAYOUT = NetLayout((10, 8), (3, 3))


def footprint(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 2) parameters: the whole square, a disc touching its sides, or the square with
    its density falling 20-fold towards u = 0 (a sparse but real edge)."""
    if kind == "square":
        return rng.random((n, 2))
    if kind == "disc":
        r, t = 0.5 * np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
        return 0.5 + np.column_stack([r * np.cos(t), r * np.sin(t)])
    x = rng.random(40 * n)
    x = x[rng.random(len(x)) < 0.05 + 0.95 * x][:n]
    return np.column_stack([x, rng.random(len(x))])


def height(uv: np.ndarray, plane: bool = False) -> np.ndarray:
    """A wave over the square, or a plane (which the net's thin-plate energy continues exactly)."""
    return 0.3 * uv[:, 0] + 0.2 * uv[:, 1] if plane else np.sin(3 * uv[:, 0]) * np.cos(2 * uv[:, 1])


def problem(kind: str, seed: int, smoothing: float = 1e-6, n: int = 3000, plane: bool = False):
    rng = np.random.default_rng(seed)
    uv = footprint(kind, n, rng)
    data = np.column_stack([uv, height(uv, plane)]) + 0.01 * rng.normal(size=(len(uv), 3))
    solver = RegularisedLeastSquares(LAYOUT.smoothness_operator(), smoothing)
    return uv, data, solver.supported_by(LAYOUT.rows(uv, np.ones(LAYOUT.n_free)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_data_leave_a_discs_corners_free_and_pin_the_rest(seed):
    _, _, disc = problem("disc", seed)
    held = np.diag(disc.fairness).reshape(LAYOUT.size)
    corners = held[[0, 0, -1, -1], [0, -1, 0, -1]]
    assert np.all(corners > 0.5)  # each corner's whole stencil is free
    assert np.all(held[3:7, 2:6] == 0)  # the middle of the net is the data's
    for kind in ("square", "graded"):  # every point pinned: no term at all
        assert problem(kind, seed)[2].fairness is None
    assert problem("disc", seed, n=LAYOUT.n_free)[2].fairness is None  # no more points than unknowns: the smoothing's


def test_the_term_holds_only_where_the_data_leave_the_net_free():
    """With the term the fit over the data stays put, while the surface at the square's
    empty corners comes nearer the data's plane (continued from the rim's last control
    points, which the data pin only loosely) instead of a flap of the rim's noise
    amplified 180-fold (noise 0.01)."""
    uv, data, fair = problem("disc", 0, smoothing=1e-8, plane=True)
    plain = RegularisedLeastSquares(LAYOUT.smoothness_operator(), 1e-8)
    rows = LAYOUT.rows(uv, np.ones(LAYOUT.n_free))
    surfaces = [LAYOUT.surface(solver.solve(rows, data), np.ones(LAYOUT.n_free)) for solver in (fair, plain)]
    on_data = [np.sqrt(np.mean(np.sum((s.evaluate(uv[:, 0], uv[:, 1]) - data) ** 2, axis=1))) for s in surfaces]
    assert on_data[0] == pytest.approx(on_data[1], rel=0.01)
    corners = np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]])
    off = [np.abs(s.evaluate(corners[:, 0], corners[:, 1])[:, 2] - height(corners, True)).max() / 0.01
           for s in surfaces]
    assert off[1] > 100 and off[0] < 0.2 * off[1]  # in noise sigmas

@pytest.mark.parametrize("weighted", [False, True])
def test_the_twins_take_the_term_as_the_solver_does(weighted):
    uv, data, fair = problem("disc", 3)
    assert fair.fairness is not None
    w = np.random.default_rng(4).uniform(0.2, 1.0, len(uv)) if weighted else None
    shape = NetShape(np.ones(LAYOUT.n_free))
    expected = fair.solve(LAYOUT.rows(uv, *shape), data, w)
    stacked = StackedLeastSquares(fair, CellLayout(LAYOUT))
    got = stacked.compiled_control(uv, shape, data, w)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10 * np.abs(expected).max())
    plain = StackedLeastSquares(RegularisedLeastSquares(LAYOUT.smoothness_operator(), 1e-6), CellLayout(LAYOUT))
    assert np.abs(plain.compiled_control(uv, shape, data, w) - got).max() > 1e-3  # the term is taken


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_noisy_cap_over_a_disc_keeps_its_net_near_the_cloud(seed):
    """A 60-degree cap of a sphere, noise 1.5% of its radius: seen from its axis its
    footprint is a disc, the square's corners empty. Without the term the noise at the disc's rim was flung into the corners (the
    net 2.1-5 times the cloud's size on these draws, 6.5 on 10,000 points) and the
    surface over the data a quarter of the noise off the sphere; now the net stays
    within twice the cloud's size and the surface within a fifth of the noise."""
    rng = np.random.default_rng(seed)
    n, radius = 4000, 1.0
    polar = np.arccos(rng.uniform(np.cos(np.radians(60)), 1.0, n))
    azimuth = rng.uniform(0, 2 * np.pi, n)
    r = radius + 0.015 * rng.normal(size=n)
    points = np.column_stack([r * np.sin(polar) * np.cos(azimuth), r * np.cos(polar), r * np.sin(polar) * np.sin(azimuth)])
    config = config_from_dict({"net_size": [10, 8], "orders": [4, 4], "parametrisation": "plane",
                               "swarm": {"particles": 8, "iterations": 10, "seed": 1}})
    result = fit_points(points, config)
    assert result.metrics["net_extent_ratio"] < 2.0 and result.metrics["extent_ratio"] < 1.2
    assert not result.warnings
    on_data = result.surface.evaluate(*closest_parameters(result.surface, points)[0].T)
    off_sphere = np.abs(np.linalg.norm(on_data, axis=1) - radius)
    assert np.sqrt(np.mean(off_sphere ** 2)) < 0.2 * 0.015  # over the data: near the sphere, not its noise

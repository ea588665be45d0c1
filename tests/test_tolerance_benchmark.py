"""benchmarks/tolerance.py: FITPACK's count at a tolerance, on clouds small enough to fit in
a blink, against answers known exactly; the config it fits with and the checks it prints."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tolerance():
    sys.path.insert(0, str(REPO / "benchmarks"))  # it imports cases.py and score.py beside it
    try:
        spec = importlib.util.spec_from_file_location("bench_tolerance", REPO / "benchmarks" / "tolerance.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules["bench_tolerance"] = module  # its dataclasses resolve their annotations there
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(REPO / "benchmarks"))


def grid_triangles(n: int) -> np.ndarray:
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    corner = (i * n + j).ravel()
    return np.concatenate([np.stack([corner, corner + n, corner + 1], 1),
                           np.stack([corner + 1, corner + n, corner + n + 1], 1)])


def test_height_axis_is_the_one_every_triangle_faces_along(tolerance):
    """A graph x = f(y, z) is a height field along x; a sheet that folds back over itself
    (a half cylinder, 200 degrees of it) along no axis."""
    n = 21
    s, t = (a.ravel() for a in np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij"))
    graph = np.column_stack([0.3 * np.sin(3 * s) * t, s, t])
    assert tolerance.height_axis(graph, grid_triangles(n)) == 0
    angle = np.radians(200.0) * s
    curled = np.column_stack([np.cos(angle), np.sin(angle), t])
    assert tolerance.height_axis(curled, grid_triangles(n)) is None


def test_the_distance_is_measured_along_the_normal(tolerance):
    """Each point of a tilted plane z = 0.5 x - 0.25 y twice, d above and d below: the fit is
    the plane, every vertical residual d, every normal one d / sqrt(1 + 0.5^2 + 0.25^2)."""
    rng = np.random.default_rng(1)
    xy = rng.random((200, 2))
    z = 0.5 * xy[:, 0] - 0.25 * xy[:, 1]
    d = 1e-3
    points = np.vstack([np.column_stack([xy, z + d]), np.column_stack([xy, z - d])])
    diagonal = np.linalg.norm(points.max(0) - points.min(0))
    fit = tolerance.surfit(points, 2, 1e-1)
    assert fit.warned == "" and fit.coefficients == 16
    assert fit.achieved == pytest.approx(d / np.sqrt(1 + 0.5 ** 2 + 0.25 ** 2) / diagonal, rel=1e-6)


def test_a_bicubic_height_field_needs_sixteen_coefficients(tolerance):
    rng = np.random.default_rng(2)
    x, y = rng.random((2, 300))
    points = np.column_stack([x, y, x ** 3 - 2 * x * y ** 2 + 0.5 * y ** 3])
    count = tolerance.fitpack_count(points, 2, 1e-6)
    assert count.best.coefficients == 16 and count.best.knots == (4, 4)
    assert count.best.achieved < 1e-9


def test_the_search_walks_to_the_plateau_of_fewest_coefficients_that_meets(tolerance):
    """A made-up FITPACK: three plateaus of the count per decade of s, plateau k (log10 s in
    (-(k+1)/3, -k/3]) with 16 + 10 k coefficients and an error from 0.1 * 0.8^k at its
    smallest s to twice that at its largest. At 1.5 * 0.1 * 0.8^10 plateau 9 is the first
    whose smallest s meets (0.8^9 < 1.5 * 0.8^10 < 0.8^8); bisection on the error alone
    ends in plateau 10, where the error crosses the tolerance inside the plateau."""
    def fit(s_rel):
        plateau = int(np.floor(-3.0 * np.log10(s_rel)))
        inside = 3.0 * np.log10(s_rel) + plateau + 1.0  # 0 at the plateau's smallest s, 1 at its largest
        return tolerance.SplineTry(s_rel, 16 + 10 * plateau, None, 0.1 * 0.8 ** plateau * (1.0 + inside), "")
    best, _ = tolerance.fewest_coefficients(fit, 1.5 * 0.1 * 0.8 ** 10)
    assert best.coefficients == 16 + 10 * 9
    assert np.log10(best.s_rel) == pytest.approx(-10.0 / 3.0, abs=1e-3)


def test_no_smoother_fit_with_fewer_coefficients_meets_the_tolerance(tolerance):
    """A bump on 800 points: the count found meets the tolerance, and on a fine log grid of
    s above the one it chose every clean fit with fewer coefficients misses it."""
    rng = np.random.default_rng(3)
    x, y = rng.random((2, 800))
    points = np.column_stack([x, y, 0.4 * np.exp(-((x - 0.4) ** 2 + (y - 0.6) ** 2) / 0.02)])
    count = tolerance.fitpack_count(points, 2, 2e-3)
    best = count.best
    assert best.achieved <= 2e-3 and best.coefficients > 16
    for s_rel in np.geomspace(best.s_rel, 1e-1, 25)[1:]:
        fit = tolerance.surfit(points, 2, s_rel)
        if not fit.warned and fit.coefficients < best.coefficients:
            assert fit.achieved > 2e-3


def test_the_config_drops_net_size_and_asks_for_the_tolerance(tolerance):
    case = "# a note\norders: [4, 4]\nnet_size: [10, 10]\ntopology: torus\nswarm:\n  particles: 40\n"
    config = yaml.safe_load(tolerance.tolerance_config(case, 3e-4))
    assert config == {"orders": [4, 4], "topology": "torus", "swarm": {"particles": 40},
                      "tolerance_rel": 3e-4, "tolerance_measure": "p99"}


def test_the_checks_hold_the_rows_to_the_issue(tolerance):
    Row = tolerance.Row
    rows = [Row("step_bump", "swarm", 3e-4, 30.0, 100, (10, 10), 2.9e-4, True, 3.1e-4, 1e-3),
            Row("step_bump", "classical", 3e-4, 12.0, 144, (12, 12), 2.5e-4, True, 2.6e-4, 1e-3),
            Row("torus", "swarm", 2e-4, 20.0, 112, (14, 8), 1.9e-4, True, 2.2e-4, 5e-3),
            Row("torus", "classical", 2e-4, 10.0, 112, (14, 8), 1.9e-4, True, 1.9e-4, 1e-3)]
    verdicts = {check.text: check.passed for check in tolerance.checks(rows, {"step_bump": 256})}
    assert verdicts["step_bump swarm: met claimed and by the scorer (p99 <= 1.05 x tol)"] is True  # 3.1 <= 3.15
    assert verdicts["torus swarm: met claimed and by the scorer (p99 <= 1.05 x tol)"] is False  # 2.2 > 2.1
    assert verdicts["torus swarm: truth_max <= 20 x tol"] is False  # 5e-3 > 4e-3
    assert verdicts["step_bump: swarm 100 <= 0.7 x classical 144 control points"] is True  # 100 <= 100.8
    assert verdicts["torus: swarm 112 <= 1 x classical 112 control points"] is True
    assert verdicts["step_bump: swarm 100 <= 0.8 x FITPACK 256"] is True
    assert verdicts["seconds summed: swarm 50.0 <= 3 x classical 22.0"] is True

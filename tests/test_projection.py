"""Foot points (psonurbs.geometry.projection): the Newton search on edges, poles and seams,
run by the numpy reference and by its compiled twin (psonurbs.geometry.foot_kernel),
which must find the same foot points."""
from __future__ import annotations

import numpy as np
import pytest

from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.geometry import compiled, projection
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.projection import GridStart, closest_parameters

needs_numba = pytest.mark.skipif(not compiled.ENABLED, reason="numba missing or PSONURBS_NO_JIT set")


@pytest.fixture(params=[False, pytest.param(True, marks=needs_numba)], ids=["numpy", "compiled"])
def search(request, monkeypatch):
    """Runs a test with the numpy search and again with the compiled one."""
    monkeypatch.setattr(projection, "COMPILED", request.param)
    return request.param


def both_searches(monkeypatch, surface, points, uv=None, **options):
    """(numpy, compiled) results of closest_parameters on the same input."""
    out = []
    for flag in (False, True):
        monkeypatch.setattr(projection, "COMPILED", flag)
        out.append(closest_parameters(surface, points, None if uv is None else uv.copy(), **options))
    return out


def seam_difference(a: np.ndarray, b: np.ndarray, closed: tuple[bool, bool]) -> np.ndarray:
    """|a - b| per parameter, measured round a closed direction's seam."""
    d = np.abs(a - b)
    for k in (0, 1):
        if closed[k]:
            d[:, k] = np.minimum(d[:, k], 1.0 - d[:, k])
    return d


def sheared_plane():
    """S(u, v) = (u + 0.8 v, v, 0): a cubic net with linear precision, S_u . S_v != 0."""
    layout = NetLayout((4, 4), (3, 3))
    i, j = np.meshgrid(np.linspace(0, 1, 4), np.linspace(0, 1, 4), indexing="ij")
    net = np.stack([i + 0.8 * j, j, np.zeros_like(i)], -1).reshape(-1, 3)
    return layout.surface(net, np.ones(16))


def shape_points(kind: str, uv: np.ndarray) -> np.ndarray:
    """Points of a wavy sheet, a cylinder, a sphere (u around, v pole to pole) or a torus."""
    around, other = 2 * np.pi * uv[:, 0], uv[:, 1]
    if kind == "open":
        return np.c_[uv, 0.2 * np.sin(3 * uv[:, 0]) * np.cos(2 * uv[:, 1])]
    if kind == "cylinder":
        return np.c_[np.cos(around), np.sin(around), other]
    if kind == "sphere":
        return np.c_[np.cos(around) * np.sin(np.pi * other), np.sin(around) * np.sin(np.pi * other),
                     np.cos(np.pi * other)]
    tube = 2 * np.pi * other
    return np.c_[(2 + 0.5 * np.cos(tube)) * np.cos(around), (2 + 0.5 * np.cos(tube)) * np.sin(around),
                 0.5 * np.sin(tube)]


LAYOUTS = {
    "open": NetLayout((7, 6), (3, 2)),
    "open_linear": NetLayout((5, 6), (1, 4)),
    "cylinder": NetLayout((8, 5), (3, 3), (True, False)),
    "sphere": NetLayout((8, 7), (3, 3), (True, False), poles=True),
    "torus": NetLayout((8, 6), (2, 3), (True, True)),
}


def fitted_surface(name: str, rng: np.random.Generator):
    """A rational surface of the layout fitted to its shape (random weights), with the
    parameters and points it was fitted to."""
    layout = LAYOUTS[name]
    uv = rng.random((1500, 2))
    points = shape_points(name.split("_")[0], uv)
    weights = rng.uniform(0.6, 1.6, layout.n_free)
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-5, layout.constraint_operator())
    control = solver.solve(layout.rows(uv, weights), points)
    return layout.surface(control, weights), uv, points


@needs_numba
@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_compiled_search_finds_the_numpy_foot_points(name, monkeypatch):
    """Open, closed (cylinder, torus) and sphere-like (poles) rational nets of degrees 1 to 4:
    points off the surface by up to 10% of its size, started near their parameters, from
    outside the domain, on the edges and seams, at the poles, and from the global search.

    The kernel's basis (de Boor's recurrence with the knot gaps' reciprocals) rounds
    differently from scipy's, so the two searches agree to rounding where a foot point is
    determined to rounding: the distance, which is stationary there, to 1e-12, the foot
    point itself to 1e-7 of the surface's size (10^-16 of squared distance moves it
    that far along a flat minimum). A point started on an edge or at a pole (u degenerate)
    may end in another local minimum: a handful of those (5 of 1,500 on the sphere)."""
    rng = np.random.default_rng(11)
    surface, uv, points = fitted_surface(name, rng)
    closed = (surface.closed_u, surface.closed_v)
    points = points + 0.1 * rng.normal(size=points.shape)
    size = float(np.ptp(points, axis=0).max())
    start = uv + 0.05 * rng.normal(size=uv.shape)
    start[:100] = rng.choice([-0.2, 0.0, 1.0, 1.2], (100, 2))  # beyond, on the edges and seams
    start[100:200, 1] = rng.choice([0.0, 1e-9, 1.0 - 1e-9, 1.0], 100)  # at a sphere's poles
    for first in (start, None):
        (numpy_uv, numpy_dist), (fast_uv, fast_dist) = both_searches(monkeypatch, surface, points, first)
        same = np.abs(fast_dist - numpy_dist) <= 1e-12
        assert np.all(same[200:]) and np.sum(~same) <= 0.01 * len(points)  # only among the edge and pole starts
        foot_gap = np.linalg.norm(surface.evaluate(*fast_uv.T) - surface.evaluate(*numpy_uv.T), axis=1)
        assert foot_gap[same].max() <= 1e-7 * size
        assert np.all((fast_uv >= 0) & (fast_uv <= 1))
        for k in (0, 1):  # a closed direction's parameter is taken modulo 1: never 1 itself
            if closed[k]:
                assert np.all(fast_uv[:, k] < 1.0)


@needs_numba
def test_the_compiled_search_in_threads_gives_the_bytes_of_one(monkeypatch):
    """Points are split among threads (compiled.over_parts): 1, 2 and 3 threads, the same bytes."""
    import psonurbs.geometry.projection as projection

    rng = np.random.default_rng(5)
    surface, uv, points = fitted_surface("torus", rng)
    points, start = np.tile(points, (4, 1)) + 0.05 * rng.normal(size=(6000, 3)), np.tile(uv, (4, 1))
    monkeypatch.setattr(projection, "THREAD_POINTS", 1000)
    found = []
    for n in (1, 2, 3):
        monkeypatch.setenv("PSONURBS_THREADS", str(n))
        found.append([a.tobytes() for a in closest_parameters(surface, points, start)])
    assert found[0] == found[1] == found[2]


@needs_numba
def test_compiled_search_takes_the_given_iterations_and_no_more(monkeypatch):
    """With one Newton step allowed, both stop after it at the same place (part way)."""
    surface, uv, points = fitted_surface("cylinder", np.random.default_rng(2))
    points = 1.3 * points
    start = np.mod(uv + 0.1, 1.0)
    (numpy_uv, numpy_dist), (fast_uv, fast_dist) = both_searches(monkeypatch, surface, points, start, iterations=1)
    converged, _ = closest_parameters(surface, points, start)
    assert seam_difference(numpy_uv, fast_uv, (True, False)).max() <= 1e-10  # one step: no flat minimum yet
    assert seam_difference(fast_uv, converged, (True, False)).max() > 1e-4  # one step is not all the way
    # a distance is 1-Lipschitz in its foot point: the two may differ by the feet's gap, no more
    foot_gap = np.linalg.norm(surface.evaluate(*fast_uv.T) - surface.evaluate(*numpy_uv.T), axis=1)
    assert np.all(np.abs(fast_dist - numpy_dist) <= foot_gap + 1e-14)


def test_point_at_its_foot_point_is_not_moved(search):
    """Points started at their foot points (inside, on an edge, at a corner) keep their
    parameters bit for bit: no step can bring them closer."""
    s = sheared_plane()
    foot = np.array([[0.3, 0.4], [0.0, 0.7], [1.0, 1.0]])
    points = np.c_[foot[:, 0] + 0.8 * foot[:, 1], foot[:, 1], [0.1, -0.2, 0.0]]
    uv, dist = closest_parameters(s, points, foot)
    np.testing.assert_array_equal(uv, foot)
    np.testing.assert_allclose(dist, [0.1, 0.2, 0.0], atol=1e-15)


def test_repeated_searches_give_the_same_bytes(search):
    surface, uv, points = fitted_surface("torus", np.random.default_rng(4))
    points = points + 0.05 * np.random.default_rng(5).normal(size=points.shape)
    first = closest_parameters(surface, points, uv)
    again = closest_parameters(surface, points, uv)
    for a, b in zip(first, again):
        assert a.tobytes() == b.tobytes()


def test_point_beyond_an_edge_slides_along_it_to_its_foot(search):
    # beyond the edge u = 1 the foot is the nearest point of the edge line (1 + 0.8 v, v):
    # v = (y + 0.8 (x - 1)) / 1.64. Clipping the free Newton step would leave the point at
    # v = y (the skewed coordinate), which is not the foot.
    s = sheared_plane()
    pts = np.array([[2.0, 0.3, 0.2], [2.5, 0.1, -0.1], [1.0, 0.5, 0.3]])
    v_edge = (pts[:2, 1] + 0.8 * (pts[:2, 0] - 1.0)) / 1.64
    want = np.array([[1.0, v_edge[0]], [1.0, v_edge[1]], [0.6, 0.5]])
    uv, dist = closest_parameters(s, pts, np.full((3, 2), 0.5))
    np.testing.assert_allclose(uv, want, atol=1e-12)
    foot = np.c_[want[:, 0] + 0.8 * want[:, 1], want[:, 1], np.zeros(3)]
    np.testing.assert_allclose(dist, np.linalg.norm(pts - foot, axis=1), atol=1e-12)


def test_foot_point_far_off_a_cylinder_patch_is_the_radial_projection(search):
    # a point far off a curved surface: Newton (with the r.S_uu terms) lands on the radial
    # foot to machine precision where Gauss-Newton alone converges only linearly
    layout = NetLayout((3, 2), (2, 1))
    w = np.sqrt(0.5)
    arc = np.array([[1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    net = np.stack([arc, arc + [0, 0, 1]], axis=1).reshape(-1, 3)
    s = layout.surface(net, np.array([1, 1, w, w, 1, 1]))
    angle, height, radius = np.array([0.3, 0.7, 1.2]), np.array([0.2, 0.5, 0.9]), np.array([3.0, 0.2, 2.5])
    pts = np.c_[radius * np.cos(angle), radius * np.sin(angle), height]
    _, dist = closest_parameters(s, pts, np.full((3, 2), 0.5), iterations=10)
    np.testing.assert_allclose(dist, np.abs(radius - 1.0), rtol=0, atol=1e-12)


def test_global_search_starts_at_the_nearest_vertex_and_finds_the_foot_point(search):
    """On a wavy patch, points off it by up to 3% of its size: the start is the nearest
    vertex of the tessellation (within a grid spacing of the foot point, the same start
    for any chunking) and Newton takes it to the foot point."""
    layout = NetLayout((6, 6), (3, 3))
    i, j = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6), indexing="ij")
    net = np.stack([i, j, 0.1 * np.sin(5 * i) * np.cos(4 * j)], -1).reshape(-1, 3)
    surface = layout.surface(net, np.ones(36))
    rng = np.random.default_rng(0)
    foot = rng.uniform(0.05, 0.95, (400, 2))
    s, su, sv = surface.derivatives(foot[:, 0], foot[:, 1])
    normal = np.cross(su, sv)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    points = s + rng.uniform(-0.03, 0.03, (400, 1)) * normal
    start = GridStart(surface, 64)(points)
    us, vs = surface.parameter_grid(64, 64)
    vertices = surface.evaluate_grid(us, vs).reshape(-1, 3)
    nearest = np.argmin(((points[:, None] - vertices[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(start, np.c_[us[nearest // 64], vs[nearest % 64]])
    assert 0.3 / 63 < np.abs(start - foot).max() < 1.0 / 63
    uv, dist = closest_parameters(surface, points, resolution=64)
    np.testing.assert_allclose(uv, foot, atol=1e-9)


def test_foot_points_on_a_sphere_reach_the_poles(search):
    """A sphere-like net (rows collapsed to the poles, where S_u = 0 and the step in u is
    held by the regularised Hessian): points above the poles, started near them, and a
    point off the equator find their foot points (no vertex of a dense tessellation is
    closer), their distances those of the parameters returned. (A search that lands on a
    pole from afar stays there: S_u = 0 gives it no direction in u.)"""
    surface, _, _ = fitted_surface("sphere", np.random.default_rng(8))
    poles = surface.evaluate(np.array([0.3, 0.3]), np.array([0.0, 1.0]))
    points = np.r_[1.5 * poles, 1.2 * surface.evaluate(np.array([0.4]), np.array([0.5]))]
    uv, dist = closest_parameters(surface, points, np.array([[0.7, 0.05], [0.2, 0.95], [0.35, 0.45]]))
    assert uv[0, 1] < 0.05 and uv[1, 1] > 0.95
    vertices = surface.evaluate_grid(*surface.parameter_grid(721, 721)).reshape(-1, 3)
    nearest = np.sqrt(((points[:, None] - vertices[None]) ** 2).sum(-1).min(axis=1))
    assert np.all(dist <= nearest + 1e-12)
    foot = surface.evaluate(uv[:, 0], uv[:, 1])
    np.testing.assert_allclose(dist, np.linalg.norm(points - foot, axis=1), rtol=0, atol=1e-12)

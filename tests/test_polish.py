"""Parameter correction: foot points on the edges, and the Anderson mixing of the polish;
the joint refinement with point weights."""
from __future__ import annotations

import numpy as np

from psonurbs.fitting.polish import AndersonMixing
from psonurbs.fitting.refine import refine_jointly
from psonurbs.fitting.solve import RegularisedLeastSquares
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.projection import GridStart, closest_parameters


def sheared_plane():
    """S(u, v) = (u + 0.8 v, v, 0): a cubic net with linear precision, S_u . S_v != 0."""
    layout = NetLayout((4, 4), (3, 3))
    i, j = np.meshgrid(np.linspace(0, 1, 4), np.linspace(0, 1, 4), indexing="ij")
    net = np.stack([i + 0.8 * j, j, np.zeros_like(i)], -1).reshape(-1, 3)
    return layout.surface(net, np.ones(16))


def test_point_beyond_an_edge_slides_along_it_to_its_foot():
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


def test_foot_point_far_off_a_cylinder_patch_is_the_radial_projection():
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


def test_global_search_starts_at_the_nearest_vertex_and_finds_the_foot_point():
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


def test_anderson_mixing_solves_a_slow_linear_iteration_much_faster():
    # x <- A x + b with spectral radius 0.97: plain iteration needs ~700 rounds for 1e-9
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(20, 20)))
    a = q @ np.diag(np.linspace(0.1, 0.97, 20)) @ q.T
    b = rng.normal(size=20)
    fixed = np.linalg.solve(np.eye(20) - a, b)
    x, mixer = np.zeros((10, 2)), AndersonMixing((False, False), depth=10)
    for rounds in range(1, 200):
        x = mixer.next(x, (a @ x.ravel() + b).reshape(10, 2))
        if np.abs(x.ravel() - fixed).max() < 1e-9:
            break
    assert rounds < 60, rounds


def test_anderson_mixing_differences_a_closed_direction_across_the_seam():
    # u is closed: a move from 0.95 to 0.05 is +0.1, not -0.9; v is open and moves plainly
    mixer = AndersonMixing((True, False))
    step = mixer.next(np.array([[0.95, 0.5]]), np.array([[0.05, 0.6]]))
    np.testing.assert_allclose(step, [[1.05, 0.6]])
    # a constant-rate iteration (u += 0.1 around the seam) is extrapolated exactly
    step = mixer.next(np.array([[0.05, 0.6]]), np.array([[0.15, 0.6]]))
    np.testing.assert_allclose(step, [[0.15, 0.6]], atol=1e-12)


def test_only_directions_with_edges_are_aligned_to_the_domain():
    from psonurbs.fitting.polish import align_to_domain
    from psonurbs.fitting.topology import layout_for

    rng = np.random.default_rng(5)
    uv = np.c_[rng.uniform(0.1, 0.9, 400), rng.uniform(0.05, 0.8, 400)]
    expected = {"open": (True, True), "cylinder": (False, True), "sphere": (False, False),
                "torus": (False, False)}
    for topology, bounded in expected.items():
        layout = layout_for(topology, (8, 6), (3, 3))
        assert layout.bounded == bounded, topology
        out = align_to_domain(uv, layout)
        for k in (0, 1):
            if bounded[k]:  # the data's extent is stretched onto [0, 1]
                assert out[:, k].min() < 0.01 and out[:, k].max() > 0.99, (topology, k)
            else:  # a closed direction, or a sphere's pole-to-pole one: no edge to align
                np.testing.assert_array_equal(out[:, k], uv[:, k])


def test_joint_refinement_with_an_integer_weight_is_the_point_given_twice():
    """The weighted refinement scales every point's residual and Jacobian rows by
    sqrt(weight): weight 2 on a point is the point twice (same start, same steps)."""
    layout = NetLayout((4, 4), (2, 2))
    rng = np.random.default_rng(3)
    uv = rng.random((120, 2))
    pts = np.column_stack([uv, 0.2 * np.sin(3 * uv[:, 0]) * uv[:, 1]]) + rng.normal(0, 0.01, (120, 3))
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-4)
    ones = np.ones(layout.n_free)
    control = solver.solve(layout.rows(uv, ones), pts)
    w = np.ones(120)
    w[[5, 17, 60]] = 2.0
    twice = np.r_[np.arange(120), [5, 17, 60]]
    bounds = np.log([0.2, 5.0])
    weighted = refine_jointly(layout, solver, pts, uv, control, ones, None, None, bounds, point_weights=w)
    repeated = refine_jointly(layout, solver, pts[twice], uv[twice], control, ones, None, None, bounds)
    np.testing.assert_allclose(weighted[0], repeated[0], rtol=1e-7, atol=1e-9)  # control points
    np.testing.assert_allclose(weighted[1], repeated[1], rtol=1e-7)  # weights
    np.testing.assert_allclose(weighted[2], repeated[2][:120], atol=1e-9)  # parameters
    assert weighted[3] == repeated[3]

"""Parameter correction: the Anderson mixing of the polish; the joint refinement with point
weights. (Foot points: tests/test_projection.py.)"""
from __future__ import annotations

import numpy as np

from psonurbs.fitting.finish.polish import AndersonMixing
from psonurbs.fitting.finish.refine import refine_jointly
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.geometry.net import NetLayout, NetShape


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


def test_relaxed_anderson_mixing_reaches_the_same_fixed_point_and_beta_one_is_the_plain_mix():
    """x <- A x + b as above: with a relaxation beta (x + beta f - (dX + beta dF) c) the
    mix still converges to the fixed point; beta 1 gives the plain mix's iterates to the bit."""
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(20, 20)))
    a = q @ np.diag(np.linspace(0.1, 0.97, 20)) @ q.T
    b = rng.normal(size=20)
    fixed = np.linalg.solve(np.eye(20) - a, b)

    def run(**relax):
        x, mixer, seen = np.zeros((10, 2)), AndersonMixing((False, False), depth=10, **relax), []
        for _ in range(80):
            x = mixer.next(x, (a @ x.ravel() + b).reshape(10, 2))
            seen.append(x)
        return seen

    plain, one, relaxed = run(), run(relaxation=1.0), run(relaxation=1.8)
    assert all(np.array_equal(p, o) for p, o in zip(plain, one))
    assert np.abs(relaxed[-1].ravel() - fixed).max() < 1e-9
    assert not np.array_equal(relaxed[3], plain[3])  # it is another iteration


def test_anderson_mixing_differences_a_closed_direction_across_the_seam():
    # u is closed: a move from 0.95 to 0.05 is +0.1, not -0.9; v is open and moves plainly
    mixer = AndersonMixing((True, False))
    step = mixer.next(np.array([[0.95, 0.5]]), np.array([[0.05, 0.6]]))
    np.testing.assert_allclose(step, [[1.05, 0.6]])
    # a constant-rate iteration (u += 0.1 around the seam) is extrapolated exactly
    step = mixer.next(np.array([[0.05, 0.6]]), np.array([[0.15, 0.6]]))
    np.testing.assert_allclose(step, [[0.15, 0.6]], atol=1e-12)


def test_only_directions_with_edges_are_aligned_to_the_domain():
    from psonurbs.fitting.finish.polish import align_to_domain
    from psonurbs.fitting.parameters.topology import layout_for

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
    weighted = refine_jointly(layout, solver, pts, uv, control, NetShape(ones), bounds, point_weights=w)
    repeated = refine_jointly(layout, solver, pts[twice], uv[twice], control, NetShape(ones), bounds)
    np.testing.assert_allclose(weighted.control, repeated.control, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(weighted.shape.weights, repeated.shape.weights, rtol=1e-7)
    np.testing.assert_allclose(weighted.uv, repeated.uv[:120], atol=1e-9)
    assert weighted.rounds == repeated.rounds


def test_a_curved_edge_is_aligned_without_bending_the_parameters():
    """Points over an ellipse: the lines fitted through the extremes of its curved edges
    would leave a cap of the data beyond them (putting it on the edges bent the
    parameters by up to 0.069 from an affine map, with 87-131 points on each edge); the
    edges are the data's extremes instead: the map is affine, the data span [0, 1] and
    one point is on each edge."""
    from psonurbs.fitting.finish.polish import align_to_domain
    from psonurbs.fitting.parameters.topology import layout_for

    rng = np.random.default_rng(2)
    uv = rng.random((8000, 2))
    uv = uv[((uv[:, 0] - 0.5) / 0.48) ** 2 + ((uv[:, 1] - 0.5) / 0.36) ** 2 < 1.0][:5000]
    out = align_to_domain(uv, layout_for("open", (8, 8), (3, 3)))
    affine = np.c_[np.ones(len(uv)), uv]
    for k in (0, 1):
        residual = out[:, k] - affine @ np.linalg.lstsq(affine, out[:, k], rcond=None)[0]
        assert np.abs(residual).max() < 1e-12, k
        assert out[:, k].min() == 0.0 and out[:, k].max() == 1.0
        assert np.sum(out[:, k] == 0.0) == 1 and np.sum(out[:, k] == 1.0) == 1


def test_a_straight_edge_puts_the_points_past_its_line_on_the_domain_edge():
    """A rectangle's edges, the parameters jittered by a tenth of the spacing: the lines
    through the edges' extremes are the edges, and the few points past them go onto the
    domain's edges (a straight edge is aligned as it always was)."""
    from psonurbs.fitting.finish.polish import align_to_domain
    from psonurbs.fitting.parameters.topology import layout_for

    rng = np.random.default_rng(4)
    uv = 0.1 + 0.8 * rng.random((4000, 2)) + rng.normal(0.0, 0.1 * 0.8 / 63, (4000, 2))
    out = align_to_domain(uv, layout_for("open", (8, 8), (3, 3)))
    for k in (0, 1):
        assert np.sum(out[:, k] == 0.0) > 1 and np.sum(out[:, k] == 1.0) > 1, k  # the extreme: 1
        inner = (out[:, k] > 0.0) & (out[:, k] < 1.0)
        np.testing.assert_allclose(out[inner, k], (uv[inner, k] - 0.1) / 0.8, atol=0.01)


def test_a_flat_disc_is_not_squeezed_onto_the_square_and_its_face_extends_without_folding():
    """A disc's edge is no straight line: its lowest points sag half its width from their
    chord (at 600-1,000 points within 2.7 spacings of the line through them, inside the
    allowance). Put on lines, its parameters were squeezed onto the square and the patch
    extended past its edge folded over its own plane."""
    from psonurbs.config import config_from_dict
    from psonurbs.fitting.finish.polish import align_to_domain
    from psonurbs.fitting.pipeline import fit_points

    rng = np.random.default_rng(3)
    for n in (600, 1000):
        r, t = 0.5 * np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
        xy = np.column_stack([r * np.cos(t), r * np.sin(t)])
        uv = (xy - xy.min(axis=0)) / np.ptp(xy, axis=0)
        assert np.allclose(align_to_domain(uv, NetLayout((4, 4), (3, 3))), uv)
    config = config_from_dict({"orders": [4, 4], "net_size": [4, 4], "topology": "open", "trim": False,
                               "swarm": {"particles": 1, "iterations": 1, "seed": 7}})
    fit = fit_points(np.column_stack([xy, np.zeros(len(xy))]), config)
    assert fit.metrics["rmse"] < 1e-9 and not fit.warnings
    longer = fit.surface.restricted((-0.2, 1.2), (-0.2, 1.2))
    u, v = (g.ravel() for g in np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 60)))
    _, su, sv = longer.derivatives(u, v)
    normal = np.cross(su, sv)[:, 2]
    assert np.all(normal > 0) or np.all(normal < 0)  # one side up everywhere: no fold

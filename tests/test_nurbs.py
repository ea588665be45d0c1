"""NURBS surfaces: exact conics, evaluation against an independent double sum built on
scipy.interpolate.BSpline, derivatives, tessellation and the JSON round trip."""
from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import random_surface, reference_basis, reference_points
from scipy.interpolate import RegularGridInterpolator

from psonurbs.geometry.basis import clamped_knots, design_matrix, periodic_knots
from psonurbs.geometry.nurbs import NurbsSurface, grid_triangles
from psonurbs.geometry.rows import Rows


def rational_basis(tensor, weights):
    """The library's rational basis rows (what the fitter solves with) from a CSR basis."""
    return Rows.from_csr(tensor).rational(np.ravel(weights))

S2 = np.sqrt(2.0) / 2.0


# ---------------------------------------------------------------------------
# Fixtures / builders
# ---------------------------------------------------------------------------

def extrude(points_2d, weights_1d, knots_u, degree_u, heights=(0.0, 1.0)):
    """Surface of degree (p, 1): a planar rational curve extruded along z (z = v)."""
    pts = np.asarray(points_2d, float)
    nu = len(pts)
    cp = np.zeros((nu, len(heights), 3))
    cp[:, :, :2] = pts[:, None, :]
    cp[:, :, 2] = np.asarray(heights)[None, :]
    w = np.repeat(np.asarray(weights_1d, float)[:, None], len(heights), axis=1)
    return NurbsSurface(degree_u, 1, knots_u, [0, 0, 1, 1], cp, w)


QUARTER_PTS = [(1, 0), (1, 1), (0, 1)]
QUARTER_W = [1, S2, 1]
QUARTER_KNOTS = [0, 0, 0, 1, 1, 1]

CIRCLE_PTS = [(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1), (1, 0)]
CIRCLE_W = [1, S2, 1, S2, 1, S2, 1, S2, 1]
CIRCLE_KNOTS = [0, 0, 0, 0.25, 0.25, 0.5, 0.5, 0.75, 0.75, 1, 1, 1]


# ---------------------------------------------------------------------------
# Exact conics
# ---------------------------------------------------------------------------

def test_quarter_circle_rational_quadratic_curve():
    u = np.linspace(0.0, 1.0, 1000)
    R = rational_basis(design_matrix(u, np.array(QUARTER_KNOTS, float), 2), np.array(QUARTER_W))
    xy = R @ np.array(QUARTER_PTS, float)
    np.testing.assert_allclose(xy[:, 0] ** 2 + xy[:, 1] ** 2, 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(xy[0], [1, 0], rtol=0, atol=0)
    np.testing.assert_allclose(xy[-1], [0, 1], rtol=0, atol=0)
    # u = 1/2 is at 45 degrees, and the angle grows monotonically
    half = rational_basis(design_matrix(np.array([0.5]), np.array(QUARTER_KNOTS, float), 2),
                          np.array(QUARTER_W)) @ np.array(QUARTER_PTS, float)
    np.testing.assert_allclose(half[0], [S2, S2], rtol=0, atol=1e-15)
    assert np.all(np.diff(np.arctan2(xy[:, 1], xy[:, 0])) > 0)


def test_quarter_cylinder_surface_is_exact():
    surf = extrude(QUARTER_PTS, QUARTER_W, QUARTER_KNOTS, 2)
    rng = np.random.default_rng(0)
    u = np.concatenate([np.linspace(0, 1, 1000), rng.uniform(0, 1, 1000)])
    v = np.concatenate([np.linspace(0, 1, 1000), rng.uniform(0, 1, 1000)])
    p = surf.evaluate(u, v)
    assert p.shape == (2000, 3)
    np.testing.assert_allclose(p[:, 0] ** 2 + p[:, 1] ** 2, 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(p[:, 2], v, rtol=0, atol=1e-15)  # degree 1 along z: z = v
    assert np.all(p[:, :2] >= -1e-15)  # stays in the first quadrant
    # tessellated mesh lies on the cylinder too
    verts, tris = surf.tessellate(33, 5)
    np.testing.assert_allclose(verts[:, 0] ** 2 + verts[:, 1] ** 2, 1.0, rtol=0, atol=1e-14)


def test_full_circle_nine_point_rational_quadratic():
    u = np.linspace(0.0, 1.0, 1000)
    t = np.array(CIRCLE_KNOTS, float)
    R = rational_basis(design_matrix(u, t, 2), np.array(CIRCLE_W))
    xy = R @ np.array(CIRCLE_PTS, float)
    np.testing.assert_allclose(xy[:, 0] ** 2 + xy[:, 1] ** 2, 1.0, rtol=0, atol=1e-14)
    # the double knots at 1/4, 1/2, 3/4 interpolate the axis points
    q = rational_basis(design_matrix(np.array([0, 0.25, 0.5, 0.75, 1]), t, 2), np.array(CIRCLE_W))
    np.testing.assert_allclose(q @ np.array(CIRCLE_PTS, float),
                               [[1, 0], [0, 1], [-1, 0], [0, -1], [1, 0]], rtol=0, atol=1e-15)
    # goes around exactly once, counter-clockwise
    ang = np.unwrap(np.arctan2(xy[:, 1], xy[:, 0]))
    assert np.all(np.diff(ang) > 0)
    np.testing.assert_allclose(ang[-1] - ang[0], 2 * np.pi, rtol=0, atol=1e-12)


def test_full_cylinder_surface_is_exact():
    surf = extrude(CIRCLE_PTS, CIRCLE_W, CIRCLE_KNOTS, 2)
    rng = np.random.default_rng(1)
    u = np.concatenate([np.linspace(0, 1, 1000), rng.uniform(0, 1, 1000), [0.25, 0.5, 0.75]])
    v = np.concatenate([rng.uniform(0, 1, 2000), [0.0, 0.5, 1.0]])
    p = surf.evaluate(u, v)
    np.testing.assert_allclose(p[:, 0] ** 2 + p[:, 1] ** 2, 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(p[:, 2], v, rtol=0, atol=1e-15)
    np.testing.assert_allclose(p[-3:], [[0, 1, 0], [-1, 0, 0.5], [0, -1, 1]], rtol=0, atol=1e-15)
    grid = surf.evaluate_grid(*surf.parameter_grid(101, 3))
    np.testing.assert_allclose(grid[..., 0] ** 2 + grid[..., 1] ** 2, 1.0, rtol=0, atol=1e-14)
    # closed: first and last rows of the grid coincide
    np.testing.assert_allclose(grid[0], grid[-1], rtol=0, atol=1e-15)


# ---------------------------------------------------------------------------
# Evaluation against an independent double sum
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("seed, pu, pv, nu, nv", [
    (0, 3, 2, 6, 5),
    (1, 2, 3, 4, 7),
    (2, 1, 4, 3, 6),
])
def test_evaluate_matches_explicit_double_sum(seed, pu, pv, nu, nv):
    surf = random_surface(seed, pu, pv, nu, nv)
    rng = np.random.default_rng(seed + 50)
    u = np.concatenate([[0, 0, 1, 1], surf.knots_u[pu:nu + 1], rng.uniform(0, 1, 300)])
    v = np.concatenate([[0, 1, 0, 1], rng.uniform(0, 1, nu + 1 - pu), rng.uniform(0, 1, 300)])
    u = np.concatenate([u, rng.uniform(0, 1, nv + 1 - pv)])
    v = np.concatenate([v, surf.knots_v[pv:nv + 1]])  # every knot of each direction
    got = surf.evaluate(u, v)
    ref = reference_points(surf, u, v)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13 * np.abs(surf.control_points).max())
    # corners of a clamped surface are the corner control points
    np.testing.assert_allclose(got[:4], surf.control_points[[0, 0, -1, -1], [0, -1, 0, -1]],
                               rtol=0, atol=1e-14)


def test_evaluate_on_a_non_unit_domain():
    surf = random_surface(4, domain_u=(2.0, 5.0))
    assert surf.domain_u == (2.0, 5.0)
    rng = np.random.default_rng(4)
    u = np.concatenate([[2.0, 5.0], rng.uniform(2, 5, 100)])
    v = np.concatenate([[0.0, 1.0], rng.uniform(0, 1, 100)])
    np.testing.assert_allclose(surf.evaluate(u, v), reference_points(surf, u, v), rtol=0, atol=1e-12)


def test_evaluate_grid_layout():
    surf = random_surface(5)
    us = np.array([0.0, 0.3, 1.0])
    vs = np.array([0.1, 0.6, 0.7, 1.0])
    g = surf.evaluate_grid(us, vs)
    assert g.shape == (3, 4, 3)
    for a, uu in enumerate(us):
        for b, vv in enumerate(vs):
            np.testing.assert_allclose(g[a, b], reference_points(surf, np.array([uu]), np.array([vv]))[0],
                                       rtol=0, atol=1e-13)


# ---------------------------------------------------------------------------
# Derivatives
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_partials_match_central_differences(seed):
    surf = random_surface(seed, pu=3, pv=2, nu=6, nv=5)
    assert np.ptp(surf.weights) > 1.0  # genuinely rational
    rng = np.random.default_rng(seed + 7)
    h = 1e-6
    u = rng.uniform(2 * h, 1 - 2 * h, 200)
    v = rng.uniform(2 * h, 1 - 2 * h, 200)
    s, su, sv = surf.derivatives(u, v)
    np.testing.assert_allclose(s, surf.evaluate(u, v), rtol=0, atol=0)
    fu = (surf.evaluate(u + h, v) - surf.evaluate(u - h, v)) / (2 * h)
    fv = (surf.evaluate(u, v + h) - surf.evaluate(u, v - h)) / (2 * h)
    for d, f in ((su, fu), (sv, fv)):
        err = np.linalg.norm(d - f, axis=1)
        assert np.all(err <= 1e-6 * np.maximum(np.linalg.norm(d, axis=1), 1.0)), err.max()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_second_partials_match_central_differences_of_first(seed):
    surf = random_surface(seed, pu=3, pv=2, nu=6, nv=5)
    rng = np.random.default_rng(seed + 11)
    h = 1e-6
    u = rng.uniform(2 * h, 1 - 2 * h, 200)
    v = rng.uniform(2 * h, 1 - 2 * h, 200)
    s, su, sv, suu, suv, svv = surf.derivatives(u, v, second=True)
    np.testing.assert_array_equal(np.stack([s, su, sv]), np.stack(surf.derivatives(u, v)))
    plus_u, minus_u = surf.derivatives(u + h, v), surf.derivatives(u - h, v)
    plus_v, minus_v = surf.derivatives(u, v + h), surf.derivatives(u, v - h)
    fuu = (plus_u[1] - minus_u[1]) / (2 * h)
    fuv = (plus_u[2] - minus_u[2]) / (2 * h)
    fvu = (plus_v[1] - minus_v[1]) / (2 * h)
    fvv = (plus_v[2] - minus_v[2]) / (2 * h)
    for d, f in ((suu, fuu), (suv, fuv), (suv, fvu), (svv, fvv)):
        err = np.linalg.norm(d - f, axis=1)
        assert np.all(err <= 1e-5 * np.maximum(np.linalg.norm(d, axis=1), 1.0)), err.max()


def test_quarter_circle_second_partial_gives_unit_curvature():
    surf = extrude(QUARTER_PTS, QUARTER_W, QUARTER_KNOTS, 2)
    u = np.linspace(0, 1, 101)
    _, su, sv, suu, suv, svv = surf.derivatives(u, np.full_like(u, 0.3), second=True)
    # a unit circle: |S_u x S_uu| / |S_u|^3 = 1, and the extrusion is straight in v
    curvature = np.linalg.norm(np.cross(su, suu), axis=1) / np.linalg.norm(su, axis=1) ** 3
    np.testing.assert_allclose(curvature, 1.0, rtol=1e-12)
    np.testing.assert_allclose(suv, 0.0, atol=1e-14)
    np.testing.assert_allclose(svv, 0.0, atol=1e-14)


def test_partials_match_independent_quotient_rule():
    surf = random_surface(9, pu=3, pv=3, nu=7, nv=5)
    rng = np.random.default_rng(9)
    u = np.concatenate([[0, 1, 0, 1], rng.uniform(0, 1, 200)])
    v = np.concatenate([[0, 0, 1, 1], rng.uniform(0, 1, 200)])
    _, su, sv = surf.derivatives(u, v)
    ru, rv = reference_points(surf, u, v, (1, 0)), reference_points(surf, u, v, (0, 1))
    scale = max(np.abs(ru).max(), np.abs(rv).max())
    np.testing.assert_allclose(su, ru, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(sv, rv, rtol=0, atol=1e-12 * scale)


def test_quarter_circle_tangent_is_perpendicular_to_radius():
    surf = extrude(QUARTER_PTS, QUARTER_W, QUARTER_KNOTS, 2)
    u = np.linspace(0, 1, 101)
    v = np.full_like(u, 0.3)
    s, su, sv = surf.derivatives(u, v)
    np.testing.assert_allclose(np.einsum("ij,ij->i", s[:, :2], su[:, :2]), 0.0, rtol=0, atol=1e-13)
    np.testing.assert_allclose(su[:, 2], 0.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(sv, np.tile([0.0, 0.0, 1.0], (len(u), 1)), rtol=0, atol=1e-14)
    # known end tangents: S_u(0) = 2 w1 (P1 - P0) / w0 = (0, sqrt2, 0)
    np.testing.assert_allclose(su[0], [0, np.sqrt(2), 0], rtol=0, atol=1e-14)
    np.testing.assert_allclose(su[-1], [-np.sqrt(2), 0, 0], rtol=0, atol=1e-14)


# ---------------------------------------------------------------------------
# Rational invariance and bilinear reproduction
# ---------------------------------------------------------------------------

def test_uniform_weights_are_invisible():
    base = random_surface(11, rational=False)
    heavy = NurbsSurface(base.degree_u, base.degree_v, base.knots_u, base.knots_v,
                         base.control_points, np.full(base.shape, 3.0))
    rng = np.random.default_rng(11)
    u = np.concatenate([[0, 1], rng.uniform(0, 1, 300)])
    v = np.concatenate([[0, 1], rng.uniform(0, 1, 300)])
    a, b = base.evaluate(u, v), heavy.evaluate(u, v)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-14 * np.abs(a).max())
    # and both equal the plain (non-rational) tensor-product B-spline
    Nu = reference_basis(u, base.knots_u, base.degree_u)
    Nv = reference_basis(v, base.knots_v, base.degree_v)
    plain = np.einsum("ri,rj,ijk->rk", Nu, Nv, base.control_points)
    np.testing.assert_allclose(a, plain, rtol=0, atol=1e-13)
    for x, y in zip(base.derivatives(u, v), heavy.derivatives(u, v)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * np.abs(x).max())


def test_bilinear_patch_is_bilinear_interpolation():
    rng = np.random.default_rng(12)
    corners = rng.normal(size=(2, 2, 3))  # a twisted (non-planar) patch
    surf = NurbsSurface(1, 1, [0, 0, 1, 1], [0, 0, 1, 1], corners, np.ones((2, 2)))
    u = np.concatenate([[0, 1, 0, 1, 0.5], rng.uniform(0, 1, 300)])
    v = np.concatenate([[0, 0, 1, 1, 0.5], rng.uniform(0, 1, 300)])
    U, V = u[:, None], v[:, None]
    expected = ((1 - U) * (1 - V) * corners[0, 0] + (1 - U) * V * corners[0, 1]
                + U * (1 - V) * corners[1, 0] + U * V * corners[1, 1])
    np.testing.assert_allclose(surf.evaluate(u, v), expected, rtol=0, atol=1e-15 * 8)
    np.testing.assert_allclose(surf.evaluate(np.array([0.5]), np.array([0.5]))[0], corners.mean(axis=(0, 1)),
                               rtol=0, atol=1e-15)
    _, su, sv = surf.derivatives(u, v)
    np.testing.assert_allclose(su, (1 - V) * (corners[1, 0] - corners[0, 0]) + V * (corners[1, 1] - corners[0, 1]),
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(sv, (1 - U) * (corners[0, 1] - corners[0, 0]) + U * (corners[1, 1] - corners[1, 0]),
                               rtol=0, atol=1e-14)


def test_piecewise_bilinear_net_interpolates_grid():
    # degree 1 x 1 with inner knots: control points sit at the knot nodes and the
    # surface is the piecewise bilinear interpolant of the net
    nodes_u = np.array([0.0, 0.2, 0.45, 1.0])
    nodes_v = np.array([0.0, 0.7, 1.0])
    rng = np.random.default_rng(13)
    cp = rng.normal(size=(4, 3, 3))
    surf = NurbsSurface(1, 1, np.r_[0, nodes_u, 1], np.r_[0, nodes_v, 1], cp, np.ones((4, 3)))
    u = np.concatenate([nodes_u, rng.uniform(0, 1, 300)])
    v = np.concatenate([[0.0, 0.7, 1.0, 0.7], rng.uniform(0, 1, 300)])
    interp = RegularGridInterpolator((nodes_u, nodes_v), cp, method="linear")
    np.testing.assert_allclose(surf.evaluate(u, v), interp(np.stack([u, v], 1)), rtol=0, atol=1e-14)


# ---------------------------------------------------------------------------
# Tessellation
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("n_u, n_v", [(7, 4), (2, 2), (5, 11)])
def test_tessellate_counts_indices_and_corners(n_u, n_v):
    surf = random_surface(21, domain_u=(2.0, 5.0))
    verts, tris = surf.tessellate(n_u, n_v)
    assert verts.shape == (n_u * n_v, 3)
    assert tris.shape == (2 * (n_u - 1) * (n_v - 1), 3)
    assert np.issubdtype(tris.dtype, np.integer)
    assert tris.min() >= 0 and tris.max() < n_u * n_v
    assert np.all((tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2]))
    assert len(np.unique(tris)) == n_u * n_v  # every vertex is used
    (u0, u1), (v0, v1) = surf.domain_u, surf.domain_v
    assert (u0, u1, v0, v1) == (2.0, 5.0, 0.0, 1.0)
    corner_uv = np.array([[u0, v0], [u0, v1], [u1, v0], [u1, v1]])
    expected = reference_points(surf, corner_uv[:, 0], corner_uv[:, 1])
    got = verts[[0, n_v - 1, (n_u - 1) * n_v, n_u * n_v - 1]]
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-13)
    # and those corners are the corner control points of the clamped net
    np.testing.assert_allclose(got, surf.control_points[[0, 0, -1, -1], [0, -1, 0, -1]], rtol=0, atol=1e-13)
    # vertex (a, b) is the surface at the a-th u and b-th v of an equally spaced grid
    a, b = n_u // 2, n_v - 2
    uu = u0 + (u1 - u0) * a / (n_u - 1)
    vv = v0 + (v1 - v0) * b / (n_v - 1)
    np.testing.assert_allclose(verts[a * n_v + b], reference_points(surf, np.array([uu]), np.array([vv]))[0],
                               rtol=0, atol=1e-12)


def test_tessellated_flat_square_has_unit_area_and_consistent_orientation():
    cp = np.array([[[0, 0, 0], [0, 1, 0]], [[1, 0, 0], [1, 1, 0]]], float)
    surf = NurbsSurface(1, 1, [0, 0, 1, 1], [0, 0, 1, 1], cp, np.ones((2, 2)))
    verts, tris = surf.tessellate(9, 6)
    e1 = verts[tris[:, 1]] - verts[tris[:, 0]]
    e2 = verts[tris[:, 2]] - verts[tris[:, 0]]
    nz = np.cross(e1, e2)[:, 2]
    # every triangle has the same orientation and the cells tile the square exactly
    assert np.all(nz > 0) or np.all(nz < 0)
    np.testing.assert_allclose(np.abs(nz).sum() / 2, 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.abs(nz) / 2, 1.0 / (2 * 8 * 5), rtol=0, atol=1e-15)


def test_grid_triangles_by_hand():
    tris = grid_triangles(2, 3)
    # vertices row-major: (i, j) -> i * 3 + j
    np.testing.assert_array_equal(tris, [[0, 3, 1], [1, 4, 2], [1, 3, 4], [2, 4, 5]])


# ---------------------------------------------------------------------------
# JSON round trip and validation
# ---------------------------------------------------------------------------

def closed_surface():
    """Closed in u (periodic, net repeats its first p rows), clamped in v."""
    rng = np.random.default_rng(31)
    p, n = 3, 6
    tu = periodic_knots(n, p, np.sort(rng.uniform(0.05, 0.95, n - 1)))
    distinct = rng.normal(size=(n, 4, 3))
    cp = np.concatenate([distinct, distinct[:p]], axis=0)
    wd = rng.uniform(0.5, 2.0, size=(n, 4))
    w = np.concatenate([wd, wd[:p]], axis=0)
    return NurbsSurface(p, 2, tu, clamped_knots(4, 2, [0.35]), cp, w, closed_u=True)


def test_closed_surface_has_no_seam():
    surf = closed_surface()
    assert surf.domain_u == (0.0, 1.0)
    v = np.linspace(0, 1, 50)
    s0, su0, sv0 = surf.derivatives(np.zeros_like(v), v)
    s1, su1, sv1 = surf.derivatives(np.ones_like(v), v)
    np.testing.assert_allclose(s0, s1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(su0, su1, rtol=0, atol=1e-9 * np.abs(su0).max())
    np.testing.assert_allclose(sv0, sv1, rtol=0, atol=1e-9 * np.abs(sv0).max())
    u = np.random.default_rng(3).uniform(0, 1, 100)
    vv = np.random.default_rng(4).uniform(0, 1, 100)
    np.testing.assert_allclose(surf.evaluate(u, vv), reference_points(surf, u, vv), rtol=0, atol=1e-12)


@pytest.mark.parametrize("make", [lambda: random_surface(41), closed_surface,
                                  lambda: extrude(CIRCLE_PTS, CIRCLE_W, CIRCLE_KNOTS, 2)])
def test_json_round_trip_is_exact(make):
    surf = make()
    d = json.loads(json.dumps(surf.to_dict()))
    assert set(d) == {"degree_u", "degree_v", "knots_u", "knots_v", "control_points",
                      "weights", "closed_u", "closed_v"}
    assert np.shape(d["control_points"]) == (*surf.shape, 3)
    assert np.shape(d["weights"]) == surf.shape
    assert len(d["knots_u"]) == surf.shape[0] + d["degree_u"] + 1
    back = NurbsSurface.from_dict(d)
    assert (back.closed_u, back.closed_v) == (surf.closed_u, surf.closed_v)
    assert (back.degree_u, back.degree_v) == (surf.degree_u, surf.degree_v)
    np.testing.assert_array_equal(back.knots_u, surf.knots_u)
    np.testing.assert_array_equal(back.weights, surf.weights)
    rng = np.random.default_rng(42)
    u = np.concatenate([[0.0, 1.0], rng.uniform(0, 1, 200)])
    v = np.concatenate([[0.0, 1.0], rng.uniform(0, 1, 200)])
    np.testing.assert_array_equal(back.evaluate(u, v), surf.evaluate(u, v))


def test_from_dict_without_weights_is_non_rational():
    surf = random_surface(43, rational=False)
    d = json.loads(json.dumps(surf.to_dict()))
    del d["weights"]
    back = NurbsSurface.from_dict(d)
    np.testing.assert_array_equal(back.weights, np.ones(surf.shape))
    u = np.linspace(0, 1, 17)
    np.testing.assert_array_equal(back.evaluate(u, u[::-1]), surf.evaluate(u, u[::-1]))


def _valid_dict():
    return json.loads(json.dumps(random_surface(51).to_dict()))


@pytest.mark.parametrize("breakage", [
    "knot_too_many_u", "knot_too_few_v", "decreasing_u", "decreasing_v",
    "zero_weight", "negative_weight", "bad_cp_shape",
])
def test_invalid_surfaces_are_rejected(breakage):
    d = _valid_dict()
    if breakage == "knot_too_many_u":
        d["knots_u"] = d["knots_u"] + [1.0]
    elif breakage == "knot_too_few_v":
        d["knots_v"] = d["knots_v"][1:]
    elif breakage == "decreasing_u":
        k = d["knots_u"]
        k[4], k[5] = 0.9, 0.2  # same length, out of order
    elif breakage == "decreasing_v":
        d["knots_v"] = d["knots_v"][::-1]
    elif breakage == "zero_weight":
        d["weights"][2][1] = 0.0
    elif breakage == "negative_weight":
        d["weights"][0][0] = -1.0
    elif breakage == "bad_cp_shape":
        d["control_points"] = [[row[:2] for row in plane] for plane in d["control_points"]]
    with pytest.raises(ValueError):
        NurbsSurface.from_dict(d)
    with pytest.raises(ValueError):
        NurbsSurface(d["degree_u"], d["degree_v"], d["knots_u"], d["knots_v"],
                     np.asarray(d["control_points"], float), d["weights"])


# ---------------------------------------------------------------------------
# Rational basis
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("make", [lambda: random_surface(61), closed_surface])
def test_rational_basis_times_net_equals_evaluate(make):
    surf = make()
    rng = np.random.default_rng(61)
    u = np.concatenate([[0.0, 1.0, 0.0, 1.0], rng.uniform(0, 1, 300)])
    v = np.concatenate([[0.0, 0.0, 1.0, 1.0], rng.uniform(0, 1, 300)])
    R = rational_basis(surf.tensor(u, v), surf.weights)
    assert R.shape == (len(u), surf.shape[0] * surf.shape[1])
    np.testing.assert_allclose(R @ surf.control_points.reshape(-1, 3), surf.evaluate(u, v),
                               rtol=0, atol=1e-13)
    Rd = R.toarray()
    np.testing.assert_allclose(Rd.sum(axis=1), 1.0, rtol=0, atol=1e-13)
    assert Rd.min() >= 0
    # independent: R[r, i*nv+j] = w_ij N_i M_j / sum_kl w_kl N_k M_l
    Nu = reference_basis(u, surf.knots_u, surf.degree_u)
    Nv = reference_basis(v, surf.knots_v, surf.degree_v)
    num = np.einsum("ri,rj,ij->rij", Nu, Nv, surf.weights).reshape(len(u), -1)
    np.testing.assert_allclose(Rd, num / num.sum(axis=1, keepdims=True), rtol=0, atol=1e-14)


def test_rational_basis_does_not_modify_its_input():
    surf = random_surface(62)
    u = np.linspace(0, 1, 20)
    T = surf.tensor(u, u)
    before = T.toarray().copy()
    rational_basis(T, surf.weights)
    np.testing.assert_array_equal(T.toarray(), before)


def test_evaluate_no_points_gives_empty_array():
    surf = random_surface(71)
    assert surf.evaluate(np.array([]), np.array([])).shape == (0, 3)


@pytest.mark.parametrize("seed", [0, 1])
def test_restricted_surface_is_the_same_surface_on_the_sub_domain(seed):
    """Restriction by knot insertion is exact, keeps the net size (a span lost at the
    ends is given back inside) and keeps the weights positive."""
    rng = np.random.default_rng(seed)
    surf = NurbsSurface(3, 2, clamped_knots(7, 3, np.array([0.2, 0.5, 0.7])), clamped_knots(5, 2, np.array([0.3, 0.6])),
                        rng.normal(size=(7, 5, 3)), rng.uniform(0.5, 2.0, (7, 5)))
    part = surf.restricted((0.25, 0.9), (0.1, 0.65))  # drops the inner knot 0.2 of u
    assert part.shape == surf.shape and np.all(part.weights > 0)
    u, v = rng.random((2, 200))
    np.testing.assert_allclose(part.evaluate(u, v), surf.evaluate(0.25 + 0.65 * u, 0.1 + 0.55 * v), atol=1e-12)
    assert part.domain_u == (0.0, 1.0) and part.domain_v == (0.0, 1.0)


def test_restricted_quarter_circle_is_a_shorter_arc_with_the_circle_invariant():
    """Half of the quarter cylinder's arc (0 to 45 degrees) is again an exact rational
    quadratic, whose shape factor w1 / sqrt(w0 w2) is cos(22.5 degrees)."""
    surf = extrude(QUARTER_PTS, QUARTER_W, QUARTER_KNOTS, 2)
    half = surf.restricted((0.0, 0.5))
    p = half.evaluate(*np.random.default_rng(2).random((2, 500)))
    np.testing.assert_allclose(np.hypot(p[:, 0], p[:, 1]), 1.0, atol=1e-14)
    assert np.arctan2(p[:, 1], p[:, 0]).max() <= np.pi / 4 + 1e-12
    w = half.weights[:, 0]
    np.testing.assert_allclose(w[1] / np.sqrt(w[0] * w[2]), np.cos(np.pi / 8), atol=1e-12)


def test_a_closed_direction_cannot_be_restricted():
    surf = extrude(QUARTER_PTS, QUARTER_W, QUARTER_KNOTS, 2)
    closed = NurbsSurface(surf.degree_u, surf.degree_v, surf.knots_u, surf.knots_v, surf.control_points,
                          surf.weights, closed_u=True)
    with pytest.raises(ValueError, match="closed"):
        closed.restricted((0.1, 0.9))

"""Trim loops: the closed-curve fit, inside tests, contours, the trimmed mesh and the
distances to a trimmed face, against answers known in closed form."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import open_surface

from psonurbs.geometry import raster
from psonurbs.geometry.contour import contours, simplify_closed
from psonurbs.geometry.trim import (
    Trim,
    TrimLoop,
    crossing,
    distances_to_boundary,
    distances_to_face,
    fit_closed_curve,
    inside,
    polygon_loop,
    signed_area,
    trimmed_mesh,
)


def circle(centre, radius, n=400, clockwise=False):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    if clockwise:
        t = -t
    return np.c_[centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)]


def plate_trim():
    outer = fit_closed_curve(circle((0.5, 0.5), 0.45), 24)
    hole = fit_closed_curve(circle((0.35, 0.5), 0.1, clockwise=True), 12)
    return Trim((outer, hole))


def test_closed_cubic_reproduces_a_circle_closely_and_closes_c1():
    loop = fit_closed_curve(circle((0.5, 0.5), 0.3), 16)
    p = loop.polygon(2000)
    r = np.hypot(p[:, 0] - 0.5, p[:, 1] - 0.5)
    assert np.abs(r - 0.3).max() < 2e-4  # 16 cubic spans on a circle: the error is O(h^4)
    cp = loop.control_points
    assert np.array_equal(cp[0], cp[-1])
    assert np.allclose(cp[1] - cp[0], cp[-1] - cp[-2])  # C1 where it closes
    assert signed_area(p) == pytest.approx(np.pi * 0.09, rel=1e-4)


def test_control_points_clamped_and_snapped_to_the_domain():
    square = np.array([[-0.1, -0.1], [1.1, -0.1], [1.1, 1.1], [-0.1, 1.1]])
    dense = np.concatenate([np.linspace(a, b, 50, endpoint=False) for a, b in zip(square, np.roll(square, -1, 0))])
    loop = fit_closed_curve(dense, 16, bounds=((0.0, 1.0), (0.0, 1.0)), snap=(0.05, 0.05))
    p = loop.polygon(4000)
    assert p.min() >= -1e-12 and p.max() <= 1.0 + 1e-12  # convex hull property
    assert np.isin(loop.control_points, [0.0, 1.0]).any(axis=1).all()  # each on a side
    # so the loop runs along the square, its corners rounded within about a control-point step
    away = np.min([np.hypot(*(p - c).T) for c in [(0, 0), (1, 0), (1, 1), (0, 1)]], axis=0) > 0.45
    assert np.abs(np.minimum(p[away], 1.0 - p[away]).min(axis=1)).max() < 1e-12


def test_polygon_loop_passes_through_its_vertices():
    poly = np.array([[0.1, 0.1], [0.9, 0.2], [0.6, 0.8], [0.2, 0.7]])
    loop = polygon_loop(poly)
    seg = np.hypot(*(np.roll(poly, -1, 0) - poly).T)
    t = np.r_[0, np.cumsum(seg)[:-1]] / seg.sum()
    assert np.allclose(loop.evaluate(t), poly, atol=1e-14)
    assert loop.degree == 1


def test_inside_even_odd_with_a_hole_and_on_the_domain_edge():
    trim = plate_trim()
    q = np.array([[0.5, 0.5], [0.35, 0.5], [0.02, 0.02], [0.8, 0.5], [0.5, 0.949]])
    assert trim.contains(q).tolist() == [True, False, False, True, True]
    # the banded test agrees with the brute-force one on random points
    rng = np.random.default_rng(3)
    pts = rng.random((3000, 2))
    polys = trim.polygons()
    brute = np.zeros(len(pts), bool)
    for p in polys:
        a, b = p, np.roll(p, -1, 0)
        x, y = pts[:, :1], pts[:, 1:]
        cr = (a[:, 1] > y) != (b[:, 1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xs = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        brute ^= (np.sum(cr & (x < xs), axis=1) % 2) == 1
    assert np.array_equal(inside(polys, pts), brute)


def test_crossing_finds_a_figure_eight_and_touching_loops():
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    eight = np.c_[np.sin(t), np.sin(t) * np.cos(t)]
    assert crossing([eight])
    assert not crossing([circle((0, 0), 1), circle((0, 0), 0.5, clockwise=True)])
    assert crossing([circle((0, 0), 1), circle((0.6, 0), 0.5, clockwise=True)])
    # edges in a row on one line, apart (a loop clamped along the domain's edge): not a touch; overlapping: one
    run = np.array([[0.0, 0.0], [0.3, 0.0], [0.5, 0.0], [0.8, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert not crossing([run])
    assert crossing([np.array([[0.0, 0.0], [0.6, 0.0], [0.5, 0.2], [0.4, 0.0], [1.0, 0.0], [1.0, 1.0]])])


def test_json_round_trip_and_validation():
    trim = plate_trim()
    again = Trim.from_list(trim.to_list())
    assert all(np.array_equal(a.control_points, b.control_points) and np.array_equal(a.knots, b.knots)
               for a, b in zip(trim.loops, again.loops))
    assert Trim.from_list(None) is None and Trim.from_list([]) is None
    with pytest.raises(ValueError, match="not closed"):
        TrimLoop(1, [0, 0, 0.5, 1, 1], [[0, 0], [1, 0], [1, 1]])


def test_contours_of_an_annulus_are_its_two_circles_oriented():
    x = y = np.linspace(-1.5, 1.5, 301)
    r = np.hypot(*np.meshgrid(x, y, indexing="ij"))
    loops = contours(np.abs(r - 0.8), x, y, 0.3)
    areas = sorted(signed_area(p) for p in loops)
    assert len(loops) == 2
    assert areas[0] == pytest.approx(-np.pi * 0.25, rel=2e-3)  # the hole r = 0.5, clockwise
    assert areas[1] == pytest.approx(np.pi * 1.21, rel=2e-3)  # the outer r = 1.1, counter-clockwise
    simple = simplify_closed(loops[0], 1e-3)
    assert len(simple) < len(loops[0]) and len(simple) >= 8
    fixed = np.zeros(len(loops[0]), bool)
    fixed[1::7] = True  # vertices a loose tolerance would drop are kept when fixed
    loose = simplify_closed(loops[0], 0.5, fixed=fixed)
    assert len(simplify_closed(loops[0], 0.5)) < fixed.sum() <= len(loose)
    assert {tuple(q) for q in loops[0][fixed]} <= {tuple(q) for q in loose}


def test_trimmed_mesh_follows_the_loops():
    s = open_surface()
    trim = plate_trim()
    verts, tris, uv = trimmed_mesh(s, trim, 61, 61)
    assert np.allclose(s.evaluate(uv[:, 0], uv[:, 1]), verts)
    a, b, c = uv[tris[:, 0]], uv[tris[:, 1]], uv[tris[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    assert np.all(cross > 0)  # counter-clockwise in (u, v), as the untrimmed mesh
    area = 0.5 * cross.sum()
    exact = abs(signed_area(trim.loops[0].polygon(20000))) - abs(signed_area(trim.loops[1].polygon(20000)))
    assert area == pytest.approx(exact, rel=2e-3)  # no staircase: a grid-cell mask is off by ~1e-2
    # the mesh's boundary vertices lie on the loops
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    boundary = np.unique(unique[count == 1])
    dense = np.concatenate(trim.polygons(20000))
    from scipy.spatial import cKDTree
    assert cKDTree(dense).query(uv[boundary])[0].max() < 1e-4


def test_distances_to_the_trimmed_face():
    # a flat unit square z = 0 with a disc face: a point above the plane outside the
    # disc is at the distance to the rim, sqrt(z^2 + (rho - R)^2)
    from psonurbs.geometry.basis import clamped_knots
    from psonurbs.geometry.nurbs import NurbsSurface

    g = np.linspace(0, 1, 4)
    cp = np.stack([*np.meshgrid(g, g, indexing="ij"), np.zeros((4, 4))], axis=-1)
    plane = NurbsSurface(3, 3, clamped_knots(4, 3), clamped_knots(4, 3), cp, np.ones((4, 4)))
    disc = Trim((fit_closed_curve(circle((0.5, 0.5), 0.3, 2000), 64),))
    pts = np.array([[0.5, 0.5, 0.2], [0.95, 0.5, 0.1], [0.5, 0.05, 0.0]])
    uv, d = pts[:, :2], np.abs(pts[:, 2])
    got = distances_to_face(plane, disc, pts, uv, d)
    want = [0.2, np.hypot(0.1, 0.15), 0.15]
    assert np.allclose(got, want, atol=1e-5)
    assert np.allclose(distances_to_boundary(plane, disc, pts[:1]), np.hypot(0.2, 0.3), atol=1e-5)


@pytest.mark.skipif(not raster.COMPILED, reason="numba not installed")
def test_the_compiled_raster_marks_the_cells_the_numpy_reference_does(monkeypatch):
    rng = np.random.default_rng(3)
    corners = rng.random((400, 1, 2)) * [50.0, 30.0] - 3.0  # some past the raster's sides
    triangles = corners + rng.normal(0.0, 2.0, (400, 3, 2))
    triangles[0] = [[1.0, 1.0], [5.0, 1.0], [1.0, 5.0]]  # cell centres on its edges count as in
    compiled = raster.rasterised(triangles, 0.0, 0.5, 0.5, (90, 55))
    monkeypatch.setattr(raster, "COMPILED", False)
    reference = raster.rasterised(triangles, 0.0, 0.5, 0.5, (90, 55))
    np.testing.assert_array_equal(compiled, reference)
    assert 0 < reference.sum() < reference.size
    # the right triangle in cells: (2, 1), (10, 1), (2, 9); its legs and hypotenuse i + j = 11
    assert reference[2:11, 1].all() and reference[2, 1:10].all() and reference[6, 5]

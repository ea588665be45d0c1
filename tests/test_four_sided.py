"""The four-sided map (psonurbs.fitting.parameters.four_sided): a flattening with four
corners onto the unit square, its sides on the square's sides; any other footprint left
to the flattening's rectangle (psonurbs.fitting.parameters.intrinsic)."""
from __future__ import annotations

import numpy as np
import pytest
from test_intrinsic import cylinder_section, spherical_cap

from psonurbs.config import config_from_dict
from psonurbs.fitting.parameters import four_sided
from psonurbs.fitting.parameters import intrinsic as intrinsic_module
from psonurbs.fitting.parameters.coarse_to_fine import BARE_LIMIT, coarse_to_fine
from psonurbs.fitting.parameters.four_sided import SCALE, SmoothLoop, aligned, corners, outline, square_map
from psonurbs.fitting.parameters.intrinsic import (
    extended,
    geodesic_embedding,
    parametrise_intrinsic,
    rigid_embedding,
    surface_graph,
)
from psonurbs.fitting.parameters.parametrisation import FILL_MARGIN, fill, fill_cells, unit_square
from psonurbs.fitting.pipeline import fit_points
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.projection import closest_parameters


def cone_sector(n=3000, degrees=270.0, seed=0):
    """Area-uniform points of a cone sector, radius 0.5 -> 1 over height 1, and their
    (angle share, ruling share) in [0, 1]^2."""
    rng = np.random.default_rng(seed)
    u = rng.random(n)
    v = (np.sqrt(0.25 + 0.75 * rng.random(n)) - 0.5) / 0.5  # the density grows with the radius
    a, r = np.radians(degrees) * u, 0.5 + 0.5 * v
    return np.column_stack([r * np.cos(a), r * np.sin(a), v]), np.column_stack([u, v])


def annular_sector(n=3000, degrees=120.0, radii=(1.0, 2.0), seed=0):
    """Area-uniform plane points of an annular sector and their (angle, radius) shares."""
    rng = np.random.default_rng(seed)
    r0, r1 = radii
    r = np.sqrt(r0 ** 2 + (r1 ** 2 - r0 ** 2) * rng.random(n))
    a = np.radians(degrees) * rng.random(n)
    return np.column_stack([r * np.cos(a), r * np.sin(a)]), np.column_stack([a / np.radians(degrees),
                                                                              (r - r0) / (r1 - r0)])


def affine_misfit(uv, truth):
    """For each of u and v: the largest and the root mean square residual of the affine
    function of one truth coordinate that fits it best, and which one that is."""
    out = []
    for k in range(2):
        fits = []
        for j in range(2):
            design = np.column_stack([truth[:, j], np.ones(len(uv))])
            residual = design @ np.linalg.lstsq(design, uv[:, k], rcond=None)[0] - uv[:, k]
            fits.append((float(np.abs(residual).max()), float(np.sqrt(np.mean(residual ** 2))), j))
        out.append(min(fits))
    return out


def random_footprint(name, n=3000, seed=0):
    """Plane points filling a shape uniformly."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1.0, 1.0, (8 * n, 2))
    r, a = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0])
    inside = {
        "rectangle": np.abs(p[:, 1]) < 1.0 / 3.0,
        "trapezoid": np.abs(p[:, 1]) < 0.3 * (1.0 + 0.5 * p[:, 0]),
        "annular sector": (r > 0.5) & (r < 1.0) & (a > 0.1) & (a < 2.8),
        "disc": r < 1.0,
        "ellipse": np.hypot(p[:, 0], 2.0 * p[:, 1]) < 1.0,
        "five-pointed star": r < 0.55 + 0.45 * np.cos(5.0 * a),
        "L": (p[:, 0] < 0.0) | (p[:, 1] < 0.0),
        "triangle": (p[:, 1] > -0.8) & (p[:, 1] < 1.0 - 2.0 * np.abs(p[:, 0])),
    }[name]
    return p[inside][:n]


@pytest.mark.parametrize("name, four", [("rectangle", True), ("trapezoid", True), ("annular sector", True),
                                        ("disc", False), ("ellipse", False), ("five-pointed star", False),
                                        ("L", False), ("triangle", False)])
@pytest.mark.parametrize("seed", [0, 1])
def test_four_corners_are_found_on_a_ragged_random_boundary(name, four, seed):
    """The alpha shape's boundary of a random sample is ragged at the scale of a spacing;
    at the scale of several spacings only real corners turn 45 degrees or more. A
    rectangle, a trapezoid and an annular sector have four convex ones; a disc and an
    ellipse none; a star, an L and a triangle other counts."""
    x = random_footprint(name, seed=seed)
    found = outline(x)
    h = SCALE * found.spacing
    where = corners(SmoothLoop.of(x[found.loop], h / 3.0, h / 12.0), h)
    assert where.four_sided == four, (name, np.degrees(where.turning).round())
    if four:
        assert np.all(np.degrees(where.turning) > 50.0)


def graded_footprint(name, n=3000, fold=20.0, seed=0):
    """Plane points filling a shape with a density rising ``fold``-fold along x (an
    annular sector: along its angle), as a scan's falls with range."""
    rng = np.random.default_rng(seed)
    t = np.log1p(rng.random(40 * n) * (fold - 1.0)) / np.log(fold)  # the inverse of an exponential CDF
    if name == "annular sector":
        r = np.sqrt(0.36 + 0.64 * rng.random(n))
        a = np.radians(300.0) * t[:n]
        return np.column_stack([r * np.cos(a), r * np.sin(a)])
    p = np.column_stack([2.0 * t - 1.0, rng.uniform(-1.0, 1.0, 40 * n)])
    inside = {"rectangle": np.abs(p[:, 1]) < 1.0 / 3.0,
              "disc": np.hypot(p[:, 0], p[:, 1]) < 1.0,
              "triangle": (p[:, 1] > -0.8) & (p[:, 1] < 1.0 - 2.0 * np.abs(p[:, 0])),
              "triangle, sparse tip": (-p[:, 0] > -0.8) & (-p[:, 0] < 1.0 - 2.0 * np.abs(p[:, 1]))}[name]
    return p[inside][:n]


@pytest.mark.parametrize("name, four", [("annular sector", True), ("rectangle", True), ("disc", False),
                                        ("triangle", False), ("triangle, sparse tip", False)])
def test_a_corner_where_the_data_thin_out_is_found(name, four):
    """Where the density falls 20-fold, the sparse corners are rounded over a spacing of
    the sparse sampling and turn less than 45 degrees at the median spacing's scale: a
    sector or a rectangle then showed three corners on some draws. Measured at its own
    spacing, the fourth is found on every draw; a disc or a triangle gains none."""
    for seed in range(6):
        square, turns = square_map(graded_footprint(name, seed=seed))
        assert (square is not None) == four, (name, seed, turns)


def test_an_annular_sector_maps_its_arcs_and_radii_onto_the_squares_sides():
    """In the plane, an annular sector (radii 1 and 2, 120 degrees) goes onto the square
    with its radii at u = 0 and 1 and its arcs at v = 0 and 1: u is the angle and v the
    radius, each up to an affine map, to 2% of the range at the ragged edge's worst point, and
    the points fill the square. Its minimum-area rectangle leaves a quarter empty."""
    x, truth = annular_sector()
    square, turns = square_map(x)
    assert square is not None, turns
    uv = square.place(x)
    (u_max, u_rms, u_is), (v_max, v_rms, v_is) = affine_misfit(uv, truth)
    assert (u_is, v_is) == (0, 1)  # u the angle, v the radius (the arcs are the longer sides)
    assert u_max < 0.02 and v_max < 0.02 and u_rms < 0.004 and v_rms < 0.004, (u_max, u_rms, v_max, v_rms)
    assert fill(uv, 16) > 0.97
    assert fill(unit_square(x), 16) < 0.8


@pytest.mark.parametrize("seed", range(6))
def test_the_inner_corners_of_a_c_shaped_sector_are_found(seed):
    """The inner arc of a C (an annular sector of radii 0.3 and 1 over 270 degrees: a
    helicoid laid flat) curves away from the chord its corners are read along: they turn
    42 to 49 degrees at h, one under ``CORNER`` on five draws of six. With the concave
    side's own turning added back they read 59 to 69 (the ragged sides' peaks 18 at most),
    all four are found, and the map puts the angle on u and the radius on v (the
    flattening's rectangle leaves a quarter of the square empty)."""
    x, truth = annular_sector(degrees=270.0, radii=(0.3, 1.0), seed=seed)
    square, turns = square_map(x)
    assert square is not None, turns
    uv = square.place(x)
    (u_max, u_rms, u_is), (v_max, v_rms, v_is) = affine_misfit(uv, truth)
    assert (u_is, v_is) == (0, 1)
    assert u_max < 0.03 and u_rms < 0.006 and v_max < 0.08 and v_rms < 0.015, (u_max, u_rms, v_max, v_rms)
    assert fill(uv, 16) > 0.97 and fill(unit_square(x), 16) < 0.75


def test_a_helicoid_laid_flat_goes_onto_the_square_by_its_four_sides():
    """1.5 turns of a helicoid, radii 0.2 to 1, noise 5e-4 of the diagonal: laid flat, a
    C whose inner corners read 36 and 33 degrees along its inner arc (the flattening's
    rectangle left 60% of the surface over no data). Found with the concave side's
    turning added back, the sheet goes onto the square by its four sides: under 5% of
    the untrimmed surface without data, and the true surface within half a noise sigma
    (rms) of the face."""
    from test_fit import config

    rng = np.random.default_rng(1)
    u, v = rng.random(4000), rng.random(4000)
    helicoid = lambda u, v: np.column_stack([(0.2 + 0.8 * v) * np.cos(3 * np.pi * u),  # noqa: E731
                                             (0.2 + 0.8 * v) * np.sin(3 * np.pi * u), 0.45 * u])
    truth = helicoid(u, v)
    sigma = 5e-4 * float(np.linalg.norm(np.ptp(truth, axis=0)))
    result = fit_points(truth + rng.normal(0.0, sigma, truth.shape),
                        config(orders=[4, 4], net_size=[12, 6], topology="open"))
    assert result.info["parametrisation"]["sides"] == "four", result.info["parametrisation"]["corners_degrees"]
    assert result.info["trim"]["empty_share"] < 0.05
    g = np.linspace(0.02, 0.98, 40)
    true_grid = helicoid(*(x.ravel() for x in np.meshgrid(g, g)))
    off = closest_parameters(result.surface, true_grid)[1]
    assert np.sqrt(np.mean(off ** 2)) < 0.5 * sigma, np.sqrt(np.mean(off ** 2)) / sigma


def test_a_cone_sectors_first_parameters_are_its_angle_and_its_ruling():
    """A 270-degree cone sector unrolls to an annular sector; its first parameters are its
    angle and its position along the ruling, each up to an affine map (to 2% of the range
    at the ragged edge's worst point, 0.4% in the mean). The rectangle of the flattening is
    47% of the range off the ruling."""
    pts, truth = cone_sector(seed=0)
    par = parametrise_intrinsic(pts)
    assert par.info["sides"] == "four", par.info
    assert par.info["fill_rectangle"] < 0.75 and par.info["fill_four_sided"] == 1.0
    (u_max, u_rms, u_is), (v_max, v_rms, v_is) = affine_misfit(par.uv, truth)
    assert {u_is, v_is} == {0, 1}
    angle, ruling = ((u_max, u_rms), (v_max, v_rms)) if u_is == 0 else ((v_max, v_rms), (u_max, u_rms))
    assert angle[0] < 0.03 and angle[1] < 0.006, angle
    assert ruling[0] < 0.04 and ruling[1] < 0.008, ruling
    graph = surface_graph(pts)
    flat = rigid_embedding(graph, geodesic_embedding(graph))
    before = unit_square(extended(graph, flat.positions, flat.rotations, pts), flat.positions[graph.component])
    assert max(affine_misfit(before, truth)[k][0] for k in range(2)) > 0.3


def test_a_graded_cone_sectors_parameters_are_its_angle_and_its_ruling():
    """The cone sector with its density rising 20-fold along the angle: on every draw its
    first parameters are still its angle and its ruling (the flattening's sparse corner,
    rounded by the sparse sampling, is found at its own spacing), to 3% and 7% of the
    range at the ragged edge's worst point, 0.6% and 0.8% in the mean."""
    for seed in range(4):
        rng = np.random.default_rng(seed)
        share = np.log1p(rng.random(3000) * 19.0) / np.log(20.0)  # the angle's density rises 20-fold
        v = (np.sqrt(0.25 + 0.75 * rng.random(3000)) - 0.5) / 0.5
        a, r = np.radians(270.0) * share, 0.5 + 0.5 * v
        par = parametrise_intrinsic(np.column_stack([r * np.cos(a), r * np.sin(a), v]))
        assert par.info["sides"] == "four", (seed, par.info["corners_degrees"])
        (u_max, u_rms, u_is), (v_max, v_rms, _) = affine_misfit(par.uv, np.column_stack([share, v]))
        angle, ruling = ((u_max, u_rms), (v_max, v_rms)) if u_is == 0 else ((v_max, v_rms), (u_max, u_rms))
        assert angle[0] < 0.03 and angle[1] < 0.006, (seed, angle)
        assert ruling[0] < 0.07 and ruling[1] < 0.008, (seed, ruling)


def test_a_rectangle_footprint_keeps_the_flattenings_rectangle():
    """A curl of 250 degrees unrolls to a rectangle, which fills its square: its sides are
    on the square's already, and the flattening's rectangle is kept, exactly. The four-
    sided map would be the rectangle but for the ragged edge (to 4% of the range at its
    worst point, 0.6% in the mean), in the same directions."""
    pts, _ = cylinder_section(n=3000, degrees=250.0)
    graph = surface_graph(pts)
    par = parametrise_intrinsic(pts, graph)
    assert par.info["sides"] == "rectangle" and len(par.info["corners_degrees"]) == 4, par.info
    assert par.info["fill_rectangle"] == 1.0
    flat = rigid_embedding(graph, geodesic_embedding(graph))
    today = unit_square(extended(graph, flat.positions, flat.rotations, pts), flat.positions[graph.component])
    np.testing.assert_array_equal(par.uv, today)
    square, _ = square_map(flat.positions[graph.component])
    gap = np.abs(aligned(square.place(extended(graph, flat.positions, flat.rotations, pts)), today) - today)
    assert gap.max() < 0.05 and np.sqrt(np.mean(gap ** 2)) < 0.007, (gap.max(), np.sqrt(np.mean(gap ** 2)))


@pytest.mark.parametrize("cloud", [spherical_cap, lambda: spherical_cap(polar_degrees=60.0, seed=4)])
def test_a_disc_footprint_is_left_to_the_flattenings_rectangle(cloud):
    """A cap unrolls to a disc, which has no corners: its parameters are the flattening's
    rectangle, exactly."""
    pts = cloud()
    graph = surface_graph(pts)
    par = parametrise_intrinsic(pts, graph)
    assert par.info["sides"] == "free" and par.info["corners_degrees"] == []
    flat = rigid_embedding(graph, geodesic_embedding(graph))
    today = unit_square(extended(graph, flat.positions, flat.rotations, pts), flat.positions[graph.component])
    np.testing.assert_array_equal(par.uv, today)


def test_a_four_sided_map_that_folds_gives_way_to_the_flattening(monkeypatch):
    """Where the four-sided map would fold more than the flattening (here: made to, by
    mirroring v on the middle third of u, which still fills the square), the flattening's
    rectangle is kept, and the fold is recorded."""
    def folding(x):
        square, turns = square_map(x)
        uv = square.uv.copy()
        band = (uv[:, 0] > 1.0 / 3.0) & (uv[:, 0] < 2.0 / 3.0)
        uv[band, 1] = 1.0 - uv[band, 1]
        return four_sided.SquareMap(square.outline, square.x, uv, square.jacobians), turns

    pts, _ = cone_sector(n=1500)
    monkeypatch.setattr(intrinsic_module, "square_map", folding)
    graph = surface_graph(pts)
    par = parametrise_intrinsic(pts, graph)
    assert par.info["sides"] == "free" and par.info["four_sided_folded_share"] > 0.1
    flat = rigid_embedding(graph, geodesic_embedding(graph))
    today = unit_square(extended(graph, flat.positions, flat.rotations, pts), flat.positions[graph.component])
    np.testing.assert_array_equal(par.uv, today)


def test_four_sided_parameters_skip_coarse_nets_that_cannot_hold_the_shape():
    """On the cone sector's own net (orders 3 x 2, 7 x 2 control points) the ladder's single
    quadratic Bezier patch cannot bend round 270 degrees: its foot points crowd the
    parameters into part of the square, and they fit 5 times farther than the four-sided
    parameters corrected on that net alone, which fill the square and are kept."""
    pts, _ = cone_sector(n=2000)
    pts = (pts - pts.mean(axis=0)) / np.linalg.norm(np.ptp(pts, axis=0))
    par = parametrise_intrinsic(pts)
    uv, report = coarse_to_fine(NetLayout((7, 2), (2, 1)), pts, par.uv, 1e-6)
    ladder, direct = report[-2], report[-1]
    assert direct["direct"] and direct["net"] == [7, 2]
    assert direct["rmse"] < ladder["rmse"] / 5.0, report
    assert ladder["fill"] < 0.7 and direct["fill"] == 1.0, report
    assert fill(uv, fill_cells(len(uv))) == 1.0


def s_fold(n=2000, noise=0.002, seed=0, ratio=1.0):
    """A sheet whose cross-section is an S of two 230-degree arcs of radius 0.5 turning
    opposite ways, extruded 1.5 along y (no plane sees it as a height field), normalised;
    its density rising ``ratio``-fold along the S."""
    rng = np.random.default_rng(seed)
    sweep, radius = np.radians(230.0), 0.5
    share = rng.random(n)  # t in [0, 1] of density 1 + (ratio - 1) t, by its inverse cumulative
    t = share if ratio == 1.0 else (np.sqrt(1.0 + (ratio ** 2 - 1.0) * share) - 1.0) / (ratio - 1.0)
    s, y = 2.0 * sweep * t, 1.5 * rng.random(n)
    first = s < sweep
    angle = np.where(first, s - sweep, np.pi - (s - sweep))
    p = np.column_stack([np.where(first, -radius, radius) + radius * np.cos(angle), y, radius * np.sin(angle)])
    p += noise * rng.normal(size=p.shape)
    return (p - p.mean(axis=0)) / np.linalg.norm(np.ptp(p, axis=0))


@pytest.mark.parametrize("seed", [0, 2])
def test_a_rectangle_flattening_keeps_the_square_filled_when_coarse_nets_cannot_bend_round(seed):
    """An S fold flattens to a rectangle that fills the square; the ladder's bicubic Bezier
    patch cannot follow two 230-degree arcs, and its foot points leave 5% of the square
    without data (the fine net extrapolates there). The parameters corrected on the
    configured 12 x 6 net alone fill the square, and they are kept."""
    pts = s_fold(seed=seed)
    par = parametrise_intrinsic(pts)
    assert par.info["sides"] == "rectangle"
    uv, report = coarse_to_fine(NetLayout((12, 6), (3, 3)), pts, par.uv, 1e-6)
    assert report[-2]["fill"] < 0.96 and report[-1]["direct"], report
    assert fill(uv, fill_cells(len(uv))) == 1.0


def test_a_flattening_is_corrected_directly_where_the_ladder_leaves_surface_over_no_data():
    """A graded S fold (density rising 20-fold along it): the ladder keeps nearly as much of
    the square filled as the first parameters (within the fill's margin), but the fine
    net's surface runs over no data on 4.8% of it (a side of the data bent off the
    square's side). The parameters corrected on the configured net alone leave none, and
    they are kept."""
    pts = s_fold(seed=8, ratio=20.0)
    par = parametrise_intrinsic(pts)
    uv, report = coarse_to_fine(NetLayout((12, 6), (3, 3)), pts, par.uv, 1e-6)
    ladder, direct = report[-2], report[-1]
    assert ladder["fill"] + FILL_MARGIN > fill(par.uv, fill_cells(len(par.uv))), report  # the fill alone: no
    assert ladder["bare"] > BARE_LIMIT and direct["direct"] and direct["bare"] == 0.0, report
    assert fill(uv, fill_cells(len(uv))) == direct["fill"]


def test_the_cone_sector_is_fitted_to_its_exact_surface():
    """End to end on the cone sector's small net (a rational quadratic by a linear patch
    holds it exactly) with a one-particle swarm: within 5e-4 of the diagonal, and the
    surface has data nearly all over (a fit over the flattening's rectangle: 2e-3, with
    half of the surface past the data). Laid flat by its own geometry, the sheet is
    trimmed to its data under ``trim: auto``: every point on the face, which nowhere
    reaches past the true sector's edges by half a point spacing."""
    pts, _ = cone_sector(n=2000, seed=1)
    config = config_from_dict({"orders": [3, 2], "net_size": [7, 2], "topology": "open",
                               "parametrisation": "intrinsic", "swarm": {"particles": 1, "iterations": 1}})
    result = fit_points(pts, config)
    assert result.metrics["rmse_relative"] < 5e-4, result.metrics["rmse_relative"]
    trim = result.info["trim"]
    assert trim["trimmed"] and trim["points_outside"] == 0 and trim["empty_share"] < 0.05, trim
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201), indexing="ij"), -1).reshape(-1, 2)
    (u0, u1), (v0, v1) = result.surface.domain_u, result.surface.domain_v
    uv = np.column_stack([u0 + (u1 - u0) * grid[:, 0], v0 + (v1 - v0) * grid[:, 1]])
    x, y, z = result.surface.evaluate(uv[:, 0], uv[:, 1]).T
    angle = np.mod(np.arctan2(y, x) + np.pi / 4, 2 * np.pi) - np.pi / 4  # the gap's middle (-45 degrees) the cut
    past = np.maximum.reduce([np.hypot(x, y) * (angle - np.radians(270.0)), np.hypot(x, y) * -angle, z - 1.0, -z,
                              np.zeros_like(z)])  # how far past the sector's edges, along the surface
    spacing = np.sqrt(np.radians(270.0) * 0.75 * np.sqrt(1.25) / len(pts))  # of the area-uniform points
    on_face = result.trim.contains(uv)
    assert past[on_face].max() < 0.5 * spacing, past[on_face].max() / spacing

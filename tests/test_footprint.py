"""The footprint of a fit's parameters as trim loops: holes found, a full rectangle left
whole, uneven density and stray pieces handled, the loops near the true boundary."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from psonurbs.fitting.finish import footprint as footprint_module
from psonurbs.fitting.finish.footprint import footprint, footprint_notes, well_spread
from psonurbs.fitting.prepare.robust_weights import Verdict
from psonurbs.geometry.basis import clamped_knots
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.trim import distances_to_face, signed_area


def plane(size=(2.0, 1.5)) -> NurbsSurface:
    g = np.linspace(0, 1, 4)
    uu, vv = np.meshgrid(g, g, indexing="ij")
    cp = np.stack([size[0] * uu, size[1] * vv, 0.1 * uu * vv], axis=-1)
    return NurbsSurface(3, 3, clamped_knots(4, 3), clamped_knots(4, 3), cp, np.ones((4, 4)))


def plate_region(u, v):
    inside = ((u - 0.5) / 0.47) ** 2 + ((v - 0.5) / 0.4) ** 2 < 1.0
    hole1 = (u - 0.3) ** 2 + (v - 0.5) ** 2 < 0.1 ** 2
    hole2 = (u - 0.7) ** 2 + (v - 0.55) ** 2 < 0.07 ** 2
    return inside & ~hole1 & ~hole2


def sample(region, n, seed=0, density=None):
    rng = np.random.default_rng(seed)
    uv = rng.random((12 * n, 2))
    keep = region(uv[:, 0], uv[:, 1])
    if density is not None:
        keep &= rng.random(len(uv)) < density(uv[:, 0], uv[:, 1])
    return uv[keep][:n]


def fit_footprint(uv, mode="auto", surface=None):
    surface = surface or plane()
    points = surface.evaluate(uv[:, 0], uv[:, 1])
    return footprint(surface, points, uv, np.full(len(uv), 1e-4), mode)


@pytest.mark.parametrize("density", [None, lambda u, v: 0.15 + 0.85 * u], ids=["uniform", "graded"])
def test_a_plate_with_two_holes_gets_three_loops(density):
    uv = sample(plate_region, 4000, density=density)
    face = fit_footprint(uv)
    assert face.trim is not None and face.loops == 3
    areas = [signed_area(p) for p in face.trim.polygons()]
    assert areas[0] > 0 and areas[1] < 0 and areas[2] < 0  # outer counter-clockwise, holes clockwise
    assert face.points_outside == 0
    assert np.all(face.distances == 1e-4)  # every point on the face keeps its distance
    # the face is the region within a few spacings: its area close to the true one
    true = np.pi * (0.47 * 0.4 - 0.1 ** 2 - 0.07 ** 2)
    got = areas[0] + areas[1] + areas[2]
    assert got == pytest.approx(true, rel=0.06)
    # the loops stay in the domain
    assert all(-1e-8 <= p.min() and p.max() <= 1 + 1e-8 for p in face.trim.polygons())


def test_a_cloud_that_fills_its_rectangle_stays_whole_under_auto():
    uv = sample(lambda u, v: np.ones_like(u, bool), 3000, seed=2)
    assert fit_footprint(uv).trim is None
    assert fit_footprint(uv, mode=False).trim is None
    forced = fit_footprint(uv, mode=True)
    assert forced.trim is not None and forced.loops == 1
    assert forced.points_outside <= 3  # at most a few hull points whose triangles are all slivers
    assert forced.empty_share < 0.02


def test_points_on_the_domain_edge_are_inside_the_face():
    uv = sample(lambda u, v: v < 0.6 + 0.3 * u, 3000, seed=5)
    uv[uv[:, 0] < 0.01, 0] = 0.0  # foot points held on the edges
    uv[uv[:, 1] < 0.01, 1] = 0.0
    face = fit_footprint(uv)
    assert face.trim is not None and face.loops == 1
    assert face.trim.contains(uv).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_plate_touching_the_domain_edge_at_single_points_holds_them(seed):
    # a convex plate whose parameters span the domain: its extreme points are held on the
    # edges, where the contour touches the domain only along a short run (no margin past them)
    uv = sample(lambda u, v: (u - 0.5) ** 2 + (v - 0.5) ** 2 < 0.25, 4000, seed=seed)
    for k in (0, 1):
        uv[np.argmin(uv[:, k]), k], uv[np.argmax(uv[:, k]), k] = 0.0, 1.0
    face = fit_footprint(uv)
    assert face.trim is not None and face.loops == 1
    assert face.trim.contains(uv).all() and face.points_outside == 0


def test_a_detached_fragment_is_left_off_the_face_and_counted():
    main = sample(lambda u, v: (u < 0.6) & (v < 0.8), 3000, seed=7)
    rng = np.random.default_rng(8)
    fragment = 0.85 + 0.05 * rng.random((60, 2))  # a separate patch, far from the main piece
    uv = np.concatenate([main, fragment])
    surface = plane()
    points = surface.evaluate(uv[:, 0], uv[:, 1])
    face = footprint(surface, points, uv, np.full(len(uv), 1e-4), "auto")
    assert face.loops == 1 and face.fragments == 1 and face.fragment_points == 60
    assert face.points_outside == 60
    off = ~face.trim.contains(uv)
    assert np.all(face.distances[off] > 0.05)  # measured to the face's boundary, far away
    notes = footprint_notes(face, len(uv))
    assert any("60 of 3060 points lie off the trimmed face" in n for n in notes)


def test_anisotropic_domain_uses_the_surface_metric():
    # a long strip: u spans 8 units, v 1; a hole round on the surface is thin in (u, v)
    surface = plane((8.0, 1.0))
    def region(u, v):
        return ((8 * (u - 0.5)) ** 2 + (v - 0.5) ** 2) > 0.2 ** 2
    uv = sample(region, 6000, seed=9)
    face = fit_footprint(uv, surface=surface)
    assert face.loops == 2


def ragged_outline(u, v):
    """A star-like outline (radius with three harmonics), no holes."""
    a = np.arctan2(v - 0.5, u - 0.5)
    r = 0.36 + 0.05 * np.sin(5 * a + 0.3) + 0.03 * np.sin(11 * a + 1.1) + 0.015 * np.sin(23 * a + 2.0)
    return np.hypot(u - 0.5, v - 0.5) < r


@pytest.mark.parametrize("seed", [3, 5])
def test_sampling_gaps_of_a_random_sample_are_not_holes(seed):
    # these two samples leave a sliver triangle wider than the alpha scale inside the
    # outline (each gave a spurious hole loop before small holes were covered)
    face = fit_footprint(sample(ragged_outline, 1500, seed=seed))
    assert face.trim is not None and face.loops == 1 and face.points_outside == 0


def test_a_big_footprint_drawn_from_a_well_spread_subsample_holds_every_point(monkeypatch):
    """12000 points of a rectangle with a hole (denser towards u = 0.6) and a detached
    patch of 200: the footprint drawn from some 2000 of them has the loops of that of all
    of them, every point of the face inside it (none lost between the subsample's
    boundary and the data's), the patch counted over every point."""
    def region(u, v):
        return (u < 0.6) & (v < 0.8) & ((u - 0.3) ** 2 + (v - 0.4) ** 2 > 0.12 ** 2)
    main = sample(region, 12000, seed=11, density=lambda u, v: 0.3 + 0.7 * u / 0.6)
    patch = 0.85 + 0.08 * np.random.default_rng(12).random((200, 2))
    uv = np.concatenate([main, patch])
    whole = fit_footprint(uv)
    monkeypatch.setattr(footprint_module, "FOOTPRINT_POINTS", 2000)
    drawn = fit_footprint(uv)
    assert whole.loops == drawn.loops == 2
    assert whole.fragments == drawn.fragments == 1 and whole.fragment_points == drawn.fragment_points == 200
    assert drawn.points_outside == 200 and 200 <= whole.points_outside <= 203  # (all: a few hull points too)
    assert drawn.trim.contains(main).all() and not drawn.trim.contains(patch).any()
    assert drawn.empty_share == pytest.approx(whole.empty_share, abs=0.01)
    assert drawn.spacing > 2 * whole.spacing  # the subsample's spacing


def test_a_well_spread_subsample_thins_the_dense_and_keeps_the_sparse():
    rng = np.random.default_rng(13)
    dense = rng.random((20000, 2)) * [0.5, 1.0]
    strays = [0.6, 0.0] + rng.random((30, 2)) * [0.4, 1.0]  # 30 points over the other half
    x = np.concatenate([dense, strays])
    kept = well_spread(x, 2000)
    assert np.all(np.diff(kept) > 0) and 1000 <= len(kept) <= 2500
    assert np.isin(np.arange(20000, 20030), kept).all()  # every stray (one per cell)
    np.testing.assert_array_equal(kept, well_spread(x, 2000))  # fixed


def test_a_face_finer_than_the_raster_leaves_the_surface_untrimmed():
    # two clusters 1e6 apart (a hostile input): the surface spans both, the face is one
    # cluster, which holds few of the points (and lies far below one cell of the
    # footprint's raster); no loops, not a crash
    from test_fit import config

    from psonurbs.fitting.pipeline import fit_points

    def bumps(seed):
        x, y = np.random.default_rng(seed).random((2, 60))
        return np.column_stack([x, y, 0.75 * np.exp(-((9 * x - 2) ** 2 + (9 * y - 2) ** 2) / 4)
                                + 0.5 * np.exp(-((9 * x - 7) ** 2) / 4)])

    pts = np.vstack([bumps(4), bumps(5) + 1e6])
    result = fit_points(pts, config(swarm={"particles": 4, "iterations": 3}, polish_iterations=5))
    assert result.info["trim"]["trimmed"] is False and result.info["trim"]["loops"] == 0
    assert np.all(np.isfinite(result.surface.control_points))


def test_a_face_that_holds_few_of_the_points_is_not_their_footprint():
    # the largest piece (by area) holds 120 of the 420 points, a dense cluster far from
    # it the other 300: the face would leave most points off it, so no trim; with the
    # cluster's share lower the same piece is the face
    rng = np.random.default_rng(3)
    spread = 0.05 + 0.4 * rng.random((120, 2))
    cluster = 0.8 + 0.03 * rng.random((300, 2))
    face = fit_footprint(np.vstack([spread, cluster]), mode=True)
    assert face.trim is None and face.loops == 0
    kept = fit_footprint(np.vstack([spread, cluster[:100]]), mode=True)
    assert kept.trim is not None and kept.fragment_points == 100


def stretched_at_the_end() -> NurbsSurface:
    """A flat sheet whose last knot span along u runs out to x = 6: the domain's last few
    hundredths of u are most of the surface (a strip of stretched surface past the data,
    as a fit's edge row of control points far out leaves it)."""
    nu, nv = 7, 4
    x = np.array([0.0, 0.33, 0.67, 1.0, 1.33, 1.67, 6.0])
    cp = np.stack(np.broadcast_arrays(x[:, None], np.linspace(0, 1.5, nv)[None, :], 0.0), axis=-1)
    return NurbsSurface(3, 3, clamped_knots(nu, 3), clamped_knots(nv, 3), cp.astype(float), np.ones((nu, nv)))


def test_a_strip_of_surface_past_the_data_is_trimmed_however_thin_in_the_domain():
    """The gap is measured on the surface, not in the domain: data on u < 0.9 leave a
    sliver of the domain empty (narrower than the alpha scale at the mean speed) that is
    a band of surface several units wide."""
    surface = stretched_at_the_end()
    near = sample(lambda u, v: u < 0.9, 3000, seed=4)
    face = fit_footprint(near, surface=surface)
    assert face.trim is not None and face.loops == 1
    assert face.points_outside <= 3  # at most a few hull points whose triangles are all slivers
    assert face.empty_share > 0.5  # the band from u = 0.9 to 1 is most of the surface


def test_residuals_of_a_near_exact_fit_along_an_edge_stay_on_the_face():
    """A noise-free fit's residuals are its approximation error: most points on the
    surface to 1e-6, a band along an edge (where the net bends least well) off it by
    1e-3, three orders of robust scale off but a thirtieth of the spacing. They lie in the
    data's layer, so the face holds them."""
    surface = plane()
    uv = sample(lambda u, v: np.ones_like(u, bool), 3000, seed=6)
    distances = np.full(len(uv), 1e-6)
    distances[uv[:, 1] < 0.05] = 1e-3
    face = footprint(surface, surface.evaluate(uv[:, 0], uv[:, 1]), uv, distances, True)
    assert face.trim is not None
    assert face.points_outside == 0
    assert np.array_equal(face.distances, distances)


def test_gross_outliers_far_off_the_surface_do_not_widen_the_face():
    """Junk far from the surface (its foot points in the empty corners of an elliptic
    plate) says nothing about where the data are: the face is the plate's, the junk off it."""
    surface = plane()
    uv = sample(lambda u, v: ((u - 0.5) / 0.47) ** 2 + ((v - 0.5) / 0.4) ** 2 < 1.0, 3000, seed=7)
    junk = np.random.default_rng(8).random((400, 2)) * 0.1  # in the corner u, v < 0.1, outside the plate
    both = np.vstack([uv, junk])
    distances = np.concatenate([np.full(len(uv), 1e-4), np.full(len(junk), 0.5)])
    face = footprint(surface, surface.evaluate(both[:, 0], both[:, 1]), both, distances, True)
    assert face.trim is not None
    assert face.trim.contains(uv).all()
    assert not face.trim.contains(junk).any()
    area = sum(signed_area(p) for p in face.trim.polygons())
    assert area == pytest.approx(np.pi * 0.47 * 0.4, rel=0.06)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_rectangle_whose_density_falls_fifty_fold_stays_whole_under_auto(seed):
    """A scan's density falls with range: its sparse end leaves sampling gaps many
    median spacings wide, as wide as its own spacing there. They are measured in the
    spacing of the data beside them, so the rectangle the data fill stays untrimmed."""
    uv = sample(lambda u, v: np.ones_like(u, bool), 3000, seed=seed, density=lambda u, v: 0.02 + 0.98 * u ** 2)
    assert fit_footprint(uv).trim is None


def outer_reach(face, side: int) -> float:
    """How far the face's outer loop reaches along u towards 0 (side 0) or 1 (side 1)."""
    polygon = face.trim.polygons()[0]
    return float(polygon[:, 0].min()) if side == 0 else float(polygon[:, 0].max())


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("strays", ["beyond_the_cut_off", "apart_within_it"])
def test_junk_just_past_an_edge_does_not_move_the_boundary(seed, strays):
    """Strays past the data's edge say nothing about where the data are: the face ends
    where the data end, as without them, and the strays lie off it. Twelve 2 to 8
    spacings past, off the surface by 12 to 19 noise sigmas: beyond the robust loss's
    cut-off, within a spacing (the surface was bent towards them). Or eight 3.5 to 6
    spacings past, each far from the others, 6 to 9.5 sigmas off (0.3 to 0.5 spacings):
    within the cut-off (a fit flared past the data passes near junk there), but apart
    from the data; taken as data, each held a spike of the face."""
    surface = plane()
    uv = sample(lambda u, v: u < 0.8, 3000, seed=seed)
    rng = np.random.default_rng(100 + seed)
    spacing = np.sqrt(0.8 / 3000)  # of the unit domain
    sigma = 0.05 * spacing * 2.0  # the plane is about 2 x 1.5 units: a twentieth of the spacing on it
    if strays == "beyond_the_cut_off":
        junk = np.column_stack([0.8 + rng.uniform(2, 8, 12) * spacing, rng.random(12)])
        off = rng.uniform(12, 19, len(junk)) * sigma
    else:
        junk = np.column_stack([0.8 + rng.uniform(3.5, 6, 8) * spacing, np.linspace(0.06, 0.94, 8)])
        off = rng.uniform(6, 9.5, len(junk)) * sigma
    both = np.vstack([uv, junk])
    distances = np.concatenate([np.abs(rng.normal(0, sigma, len(uv))), off])
    clean = footprint(surface, surface.evaluate(*uv.T), uv, distances[:len(uv)], True)
    face = footprint(surface, surface.evaluate(*both.T), both, distances, True)
    assert outer_reach(face, 1) == pytest.approx(outer_reach(clean, 1), abs=0.5 * spacing)
    assert not face.trim.contains(junk).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_doubted_points_on_the_surface_past_an_edge_do_not_move_the_boundary(seed):
    """Strays 5 to 8 spacings past the data's edge lying on the surface (at the noise
    level: the fit passes through them), doubted by the robust stage, mark no data: the
    face ends where the data end, as without them. Taken as data, they widen it."""
    surface = plane()
    uv = sample(lambda u, v: u < 0.8, 3000, seed=seed)
    rng = np.random.default_rng(200 + seed)
    spacing = np.sqrt(0.8 / 3000)
    sigma = 0.05 * spacing * 2.0
    junk = np.column_stack([0.8 + rng.uniform(5, 8, 40) * spacing, 0.3 + 0.4 * rng.random(40)])
    both = np.vstack([uv, junk])
    distances = np.abs(rng.normal(0, sigma, len(both)))
    doubted = np.arange(len(both)) >= len(uv)
    clean = footprint(surface, surface.evaluate(*uv.T), uv, distances[:len(uv)], True)
    face = footprint(surface, surface.evaluate(*both.T), both, distances, True, Verdict(doubted))
    taken = footprint(surface, surface.evaluate(*both.T), both, distances, True)
    assert outer_reach(face, 1) == pytest.approx(outer_reach(clean, 1), abs=0.5 * spacing)
    assert not face.trim.contains(junk).any()
    assert outer_reach(taken, 1) > outer_reach(clean, 1) + 3 * spacing


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_share_of_a_neighbourhood_the_data_fill(seed):
    """A uniform square: its points' neighbourhoods are full inside it (share 1, read
    within the scatter of 16 points' centroid), half full on its edges."""
    x = np.random.default_rng(seed).random((40000, 2))
    share = footprint_module.filled_share(x)
    inside = np.all((x > 0.1) & (x < 0.9), axis=1)
    on_edge = (x[:, 0] < 0.001) & (np.abs(x[:, 1] - 0.5) < 0.4)
    assert 0.88 <= share[inside].mean() <= 1.0
    assert np.median(share[inside]) == 1.0
    assert 0.45 <= np.median(share[on_edge]) <= 0.6


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_slot_three_spacings_wide_is_a_hole(seed):
    """A slot through the data, 3 spacings from its midline to either side and 24 long:
    the points along its rims fill half their neighbourhoods, and judged by the spacing
    they read across it (sqrt 2 too wide) the triangles across it passed the alpha test,
    bridging it. Judged by the data's spacing where the data are, the slot is a hole of
    the face: the face misses its middle, and holds every point."""
    n = 4000
    spacing = np.sqrt(1.0 / n)
    slot = lambda u, v: (np.abs(u - 0.5) < 12 * spacing) & (np.abs(v - 0.5) < 3 * spacing)  # noqa: E731
    uv = sample(lambda u, v: ~slot(u, v), n, seed=seed)
    face = fit_footprint(uv, mode="auto", surface=plane((1.0, 1.0)))
    assert face.trim is not None and face.loops == 2
    middle = np.column_stack([0.5 + np.linspace(-7, 7, 15) * spacing, np.full(15, 0.5)])
    assert not face.trim.contains(middle).any()  # the slot's ends are rounded by the alpha scale
    assert -signed_area(face.trim.polygons()[1]) >= 0.5 * 24 * 6 * spacing ** 2
    assert face.points_outside == 0


def curved_sheet() -> NurbsSurface:
    g = np.linspace(0, 1, 5)
    uu, vv = np.meshgrid(g, g, indexing="ij")
    net = np.stack([2.0 * uu, 1.5 * vv, 0.4 * np.sin(3 * uu) * (1 + vv)], axis=-1)
    return NurbsSurface(3, 3, clamped_knots(5, 3), clamped_knots(5, 3), net, np.ones((5, 5)))


def with_a_point_past_side_u1(surface, uv, past, v):
    """The points of the surface at uv (N, 2) and one more on its continuation about
    ``past`` beyond its side u = 1 at ``v``; their feet on the surface and distances."""
    speed = np.linalg.norm(surface.derivatives(np.array([1.0]), np.array([v]))[1])
    corner = surface.restricted((0.0, 1.0 + past / speed), (0.0, 1.0)).evaluate(np.array([1.0]), np.array([v]))
    points = np.vstack([surface.evaluate(*uv.T), corner])
    feet, distances = closest_parameters(surface, points, np.vstack([uv, [1.0, v]]))
    return points, feet, distances


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_side_is_carried_out_to_the_spared_corner_of_a_sparse_edge(seed):
    """A curved sheet's points thin out tenfold towards its side u = 1; one more of them, the
    lone corner of that sparse edge, lies two median spacings past the side beyond its last
    point (its foot held on the side), sampled like its neighbours. The robust stage spares it: the side is carried out
    to it, along the surface's own continuation, and the point is on the face; doubted, it
    stays off it, and so it does lifted off the continuation by a spacing (farther than
    the surface between samples is uncertain: junk beside the continuation)."""
    rng = np.random.default_rng(seed)
    surface = curved_sheet()
    uv = np.column_stack([1.0 - 0.9 * np.sqrt(rng.random(3000)), rng.random(3000)])  # density 10 -> 1 along u
    spacing = footprint_module.median_spacing(surface.evaluate(*uv.T))
    last = uv[np.argmax(uv[:, 0])]  # the edge's last point: the corner lies beyond it
    points, feet, distances = with_a_point_past_side_u1(surface, uv, 2.0 * spacing, last[1])
    assert feet[-1, 0] == 1.0 and distances[-1] > 1.5 * spacing  # held on the side, past it
    spared = np.ones(len(points), bool)
    face = footprint(surface, points, feet, distances, True, Verdict(np.zeros(len(points), bool), spared))
    assert face.surface is not surface and face.points_outside == 0
    assert face.distances[-1] < 1e-3 * spacing  # on the surface's own continuation
    doubted = np.arange(len(points)) == len(points) - 1
    left = footprint(surface, points, feet, distances, True, Verdict(doubted, spared & ~doubted))
    assert left.surface is surface and left.distances[-1] > 1.5 * spacing
    normal = np.cross(*surface.derivatives(feet[-1:, 0], feet[-1:, 1])[1:])[0]
    points[-1] += spacing * normal / np.linalg.norm(normal)
    feet[-1:], distances[-1:] = closest_parameters(surface, points[-1:], feet[-1:])
    off = footprint(surface, points, feet, distances, True, Verdict(np.zeros(len(points), bool), spared))
    assert off.surface is surface and off.distances[-1] > 1.5 * spacing


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_sparse_corner_judged_a_local_outlier_is_carried_to_when_the_surface_passes_through_it(seed):
    """The sparse edge's lone corner as above, judged a gross outlier by its neighbours
    (another turn of the sheet nearer than its own): the side is carried out to it,
    re-judged on the longer surface, which passes through it, and it is on the face.
    Lifted off the surface's continuation by half a spacing, it stays off."""
    rng = np.random.default_rng(seed)
    surface = curved_sheet()
    uv = np.column_stack([1.0 - 0.9 * np.sqrt(rng.random(3000)), rng.random(3000)])
    spacing = footprint_module.median_spacing(surface.evaluate(*uv.T))
    last = uv[np.argmax(uv[:, 0])]
    points, feet, distances = with_a_point_past_side_u1(surface, uv, 2.0 * spacing, last[1])
    outlying = np.arange(len(points)) == len(points) - 1
    verdict = Verdict(outlying, ~outlying, outlying)
    face = footprint(surface, points, feet, distances, True, verdict)
    assert face.surface is not surface and face.points_outside == 0
    assert face.distances[-1] < 1e-3 * spacing
    normal = np.cross(*surface.derivatives(feet[-1:, 0], feet[-1:, 1])[1:])[0]
    points[-1] += 0.5 * spacing * normal / np.linalg.norm(normal)
    foot, distance = closest_parameters(surface, points[-1:], feet[-1:])
    feet[-1], distances[-1] = foot[0], distance[0]
    off = footprint(surface, points, feet, distances, True, verdict)
    assert off.surface is surface and off.distances[-1] > 1.5 * spacing


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_local_outliers_the_fit_passes_through_mark_the_data(seed):
    """The last tenth of a sheet's data (u from 0.8 to 0.9) judged gross outliers by their
    neighbours (another turn of the sheet nearer than their own): on the fit at the noise
    level, they mark the data, and the face reaches them; 30 sigmas off it, they do not."""
    surface = plane()
    rng = np.random.default_rng(300 + seed)
    uv = sample(lambda u, v: u < 0.9, 3000, seed=seed)
    spacing = np.sqrt(0.9 / 3000)
    sigma = 0.05 * spacing * 2.0
    outlying = uv[:, 0] > 0.8
    distances = np.abs(rng.normal(0, sigma, len(uv)))
    verdict = Verdict(outlying, ~outlying, outlying)
    face = footprint(surface, surface.evaluate(*uv.T), uv, distances, True, verdict)
    assert outer_reach(face, 1) == pytest.approx(0.9, abs=spacing)
    distances[outlying] += 30 * sigma
    off = footprint(surface, surface.evaluate(*uv.T), uv, distances, True, verdict)
    assert outer_reach(off, 1) == pytest.approx(0.8, abs=spacing)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_spared_stray_apart_from_a_dense_edge_carries_no_side(seed):
    """Uniform points of the sheet and one more on its continuation 4 to 6 spacings past
    the side u = 1: spared (junk on the surface's continuation passes the local test), but
    it lies apart from the data beside it, farther than the alpha shape's scale of a
    sampling gap. No side is carried to it, and it stays off the face."""
    rng = np.random.default_rng(seed)
    surface = curved_sheet()
    uv = rng.random((3000, 2))
    spacing = footprint_module.median_spacing(surface.evaluate(*uv.T))
    points, feet, distances = with_a_point_past_side_u1(surface, uv, rng.uniform(4, 6) * spacing,
                                                        rng.uniform(0.3, 0.7))
    face = footprint(surface, points, feet, distances, True, Verdict(np.zeros(len(points), bool),
                                                                      np.ones(len(points), bool)))
    assert face.surface is surface and face.distances[-1] > 3.5 * spacing


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_sparse_end_of_a_graded_cloud_stays_covered(seed):
    """Data on u > 0.2, their density falling twentyfold towards that edge: the face
    reaches the data's true edge to within a quarter of its spacing there (the last
    points lie up to a spacing inside it), not of the median spacing, so the sparse
    end's last spacings are not left uncovered."""
    density = lambda u, v: 0.05 + 0.95 * (u - 0.2) / 0.8  # noqa: E731
    uv = sample(lambda u, v: u > 0.2, 3000, seed=seed, density=density)
    face = fit_footprint(uv)
    assert face.trim is not None
    local = np.sqrt(0.8 / 3000 / 0.05 * np.mean(0.05 + 0.95 * np.linspace(0, 1, 1001)))  # the spacing at u = 0.2
    assert outer_reach(face, 0) <= 0.2 + 0.1 * local
    assert outer_reach(face, 0) >= 0.2 - 0.6 * local  # and not far past it


def test_a_strip_where_the_surface_runs_past_the_data_along_an_edge_is_trimmed():
    """Data that fill the square but for a strip along part of its u = 1 edge (where a
    fit's surface grew past the data: three spacings deep, a fifth of the edge long) are
    trimmed back to the data there, though no disc of the alpha scale fits in the strip;
    the same cloud without the strip stays whole."""
    spacing = np.sqrt(1.0 / 4000)
    strip = lambda u, v: (u > 1 - 3 * spacing) & (np.abs(v - 0.5) < 0.1)  # noqa: E731
    uv = sample(lambda u, v: ~strip(u, v), 4000, seed=3)
    face = fit_footprint(uv)
    assert face.trim is not None and face.loops == 1
    assert not face.trim.contains(np.array([[1 - spacing, 0.5]]))[0]
    assert fit_footprint(sample(lambda u, v: np.ones_like(u, bool), 4000, seed=3)).trim is None


@pytest.mark.parametrize("seed", [0, 1])
def test_a_rectangle_filling_cloud_is_fitted_to_its_edges(seed):
    """A gentle height field sampled over the unit square, fitted end to end: where the
    delivered surface ends (its edges, or its loops when trimmed) lies within a spacing
    of the square's edges, on the surface, neither past them nor short of them."""
    from test_fit import config

    from psonurbs.fitting.pipeline import fit_points

    rng = np.random.default_rng(seed)
    xy = rng.random((2000, 2))
    pts = np.column_stack([xy, 0.2 * np.sin(2.5 * xy[:, 0]) * np.cos(1.5 * xy[:, 1])])
    result = fit_points(pts, config(orders=[4, 4], net_size=[6, 6], polish_iterations=20))
    spacing = np.sqrt(1.0 / len(pts))
    if result.trim is None:
        t = np.linspace(0, 1, 400)
        params = np.concatenate([np.column_stack([t, 0 * t]), np.column_stack([t, 0 * t + 1]),
                                 np.column_stack([0 * t, t]), np.column_stack([0 * t + 1, t])])
    else:
        params = np.concatenate(result.trim.polygons())
    boundary = result.surface.evaluate(*params.T)[:, :2]
    off_edge = np.abs(np.max(np.abs(boundary - 0.5), axis=1) - 0.5)  # past the square's edge or short of it
    assert off_edge.max() <= spacing


def test_the_sparse_end_of_a_graded_helicoid_is_on_the_face():
    """1.5 turns of a helicoid whose density rises twentyfold along the turns: the sparse
    end's last points have the next turn nearer than their own neighbours, and the local
    test reads two of them as gross outliers. Re-judged on the surface carried out to
    them, they are on the face or beside it: every point within a fifth of the sparse
    end's spacing of it (the surface stopped 1.6 such spacings short of them), and the
    true sparse edge within three quarters of a spacing (1.8)."""
    from test_fit import config

    from psonurbs.fitting.pipeline import fit_points

    rng = np.random.default_rng(0)
    u = (np.sqrt(1.0 + 399.0 * rng.random(4000)) - 1.0) / 19.0  # density 1 -> 20 along the turns
    angle, radius = 3.0 * np.pi * u, 0.3 + 0.7 * rng.random(4000)
    truth = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), 0.3 * angle / (2 * np.pi)])
    diagonal = float(np.linalg.norm(np.ptp(truth, axis=0)))
    pts = truth + rng.normal(0.0, 5e-4 * diagonal, truth.shape)
    result = fit_points(pts, config(orders=[4, 4], net_size=[12, 6], topology="open"))
    sparse = float(np.mean(cKDTree(pts).query(pts[np.argmin(u)], 7)[0][1:]))  # the spacing at the sparse end
    assert result.distances.max() < 0.2 * sparse
    edge = np.column_stack([np.linspace(0.3, 1.0, 50), np.zeros(50), np.zeros(50)])  # the true sparse edge
    uv, d = closest_parameters(result.surface, edge)
    off = d if result.trim is None else distances_to_face(result.surface, result.trim, edge, uv, d)
    assert off.max() < 0.75 * sparse


def test_a_triangle_is_judged_at_most_at_a_jump_times_its_densest_corner():
    """Without a jump in density on the surface a triangle is judged by its sparsest
    corner, but never wider than DENSITY_JUMP times its densest: one corner spread wide
    by the map (the outer side of a flattened curved strip, a lone point in the domain)
    does not let the triangle bridge the strip's concave side. Across a jump on the
    surface the densest corner's spacing counts."""
    jump = footprint_module.DENSITY_JUMP
    corners = np.array([[1.0, 1.2, 1.5], [1.0, 1.0, 10.0], [1.0, 1.0, 10.0]])
    density = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 3.0]])
    judged = footprint_module.judging_spacing(corners, density)
    np.testing.assert_allclose(judged, [1.5, jump, 1.0])


def test_a_point_cut_off_the_raster_face_is_joined_back_to_it():
    """Two pieces of a face raster, most points on the first, one point on a far blob (the
    rim triangles joining it were bowed off): after ``rejoined`` the raster is one piece
    holding every point, joined by a strip along the way to the nearest point."""
    from scipy import ndimage

    mask = np.zeros((60, 40), bool)
    mask[5:30, 5:30] = True
    mask[50:53, 30:33] = True
    cell = 0.1
    points = np.array([[1.0, 1.0], [2.0, 2.0], [2.5, 2.5], [5.15, 3.15]])  # (x, y) = (i, j) * cell
    footprint_module.rejoined(mask, points, 0.0, 0.0, cell)
    labels, count = ndimage.label(mask)
    assert count == 1
    assert mask[40, 28:30].any()  # on the segment from (5.15, 3.15) to (2.5, 2.5), at x = 4: y = 2.87
    assert mask.sum() < 25 * 25 + 9 + 4 * 40  # a strip, not a filled hull


def test_a_clamped_contour_loses_only_the_vertices_inside_its_runs_along_an_edge():
    """Vertices in a row on the domain's edge: the ones between their neighbours along it
    go (their segments would touch end to end), a vertex where the contour turns back
    along the edge stays, as do vertices off the edge."""
    lo, hi = np.array([0.0, 0.0]), np.array([1.0, 1.0])
    polygon = np.array([[0.5, 0.2], [1.0, 0.3], [1.0, 0.4], [1.0, 0.5], [1.0, 0.6], [0.6, 0.7],
                        [1.0, 0.8], [1.0, 0.9], [1.0, 0.85], [0.7, 0.95]])
    keep = footprint_module.not_between_on_an_edge(polygon, lo, hi)
    assert keep.tolist() == [True, True, False, False, True, True, True, True, True, True]


@pytest.mark.parametrize("bow", [0.0, 0.1])
def test_raster_cells_where_the_surface_bows_out_of_a_rim_triangle_are_dropped(bow):
    """One rim triangle with corners (0, 0), (1, 0.5), (0, 0.5) on the sheet
    S(u, v) = (u, v + 4 bow u (1 - u)): its corners are where they are in the plane, its
    long side's middle bows out by ``bow``. Cells of it farther than a cell's step
    sideways from the triangle through the corners are dropped; near the corners (bowed by
    less than a step) and on a flat sheet none."""
    from scipy.spatial import Delaunay

    from psonurbs.geometry.raster import rasterised

    cp = np.zeros((3, 2, 3))
    cp[:, :, 0] = np.array([0.0, 0.5, 1.0])[:, None]
    cp[:, :, 1] = np.array([0.0, 1.0])[None, :] + np.array([0.0, 2.0 * bow, 0.0])[:, None]
    surface = NurbsSurface(2, 1, clamped_knots(3, 2), clamped_knots(2, 1), cp, np.ones((3, 2)))
    corners = np.array([[0.0, 0.0], [1.0, 0.5], [0.0, 0.5]])
    far = 100.0 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    tri = Delaunay(np.concatenate([corners, far]))
    in_face = np.all(tri.simplices < 3, axis=1)
    cell = 0.01
    xs, ys = np.arange(-0.05, 1.06, cell), np.arange(-0.05, 0.56, cell)
    mask = rasterised(corners[None], xs[0], ys[0], cell, (len(xs), len(ys)))
    scale = np.array([1.0, 1.0])
    dropped = footprint_module.bent_off(surface, tri, in_face, mask, xs, ys, scale, cell)
    i, j = np.nonzero(dropped)
    if bow == 0.0:
        assert not dropped.any()
    else:
        assert dropped[np.argmin(np.abs(xs - 0.5)), np.argmin(np.abs(ys - 0.45))]  # the bowed middle
        assert np.all(np.minimum(xs[i], 1.0 - xs[i]) > 0.01)  # nothing at the corners' ends of the side
        assert dropped.sum() < mask.sum()

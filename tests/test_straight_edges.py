"""A cloud's straight edges: found where a plane cut the data, seen at a tilt too, no tilt
read into a graded edge's scatter; none on a disc; the face of a surface spreading past
one ends there, and a graded cloud's sparse end stays covered."""
from __future__ import annotations

import numpy as np

from psonurbs.config import config_from_dict
from psonurbs.fitting.finish.footprint import footprint, footprint_notes, median_spacing
from psonurbs.fitting.finish.straight_edges import straight_edges
from psonurbs.fitting.pipeline import fit_points
from psonurbs.geometry.basis import clamped_knots
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.trim import distances_to_face


def wavy_tile(n=3000, seed=0):
    """A height field on [0, 1]^2 cut along x = 0, x = 1, y = 0, y = 1."""
    x, y = np.random.default_rng(seed).random((2, n))
    return np.column_stack([x, y, 0.2 * np.sin(3 * np.pi * y) + 0.1 * x])


def tilted(degrees):
    a = np.radians(degrees)
    return np.array([np.sin(a), 0.0, np.cos(a)])


def test_a_tile_cut_by_planes_has_four_straight_edges_seen_at_a_tilt():
    points = wavy_tile()
    for view in (tilted(0), tilted(20)):
        edges = straight_edges(points, view, 2.5)
        assert edges is not None and len(edges.edges) == 4
        assert edges.beyond(points).max() <= 1e-12  # no point past an edge
        y = np.array([0.3, 0.7])
        z = 0.2 * np.sin(3 * np.pi * y)
        past = edges.beyond(np.column_stack([[1.02, 1.02], y, z + 0.1]))
        inside = edges.beyond(np.column_stack([[0.95, 0.95], y, z + 0.1]))
        # 0.02 past x = 1 across the view's plane (0.02 cos(tilt), 0.0188 at 20 degrees),
        # the edge's line within a spacing (0.018) of x = 1
        assert np.all(past > 0.012) and np.all(past < 0.03), past
        assert np.all(inside < 0)


def test_the_tilt_of_the_cut_is_what_keeps_a_tilted_view_of_a_wavy_edge_straight():
    """Seen at 20 degrees, the edge x = 1 of a surface whose height swings by 0.4 along it
    is a line in the plane only with its heights taken into account."""
    points = wavy_tile()
    edges = straight_edges(points, tilted(20), 2.5)
    cut = [e for e in edges.edges if abs(edges.axes[e[0]] @ [1.0, 0.0, 0.0]) > 0.9]
    assert len(cut) == 2 and all(abs(c) > 0.1 for *_, c in cut)  # both x edges lean with the heights


def test_a_disc_has_no_straight_edge():
    rng = np.random.default_rng(1)
    r, t = np.sqrt(rng.random(3000)), 2 * np.pi * rng.random(3000)
    points = np.column_stack([r * np.cos(t), r * np.sin(t), 0.05 * r ** 2])
    assert straight_edges(points, np.array([0.0, 0.0, 1.0]), 2.5) is None


def spreading_corner(spread=0.15):
    """A flat patch on [0, 2] x [0, 1.5] whose corner at u = v = 1 runs out to (2 + spread,
    1.5 + spread): the u^3 v^3 term of a bicubic Bezier patch is its last control point."""
    g = np.linspace(0, 1, 4)
    uu, vv = np.meshgrid(g, g, indexing="ij")
    cp = np.stack([2.0 * uu, 1.5 * vv, np.zeros_like(uu)], axis=-1)
    cp[3, 3, :2] += spread
    return NurbsSurface(3, 3, clamped_knots(4, 3), clamped_knots(4, 3), cp, np.ones((4, 4)))


def test_a_corner_spreading_past_the_data_s_straight_edges_is_cut_there():
    surface = spreading_corner(0.06)  # two spacings
    uv = np.random.default_rng(3).random((6000, 2))
    points = surface.evaluate(uv[:, 0], uv[:, 1])
    keep = (points[:, 0] <= 2.0) & (points[:, 1] <= 1.5)  # the data: the rectangle, cut straight
    uv, points = uv[keep][:3000], points[keep][:3000]
    distances = np.full(len(uv), 1e-4)
    whole = footprint(surface, points, uv, distances, "auto")
    face = footprint(surface, points, uv, distances, "auto", seen_along=np.array([0.0, 0.0, 1.0]))
    assert whole.trim is None  # no gap: without the straight edges the corner stays
    assert face.trim is not None and face.points_outside == 0
    assert not face.trim.contains(np.array([[1.0, 1.0], [0.99, 0.99]])).any()  # the corner is cut off
    spacing = np.sqrt(3.0 / len(points))
    rim = np.concatenate([surface.evaluate(*p.T) for p in face.trim.polygons()])
    reach = np.maximum(rim[:, 0] - points[:, 0].max(), rim[:, 1] - points[:, 1].max())
    assert reach.max() <= 0.5 * spacing  # the loop a margin past the edges, no farther
    assert face.empty_share < 0.02  # and the rest of the surface kept
    assert face.cut and face.to_dict()["cut"] and not whole.cut
    assert footprint_notes(face, len(points))[0].startswith("trimmed where the surface ran past the data's straight")


def graded_x(rng, n):
    """x on [-1, 1] of density 0.05 + u (u = (1 + x) / 2): 21-fold sparser at x = -1."""
    return -1.0 + 2.0 * (np.sqrt(0.0025 + 1.1 * rng.random(n)) - 0.05)


def graded_tile(n=3000, seed=0):
    """The wavy tile's heights on [-1, 1]^2, the density falling towards x = -1."""
    rng = np.random.default_rng(seed)
    x = graded_x(rng, n)
    y = rng.uniform(-1.0, 1.0, n)
    return np.column_stack([x, y, 0.2 * np.sin(1.5 * np.pi * y) + 0.1 * x])


def test_a_graded_edge_seen_square_does_not_lean_with_the_heights():
    """Seen square, the cut x = -1 of a cloud whose density falls towards it has its slices'
    outermost points scattered by their sampling; their chance correlation with the heights
    is not a tilt: every edge found stays the plain line (c = 0)."""
    for seed in range(10):
        points = graded_tile(seed=seed)
        edges = straight_edges(points, np.array([0.0, 0.0, 1.0]), 2.5)
        across_x = [e for e in edges.edges if abs(edges.axes[e[0]] @ [1.0, 0.0, 0.0]) > 0.9]
        assert len(across_x) == 2  # the sparse edge and the dense one
        assert all(c == 0.0 for *_, c in edges.edges), edges.edges


def test_a_graded_cloud_s_sparse_end_stays_covered():
    """A wave sampled with its density falling to nothing at x = -1 (two draws), fitted
    without a swarm: between the sparse last points the fit's edge bulges in (3.98 and
    5.04 median spacings of true surface left uncovered along x = -1 when the face only
    ended at the straight edges); carried to the edge and cut there, the true surface
    along it lies within 2.5 median spacings of the face."""
    def height(x, y):
        return 0.25 * np.sin(2.5 * x + 0.5) * np.cos(1.5 * y)

    cfg = config_from_dict({"orders": [4, 4], "net_size": [8, 8], "topology": "open",
                            "swarm": {"particles": 1, "iterations": 1}})
    ys = np.linspace(-0.95, 0.95, 200)
    truth = np.column_stack([np.full(200, -1.0), ys, height(-1.0, ys)])
    for seed in (1, 2):
        rng = np.random.default_rng(seed)
        x, y = -1.0 + 2.0 * np.sqrt(rng.random(4000)), rng.uniform(-1.0, 1.0, 4000)
        points = np.column_stack([x, y, height(x, y)])
        fit = fit_points(points, cfg)
        uv, cover = closest_parameters(fit.surface, truth)
        assert fit.trim is not None
        cover = distances_to_face(fit.surface, fit.trim, truth, uv, cover)
        assert cover.max() <= 2.5 * median_spacing(points), cover.max() / median_spacing(points)
        assert fit.metrics["outside_trim"] == 0  # every point on the face

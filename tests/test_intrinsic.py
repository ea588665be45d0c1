"""Intrinsic first parameters of open surfaces (psonurbs.fitting.parameters.intrinsic), the choice
between them and a plane projection (open_parameters), and the coarse-to-fine correction."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import franke

from psonurbs.config import config_from_dict
from psonurbs.fitting.parameters.coarse_to_fine import coarse_to_fine, ladder
from psonurbs.fitting.parameters.intrinsic import (
    extended,
    geodesic_embedding,
    parametrise_intrinsic,
    reversed_points,
    reversed_share,
    rigid_embedding,
    surface_graph,
)
from psonurbs.fitting.parameters.open_patch import parametrise_open_patch
from psonurbs.fitting.parameters.parametrisation import fill, unit_square
from psonurbs.fitting.parameters.plane import parametrise_open
from psonurbs.fitting.parameters.topology import choose_topology
from psonurbs.geometry.basis import uniform_inner_knots
from psonurbs.geometry.net import NetLayout


def cylinder_section(n=3000, degrees=250.0, noise=0.0, seed=0, density=None):
    """Points of an open cylinder section (radius 1, height 1.5) and their true intrinsic
    coordinates (arc length, height)."""
    rng = np.random.default_rng(seed)
    u = np.sqrt(rng.random(n)) if density == "graded" else rng.random(n)
    a, z = np.radians(degrees) * u, 1.5 * rng.random(n)
    pts = np.column_stack([np.cos(a), np.sin(a), z]) + rng.normal(0.0, noise, (n, 3))
    return pts, np.column_stack([a, z])


def twisted_ribbon(n=2000, degrees=150.0, seed=1, noise=0.0):
    rng = np.random.default_rng(seed)
    u, w = rng.random(n), rng.random(n) - 0.5
    t = np.radians(degrees) * u
    return np.column_stack([3.0 * u, w * np.cos(t), w * np.sin(t)]) + rng.normal(0.0, noise, (n, 3))


def spherical_cap(n=3000, polar_degrees=90.0, seed=2):
    """Area-uniform points of a cap from the pole down to the given polar angle."""
    rng = np.random.default_rng(seed)
    z = 1.0 - rng.random(n) * (1.0 - np.cos(np.radians(polar_degrees)))
    phi = 2 * np.pi * rng.random(n)
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def height_field(n=3000, seed=3, noise=0.002, graded=False, strays=0.0, saddle=False):
    rng = np.random.default_rng(seed)
    x = (2 * np.sqrt(rng.random(n)) - 1) if graded else rng.uniform(-1, 1, n)
    y = rng.uniform(-1, 1, n)
    z = 0.4 * (x * x - y * y) if saddle else 0.6 * np.exp(-2.0 * (x * x + y * y))
    pts = np.column_stack([x, y, z]) + rng.normal(0.0, noise, (n, 3))
    k = int(strays * n)
    if k:
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pts[:k] = lo + rng.random((k, 3)) * (hi - lo)
    return pts


def plate():
    """A gently curved plate whose data cover an ellipse: the square's corners are empty."""
    pts = height_field(saddle=True, noise=5e-4)
    return pts[np.sum((pts[:, :2] / [0.9, 0.6]) ** 2, axis=1) < 1.0]


def with_strays(pts, share, seed=9):
    rng = np.random.default_rng(seed)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return np.vstack([pts, lo + rng.random((int(share * len(pts)), 3)) * (hi - lo)])


def test_a_cylinder_section_is_unrolled_isometrically():
    """A developable surface lays flat without stretch: every distance between far-apart
    points of the flattened graph is the distance along the surface (arc length, height)
    to 0.5%; the landmark-Isomap start alone is off by a few per cent (the graph zigzags)."""
    pts, truth = cylinder_section(n=3000, degrees=200.0)
    graph = surface_graph(pts)
    start = geodesic_embedding(graph)
    plane, rotations, _ = rigid_embedding(graph, start)
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, len(pts), (2, 4000))
    true = np.linalg.norm(truth[i] - truth[j], axis=1)
    far = true > 0.3
    ratio = np.linalg.norm(plane[i] - plane[j], axis=1)[far] / true[far]
    assert np.abs(ratio - 1.0).max() < 5e-3
    start_ratio = np.linalg.norm(start[i] - start[j], axis=1)[far] / true[far]
    assert np.abs(start_ratio / np.median(start_ratio) - 1.0).max() > 5e-3  # what the rigid rounds remove
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-12)  # rotations, not reflections


def test_the_unit_square_parameters_are_an_affine_image_of_arc_length_and_height():
    """Scaled to the unit square along the rectangle the flattening fills (the parameters
    of a footprint that is not four-sided), the parameters are (arc length, height) up to
    an affine map to 0.5% (the rectangle of a random sample may turn by a fraction of a
    degree), with u along the longer side (the arc)."""
    pts, truth = cylinder_section(n=3000, degrees=250.0)
    graph = surface_graph(pts)
    flat = rigid_embedding(graph, geodesic_embedding(graph))
    uv = unit_square(extended(graph, flat.positions, flat.rotations, pts), flat.positions[graph.component])
    design = np.column_stack([truth, np.ones(len(pts))])
    coeffs = np.linalg.lstsq(design, uv, rcond=None)[0]
    assert np.abs(design @ coeffs - uv).max() < 5e-3
    assert abs(coeffs[0, 0]) > 10 * abs(coeffs[1, 0])  # u follows the arc, v the height


@pytest.mark.parametrize("name, cloud", [
    ("curl, noisy", lambda: cylinder_section(noise=2e-3)[0]),
    ("curl, uneven density", lambda: cylinder_section(noise=1e-3, density="graded")[0]),
    ("twisted ribbon", twisted_ribbon),
    ("hemisphere", spherical_cap),
])
@pytest.mark.parametrize("strays", [0.0, 0.02])
def test_the_flattening_is_fold_free(name, cloud, strays):
    """Nowhere on the surface does the flattening reverse its orientation (strays, which
    have no surface around them, are not judged)."""
    pts = cloud()
    graph = surface_graph(with_strays(pts, strays))
    plane = rigid_embedding(graph, geodesic_embedding(graph)).positions
    assert not reversed_points(graph, plane)[:len(pts)].any(), name


def test_a_plane_projection_of_the_curl_folds():
    """The same fold measure sees what the plane does to a 250-degree curl: it maps both
    sides of the sheet onto the same place, with opposite orientation."""
    pts, _ = cylinder_section(noise=1e-3)
    graph = surface_graph(pts)
    assert reversed_share(graph, parametrise_open(pts).uv) > 0.2


def test_normals_are_oriented_consistently_along_the_curl():
    pts, truth = cylinder_section(noise=1e-3)
    graph = surface_graph(pts)
    n = graph.normals
    radial = np.column_stack([np.cos(truth[:, 0]), np.sin(truth[:, 0]), np.zeros(len(pts))])
    side = np.sign(np.sum(n * radial, axis=1))
    assert np.all(side == side[0])  # all outwards or all inwards, over 250 degrees


def helicoid(n=4000, turns=1.5, seed=0, noise=5e-4):
    """A helicoid strip: radius 0.3 to 1 along v, rising 0.3 a turn: never seen edge-on,
    its projection fills its square, and the plane stacks its turns."""
    rng = np.random.default_rng(seed)
    a, r = rng.uniform(0, 2 * np.pi * turns, n), rng.uniform(0.3, 1.0, n)
    pts = np.column_stack([r * np.cos(a), r * np.sin(a), 0.3 * a / (2 * np.pi)])
    return pts + rng.normal(0, noise, pts.shape)


def pushed_off(n=4000, share=0.1, seed=3):
    """A noisy Franke surface with a tenth of its points pushed 5 to 20 sigmas off along z."""
    pts = franke(n=n, seed=seed, noise=0.001)
    rng = np.random.default_rng(seed + 1)
    pushed = rng.random(n) < share
    sigma = 0.001 * float(np.linalg.norm(np.ptp(pts, axis=0)))
    pts[pushed, 2] += rng.uniform(5, 20, pushed.sum()) * sigma * rng.choice([-1.0, 1.0], pushed.sum())
    return pts


@pytest.mark.parametrize("name, cloud", [
    ("bump, noisy", lambda: height_field()),
    ("franke, a tenth pushed 5-20 sigmas off", pushed_off),
    ("saddle, uneven density, 2% strays", lambda: height_field(saddle=True, graded=True, strays=0.02)),
    ("franke, steep flanks", lambda: franke(n=3000, seed=5, noise=0.002)),
    ("plate over an ellipse", lambda: plate()),
])
def test_auto_keeps_the_plane_on_a_height_field(name, cloud):
    par = parametrise_open_patch(cloud(), "auto")
    assert par.info["method"] == "plane", (name, par.info["choice"])


@pytest.mark.parametrize("name, cloud, why", [
    ("curl, noisy", lambda: cylinder_section(noise=1e-3)[0], "edge-on"),
    ("curl 200 degrees, uneven density", lambda: cylinder_section(degrees=200.0, density="graded")[0], "edge-on"),
    ("hemisphere", spherical_cap, "edge-on"),
    ("twisted ribbon", twisted_ribbon, "fills"),
    ("strip twisted 90 degrees, noisy", lambda: twisted_ribbon(n=4000, degrees=90.0, noise=1e-3), "fills"),
    ("helicoid, one and a half turns", helicoid, "over another part"),
])
def test_auto_lays_flat_what_no_plane_sees_as_a_height_field(name, cloud, why):
    par = parametrise_open_patch(cloud(), "auto")
    assert par.info["method"] == "intrinsic", (name, par.info["choice"])
    assert why in par.info["choice"]["reason"]


def flat_l(n: int = 1500, seed: int = 3, noise: float = 5e-4, tilt=(20.0, -35.0, 10.0)) -> np.ndarray:
    """A flat L (a 1 x 0.2 foot and a 0.25 x 0.6 upright), turned in space: its outline
    fills 44% of its bounding rectangle."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    xy = rng.random((3 * n, 2)) * [1.0, 0.8]
    xy = xy[(xy[:, 1] <= 0.2) | (xy[:, 0] <= 0.25)][:n]
    pts = np.column_stack([xy, noise * rng.standard_normal(len(xy))])
    return Rotation.from_euler("xyz", tilt, degrees=True).apply(pts)


def test_a_flat_l_is_projected_on_its_own_plane():
    """Flat: every normal within 15 degrees of the PCA normal. Neither a view tilted to
    square its outline nor an embedding of its graph (which bends round the inner
    corner and fills a turned rectangle better for it) is taken: the projection on its
    own plane is already its flattening, and an affine one."""
    from scipy.spatial.transform import Rotation

    pts = flat_l()
    normal = Rotation.from_euler("xyz", (20.0, -35.0, 10.0), degrees=True).apply([0.0, 0.0, 1.0])
    for par in (parametrise_open(pts), parametrise_open_patch(pts, "auto")):
        assert par.info["method"] == "plane"
        assert abs(np.dot(par.info["normal"], normal)) > np.cos(np.radians(1.0))
    assert "flat" in parametrise_open_patch(pts, "auto").info["choice"]["reason"]
    # the map is affine: the parameters are an affine image of the points
    par = parametrise_open(pts)
    design = np.column_stack([pts, np.ones(len(pts))])
    residual = par.uv - design @ np.linalg.lstsq(design, par.uv, rcond=None)[0]
    assert np.abs(residual).max() < 1e-9


def test_auto_computes_both_candidates_side_by_side_with_the_same_result(monkeypatch):
    cloud = cylinder_section(noise=1e-3)[0]
    monkeypatch.setenv("PSONURBS_THREADS", "1")
    alone = parametrise_open_patch(cloud, "auto")
    monkeypatch.setenv("PSONURBS_THREADS", "2")
    beside = parametrise_open_patch(cloud, "auto")
    np.testing.assert_array_equal(alone.uv, beside.uv)
    assert alone.info == beside.info and alone.info["method"] == "intrinsic"


def test_strays_do_not_shrink_the_square_the_surface_fills():
    """A stray's offset is not unrolled (it is cut to the neighbourhood's reach), so the
    rectangle is the surface's: its points still fill the unit square."""
    pts, _ = cylinder_section(noise=1e-3)
    uv = parametrise_intrinsic(with_strays(pts, 0.02)).uv[:len(pts)]
    assert fill(uv, 16) > 0.99


def test_ladder_is_nested_from_a_bezier_patch_to_the_configured_knots():
    layout = NetLayout((10, 6), (3, 3))
    levels = ladder(layout)
    assert levels[0].size == (0, 0)
    np.testing.assert_array_equal(levels[-1].inner_u, uniform_inner_knots(6))
    np.testing.assert_array_equal(levels[-1].inner_v, uniform_inner_knots(2))
    for coarse, fine in zip(levels, levels[1:]):
        assert set(coarse.inner_u) <= set(fine.inner_u) and set(coarse.inner_v) <= set(fine.inner_v)
        assert len(coarse.inner_u) < len(fine.inner_u) or len(coarse.inner_v) < len(fine.inner_v)


def test_coarse_to_fine_brings_the_curl_to_its_noise():
    """From the flattened graph, the ladder's last level (the configured 10 x 6 bicubic
    net, uniform knots) is within 3% of the noise; each level is nearer than the last."""
    sigma = 2e-3
    pts, _ = cylinder_section(n=2000, noise=sigma, seed=4)
    diagonal = np.linalg.norm(np.ptp(pts, axis=0))
    local = (pts - pts.mean(axis=0)) / diagonal
    uv = parametrise_intrinsic(local).uv
    _, levels = coarse_to_fine(NetLayout((10, 6), (3, 3)), local, uv, 1e-6)
    rmse = [level["rmse"] * diagonal for level in levels if not level.get("direct")]
    assert rmse[-1] < 1.03 * sigma  # the noise's component across the surface
    assert all(b < a for a, b in zip(rmse, rmse[1:]))


def test_topology_auto_fits_the_curl_as_an_intrinsic_open_patch():
    """The open candidate of a 250-degree curl is laid flat and wins; the cylinder has no
    data on a third of the turn, and a torus forced onto the sheet fails its self-checks."""
    pts, _ = cylinder_section(n=1200, noise=1e-3, seed=5)
    config = config_from_dict({"orders": [4, 4], "net_size": [10, 6], "topology": "auto"})
    topology, par, scores = choose_topology(pts, np.arange(len(pts)), config)
    assert topology == "open" and par.info["method"] == "intrinsic", scores
    assert scores["open"]["parametrisation"] == "intrinsic"
    assert "no data" in scores["cylinder"]["rejected"]
    assert scores["torus"]["rejected"].startswith("suspect: ")


def test_topology_auto_rejects_an_open_patch_laid_over_a_tube():
    """Unrolled, a closed tube is an annulus: an open patch over it caps one end and folds
    there, or runs a seam through the data. Its data close round the tube, so the open
    patch is rejected before it is parametrised, and the cylinder wins."""
    rng = np.random.default_rng(6)
    a, h = rng.uniform(0, 2 * np.pi, 400), rng.uniform(0, 3, 400)
    pts = np.column_stack([1.7 * np.cos(a), 1.7 * np.sin(a), h]) / 5.0
    topology, _, scores = choose_topology(pts, np.arange(len(pts)), config_from_dict({"net_size": [6, 5]}))
    assert topology == "cylinder", scores
    assert "classical_error_relative" not in scores["open"]  # not fitted: rejected on the data
    assert scores["open"]["rejected"].startswith("the data close round a tube")

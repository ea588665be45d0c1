"""The repository's own benchmark: the case registry, the runner and the independent scorer.

The scorer (benchmarks/score.py) is checked against answers known exactly: points at
known distances from a surface, a surface against itself, a seam, a trimmed surface, and
its mesh distance against a search over every triangle. Where the outside scorer
(../shared/bench/score.py, beside a checkout of the team's workspace) is there, both must
give the same figures on a real fit (to the outside one's float32 / tessellation noise);
without it that check is skipped.
"""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import SAMPLES, closed_u_surface, open_surface, run

from psonurbs.formats.outputs import render_ply

REPO = Path(__file__).resolve().parents[1]
OUTSIDE = REPO.parent / "shared" / "bench"
RES = 121  # the scorer's sample grid in the unit tests (its default, 301, for the benchmark)


def load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


cases = load("cases", REPO / "benchmarks" / "cases.py")  # the names the runner imports them by
scorer = load("score", REPO / "benchmarks" / "score.py")
runner = load("run", REPO / "benchmarks" / "run.py")


# ---- the generator ------------------------------------------------------------------------

def test_the_generator_makes_the_sample_clouds():
    samples = sorted(SAMPLES.glob("*.ply"))
    assert len(samples) == 5
    for path in samples:
        made, kept = (data.partition(b"end_header\n") for data in (cases.ply(cases.CASES[path.stem].points(0)),
                                                                     path.read_bytes()))
        assert made[0] == kept[0], path.name  # the same header: the same points, count and layout
        # to rounding only: numpy's exp may differ in the last bit between builds (SIMD or not)
        made_xyz, kept_xyz = (np.frombuffer(data[2], "<f8") for data in (made, kept))
        np.testing.assert_allclose(made_xyz, kept_xyz, rtol=0, atol=2 * np.finfo(float).eps * np.abs(kept_xyz).max(),
                                   err_msg=path.name)
        assert cases.CASES[path.stem].yaml() == path.with_suffix(".yaml").read_text(), path.name


def test_every_suite_is_one_kind_of_case_with_names_of_its_own():
    names = [name for suite in cases.SUITES.values() for name in suite]
    assert len(names) == len(set(names))  # a name says which case, whatever the suite
    assert set(cases.SUITES) == {"public", "robust", "unseen", "features", "trims", "edges", "thick"}
    assert len(cases.CASES) == 15 and cases.CASES is cases.SUITES["public"]
    for suite, members in cases.SUITES.items():
        assert all(isinstance(c, cases.Case) and c.suite == suite for c in members.values()), suite
    assert all(c.loops is not None or c.footprint is None for c in cases.SUITES["trims"].values())


@pytest.mark.parametrize("name, share", [("blob_junk5", 0.05), ("piece_junk5", 0.05), ("near_junk10", 0.10)])
def test_junk_of_each_kind_replaces_its_share_of_the_points(name, share):
    """Away from the surface by more than 4 noise sigmas: the junk's share, to the count."""
    case = cases.SUITES["robust"][name]
    points = case.points(0)
    truth = scorer.MeshDistance(*case.truth())
    diagonal = np.linalg.norm(np.ptp(case.shape(*case.sampler(np.random.default_rng(0))), axis=0))  # clean
    far = truth(points) > 4.5 * case.noise * diagonal
    assert abs(far.sum() - share * len(points)) <= 0.01 * share * len(points) + 2


def test_the_generator_writes_cases_with_their_truth(tmp_path):
    assert cases.main([str(tmp_path), "--only", "plate_holes", "cylinder"]) == 0
    truth = np.load(tmp_path / "plate_holes.gt.npz")
    assert float(truth["noise"]) == 0.0005 and float(truth["outliers"]) == 0.0
    # the footprint's truth: every vertex used, none outside the ellipse
    assert len(np.unique(truth["triangles"])) == len(truth["vertices"])
    x, y = truth["vertices"][:, 0], truth["vertices"][:, 1]
    assert np.all(((x / 2 + 0.5 - 0.5) / 0.48) ** 2 + ((y / 2 + 0.5 - 0.5) / 0.36) ** 2 < 1.0)
    points = scorer.read_points(tmp_path / "cylinder.ply")
    assert points.shape == (4000, 3)
    assert np.allclose(np.hypot(points[:, 0], points[:, 1]), 0.8, atol=0.02)  # radius 0.8, noise 0.1% of 3.4
    assert cases.CASES["cylinder"].points(1).tobytes() != points.tobytes()  # another seed, another draw
    assert cases.main([str(tmp_path / "trims"), "--suite", "trims", "--only", "franke_annulus"]) == 0
    assert (tmp_path / "trims" / "franke_annulus.yaml").read_text() == cases.SUITES["trims"]["franke_annulus"].yaml()
    assert cases.main([str(tmp_path), "--only", "franke_annulus"]) == 2  # not a public case


EDGES = {"step_bump14": ((4, 4), (14, 14), 4000), "graded_helicoid": ((4, 4), (12, 6), 4000),
         "s_fold": ((4, 4), (12, 6), 4000), "tilted_saddle_junk5": ((4, 4), (8, 8), 4000),
         "franke_junk4": ((4, 4), (12, 12), 5000), "cone_sector270": ((3, 2), (7, 2), 3000),
         "sphere_band288": ((4, 4), (10, 6), 4000), "wave_sparse_end": ((4, 4), (10, 10), 4000)}


def test_the_thick_suite_is_about_as_noisy_as_its_sampling_step_or_noisier():
    """sigma (a share of the noise-free cloud's diagonal) over the sampling step
    sqrt(area / points), the area the truth mesh's."""
    for case in cases.SUITES["thick"].values():
        clean = case.shape(*case.sampler(np.random.default_rng(0)))
        diagonal = np.linalg.norm(clean.max(0) - clean.min(0))
        vertices, triangles = case.truth()
        a, b, c = (vertices[triangles[:, k]] for k in range(3))
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
        assert case.noise * diagonal / np.sqrt(area / len(clean)) >= 0.8, case.name


def test_the_edges_suite_writes_its_cases(tmp_path):
    suite = cases.SUITES["edges"]
    assert list(suite) == list(EDGES)
    assert cases.main([str(tmp_path), "--suite", "edges"]) == 0
    for name, (orders, net, count) in EDGES.items():
        case = suite[name]
        assert (case.orders, case.net, case.topology, case.footprint) == (orders, net, "open", None), name
        assert f"orders: [{orders[0]}, {orders[1]}]\nnet_size: [{net[0]}, {net[1]}]" in \
            (tmp_path / f"{name}.yaml").read_text(), name
        assert scorer.read_points(tmp_path / f"{name}.ply").shape == (count, 3), name
        truth = np.load(tmp_path / f"{name}.gt.npz")
        assert len(truth["vertices"]) == cases.TRUTH_GRID ** 2, name  # the whole square
        assert float(truth["outliers"]) == case.outliers and float(truth["noise"]) == case.noise, name
    assert np.array_equal(suite["tilted_saddle_junk5"].points(0), cases.SUITES["robust"]["saddle_junk5"].points(0))


def test_the_cone_sector_is_a_cone_sampled_evenly_by_area(tmp_path):
    """Radius 0.5 + 0.5 z over 270 degrees, and as many points per unit of area near the
    narrow end as near the wide one."""
    case = cases.SUITES["edges"]["cone_sector270"]
    truth = case.truth()[0]
    points = case.points(0)
    for xyz in (truth, points):
        assert np.allclose(np.hypot(xyz[:, 0], xyz[:, 1]), 0.5 + 0.5 * xyz[:, 2], rtol=0, atol=1e-12)
    angle = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360
    assert angle.max() < 270 and angle.max() > 269  # 0 to 270 degrees
    narrow, wide = np.count_nonzero(points[:, 2] < 0.2), np.count_nonzero(points[:, 2] > 0.8)
    # area of a band: proportional to its mean radius (0.55 and 0.95)
    assert narrow / wide == pytest.approx(0.55 / 0.95, rel=0.15)


@pytest.mark.skipif(not (OUTSIDE / "cases.py").exists(), reason="no outside benchmark beside the repository")
def test_the_generator_makes_the_outside_cases():
    outside = load("outside_cases", OUTSIDE / "cases.py")
    assert sorted(outside.CASES) == sorted(cases.CASES)
    for name, case in cases.CASES.items():
        assert np.array_equal(case.points(0), outside.make_points(outside.CASES[name], 0)), name
        vertices, triangles = outside.gt_mesh(outside.CASES[name])
        mine = case.truth()
        assert np.array_equal(mine[0], vertices) and np.array_equal(mine[1], triangles), name


# ---- the scorer against known answers ---------------------------------------------------------

def normals(surface, u, v):
    from conftest import reference_points

    su, sv = reference_points(surface, u, v, (1, 0)), reference_points(surface, u, v, (0, 1))
    n = np.cross(su, sv)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def write_fit(out: Path, surface, points: np.ndarray, stem: str = "scan", trim=None,
              curve=(0.3, 0.2, 0.2, 0.1), topology: str = "open") -> Path:
    """A fit's files as psonurbs writes them (JSON, mesh, error curve) and the cloud."""
    out.mkdir(parents=True, exist_ok=True)
    doc = surface.to_dict()
    if trim is not None:
        doc["trim"] = trim
    (out / f"{stem}.json").write_text(json.dumps({"topology": topology, "surface": doc,
                                                  "metrics": {"rmse": 0.125}}))
    vertices, triangles = surface.tessellate(101, 101)
    (out / f"{stem}.ply").write_bytes(render_ply(vertices, triangles))
    (out / f"{stem}_error.csv").write_text("iteration,best_rmse,mean_rmse\n" +
                                           "".join(f"{k},{b},{b + 1}\n" for k, b in enumerate(curve)))
    cloud = out / f"{stem}_cloud.ply"
    cloud.write_bytes(cases.ply(points))
    return cloud


def offset_cloud(surface, n=400, seed=0, box=(0.05, 0.95)):
    rng = np.random.default_rng(seed)
    lo, hi = box
    u = surface.knots_u[surface.degree_u] + (lo + (hi - lo) * rng.random(n)) * np.ptp(surface.knots_u)
    v = surface.knots_v[surface.degree_v] + (lo + (hi - lo) * rng.random(n)) * np.ptp(surface.knots_v)
    from conftest import reference_points

    offsets = rng.uniform(-2.0, 2.0, n)  # 2 units off a 250-unit patch: the foot point is the base point
    return reference_points(surface, u, v) + offsets[:, None] * normals(surface, u, v), offsets


def test_scorer_measures_known_distances_exactly(tmp_path):
    surface = open_surface()
    points, offsets = offset_cloud(surface)
    cloud = write_fit(tmp_path, surface, points)
    figures = scorer.score(cloud, tmp_path, stem="scan", res=RES)
    diag = np.linalg.norm(np.ptp(points, axis=0))
    assert figures["rmse"] == pytest.approx(np.sqrt(np.mean(offsets ** 2)) / diag, rel=1e-9)
    assert figures["max"] == pytest.approx(np.abs(offsets).max() / diag, rel=1e-9)
    assert figures["claimed_rmse"] == pytest.approx(0.125 / diag)
    assert 0 < figures["mesh_vs_nurbs"] < 1e-3  # the 101 x 101 mesh's chords, nothing more
    assert figures["curve_ok"] is True and figures["trimmed"] is False
    assert "seam_u" not in figures and "pole_spread" not in figures


def test_scorer_truth_of_a_surface_against_itself(tmp_path):
    surface = open_surface()
    points, _ = offset_cloud(surface)
    cloud = write_fit(tmp_path, surface, points)
    vertices, triangles = surface.tessellate(241, 241)
    np.savez(tmp_path / "truth.npz", vertices=vertices, triangles=triangles, noise=0.0, outliers=0.0)
    figures = scorer.score(cloud, tmp_path, tmp_path / "truth.npz", stem="scan", res=RES)
    assert figures["cover_max"] < 1e-12  # the truth's vertices lie on the surface
    assert figures["truth_max"] < 2e-4 and figures["truth_rms"] < 5e-5  # chords of the truth only


def test_scorer_seam_and_rising_curve(tmp_path):
    surface = closed_u_surface()
    u = np.linspace(surface.knots_u[surface.degree_u], surface.knots_u[-surface.degree_u - 1], 50)
    from conftest import reference_points

    points = reference_points(surface, np.tile(u, 4), np.repeat(np.linspace(0, 1, 4), 50))
    cloud = write_fit(tmp_path, surface, points, curve=(0.3, 0.2, 0.25))
    figures = scorer.score(cloud, tmp_path, stem="scan", res=RES)
    assert figures["seam_u"] < 1e-12
    assert figures["rmse"] < 1e-12
    assert figures["curve_ok"] is False  # the best column rose


def square_loop(lo: float, hi: float, clockwise: bool = False) -> dict:
    corners = [[lo, lo], [hi, lo], [hi, hi], [lo, hi], [lo, lo]]
    if clockwise:
        corners = corners[::-1]
    return {"degree": 1, "knots": [0.0, 0.0, 0.25, 0.5, 0.75, 1.0, 1.0], "control_points": corners}


def test_scorer_reads_trimmed_surfaces(tmp_path):
    surface = open_surface()
    inner, _ = offset_cloud(surface, n=3000, box=(0.3, 0.7))  # data only in the middle of the domain
    untrimmed = scorer.score(write_fit(tmp_path / "a", surface, inner), tmp_path / "a", stem="scan", res=RES)
    trim = [square_loop(0.3, 0.7), square_loop(0.45, 0.55, clockwise=True)]  # with a hole in it
    trimmed = scorer.score(write_fit(tmp_path / "b", surface, inner, trim=trim), tmp_path / "b", stem="scan", res=RES)
    assert trimmed["trimmed"] is True
    assert untrimmed["overhang"] > 0.5 and trimmed["overhang"] < 0.02
    # a point over the hole is as far from the trimmed surface as from the hole's rim
    s = scorer.Surface(json.loads((tmp_path / "b" / "scan.json").read_text())["surface"])
    above_hole = s.at(np.array([0.5]), np.array([0.5]))
    side, edge = np.linspace(0.45, 0.55, 401), np.full(401, 0.45)
    rim = np.concatenate([s.at(side, edge), s.at(side, edge + 0.1), s.at(edge, side), s.at(edge + 0.1, side)])
    d = scorer.SurfaceDistance(s)(above_hole)[0]
    assert d == pytest.approx(np.linalg.norm(rim - above_hole, axis=1).min(), rel=1e-3)
    assert scorer.SurfaceDistance(s, trimmed=False)(above_hole)[0] < 1e-9


# ---- where the data end: spacing, overrun, bare share ---------------------------------------------

STEP = 1.0 / 40  # the grid cloud's step
INTERIOR = (4 + 2 * np.sqrt(2.0)) * STEP / 6  # 4 neighbours at h, 2 at h sqrt 2
EDGE = (5 + 2 * np.sqrt(2.0)) * STEP / 6  # an edge point's: 3 at h, 2 at h sqrt 2, then one at 2h


def grid_cloud() -> np.ndarray:
    """The unit square in z = 0 as a 41 x 41 grid."""
    x, y = np.meshgrid(np.linspace(0, 1, 41), np.linspace(0, 1, 41), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def flat_patch(width: float, height: float = 1.0):
    """The bilinear patch [0, width] x [0, height] in z = 0 over the domain [0, 1]^2."""
    from psonurbs.geometry.nurbs import NurbsSurface

    corners = np.array([[[0.0, 0.0, 0.0], [0.0, height, 0.0]], [[width, 0.0, 0.0], [width, height, 0.0]]])
    return NurbsSurface(1, 1, [0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 1.0, 1.0], corners, np.ones((2, 2)))


def test_local_spacing_on_a_square_grid():
    spacing = scorer.local_spacing(grid_cloud())
    x, y = grid_cloud()[:, :2].T
    side = (np.minimum(x, 1 - x) < 1e-9) & (np.minimum(y, 1 - y) > 1.5 * STEP)  # on an edge, off the corners
    inner = np.minimum.reduce([x, 1 - x, y, 1 - y]) > 1.5 * STEP
    assert np.allclose(spacing[inner], INTERIOR, rtol=1e-12)
    assert np.allclose(spacing[side], EDGE, rtol=1e-12)


def test_a_surface_past_the_data_overruns_by_its_overhang_in_spacings(tmp_path):
    """The patch runs d = 0.2 past the grid's edge u = 1: its far edge is d from the last
    column (and at most half a step along it), whose points are EDGE apart."""
    d = 0.2
    points = grid_cloud()
    cloud = write_fit(tmp_path, flat_patch(1.0 + d), points)
    figures = scorer.score(cloud, tmp_path, stem="scan", res=301)
    diag = np.sqrt(2.0)
    assert figures["spacing"] == pytest.approx(INTERIOR / diag, rel=1e-12)
    far = np.hypot(d, STEP / 2) / EDGE  # the far edge halfway between two points of the column
    assert d / EDGE <= figures["overrun_max"] <= far * (1 + 1e-9)
    assert figures["overrun_max"] == pytest.approx(far, rel=1e-4)
    # the far edge is 1 of the boundary's 4.4 units, its ends near the corners (h in all) nearer
    # to a corner point of a wider spacing: the top 0.22 units all lie on it, where the ratio
    # grows with the offset along the column, uniform in [0, h / 2]
    offset = (1 - 0.05 * 4.4 / (1 - STEP)) * STEP / 2
    assert figures["overrun_p95"] == pytest.approx(np.hypot(d, offset) / EDGE, rel=2e-4)
    # bare: farther than 3 EDGE from the last column, a strip (0.2 - 3 EDGE) wide of 1.2
    assert figures["bare_share"] == pytest.approx((d - 3 * EDGE) / (1 + d), rel=0.03)
    assert "truth_sigma" not in figures and "cover_max_sp" not in figures


def test_a_trim_loop_inside_the_data_does_not_overrun(tmp_path):
    points = grid_cloud()
    cloud = write_fit(tmp_path, flat_patch(1.2), points, trim=[square_loop(0.1, 0.7)])
    figures = scorer.score(cloud, tmp_path, stem="scan", res=RES)
    assert figures["trimmed"] is True
    assert 0 < figures["overrun_max"] <= STEP / np.sqrt(2.0) / INTERIOR  # never farther than a cell's middle
    assert figures["overrun_p95"] <= figures["overrun_max"]
    untrimmed = scorer.score(write_fit(tmp_path / "b", flat_patch(1.2), points), tmp_path / "b", stem="scan", res=RES)
    assert figures["bare_share"] == untrimmed["bare_share"] > 0  # the untrimmed surface's, either way


def test_cover_in_spacings_and_truth_in_sigmas_on_the_inliers(tmp_path):
    """The truth runs 0.3 past the patch's edge y = 1; 20 junk points over the square do not
    count in the spacing when the truth says there are outliers."""
    junk = np.column_stack([np.random.default_rng(0).random((20, 2)), np.full(20, 0.5)])
    points = np.concatenate([grid_cloud(), junk])
    cloud = write_fit(tmp_path, flat_patch(1.0), points)
    vertices, triangles = flat_patch(1.0, 1.3).tessellate(41, 53)
    np.savez(tmp_path / "truth.npz", vertices=vertices, triangles=triangles, noise=0.001, outliers=0.01)
    figures = scorer.score(cloud, tmp_path, tmp_path / "truth.npz", stem="scan", res=RES)
    diag = np.sqrt(2.0 + 0.25)
    assert figures["inliers"] == len(grid_cloud())
    assert figures["spacing"] == pytest.approx(INTERIOR / diag, rel=1e-12)
    assert figures["cover_max"] == pytest.approx(0.3 / diag, rel=1e-9)
    assert figures["cover_max_sp"] == pytest.approx(figures["cover_max"] / figures["spacing"], rel=1e-12)
    assert figures["cover_max_sp"] == pytest.approx(0.3 / INTERIOR, rel=1e-9)
    assert figures["sample_cover_sp"] == pytest.approx(0.3 / INTERIOR, rel=1e-9)  # the truth's row y = 1.3
    assert figures["truth_sigma"] == pytest.approx(figures["truth_rms"] / 0.001, rel=1e-12)
    assert figures["overrun_max"] < 0.6 and figures["bare_share"] == 0.0  # the patch is where the grid is


def test_a_noise_free_cloud_with_junk_keeps_its_points_as_inliers(tmp_path):
    """Exact points of a curved surface lie a chord off its triangulated truth, not on it:
    they are the inliers, the junk 0.05 off is not."""
    surface = open_surface()
    from conftest import reference_points

    rng = np.random.default_rng(0)
    u = surface.knots_u[surface.degree_u] + (0.05 + 0.9 * rng.random(400)) * np.ptp(surface.knots_u)
    v = surface.knots_v[surface.degree_v] + (0.05 + 0.9 * rng.random(400)) * np.ptp(surface.knots_v)
    exact = reference_points(surface, u, v)
    diag = np.linalg.norm(np.ptp(exact, axis=0))
    junk = reference_points(surface, u[:8], v[:8]) + 0.05 * diag * normals(surface, u[:8], v[:8])
    cloud = write_fit(tmp_path, surface, np.concatenate([exact, junk]))
    vertices, triangles = surface.tessellate(241, 241)
    np.savez(tmp_path / "truth.npz", vertices=vertices, triangles=triangles, noise=0.0, outliers=0.02)
    chord = scorer.MeshDistance(vertices, triangles)(exact) / diag
    assert chord.max() > 1e-9  # off the triangulation
    figures = scorer.score(cloud, tmp_path, tmp_path / "truth.npz", stem="scan", res=RES)
    assert figures["inliers"] == len(exact)
    assert figures["inlier_rmse"] < 1e-6


def test_the_boundary_leaves_out_seams_and_poles():
    closed = scorer.Surface(closed_u_surface().to_dict())
    rim, lengths = scorer.boundary(closed, 1.0)
    assert len(rim) == 2 * scorer.BOUNDARY_SAMPLES  # the two ends of the tube, not its seam
    heights = np.unique(np.round(rim[:, 2], 9))
    assert np.allclose(heights, [0.0, 2.0])
    corners = [[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0], [1.0, 1.0, 0.0]]]  # u = 0 is a point
    triangle = scorer.Surface({"degree_u": 1, "degree_v": 1, "knots_u": [0, 0, 1, 1], "knots_v": [0, 0, 1, 1],
                               "control_points": corners})
    rim, lengths = scorer.boundary(triangle, 1.0)
    assert len(rim) == 3 * scorer.BOUNDARY_SAMPLES
    assert lengths.sum() == pytest.approx(2 + np.sqrt(2.0), rel=1e-9)
    steps = np.linalg.norm(np.diff(rim[:scorer.BOUNDARY_SAMPLES], axis=0), axis=1)
    assert np.allclose(steps, steps.mean(), rtol=1e-6)  # evenly in arc length


@pytest.mark.parametrize("kind", ["patch", "collapsed-row", "wild"])
def test_mesh_distance_is_the_least_over_every_triangle(kind):
    vertices, triangles = open_surface().tessellate(31, 25)
    rng = np.random.default_rng(2)
    centre, size = vertices.mean(0), np.ptp(vertices, axis=0)
    if kind == "collapsed-row":  # the first row at one point, as a sphere's pole: 25 copies of a vertex
        vertices[:25] = vertices[:25].mean(0)
    if kind == "wild":  # a fit flung far past its cloud: a few vertices 50 sizes out, long triangles
        far = rng.choice(len(vertices), 12, replace=False)
        vertices[far] += rng.normal(size=(12, 3)) * 50 * size.max()
    probes = centre + (rng.random((300, 3)) - 0.5) * size * 1.4  # near and far, inside and beyond
    exhaustive = scorer.point_triangle_distance(probes[:, None, :], *(vertices[triangles][None, :, i]
                                                                      for i in range(3))).min(axis=1)
    assert np.allclose(scorer.MeshDistance(vertices, triangles)(probes), exhaustive, rtol=1e-12, atol=0)


def test_point_triangle_distance_in_each_region():
    a, b, c = np.zeros(3), np.array([2.0, 0, 0]), np.array([0, 2.0, 0])
    probes = np.array([[0.5, 0.5, 3.0], [-1.0, -1.0, 0.0], [1.0, -2.0, 0.0], [2.0, 2.0, 0.0], [3.0, 0.0, 4.0]])
    expected = [3.0, np.sqrt(2.0), 2.0, np.sqrt(2.0), np.hypot(1.0, 4.0)]
    got = scorer.point_triangle_distance(probes, *(np.broadcast_to(x, probes.shape) for x in (a, b, c)))
    assert np.allclose(got, expected, rtol=1e-14)


# ---- the outside scorer, where it is ------------------------------------------------------------

@pytest.mark.skipif(not (OUTSIDE / "score.py").exists(), reason="no outside scorer beside the repository")
def test_both_scorers_agree_on_a_fit(tmp_path):
    pytest.importorskip("open3d")
    assert cases.main([str(tmp_path / "cases"), "--only", "quarter_cylinder"]) == 0
    cloud, truth = tmp_path / "cases" / "quarter_cylinder.ply", tmp_path / "cases" / "quarter_cylinder.gt.npz"
    out = tmp_path / "fit"
    result = run("fit", cloud, "-c", cloud.with_suffix(".yaml"), "-o", out, "--particles", "1", "--iterations", "1",
                 "-q")
    assert result.exit_code == 0, result.stderr
    doc = json.loads((out / "quarter_cylinder.json").read_text())
    lo_u, hi_u = doc["surface"]["knots_u"][2], doc["surface"]["knots_u"][-3]
    lo_v, hi_v = doc["surface"]["knots_v"][1], doc["surface"]["knots_v"][-2]
    trimmed_out = tmp_path / "trimmed"
    trimmed_out.mkdir()
    for name in ("quarter_cylinder.ply", "quarter_cylinder_error.csv"):
        (trimmed_out / name).write_bytes((out / name).read_bytes())
    u0, u1 = lo_u + 0.2 * (hi_u - lo_u), lo_u + 0.8 * (hi_u - lo_u)
    v0, v1 = lo_v + 0.1 * (hi_v - lo_v), lo_v + 0.9 * (hi_v - lo_v)
    doc["surface"]["trim"] = [{"degree": 1, "knots": [0, 0, 0.25, 0.5, 0.75, 1, 1],
                               "control_points": [[u0, v0], [u1, v0], [u1, v1], [u0, v1], [u0, v0]]}]
    (trimmed_out / "quarter_cylinder.json").write_text(json.dumps(doc))
    grid = scorer.Surface(doc["surface"]).grid(*(np.linspace(lo, hi, 301) for lo, hi in ((lo_u, hi_u), (lo_v, hi_v))))
    diagonal = float(np.linalg.norm(np.ptp(scorer.read_points(cloud), axis=0)))
    cell = float(np.linalg.norm(grid[1:, 1:] - grid[:-1, :-1], axis=2).max()) / diagonal
    assert 1e-3 < cell < 1e-2, cell  # about 1/300 of the sheet
    for directory in (out, trimmed_out):
        outside = subprocess.run([sys.executable, str(OUTSIDE / "score.py"), str(cloud), str(directory), "--gt",
                                  str(truth)], capture_output=True, text=True, timeout=300)
        theirs = json.loads(outside.stdout.strip().splitlines()[-1])
        ours = scorer.score(cloud, directory, truth)
        assert theirs["trimmed"] == ours["trimmed"] == (directory == trimmed_out)
        floor = 2e-6  # the outside scorer's: float32 distances on a 301 x 301 mesh
        for key in ("rmse", "p99", "max", "truth_rms", "truth_max", "cover_rms", "cover_max", "mesh_vs_nurbs"):
            # the outside scorer trims by dropping every cell of its mesh that a loop crosses, so
            # its face ends up to one cell inside the loops: the distances of the truth to the
            # face (cover) may differ by up to one cell's diagonal
            allowed = 0.02 * theirs[key] + floor + (cell if key.startswith("cover") and theirs["trimmed"] else 0.0)
            assert abs(ours[key] - theirs[key]) <= allowed, (directory.name, key, ours, theirs)
        assert ours["overhang"] == pytest.approx(theirs["overhang"], abs=1e-3)
        assert ours["claimed_rmse"] == theirs["claimed_rmse"] and ours["curve_ok"] == theirs["curve_ok"]


def test_stability_fits_the_cloud_and_its_perturbed_copies(tmp_path, capsys):
    """benchmarks/stability.py: the cloud itself (draw 0) and each perturbed copy fitted by
    the installed command with the config and the added keys; one row each, the spread."""
    stability = load("bench_stability", REPO / "benchmarks" / "stability.py")
    rng = np.random.default_rng(3)
    uv = rng.random((300, 2))
    cloud = tmp_path / "sheet.xyz"
    np.savetxt(cloud, np.column_stack([uv, 0.1 * np.sin(3 * uv[:, 0])]))
    config = tmp_path / "c.yaml"
    config.write_text("net_size: [5, 5]\norders: [3, 3]\npolish_iterations: 3\n")
    out = tmp_path / "out"
    assert stability.main([str(cloud), "--config", str(config), "--draws", "1", "--out", str(out),
                           "--set", "swarm={particles: 2, iterations: 2}", "--set", "refine=false"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert [row.split(" | ")[0] for row in rows] == ["| 0", "| 1"]
    assert all(row.split(" | ")[4] == "NO" for row in rows)  # refine: false reached the fit
    written = (out / "config.yaml").read_text()
    assert "refine: false" in written and "particles: 2" in written and "polish_iterations: 3" in written
    moved = np.loadtxt(out / "draw1" / "sheet.xyz")
    original = np.loadtxt(cloud)
    assert 0 < np.abs(moved - original).max() < 1e-10
    with pytest.raises(SystemExit):
        stability.config_with(config, ["refine"], tmp_path)


# ---- the runner -------------------------------------------------------------------------------

STAND_IN = """import json, sys
print("scoring", sys.argv[1:])
print(json.dumps({"rmse": 0.5, "truth_rms": 0.25 if "--gt" in sys.argv else None, "claimed_rmse": 0.5}))
"""


def test_the_runner_fits_with_the_build_it_is_given(tmp_path, capsys):
    """``--build EXE`` names the executable of the rows ``this`` (a pyenv shim's python
    puts its own bin first on PATH, ahead of a build under test)."""
    build = tmp_path / "other_build"
    build.write_text("#!/bin/sh\necho 'the other build ran' >&2\nexit 3\n")
    build.chmod(0o755)
    assert runner.main(["--cases", "seed_patch16", "--variants", "swarm", "--build", str(build),
                        "--out", str(tmp_path / "run")]) == 0
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| seed_patch16 |")]
    assert len(row) == 1 and "the other build ran" in row[0]


def test_the_runner_fits_scores_tabulates_and_reuses_its_rows(tmp_path, capsys):
    """One tiny public case, both variants, through the real ``psonurbs fit`` and an outside
    scorer of the shared interface (``python SCRIPT CLOUD OUTDIR --gt GT``, a JSON line
    last); run again with --reuse, nothing is refitted and the table is the same."""
    stand_in = tmp_path / "stand_in.py"
    stand_in.write_text(STAND_IN)
    args = ["--cases", "seed_patch16", "--scorer", str(stand_in), "--reuse", str(tmp_path / "run")]
    assert runner.main(args) == 0
    first = capsys.readouterr().out
    rows = [line for line in first.splitlines() if line.startswith("| seed_patch16 |")]
    assert [row.split(" | ")[1] for row in rows[:2]] == ["classical", "swarm"]
    assert rows[0].startswith("| seed_patch16 | classical | open | plane | 0.5 | 0.25 |")
    assert rows[2] == "| seed_patch16 | 0.5 | 0.5 | 0.25 | 0.25 | 1.00 |"  # the swarm / classical ratio
    fitted = tmp_path / "run" / "results" / "this" / "swarm" / "seed_patch16" / "seed_patch16.json"
    stamp = fitted.stat().st_mtime_ns
    assert runner.main(args) == 0
    again = capsys.readouterr().out
    assert fitted.stat().st_mtime_ns == stamp
    assert [line for line in again.splitlines() if line.startswith("| seed_patch16 |")] == rows


def test_the_runner_refuses_what_it_cannot_run(tmp_path):
    with pytest.raises(SystemExit, match="no case 'torus_x'"):
        runner.main(["--cases", "torus_x", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="needs --scans"):
        runner.main(["--suite", "real", "--out", str(tmp_path)])


def test_the_scorer_finds_feet_across_a_pole():
    """Points just off a sphere-topology surface near its poles, at every azimuth (the
    rings next to the poles given light weights: the surface leaves its poles fast, the
    pole is the nearest grid sample, and every u there is the same point): their
    distances are never more than a dense grid's nearest sample's."""
    from scipy.spatial import cKDTree

    from psonurbs.config import config_from_dict
    from psonurbs.fitting.pipeline import fit_points
    from psonurbs.geometry.nurbs import NurbsSurface

    rng = np.random.default_rng(2)
    d = rng.standard_normal((3000, 3))
    config = config_from_dict({"orders": [4, 4], "net_size": [8, 6], "topology": "sphere",
                               "swarm": {"particles": 1, "iterations": 1}})
    fit = fit_points(d / np.linalg.norm(d, axis=1, keepdims=True), config)
    weights = fit.surface.weights.copy()
    weights[:, [1, -2]] *= 0.15
    surface = NurbsSurface(fit.surface.degree_u, fit.surface.degree_v, fit.surface.knots_u, fit.surface.knots_v,
                           fit.surface.control_points, weights, fit.surface.closed_u, fit.surface.closed_v)
    axis = np.asarray(fit.info["parametrisation"]["axis"])
    frame = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]
    polar, azimuth = (a.ravel()[:, None] for a in np.meshgrid([0.002, 0.01, 0.03],
                                                              np.linspace(0, 2 * np.pi, 24, endpoint=False)))
    side = np.cos(azimuth) * frame[:, 0] + np.sin(azimuth) * frame[:, 1]
    points = np.concatenate([1.05 * (np.cos(polar) * pole + np.sin(polar) * side) for pole in (axis, -axis)])
    u, v = np.meshgrid(np.linspace(0, 1, 1500, endpoint=False), np.linspace(0, 1, 3000), indexing="ij")
    dense = cKDTree(surface.evaluate(u.ravel(), v.ravel()).reshape(-1, 3)).query(points)[0]
    found = scorer.SurfaceDistance(scorer.Surface(surface.to_dict()))(points)
    assert np.all(found <= dense + 1e-9)


def test_a_rounded_edge_joins_its_two_faces_into_one_region_and_the_sharp_edges_still_part_them():
    """The benchmark's box with one edge rounded (radius 0.1, a quarter of its height):
    the fillet, bending 90 degrees over 8 point spacings, is no crease; the box's other
    edges are. Five regions: the bottom, fillet and front as one; top, back, two ends."""
    from psonurbs.objects.regions import segment

    objects = load("objects", REPO / "benchmarks" / "objects.py")
    points, _, _ = objects.sample(objects.OBJECTS["filleted_box"], 0)
    regions = segment(points)
    assert regions.count == 5
    largest = points[regions.members(0)]
    assert largest[:, 1].min() < 0.01 and largest[:, 2].min() < 0.01  # holds the front (y = 0) and the bottom (z = 0)
    assert np.ptp(largest[:, 1]) > 0.5 and np.ptp(largest[:, 2]) > 0.25  # and reaches across both

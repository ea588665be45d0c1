"""Self-checks without ground truth (psonurbs.fitting.finish.self_checks): quiet on good surfaces of
every topology, loud on a surface that flaps out of the box, folds or leaves the data,
and reported through the CLI (a warning, the summary status, --fail-suspect)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import ply_bytes

from psonurbs.config import config_from_dict
from psonurbs.fitting.finish.self_checks import MAX_FOLDED, check_fit, flipped_share
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.parameters.topology import layout_for
from psonurbs.fitting.pipeline import fit_points
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.trim import Trim, polygon_loop


def least_squares(topology: str, size, degrees, uv: np.ndarray, points: np.ndarray) -> NurbsSurface:
    """The classical least-squares surface of a topology at known parameters: a good fit."""
    layout = layout_for(topology, size, degrees)
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-6, layout.constraint_operator())
    weights = np.ones(layout.n_free)
    return layout.surface(solver.solve(layout.rows(uv, weights), points), weights)


def sheet(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    return np.stack([x, y, 0.6 * np.exp(-2 * (x * x + y * y))], -1)


def curl(u, v):
    a = np.radians(250.0) * u
    return np.stack([np.cos(a), np.sin(a), 1.5 * v], -1)


def tube(u, v):
    return np.stack([np.cos(2 * np.pi * u), np.sin(2 * np.pi * u), 3.0 * v], -1)


def ball(u, v):
    th, ph = 2 * np.pi * u, np.pi * v
    return np.stack([np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), -np.cos(ph)], -1)


def ring(u, v):
    th, ph = 2 * np.pi * u, 2 * np.pi * v
    return np.stack([(1 + 0.35 * np.cos(ph)) * np.cos(th), (1 + 0.35 * np.cos(ph)) * np.sin(th),
                     0.35 * np.sin(ph)], -1)


def ellipse_with_holes(u, v):
    inside = ((u - 0.5) / 0.48) ** 2 + ((v - 0.5) / 0.36) ** 2 < 1.0
    return inside & ((u - 0.32) ** 2 + (v - 0.5) ** 2 > 0.09 ** 2) & ((u - 0.68) ** 2 + (v - 0.55) ** 2 > 0.06 ** 2)


GOOD = [  # (name, topology, net, degrees, shape, footprint)
    ("height field", "open", (8, 8), (3, 3), sheet, None),
    ("plate over an ellipse with two holes", "open", (8, 8), (3, 3), sheet, ellipse_with_holes),
    ("250-degree curl", "open", (10, 6), (3, 3), curl, None),
    ("cylinder", "cylinder", (10, 6), (3, 3), tube, None),
    ("sphere", "sphere", (10, 8), (3, 3), ball, None),
    ("torus", "torus", (14, 8), (3, 3), ring, None),
]


@pytest.mark.parametrize("name, topology, net, degrees, shape, footprint", GOOD, ids=[g[0] for g in GOOD])
def test_quiet_on_a_good_surface_of_every_kind(name, topology, net, degrees, shape, footprint):
    rng = np.random.default_rng(0)
    uv = rng.random((6000, 2))
    if footprint is not None:
        uv = uv[footprint(uv[:, 0], uv[:, 1])]
    pts = shape(uv[:, 0], uv[:, 1])
    checks = check_fit(least_squares(topology, net, degrees, uv, pts), pts)
    assert not checks.suspect, (name, checks.warnings)
    assert checks.folded == 0.0


def test_quiet_on_sixteen_points_interpolated():
    """A sparse cloud is far from most of its surface; far is judged against its spacing."""
    u, v = np.meshgrid(np.linspace(0, 1, 4), np.linspace(0, 1, 4), indexing="ij")
    uv = np.column_stack([u.ravel(), v.ravel()])
    pts = sheet(uv[:, 0], uv[:, 1])
    assert not check_fit(least_squares("open", (4, 4), (2, 2), uv, pts), pts).suspect


def good_sheet():
    rng = np.random.default_rng(1)
    uv = rng.random((3000, 2))
    pts = sheet(uv[:, 0], uv[:, 1])
    return least_squares("open", (6, 6), (3, 3), uv, pts), pts


def test_a_net_flung_out_of_the_box_is_flagged():
    surface, pts = good_sheet()
    net = surface.control_points.copy()
    net[5, 5] += [0.0, 0.0, 40.0]  # a corner control point 40 units up (the cloud is 3 across)
    bad = NurbsSurface(3, 3, surface.knots_u, surface.knots_v, net, surface.weights)
    checks = check_fit(bad, pts)
    assert checks.net_extent_ratio > 10 and checks.extent_ratio > 1.5
    assert any("control net reaches" in w for w in checks.warnings)
    assert any("surface reaches" in w for w in checks.warnings)


def test_a_folded_sheet_is_flagged_and_a_smooth_hairpin_is_not():
    """A sheet folded flat onto itself along u = 1/2 (x runs out and back on the plane
    z = 0): its normal flips across the crease. Lifted into a hairpin (z rising with u),
    the same parameters give a smooth U-turn, whose normal turns but never flips."""
    rng = np.random.default_rng(2)
    uv = rng.random((3000, 2))
    x = np.sin(np.pi * uv[:, 0])  # out to 1 and back to 0
    for lift, folded in ((0.0, True), (0.3, False)):
        pts = np.column_stack([x, uv[:, 1], lift * uv[:, 0]])
        checks = check_fit(least_squares("open", (8, 5), (3, 3), uv, pts), pts)
        assert (checks.folded > MAX_FOLDED) == folded, lift
        assert any("folds" in w for w in checks.warnings) == folded


def test_a_surface_mostly_away_from_the_data_is_flagged():
    """Data on a tenth of the domain only, extrapolated over the rest."""
    surface, pts = good_sheet()
    near_corner = pts[(pts[:, 0] < -0.7) & (pts[:, 1] < -0.7)]
    checks = check_fit(surface, near_corner)
    assert checks.uncovered > 0.5
    assert any("far from every point" in w for w in checks.warnings)


def test_flipped_share_counts_the_pairs_across_a_fold():
    normals = np.zeros((64, 64, 3))
    normals[..., 2] = 1.0
    assert flipped_share(normals) == 0.0
    normals[32:, :, 2] = -1.0  # one fold line across u
    assert flipped_share(normals) == pytest.approx(64 / (2 * 63 * 64))
    normals[10, 10] = 0.0  # a vanishing normal (a pole) is not judged
    assert flipped_share(normals) == pytest.approx(64 / (2 * 63 * 64 - 4))


def test_the_plane_fit_of_a_curl_is_flagged_and_the_intrinsic_one_is_not():
    """The failure the checks are for: a 250-degree curl fitted over a plane projection
    flaps far outside the data; with the intrinsic parameters it is fitted to the noise."""
    rng = np.random.default_rng(3)
    uv = rng.random((1500, 2))
    pts = curl(uv[:, 0], uv[:, 1]) + rng.normal(0.0, 2e-3, (1500, 3))
    results = {}
    for method in ("plane", "intrinsic"):
        cfg = config_from_dict({"orders": [4, 4], "net_size": [10, 6], "parametrisation": method,
                                "swarm": {"particles": 1, "iterations": 1}})
        results[method] = fit_points(pts, cfg)
    assert results["plane"].warnings and results["plane"].metrics["suspect"]
    assert any(note.startswith("suspect fit: ") for note in results["plane"].notes)
    good = results["intrinsic"]
    assert not good.warnings and good.metrics["suspect"] is False
    assert good.metrics["rmse"] < 1.05 * 2e-3
    assert good.info["parametrisation"]["method"] == "intrinsic"
    radius = np.hypot(*good.surface.evaluate_grid(*good.surface.parameter_grid(40, 40))[..., :2].transpose(2, 0, 1))
    assert np.abs(radius - 1.0).max() < 0.01  # the surface itself is the cylinder


# ---- through the command line --------------------------------------------------------

@pytest.fixture
def cloud(tmp_path):
    path = tmp_path / "scan.ply"
    path.write_bytes(ply_bytes(np.random.default_rng(0).random((20, 3))))
    return path


def with_warning(fake_fit):
    from conftest import FakeResult

    fake_fit.behaviour = lambda: FakeResult(notes=["suspect fit: the surface folds"],
                                            warnings=["the surface folds"])
    return fake_fit


def test_a_suspect_fit_is_written_warned_about_and_marked_but_exits_0(tmp_path, fake_fit, cloud):
    out = tmp_path / "out"
    result = with_warning(fake_fit).run("fit", cloud, "-o", out, "-q")
    assert result.exit_code == 0
    assert result.stderr == f"psonurbs: warning: {cloud}: suspect fit: the surface folds\n"
    assert "; suspect fit: the surface folds" in result.stdout
    assert (out / "scan.json").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["clouds"][0]["status"] == "suspect" and summary["counts"]["suspect"] == 1
    assert summary["exit_code"] == 0


def test_fail_suspect_makes_it_a_gate_failure(tmp_path, fake_fit, cloud):
    out = tmp_path / "out"
    result = with_warning(fake_fit).run("fit", cloud, "-o", out, "-q", "--fail-suspect")
    assert result.exit_code == 3
    assert f"psonurbs: gate exceeded: {cloud}: suspect fit (1 self-check failed) with --fail-suspect" in result.stderr
    assert (out / "scan.json").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["clouds"][0]["status"] == "gate-exceeded" and summary["gate"]["fail_suspect"] is True


def test_fail_suspect_passes_a_good_fit(tmp_path, fake_fit, cloud):
    assert fake_fit.run("fit", cloud, "-o", tmp_path / "out", "-q", "--fail-suspect").exit_code == 0


def test_a_trimmed_face_is_judged_inside_its_loops_only():
    """The sheet folded along u = 1/2, trimmed to u < 0.4: the fold lies beyond the loops,
    outside the face the user gets, and is not flagged; trimmed to u < 0.7 it is inside."""
    rng = np.random.default_rng(2)
    uv = rng.random((3000, 2))
    pts = np.column_stack([np.sin(np.pi * uv[:, 0]), uv[:, 1], np.zeros(len(uv))])
    surface = least_squares("open", (8, 5), (3, 3), uv, pts)
    whole = check_fit(surface, pts)
    assert whole.folded > MAX_FOLDED

    def trimmed_to(u_max):
        box = np.array([[0.05, 0.05], [u_max, 0.05], [u_max, 0.95], [0.05, 0.95]])
        return check_fit(surface, pts, trim=Trim((polygon_loop(box),)))

    assert trimmed_to(0.4).folded == 0.0 and not trimmed_to(0.4).suspect
    assert trimmed_to(0.7).folded > MAX_FOLDED
    assert trimmed_to(0.4).extent_ratio <= whole.extent_ratio

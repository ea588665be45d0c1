"""``psonurbs score``: distances from a cloud to a saved surface."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import ply_bytes, run

from psonurbs.errors import InputError
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.run.scoring import load_surface, score

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "data_samples"


def plane() -> NurbsSurface:
    """The square [0, 4] x [0, 2] in z = 1, as a biquadratic rational surface."""
    u, v = np.meshgrid(np.linspace(0, 4, 4), np.linspace(0, 2, 3), indexing="ij")
    cp = np.stack([u, v, np.ones_like(u)], -1)
    return NurbsSurface(2, 2, [0, 0, 0, 0.5, 1, 1, 1], [0, 0, 0, 1, 1, 1], cp, np.ones((4, 3)))


def cloud_over_plane(offsets: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(1)
    n = len(offsets)
    return np.stack([rng.uniform(0.2, 3.8, n), rng.uniform(0.2, 1.8, n), 1.0 + offsets], -1)


def test_score_figures_are_the_distances():
    offsets = np.linspace(-0.05, 0.05, 101)
    points = cloud_over_plane(offsets)
    figures = score([(plane(), None)], points)
    d = np.abs(offsets)
    assert figures["points"] == 101
    assert figures["rmse"] == pytest.approx(np.sqrt(np.mean(d ** 2)), rel=1e-9, abs=1e-12)
    assert figures["max_error"] == pytest.approx(0.05, rel=1e-9)
    assert figures["mean_error"] == pytest.approx(d.mean(), rel=1e-9)
    for p in (50, 90, 95, 99):
        assert figures[f"p{p}"] == pytest.approx(np.percentile(d, p), rel=1e-8, abs=1e-12)
    diag = np.linalg.norm(points.max(0) - points.min(0))
    assert figures["bbox_diagonal"] == pytest.approx(diag)
    assert figures["rmse_relative"] == pytest.approx(figures["rmse"] / diag)
    assert figures["p99_relative"] == pytest.approx(figures["p99"] / diag)


def write_case(tmp_path: Path, offsets) -> tuple[Path, Path]:
    surface_json = tmp_path / "fit.json"
    surface_json.write_text(json.dumps({"cloud": "scan.ply", "surface": plane().to_dict()}))
    cloud = tmp_path / "scan.ply"
    cloud.write_bytes(ply_bytes(cloud_over_plane(np.asarray(offsets, float))))
    return surface_json, cloud


def test_cli_table(tmp_path):
    surface_json, cloud = write_case(tmp_path, [0.01, -0.01, 0.01, -0.01])
    result = run("score", surface_json, cloud)
    assert result.exit_code == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == f"{surface_json} vs {cloud}"
    table = {line.split()[0]: line.split()[1:] for line in lines[2:]}
    assert table["points"] == ["4"]
    assert float(table["rmse"][0]) == pytest.approx(0.01, rel=1e-5)
    assert float(table["max"][0]) == pytest.approx(0.01, rel=1e-5)
    assert set(table) >= {"mean", "p50", "p90", "p95", "p99", "bbox"}


def test_cli_json_and_gate(tmp_path):
    surface_json, cloud = write_case(tmp_path, [0.02, 0.0, -0.02, 0.0])
    result = run("score", surface_json, cloud, "--json")
    assert result.exit_code == 0
    doc = json.loads(result.stdout)
    assert doc["points"] == 4 and doc["rmse"] == pytest.approx(np.sqrt(2e-4), rel=1e-6)
    assert doc["max_error_relative"] == pytest.approx(0.02 / doc["bbox_diagonal"], rel=1e-6)
    gated = run("score", surface_json, cloud, "--json", "--max-rmse", "0.01")
    assert gated.exit_code == 3
    assert json.loads(gated.stdout)["rmse"] == doc["rmse"]  # still reported
    assert "gate exceeded" in gated.stderr
    assert run("score", surface_json, cloud, "--max-rmse-rel", "0.01").exit_code == 0


def test_a_bare_surface_object_is_accepted(tmp_path):
    path = tmp_path / "s.json"
    path.write_text(json.dumps(plane().to_dict()))
    surface, _ = load_surface(path)
    assert surface.shape == (4, 3)


@pytest.mark.parametrize("content, problem", [
    ("{not json", "malformed JSON"),
    ("[1, 2]", "expected an object"),
    ('{"surface": {"degree_u": 2}}', "missing degree_v, knots_u, knots_v, control_points"),
    ('{"degree_u": 1, "degree_v": 1, "knots_u": [0, 1], "knots_v": [0, 0, 1, 1], '
     '"control_points": [[[0, 0, 0], [0, 1, 0]], [[1, 0, 0], [1, 1, 0]]]}', "invalid surface"),
])
def test_bad_surface_file_is_exit_2(tmp_path, content, problem):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(InputError, match=problem):
        load_surface(path)
    result = run("score", path, SAMPLES / "seed_patch16.ply")
    assert result.exit_code == 2
    assert result.stderr.startswith(f"psonurbs: error: {path}: ") and problem in result.stderr


def test_bad_cloud_is_exit_2(tmp_path):
    surface_json, _ = write_case(tmp_path, [0.0, 0.0, 0.0])
    result = run("score", surface_json, tmp_path / "nope.ply")
    assert result.exit_code == 2
    assert result.stderr == f"psonurbs: error: {tmp_path / 'nope.ply'}: no such file\n"


def test_score_agrees_with_the_fit(tmp_path):
    pytest.importorskip("psonurbs.fitting.pipeline")
    out = tmp_path / "out"
    assert run("fit", SAMPLES / "quarter_cylinder.ply", "-c", SAMPLES / "quarter_cylinder.yaml",
               "-o", out, "--particles", "6", "--iterations", "5", "-q").exit_code == 0
    claimed = json.loads((out / "quarter_cylinder.json").read_text())["metrics"]
    result = run("score", out / "quarter_cylinder.json", SAMPLES / "quarter_cylinder.ply", "--json")
    measured = json.loads(result.stdout)
    assert measured["rmse"] == pytest.approx(claimed["rmse"], rel=1e-6)
    assert measured["max_error"] == pytest.approx(claimed["max_error"], rel=1e-6)

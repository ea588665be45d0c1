"""``psonurbs plot`` and ``psonurbs demo``: the PNGs exist, have their size, are not blank."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import closed_u_surface, open_surface, ply_bytes, run

from psonurbs.formats.outputs import render_csv
from psonurbs.run.plots import SIZES

matplotlib = pytest.importorskip("matplotlib")
from matplotlib.image import imread  # noqa: E402


def write_fit(directory: Path, surface, stem: str = "scan") -> Path:
    """A fit's files as `psonurbs fit` writes them: JSON, error curve, and the cloud beside."""
    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(2)
    u = rng.uniform(*surface.domain_u, 400)
    v = rng.uniform(*surface.domain_v, 400)
    points = surface.evaluate(u, v) + rng.normal(0, 0.01, (400, 3))
    (directory / f"{stem}.ply").write_bytes(ply_bytes(points))
    doc = {"psonurbs_version": "0", "cloud": f"{stem}.ply", "topology": "open",
           "surface": surface.to_dict(), "metrics": {}}
    path = directory / f"{stem}.json"
    path.write_text(json.dumps(doc))
    best = 1.0 / np.arange(1, 21)
    curve = np.column_stack([np.arange(1, 21), best, best * 1.5])
    (directory / f"{stem}_error.csv").write_text(
        render_csv(["iteration", "best_rmse", "mean_rmse"], curve))
    return path


def check_png(path: Path, kind: str) -> None:
    assert path.is_file(), path
    image = imread(str(path))
    height, width = image.shape[:2]
    assert (width, height) == SIZES[kind]
    gray = image[..., :3].mean(axis=2)
    assert gray.std() > 0.02, f"{path.name} looks blank"
    assert (gray < 0.5).mean() > 0.001, f"{path.name} has (almost) nothing drawn"


@pytest.mark.parametrize("make", [open_surface, closed_u_surface])
def test_plot_writes_every_picture(tmp_path, make):
    result_json = write_fit(tmp_path / "res", make())
    result = run("plot", result_json)
    assert result.exit_code == 0, result.stderr
    assert result.stderr == ""
    names = ["curve", "views", "distance", "domain", "basis"]
    assert result.stdout.splitlines() == [str(tmp_path / "res" / f"scan_{n}.png") for n in names]
    for name in names:
        check_png(tmp_path / "res" / f"scan_{name}.png", name)


def test_plot_without_cloud_draws_surface_and_net(tmp_path, monkeypatch):
    result_json = write_fit(tmp_path / "res", open_surface())
    (tmp_path / "res" / "scan.ply").unlink()
    monkeypatch.chdir(tmp_path)
    result = run("plot", result_json, "-o", tmp_path / "pics")
    assert result.exit_code == 0, result.stderr
    assert "cloud scan.ply not found" in result.stderr
    assert sorted(p.name for p in (tmp_path / "pics").iterdir()) == \
        ["scan_basis.png", "scan_curve.png", "scan_domain.png", "scan_views.png"]
    check_png(tmp_path / "pics" / "scan_views.png", "views")


def test_plot_finds_the_cloud_in_the_cwd_or_by_option(tmp_path, monkeypatch):
    result_json = write_fit(tmp_path / "res", open_surface())
    (tmp_path / "res" / "scan.ply").rename(tmp_path / "scan.ply")
    monkeypatch.chdir(tmp_path)
    assert run("plot", result_json).exit_code == 0
    assert (tmp_path / "res" / "scan_distance.png").is_file()
    os.remove(tmp_path / "res" / "scan_distance.png")
    (tmp_path / "scan.ply").rename(tmp_path / "elsewhere.ply")
    assert run("plot", result_json, "--cloud", tmp_path / "elsewhere.ply").exit_code == 0
    check_png(tmp_path / "res" / "scan_distance.png", "distance")


def test_plot_bad_input_is_exit_2(tmp_path):
    result = run("plot", tmp_path / "nope.json")
    assert result.exit_code == 2
    assert result.stderr == f"psonurbs: error: {tmp_path / 'nope.json'}: no such file\n"


def test_plot_without_matplotlib_is_exit_2(tmp_path, monkeypatch):
    import builtins

    result_json = write_fit(tmp_path, open_surface())
    real_import = builtins.__import__

    def no_matplotlib(name, *args, **kwargs):
        if name.startswith("matplotlib"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    result = run("plot", result_json)
    assert result.exit_code == 2
    assert "pip install 'psonurbs[plot]'" in result.stderr


def test_demo_fits_the_samples_and_plots(tmp_path):
    pytest.importorskip("psonurbs.fitting.pipeline")
    out = tmp_path / "demo"
    result = run("demo", out, "-q")
    assert result.exit_code == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == f"wrote 2 sample clouds and their configs to {out / 'clouds'}"
    assert lines[1].startswith("bump.ply: 1500 points, net 6x6 (open), rmse ")
    assert lines[2].startswith("quarter_cylinder.ply: 800 points, net 3x2 (open), rmse ")
    summary = json.loads((out / "results" / "summary.json").read_text())
    assert [c["status"] for c in summary["clouds"]] == ["ok", "ok"]
    assert all(c["rmse_relative"] < 0.01 for c in summary["clouds"])
    for name in ("bump.ply", "bump.yaml", "quarter_cylinder.ply", "quarter_cylinder.yaml"):
        assert (out / "clouds" / name).is_file()
    # the clouds are the same every time
    again = tmp_path / "again"
    from psonurbs.run.demo import write_samples

    write_samples(again)
    assert (again / "bump.ply").read_bytes() == (out / "clouds" / "bump.ply").read_bytes()


def test_plot_of_a_trimmed_fit_draws_its_loops(tmp_path):
    from test_trim import plate_trim

    surface, trim = open_surface(), plate_trim()
    result_json = write_fit(tmp_path / "res", surface)
    doc = json.loads(result_json.read_text())
    doc["surface"]["trim"] = trim.to_list()
    result_json.write_text(json.dumps(doc))
    result = run("plot", result_json)
    assert result.exit_code == 0, result.stderr
    check_png(tmp_path / "res" / "scan_domain.png", "domain")
    check_png(tmp_path / "res" / "scan_views.png", "views")
    # the loops are drawn: red pixels along the outer loop
    image = imread(str(tmp_path / "res" / "scan_domain.png"))[..., :3]
    red = (image[..., 0] > 0.7) & (image[..., 1] < 0.4) & (image[..., 2] < 0.4)
    assert red.mean() > 0.002

"""Batch runs: input expansion, the worker pool, the summary files."""
from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import GOOD, ply_bytes, run

from psonurbs.config import FitConfig
from psonurbs.formats.outputs import render_ply
from psonurbs.run.batch import run_batch
from psonurbs.run.demo import SAMPLES as DEMO_SAMPLES
from psonurbs.run.gate import Gate
from psonurbs.run.inputs import expand_inputs, jobs_from_inputs
from psonurbs.run.summary import Row, exit_code, render_summary_csv, write_summary

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "data_samples"
CONTRACT = ("{}.json", "{}.obj", "{}.ply", "{}_error.csv")


def touch(path: Path, content: bytes = b"0 0 0\n") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(content)
    return path


# ---- input expansion ----------------------------------------------------------------

def test_expand_files_directories_and_globs(tmp_path):
    scans = tmp_path / "scans"
    b = touch(scans / "b.xyz")
    a = touch(scans / "a.PLY")
    touch(scans / "notes.yaml")
    (scans / "sub").mkdir()
    deep = touch(scans / "sub" / "c.pts")
    single = touch(tmp_path / "single.ply")
    items = expand_inputs([single, scans, str(scans / "**" / "*.pts"), str(scans / "a.*"),
                           tmp_path / "missing.ply"])
    # a directory gives its clouds (not the YAML, not the sub-directory), sorted; a glob
    # its matching clouds; a path met twice is fitted once; a missing file stays (the
    # reader reports it)
    assert items == [single, a, b, deep, tmp_path / "missing.ply"]


def test_expand_reports_empty_directories_and_patterns(tmp_path):
    (tmp_path / "empty").mkdir()
    touch(tmp_path / "only.yaml")
    items = expand_inputs([tmp_path / "empty", str(tmp_path / "*.ply")])
    assert all(isinstance(item, Row) and item.status == "bad-input" for item in items)
    assert items[0].message == (f"{tmp_path / 'empty'}: directory has no point cloud files "
                                "(.ply, .pcd, .xyz, .txt, .pts, .las, .laz, .e57)")
    assert items[1].message == f"{tmp_path / '*.ply'}: no point cloud files match this pattern"
    jobs = jobs_from_inputs(items, FitConfig())
    rows = run_batch(jobs, tmp_path / "out")
    assert [r.message for r in rows] == [i.message for i in items]


def test_cli_takes_a_directory_and_a_quoted_glob(tmp_path, fake_fit):
    scans = tmp_path / "scans"
    touch(scans / "one.ply", ply_bytes(GOOD))
    touch(scans / "two.ply", ply_bytes(GOOD + 1))
    touch(tmp_path / "more" / "three.ply", ply_bytes(GOOD + 2))
    out = tmp_path / "out"
    result = fake_fit.run("fit", scans, str(tmp_path / "more" / "*.ply"), "-o", out, "-q")
    assert result.exit_code == 0, result.stderr
    assert [line.split(":")[0] for line in result.stdout.splitlines()] == \
        ["one.ply", "two.ply", "three.ply"]
    for stem in ("one", "two", "three"):
        assert all((out / f.format(stem)).is_file() for f in CONTRACT)


# ---- summary ------------------------------------------------------------------------

def test_summary_rows_for_good_bad_and_gated_clouds(tmp_path, fake_fit):
    good = touch(tmp_path / "good.ply", ply_bytes(GOOD))
    bad = touch(tmp_path / "bad.xyz", b"1 2 3\n4 5\n")
    out = tmp_path / "out"
    result = fake_fit.run("fit", bad, good, "-o", out, "-q", "--max-rmse", "1e-4")
    assert result.exit_code == 2  # bad input beats the gate
    with open(out / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["file", "points", "topology", "net", "rmse", "max_error",
                             "rmse_relative", "max_error_relative", "seconds", "status", "message"]
    assert [(r["file"], r["status"]) for r in rows] == [(str(bad), "bad-input"),
                                                       (str(good), "gate-exceeded")]
    assert rows[0]["message"].startswith(f"{bad}: malformed point data at line 2")
    assert rows[0]["points"] == rows[0]["rmse"] == ""
    assert rows[1]["points"] == "16" and rows[1]["net"] == "5x5" and rows[1]["topology"] == "open"  # net_size
    assert float(rows[1]["rmse"]) == 1.234e-4 and float(rows[1]["max_error"]) == 4.567e-4
    assert rows[1]["message"] == "rmse 1.234e-04 > --max-rmse 0.0001; 16 points for 4 control points"
    assert float(rows[1]["seconds"]) >= 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["exit_code"] == 2
    assert summary["counts"] == {"ok": 0, "suspect": 0, "gate-exceeded": 1, "bad-input": 1, "worker-lost": 0,
                                 "internal-error": 0}
    assert summary["gate"] == {"max_rmse": 1e-4, "max_rmse_rel": None, "fail_suspect": False}
    assert [c["status"] for c in summary["clouds"]] == ["bad-input", "gate-exceeded"]
    assert summary["clouds"][1]["rmse"] == 1.234e-4
    assert not [p for p in out.iterdir() if ".tmp-" in p.name]


def test_summary_csv_quotes_and_keeps_numbers_exact():
    row = Row("a,b.ply", points=3, topology="open", net="2x2", rmse=0.1 + 0.2, max_error=1e-300,
              seconds=1.23456, status="ok", message='said "hi", twice')
    text = render_summary_csv([row])
    (parsed,) = list(csv.DictReader(text.splitlines()))
    assert parsed["file"] == "a,b.ply" and parsed["message"] == 'said "hi", twice'
    assert float(parsed["rmse"]) == 0.1 + 0.2 and float(parsed["max_error"]) == 1e-300
    assert parsed["seconds"] == "1.235"


def test_summary_json_has_no_nan(tmp_path):
    row = Row("x.ply", rmse=float("nan"), status="internal-error", message="boom")
    write_summary(tmp_path, [row])
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert doc["clouds"][0]["rmse"] is None and doc["exit_code"] == 1


def test_a_cloud_named_summary_is_refused(tmp_path, fake_fit):
    cloud = touch(tmp_path / "summary.ply", ply_bytes(GOOD))
    result = fake_fit.run("fit", cloud, "-o", tmp_path / "out", "-q")
    assert result.exit_code == 2
    assert "would overwrite the run summary" in result.stderr
    assert fake_fit.calls == []


@pytest.mark.parametrize("statuses, code", [
    ([], 0), (["ok"], 0), (["ok", "gate-exceeded"], 3), (["gate-exceeded", "bad-input"], 2),
    (["bad-input", "internal-error", "gate-exceeded"], 1),
])
def test_exit_code_precedence(statuses, code):
    assert exit_code([Row("f", status=s) for s in statuses]) == code


def test_gate_checks_both_bounds():
    metrics = {"rmse": 2.0, "rmse_relative": 0.01}
    assert Gate().check(metrics) == ""
    assert Gate(max_rmse=2.0, max_rmse_rel=0.01).check(metrics) == ""  # at the bound passes
    assert Gate(max_rmse=1.0).check(metrics) == "rmse 2.000e+00 > --max-rmse 1"
    assert Gate(max_rmse_rel=1e-3).check(metrics) == "relative rmse 1.000e-02 > --max-rmse-rel 0.001"
    assert Gate(max_rmse=1.0).check({"rmse": float("nan"), "rmse_relative": 0.0})  # NaN fails


# ---- the worker pool (real library) --------------------------------------------------

def small_clouds(directory: Path) -> list[Path]:
    """Three small clouds: the paper's 16 points, and subsampled demo clouds."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = [directory / "seed_patch16.ply"]
    shutil.copy(SAMPLES / "seed_patch16.ply", paths[0])
    for sample in DEMO_SAMPLES:
        path = directory / f"{sample.name}.ply"
        path.write_bytes(render_ply(sample.cloud()[:80], np.zeros((0, 3), np.int64)))
        paths.append(path)
    return paths


def test_jobs_2_writes_the_same_files_as_jobs_1(tmp_path):
    pytest.importorskip("psonurbs.fitting.pipeline")
    clouds = tmp_path / "clouds"
    paths = small_clouds(clouds)
    (clouds / "broken.xyz").write_text("1 2 3\nnot a number\n")
    outputs = {}
    for jobs in ("1", "2"):
        out = tmp_path / f"out{jobs}"
        result = run("fit", clouds, "-o", out, "--particles", "6", "--iterations", "5", "-q",
                     "--jobs", jobs, "--format", "iges")
        assert result.exit_code == 2, result.stderr  # the broken cloud
        # 80 points on a 5 x 5 net after 5 iterations may fold (a self-check warning): not an error
        errors = [line for line in result.stderr.splitlines() if not line.startswith("psonurbs: warning: ")]
        assert errors == [f"psonurbs: error: {clouds / 'broken.xyz'}: malformed "
                          "point data at line 2: 'not' is not a number"]
        outputs[jobs] = out
    names = sorted(p.name for p in outputs["1"].iterdir())
    assert names == sorted(p.name for p in outputs["2"].iterdir())
    assert len(names) == 5 * len(paths) + 2  # 4 contract files + .igs per cloud, the summary
    for name in names:
        if not name.startswith("summary."):
            assert (outputs["1"] / name).read_bytes() == (outputs["2"] / name).read_bytes(), name
    rows = [json.loads((outputs[j] / "summary.json").read_text())["clouds"] for j in ("1", "2")]
    strip = [[{k: v for k, v in r.items() if k != "seconds"} for r in rs] for rs in rows]
    assert strip[0] == strip[1]  # same rows, same (input) order
    assert rows[0][0]["status"] == "bad-input"
    assert all(r["status"] in ("ok", "suspect") for r in rows[0][1:])  # fitted and written

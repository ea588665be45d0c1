"""The ``psonurbs`` command line: exit codes, messages, and what is (not) written.

Most tests pass a stand-in fitter (``fake_fit``, see conftest.py) so that the CLI's own
work (reading, reporting, the output contract) is tested apart from the numerics; the
end-to-end tests at the bottom use the real library.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import GOOD, REPO, SAMPLES, FakeResult, ply_bytes, run

import psonurbs


def bad_clouds(tmp: Path) -> dict[str, tuple[Path, str]]:
    """name -> (path, the problem the message must state)."""
    nan = GOOD.copy()
    nan[[1, 5], 2] = np.nan
    inf = GOOD.copy()
    inf[3, 0] = np.inf
    (tmp / "adir.ply").mkdir()
    files = {
        "garbage.ply": (b"\x00\x01 this is not a ply \xff" * 10, "not a PLY file"),
        "empty.xyz": (b"", "file is empty"),
        "header_only.ply": (ply_bytes(np.zeros((0, 3))), "PLY file has no vertices"),
        "faces_only.ply": (b"ply\nformat ascii 1.0\nelement face 1\n"
                           b"property list uchar int vertex_indices\nend_header\n3 0 1 2\n",
                           "PLY file has no vertices"),
        "nan.ply": (ply_bytes(nan), "2 of 16 points have non-finite coordinates (2 NaN, 0 infinite)"),
        "inf.ply": (ply_bytes(inf), "1 of 16 points have non-finite coordinates (0 NaN, 1 infinite)"),
        "malformed.xyz": (b"0 0 0\n1 0 1\n1 1 one\n", "line 3: 'one' is not a number"),
    }
    out = {}
    for name, (content, problem) in files.items():
        (tmp / name).write_bytes(content)
        out[name] = (tmp / name, problem)
    out["missing.ply"] = (tmp / "missing.ply", "no such file")
    out["adir.ply"] = (tmp / "adir.ply", "directory has no point cloud files")  # dirs are expanded
    return out


def only_summary(out: Path) -> bool:
    """Nothing but the run summary was written to ``out``."""
    return sorted(p.name for p in out.iterdir()) == ["summary.csv", "summary.json"]


def stem_files(out: Path, stem: str) -> list[str]:
    if not out.exists():
        return []
    return sorted(p.name for p in out.iterdir() if p.name.split(".")[0].removesuffix("_error") == stem)


# ---- top level -------------------------------------------------------------

def test_version():
    result = run("--version")
    assert result.exit_code == 0
    assert result.output.strip() == f"psonurbs, version {psonurbs.__version__}"


def test_fit_help_lists_exit_codes_and_examples():
    result = run("fit", "--help")
    assert result.exit_code == 0
    text = " ".join(result.output.split())
    for needle in ["Exit codes:", "0 every cloud was fitted", "1 internal error",
                   "2 unusable input or config", "130 interrupted",
                   "psonurbs fit scan.ply -o results/", "--particles", "--topology"]:
        assert needle in text


def test_no_cloud_is_a_usage_error(tmp_path):
    result = run("fit", "-o", tmp_path / "out")
    assert result.exit_code == 2
    assert "Missing argument" in result.stderr


# ---- config errors: exit 2 before anything is fitted ------------------------------

def test_config_error_exits_2_before_fitting(tmp_path, fake_fit):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("swarm:\n  particles: -3\n")
    cloud = tmp_path / "good.ply"
    cloud.write_bytes(ply_bytes(GOOD))
    result = fake_fit.run("fit", cloud, "-c", cfg, "-o", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr == (f"psonurbs: error: {cfg}: config key 'swarm.particles': "
                             "expected a positive integer, got -3\n")
    assert result.stdout == ""
    assert fake_fit.calls == []
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("text, needle", [
    ("orders: [6, 3]\nnet_size: [5, 5]\n", "config key 'orders': order 6 in u is larger than net_size 5"),
    ("swarm:\n  partciles: 3\n", "unknown config key 'swarm.partciles'"),
    ("orders: [3, 3\n", "malformed YAML in"),
    ("swarm:\n  seed: yes\n", "config key 'swarm.seed': expected an integer >= 0, got true"),
])
def test_config_errors_name_the_key(tmp_path, fake_fit, text, needle):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(text)
    result = fake_fit.run("fit", SAMPLES / "seed_patch16.ply", "-c", cfg, "-o", tmp_path / "out")
    assert result.exit_code == 2
    assert needle in result.stderr and str(cfg) in result.stderr
    assert len(result.stderr.splitlines()) == 1
    assert fake_fit.calls == []


def test_missing_config_file(tmp_path, fake_fit):
    result = fake_fit.run("fit", SAMPLES / "seed_patch16.ply", "-c", tmp_path / "nope.yaml", "-o", tmp_path)
    assert result.exit_code == 2
    assert result.stderr == f"psonurbs: error: {tmp_path / 'nope.yaml'}: config file not found\n"


def test_bad_override_names_the_key(tmp_path, fake_fit):
    result = fake_fit.run("fit", SAMPLES / "seed_patch16.ply", "--particles", "0", "-o", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr == ("psonurbs: error: command-line options: config key 'swarm.particles': "
                             "expected a positive integer, got 0\n")
    assert fake_fit.calls == []


def test_parametrisation_override_reaches_the_fit_and_overrides_the_file(tmp_path, fake_fit):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("parametrisation: plane\n")
    for args, expected in (([], "plane"), (["--parametrisation", "intrinsic"], "intrinsic")):
        result = fake_fit.run("fit", SAMPLES / "seed_patch16.ply", "-c", cfg, "-o", tmp_path / "out", *args)
        assert result.exit_code == 0, result.stderr
        assert fake_fit.calls[-1][1].parametrisation == expected
    assert json.loads((tmp_path / "out" / "seed_patch16.json").read_text())["config"]["parametrisation"] == "intrinsic"


def test_bad_topology_choice(tmp_path):
    result = run("fit", SAMPLES / "seed_patch16.ply", "--topology", "klein", "-o", tmp_path)
    assert result.exit_code == 2
    assert "'klein' is not one of" in result.stderr


# ---- bad clouds: exit 2, one line naming file and problem, nothing written -----

@pytest.mark.parametrize("name", ["garbage.ply", "empty.xyz", "header_only.ply", "faces_only.ply",
                                  "nan.ply", "inf.ply", "malformed.xyz", "missing.ply", "adir.ply"])
def test_bad_cloud(tmp_path, fake_fit, name):
    path, problem = bad_clouds(tmp_path)[name]
    out = tmp_path / "out"
    result = fake_fit.run("fit", path, "-o", out)
    assert result.exit_code == 2
    lines = result.stderr.splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(f"psonurbs: error: {path}: ")
    assert problem in lines[0]
    assert lines[0].count(str(path)) == 1  # the path is not repeated
    assert result.stdout == ""
    assert fake_fit.calls == []
    assert stem_files(out, path.stem) == []


def test_every_bad_cloud_is_reported(tmp_path, fake_fit):
    clouds = bad_clouds(tmp_path)
    result = fake_fit.run("fit", *[p for p, _ in clouds.values()], "-o", tmp_path / "out", "-q")
    assert result.exit_code == 2
    lines = result.stderr.splitlines()
    assert len(lines) == len(clouds)
    for line, (path, problem) in zip(lines, clouds.values()):
        assert line.startswith(f"psonurbs: error: {path}: ") and problem in line
    assert only_summary(tmp_path / "out")


def test_unfittable_cloud_from_the_library(tmp_path, fake_fit):
    cloud = tmp_path / "tiny.xyz"
    cloud.write_text("0 0 0\n1 0 0\n0 1 0\n")
    result = fake_fit.run("fit", cloud, "-o", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr == (f"psonurbs: error: {cloud}: 3 points are too few for "
                             "orders (3, 3)\n")
    assert only_summary(tmp_path / "out")


def test_same_stem_twice_is_refused(tmp_path, fake_fit):
    (tmp_path / "a").mkdir()
    first = tmp_path / "good.ply"
    first.write_bytes(ply_bytes(GOOD))
    second = tmp_path / "a" / "good.xyz"
    np.savetxt(second, GOOD + 1)
    out = tmp_path / "out"
    result = fake_fit.run("fit", first, second, "-o", out)
    assert result.exit_code == 2
    assert result.stderr.startswith(f"psonurbs: error: {second}: has the same name as {first}")
    assert len(fake_fit.calls) == 1
    doc = json.loads((out / "good.json").read_text())
    assert doc["cloud"] == "good.ply"


# ---- the output contract (fake library) ------------------------------------------

def test_good_cloud_outputs_and_summary(tmp_path, fake_fit):
    cloud = tmp_path / "good.ply"
    cloud.write_bytes(ply_bytes(GOOD))
    out = tmp_path / "out"
    result = fake_fit.run("fit", cloud, "-o", out, "--seed", "3", "--iterations", "2")
    assert result.exit_code == 0, result.stderr
    assert result.stderr == ""  # stderr is not a TTY: no progress bar
    line = result.stdout.strip()
    assert "\n" not in line
    assert line.startswith("good.ply: 16 points, net 5x5 (open), rmse 1.23e-04, max 4.57e-04, ")  # net_size
    assert line.endswith(" s; 16 points for 4 control points")

    assert stem_files(out, "good") == ["good.json", "good.obj", "good.ply", "good_error.csv"]
    doc = json.loads((out / "good.json").read_text())
    assert list(doc) == ["psonurbs_version", "cloud", "topology", "surface", "metrics", "fit",
                         "notes", "config"]
    assert doc["psonurbs_version"] == psonurbs.__version__
    assert doc["cloud"] == "good.ply"
    assert doc["metrics"] == {"rmse": 1.234e-4, "max_error": 4.567e-4, "n_points": 16}
    assert doc["surface"]["knots_u"] == [0.0, 0.0, 1.0, 1.0]
    assert doc["config"]["swarm"]["seed"] == 3 and doc["config"]["swarm"]["iterations"] == 2
    assert doc["notes"] == ["16 points for 4 control points"]
    assert str(tmp_path) not in (out / "good.json").read_text()  # no absolute paths
    assert (out / "good_error.csv").read_text() == \
        "iteration,best_rmse,mean_rmse\n0,0.20000000000000001,0.29999999999999999\n" \
        "1,0.10000000000000001,0.25\n"
    n = 101 * 101
    assert (out / "good.obj").read_text().count("\nv ") == n
    (_, config), = fake_fit.calls
    assert config.swarm.seed == 3


def test_mixed_good_and_bad_clouds(tmp_path, fake_fit):
    good = tmp_path / "good.ply"
    good.write_bytes(ply_bytes(GOOD))
    bad = tmp_path / "bad.xyz"
    bad.write_text("1 2 3\n4 5\n")
    out = tmp_path / "out"
    result = fake_fit.run("fit", bad, good, "-o", out)
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"psonurbs: error: {bad}: malformed point data at line 2: "
        "expected at least 3 numbers (x y z), found 2"]
    assert result.stdout.startswith("good.ply: 16 points")
    assert stem_files(out, "good") == ["good.json", "good.obj", "good.ply", "good_error.csv"]
    assert stem_files(out, "bad") == []


def test_outputs_are_deterministic(tmp_path, fake_fit):
    for name in ("a", "b"):
        assert fake_fit.run("fit", SAMPLES / "seed_patch16.ply", "-o", tmp_path / name, "-q").exit_code == 0
    for f in (tmp_path / "a").iterdir():
        if f.name.startswith("summary."):
            continue  # holds the run times
        assert f.read_bytes() == (tmp_path / "b" / f.name).read_bytes(), f.name


def test_internal_error_exits_1_without_traceback(tmp_path, fake_fit, monkeypatch):
    def broken():
        raise RuntimeError("boom")

    fake_fit.behaviour = broken
    monkeypatch.delenv("PSONURBS_DEBUG", raising=False)
    result = fake_fit.run("fit", SAMPLES / "seed_patch16.ply", "-o", tmp_path / "out")
    assert result.exit_code == 1
    assert result.stderr.splitlines()[0] == \
        f"psonurbs: internal error: {SAMPLES / 'seed_patch16.ply'}: RuntimeError: boom"
    assert "Traceback" not in result.stderr
    assert stem_files(tmp_path / "out", "seed_patch16") == []


def test_internal_error_traceback_with_debug(tmp_path, fake_fit, monkeypatch):
    def broken():
        raise RuntimeError("boom")

    fake_fit.behaviour = broken
    monkeypatch.setenv("PSONURBS_DEBUG", "1")
    result = fake_fit.run("fit", SAMPLES / "seed_patch16.ply", "-o", tmp_path / "out")
    assert result.exit_code == 1
    assert "Traceback" in result.stderr and "RuntimeError: boom" in result.stderr


def test_interrupt_exits_130_and_leaves_nothing(tmp_path, fake_fit):
    def interrupted():
        raise KeyboardInterrupt

    fake_fit.behaviour = interrupted
    result = fake_fit.run("fit", SAMPLES / "seed_patch16.ply", SAMPLES / "franke_noisy.ply",
                 "-o", tmp_path / "out")
    assert result.exit_code == 130
    assert result.stderr == "psonurbs: interrupted\n"
    assert list((tmp_path / "out").iterdir()) == []
    assert len(fake_fit.calls) == 1  # stopped at once


def test_nan_in_result_is_an_internal_error_and_writes_nothing(tmp_path, fake_fit):
    fake_fit.behaviour = lambda: FakeResult(metrics={"rmse": float("nan"),
                                                            "max_error": 1.0})
    result = fake_fit.run("fit", SAMPLES / "seed_patch16.ply", "-o", tmp_path / "out")
    assert result.exit_code == 1
    assert "seed_patch16.ply: ValueError: fit document is not valid JSON" in result.stderr
    assert only_summary(tmp_path / "out")


def test_console_script_subprocess_exit_code(tmp_path):
    """The real entry point, in a fresh interpreter: exit status and stderr."""
    missing = tmp_path / "missing.ply"
    proc = subprocess.run([sys.executable, "-c", "from psonurbs.cli.main import main; main()", "fit",
                           str(missing), "-o", str(tmp_path / "out")],
                          capture_output=True, text=True, cwd=REPO, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr == f"psonurbs: error: {missing}: no such file\n"
    assert proc.stdout == ""


# ---- end to end with the real library ------------------------------------------

@pytest.fixture
def real_fit():
    pytest.importorskip("psonurbs.fitting.pipeline", reason="the numerical library (psonurbs.fitting.pipeline) is not there yet")


def test_real_fit_good_and_bad_together(tmp_path, real_fit):
    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    out = tmp_path / "out"
    result = run("fit", SAMPLES / "seed_patch16.ply", bad, "-c", SAMPLES / "seed_patch16.yaml",
                 "-o", out, "--particles", "6", "--iterations", "5", "-q")
    assert result.exit_code == 2, result.stderr
    assert result.stderr.splitlines() == [
        f"psonurbs: error: {bad}: PLY file has no vertices (no 'vertex' element; elements: none)"]
    assert stem_files(out, "seed_patch16") == ["seed_patch16.json", "seed_patch16.obj",
                                               "seed_patch16.ply", "seed_patch16_error.csv"]
    assert stem_files(out, "broken") == []
    doc = json.loads((out / "seed_patch16.json").read_text())
    assert doc["cloud"] == "seed_patch16.ply"
    assert doc["config"]["swarm"]["particles"] == 6
    surface = doc["surface"]
    cp = np.asarray(surface["control_points"])
    assert cp.shape == (5, 5, 3)
    assert len(surface["knots_u"]) == 5 + surface["degree_u"] + 1
    assert np.isfinite(doc["metrics"]["rmse"]) and doc["metrics"]["rmse"] >= 0
    rows = (out / "seed_patch16_error.csv").read_text().splitlines()
    assert len(rows) == 1 + 5
    best = [c for c in rows[0].split(",") if "best" in c][0]
    col = rows[0].split(",").index(best)
    values = [float(r.split(",")[col]) for r in rows[1:]]
    assert all(b <= a for a, b in zip(values, values[1:]))  # a best never rises


def test_real_fit_is_deterministic(tmp_path, real_fit):
    for name in ("a", "b"):
        result = run("fit", SAMPLES / "seed_patch16.ply", "-c", SAMPLES / "seed_patch16.yaml",
                     "-o", tmp_path / name, "--particles", "6", "--iterations", "5", "-q")
        assert result.exit_code == 0, result.stderr
    for f in sorted((tmp_path / "a").iterdir()):
        if f.name.startswith("summary."):
            continue  # holds the run times
        assert f.read_bytes() == (tmp_path / "b" / f.name).read_bytes(), f.name

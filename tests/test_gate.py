"""Exit codes through the CLI: 0 ok, 2 bad input, 3 gate exceeded, 130 interrupted,
143 terminated.

0/2/3 run in-process with the stand-in library of test_cli; 3, 130 and 143 also with
the real one, 130 and 143 in a subprocess that receives SIGINT or SIGTERM in the middle
of a long fit.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import GOOD, FakeResult, ply_bytes, run

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "data_samples"


@pytest.fixture
def good(tmp_path):
    path = tmp_path / "good.ply"
    path.write_bytes(ply_bytes(GOOD))
    return path


def test_help_documents_every_exit_code_and_the_precedence():
    text = " ".join(run("fit", "--help").output.split())
    for needle in ["0 every cloud was fitted", "1 internal error", "2 unusable input or config",
                   "3 gate exceeded", "4 a worker process died", "130 interrupted", "143 terminated",
                   "most severe wins: 143 > 130 > 1 > 4 > 2 > 3",
                   "--max-rmse X", "--max-rmse-rel X", "--jobs", "--scheduler", "--format"]:
        assert needle in text, needle


def test_exit_0_under_the_bound(tmp_path, fake_fit, good):
    # the stand-in's rmse is 1.234e-4
    result = fake_fit.run("fit", good, "-o", tmp_path / "out", "--max-rmse", "2e-4")
    assert result.exit_code == 0, result.stderr
    assert result.stderr == ""


def test_exit_3_above_max_rmse(tmp_path, fake_fit, good):
    out = tmp_path / "out"
    result = fake_fit.run("fit", good, "-o", out, "--max-rmse", "1e-4")
    assert result.exit_code == 3
    assert result.stderr == f"psonurbs: gate exceeded: {good}: rmse 1.234e-04 > --max-rmse 0.0001\n"
    assert result.stdout.startswith("good.ply: 16 points")
    assert (out / "good.json").is_file()  # the fit is still written, and reported
    assert json.loads((out / "summary.json").read_text())["clouds"][0]["status"] == "gate-exceeded"


def test_exit_3_above_max_rmse_rel(tmp_path, fake_fit, good):
    fake_fit.behaviour = lambda: FakeResult(metrics={"rmse": 0.5, "max_error": 1.0,
                                                            "rmse_relative": 0.02})
    result = fake_fit.run("fit", good, "-o", tmp_path / "out", "--max-rmse-rel", "0.01")
    assert result.exit_code == 3
    assert "relative rmse 2.000e-02 > --max-rmse-rel 0.01" in result.stderr
    assert fake_fit.run("fit", good, "-o", tmp_path / "out", "--max-rmse-rel", "0.03").exit_code == 0


def test_exit_2_beats_3(tmp_path, fake_fit, good):
    result = fake_fit.run("fit", good, tmp_path / "missing.ply", "-o", tmp_path / "out", "--max-rmse", "0")
    assert result.exit_code == 2
    assert "gate exceeded" in result.stderr and "no such file" in result.stderr


def test_exit_1_beats_2(tmp_path, fake_fit, good):
    calls = []

    def sometimes_broken():
        calls.append(1)
        raise RuntimeError("boom")

    fake_fit.behaviour = sometimes_broken
    result = fake_fit.run("fit", tmp_path / "missing.ply", good, "-o", tmp_path / "out")
    assert result.exit_code == 1
    assert calls == [1]


@pytest.mark.parametrize("value", ["-1", "nan", "inf", "abc"])
def test_bad_gate_value_is_exit_2(tmp_path, fake_fit, good, value):
    result = fake_fit.run("fit", good, "-o", tmp_path / "out", "--max-rmse", value)
    assert result.exit_code == 2
    assert "--max-rmse" in result.stderr
    assert fake_fit.calls == []


def test_missing_rhino3dm_is_exit_2_before_fitting(tmp_path, fake_fit, good, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_rhino(name, *args, **kwargs):
        if name == "rhino3dm":
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rhino)
    result = fake_fit.run("fit", good, "-o", tmp_path / "out", "--format", "3dm")
    assert result.exit_code == 2
    assert result.stderr == ("psonurbs: error: --format 3dm needs the optional package rhino3dm, "
                             "which is not installed: pip install 'psonurbs[cad]'\n")
    assert fake_fit.calls == []


def test_real_fit_gate(tmp_path):
    pytest.importorskip("psonurbs.fitting.pipeline")
    args = ["fit", SAMPLES / "seed_patch16.ply", "-c", SAMPLES / "seed_patch16.yaml",
            "--particles", "6", "--iterations", "5", "-q"]
    first = run(*args, "-o", tmp_path / "a")
    assert first.exit_code == 0, first.stderr
    metrics = json.loads((tmp_path / "a" / "seed_patch16.json").read_text())["metrics"]
    assert run(*args, "-o", tmp_path / "b", "--max-rmse", repr(metrics["rmse"])).exit_code == 0
    assert run(*args, "-o", tmp_path / "c", "--max-rmse", repr(metrics["rmse"] * 0.99)).exit_code == 3
    assert run(*args, "-o", tmp_path / "d", "--max-rmse-rel",
               repr(metrics["rmse_relative"] * 0.99)).exit_code == 3


# ---- 130 / 143: SIGINT / SIGTERM in the middle of a fit ------------------------------

STOPS = [pytest.param(signal.SIGINT, 130, "interrupted", id="SIGINT"),
         pytest.param(signal.SIGTERM, 143, "terminated", id="SIGTERM")]


def interrupt(args: list[str], out: Path, wait_for: float,
              signum: int = signal.SIGINT) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # Ctrl-C's handler, as Python installs it for a command started from a terminal (a shell
    # without job control starts a background job, a test run under ``nohup ... &``, say,
    # with SIGINT ignored, and its children would inherit that)
    start = "import signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
    proc = subprocess.Popen([sys.executable, "-c", start + "from psonurbs.cli.main import main; main()", *args,
                             "-o", str(out), "-q"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(wait_for)
        assert proc.poll() is None, "the fit ended before it could be interrupted"
        proc.send_signal(signum)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


def complete_stems(out: Path) -> set[str]:
    """Check every stem in ``out`` has its four files; return the stems."""
    files = {p.name for p in out.iterdir()} if out.exists() else set()
    stems = {name.split(".")[0].removesuffix("_error") for name in files}
    for stem in stems:
        assert {f"{stem}.json", f"{stem}.obj", f"{stem}.ply", f"{stem}_error.csv"} <= files, stem
    return stems


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize("signum, code, word", STOPS)
def test_stop_signal_exits_with_its_code_and_leaves_no_partial_file(tmp_path, signum, code, word):
    pytest.importorskip("psonurbs.fitting.pipeline")
    out = tmp_path / "out"
    result = interrupt(["fit", str(SAMPLES / "franke_noisy.ply"), "--iterations", "100000"],
                       out, wait_for=4.0, signum=signum)
    assert result.returncode == code, result.stderr
    assert result.stderr == f"psonurbs: {word}\n"
    assert list(out.iterdir()) == []  # nothing: no outputs, no temporary files, no summary


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize("signum, code, word", STOPS)
def test_stop_signal_while_the_command_line_loads_is_one_line_and_its_code(tmp_path, signum, code, word):
    """The console script (``cli/launch.py``), stopped 50 ms in: while numpy and scipy load
    (half a second or more), before the command line handles signals itself."""
    out = tmp_path / "out"
    script = ("import os, signal, sys, threading; signal.signal(signal.SIGINT, signal.default_int_handler); "
              f"sys.argv = ['psonurbs', 'fit', {str(SAMPLES / 'franke_noisy.ply')!r}, '-o', {str(out)!r}, '-q']; "
              f"threading.Timer(0.05, os.kill, (os.getpid(), {int(signum)})).start(); "
              "from psonurbs.cli.launch import main; main()")
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == code, result.stderr
    assert result.stderr == f"psonurbs: {word}\n"
    assert not out.exists()


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize("signum, code, word", STOPS)
def test_stop_signal_stops_the_worker_pool(tmp_path, signum, code, word):
    pytest.importorskip("psonurbs.fitting.pipeline")
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    shutil.copy(SAMPLES / "seed_patch16.ply", clouds / "a_small.ply")
    for k in range(3):
        shutil.copy(SAMPLES / "franke_noisy.ply", clouds / f"big{k}.ply")
    out = tmp_path / "out"
    start = time.perf_counter()
    result = interrupt(["fit", str(clouds), "--iterations", "100000", "--jobs", "2"], out,
                       wait_for=6.0, signum=signum)
    assert result.returncode == code, result.stderr
    assert time.perf_counter() - start < 40  # stopped, not waited for
    assert result.stderr.splitlines()[-1] == f"psonurbs: {word}"
    assert not [p for p in out.iterdir() if ".tmp-" in p.name]
    assert complete_stems(out) <= {"a_small"}  # finished clouds are complete, nothing else

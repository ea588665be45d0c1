"""Hostile inputs (issue 16): each case that once crashed, hung or ate the memory.

Every case is the command line's contract: exit 2 with one line ``psonurbs: error: PATH:
PROBLEM`` (or exit 0 where the input was valid after all), no traceback, nothing written
for a refused cloud. Cases that once hung or allocated gigabytes run ``psonurbs`` in a
subprocess under a time limit and an address-space limit (3 GiB; the imports alone map
1.2 GiB), so that a regression fails the test instead of the machine.
"""
from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import GOOD, FakeFit, FakeResult, franke, ply_bytes, run

MEMORY_LIMIT = 3 << 30


def psonurbs(*args, cwd: Path, timeout: float = 60, memory: int = MEMORY_LIMIT) -> subprocess.CompletedProcess:
    """``psonurbs ARGS`` in a fresh interpreter with limits on time and address space; a
    timeout is a failed test, not a hung suite."""
    def limits():
        resource.setrlimit(resource.RLIMIT_AS, (memory, memory))

    command = [sys.executable, "-c", "from psonurbs.cli.main import main; main()", *map(str, args)]
    try:
        return subprocess.run(command, capture_output=True, text=True, cwd=cwd, timeout=timeout,
                              preexec_fn=limits, env={**os.environ, "PSONURBS_DEBUG": ""})
    except subprocess.TimeoutExpired:
        pytest.fail(f"psonurbs {' '.join(map(str, args))} did not finish in {timeout} s")


def refused(result, *needles: str, longest: int = 400) -> str:
    """Exit 2, one stderr line in the tool's format holding every needle (and, a path aside,
    short); returns the line."""
    lines = result.stderr.splitlines()
    code = result.returncode if isinstance(result, subprocess.CompletedProcess) else result.exit_code
    assert code == 2, result.stderr[-2000:]
    assert len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith("psonurbs: error: ") and len(lines[0]) < longest, lines[0][:2000]
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert "Traceback" not in result.stderr
    return lines[0]


def cloud_files(out: Path) -> list[str]:
    """What was written besides the run summary."""
    return sorted(p.name for p in out.iterdir() if not p.name.startswith("summary.")) if out.exists() else []


@pytest.fixture
def cloud50(tmp_path) -> Path:
    path = tmp_path / "c50.ply"
    path.write_bytes(ply_bytes(franke(50, seed=2)))
    return path


# ---- extreme coordinates: refused before fitting, with the real fitter ----------------

@pytest.mark.parametrize("scale", [1e308, 1e200, 1e154, 1e-308, 1e-320])
def test_extreme_coordinates_are_refused(tmp_path, scale):
    path = tmp_path / "scaled.ply"
    with np.errstate(over="ignore", under="ignore"):
        points = franke(60, seed=3) * scale
    path.write_bytes(ply_bytes(points))
    out = tmp_path / "out"
    result = run("fit", path, "-o", out, "--particles", "3", "--iterations", "2", "-q")
    line = refused(result, str(path))
    assert ("overflow" in line) if scale > 1 else ("underflow" in line)
    assert cloud_files(out) == []


def test_scaled_clouds_inside_the_limits_are_fitted(tmp_path):
    """2^400 (2.6e120) and 2^-400 times a cloud fit as the cloud itself: a power of two
    scales every float exactly, so the relative figures agree to rounding."""
    quick = tmp_path / "quick.yaml"
    quick.write_text("swarm: {particles: 3, iterations: 2}\npolish_iterations: 3\nrefine: false\n")
    rel = {}
    for k in (0, 400, -400):
        path = tmp_path / f"s{k}.ply"
        path.write_bytes(ply_bytes(franke(60, seed=3) * 2.0 ** k))
        out = tmp_path / f"out{k}"
        result = run("fit", path, "-o", out, "-c", quick, "-q")
        assert result.exit_code == 0, result.stderr
        rel[k] = json.loads((out / f"s{k}.json").read_text())["metrics"]["rmse_relative"]
    assert rel[400] == pytest.approx(rel[0], rel=1e-9) and rel[-400] == pytest.approx(rel[0], rel=1e-9)


# ---- sizes without bounds ---------------------------------------------------------------

def test_a_billion_iterations_is_refused_with_the_bound(tmp_path, cloud50):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("swarm:\n  iterations: 1000000000\n")
    result = psonurbs("fit", cloud50, "-c", cfg, "-o", tmp_path / "out", cwd=tmp_path)
    refused(result, "swarm.iterations", "1000000000", "at most 100,000")
    assert not (tmp_path / "out").exists()


def test_a_huge_iterations_option_is_refused(tmp_path, cloud50):
    result = psonurbs("fit", cloud50, "--iterations", "99999999999999999999999", "-o", tmp_path / "out",
                      cwd=tmp_path)
    refused(result, "command-line options", "swarm.iterations", "at most 100,000")


def test_a_huge_tessellation_is_refused(tmp_path, cloud50):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("tessellation: [100000, 100000]\n")
    result = psonurbs("fit", cloud50, "-c", cfg, "-o", tmp_path / "out", cwd=tmp_path)
    refused(result, "tessellation", "at most 10,000")


def test_a_huge_net_on_few_points_is_refused_with_the_estimate(tmp_path, cloud50):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("net_size: [200, 200]\n")
    result = psonurbs("fit", cloud50, "-c", cfg, "-o", tmp_path / "out", cwd=tmp_path)
    refused(result, "needs an estimated 190.7 GiB", "160,000 x 160,000", "1.0 GiB")


def test_a_net_too_large_for_the_points_is_refused(tmp_path, cloud50):
    """30 x 30 fits in memory but 900 control points cannot be decided by 50 points."""
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("net_size: [30, 30]\n")
    out = tmp_path / "out"
    result = run("fit", cloud50, "-c", cfg, "-o", out, "-q")
    refused(result, str(cloud50), "900 control points are too many for 50 points: at most 200")
    assert cloud_files(out) == []


def test_a_billion_particles_is_refused_at_once(tmp_path, cloud50):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("swarm:\n  particles: 1000000000\n")
    start = time.perf_counter()
    result = psonurbs("fit", cloud50, "-c", cfg, "-o", tmp_path / "out", cwd=tmp_path, timeout=60)
    refused(result, "swarm.particles", "at most 10,000")
    assert time.perf_counter() - start < 30


# ---- YAML bombs --------------------------------------------------------------------------

def laughs(levels: int = 9, width: int = 9, key: str = "tessellation") -> str:
    """A "billion laughs" under a config key: width**levels values once expanded (9**9: 387
    million), which printing the value in the message would have built."""
    lines = [f"{key}:", "  - &a0 [" + ", ".join(["1"] * width) + "]"]
    lines += [f"  - &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


def test_billion_laughs_is_refused_without_expanding(tmp_path, cloud50):
    cfg = tmp_path / "bomb.yaml"
    cfg.write_text(laughs(9, 9))
    result = psonurbs("fit", cloud50, "-c", cfg, "-o", tmp_path / "out", cwd=tmp_path, timeout=60)
    refused(result, "malformed YAML", "10,000 values once its aliases are expanded")


def test_a_small_bomb_under_a_key_gives_a_short_message(tmp_path, fake_fit, cloud50):
    cfg = tmp_path / "bomb.yaml"
    cfg.write_text("tessellation: &t [[1, 2, 3, 4, 5, 6, 7, 8, 9], [10, 11, 12]]\n"
                   "swarm:\n  particles: [" + ", ".join(["*t"] * 90) + "]\n")
    result = fake_fit.run("fit", cloud50, "-c", cfg, "-o", tmp_path / "out")
    line = refused(result, "config key")
    assert len(line) < 200
    assert fake_fit.calls == []


def test_deep_nesting_is_refused(tmp_path, cloud50):
    cfg = tmp_path / "deep.yaml"
    cfg.write_text("tessellation: " + "[" * 100_000 + "]" * 100_000 + "\n")
    result = psonurbs("fit", cloud50, "-c", cfg, "-o", tmp_path / "out", cwd=tmp_path)
    refused(result, "malformed YAML", "nested deeper than 32 levels")


# ---- paths that are not regular files -----------------------------------------------------

def test_a_named_pipe_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    result = psonurbs("fit", fifo, "-o", tmp_path / "out", cwd=tmp_path, timeout=60)
    refused(result, f"{fifo}: is a named pipe, not a point cloud file")


def test_a_symlink_to_dev_zero_is_refused(tmp_path):
    link = tmp_path / "zero.xyz"
    link.symlink_to("/dev/zero")
    result = psonurbs("fit", link, "-o", tmp_path / "out", cwd=tmp_path, timeout=60)
    refused(result, f"{link}: is a character device")


def test_a_named_pipe_as_config_is_refused(tmp_path, cloud50):
    fifo = tmp_path / "cfg.yaml"
    os.mkfifo(fifo)
    result = psonurbs("fit", cloud50, "-c", fifo, "-o", tmp_path / "out", cwd=tmp_path, timeout=60)
    refused(result, f"{fifo}: is a named pipe, not a config file")


# ---- counts the header promises -------------------------------------------------------------

def pcd_ascii(points, declared: int) -> bytes:
    head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            f"WIDTH {declared}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {declared}\nDATA ascii\n")
    return (head + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(points).tolist())).encode()


def test_a_pcd_promising_more_points_than_it_holds_is_refused(tmp_path):
    path = tmp_path / "short.pcd"
    path.write_bytes(pcd_ascii(franke(40, seed=5), declared=100))
    out = tmp_path / "out"
    result = run("fit", path, "-o", out, "--particles", "3", "--iterations", "2", "-q")
    refused(result, str(path), "the header declares 100 points, the body holds 40")
    assert cloud_files(out) == []


# ---- valid files that were refused ---------------------------------------------------------

def recording_fit(seen: list):
    def fit(points, config, on_iteration=None):
        seen.append(np.array(points))
        return FakeResult()
    return fit


def test_a_text_cloud_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "bom.xyz"
    path.write_bytes("\ufeff".encode() + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in GOOD.tolist()).encode())
    seen = []
    result = run("fit", path, "-o", tmp_path / "out", fit=recording_fit(seen))
    assert result.exit_code == 0, result.stderr
    np.testing.assert_array_equal(seen[0], GOOD)


def test_ply_properties_in_any_order_with_extras_are_read_by_name(tmp_path):
    points = franke(30, seed=6)
    extra = np.arange(30.0)
    records = np.column_stack([points[:, 2], extra, points[:, 0], points[:, 1]])  # z, intensity, x, y
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 30\nproperty double z\n"
            "property double intensity\nproperty double x\nproperty double y\nend_header\n")
    path = tmp_path / "zxy.ply"
    path.write_bytes(head.encode() + records.astype("<f8").tobytes())
    seen = []
    result = run("fit", path, "-o", tmp_path / "out", fit=recording_fit(seen))
    assert result.exit_code == 0, result.stderr
    np.testing.assert_array_equal(seen[0], points)


# ---- click's usage errors in the tool's format -----------------------------------------------

@pytest.mark.parametrize("args, needle", [
    (["--topology", "Sphere"], "Invalid value for '--topology': 'Sphere' is not one of"),
    (["--out", "FILE"], "Directory 'FILE' is a file"),
    (["--particles", "many"], "'many' is not a valid integer"),
    (["--no-such-option"], "--no-such-option"),
])
def test_usage_errors_are_one_line(tmp_path, cloud50, args, needle):
    existing = tmp_path / "FILE"
    existing.write_text("x")
    args = [str(existing) if a == "FILE" else a for a in args]
    if "--out" not in args:
        args += ["--out", str(tmp_path / "out")]
    result = run("fit", cloud50, *args)
    refused(result, needle.replace("FILE", str(existing)))
    assert result.stdout == ""


# ---- a worker killed in a real batch --------------------------------------------------------

class KillingFit(FakeFit):
    """The stand-in fitter, except that fitting a cloud of ``victim`` points kills its own
    process with SIGKILL, as the kernel's out-of-memory killer would."""

    def __init__(self, victim: int):
        super().__init__()
        self.victim = victim

    def __call__(self, points, config, on_iteration=None):
        if len(points) == self.victim:
            os.kill(os.getpid(), signal.SIGKILL)
        time.sleep(0.2)
        return FakeResult()


def test_a_killed_worker_costs_only_its_own_cloud(tmp_path):
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for k in range(6):
        (clouds / f"c{k}.ply").write_bytes(ply_bytes(franke(20 + k, seed=k)))
    out = tmp_path / "out"
    result = run("fit", clouds, "-o", out, "--jobs", "2", "-q", fit=KillingFit(victim=22))
    assert result.exit_code == 4, result.stderr
    victim = clouds / "c2.ply"
    (line,) = result.stderr.splitlines()
    assert line.startswith(f"psonurbs: error: {victim}: the worker process fitting it was killed by SIGKILL")
    assert "memory" in line
    summary = json.loads((out / "summary.json").read_text())
    assert [c["status"] for c in summary["clouds"]] == ["ok", "ok", "worker-lost", "ok", "ok", "ok"]
    assert summary["exit_code"] == 4 and summary["counts"]["worker-lost"] == 1
    for k in (0, 1, 3, 4, 5):
        assert (out / f"c{k}.json").is_file()
    assert not list(out.glob("c2*"))


# ---- clouds larger than the config can fit, refused from the header ---------------------------

def test_a_cloud_larger_than_the_budget_is_refused_before_reading(tmp_path, fake_fit):
    """A header declaring 10^9 vertices (24 GB of doubles) is refused from the header alone;
    the budget allows 2^30 / (8 x 9) = 14,913,080 points for orders 3 x 3."""
    path = tmp_path / "billion.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n"
                     b"property double x\nproperty double y\nproperty double z\nend_header\n" + b"\0" * 480)
    result = fake_fit.run("fit", path, "-o", tmp_path / "out")
    refused(result, "1,000,000,000 points are more than this config can fit (at most 14,913,080")
    assert fake_fit.calls == []


# ---- names the terminal and the summary must survive ------------------------------------------

def test_a_file_name_that_is_not_utf8_is_fitted_and_reported_escaped(tmp_path, fake_fit):
    path = Path(os.fsdecode(os.fsencode(tmp_path) + b"/\xff\xfe.ply"))
    path.write_bytes(ply_bytes(GOOD))
    out = tmp_path / "out"
    result = fake_fit.run("fit", path, "-o", out, "--format", "obj-nurbs")
    assert result.exit_code == 0, result.stderr
    assert result.stdout.startswith("\\xff\\xfe.ply: 16 points")
    assert f"{tmp_path}/\\xff\\xfe.ply" in (out / "summary.csv").read_text()
    assert "g \\xff\\xfe" in Path(os.fsdecode(os.fsencode(out) + b"/\xff\xfe.obj")).read_text(errors="replace")


def test_a_newline_in_a_file_name_stays_one_line(tmp_path, fake_fit):
    path = tmp_path / "two\nlines.xyz"
    path.write_text("1 2\n")
    result = fake_fit.run("fit", path, "-o", tmp_path / "out")
    refused(result, "two\\nlines.xyz: malformed point data")


def test_a_path_too_long_is_refused(tmp_path, fake_fit):
    path = str(tmp_path) + "/a" * 3000 + ".ply"
    result = fake_fit.run("fit", path, "-o", tmp_path / "out")
    refused(result, f"{path}: cannot read file (File name too long)", longest=len(path) + 100)


# ---- a net the points cannot decide -----------------------------------------------------------

def test_a_singular_fit_is_refused_as_input_not_a_crash(tmp_path):
    """smoothing 0 on a sphere's 8 x 7 net with 40 points leaves the least-squares system
    singular (the robust pass's first solve): a config these points cannot decide, exit 2."""
    rng = np.random.default_rng(0)
    x, y = rng.random((2, 40))
    path = tmp_path / "sparse.ply"
    path.write_bytes(ply_bytes(np.column_stack([x, y, np.sin(3 * x) * y])))
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("orders: [2, 2]\nnet_size: [8, 7]\ntopology: sphere\nsmoothing: 0.0\n"
                   "swarm: {particles: 1, iterations: 1}\npolish_iterations: 0\nrefine: false\n")
    out = tmp_path / "out"
    result = run("fit", path, "-c", cfg, "-o", out, "-q")
    refused(result, f"{path}: the least-squares system of the fit is singular", "smoothing above 0")
    assert cloud_files(out) == []

"""``--scheduler``: a batch fitted on a dask.distributed cluster.

A scheduler and two workers are started on 127.0.0.1 as separate processes, as a user
would (``dask scheduler``, ``dask worker``); the batch must write byte-identical files to
``--jobs 1``, a worker killed twice under a cloud makes that cloud a ``worker-lost`` row,
and SIGTERM cancels the futures (the workers are free again) and leaves no file behind.
Skipped when dask.distributed is not installed (the ``test`` extra installs it).
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import run

from psonurbs.errors import ConfigError
from psonurbs.formats.outputs import render_ply
from psonurbs.run.cluster import Scheduler
from psonurbs.run.demo import SAMPLES as DEMO_SAMPLES

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "data_samples"
QUICK = ["--particles", "6", "--iterations", "5", "-q"]
FIT_KEY = "psonurbs-fit-"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1; yields the address
    and a client to watch them with. The scheduler leaves the retry to psonurbs."""
    distributed = pytest.importorskip("distributed")
    work = tmp_path_factory.mktemp("dask")
    address = f"tcp://127.0.0.1:{free_port()}"
    env = dict(os.environ, DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES="0")
    dask = [sys.executable, "-m", "dask"]
    logs = open(work / "cluster.log", "w")
    processes = [subprocess.Popen([*dask, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                                   "--no-dashboard"], cwd=work, env=env, stdout=logs, stderr=logs)]
    try:
        for name in ("one", "two"):
            processes.append(subprocess.Popen([*dask, "worker", address, "--nthreads", "1", "--no-dashboard",
                                               "--name", name], cwd=work, env=env, stdout=logs, stderr=logs))
        client = distributed.Client(address, timeout="60s")
        client.wait_for_workers(2, timeout=120)
        yield address, client
        client.close()
    finally:
        for process in processes:
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
        logs.close()


def batch(directory: Path) -> Path:
    """Six small clouds (two of them scattered samples of the demo shapes) and a broken one."""
    directory.mkdir(parents=True)
    shutil.copy(SAMPLES / "seed_patch16.ply", directory / "seed_patch16.ply")
    shutil.copy(SAMPLES / "seed_sphere169.ply", directory / "seed_sphere169.ply")
    for sample in DEMO_SAMPLES:
        for k, size in enumerate((60, 150)):
            rows = np.random.default_rng(k).permutation(len(sample.cloud()))[:size]
            (directory / f"{sample.name}_{size}.ply").write_bytes(
                render_ply(sample.cloud()[rows], np.zeros((0, 3), np.int64)))
    (directory / "broken.xyz").write_text("1 2 3\nnot a number\n")
    assert len(list(directory.glob("*.ply"))) == 6
    return directory


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The batch, and its outputs with --jobs 1."""
    root = tmp_path_factory.mktemp("batch")
    clouds = batch(root / "clouds")
    result = run("fit", clouds, "-o", root / "jobs1", *QUICK)
    assert result.exit_code == 2, result.stderr  # the broken cloud
    return clouds, root / "jobs1"


def assert_same_outputs(one: Path, other: Path) -> None:
    names = sorted(p.name for p in one.iterdir())
    assert names == sorted(p.name for p in other.iterdir())
    assert len(names) == 4 * 6 + 2
    for name in names:
        if not name.startswith("summary."):
            assert (one / name).read_bytes() == (other / name).read_bytes(), name
    rows = [json.loads((d / "summary.json").read_text())["clouds"] for d in (one, other)]
    without_time = [[{k: v for k, v in r.items() if k != "seconds"} for r in rs] for rs in rows]
    assert without_time[0] == without_time[1]  # same rows in the input order
    assert rows[1][0]["status"] == "bad-input"
    assert all(r["status"] in ("ok", "suspect") for r in rows[1][1:])  # fitted and written (a self-check may warn)


def test_a_batch_on_a_scheduler_writes_the_files_of_jobs_1(tmp_path, cluster, reference):
    address, client = cluster
    clouds, jobs1 = reference
    out = tmp_path / "dask"
    proc = subprocess.run([sys.executable, "-c", "from psonurbs.cli.main import main; main()", "fit", str(clouds),
                           "-o", str(out), *QUICK, "--scheduler", address],
                          capture_output=True, text=True, cwd=REPO, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert f"{clouds / 'broken.xyz'}: malformed point data at line 2" in proc.stderr
    assert_same_outputs(jobs1, out)
    assert not [k for k in client.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.tasks))
                if str(k).startswith(FIT_KEY)]  # nothing left behind on the cluster


def test_a_local_cluster_writes_the_files_of_jobs_1(tmp_path, reference):
    pytest.importorskip("distributed")
    clouds, jobs1 = reference
    environment = dict(os.environ)
    result = run("fit", clouds, "-o", tmp_path / "local", *QUICK, "--scheduler", "local:2")
    assert result.exit_code == 2, result.stderr
    assert_same_outputs(jobs1, tmp_path / "local")
    # the nannies set their workers' variables (OMP_NUM_THREADS=1, ...) here to spawn them
    assert dict(os.environ) == environment


def long_clouds(directory: Path, count: int) -> Path:
    """``count`` copies of a 400-point cloud whose swarm (100000 iterations) starts at once."""
    directory.mkdir()
    bump = DEMO_SAMPLES[0].cloud()[:400]
    for k in range(count):
        (directory / f"long{k}.ply").write_bytes(render_ply(bump, np.zeros((0, 3), np.int64)))
    return directory


def start_fit(clouds: Path, out: Path, address: str) -> subprocess.Popen:
    """A long fit on the cluster, in its own process as from a shell."""
    return subprocess.Popen([sys.executable, "-c", "from psonurbs.cli.main import main; main()", "fit", str(clouds),
                             "-o", str(out), "-q", "--iterations", "100000", "--scheduler", address],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def running_fit(client, proc: subprocess.Popen, timeout: float = 60.0) -> tuple[str, str]:
    """(worker address, task key) of the fit task once a worker runs it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        for worker, keys in client.processing().items():
            for key in keys:
                if str(key).startswith(FIT_KEY):
                    return worker, str(key)
        time.sleep(0.5)
    raise AssertionError("no fit task started on the cluster")


def test_a_worker_lost_twice_under_a_cloud_is_reported(tmp_path, cluster):
    address, client = cluster
    clouds = long_clouds(tmp_path / "clouds", 1)
    out = tmp_path / "out"
    proc = start_fit(clouds, out, address)
    try:
        keys = []
        for _ in range(2):  # kill the worker running it, twice (its nanny starts a new one)
            worker, key = running_fit(client, proc)
            keys.append(key)
            os.kill(client.run(os.getpid, workers=[worker])[worker], signal.SIGKILL)
            while key in {str(k) for ks in client.processing().values() for k in ks}:
                time.sleep(0.2)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert keys[0].endswith("-0-0") and keys[1].endswith("-0-1")  # submitted once more after the first loss
    assert proc.returncode == 4, stderr
    assert stderr.startswith(f"psonurbs: error: {clouds / 'long0.ply'}: the worker process fitting it died twice on the "
                             "cluster (the second time on worker tcp://127.0.0.1:"), stderr
    row = json.loads((out / "summary.json").read_text())["clouds"][0]
    assert row["status"] == "worker-lost" and row["points"] is None
    assert sorted(p.name for p in out.iterdir()) == ["summary.csv", "summary.json"]
    client.wait_for_workers(2, timeout=120)  # the nannies have restarted them


def test_sigterm_cancels_the_futures_and_writes_nothing(tmp_path, cluster):
    address, client = cluster
    clouds = long_clouds(tmp_path / "clouds", 3)
    out = tmp_path / "out"
    proc = start_fit(clouds, out, address)
    try:
        running_fit(client, proc)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, stderr
    assert stderr.splitlines()[-1] == "psonurbs: terminated"
    assert list(out.iterdir()) == []  # no outputs, no temporary files, no summary
    # the cancelled fits stop at their next swarm iteration: the workers are free again
    def busy() -> int:
        return sum(client.run(lambda dask_worker: len(dask_worker.state.executing)).values())

    deadline = time.monotonic() + 30
    while (any(client.processing().values()) or busy()) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not any(client.processing().values()) and busy() == 0


@pytest.mark.parametrize("text, message", [
    ("local:0", "expected local:N with N a positive number of workers"),
    ("local:two", "expected local:N with N a positive number of workers"),
    ("cluster", "expected a scheduler address (tcp://host:8786), local:N or a scheduler file"),
    ("missing.json", "no such scheduler file"),
])
def test_scheduler_option_is_checked(text, message):
    with pytest.raises(ConfigError, match=f"--scheduler {text}: " + message.replace("(", r"\(").replace(")", r"\)")):
        Scheduler.parse(text)


def test_unreachable_scheduler_is_a_one_line_error(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setenv("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "1s")
    import dask

    dask.config.refresh()
    address = f"tcp://127.0.0.1:{free_port()}"
    try:
        result = run("fit", SAMPLES / "seed_patch16.ply", "-o", tmp_path / "out", "--scheduler", address)
    finally:
        monkeypatch.delenv("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT")
        dask.config.refresh()
    assert result.exit_code == 2
    assert result.stderr.startswith(f"psonurbs: error: --scheduler {address}: cannot reach the scheduler (")
    assert len(result.stderr.splitlines()) == 1


def test_scheduler_and_jobs_do_not_go_together(tmp_path):
    result = run("fit", SAMPLES / "seed_patch16.ply", "-o", tmp_path / "out", "--scheduler", "local:2", "--jobs", "2")
    assert result.exit_code == 2
    assert result.stderr == ("psonurbs: error: --scheduler and --jobs do not go together: the cluster's workers "
                             "do the work\n")


def test_without_dask_the_error_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    result = run("fit", SAMPLES / "seed_patch16.ply", "-o", tmp_path / "out", "--scheduler", "local:2")
    assert result.exit_code == 2
    assert result.stderr == ("psonurbs: error: --scheduler needs the optional package dask.distributed, which is "
                             "not installed: pip install 'psonurbs[dask]'\n")
    assert not (tmp_path / "out").exists() or list((tmp_path / "out").iterdir()) == []

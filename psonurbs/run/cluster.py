"""Fitting clouds on a dask.distributed cluster (``--scheduler``).

The cluster only computes: this process reads every cloud, sends the points to a worker,
gets the rendered outputs back and writes every file, so the workers need no access to
the inputs or the output directory and ``--scheduler`` writes byte-identical files to
``--jobs 1``. At most two tasks per worker thread are in flight, so a batch of
thousands of scans is read as the cluster consumes it, not all at once.

* ``tcp://host:8786`` (any dask address): an existing scheduler; ``local:N``: a
  ``LocalCluster`` of N single-threaded worker processes, started and closed here;
  ``PATH.json``: a scheduler file (``dask scheduler --scheduler-file PATH.json``).
* A task whose worker was lost (killed, out of memory, the machine gone) is submitted
  once more; lost again, it is reported. The scheduler counts its own retries first
  (``distributed.scheduler.allowed-failures``; ``local:N`` sets it to 0).
* Ctrl-C and SIGTERM cancel every future and close the connection (and a local
  cluster); nothing is half-written since the files are written here, each atomically.
* A local cluster's nannies put their workers' variables (one BLAS/OpenMP thread, ...:
  ``distributed.nanny.pre-spawn-environ``) into this process's environment to spawn them,
  and leave them there; the environment is given back as it was once the cluster is
  closed, so that fits run here afterwards keep their threads.

Needs the optional extra ``dask`` (``pip install 'psonurbs[dask]'``).
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

from psonurbs.errors import ConfigError

__all__ = ["Cancelled", "Scheduler", "check_available", "cluster_run", "stop_if_cancelled"]

_INSTALL = "pip install 'psonurbs[dask]'"
_IN_FLIGHT_PER_THREAD = 2


@dataclass(frozen=True)
class Scheduler:
    """Where to run: an address, a scheduler file, or ``local_workers`` for a LocalCluster."""

    text: str
    address: str | None = None
    scheduler_file: Path | None = None
    local_workers: int = 0

    @classmethod
    def parse(cls, text: str) -> Scheduler:
        """``tcp://host:port`` (or ``host:port``), ``local:N``, or an existing ``*.json`` file."""
        value = text.strip()
        if value.startswith("local:") or value == "local":
            count = value.partition(":")[2]
            if not count.isdigit() or int(count) < 1:
                raise ConfigError(f"--scheduler {text}: expected local:N with N a positive number of workers")
            return cls(text, local_workers=int(count))
        if value.endswith(".json"):
            path = Path(value)
            if not path.is_file():
                raise ConfigError(f"--scheduler {text}: no such scheduler file")
            return cls(text, scheduler_file=path)
        if "://" in value or (":" in value and value.rsplit(":", 1)[1].isdigit()):
            return cls(text, address=value)
        raise ConfigError(f"--scheduler {text}: expected a scheduler address (tcp://host:8786), "
                          "local:N or a scheduler file (scheduler.json)")


def _distributed():
    try:
        import distributed
    except ImportError:
        raise ConfigError(f"--scheduler needs the optional package dask.distributed, which is not installed: "
                          f"{_INSTALL}") from None
    return distributed


def check_available() -> None:
    """Raise ConfigError (naming the extra) when dask.distributed is not installed."""
    _distributed()


@contextlib.contextmanager
def _connect(scheduler: Scheduler) -> Iterator[object]:
    """A connected ``distributed.Client``; a local cluster is started and closed with it."""
    distributed = _distributed()
    import dask

    cluster, environment = None, dict(os.environ)
    try:
        if scheduler.local_workers:
            # one retry is ours (cluster_run), none the scheduler's; the workers start with
            # SIGINT ignored (inherited through spawn), so a Ctrl-C reaches this process only
            with dask.config.set({"distributed.scheduler.allowed-failures": 0}), _sigint_ignored():
                cluster = distributed.LocalCluster(n_workers=scheduler.local_workers, threads_per_worker=1,
                                                   processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                                   silence_logs=50)
            client = distributed.Client(cluster)
        elif scheduler.scheduler_file is not None:
            client = distributed.Client(scheduler_file=str(scheduler.scheduler_file))
        else:
            client = distributed.Client(scheduler.address)
    except (OSError, TimeoutError) as e:
        if cluster is not None:
            cluster.close()
        _restore(environment)  # a cluster that failed to start may have spawned some workers
        raise ConfigError(f"--scheduler {scheduler.text}: cannot reach the scheduler ({_reason(e)})") from None
    try:
        yield client
    finally:
        with contextlib.suppress(Exception):
            client.close()
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()
        _restore(environment)


def _restore(environment: dict[str, str]) -> None:
    """``os.environ`` back to ``environment``: the variables set since removed, the ones
    changed given their values back."""
    for name in set(os.environ) - set(environment):
        del os.environ[name]
    for name, value in environment.items():
        if os.environ.get(name) != value:
            os.environ[name] = value


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    try:
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _check_workers(client, scheduler: Scheduler) -> None:
    """Every worker connected now runs this psonurbs version (a task pickled here is run
    by the workers' own psonurbs); a note on stderr while there is no worker yet."""
    import psonurbs

    versions = client.run(_worker_version, on_error="return")
    if not versions:
        print(f"psonurbs: note: --scheduler {scheduler.text}: no worker yet; the fits start when "
              "workers join", file=sys.stderr)
        return
    wrong = {worker: v for worker, v in versions.items() if v != psonurbs.__version__}
    if wrong:
        worker, version = sorted(wrong.items())[0]
        found = "no psonurbs" if isinstance(version, BaseException) else f"psonurbs {version}"
        raise ConfigError(f"--scheduler {scheduler.text}: {len(wrong)} of {len(versions)} workers cannot run "
                          f"this psonurbs {psonurbs.__version__} (worker {worker} has {found}); install the "
                          "same version on the workers")


def _worker_version() -> str:
    """Run on each worker: its psonurbs version (unpickling this fails without psonurbs)."""
    import psonurbs

    return psonurbs.__version__


def _call(task: Callable, arguments: tuple):
    """Run on a worker: ``task(*arguments)``, the arguments sent as one piece of data."""
    return task(*arguments)


class Cancelled(Exception):
    """Raised inside a worker's fit once the client has cancelled its task."""


def stop_if_cancelled(iteration: int, best: float, mean: float) -> None:
    """A fit's ``on_iteration`` on a worker: stop at the next swarm iteration once the task
    was cancelled (a Ctrl-C on the client), so the worker's thread is free again instead of
    finishing a fit nobody waits for. Outside a dask task it does nothing."""
    try:
        from distributed import get_worker
        from distributed.worker import thread_state

        key = getattr(thread_state, "key", None)
        tasks = get_worker().state.tasks
    except Exception:  # not on a worker
        return
    task = tasks.get(key) if key is not None else None
    if key is not None and (task is None or task.state in ("cancelled", "released", "forgotten")):
        raise Cancelled(f"task {key} was cancelled")


def _worker_lost(error: BaseException) -> bool:
    """Whether a task failed because its worker (or the connection to it) went away, as
    opposed to the task raising (our tasks never raise: they return a failed row)."""
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    return isinstance(error, (KilledWorker, CommClosedError, OSError))


def _lost_twice(error: BaseException | None) -> str:
    """How a task was lost the second time, for the row's message."""
    last = getattr(error, "last_worker", None)
    if last is not None:
        return f"died twice on the cluster (the second time on worker {getattr(last, 'address', last)})"
    if error is None:
        return "was lost twice on the cluster (its task was cancelled by the scheduler)"
    return f"was lost twice on the cluster ({_reason(error)})"


def _reason(error: BaseException) -> str:
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def cluster_run(task: Callable, keys: Sequence[int], prepare: Callable[[int], tuple | None],
                scheduler: Scheduler, on_result: Callable[[int, object], None],
                on_lost: Callable[[int, str], None], on_failed: Callable[[int, str, str], None]) -> None:
    """Run ``task(*prepare(k))`` on the cluster for every k in ``keys``, in that order.

    ``prepare(k)`` is called here just before k is submitted; it returns the task's
    arguments, or None when k needs no task (e.g. its cloud could not be read: it has
    reported itself). As each task ends, in this process: ``on_result(k, result)``, or
    ``on_lost(k, how)`` when its worker was lost twice, or ``on_failed(k, message,
    traceback)`` when the task could not run at all. Any exception here (KeyboardInterrupt
    and SIGTERM's Terminated included) cancels every future and propagates.
    """
    distributed = _distributed()
    with _connect(scheduler) as client:
        _check_workers(client, scheduler)
        pending = iter(keys)
        running: dict[object, tuple[int, tuple, int]] = {}  # future -> (k, arguments, attempt)
        finished = distributed.as_completed()
        run_id = uuid.uuid4().hex[:8]

        def submit(k: int, arguments: tuple, attempt: int) -> None:
            # the points travel as data to a worker, not inside the task graph (it warns above 10 MB)
            [data] = client.scatter([arguments], hash=False)
            future = client.submit(_call, task, data, key=f"psonurbs-fit-{run_id}-{k}-{attempt}", pure=False)
            running[future] = (k, arguments, attempt)
            finished.add(future)

        def fill() -> None:
            threads = sum(client.nthreads().values()) or 1
            while len(running) < _IN_FLIGHT_PER_THREAD * threads:
                for k in pending:
                    arguments = prepare(k)
                    if arguments is not None:
                        submit(k, arguments, 0)
                        break
                else:
                    return

        try:
            fill()
            while running:
                future = next(finished)
                k, arguments, attempt = running.pop(future)
                fill()  # the next cloud goes out before this one's files are written
                if future.status == "finished":
                    result = future.result()
                    future.release()
                    on_result(k, result)
                else:
                    error = future.exception() if future.status == "error" else None
                    future.release()
                    if error is None or _worker_lost(error):
                        if attempt == 0:
                            submit(k, arguments, 1)
                        else:
                            on_lost(k, _lost_twice(error))
                    else:
                        on_failed(k, f"the cluster could not run the fit: {_reason(error)}", "")
                    fill()
        except BaseException:
            with contextlib.suppress(Exception):
                client.cancel(list(running), force=True)
            raise

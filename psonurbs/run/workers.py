"""A pool of worker processes that fit clouds (``--jobs N``).

Workers are started with ``spawn`` and limited to one BLAS/OpenMP thread (a fit is
already vectorised); they only compute and send back the rendered outputs, so the
parent writes every file and can stop the workers at any moment.

Each worker is a process with its own pipe, and the parent knows which task each one
holds. So a worker that dies (killed by the kernel's out-of-memory killer, a crash in a
C extension) costs only the task it held: that task is reported lost with the signal
that ended it, a new worker takes the dead one's place, and the other workers never
notice. (``concurrent.futures.ProcessPoolExecutor`` cannot do this: one dead worker
breaks the whole pool, and every task in flight or waiting fails with it.)
"""
from __future__ import annotations

import os
import signal
import traceback
from collections import deque
from typing import Callable

from psonurbs.run.heap import keep_freed_memory

__all__ = ["pool_run", "describe_exit"]


_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                     "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def _worker_init() -> None:
    """Each worker: Ctrl-C is the parent's business (it started with SIGINT blocked, see
    :class:`_Worker`; now ignored, then unblocked); it ends with its parent; one BLAS/OpenMP
    thread; freed memory kept (:mod:`psonurbs.run.heap`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    _end_with_parent()
    keep_freed_memory()
    for name in _THREAD_VARIABLES:
        os.environ[name] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
    except Exception:  # pragma: no cover - threadpoolctl is a dependency
        pass


def _end_with_parent() -> None:
    """Linux: SIGTERM this worker when its parent dies (killed with SIGKILL, say), instead of
    computing on for nobody. Elsewhere a worker notices when it next answers."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:  # pragma: no cover - not Linux
        pass


def _serve(connection, task: Callable) -> None:
    """A worker's loop: receive ``(k, args)``, send ``(k, True, task(*args))`` back, or
    ``(k, False, (error, traceback))`` if it raised; ``None`` ends the loop."""
    _worker_init()
    while True:
        try:
            message = connection.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        k, args = message
        try:
            reply = (k, True, task(*args))
        except BaseException as e:
            reply = (k, False, (_describe(e), traceback.format_exc()))
        try:
            connection.send(reply)
        except OSError:  # the parent is gone (killed): nobody to answer
            return
        except Exception as e:  # the result could not be pickled
            connection.send((k, False, (f"cannot send the result: {_describe(e)}", traceback.format_exc())))


def _describe(error: BaseException) -> str:
    return f"{type(error).__name__}: {error}" if str(error) else type(error).__name__


def describe_exit(exitcode: int | None) -> str:
    """How a worker process ended, for a message: 'was killed by SIGKILL', 'exited with status 3'."""
    if exitcode is None:
        return "stopped answering"
    if exitcode < 0:
        try:
            return f"was killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"was killed by signal {-exitcode}"
    return f"exited with status {exitcode} before it finished"


class _Worker:
    """One worker process, its end of the pipe, and the task it holds (None: idle)."""

    def __init__(self, context, task: Callable):
        parent_end, child_end = context.Pipe(duplex=True)
        # the worker starts with SIGINT blocked (a signal mask survives exec) until it ignores
        # it, so a Ctrl-C reaches only this process; here a SIGINT meanwhile stays pending and
        # is raised as soon as the mask is restored (ignoring it instead would lose it)
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            self.process = context.Process(target=_serve, args=(child_end, task), daemon=True)
            self.process.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)
        child_end.close()
        self.connection = parent_end
        self.job: int | None = None

    def give(self, k: int, args: tuple) -> None:
        self.job = k
        self.connection.send((k, args))

    def stop(self, wait: bool) -> None:
        """Tell the worker to finish (wait) or end it at once."""
        if wait and self.process.is_alive():
            try:
                self.connection.send(None)
            except OSError:
                pass
            self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout=5)
        if self.process.is_alive():  # pragma: no cover - a worker that ignores SIGTERM
            self.process.kill()
            self.process.join(timeout=5)
        self.connection.close()


def pool_run(task: Callable, calls: dict[int, tuple], workers: int,
             on_result: Callable[[int, object], None],
             on_failed: Callable[[int, str, str], None],
             on_lost: Callable[[int, str], None]) -> None:
    """Run ``task(*calls[k])`` for every k in ``workers`` processes.

    In this process, as each finishes: ``on_result(k, result)``; ``on_failed(k, error,
    traceback)`` when the task raised; ``on_lost(k, how)`` when its worker process died
    before answering (``how``: :func:`describe_exit`, 'was killed by SIGKILL'). A lost
    worker is replaced and the other tasks go on. ``task`` must be importable by name
    (spawn). Any exception here (KeyboardInterrupt included) stops every worker at once
    and propagates.
    """
    import multiprocessing
    from multiprocessing.connection import wait

    context = multiprocessing.get_context("spawn")
    waiting = deque(sorted(calls))
    pool: list[_Worker] = []

    def next_task(worker: _Worker) -> None:
        if waiting:
            k = waiting.popleft()
            worker.give(k, calls[k])

    try:
        for _ in range(min(workers, len(waiting))):
            pool.append(_Worker(context, task))  # one by one: a Ctrl-C meanwhile stops those started
            next_task(pool[-1])
        while any(w.job is not None for w in pool):
            busy = [w for w in pool if w.job is not None]
            ready = set(wait([w.connection for w in busy] + [w.process.sentinel for w in busy]))
            for worker in busy:
                if worker.connection not in ready and worker.process.sentinel not in ready:
                    continue
                k, worker.job = worker.job, None
                try:
                    _, ok, payload = worker.connection.recv()
                except (EOFError, OSError):  # it died: its end of the pipe closed unanswered
                    worker.process.join(timeout=5)
                    how = describe_exit(worker.process.exitcode)
                    worker.stop(wait=False)
                    pool.remove(worker)
                    if waiting:
                        pool.append(_Worker(context, task))
                        next_task(pool[-1])
                    on_lost(k, how)
                    continue
                next_task(worker)  # keep it busy while this process writes the result
                if ok:
                    on_result(k, payload)
                else:
                    on_failed(k, *payload)
    except BaseException:
        for worker in pool:
            worker.stop(wait=False)
        raise
    for worker in pool:
        worker.stop(wait=True)

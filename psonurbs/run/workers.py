"""A pool of worker processes that fit clouds (``--jobs N``).

Workers are started with ``spawn`` and limited to one BLAS/OpenMP thread (a fit is
already vectorised); they only compute and send back the rendered outputs, so the
parent writes every file and can stop the workers at any moment.
"""
from __future__ import annotations

import os
import signal
import traceback
from typing import Callable

from .heap import keep_freed_memory

__all__ = ["pool_run"]


_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                     "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def _worker_init() -> None:
    """Each worker: Ctrl-C is the parent's business; one BLAS/OpenMP thread; freed memory kept."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    keep_freed_memory()
    for name in _THREAD_VARIABLES:
        os.environ[name] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
    except Exception:  # pragma: no cover - threadpoolctl is a dependency
        pass


def pool_run(task: Callable, calls: dict[int, tuple], workers: int,
             on_result: Callable[[int, object], None], on_lost: Callable[[int, BaseException, str], None]) -> None:
    """Run ``task(*calls[k])`` for every k in ``workers`` processes.

    In this process, as each finishes: ``on_result(k, result)``, or ``on_lost(k, error,
    traceback)`` when its worker process died. ``task`` must be importable by name (spawn).
    Any exception here (KeyboardInterrupt included) stops the pool and propagates.
    """
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    context = multiprocessing.get_context("spawn")
    # Workers start with SIGINT ignored (a disposition that survives exec), so a Ctrl-C
    # reaches only this process, which then stops the pool.
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    executor = ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_worker_init)
    try:
        try:
            futures = {executor.submit(task, *args): k for k, args in calls.items()}
        finally:
            signal.signal(signal.SIGINT, previous)
        remaining = set(futures)
        while remaining:
            finished, remaining = wait(remaining, return_when=FIRST_COMPLETED)
            for future in sorted(finished, key=lambda f: futures[f]):
                k = futures[future]
                try:
                    result = future.result()
                except Exception as e:  # the worker process died
                    on_lost(k, e, traceback.format_exc())
                    continue
                on_result(k, result)
    except BaseException:
        _stop_pool(executor)
        raise
    executor.shutdown(wait=True)


def _stop_pool(executor) -> None:
    """Cancel what has not started and end the worker processes this run started."""
    processes = list(getattr(executor, "_processes", {}).values())
    executor.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(timeout=5)

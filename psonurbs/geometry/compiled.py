"""Work in parts: chunks of bounded memory, threads, and optional compiled kernels (numba,
the ``fast`` extra) with numpy as the reference.

A hot loop that numpy can only express as many passes over padded arrays (the swarm's
fitness, foot-point searches) may have a compiled twin. Each twin is written next to its
numpy reference and is used only when :data:`ENABLED`; the tests run both and compare
them. Without numba (or with ``PSONURBS_NO_JIT=1`` in the environment) every result
comes from the numpy code, a few times slower.

Kernels are compiled on first use and cached on disk (``cache=True``: next to the
source, or in numba's user-wide cache when that is not writable), so only the first fit
on a machine pays the compile time. No ``fastmath``: the same inputs give the same bits.

Kernels release the GIL (``nogil``), so a kernel over independent items (points, particles)
runs on parts of them in threads (:func:`over_parts`): up to :func:`threads` at once. Each
item's numbers are its own, so the bits do not depend on the split. Work shared out from
inside one of these threads runs in that thread (the pool's workers are busy with it).
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from typing import Callable, Iterable, Iterator, TypeVar

try:
    if os.environ.get("PSONURBS_NO_JIT", "") not in ("", "0"):
        raise ImportError("disabled by PSONURBS_NO_JIT")
    import numba
except ImportError:  # the numpy reference path
    numba = None

ENABLED = numba is not None


def chunks(n: int, size: int) -> Iterator[slice]:
    """Consecutive slices of at most ``size`` items covering ``range(n)``.

    A computation independent per point (a surface's value, a foot point) gives the same
    numbers on a chunk as on all points at once, so chunking bounds the memory of its
    intermediate arrays (a few hundred bytes per point) without changing a result; the
    chunks are what :func:`in_order` and :func:`each` share out among threads."""
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))


def kernel(function=None, *, inline: bool = False):
    """``function`` compiled by numba (no Python objects, cached), or itself without it:
    call a kernel only where :data:`ENABLED`, or accept the Python loop's speed.

    ``@kernel(inline=True)`` marks a small helper that is compiled into every kernel
    calling it (numba's ``inline="always"``: no call in a per-point loop)."""
    if function is None:
        return lambda f: kernel(f, inline=inline)
    if numba is None:
        return function
    return numba.njit(cache=True, nogil=True, inline="always" if inline else "never")(function)


def threads() -> int:
    """Threads a kernel over independent items may use: ``PSONURBS_THREADS``, else
    ``OMP_NUM_THREADS`` (1 in the worker processes of ``--jobs`` and of dask, which fit
    one cloud per core), else every CPU this process may run on."""
    for name in ("PSONURBS_THREADS", "OMP_NUM_THREADS"):
        try:
            return max(1, int(os.environ[name]))
        except (KeyError, ValueError):
            continue
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


POOL_PREFIX = "psonurbs-kernel"


@lru_cache(maxsize=4)
def _pool(size: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=size, thread_name_prefix=POOL_PREFIX)


def _shared() -> int:
    """Threads work may be shared among here: :func:`threads`, or 1 inside a pool's own
    worker (work nested in work already shared would wait on the workers it occupies)."""
    return 1 if threading.current_thread().name.startswith(POOL_PREFIX) else threads()


Item, Result = TypeVar("Item"), TypeVar("Result")


def in_order(function: Callable[[Item], Result], items: Iterable[Item]) -> Iterator[Result]:
    """``function(item)`` for each item, up to :func:`threads` at once, yielded in the
    items' order: for numpy work on fixed chunks (numpy releases the GIL inside its
    loops). A caller that sums the results in that order gets the same bits whatever the
    number of threads."""
    items, shared = list(items), _shared()
    if shared <= 1 or len(items) <= 1:
        yield from map(function, items)
        return
    yield from _pool(min(shared, len(items))).map(function, items)


def each(function: Callable[[Item], None], items: Iterable[Item]) -> None:
    """``function(item)`` for each item, in threads as :func:`in_order`: for numpy work
    on fixed chunks that writes only its own part of a shared output (the bits do not
    depend on the number of threads)."""
    for _ in in_order(function, items):
        pass


def over_parts(count: int, run: Callable[[slice], None], smallest: int = 1) -> None:
    """``run(part)`` for contiguous slices covering range(count), each at least ``smallest``
    items, in up to :func:`threads` threads at once (one call, in this thread, when one
    thread is all there is or the items are too few to share); exceptions propagate.
    ``run`` must write only its own part of any shared output."""
    parts = min(_shared(), count // max(smallest, 1)) if ENABLED else 1
    if parts <= 1:
        run(slice(0, count))
        return
    bounds = [count * k // parts for k in range(parts + 1)]
    futures = [_pool(parts).submit(run, slice(a, b)) for a, b in zip(bounds, bounds[1:])]
    for future in futures:
        future.result()

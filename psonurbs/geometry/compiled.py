"""Optional compiled kernels: numba (the ``fast`` extra), with numpy as the reference.

A hot loop that numpy can only express as many passes over padded arrays (the swarm's
fitness, foot-point searches) may have a compiled twin. Each twin is written next to its
numpy reference and is used only when :data:`ENABLED`; the tests run both and compare
them. Without numba (or with ``PSONURBS_NO_JIT=1`` in the environment) every result
comes from the numpy code, a few times slower.

Kernels are compiled on first use and cached on disk (``cache=True``: next to the
source, or in numba's user-wide cache when that is not writable), so only the first fit
on a machine pays the compile time. No ``fastmath``: the same inputs give the same bits.
"""
from __future__ import annotations

import os

try:
    if os.environ.get("PSONURBS_NO_JIT", "") not in ("", "0"):
        raise ImportError("disabled by PSONURBS_NO_JIT")
    import numba
except ImportError:  # the numpy reference path
    numba = None

ENABLED = numba is not None


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

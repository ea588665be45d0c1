"""Keep freed memory in a fitting process instead of handing it back to the system at once.

The swarm's batched fitness allocates and frees a few tens of MB of numpy temporaries per
iteration. glibc's malloc maps such blocks freshly (or trims the heap when they are freed),
so every iteration page-faults them in again: on franke_noisy that was a third of the
swarm's time, spent in the kernel. Raising the trim and mmap thresholds (``mallopt``) keeps
the pages: the process' memory stays at its peak instead. Only glibc is touched; elsewhere
this does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
KEEP_BYTES = 512 * 2 ** 20  # freed memory kept before trimming, and the smallest block mapped alone


def keep_freed_memory() -> bool:
    """Raise glibc's trim and mmap thresholds for this process; True if it was done."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_TRIM_THRESHOLD, KEEP_BYTES)) and bool(mallopt(M_MMAP_THRESHOLD, KEEP_BYTES))

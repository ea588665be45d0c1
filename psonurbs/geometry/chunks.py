"""Many points a chunk at a time: work arrays of a bounded size, whatever the cloud's.

A computation that is independent per point (evaluating a surface, a foot point) gives
the same numbers on a chunk as on all points at once, so chunking only bounds the
memory of its intermediate arrays (basis matrices, derivatives: a few hundred bytes
per point) without changing a result.
"""
from __future__ import annotations

from typing import Iterator


def chunks(n: int, size: int) -> Iterator[slice]:
    """Consecutive slices of at most ``size`` items covering ``range(n)``."""
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))

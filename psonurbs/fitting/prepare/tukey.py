"""Tukey's biweight, the one weight function of both robust fits (the outlier test's local
quadrics and the robust loss of every solve).

    w(r) = (1 - r^2)^2  for |r| < 1,   0 beyond

with r a residual over its cut-off (a tuning constant times a scale): a point's weight
falls smoothly from 1 and a point past the cut-off pulls nothing.
"""
from __future__ import annotations

import numpy as np


def biweight(ratio: np.ndarray) -> np.ndarray:
    """``(1 - min(|r|, 1)^2)^2`` of every residual over its cut-off, same shape."""
    u = np.minimum(np.abs(ratio), 1.0)
    return (1.0 - u * u) ** 2

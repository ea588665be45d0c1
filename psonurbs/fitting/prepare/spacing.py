"""A cloud's local spacing: each point's mean distance to its nearest neighbours."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

NEIGHBOURS = 6  # a point's spacing: its mean distance to this many nearest points


@dataclass(frozen=True)
class Spacing:
    """Points (N, 3) in a KD-tree, and each one's local spacing (N,): its mean distance to
    its ``NEIGHBOURS`` nearest (fewer in a smaller cloud; 0 for a single point)."""

    tree: cKDTree
    local: np.ndarray

    @staticmethod
    def of(points: np.ndarray) -> "Spacing":
        tree = cKDTree(points)
        k = min(NEIGHBOURS, len(points) - 1)
        if k < 1:
            return Spacing(tree, np.zeros(len(points)))
        return Spacing(tree, tree.query(points, k + 1)[0][:, 1:].mean(axis=1))

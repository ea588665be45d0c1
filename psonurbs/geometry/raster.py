"""Triangles rasterised: which cell centres of a regular grid lie in any of them.

A cell centre q is in the triangle (a, b, c) when the three edge functions

    side(s, t) = (t_x - s_x)(q_y - s_y) - (t_y - s_y)(q_x - s_x)

over the edges a-b, b-c, c-a do not have both signs (either orientation; on an edge
counts as in). Each triangle tests the cell centres of its bounding box.
:func:`rasterised` is the numpy reference (every triangle's candidates at once); where
:data:`psonurbs.geometry.compiled.ENABLED` its compiled twin gives the same mask,
triangle by triangle, without the candidate arrays.
"""
from __future__ import annotations

import numpy as np

from psonurbs.geometry import compiled
from psonurbs.geometry.compiled import kernel

COMPILED = compiled.ENABLED


def rasterised(triangles: np.ndarray, x0: float, y0: float, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """Mask (shape) of the cells (centres x0 + i cell, y0 + j cell) inside any of the
    triangles (K, 3, 2)."""
    p = (np.asarray(triangles, float) - np.array([x0, y0])) / cell
    mask = np.zeros(shape, bool)
    if COMPILED:
        if len(p):
            raster_kernel(np.ascontiguousarray(p), mask)
        return mask
    lo = np.clip(np.ceil(p.min(axis=1)).astype(int), 0, np.array(shape) - 1)
    hi = np.clip(np.floor(p.max(axis=1)).astype(int), 0, np.array(shape) - 1)
    n = np.maximum(hi - lo + 1, 0)
    count = n[:, 0] * n[:, 1]
    owner = np.repeat(np.arange(len(p)), count)
    local = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    i = lo[owner, 0] + local // np.maximum(n[owner, 1], 1)
    j = lo[owner, 1] + local % np.maximum(n[owner, 1], 1)
    a, b, c = p[owner, 0], p[owner, 1], p[owner, 2]
    q = np.stack([i, j], axis=1).astype(float)

    def side(s, t):
        return (t[:, 0] - s[:, 0]) * (q[:, 1] - s[:, 1]) - (t[:, 1] - s[:, 1]) * (q[:, 0] - s[:, 0])

    d1, d2, d3 = side(a, b), side(b, c), side(c, a)
    hit = ~((np.minimum(np.minimum(d1, d2), d3) < 0) & (np.maximum(np.maximum(d1, d2), d3) > 0))
    mask[i[hit], j[hit]] = True
    return mask


@kernel(inline=True)
def _side(sx, sy, tx, ty, qx, qy):
    return (tx - sx) * (qy - sy) - (ty - sy) * (qx - sx)


@kernel
def raster_kernel(p, mask):
    """:func:`rasterised` for triangles p (K, 3, 2) already in cell units: mask set in place."""
    nx, ny = mask.shape
    for k in range(p.shape[0]):
        ax, ay, bx, by, cx, cy = p[k, 0, 0], p[k, 0, 1], p[k, 1, 0], p[k, 1, 1], p[k, 2, 0], p[k, 2, 1]
        i0 = min(max(int(np.ceil(min(ax, bx, cx))), 0), nx - 1)
        i1 = min(max(int(np.floor(max(ax, bx, cx))), 0), nx - 1)
        j0 = min(max(int(np.ceil(min(ay, by, cy))), 0), ny - 1)
        j1 = min(max(int(np.floor(max(ay, by, cy))), 0), ny - 1)
        for i in range(i0, i1 + 1):
            qx = float(i)
            for j in range(j0, j1 + 1):
                qy = float(j)
                d1 = _side(ax, ay, bx, by, qx, qy)
                d2 = _side(bx, by, cx, cy, qx, qy)
                d3 = _side(cx, cy, ax, ay, qx, qy)
                if not (min(d1, d2, d3) < 0 and max(d1, d2, d3) > 0):
                    mask[i, j] = True

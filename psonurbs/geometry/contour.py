"""Closed contours of a sampled field (marching squares) and polyline simplification.

:func:`contours` returns the level set ``f = level`` of a field sampled on a regular grid
as closed polygons with the region ``f < level`` on their left: outer boundaries
counter-clockwise, holes clockwise. Each grid cell with corners a, b, c, d (counter-
clockwise) crosses the level on the edges whose corners lie on opposite sides; walking
round the cell, a segment runs from an edge left inside -> outside to the next one
entered outside -> inside, so an edge shared by two cells starts a segment in one and
ends one in the other and the segments chain into closed loops. A saddle cell (two
opposite corners inside) is resolved by the value at its centre. Crossings are placed
by linear interpolation along the edges.
"""
from __future__ import annotations

import numpy as np

__all__ = ["contours", "simplify_closed"]


def contours(field: np.ndarray, x: np.ndarray, y: np.ndarray, level: float) -> list[np.ndarray]:
    """Closed polygons (each (M, 2), not repeating its first vertex) of ``field == level``.

    ``field[i, j]`` is the value at ``(x[i], y[j])``. The grid's border must lie outside
    (``field >= level``) so that every contour closes.
    """
    f = np.asarray(field, float)
    nx, ny = f.shape
    if np.any(f[[0, -1], :] < level) or np.any(f[:, [0, -1]] < level):
        raise ValueError("the field's border must lie outside the contour level")
    inside = f < level
    n_h = (nx - 1) * ny  # horizontal edges (i, j)-(i+1, j) first, then vertical (i, j)-(i, j+1)

    def h(i, j):
        return i * ny + j

    def v(i, j):
        return n_h + i * (ny - 1) + j

    # only the cells the level crosses (corners on both sides), in the grid's order
    a, b, c, d = inside[:-1, :-1], inside[1:, :-1], inside[1:, 1:], inside[:-1, 1:]
    i, j = np.nonzero((a | b | c | d) & ~(a & b & c & d))
    corners = np.stack([inside[i, j], inside[i + 1, j], inside[i + 1, j + 1], inside[i, j + 1]], axis=1)
    edges = np.stack([h(i, j), v(i + 1, j), h(i, j + 1), v(i, j)], axis=1)  # a-b, b-c, c-d, d-a
    leaving = corners & ~np.roll(corners, -1, axis=1)  # edge k walked from inside to outside
    entering = ~corners & np.roll(corners, -1, axis=1)
    count = leaving.sum(axis=1)
    centre = 0.25 * (f[i, j] + f[i + 1, j] + f[i + 1, j + 1] + f[i, j + 1]) < level
    starts, ends = [], []
    for k in range(4):
        # non-saddle cells: the one leaving edge pairs with the one entering edge
        one = (count == 1) & leaving[:, k]
        starts.append(edges[one, k])
        ends.append(edges[one][np.arange(one.sum()), np.argmax(entering[one], axis=1)])
        # saddles: the entering edge next (centre inside) or before (centre outside)
        two = (count == 2) & leaving[:, k]
        step = np.where(centre[two], 1, -1)
        starts.append(edges[two, k])
        ends.append(edges[two][np.arange(two.sum()), (k + step) % 4])
    starts, ends = np.concatenate(starts), np.concatenate(ends)
    successor = np.full(n_h + nx * (ny - 1), -1)
    successor[starts] = ends

    chains = []
    visited = np.zeros(len(successor), bool)
    for start in starts:
        if visited[start]:
            continue
        loop = []
        e = int(start)
        while not visited[e]:
            visited[e] = True
            loop.append(e)
            e = int(successor[e])
        chains.append(np.array(loop))
    return [np.stack(crossings(f, x, y, level, n_h, ny, loop), axis=1) for loop in chains]


def crossings(f: np.ndarray, x: np.ndarray, y: np.ndarray, level: float, n_h: int, ny: int,
              edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the level crosses the grid's ``edges`` (ids as in :func:`contours`: the
    horizontal ones first), by linear interpolation along each: (x, y), each (M,)."""
    horizontal = edges < n_h
    ei = np.where(horizontal, edges // ny, (edges - n_h) // (ny - 1))
    ej = np.where(horizontal, edges % ny, (edges - n_h) % (ny - 1))
    di = horizontal.astype(int)
    f0, f1 = f[ei, ej], f[ei + di, ej + 1 - di]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.where(f1 != f0, (level - f0) / (f1 - f0), 0.5), 0.0, 1.0)
    return x[ei] + t * (x[ei + di] - x[ei]), y[ej] + t * (y[ej + 1 - di] - y[ej])


def simplify_closed(polygon: np.ndarray, tolerance: float, fixed: np.ndarray | None = None) -> np.ndarray:
    """Douglas-Peucker simplification of a closed polygon (M, 2): every dropped vertex is
    within ``tolerance`` of the kept polygon. The vertices ``fixed`` (mask (M,)) are kept,
    and the first and the vertex farthest from it, as anchors."""
    p = np.asarray(polygon, float)
    if len(p) <= 4:
        return p
    far = int(np.argmax(np.sum((p - p[0]) ** 2, axis=1)))
    keep = np.zeros(len(p), bool) if fixed is None else np.array(fixed, bool)
    keep[[0, far]] = True
    ring = np.concatenate([p, p[:1]])
    anchors = np.append(np.flatnonzero(keep), len(p))
    stack = list(zip(anchors[:-1].tolist(), anchors[1:].tolist()))
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        seg = ring[b] - ring[a]
        rel = ring[a + 1:b] - ring[a]
        length = float(np.hypot(*seg))
        if length > 0:
            d = np.abs(seg[0] * rel[:, 1] - seg[1] * rel[:, 0]) / length
        else:
            d = np.hypot(rel[:, 0], rel[:, 1])
        k = int(np.argmax(d))
        if d[k] > tolerance:
            keep[a + 1 + k] = True
            stack += [(a, a + 1 + k), (a + 1 + k, b)]
    return p[keep]

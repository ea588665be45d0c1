"""The data's straight edges: where a cloud ends along a line, the surface ends there.

A cloud cut along a line (a terrain tile, a plate scanned to its rim, a rectangle of any
height field) has a straight edge in the plane it is seen from, and its true edge lies
within a sampling gap beyond its outermost points. A fitted surface is free past them:
a corner spreads or an edge bulges where the fit extrapolates, by a spacing and more
(step_bump's tolerance fit ran 0.018 past its data's edge at a corner, 38 times its
tolerance from the truth). In the plane, the edge is a line the data do not cross, and
every part of the surface beyond it is surface without data.

The line is the one along which the parameters are aligned (:func:`straight_line`):
least squares through the outermost point of each of a few slices along the edge,
straight only if no point lies beyond it by more than the sampling scatter and the
outermost points do not bend. For the face it is a plane across the view (a cut seen at
a tilt), fitted with each slice weighted by its count, and moved out to the outermost
point, so that no point of the data lies beyond it (:func:`straight_edges`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psonurbs.fitting.parameters.parametrisation import min_area_rectangle, plane_basis

SAG = 2.0  # a straight edge's outermost points sag from their chord by at most this many scatters
SLICES = 8  # slices along an edge, each giving its outermost point


def straight_line(along: np.ndarray, across: np.ndarray, upper: bool, scatter: float, bins: int = SLICES,
                  height: np.ndarray | None = None) -> tuple[float, float, float] | None:
    """The line ``across = a + b * along`` (a, b, 0) of the data's edge, or None if the edge is
    not straight: the least-squares line through the lowest (or highest) ``across`` value
    in each of ``bins`` slices of ``along`` (in [0, 1]). With the points' ``height`` (N,)
    off the plane of ``along`` and ``across``, the plane ``across = a + b along + c
    height`` (a, b, c): an edge cut by a plane the view is not square to (a tilted view
    of a height field cut along x = 1 sees the cut's heights as a ragged line); each
    slice's outermost point then weighs by the square of its slice's count (the
    outermost of n points lies about 1/n of the slice's depth short of the true edge), so
    that the sparse end of a graded edge, its outermost points farther in, does not tilt
    the plane (moved out to the outermost point, it would stand off the dense end). The
    parameters' alignment, which needs only the data's extent, takes the plain line.

    A straight edge's points lie beyond that line by no more than their sampling
    ``scatter``, and its lowest points do not bend: the parabola through them sags from
    its chord by at most ``SAG`` times the scatter (a random or graded sample's sags up
    to 1.5 times, a disc's of 500 points 2.3 times and more as it grows, while its points
    lie only 1.4-2.7 spacings past the line). If some reach farther, or the lowest
    points bend, the edge is not straight (an ellipse's bends away from the line, a
    scan's is ragged). Fewer than two slices holding points: a constant line through
    their mean, straight by default.
    """
    slices = np.minimum((along * bins).astype(int), bins - 1)
    order = np.lexsort((-across if upper else across, slices))
    first = order[np.r_[True, slices[order][1:] != slices[order][:-1]]]
    if len(first) < 2:
        return float(across[first].mean()), 0.0, 0.0
    if height is None or len(first) < 4:
        b, a = np.polyfit(along[first], across[first], 1)
        c = 0.0
    else:
        w = np.bincount(slices, minlength=bins)[slices[first]].astype(float)  # by inverse variance
        rows = np.column_stack([np.ones(len(first)), along[first], height[first]])
        a, b, c = np.linalg.lstsq(rows * w[:, None], across[first] * w, rcond=None)[0]
    flat = across - c * height if height is not None else across  # across, the cut's tilt taken out
    line = a + b * along
    beyond = float(np.max(flat - line) if upper else np.max(line - flat))
    sag = 0.0
    if len(first) >= 4:  # the parabola's sag over the edge's length: |c| L^2 / 4
        sag = abs(np.polyfit(along[first], flat[first], 2)[0]) * np.ptp(along) ** 2 / 4.0
    if beyond > scatter or sag > SAG * scatter:
        return None
    return float(a), float(b), float(c)


@dataclass(frozen=True)
class StraightEdges:
    """The straight edges of a cloud seen along a direction: coordinates t = (x - origin)
    @ axes.T / span (axes (3, 3): rows along the sides of the data's smallest rectangle in
    the plane, then the direction seen along; span (2,) scales the plane's onto [0, 1]^2,
    the third stays in cloud units); each edge (k, upper, a, b, c): the data lie on the
    inner side of t_k = a + b t_{1-k} + c t_2."""

    origin: np.ndarray  # (3,)
    axes: np.ndarray  # (3, 3)
    span: np.ndarray  # (2,)
    edges: tuple[tuple[int, bool, float, float, float], ...]

    def beyond(self, x: np.ndarray) -> np.ndarray:
        """How far the points x (M, 3) lie past the farthest-reaching edge, across it in the
        plane (cloud units; negative inside every edge)."""
        t = (x - self.origin) @ self.axes.T
        t[:, :2] /= self.span
        out = np.full(len(x), -np.inf)
        for k, upper, a, b, c in self.edges:
            edge = a + b * t[:, 1 - k] + c * t[:, 2]
            past = t[:, k] - edge if upper else edge - t[:, k]
            out = np.maximum(out, past * self.span[k] / np.hypot(1.0, b * self.span[k] / self.span[1 - k]))
        return out


def straight_edges(points: np.ndarray, normal: np.ndarray, alpha: float) -> StraightEdges | None:
    """The straight edges of the points (N, 3) seen along ``normal`` (3,), each moved out
    to its outermost point; the scatter a straight edge may show is ``alpha`` spacings
    sqrt(A / N) of the data's rectangle of area A. None without points or straight edges."""
    if len(points) < 4:
        return None
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    plane = plane_basis(normal)
    plane = min_area_rectangle(points @ plane.T) @ plane
    axes = np.vstack([plane, normal])
    t = points @ axes.T
    origin, span = t.min(axis=0), np.ptp(t[:, :2], axis=0)
    if np.any(span <= 0):
        return None
    t = t - origin
    t[:, :2] /= span
    scatter = alpha * float(np.sqrt(1.0 / len(points)))
    edges = []
    for k in (0, 1):
        across, along = t[:, k], t[:, 1 - k]
        for upper in (False, True):
            edge = straight_line(along, across, upper, scatter, height=t[:, 2])
            if edge is None:
                continue
            a, b, c = edge
            inner = a + b * along + c * t[:, 2]
            reach = float(np.max(across - inner) if upper else np.max(inner - across))
            edges.append((k, upper, a + reach if upper else a - reach, b, c))
    if not edges:
        return None
    return StraightEdges(origin @ axes, axes, span, tuple(edges))

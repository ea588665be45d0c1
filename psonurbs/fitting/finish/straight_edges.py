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

A surface can also end short of such an edge: where a graded cloud thins out, its edge
bulges in between the sparse last points, and the true surface there is left uncovered.
Such a side is carried past the edge by continuing its end spans
(:func:`reaching_domain`), and the face is cut at the edge as before.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.special import fdtri

from psonurbs.fitting.parameters.parametrisation import min_area_rectangle, plane_basis
from psonurbs.geometry.nurbs import NurbsSurface

SAG = 2.0  # a straight edge's outermost points sag from their chord by at most this many scatters
SLICES = 8  # slices along an edge, each giving its outermost point
BEYOND = 0.25  # a side short of a straight edge is carried this many spacings past it
EXTENSION_STEPS = 3  # a side carried past its straight edge is checked this many times at most
MAX_TILT = 1.0  # a cut's tilt to the view's normal, tan: at most 45 degrees (a steeper one is no edge seen)
TILT_LEVEL = 0.99  # a straight edge's tilt with the heights is kept at this significance
SIDES = ((0, False), (1, False), (0, True), (1, True))  # (direction, upper end): u = 0, v = 0, u = 1, v = 1


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
    height's term is kept only where it is significant and physical (:func:`tilted_edge`).
    The parameters' alignment, which needs only the data's extent, takes the plain line.

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
        rows = np.column_stack([np.ones(len(first)), along[first], height[first]]) * w[:, None]
        a, b, c = tilted_edge(rows, across[first] * w)
    flat = across - c * height if height is not None else across  # across, the cut's tilt taken out
    line = a + b * along
    beyond = float(np.max(flat - line) if upper else np.max(line - flat))
    sag = 0.0
    if len(first) >= 4:  # the parabola's sag over the edge's length: |c| L^2 / 4
        sag = abs(np.polyfit(along[first], flat[first], 2)[0]) * np.ptp(along) ** 2 / 4.0
    if beyond > scatter or sag > SAG * scatter:
        return None
    return float(a), float(b), float(c)


def tilted_edge(rows: np.ndarray, target: np.ndarray, level: float = TILT_LEVEL) -> tuple[float, float, float]:
    """The weighted least squares (a, b, c) of ``rows`` (n, 3: the columns 1, along, height
    in the units of across, each row scaled by its weight) against ``target`` (n,), with
    the height's c kept only where it explains the outermost points better than the line
    alone at the F test's ``level`` (1 and n - 3 degrees of freedom) and the cut it
    describes leans at most ``MAX_TILT`` (c is the tangent of its angle to the view's
    normal; a view chosen to see the surface squarely sees a cut across it nearly edge
    on), else c = 0. A sparse edge's outermost points lie up to a spacing short of it at
    random, and a c fitted to that scatter tilts the edge by the heights' swing (a
    wave's 0.2 moved its corner 0.01 past the true edge)."""
    line = np.linalg.lstsq(rows[:, :2], target, rcond=None)[0]
    plane = np.linalg.lstsq(rows, target, rcond=None)[0]
    if len(target) > 4:
        sse2 = float(np.sum((rows[:, :2] @ line - target) ** 2))
        sse3 = float(np.sum((rows @ plane - target) ** 2))
        if sse2 - sse3 > fdtri(1, len(target) - 3, level) * sse3 / (len(target) - 3) and abs(plane[2]) <= MAX_TILT:
            return float(plane[0]), float(plane[1]), float(plane[2])
    return float(line[0]), float(line[1]), 0.0


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

    def past(self, x: np.ndarray) -> np.ndarray:
        """How far the points x (M, 3) lie past each edge, across it in the plane (E, M);
        cloud units, negative inside. Affine in x."""
        t = (x - self.origin) @ self.axes.T
        t[:, :2] /= self.span
        out = np.empty((len(self.edges), len(x)))
        for e, (k, upper, a, b, c) in enumerate(self.edges):
            edge = a + b * t[:, 1 - k] + c * t[:, 2]
            out[e] = (t[:, k] - edge if upper else edge - t[:, k]) * self.span[k] / \
                np.hypot(1.0, b * self.span[k] / self.span[1 - k])
        return out

    def beyond(self, x: np.ndarray) -> np.ndarray:
        """How far the points x (M, 3) lie past the farthest-reaching edge (cloud units;
        negative inside every edge)."""
        return self.past(x).max(axis=0)

    def untilted(self) -> StraightEdges | None:
        """The edges seen square (c = 0) alone, None if none is: a tilted edge's plane
        holds only near its data's heights (its tilt's error times a surface's height
        swing: 0.05 on step_bump), so what lies past it elsewhere is not measured by it."""
        kept = tuple(edge for edge in self.edges if edge[4] == 0.0)
        if len(kept) == len(self.edges):
            return self
        return replace(self, edges=kept) if kept else None


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
            edge = straight_line(along, across, upper, scatter, height=t[:, 2] / span[k])  # c: the cut's tilt
            if edge is None:
                continue
            a, b, c = edge
            c = float(c / span[k])
            inner = a + b * along + c * t[:, 2]
            reach = float(np.max(across - inner) if upper else np.max(inner - across))
            edges.append((k, upper, a + reach if upper else a - reach, b, c))
    if not edges:
        return None
    return StraightEdges(origin @ axes, axes, span, tuple(edges))


class GrownDomain:
    """A domain around [0, 1]^2 grown side by side (``ranges``: u range, v range, in the
    surface's parameters), each end by at most its end span: an extrapolation farther
    than its span is a guess, not the data's surface; nor is one whose weights turn
    negative (:meth:`longer` then takes back the last growth)."""

    def __init__(self, surface: NurbsSurface):
        self.surface = surface
        self.spans = [[float(np.diff(np.unique(knots))[0]), float(np.diff(np.unique(knots))[-1])]
                      for knots in (surface.knots_u, surface.knots_v)]
        self.ranges = [[0.0, 1.0], [0.0, 1.0]]
        self.before = [[0.0, 1.0], [0.0, 1.0]]

    @staticmethod
    def fits(surface: NurbsSurface) -> bool:
        """Whether the surface is open and on the unit square (not closed, not restricted)."""
        return not (surface.closed_u or surface.closed_v) and \
            (surface.domain_u, surface.domain_v) == ((0, 1), (0, 1))

    def width(self, k: int) -> float:
        return self.ranges[k][1] - self.ranges[k][0]

    def grow(self, k: int, upper: bool, step: float) -> bool:
        """Move the end ``upper`` of direction k out by ``step`` (of the surface's own
        parameter), at most to its end span; whether it moved."""
        end = 1 if upper else 0
        step = min(step, self.spans[k][end] - abs(self.ranges[k][end] - end))
        if step <= 1e-9 * self.width(k):
            return False
        self.ranges[k][end] += step if upper else -step
        return True

    def start(self) -> None:
        """A round of growth begins: :meth:`longer` can take it back."""
        self.before = [list(r) for r in self.ranges]

    def longer(self) -> NurbsSurface | None:
        """The surface on the grown domain, its end spans continued
        (:meth:`NurbsSurface.restricted`); None, and the round taken back, if its weights
        would turn negative."""
        try:
            return self.surface.restricted(tuple(self.ranges[0]), tuple(self.ranges[1]))
        except ValueError:
            self.ranges = self.before
            return None

    @property
    def domain(self) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """(u range, v range), None if no end moved."""
        if self.ranges == [[0.0, 1.0], [0.0, 1.0]]:
            return None
        return (self.ranges[0][0], self.ranges[0][1]), (self.ranges[1][0], self.ranges[1][1])


def reaching_domain(surface: NurbsSurface, edges: StraightEdges, spacing: float, n: int = 101
                    ) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The domain (u range, v range) around [0, 1]^2 on which an open surface reaches
    ``BEYOND`` times the data's ``spacing`` past every untilted straight edge of its data
    that a side of it falls short of by more than a spacing; None if no side does.

    Past its data's last points a fitted surface ends where the fit put its edge, and
    where the data thin out (a graded cloud's sparse end) that is up to a sampling gap
    short of the data's edge, whose true surface is then left uncovered. Within a
    spacing it is at the data's edge (a noisy cloud's outermost points stand a few
    sigmas out, a random sample's a fraction of a spacing in). A tilted edge carries no
    side (:meth:`StraightEdges.untilted`). A side runs along the
    edge it moves out across: e = argmin median |past_e| over the side's n samples S_i
    among the edges with g_ie = past_e(S_i + D_i) - past_e(S_i) >= cos 60° |D_i| at
    every sample (D the outward derivative: past_e is affine). It is carried out by
    delta = (reach - past_e(S_i)) / g_ie at its shortest sample i (its end spans'
    polynomials continued, :meth:`NurbsSurface.restricted`), no part of it moved farther
    than twice that sample's need (a side turning along the edge near a corner moves
    out slowly there, and a step to carry that point is a long extrapolation
    elsewhere), checked on the longer surface, at most ``EXTENSION_STEPS`` times and at
    most one end span: an extrapolation farther than its span is a guess, not the
    data's surface; nor is one whose weights turn negative.
    """
    reach, edges = BEYOND * spacing, edges.untilted()
    if edges is None or not GrownDomain.fits(surface):
        return None
    t = np.linspace(0.0, 1.0, n)
    grown = GrownDomain(surface)
    matched: dict[tuple[int, bool], int] = {}
    current = surface
    for _ in range(EXTENSION_STEPS):
        grown.start()
        moved = False
        for k, upper in SIDES:
            at = np.full(n, 1.0 if upper else 0.0)
            uv = (at, t) if k == 0 else (t, at)
            s, su, sv = current.derivatives(*uv)
            outward = (su if k == 0 else sv) * (1.0 if upper else -1.0)
            past = edges.past(s)
            rate = edges.past(s + outward) - past
            if (k, upper) not in matched:
                along = np.all(rate >= 0.5 * np.linalg.norm(outward, axis=1), axis=1)
                if not along.any():
                    continue
                e = int(np.flatnonzero(along)[np.argmin(np.median(np.abs(past[along]), axis=1))])
                if np.max(-past[e]) <= spacing:  # at the data's edge
                    continue
                matched[(k, upper)] = e
            e = matched[(k, upper)]
            if np.min(past[e]) >= reach or np.any(rate[e] <= 0.0):
                continue
            short = int(np.argmin(past[e]))  # where it falls shortest, carried a quarter spacing past
            need = reach - float(past[e][short])
            step = min(need / float(rate[e][short]),  # no part of the side moved farther than twice that
                       2.0 * need / float(np.linalg.norm(outward, axis=1).max())) * grown.width(k)
            moved |= grown.grow(k, upper, step)
        if not moved:
            break
        current = grown.longer()
        if current is None:
            break
    return grown.domain

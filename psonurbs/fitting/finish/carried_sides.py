"""Points past a side of the surface: the side is carried out to them.

The parameters of a fit are laid out from the points the robust stage trusts, and a
point it only spares (the corner of a sparse edge: its neighbours' quadric holds it,
but none of them reaches back to it, :class:`psonurbs.fitting.prepare.outliers.Neighbourhoods`)
starts at its nearest trusted point's parameters. Where the data thin out, such a point
can lie past the domain's side by most of a sampling gap; its foot point is held on the
side, and the surface there ends short of real data (a 200-degree twisted strip whose
density falls tenfold: its last corner point 0.04 of the diagonal, 0.6 local spacings,
past the surface).

A point lies past side (k, upper) by its reach along the outward tangent at its foot S
on the side,

    g = (x - S) . D / |D|,   D = +-dS/dk (outward),

which a point's noise off the surface does not change. Where a marking point lies more
than a spacing past, the side is carried out by (g + BEYOND spacing) / |D| of the
parameter (its end spans' polynomials continued, :meth:`NurbsSurface.restricted`), the
feet found again on the longer surface, at most ``STEPS`` times and at most one end span
(farther is a guess, not the data's surface). The face is then the trim of the longer
surface (:mod:`psonurbs.fitting.finish.footprint`).
"""
from __future__ import annotations

import numpy as np

from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters

from .straight_edges import BEYOND, SIDES

STEPS = 3  # a carried side is checked this many times at most


def past_sides(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(4, N) how far each point (N, 3) lies past each side of ``SIDES`` along the surface's
    outward tangent at its foot ``uv`` (N, 2); -inf where its foot is not on that side."""
    s, su, sv = surface.derivatives(uv[:, 0], uv[:, 1])
    out = np.full((len(SIDES), len(points)), -np.inf)
    for i, (k, upper) in enumerate(SIDES):
        on = uv[:, k] >= 1.0 if upper else uv[:, k] <= 0.0
        if on.any():
            d = (su if k == 0 else sv)[on] * (1.0 if upper else -1.0)
            out[i, on] = np.einsum("ij,ij->i", points[on] - s[on], d) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
    return out


def reaching_points(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray, marks: np.ndarray,
                    spacing: float) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The domain (u range, v range) around [0, 1]^2 on which an open surface holds the feet
    of the marking points (``marks`` (N,) bool over the points (N, 3), feet ``uv`` (N, 2))
    that lie more than ``spacing`` past one of its sides (see the module); None if none
    does, or the surface is closed or already restricted."""
    if surface.closed_u or surface.closed_v or (surface.domain_u, surface.domain_v) != ((0, 1), (0, 1)):
        return None
    rows = np.flatnonzero(marks)
    past = past_sides(surface, points[rows], uv[rows])
    far = past.max(axis=0) > spacing
    if not far.any():
        return None
    rows = rows[far]
    x, at = points[rows], uv[rows]
    spans = [[float(np.diff(np.unique(knots))[0]), float(np.diff(np.unique(knots))[-1])]
             for knots in (surface.knots_u, surface.knots_v)]
    ranges = [[0.0, 1.0], [0.0, 1.0]]
    current = surface
    for _ in range(STEPS):
        before = [list(r) for r in ranges]
        _, su, sv = current.derivatives(at[:, 0], at[:, 1])
        past = past_sides(current, x, at)
        grown = False
        for i, (k, upper) in enumerate(SIDES):
            on = past[i] > -BEYOND * spacing
            if not on.any():
                continue
            speed = np.linalg.norm((su if k == 0 else sv)[on], axis=1)
            width = ranges[k][1] - ranges[k][0]
            step = float(np.max((past[i][on] + BEYOND * spacing) / np.maximum(speed, 1e-300))) * width
            end = 1 if upper else 0
            step = min(step, spans[k][end] - abs(ranges[k][end] - end))
            if step <= 1e-9 * width:
                continue
            ranges[k][end] += step if upper else -step
            grown = True
        if not grown:
            break
        try:
            longer = surface.restricted(tuple(ranges[0]), tuple(ranges[1]))
        except ValueError:  # a rational surface's weights continued below zero: no farther
            ranges = before
            break
        lo = np.array([ranges[0][0], ranges[1][0]])
        width = np.array([ranges[0][1] - ranges[0][0], ranges[1][1] - ranges[1][0]])
        old_lo = np.array([before[0][0], before[1][0]])
        old_width = np.array([before[0][1] - before[0][0], before[1][1] - before[1][0]])
        at = closest_parameters(longer, x, (old_lo + at * old_width - lo) / width)[0]
        current = longer
    if ranges == [[0.0, 1.0], [0.0, 1.0]]:
        return None
    return (ranges[0][0], ranges[0][1]), (ranges[1][0], ranges[1][1])

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

which a point's noise off the surface does not change. Where a spared point lies more
than a spacing past, sampled like the data beside it (:func:`joined`: junk just past an
edge is spared too, but lies apart), the side is carried out by (g + BEYOND spacing) / |D| of the
parameter (its end spans' polynomials continued, :meth:`NurbsSurface.restricted`), the
feet found again on the longer surface, at most ``STEPS`` times and at most one end span
(farther is a guess, not the data's surface). The face is then the trim of the longer
surface, on which those points mark the data (:mod:`psonurbs.fitting.finish.footprint`).

A point is kept for the carry only if the longer surface then passes as near it as a
point that marks the data (within the robust cut-off, or half a spacing), a local outlier
of the robust stage only if within the fit's noise (:func:`reaching_data`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psonurbs.fitting.prepare.robust_weights import Verdict
from psonurbs.fitting.prepare.spacing import NEIGHBOURS as SPACING_NEIGHBOURS
from psonurbs.fitting.prepare.spacing import Spacing
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters

from .straight_edges import BEYOND, SIDES, GrownDomain

STEPS = 3  # a carried side is checked this many times at most
# spacings: a spared point the longer surface passes this near is data, however exact the
# fit (the surface between samples is known to no better than half their spacing; a noise-
# free twisted strip's sparse corner lay 0.29 of a spacing off its side's continuation)
CARRIED_NEAR = 0.5


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


def joined(points: np.ndarray, rows: np.ndarray, marks: np.ndarray, alpha: float) -> np.ndarray:
    """(M,) bool: the points ``rows`` (M,) lie within ``alpha`` spacings of the data beside
    them: the nearest other marking point (``marks`` (N,) bool over the points (N, 3)) no
    farther than ``alpha`` times the median local spacing (mean distance to the
    ``SPACING_NEIGHBOURS`` nearest, :class:`Spacing`) of the nearest ones, the alpha shape's scale of a
    sampling gap. The last point of a sparse edge is sampled like its neighbours; a stray
    past a dense edge lies apart from them (the saddle with 5% junk: 4.2 of its
    neighbours' spacings from the nearest, a twisted strip's sparse corner 1.7)."""
    pool = np.flatnonzero(marks)
    k = min(SPACING_NEIGHBOURS, len(pool) - 2)
    if k < 1:
        return np.zeros(len(rows), bool)
    spacing = Spacing.of(points[pool])
    tree, local = spacing.tree, spacing.local
    distance, nearest = tree.query(points[rows], k + 1)
    other = pool[nearest] != rows[:, None]  # the point itself left out
    distance = np.where(other, distance, np.inf)
    order = np.argsort(distance, axis=1)[:, :k]
    gap = np.take_along_axis(distance, order[:, :1], axis=1)[:, 0]
    beside = np.median(local[np.take_along_axis(nearest, order, axis=1)], axis=1)
    return gap <= alpha * beside


@dataclass(frozen=True)
class Carried:
    """Sides carried out to points past them: the domain (u range, v range) around
    [0, 1]^2, and the points (M,) indices) it was carried to, which mark the data."""

    domain: tuple[tuple[float, float], tuple[float, float]]
    points: np.ndarray


def reaching_points(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray, marks: np.ndarray,
                    carriers: np.ndarray, spacing: float, alpha: float) -> Carried | None:
    """The domain around [0, 1]^2 on which an open surface holds the feet of the
    ``carriers`` ((N,) bool over the points (N, 3), feet ``uv`` (N, 2)) that lie more than
    ``spacing`` past one of its sides and are :func:`joined` to the marking points
    (``marks``); None if none does, or the surface is closed or already restricted."""
    if not GrownDomain.fits(surface):
        return None
    rows = np.flatnonzero(carriers)
    past = past_sides(surface, points[rows], uv[rows])
    rows = rows[past.max(axis=0) > spacing]
    if len(rows):
        rows = rows[joined(points, rows, marks, alpha)]
    if not len(rows):
        return None
    x, at = points[rows], uv[rows]
    grown = GrownDomain(surface)
    current = surface
    for _ in range(STEPS):
        grown.start()
        _, su, sv = current.derivatives(at[:, 0], at[:, 1])
        past = past_sides(current, x, at)
        moved = False
        for i, (k, upper) in enumerate(SIDES):
            on = past[i] > -BEYOND * spacing
            if on.any():
                speed = np.linalg.norm((su if k == 0 else sv)[on], axis=1)
                need = float(np.max((past[i][on] + BEYOND * spacing) / np.maximum(speed, 1e-300)))
                moved |= grown.grow(k, upper, need * grown.width(k))
        if not moved:
            break
        longer = grown.longer()
        if longer is None:
            break
        new_lo, new_width = domain_frame(grown.ranges)
        old_lo, old_width = domain_frame(grown.before)
        at = closest_parameters(longer, x, (old_lo + at * old_width - new_lo) / new_width)[0]
        current = longer
    return None if grown.domain is None else Carried(grown.domain, rows)


def domain_frame(ranges) -> tuple[np.ndarray, np.ndarray]:
    """The lower corner (2,) and the sides (2,) of a domain (u range, v range)."""
    return np.array([ranges[0][0], ranges[1][0]]), np.array([ranges[0][1] - ranges[0][0], ranges[1][1] - ranges[1][0]])


def reaching_data(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray, marks: np.ndarray,
                  verdict: Verdict, spacing: float, alpha: float, band: float, within: float) -> Carried | None:
    """:func:`reaching_points` carried to the points the robust stage spares that the
    longer surface then passes within ``band`` (the distance within which any point
    marks the data) or ``CARRIED_NEAR`` spacings of, and to those of its local outliers
    that it passes within ``within`` of (the fit's noise: the distance within which a
    local outlier is taken for data). Junk on the surface's continuation passes the local
    test (a helicoid with 3% junk: a stray 2.9 spacings past its side, 12 of the fit's
    sigmas and 0.54 spacings off the side carried to it, held a flap over 30% of the
    face), and the sparse edge's real last points lie on the continuation to within the
    extrapolation's error. A local outlier is judged against its k nearest neighbours; where
    a sheet's sparse end lies near another turn of the same sheet, they are the other
    turn's, and the sheet's own last points read as gross outliers of it (a helicoid
    whose density falls twentyfold: its two last points, 6.1 and 6.5 median spacings
    past its side). Re-judged against the fit's own continuation, junk lies off it or
    apart from the data beside it (:func:`joined`). A point found off is dropped and the
    sides carried again without it, ``STEPS`` times at most."""
    spared = verdict.spared if verdict.doubted is None else verdict.spared & ~verdict.doubted
    outlying = verdict.outlying
    candidates = spared if outlying is None else spared | outlying
    spared_near = max(band, CARRIED_NEAR * spacing)
    for _ in range(STEPS):
        reach = reaching_points(surface, points, uv, marks, candidates, spacing, alpha)
        if reach is None:
            return None
        near = spared_near if outlying is None else np.where(outlying[reach.points], within, spared_near)
        off = closest_parameters(surface.restricted(*reach.domain), points[reach.points])[1] > near
        if not off.any():
            return reach
        candidates = candidates.copy()
        candidates[reach.points[off]] = False
    return None

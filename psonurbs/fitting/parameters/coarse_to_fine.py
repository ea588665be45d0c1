"""Parameters corrected from coarse to fine: fit a coarse net, move the parameters to its
foot points, refine the net by knot insertion towards the configured one, correct again.

A first parametrisation that is only roughly right (an unrolled graph: a few per cent of
stretch, a wobble at the scale of the neighbourhoods) is followed faithfully by a fine
net, and parameter correction on it barely moves: the fine net bends to the wrong
parameters instead. A coarse net cannot bend like that, so its foot points carry the
parameters towards the surface's own; each finer net then starts from parameters that
only need a finer correction.

The levels are nested: the inner knots of each are a subset of the next one's (the
configured uniform knots at the end), so every coarse surface lies in the finer spline
space (knot insertion) and each level's least-squares fit can only be closer to the
data than the last one's. No point is left out here: a coarse net's own approximation
error is not noise, and the robust test (:mod:`psonurbs.fitting.prepare.robust_weights`) would take it
for outliers at the data's edges; gross outliers are left out later, on the fine net.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psonurbs.fitting.finish.polish import polish
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.prepare.spacing import Spacing
from psonurbs.geometry.basis import uniform_inner_knots
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.nurbs import NurbsSurface

from .parametrisation import FILL_MARGIN, fill, fill_cells

LEVEL_ROUNDS = 20  # parameter-correction rounds per level
BARE_SPACINGS = 3.0  # surface farther than this many local spacings from every point holds no data
BARE_LIMIT = 0.01  # a fine net's surface this much bare: the ladder lost part of the sheet
BARE_GRID = 48  # surface samples a side that measure it


@dataclass(frozen=True)
class Level:
    """One net of the ladder: its inner knots in both directions."""

    inner_u: np.ndarray
    inner_v: np.ndarray

    def layout(self, fine: NetLayout) -> NetLayout:
        p, q = fine.degrees
        return NetLayout((len(self.inner_u) + p + 1, len(self.inner_v) + q + 1), fine.degrees,
                         free_edges=fine.free_edges)

    @property
    def size(self) -> tuple[int, int]:
        return (len(self.inner_u), len(self.inner_v))


def coarser(knots: np.ndarray) -> np.ndarray:
    """Half as many knots, fewer by one, chosen among ``knots``: the ones nearest to the
    uniform positions of that many (so the coarse space lies in the fine one)."""
    count = (len(knots) - 1) // 2
    if count <= 0:
        return knots[:0]
    nearest = np.abs(knots[None, :] - uniform_inner_knots(count)[:, None]).argmin(axis=1)
    return knots[np.unique(nearest)]


def ladder(layout: NetLayout) -> list[Level]:
    """The nested levels from a single Bezier patch up to ``layout``'s uniform knots."""
    u, v = (uniform_inner_knots(c) for c in layout.inner_counts)
    levels = [Level(u, v)]
    while len(u) or len(v):
        u, v = coarser(u), coarser(v)
        levels.append(Level(u, v))
    return levels[::-1]


def bare_share(surface: NurbsSurface, spacing: Spacing) -> float:
    """Share of the surface (by samples of a ``BARE_GRID`` square grid of its domain)
    farther than ``BARE_SPACINGS`` local spacings (:class:`Spacing`) from every point."""
    t = np.linspace(0.0, 1.0, BARE_GRID)
    distance, nearest = spacing.tree.query(surface.evaluate_grid(t, t).reshape(-1, 3))
    return float(np.mean(distance > BARE_SPACINGS * spacing.local[nearest]))


def corrected(level: Level, layout: NetLayout, points: np.ndarray, uv: np.ndarray, smoothing: float,
              rounds: int, spacing: Spacing | None = None) -> tuple[np.ndarray, dict]:
    """Parameters (N, 2) corrected on one level's net, and its net size, rounds, RMSE and
    fill (with the points' ``spacing``, also its bare share)."""
    net = level.layout(layout)
    solver = RegularisedLeastSquares(net.smoothness_operator(), smoothing)
    shape = NetShape(np.ones(net.n_free), level.inner_u, level.inner_v)
    _, surface, uv, steps = polish(net, solver, points, uv, shape, rounds)
    rmse = float(np.sqrt(np.mean(np.sum((surface.evaluate(uv[:, 0], uv[:, 1]) - points) ** 2, axis=1))))
    entry = {"net": list(net.size), "rounds": int(steps), "rmse": rmse, "fill": fill(uv, fill_cells(len(uv)))}
    if spacing is not None:
        entry["bare"] = bare_share(surface, spacing)
    return uv, entry


def coarse_to_fine(layout: NetLayout, points: np.ndarray, uv: np.ndarray, smoothing: float,
                   rounds: int = LEVEL_ROUNDS) -> tuple[np.ndarray, list[dict]]:
    """Parameters (N, 2) of ``points`` corrected on each level of :func:`ladder` (open
    layouts), and per level its net size, rounds taken, RMSE (normalised units) and
    :func:`fill` of the square.

    Where the ladder leaves at least ``FILL_MARGIN`` less of the square filled than the
    first parameters did, or the fine net's surface runs over no data (more than
    ``BARE_LIMIT`` of it farther than ``BARE_SPACINGS`` local spacings from every point:
    :func:`bare_share`), the first parameters are also corrected on the configured net
    alone (reported last, ``"direct": true``), and that is kept if it fills at least
    ``FILL_MARGIN`` more of the square than the ladder's, or leaves at most half its bare
    share without filling less by the margin. A flattening already holds the sheet's
    sides on the square's sides, and a coarse net that cannot bend round the sheet spoils
    that: its foot points crowd the parameters where it can reach, leaving part of the
    square without data, and the fine net extrapolates there. A single quadratic Bezier
    patch round a 270-degree cone fills 62% of the square (its fit 3 times farther than
    without the ladder); a cubic one round an S of two 230-degree arcs 92-97%, and the
    surface past the data was 4-33% of its area. Where the data thin out, a side bent
    off the square's side by the ladder empties a strip that a grid of cells hardly sees
    (a graded S: fill 0.93 against the first parameters' 0.95, 4.8% of the surface bare),
    hence the bare share. Where the ladder keeps the square it stays: its fits are nearer
    the truth (a sphere's band fitted directly: truth 0.29-0.34 noise sigmas against
    0.19-0.21)."""
    first, levels = uv, ladder(layout)
    spacing = Spacing.of(points)
    report = []
    for k, level in enumerate(levels):
        uv, entry = corrected(level, layout, points, uv, smoothing, rounds, spacing if k == len(levels) - 1 else None)
        report.append(entry)
    ladder_end = report[-1]
    if ladder_end["fill"] + FILL_MARGIN > fill(first, fill_cells(len(first))) and ladder_end["bare"] <= BARE_LIMIT:
        return uv, report
    alone, entry = corrected(levels[-1], layout, points, first, smoothing, rounds, spacing)
    report.append({**entry, "direct": True})
    if entry["fill"] >= ladder_end["fill"] + FILL_MARGIN or \
            (entry["bare"] <= 0.5 * ladder_end["bare"] and entry["fill"] + FILL_MARGIN > ladder_end["fill"]):
        return alone, report
    return uv, report
